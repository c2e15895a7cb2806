"""The six joint-limit ligaments of the body (OpenSim `CoordinateLimitForce`).

Each ligament is a one-sided spring on one coordinate: zero inside [lower, upper], a stiffness
that rises along Simbody's quintic step over `transition` degrees past a limit, and then stays
constant; its damping follows the same step, so it acts only past a limit. The .osim file
gives stiffness in N·m/degree, limits and transition in degrees and damping in
N·m/(degree/s); everything here is converted once to radians. The parameters are read from the
.osim file shipped with the package, so the force always matches the body it came from.
"""

from __future__ import annotations

import functools
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np

from l2r.sim.model import OSIM_PATH


# Order of the ligament forces everywhere in l2r (the right leg, then the left).
LIGAMENTS = ("HipLimit_r", "KneeLimit_r", "AnkleLimit_r", "HipLimit_l", "KneeLimit_l", "AnkleLimit_l")


@dataclass(frozen=True)
class LimitParams:
    """Per-ligament parameters in SI units (radians), arrays in `LIGAMENTS` order."""

    names: tuple[str, ...]
    coordinates: tuple[str, ...]
    upper: np.ndarray  # rad
    lower: np.ndarray  # rad
    k_upper: np.ndarray  # N·m/rad
    k_lower: np.ndarray  # N·m/rad
    damping: np.ndarray  # N·m·s/rad
    transition: np.ndarray  # rad


def read_limits(osim_path: Path | str = OSIM_PATH, names: tuple[str, ...] = LIGAMENTS) -> LimitParams:
    """Read the named `CoordinateLimitForce`s of an .osim file."""
    # OpenSim writes tags such as `HuntCrossleyForce::ContactParameters`, which a
    # namespace-aware XML parser rejects; the ligaments never use them.
    root = ET.fromstring(Path(osim_path).read_text().replace("::", "__"))
    found = {el.get("name"): el for el in root.iter("CoordinateLimitForce")}
    missing = [n for n in names if n not in found]
    if missing:
        raise ValueError(f"{osim_path}: no CoordinateLimitForce named {', '.join(missing)}")

    def column(tag: str) -> np.ndarray:
        return np.array([float(found[n].findtext(tag)) for n in names])

    per_degree = 180.0 / np.pi  # every ligament here limits a rotational coordinate
    params = LimitParams(
        names=tuple(names),
        coordinates=tuple(found[n].findtext("coordinate").strip() for n in names),
        upper=np.radians(column("upper_limit")),
        lower=np.radians(column("lower_limit")),
        k_upper=column("upper_stiffness") * per_degree,
        k_lower=column("lower_stiffness") * per_degree,
        damping=column("damping") * per_degree,
        transition=np.radians(column("transition")),
    )
    # The signed-overshoot form below needs the two sides never to be active together.
    if np.any(params.lower > params.upper):
        raise ValueError(f"{osim_path}: a ligament's lower limit exceeds its upper limit")
    return params


@functools.cache
def default_limits() -> LimitParams:
    """The ligaments of the packaged body, read once."""
    return read_limits()


# Columns of the kernel's parameter table, one row per ligament.
UPPER, LOWER, K_UPPER, K_LOWER, DAMPING, INVERSE_TRANSITION = range(6)


def ligament_table(params: LimitParams | None = None) -> np.ndarray:
    """The kernel's parameters (n, 6), in the columns above."""
    p = default_limits() if params is None else params
    return np.stack([p.upper, p.lower, p.k_upper, p.k_lower, p.damping, 1.0 / p.transition], axis=1)


@numba.njit(cache=True, error_model="numpy")
def engage(table: np.ndarray, qpos: np.ndarray, qpos_adr: np.ndarray, spring: np.ndarray, damping: np.ndarray) -> None:
    """Each ligament's spring force (N·m) and engaged damping (N·m·s/rad) at `qpos`, whose
    limited coordinates `qpos_adr` locates in the table's order; the whole force is
    spring - damping · speed.

    The two parts are kept apart because the simulation applies the spring as a generalised
    force and gives the damping to MuJoCo as joint damping, which the implicit integrator
    handles stably: applied explicitly, the 14 N·m·s/rad of a fully engaged ligament on the
    light foot makes the physics step diverge now and then.
    """
    for i in range(table.shape[0]):
        x = qpos[qpos_adr[i]]
        if x > table[i, UPPER]:
            over, k = x - table[i, UPPER], table[i, K_UPPER]
            s = over * table[i, INVERSE_TRANSITION]
        elif x < table[i, LOWER]:
            over, k = x - table[i, LOWER], table[i, K_LOWER]
            s = -over * table[i, INVERSE_TRANSITION]
        else:
            spring[i] = damping[i] = 0.0
            continue
        if s > 1.0:
            s = 1.0
        step = s * s * s * (10.0 + s * (-15.0 + 6.0 * s))  # Simbody's quintic step
        spring[i] = -step * k * over
        damping[i] = step * table[i, DAMPING]


def ligament_forces(q: np.ndarray, qdot: np.ndarray, params: LimitParams | None = None) -> np.ndarray:
    """Generalised force (N·m) of each ligament, as OpenSim's `calcLimitForce`.

    `q` (rad) and `qdot` (rad/s) hold the limited coordinates in `LIGAMENTS` order along the last
    axis; any leading batch shape is kept.
    """
    table = ligament_table(params)
    q, qdot = np.broadcast_arrays(np.asarray(q, dtype=np.float64), np.asarray(qdot, dtype=np.float64))
    out = np.empty(q.shape)
    _forces(table, q.reshape(-1, len(table)), qdot.reshape(-1, len(table)), out.reshape(-1, len(table)))
    return out


@numba.njit(cache=True, error_model="numpy")
def _forces(table, q, qdot, out):
    adr = np.arange(table.shape[0])
    spring, damping = np.empty(table.shape[0]), np.empty(table.shape[0])
    for row in range(q.shape[0]):
        engage(table, q[row], adr, spring, damping)
        out[row] = spring - damping * qdot[row]
