"""The knee's translation exactly as OpenSim's splines move it, for MuJoCo's joint couplings.

The .osim knee slides the tibia along two `SimmSpline`s of the knee angle. The MJCF couples
the slide joints to the angle with a quartic fit (MuJoCo's `polycoef`), which is within 0.4 mm
of the splines but up to 2 mm/rad off in slope: at 5 rad/s of knee speed that moves the foot
1 cm/s, and a foot standing on the ground (friction rises by 8 times the normal force per m/s
of slip below 0.1 m/s) answers with tens of newtons. On each spline segment the spline is a
cubic, so the env writes the cubic of the segment the knee is in into the coupling before
MuJoCo builds its constraints: the coupling then holds the spline's position and slope exactly.

A soft constraint still drifts at a 2.5 ms step: under half excitation the tibia strayed up to
0.9 mm and 7 cm/s from the splines (MuJoCo enforces it through a spring of two steps' time
constant, and the implicit integrator's correction is not constrained). So after each physics
step `project` puts positions and speeds back on the splines, moving the body as an impulse
along the constraint would (the mass-weighted projection), as OpenSim's exact joint keeps them.
"""

from __future__ import annotations

import mujoco
import numba
import numpy as np

from l2r.sim.mujoco_numba import mj_solveM
from l2r.sim.opensim import Osim

EXTRAPOLATION = 1.0  # rad past the end knots over which the linear ends are sampled for their fit


def segment_cubics(f, origin: float) -> tuple[np.ndarray, np.ndarray]:
    """A spline of the knee angle as (breaks, cubics): cubics[i] (power coefficients, constant
    first) holds f - origin between breaks[i - 1] and breaks[i], the first and last rows the
    linear extrapolation beyond the end knots."""
    knots = np.asarray(f.x, float)
    edges = np.concatenate([[knots[0] - EXTRAPOLATION], knots, [knots[-1] + EXTRAPOLATION]])
    cubics = []
    for lo, hi in zip(edges, edges[1:]):
        q = np.linspace(lo, hi, 8)
        cubics.append(np.polyfit(q, f(q) - origin, 3)[::-1])  # exact: the segment is a cubic
    return knots, np.array(cubics)


class KneeCoupling:
    """A model's knee slide couplings and the .osim splines they follow.

    slides: {knee joint: (x slide joint, y slide joint)}; each slide's coupling is the equality
    named "<slide>_coupling", and the knee's and slides' reference positions (qpos0) must be 0.
    Every joint of the model must be a hinge or a slide (one qpos per dof).
    """

    def __init__(self, m: mujoco.MjModel, osim: Osim, slides: dict[str, tuple[str, str]]):
        self.knee_names, self.slide_names = [], []
        breaks, cubics = [], []
        if m.nq != m.nv:
            raise ValueError("the knee projection needs a model of hinges and slides only")
        for knee, pair in slides.items():
            if any(m.qpos0[m.joint(j).qposadr[0]] != 0.0 for j in (knee, *pair)):
                raise ValueError(f"{knee}: the coupling assumes the knee's and slides' reference positions are 0")
            joint = next(b.joint for b in osim.bodies.values() if b.joint is not None and b.joint.kind == "CustomJoint"
                         and b.joint.coordinates[0].name == knee)
            for slide, (_, _, f) in zip(pair, joint.translations):
                knots, segments = segment_cubics(f, float(f(np.zeros(1))[0]))
                self.knee_names.append(knee)
                self.slide_names.append(slide)
                breaks.append(knots)
                cubics.append(segments)
        self.equality = np.array([m.equality(f"{s}_coupling").id for s in self.slide_names])
        self.knee = np.array([m.joint(k).qposadr[0] for k in self.knee_names])  # qpos = dof addresses here
        self.slide = np.array([m.joint(k).qposadr[0] for k in self.slide_names])
        n = max(len(b) for b in breaks)
        self.breaks = np.full((len(breaks), n), np.inf)
        self.cubics = np.zeros((len(breaks), n + 1, 4))
        for i, (b, c) in enumerate(zip(breaks, cubics)):
            self.breaks[i, : len(b)] = b
            self.cubics[i, : len(c)] = c

    def slide_position(self, k: int, angle: float) -> float:
        """Coupling k's slide position (relative to its reference) at this knee angle."""
        return float(np.polyval(self.cubics[k, _segment(self.breaks[k], angle)][::-1], angle))


@numba.njit(cache=True)
def _segment(breaks: np.ndarray, q: float) -> int:
    i = 0
    while i < breaks.shape[0] and q >= breaks[i]:
        i += 1
    return i


@numba.njit(cache=True)
def follow_splines(equality, knee, breaks, cubics, qpos, eq_data) -> None:
    """Write into each coupling (MuJoCo's polycoef) the cubic of the segment its knee is in."""
    for k in range(equality.shape[0]):
        row = cubics[k, _segment(breaks[k], qpos[knee[k]])]
        for j in range(4):
            eq_data[equality[k], j] = row[j]
        eq_data[equality[k], 4] = 0.0


@numba.njit(cache=True)
def project(model, data, knee, slide, breaks, cubics, qpos, qvel) -> None:
    """Put the slides back on their splines, positions then speeds, each by the mass-weighted
    least change of all coordinates (one Newton step for positions; M from the last mj_step1)."""
    n, nv = knee.shape[0], qvel.shape[0]
    jac = np.zeros((n, nv))  # the couplings' Jacobian: slide - slope · knee
    residual = np.empty(n)
    for k in range(n):
        row = cubics[k, _segment(breaks[k], qpos[knee[k]])]
        q = qpos[knee[k]]
        jac[k, slide[k]] = 1.0
        jac[k, knee[k]] = -(row[1] + q * (2.0 * row[2] + q * 3.0 * row[3]))
        residual[k] = qpos[slide[k]] - (row[0] + q * (row[1] + q * (row[2] + q * row[3])))
    moves = np.empty((n, nv))
    mj_solveM(model, data, moves.ctypes.data, jac.ctypes.data, n)  # M^-1 J^T, a row per coupling
    gram = jac @ moves.T
    _correct(gram, moves, residual, qpos)
    _correct(gram, moves, jac @ qvel, qvel)


@numba.njit(cache=True)
def _correct(gram, moves, residual, x) -> None:
    """x -= moves^T gram^-1 residual, gram symmetric positive definite (Cholesky)."""
    n = residual.shape[0]
    low = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            total = gram[i, j]
            for k in range(j):
                total -= low[i, k] * low[j, k]
            low[i, j] = np.sqrt(total) if i == j else total / low[j, j]
    y = residual.copy()
    for i in range(n):  # forward, then back substitution
        for k in range(i):
            y[i] -= low[i, k] * y[k]
        y[i] /= low[i, i]
    for i in range(n - 1, -1, -1):
        for k in range(i + 1, n):
            y[i] -= low[k, i] * y[k]
        y[i] /= low[i, i]
    for k in range(n):
        for j in range(x.shape[0]):
            x[j] -= moves[k, j] * y[k]
