"""`l2r.sim.ligaments`' joint-limit ligaments as a Warp kernel over many worlds, in float32.

The parameter table is the numba module's (`ligaments.ligament_table`, one row per ligament,
shared by every world).
"""

from __future__ import annotations

import warp as wp

# Forward only: no adjoint code to compile (half the cold compile time)
wp.set_module_options({"enable_backward": False})

from l2r.sim import ligaments

UPPER = wp.constant(ligaments.UPPER)
LOWER = wp.constant(ligaments.LOWER)
K_UPPER = wp.constant(ligaments.K_UPPER)
K_LOWER = wp.constant(ligaments.K_LOWER)
DAMPING = wp.constant(ligaments.DAMPING)
INVERSE_TRANSITION = wp.constant(ligaments.INVERSE_TRANSITION)


@wp.func
def engage_one(table: wp.array2d(dtype=float), i: int, x: float):
    """Ligament i's spring force (N·m) and engaged damping (N·m·s/rad) at coordinate value x."""
    over = float(0.0)
    k = float(0.0)
    s = float(0.0)
    if x > table[i, UPPER]:
        over = x - table[i, UPPER]
        k = table[i, K_UPPER]
        s = over * table[i, INVERSE_TRANSITION]
    elif x < table[i, LOWER]:
        over = x - table[i, LOWER]
        k = table[i, K_LOWER]
        s = -over * table[i, INVERSE_TRANSITION]
    else:
        return 0.0, 0.0
    s = wp.min(s, 1.0)
    step = s * s * s * (10.0 + s * (-15.0 + 6.0 * s))  # Simbody's quintic step
    return -step * k * over, step * table[i, DAMPING]


@wp.kernel
def engage(table: wp.array2d(dtype=float), qpos: wp.array2d(dtype=float), qpos_adr: wp.array(dtype=int),
           spring: wp.array2d(dtype=float), damping: wp.array2d(dtype=float)):
    """`ligaments.engage`, one thread per world and ligament."""
    w, i = wp.tid()
    s, d = engage_one(table, i, qpos[w, qpos_adr[i]])
    spring[w, i] = s
    damping[w, i] = d
