"""Fitting the MuJoCo body to OpenSim: the knee coupling, the muscle paths (sites and wrapping
cylinders) and the muscle curves.

Targets are computed by `l2r.sim.opensim` from the .osim file over a dense grid of poses; the
fits are deterministic least squares, so the converter reproduces its output exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from l2r.sim.opensim import Muscle, Osim, body_frames, opensim_length, place, thelen_isometric_force, to_body

KNEE_POLY_DEGREE = 4  # MuJoCo's joint coupling is a quartic
GRID_POINTS = {1: 81, 2: 29}  # samples per coordinate for muscles spanning one or two joints
# The fit spans each coordinate's .osim range clipped to +-90 degrees: the ligaments stop the
# joints well inside it, and past it (hip hyperextension beyond 90 degrees) the conditional
# psoas point makes the OpenSim path jump by 2 cm, which no smooth path should chase.
GRID_LIMIT = np.pi / 2
MOMENT_ARM_STEP = 1e-6
ISOMETRIC_ACTIVATIONS = (0.0, 0.5, 1.0)


@dataclass
class MusclePath:
    """The MuJoCo path of one muscle: sites (body, local position) in order, and optionally a
    wrapping cylinder (body, centre, radius, unit direction of its side site from the centre)
    between sites `wrap_after` and `wrap_after + 1`."""

    sites: list[tuple[str, np.ndarray]]
    wrap: tuple[str, np.ndarray, float, np.ndarray] | None = None
    wrap_after: int = 0


@dataclass
class MuscleCurves:
    """MuJoCo's muscle curve parameters (normalised lengths; forces relative to max force)."""

    lmin: float = 0.5
    lmax: float = 1.6
    fpmax: float = 1.3
    fvmax: float = 1.2


def static_path(muscle: Muscle) -> MusclePath:
    """Every OpenSim point as a site; moving points at their knee-angle-0 position."""
    sites = []
    for p in muscle.points:
        local = p.location if p.kind != "moving" else np.array([f(np.zeros(1))[0] for f in p.moving])
        sites.append((p.body, local))
    return MusclePath(sites)


def knee_coupling(osim: Osim, body: str) -> np.ndarray:
    """Quartic coefficients (MuJoCo `polycoef`) of the knee's x and y translation, relative to
    knee angle 0, least-squares over the angle's range: shape (2, 5)."""
    joint = osim.bodies[body].joint
    lo, hi = joint.coordinates[0].range
    q = np.linspace(lo, hi, 801)
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


def coupled_translations(osim: Osim) -> dict:
    """The knee translation as MuJoCo's quartic coupling makes it, for `body_frames`."""
    out = {}
    for name, body in osim.bodies.items():
        if body.joint is not None and body.joint.kind == "CustomJoint":
            coefs, origin = knee_coupling(osim, name), knee_origin(osim, name)
            out[name] = lambda q, c=coefs, o=origin: o + np.stack(
                [np.polyval(c[0][::-1], q), np.polyval(c[1][::-1], q), np.zeros_like(q)], axis=1)
    return out


def spanned_coordinates(osim: Osim, muscle: Muscle) -> list[str]:
    """The unlocked coordinates of the joints between the muscle's first and last body."""
    def chain(body):
        out = [body]
        while osim.bodies[out[-1]].joint is not None and out[-1] != "pelvis":
            out.append(osim.bodies[out[-1]].joint.parent)
        return out

    first, last = chain(muscle.points[0].body), chain(muscle.points[-1].body)
    between = [b for b in first + last if (b in first) != (b in last)]
    spanned = {c.name for b in between if b != "pelvis" for c in osim.bodies[b].joint.coordinates if not c.locked}
    in_file_order = [c.name for b in osim.bodies.values() if b.joint is not None for c in b.joint.coordinates]
    return [c for c in in_file_order if c in spanned]


def pose_grid(osim: Osim, coordinates: list[str]) -> dict[str, np.ndarray]:
    """A full grid over the coordinates' .osim ranges."""
    axes = [np.linspace(*np.clip(osim.coordinate(c).range, -GRID_LIMIT, GRID_LIMIT), GRID_POINTS[len(coordinates)]) for c in coordinates]
    return {c: g.ravel() for c, g in zip(coordinates, np.meshgrid(*axes, indexing="ij"))}


def _shifted_poses(pose: dict, coordinates: list[str]) -> list[dict]:
    """The pose, then each coordinate nudged up and down, for central-difference moment arms."""
    out = [pose]
    for c in coordinates:
        for sign in (1, -1):
            out.append({**pose, c: pose[c] + sign * MOMENT_ARM_STEP})
    return out


def _lengths_and_arms(lengths: list[np.ndarray]) -> np.ndarray:
    """[L, -dL/dq per coordinate] flattened, from lengths at the `_shifted_poses`."""
    arms = [-(up - down) / (2 * MOMENT_ARM_STEP) for up, down in zip(lengths[1::2], lengths[2::2])]
    return np.concatenate([lengths[0], *arms])


def _segments_cross(p1, p2, p3, p4) -> np.ndarray:
    """Whether 2D segments p1-p2 and p3-p4 (arrays of (n,2)) intersect."""
    det = (p4[:, 1] - p3[:, 1]) * (p2[:, 0] - p1[:, 0]) - (p4[:, 0] - p3[:, 0]) * (p2[:, 1] - p1[:, 1])
    safe = np.where(np.abs(det) < 1e-15, 1.0, det)
    a = ((p4[:, 0] - p3[:, 0]) * (p1[:, 1] - p3[:, 1]) - (p4[:, 1] - p3[:, 1]) * (p1[:, 0] - p3[:, 0])) / safe
    b = ((p2[:, 0] - p1[:, 0]) * (p1[:, 1] - p3[:, 1]) - (p2[:, 1] - p1[:, 1]) * (p1[:, 0] - p3[:, 0])) / safe
    return (np.abs(det) >= 1e-15) & (a >= 0) & (a <= 1) & (b >= 0) & (b <= 1)


def wrapped_length(a: np.ndarray, b: np.ndarray, centre: np.ndarray, radius: float, side: np.ndarray) -> np.ndarray:
    """Length from a to b (n,3, in the cylinder's body frame; axis z) as MuJoCo wraps a tendon
    on a cylinder with a side site in direction `side`: straight when the segment clears the
    circle on the side site's side; else along the tangents whose chord midpoint lies towards
    the side site and the arc between them, the height change spread along (a helix)."""
    pa, pb = a[:, :2] - centre[:2], b[:, :2] - centre[:2]
    sq0, sq1, r2 = np.sum(pa**2, axis=1), np.sum(pb**2, axis=1), radius**2
    dif = pb - pa
    t = np.clip(-np.sum(dif * pa, axis=1) / np.maximum(np.sum(dif**2, axis=1), 1e-15), 0.0, 1.0)
    near = pa + t[:, None] * dif
    straight = (sq0 < r2) | (sq1 < r2) | ((np.sum(near**2, axis=1) > r2) & (near @ side[:2] >= 0))
    root0, root1 = np.sqrt(np.maximum(sq0 - r2, 0.0)), np.sqrt(np.maximum(sq1 - r2, 0.0))
    options = []
    for sgn in (1.0, -1.0):
        t0 = np.stack([pa[:, 0] * r2 + sgn * radius * pa[:, 1] * root0, pa[:, 1] * r2 - sgn * radius * pa[:, 0] * root0], 1) / sq0[:, None]
        t1 = np.stack([pb[:, 0] * r2 - sgn * radius * pb[:, 1] * root1, pb[:, 1] * r2 + sgn * radius * pb[:, 0] * root1], 1) / sq1[:, None]
        mid = t0 + t1
        good = (mid @ side[:2]) / np.maximum(np.linalg.norm(mid, axis=1), 1e-15)
        crossing = _segments_cross(pa, t0, pb, t1)
        options.append((t0, t1, np.where(crossing, -1e4, good), crossing))
    first = options[0][2] > options[1][2]
    t0 = np.where(first[:, None], options[0][0], options[1][0])
    t1 = np.where(first[:, None], options[0][1], options[1][1])
    straight |= np.where(first, options[0][3], options[1][3])
    cos = np.sum(t0 * t1, axis=1) / np.maximum(np.linalg.norm(t0, axis=1) * np.linalg.norm(t1, axis=1), 1e-15)
    angle = np.arccos(np.clip(cos, -1.0, 1.0))
    cross = t0[:, 1] * t1[:, 0] - t0[:, 0] * t1[:, 1]
    angle = np.where(((cross > 0) & ~first) | ((cross < 0) & first), 2 * np.pi - angle, angle)
    wrapped = np.linalg.norm(pa - t0, axis=1) + radius * angle + np.linalg.norm(pb - t1, axis=1)
    planar = np.where(straight, np.linalg.norm(dif, axis=1), wrapped)
    return np.sqrt(planar**2 + (b[:, 2] - a[:, 2]) ** 2)


def path_length(frames: dict, path: MusclePath) -> np.ndarray:
    """Length of a MuJoCo muscle path (sites and an optional wrapping cylinder)."""
    points = [place(frames, b, pos) for b, pos in path.sites]
    total = 0.0
    for i, (p, q) in enumerate(zip(points, points[1:])):
        if path.wrap is not None and i == path.wrap_after:
            body, centre, radius, side = path.wrap
            total = total + wrapped_length(to_body(frames, body, p), to_body(frames, body, q), centre, radius, side)
        else:
            total = total + np.linalg.norm(q - p, axis=1)
    return total


def initial_paths(osim: Osim, muscle: Muscle) -> list[MusclePath]:
    """Starting paths to fit: every OpenSim point as a site (conditional ones always on, moving
    ones at knee angle 0), and, for each conditional point, a thin cylinder just behind it on
    the side it bends the path to: the path then bends there only while the point would be
    in the way, and goes straight when it has moved clear, as the conditional point does."""
    paths = [static_path(muscle)]
    default = {c: np.array([osim.coordinate(c).default]) for c in spanned_coordinates(osim, muscle)}
    frames = body_frames(osim, default)
    for i, point in enumerate(muscle.points):
        if point.kind != "conditional" or i in (0, len(muscle.points) - 1):
            continue
        # neighbours and the point in the point's body frame, at the default pose
        before, after = (to_body(frames, point.body, place(frames, q.body, q.location))[0] for q in (muscle.points[i - 1], muscle.points[i + 1]))
        chord = after - before
        normal = np.array([-chord[1], chord[0], 0.0])
        side = normal * np.sign(np.dot(normal, point.location - before))
        side /= np.linalg.norm(side)
        radius = 0.005
        sites = [site for j, site in enumerate(static_path(muscle).sites) if j != i]
        paths.append(MusclePath(sites, (point.body, point.location - side * radius, radius, side), wrap_after=i - 1))
    return paths


def fit_path(osim: Osim, muscle: Muscle, start: MusclePath) -> tuple[MusclePath, float]:
    """Site positions (x, y in their bodies; z kept) and cylinder centre and radius whose
    MuJoCo path best matches OpenSim's length and moment arms over the pose grid. Returns
    the path and its RMS residual (m)."""
    from scipy.optimize import least_squares

    coords = spanned_coordinates(osim, muscle)
    pose = pose_grid(osim, coords)
    poses = _shifted_poses(pose, coords)
    # OpenSim holds the active path points fixed while it differentiates, so do we
    target = _lengths_and_arms([opensim_length(osim, muscle, p, pose) for p in poses])
    translations = coupled_translations(osim)
    frames = [body_frames(osim, p, translations) for p in poses]
    x0 = np.array([pos[:2] for _, pos in start.sites]).ravel()
    if start.wrap is not None:
        x0 = np.concatenate([x0, start.wrap[1][:2], [start.wrap[2]]])

    def path(x):
        sites = [(b, np.array([x[2 * i], x[2 * i + 1], pos[2]])) for i, (b, pos) in enumerate(start.sites)]
        if start.wrap is None:
            return MusclePath(sites)
        body, centre, _, side = start.wrap
        return MusclePath(sites, (body, np.array([x[-3], x[-2], centre[2]]), x[-1], side), start.wrap_after)

    def residual(x):
        p = path(x)
        # a weak pull towards the anatomical positions keeps redundant sites where they were
        return np.concatenate([_lengths_and_arms([path_length(f, p) for f in frames]) - target, 0.01 * (x - x0)])

    lower = np.full(len(x0), -np.inf)
    if start.wrap is not None:
        lower[-1] = 0.002
    fit = least_squares(residual, x0, bounds=(lower, np.inf), method="trf", x_scale=0.01, diff_step=1e-3)
    # 10 µm steps: far below the errors that matter, and coarse enough that another BLAS is
    # very unlikely to move a rounded digit
    return path(np.round(fit.x, 5)), float(np.sqrt(np.mean(fit.fun[: len(target)] ** 2)))


def fit_muscle_path(osim: Osim, muscle: Muscle) -> MusclePath:
    """The best fitted path among `initial_paths`."""
    fits = [fit_path(osim, muscle, start) for start in initial_paths(osim, muscle)]
    return min(fits, key=lambda f: f[1])[0]


def mujoco_isometric_force(muscle: Muscle, mtu_length: np.ndarray, activation: float, c: MuscleCurves) -> np.ndarray:
    """MuJoCo's muscle force at rest with a rigid tendon (its FL and passive curves)."""
    x = (mtu_length - muscle.slack_length) / muscle.optimal_length
    a, b = 0.5 * (c.lmin + 1), 0.5 * (1 + c.lmax)
    active = np.select(
        [(x < c.lmin) | (x > c.lmax), x <= a, x <= 1, x <= b],
        [0.0, 0.5 * ((x - c.lmin) / (a - c.lmin)) ** 2, 1 - 0.5 * ((1 - x) / (1 - a)) ** 2, 1 - 0.5 * ((x - 1) / (b - 1)) ** 2],
        0.5 * ((c.lmax - x) / (c.lmax - b)) ** 2,
    )
    passive = np.select([x <= 1, x <= b], [0.0, 0.5 * ((x - 1) / (b - 1)) ** 2], 0.5 + (x - b) / (b - 1)) * c.fpmax
    return muscle.max_force * (activation * active + passive)


def fit_curves(muscle: Muscle, mtu_lengths: np.ndarray) -> MuscleCurves:
    """lmin, lmax, fpmax matching Thelen's isometric tendon force over the lengths the muscle
    reaches, and fvmax matching Thelen's force-velocity curve (Af 0.25, Flen 1.4)."""
    from scipy.optimize import least_squares

    targets = [thelen_isometric_force(muscle, mtu_lengths, a) / muscle.max_force for a in ISOMETRIC_ACTIVATIONS]

    def residual(p):
        c = MuscleCurves(p[0], p[1], p[2])
        return np.concatenate([mujoco_isometric_force(muscle, mtu_lengths, a, c) / muscle.max_force - t
                               for a, t in zip(ISOMETRIC_ACTIVATIONS, targets)])

    fit = least_squares(residual, [0.5, 1.6, 1.3], bounds=([0.05, 1.05, 0.0], [0.95, 3.0, 20.0]), method="trf", diff_step=1e-4)
    # Thelen's lengthening branch at full activation, solved for force: v = (F - 1) / b with
    # b = (2 + 2/Af) (Flen - F) / (Flen - 1), Af = 0.25; v in max-velocity units
    v = np.linspace(0.0, 1.0, 101)
    f_len = 1.4  # OpenSim 4's Thelen2003Muscle default
    thelen = (10 * v * f_len + f_len - 1) / (10 * v + f_len - 1)

    def fv_residual(fvmax):
        y = fvmax - 1
        return np.where(v <= y, fvmax - (y - v) ** 2 / y, fvmax) - thelen

    fvmax = least_squares(lambda p: fv_residual(p[0]), [1.4], bounds=([1.05], [2.0])).x[0]
    return MuscleCurves(*np.round(fit.x, 4), round(float(fvmax), 4))
