"""The MuJoCo body's geometry from OpenSim's: the knee coupling and the muscle paths.

The MJCF's knee coupling is a least-squares quartic of the .osim splines (MuJoCo's `polycoef`),
so the converter reproduces its output exactly; the env replaces it with the splines themselves
as it steps (`l2r.sim.knee`), and the quartic serves MuJoCo used on its own. The muscle paths need no fit: their sites are the .osim path
points, and what a fixed site cannot do (conditional and moving points) `l2r.sim.paths` does.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from l2r.sim.opensim import Muscle, Osim, place

KNEE_POLY_DEGREE = 4  # MuJoCo's joint coupling is a quartic
# The knee coupling is fitted past the .osim range by this much (rad): the range is the knee's
# normal motion, not its limit, and the runner hyperextends it beyond its 10 degrees (to 14
# degrees falling passively, 19 under half excitation).
RANGE_MARGIN = 0.35


@dataclass
class MusclePath:
    """A MuJoCo path of one muscle: sites (body, local position) in order."""

    sites: list[tuple[str, np.ndarray]]


@dataclass
class MusclePaths:
    """A muscle's MuJoCo paths: `on`, through every point, and for a muscle with a
    `ConditionalPathPoint`, `off`, without it, for when its coordinate leaves the point's range
    (OpenSim then drops the point from the path: the length jumps, and so does the force)."""

    on: MusclePath
    off: MusclePath | None = None


def static_path(muscle: Muscle) -> MusclePath:
    """Every OpenSim point as a site; moving points at their knee-angle-0 position."""
    sites = []
    for p in muscle.points:
        local = p.location if p.kind != "moving" else np.array([f(np.zeros(1))[0] for f in p.moving])
        sites.append((p.body, local))
    return MusclePath(sites)


def knee_coupling(osim: Osim, body: str) -> np.ndarray:
    """Quartic coefficients (MuJoCo `polycoef`) of the knee's x and y translation, relative to
    knee angle 0, least-squares over the angle's range and RANGE_MARGIN beyond: shape (2, 5)."""
    joint = osim.bodies[body].joint
    lo, hi = joint.coordinates[0].range
    q = np.linspace(lo - RANGE_MARGIN, hi + RANGE_MARGIN, 801)
    coefs = []
    for axis_index in (0, 1):
        _, _, f = joint.translations[axis_index]
        dy = f(q) - f(np.zeros(1))
        # no constant term, so the coupling holds exactly at the default pose (all zeros)
        basis = np.stack([q**k for k in range(1, KNEE_POLY_DEGREE + 1)], axis=1)
        c, *_ = np.linalg.lstsq(basis, dy, rcond=None)
        coefs.append(np.concatenate([[0.0], c]))
    return np.array(coefs)


def knee_origin(osim: Osim, body: str) -> np.ndarray:
    """Where the knee's translation splines put the tibia at knee angle 0 (femur frame)."""
    joint = osim.bodies[body].joint
    return np.array([f(np.zeros(1))[0] for _, _, f in joint.translations])


def path_length(frames: dict, path: MusclePath) -> np.ndarray:
    """Length of a MuJoCo muscle path: straight lines from site to site."""
    points = [place(frames, b, pos) for b, pos in path.sites]
    return sum(np.linalg.norm(q - p, axis=1) for p, q in zip(points, points[1:]))


def muscle_paths(muscle: Muscle) -> MusclePaths:
    """A muscle's MuJoCo paths: its .osim points as sites, moving ones where they sit at
    coordinate 0 (the env moves them), and a second path without a conditional point."""
    full = static_path(muscle)
    conditional = [i for i, p in enumerate(muscle.points) if p.kind == "conditional"]
    if not conditional:
        return MusclePaths(full)
    if len(conditional) > 1:
        raise ValueError(f"{muscle.name}: more than one conditional path point is not supported")
    without = MusclePath([site for i, site in enumerate(full.sites) if i != conditional[0]])
    return MusclePaths(full, without)
