"""`l2r.sim.knee`'s knee on its splines as Warp kernels over many worlds, in float32.

The segment cubics are the numba module's (`KneeCoupling`), shared by every world. The
projection's M^-1 J^T comes from MuJoCo Warp's `solve_m`, one coupling row at a time, with the
factor of the last step1, as the numba twin takes it from `mj_solveM`.
"""

from __future__ import annotations

import mujoco_warp as mjw
import warp as wp

# Forward only: no adjoint code to compile (half the cold compile time)
wp.set_module_options({"enable_backward": False})

NUM_COUPLINGS = 4  # two slides per knee: the projection's Gram matrix is this size

Gram = wp.types.matrix(shape=(NUM_COUPLINGS, NUM_COUPLINGS), dtype=float)
Couplings = wp.types.vector(length=NUM_COUPLINGS, dtype=float)


@wp.func
def _segment(breaks: wp.array2d(dtype=float), k: int, q: float) -> int:
    i = int(0)
    while i < breaks.shape[1] and q >= breaks[k, i]:
        i += 1
    return i


@wp.func
def _cubic(cubics: wp.array3d(dtype=float), k: int, i: int) -> wp.vec4:
    return wp.vec4(cubics[k, i, 0], cubics[k, i, 1], cubics[k, i, 2], cubics[k, i, 3])


@wp.kernel
def follow_splines(equality: wp.array(dtype=int), knee: wp.array(dtype=int), breaks: wp.array2d(dtype=float),
                   cubics: wp.array3d(dtype=float), qpos: wp.array2d(dtype=float),
                   eq_data: wp.array2d(dtype=wp.types.vector(length=12, dtype=float))):
    """`knee.follow_splines`, one thread per world and coupling; `eq_data` is a per-world model
    array."""
    w, k = wp.tid()
    row = _cubic(cubics, k, _segment(breaks, k, qpos[w, knee[k]]))
    data = eq_data[w, equality[k]]
    for j in range(4):
        data[j] = row[j]
    data[4] = 0.0
    eq_data[w, equality[k]] = data


@wp.kernel
def _jacobian(knee: wp.array(dtype=int), slide: wp.array(dtype=int), breaks: wp.array2d(dtype=float),
              cubics: wp.array3d(dtype=float), qpos: wp.array2d(dtype=float),
              jac: wp.array3d(dtype=float), residual: wp.array2d(dtype=float)):
    """Each coupling's row of the Jacobian (slide - slope · knee) and position residual, per world."""
    w, k = wp.tid()
    q = qpos[w, knee[k]]
    row = _cubic(cubics, k, _segment(breaks, k, q))
    for j in range(jac.shape[2]):
        jac[k, w, j] = 0.0
    jac[k, w, slide[k]] = 1.0
    jac[k, w, knee[k]] = -(row[1] + q * (2.0 * row[2] + q * 3.0 * row[3]))
    residual[w, k] = qpos[w, slide[k]] - (row[0] + q * (row[1] + q * (row[2] + q * row[3])))


@wp.func
def _correct(gram: Gram, moves: wp.array3d(dtype=float), w: int, residual: Couplings, x: wp.array2d(dtype=float)):
    """x -= moves^T gram^-1 residual."""
    y = wp.inverse(gram) * residual
    for k in range(NUM_COUPLINGS):
        for j in range(x.shape[1]):
            x[w, j] = x[w, j] - moves[k, w, j] * y[k]


@wp.kernel
def _project(jac: wp.array3d(dtype=float), moves: wp.array3d(dtype=float), residual: wp.array2d(dtype=float),
             qpos: wp.array2d(dtype=float), qvel: wp.array2d(dtype=float)):
    """Positions, then speeds, back on the splines by the mass-weighted least change, per world."""
    w = wp.tid()
    gram = Gram()
    drift = Couplings()
    for a in range(NUM_COUPLINGS):
        for j in range(qvel.shape[1]):
            drift[a] = drift[a] + jac[a, w, j] * qvel[w, j]
        for b in range(NUM_COUPLINGS):
            total = float(0.0)
            for j in range(qvel.shape[1]):
                total += jac[a, w, j] * moves[b, w, j]
            gram[a, b] = total
    position = Couplings()
    for a in range(NUM_COUPLINGS):
        position[a] = residual[w, a]
    _correct(gram, moves, w, position, qpos)
    _correct(gram, moves, w, drift, qvel)


class Projection:
    """`knee.project` for MuJoCo Warp: the slides back on their splines in every world."""

    def __init__(self, coupling, nworld: int, nv: int):
        if len(coupling.knee) != NUM_COUPLINGS:
            raise ValueError(f"the projection is built for {NUM_COUPLINGS} couplings, got {len(coupling.knee)}")
        self.knee, self.slide = wp.array(coupling.knee, dtype=int), wp.array(coupling.slide, dtype=int)
        self.breaks, self.cubics = wp.array(coupling.breaks, dtype=float), wp.array(coupling.cubics, dtype=float)
        self.jac = wp.zeros((NUM_COUPLINGS, nworld, nv), dtype=float)
        self.moves = wp.zeros((NUM_COUPLINGS, nworld, nv), dtype=float)
        self.residual = wp.zeros((nworld, NUM_COUPLINGS), dtype=float)

    def __call__(self, m: mjw.Model, d: mjw.Data) -> None:
        wp.launch(_jacobian, (d.nworld, NUM_COUPLINGS),
                  [self.knee, self.slide, self.breaks, self.cubics, d.qpos, self.jac, self.residual])
        for k in range(NUM_COUPLINGS):  # M^-1 J^T, a coupling at a time
            mjw.solve_m(m, d, self.moves[k], self.jac[k])
        wp.launch(_project, d.nworld, [self.jac, self.moves, self.residual, d.qpos, d.qvel])
