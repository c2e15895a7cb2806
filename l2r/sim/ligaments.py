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


def smooth_step(x: np.ndarray) -> np.ndarray:
    """Simbody's quintic step on [0, 1]: 0 below, 1 above, C2 in between."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * x * (10.0 + x * (-15.0 + 6.0 * x))


def ligament_forces(q: np.ndarray, qdot: np.ndarray, params: LimitParams | None = None) -> np.ndarray:
    """Generalised force (N·m) of each ligament, as OpenSim's `calcLimitForce`.

    `q` (rad) and `qdot` (rad/s) hold the limited coordinates in `LIGAMENTS` order along the last
    axis; any leading batch shape is kept.
    """
    p = default_limits() if params is None else params
    q = np.asarray(q, dtype=np.float64)
    qdot = np.asarray(qdot, dtype=np.float64)
    over = q - p.upper
    under = p.lower - q
    s_up = smooth_step(over / p.transition)
    s_low = smooth_step(under / p.transition)
    return -p.k_upper * s_up * over + p.k_lower * s_low * under - p.damping * (s_up + s_low) * qdot


class LigamentKernel:
    """`ligament_forces` for a single state, in plain Python floats, split in two parts.

    The simulation calls this every physics substep, where numpy's per-call overhead on six
    numbers would cost several times the arithmetic. It returns the spring part of each force and
    the damping coefficient in force (the damping times the quintic step), apart: the simulation
    applies the spring as a generalised force and gives the damping to MuJoCo as joint damping,
    which the implicit integrator handles stably. Applied explicitly, the 14 N·m·s/rad of a fully
    engaged ligament on the light foot makes the 0.005 s step diverge now and then.
    `qpos_adr` and `qvel_adr` locate the limited coordinates (in `params.coordinates` order) in
    the sequences passed to `__call__` and `total`. `total` agrees with `ligament_forces` to
    rounding (a test checks it).
    """

    def __init__(self, qpos_adr: list[int], qvel_adr: list[int], params: LimitParams | None = None):
        p = default_limits() if params is None else params
        if not len(qpos_adr) == len(qvel_adr) == len(p.names):
            raise ValueError(f"need {len(p.names)} position and velocity addresses")
        self.params = p
        self._qvel_adr = [int(i) for i in qvel_adr]
        self._rows = list(
            zip(
                [int(i) for i in qpos_adr],
                p.upper.tolist(),
                p.lower.tolist(),
                p.k_upper.tolist(),
                p.k_lower.tolist(),
                p.damping.tolist(),
                (1.0 / p.transition).tolist(),
            )
        )

    def __call__(self, qpos: list[float]) -> tuple[list[float], list[float]]:
        """Spring force (N·m) and engaged damping (N·m·s/rad) of each ligament at `qpos`."""
        springs, dampings = [], []
        for qa, upper, lower, k_up, k_low, damping, inv_tr in self._rows:
            x = qpos[qa]
            if x > upper:
                over, k = x - upper, k_up
                s = over * inv_tr
            elif x < lower:
                over, k = x - lower, k_low
                s = -over * inv_tr
            else:
                springs.append(0.0)
                dampings.append(0.0)
                continue
            if s > 1.0:
                s = 1.0
            step = s * s * s * (10.0 + s * (-15.0 + 6.0 * s))
            springs.append(-step * k * over)
            dampings.append(step * damping)
        return springs, dampings

    def total(self, springs: list[float], dampings: list[float], qvel: list[float]) -> list[float]:
        """The whole force of each ligament (N·m), as OpenSim reports it, at speeds `qvel`."""
        return [f - c * qvel[va] for f, c, va in zip(springs, dampings, self._qvel_adr)]
