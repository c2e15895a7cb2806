"""Generate the MuJoCo body (`assets/runner.xml`) from the OpenSim model it ports.

    python -m l2r.sim.convert [--osim IN] [--out OUT] [--check]

The output depends only on the .osim file: every fitted number comes from OpenSim geometry
computed here in numpy (see `l2r.sim.opensim_geometry` in this module's lower half) over a
dense grid of poses, never from the validation figures. `--check` regenerates in memory and
exits 1 when the committed file differs, so a test can hold the two together.
"""

from __future__ import annotations

import argparse
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ASSETS = Path(__file__).parent / "assets"
OSIM_PATH = ASSETS / "gait9dof18musc.osim"
MJCF_PATH = ASSETS / "runner.xml"

TIMESTEP = 0.005  # two physics steps per 0.01 s env step
KNEE_POLY_DEGREE = 4  # MuJoCo's joint coupling is a quartic
OBSTACLE_PARK = (-100.0, -10.0, 0.0)  # far behind and below the start until the env places them
MUSCLE_RANGE = (0.5, 1.6)  # normalised fibre lengths that `lengthrange` maps onto


# --------------------------------------------------------------------------- reading the .osim


class Spline:
    """OpenSim's `SimmSpline`: a cubic spline whose end third derivatives match the cubic
    through the four end knots (Forsythe, Malcolm and Moler), extrapolated linearly."""

    def __init__(self, x, y):
        self.x, self.y = np.asarray(x, float), np.asarray(y, float)
        n, h = len(self.x), np.diff(self.x)
        # unknowns: second derivatives m at the knots
        a, rhs = np.zeros((n, n)), np.zeros(n)
        if n == 2:
            a[0, 0] = a[1, 1] = 1.0
        else:
            slope = np.diff(self.y) / h
            for i in range(1, n - 1):
                a[i, i - 1 : i + 2] = h[i - 1], 2 * (h[i - 1] + h[i]), h[i]
                rhs[i] = 6 * (slope[i] - slope[i - 1])
            third = [0.0, 0.0]
            if n > 3:
                third = [6 * self._divided(slice(0, 4)), 6 * self._divided(slice(n - 4, n))]
            a[0, :2] = -1.0 / h[0], 1.0 / h[0]
            a[-1, -2:] = -1.0 / h[-1], 1.0 / h[-1]
            rhs[0], rhs[-1] = third
        self.m = np.linalg.solve(a, rhs)
        self.end_slopes = (self.derivative(self.x[0]), self.derivative(self.x[-1]))

    def _divided(self, s: slice) -> float:
        x, y = self.x[s], self.y[s].copy()
        for k in range(1, 4):
            y[k:] = (y[k:] - y[k - 1 : -1]) / (x[k:] - x[:-k])
        return float(y[3])

    def _segment(self, q):
        i = np.clip(np.searchsorted(self.x, q, side="right") - 1, 0, len(self.x) - 2)
        h = self.x[i + 1] - self.x[i]
        return i, h, (q - self.x[i]) / h

    def derivative(self, q):
        i, h, t = self._segment(np.asarray(q, float))
        m0, m1, y0, y1 = self.m[i], self.m[i + 1], self.y[i], self.y[i + 1]
        return (y1 - y0) / h - h * (m0 * (3 * (1 - t) ** 2 - 1) - m1 * (3 * t**2 - 1)) / 6

    def __call__(self, q):
        q = np.asarray(q, float)
        i, h, t = self._segment(np.clip(q, self.x[0], self.x[-1]))
        m0, m1, y0, y1 = self.m[i], self.m[i + 1], self.y[i], self.y[i + 1]
        inside = (1 - t) * y0 + t * y1 + h * h / 6 * (((1 - t) ** 3 - (1 - t)) * m0 + (t**3 - t) * m1)
        below = self.y[0] + (q - self.x[0]) * self.end_slopes[0]
        above = self.y[-1] + (q - self.x[-1]) * self.end_slopes[1]
        return np.where(q < self.x[0], below, np.where(q > self.x[-1], above, inside))


def _vec(el: ET.Element, tag: str) -> np.ndarray:
    found = el.find(tag)
    if found is None or found.text is None:
        raise ValueError(f"<{el.tag} name={el.get('name')!r}> has no <{tag}>")
    return np.array(found.text.split(), float)


def _num(el: ET.Element, tag: str, default: float | None = None) -> float:
    if el.find(tag) is None and default is not None:
        return default
    return float(_vec(el, tag)[0])


def _function(el: ET.Element):
    """A TransformAxis/MovingPathPoint function as a callable of the coordinate value."""
    (f,) = list(el)
    if f.tag == "SimmSpline":
        return Spline(_vec(f, "x"), _vec(f, "y"))
    if f.tag == "Constant":
        value = _num(f, "value")
        return lambda q: np.full_like(np.asarray(q, float), value)
    if f.tag == "LinearFunction":
        slope, offset = _vec(f, "coefficients")
        return lambda q: slope * np.asarray(q, float) + offset
    raise ValueError(f"unsupported OpenSim function <{f.tag}>")


@dataclass
class Coordinate:
    name: str
    default: float
    range: tuple[float, float]
    locked: bool


@dataclass
class Joint:
    kind: str
    parent: str
    offset: np.ndarray  # location_in_parent
    orientation: np.ndarray  # orientation_in_parent (body-fixed XYZ)
    coordinates: list[Coordinate]
    rotations: list = field(default_factory=list)  # (axis, coordinate name or None, function)
    translations: list = field(default_factory=list)


@dataclass
class Body:
    name: str
    mass: float
    com: np.ndarray
    inertia: np.ndarray  # xx yy zz xy xz yz
    joint: Joint | None


@dataclass
class PathPoint:
    name: str
    body: str
    location: np.ndarray
    kind: str  # "fixed", "conditional" or "moving"
    coordinate: str | None = None
    active_range: tuple[float, float] | None = None
    moving: tuple | None = None  # x, y, z functions of `coordinate`


@dataclass
class Muscle:
    name: str
    max_force: float
    optimal_length: float
    slack_length: float
    pennation: float
    max_velocity: float
    activation_tau: float
    deactivation_tau: float
    tendon_strain: float
    muscle_strain: float
    passive_shape: float
    points: list[PathPoint]


@dataclass
class Sphere:
    name: str
    body: str
    location: np.ndarray
    radius: float


@dataclass
class Osim:
    gravity: np.ndarray
    bodies: dict[str, Body]
    muscles: list[Muscle]
    spheres: list[Sphere]
    contact: dict[str, float]

    def coordinate(self, name: str) -> Coordinate:
        for body in self.bodies.values():
            for c in body.joint.coordinates if body.joint else ():
                if c.name == name:
                    return c
        raise KeyError(name)


def _read_joint(body_el: ET.Element) -> Joint | None:
    holder = body_el.find("Joint")
    if holder is None or len(holder) == 0:
        return None
    (j,) = list(holder)
    if np.any(_vec(j, "location")) or np.any(_vec(j, "orientation")):
        raise ValueError(f"joint {j.get('name')}: child-side joint frames are not supported")
    coords = [
        Coordinate(c.get("name"), _num(c, "default_value"), tuple(_vec(c, "range")), (c.findtext("locked") or "").strip() == "true")
        for c in j.iter("Coordinate")
    ]
    joint = Joint(j.tag, j.findtext("parent_body").strip(), _vec(j, "location_in_parent"), _vec(j, "orientation_in_parent"), coords)
    for axis_el in j.iter("TransformAxis"):
        coord = (axis_el.findtext("coordinates") or "").strip() or None
        entry = (_vec(axis_el, "axis"), coord, _function(axis_el.find("function")))
        (joint.rotations if axis_el.get("name").startswith("rotation") else joint.translations).append(entry)
    return joint


def _read_point(p: ET.Element) -> PathPoint:
    point = PathPoint(p.get("name"), p.findtext("body").strip(), _vec(p, "location"), "fixed")
    if p.tag == "ConditionalPathPoint":
        point.kind, point.coordinate, point.active_range = "conditional", p.findtext("coordinate").strip(), tuple(_vec(p, "range"))
    elif p.tag == "MovingPathPoint":
        point.kind, point.coordinate = "moving", p.findtext("x_coordinate").strip()
        point.moving = tuple(_function(p.find(f"{a}_location")) for a in "xyz")
    return point


def read_osim(path: Path | str) -> Osim:
    """Parse the parts of an OpenSim 3/4 model file that the port needs."""
    try:
        # OpenSim tags such as `HuntCrossleyForce::ContactParameters` are not valid XML names
        root = ET.fromstring(Path(path).read_text().replace("::", "__"))
    except (OSError, ET.ParseError) as e:
        raise ValueError(f"cannot read {path}: {e}") from e
    model = root.find("Model")
    if model is None:
        raise ValueError(f"{path}: no <Model> element; is this an .osim file?")
    bodies = {}
    for b in model.find("BodySet").iter("Body"):
        inertia = np.array([_num(b, f"inertia_{a}") for a in ("xx", "yy", "zz", "xy", "xz", "yz")])
        bodies[b.get("name")] = Body(b.get("name"), _num(b, "mass"), _vec(b, "mass_center"), inertia, _read_joint(b))
    muscles = []
    for m in model.iter("Thelen2003Muscle"):
        points = [_read_point(p) for p in m.find("GeometryPath/PathPointSet/objects")]
        muscles.append(
            Muscle(
                m.get("name"), _num(m, "max_isometric_force"), _num(m, "optimal_fiber_length"), _num(m, "tendon_slack_length"),
                _num(m, "pennation_angle_at_optimal"), _num(m, "max_contraction_velocity"), _num(m, "activation_time_constant"),
                _num(m, "deactivation_time_constant"), _num(m, "FmaxTendonStrain", 0.04), _num(m, "FmaxMuscleStrain", 0.6),
                _num(m, "KshapePassive", 5.0), points,
            )
        )
    spheres = [
        Sphere(s.get("name"), s.findtext("body_name").strip(), _vec(s, "location"), _num(s, "radius"))
        for s in model.iter("ContactSphere")
    ]
    hc = next(model.iter("HuntCrossleyForce__ContactParameters"))
    contact = {k: _num(hc, k) for k in ("stiffness", "dissipation", "static_friction")}
    return Osim(_vec(model, "gravity"), bodies, muscles, spheres, contact)


# --------------------------------------------------------------------------- OpenSim geometry


def _axis_rotation(axis: np.ndarray, angle) -> np.ndarray:
    """Rotation matrices (n, 3, 3) about a unit axis (Rodrigues)."""
    angle = np.atleast_1d(np.asarray(angle, float))
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    s, c = np.sin(angle)[:, None, None], np.cos(angle)[:, None, None]
    return np.eye(3) + s * k + (1 - c) * (k @ k)


def _euler_xyz(angles: np.ndarray) -> np.ndarray:
    r = np.eye(3)
    for axis, a in zip(np.eye(3), angles):
        r = r @ _axis_rotation(axis, a)[0]
    return r


def body_frames(osim: Osim, pose: dict[str, np.ndarray], translations: dict | None = None) -> dict:
    """Rotation (n,3,3) and origin (n,3) of every body in the pelvis frame.

    `pose` maps coordinate names to arrays of n values (missing ones take their defaults);
    `translations` optionally replaces a joint's translation functions: {body: f(q) -> (n,3)}.
    """
    n = len(next(iter(pose.values())))
    frames = {"pelvis": (np.broadcast_to(np.eye(3), (n, 3, 3)), np.zeros((n, 3)))}

    def value(coord_name):
        if coord_name in pose:
            return np.asarray(pose[coord_name], float)
        return np.full(n, osim.coordinate(coord_name).default)

    def frame(name):
        if name in frames:
            return frames[name]
        joint = osim.bodies[name].joint
        parent_r, parent_p = frame(joint.parent)
        fixed = _euler_xyz(joint.orientation)
        rot, trans = np.broadcast_to(np.eye(3), (n, 3, 3)), np.zeros((n, 3))
        if joint.kind == "PinJoint":
            rot = _axis_rotation(np.array([0.0, 0.0, 1.0]), value(joint.coordinates[0].name))
        elif joint.kind == "CustomJoint":
            for axis, coord, f in joint.rotations:
                rot = rot @ _axis_rotation(axis, f(value(coord)) if coord else f(np.zeros(n)))
            if name in (translations or {}):
                trans = translations[name](value(joint.coordinates[0].name))
            else:
                for axis, coord, f in joint.translations:
                    trans = trans + np.outer(f(value(coord)) if coord else f(np.zeros(n)), axis)
        elif joint.kind != "WeldJoint":
            raise ValueError(f"{name}: unsupported joint type {joint.kind}")
        r = parent_r @ fixed @ rot
        p = parent_p + np.einsum("nij,j->ni", parent_r, joint.offset) + np.einsum("nij,nj->ni", parent_r @ fixed, trans)
        frames[name] = (r, p)
        return frames[name]

    for name in osim.bodies:
        if name not in ("ground", "pelvis"):
            frame(name)
    return frames


def _place(frames: dict, body: str, local) -> np.ndarray:
    r, p = frames[body]
    local = np.asarray(local, float)
    return p + (np.einsum("nij,nj->ni", r, local) if local.ndim == 2 else np.einsum("nij,j->ni", r, local))


def opensim_length(osim: Osim, muscle: Muscle, pose: dict[str, np.ndarray], switch_pose: dict | None = None) -> np.ndarray:
    """Muscle-tendon length along OpenSim's path: fixed points, conditional points only
    inside their coordinate range (judged at `switch_pose`, default `pose`, so that moment
    arms can hold the path's points fixed as OpenSim does), moving points at their spline
    positions."""
    frames = body_frames(osim, pose)
    switch_pose = pose if switch_pose is None else switch_pose
    n = len(next(iter(pose.values())))
    length, previous = np.zeros(n), None
    for point in muscle.points:
        active = np.ones(n, bool)
        local = point.location
        if point.kind != "fixed":
            q = np.asarray(pose.get(point.coordinate, np.full(n, osim.coordinate(point.coordinate).default)))
            if point.kind == "conditional":
                q = np.asarray(switch_pose[point.coordinate]) if point.coordinate in switch_pose else q
                active = (q >= point.active_range[0]) & (q <= point.active_range[1])
            else:
                local = np.stack([f(q) for f in point.moving], axis=1)
        position = _place(frames, point.body, local)
        if previous is None:
            previous = position
            continue
        length += np.where(active, np.linalg.norm(position - previous, axis=1), 0.0)
        previous = np.where(active[:, None], position, previous)
    return length


def thelen_isometric_force(muscle: Muscle, mtu_length: np.ndarray, activation: float) -> np.ndarray:
    """Tendon force (N) of OpenSim's Thelen2003Muscle at rest, fibre and tendon in equilibrium.

    Thelen (2003): Gaussian active force-length (shape 0.45), exponential passive curve,
    exponential-then-linear tendon, fixed-width pennation; OpenSim holds activation >= 0.01.
    """
    a = max(activation, 0.01)
    l0, ls, e0t = muscle.optimal_length, muscle.slack_length, muscle.tendon_strain
    width = l0 * np.sin(muscle.pennation)
    kpe, e0m = muscle.passive_shape, muscle.muscle_strain
    toe_strain, toe_force, k_toe = 99 * e0t * np.exp(3) / (166 * np.exp(3) - 67), 0.33, 3.0
    k_lin = 0.67 / (e0t - toe_strain)

    def tendon(strain):
        toe = toe_force / (np.exp(k_toe) - 1) * (np.exp(k_toe * strain / toe_strain) - 1)
        return np.where(strain > toe_strain, k_lin * (strain - toe_strain) + toe_force, np.where(strain > 0, toe, 0.0))

    def fibre(along):  # fibre force along the tendon for fibre length projected on the tendon
        lm = np.sqrt(along**2 + width**2) / l0
        passive = np.where(lm > 1, (np.exp(kpe * (lm - 1) / e0m) - 1) / (np.exp(kpe) - 1), 0.0)
        return (a * np.exp(-((lm - 1) ** 2) / 0.45) + passive) * along / (lm * l0)

    # bisection on the projected fibre length: the tendon side falls as the fibre lengthens
    lo, hi = np.full_like(mtu_length, 1e-6), np.maximum(mtu_length - ls, 2e-6)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        tendon_longer = fibre(mid) < tendon((mtu_length - mid) / ls - 1)
        lo, hi = np.where(tendon_longer, mid, lo), np.where(tendon_longer, hi, mid)
    force = muscle.max_force * tendon((mtu_length - 0.5 * (lo + hi)) / ls - 1)
    return np.where(mtu_length > ls, force, 0.0)


def mujoco_isometric_force(muscle: Muscle, mtu_length: np.ndarray, activation: float, c: "MuscleCurves") -> np.ndarray:
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


ISOMETRIC_ACTIVATIONS = (0.0, 0.5, 1.0)


def fit_curves(muscle: Muscle, mtu_lengths: np.ndarray) -> "MuscleCurves":
    """lmin, lmax, fpmax matching Thelen's isometric tendon force over the lengths the muscle
    reaches, and fvmax matching Thelen's force-velocity curve (Af 0.25, Flen 1.4)."""
    from scipy.optimize import least_squares

    targets = [thelen_isometric_force(muscle, mtu_lengths, a) / muscle.max_force for a in ISOMETRIC_ACTIVATIONS]

    def residual(p):
        c = MuscleCurves(p[0], p[1], p[2])
        return np.concatenate([mujoco_isometric_force(muscle, mtu_lengths, a, c) / muscle.max_force - t
                               for a, t in zip(ISOMETRIC_ACTIVATIONS, targets)])

    fit = least_squares(residual, [0.5, 1.6, 1.3], bounds=([0.05, 1.05, 0.0], [0.95, 3.0, 20.0]), method="trf", diff_step=1e-4)
    v = np.linspace(0.0, 1.0, 101)  # lengthening velocity in max-velocity units
    f_len = 1.4  # OpenSim 4's Thelen2003Muscle default
    thelen = (10 * v * f_len + f_len - 1) / (10 * v + f_len - 1)

    def fv_residual(fvmax):
        y = fvmax - 1
        return np.where(v <= y, fvmax - (y - v) ** 2 / y, fvmax) - thelen

    fvmax = least_squares(lambda p: fv_residual(p[0]), [1.4], bounds=([1.05], [2.0])).x[0]
    return MuscleCurves(*np.round(fit.x, 4), round(float(fvmax), 4))



# --------------------------------------------------------------------------- fitting muscle paths

GRID_POINTS = {1: 81, 2: 29}  # samples per coordinate for muscles spanning one or two joints
# The fit spans each coordinate's .osim range clipped to +-90 degrees: the ligaments stop the
# joints well inside it, and past it (hip hyperextension beyond 90 degrees) the conditional
# psoas point makes the OpenSim path jump by 2 cm, which no smooth path should chase.
GRID_LIMIT = np.pi / 2
MOMENT_ARM_STEP = 1e-6


def spanned_coordinates(osim: Osim, muscle: Muscle) -> list[str]:
    """The unlocked coordinates of the joints between the muscle's first and last body."""
    def chain(body):
        out = [body]
        while osim.bodies[out[-1]].joint is not None and out[-1] != "pelvis":
            out.append(osim.bodies[out[-1]].joint.parent)
        return out

    first, last = chain(muscle.points[0].body), chain(muscle.points[-1].body)
    between = [b for b in first + last if (b in first) != (b in last)]
    coords = [c.name for b in between if b != "pelvis" for c in osim.bodies[b].joint.coordinates if not c.locked]
    return [c for name in osim.bodies for c in coords if c in [k.name for k in (osim.bodies[name].joint.coordinates if osim.bodies[name].joint else [])]]


def pose_grid(osim: Osim, coordinates: list[str]) -> dict[str, np.ndarray]:
    """A full grid over the coordinates' .osim ranges."""
    axes = [np.linspace(*np.clip(osim.coordinate(c).range, -GRID_LIMIT, GRID_LIMIT), GRID_POINTS[len(coordinates)]) for c in coordinates]
    return {c: g.ravel() for c, g in zip(coordinates, np.meshgrid(*axes, indexing="ij"))}


def coupled_translations(osim: Osim) -> dict:
    """The knee translation as MuJoCo's quartic coupling makes it, for `body_frames`."""
    out = {}
    for name, body in osim.bodies.items():
        if body.joint is not None and body.joint.kind == "CustomJoint":
            coefs, origin = knee_coupling(osim, name), _knee_origin(osim, name)
            out[name] = lambda q, c=coefs, o=origin: o + np.stack(
                [np.polyval(c[0][::-1], q), np.polyval(c[1][::-1], q), np.zeros_like(q)], axis=1)
    return out


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


def _to_body(frames: dict, body: str, points: np.ndarray) -> np.ndarray:
    r, p = frames[body]
    return np.einsum("nji,nj->ni", r, points - p)


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
    points = [_place(frames, b, pos) for b, pos in path.sites]
    total = 0.0
    for i, (p, q) in enumerate(zip(points, points[1:])):
        if path.wrap is not None and i == path.wrap_after:
            body, centre, radius, side = path.wrap
            total = total + wrapped_length(_to_body(frames, body, p), _to_body(frames, body, q), centre, radius, side)
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
        before, after = (_to_body(frames, point.body, _place(frames, q.body, q.location))[0] for q in (muscle.points[i - 1], muscle.points[i + 1]))
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
    return path(np.round(fit.x, 6)), float(np.sqrt(np.mean(fit.fun[: len(target)] ** 2)))


def fit_muscle_path(osim: Osim, muscle: Muscle) -> MusclePath:
    """The best fitted path among `initial_paths`."""
    fits = [fit_path(osim, muscle, start) for start in initial_paths(osim, muscle)]
    return min(fits, key=lambda f: f[1])[0]


# --------------------------------------------------------------------------- the MuJoCo body


def _fmt(*values: float, digits: int = 6) -> str:
    out = []
    for v in np.ravel(values):
        s = f"{float(v):.{digits}f}".rstrip("0").rstrip(".")
        out.append("0" if s in ("-0", "") else s)
    return " ".join(out)


def _quat_z(angle: float) -> str:
    return _fmt(np.cos(angle / 2), 0, 0, np.sin(angle / 2), digits=9)


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


def _knee_origin(osim: Osim, body: str) -> np.ndarray:
    joint = osim.bodies[body].joint
    return np.array([f(np.zeros(1))[0] for _, _, f in joint.translations])


@dataclass
class MusclePath:
    """The MuJoCo path of one muscle: sites (body, local position) in order, and optionally a
    wrapping cylinder (body, centre, radius, side-site position) between sites `wrap_after`
    and `wrap_after + 1`."""

    sites: list[tuple[str, np.ndarray]]
    wrap: tuple[str, np.ndarray, float, np.ndarray] | None = None
    wrap_after: int = 0


def static_path(muscle: Muscle) -> MusclePath:
    """Every OpenSim point as a site; moving points at their knee-angle-0 position."""
    sites = []
    for p in muscle.points:
        local = p.location if p.kind != "moving" else np.array([f(np.zeros(1))[0] for f in p.moving])
        sites.append((p.body, local))
    return MusclePath(sites)


@dataclass
class MuscleCurves:
    lmin: float = 0.5
    lmax: float = 1.6
    fpmax: float = 1.3
    fvmax: float = 1.2


def build_mjcf(osim: Osim, paths: dict[str, MusclePath], curves: dict[str, MuscleCurves], contact: dict) -> str:
    """The MJCF text of the body: planar joints, welded lumbar, coupled knee translation,
    muscles on spatial tendons, foot spheres, ground and parked obstacles."""
    root = ET.Element("mujoco", model="l2r_runner")
    ET.SubElement(root, "compiler", angle="radian", autolimits="true")
    ET.SubElement(root, "option", timestep=_fmt(TIMESTEP), gravity=_fmt(osim.gravity), integrator="implicitfast")
    default = ET.SubElement(root, "default")
    ET.SubElement(default, "joint", limited="false", armature="0", damping="0")
    ET.SubElement(default, "site", size="0.005", group="3")
    contact_attrs = dict(condim="3", friction=_fmt(contact["friction"], 0.005, 0.0001), solref=_fmt(contact["timeconst"], 1.0), solimp=_fmt(CONTACT_IMPEDANCE))
    foot = ET.SubElement(default, "default", attrib={"class": "foot"})
    ET.SubElement(foot, "geom", type="sphere", contype="1", conaffinity="2", rgba="0.8 0.3 0.3 1", **contact_attrs)
    world_geom = ET.SubElement(default, "default", attrib={"class": "world"})
    ET.SubElement(world_geom, "geom", contype="2", conaffinity="1", rgba="0.6 0.6 0.6 1", **contact_attrs)

    world = ET.SubElement(root, "worldbody")
    ET.SubElement(world, "geom", name="ground", type="plane", size="0 0 1", zaxis="0 1 0", attrib={"class": "world"})
    for i in range(3):
        ET.SubElement(world, "geom", name=f"obstacle_{i}", type="sphere", size="0.05", pos=_fmt(OBSTACLE_PARK), attrib={"class": "world"})

    children: dict[str, list[str]] = {}
    for name, body in osim.bodies.items():
        if body.joint is not None and name != "pelvis":
            children.setdefault(body.joint.parent, []).append(name)
    spheres = {s.body: s for s in osim.spheres}
    sites_by_body: dict[str, list] = {}
    for muscle in osim.muscles:
        for i, (body, pos) in enumerate(paths[muscle.name].sites):
            sites_by_body.setdefault(body, []).append((f"{muscle.name}_{i}", pos))
        wrap = paths[muscle.name].wrap
        if wrap is not None:
            sites_by_body.setdefault(wrap[0], []).append((f"{muscle.name}_side", wrap[1] + wrap[3] * (wrap[2] + 0.01)))

    qpos0: list[float] = []  # the .osim default pose, in MuJoCo's joint order

    def add_joint(el: ET.Element, name: str, kind: str, axis: str, value: float) -> None:
        ET.SubElement(el, "joint", name=name, type=kind, axis=axis)
        qpos0.append(value)

    def add_body(parent_el: ET.Element, name: str) -> None:
        body = osim.bodies[name]
        joint = body.joint
        attrs = {"name": name}
        if name == "pelvis":
            el = ET.SubElement(parent_el, "body", **attrs)
            # translations first: MuJoCo moves along slide axes in the frame before later hinges
            for coord, kind, axis in (("pelvis_tx", "slide", "1 0 0"), ("pelvis_ty", "slide", "0 1 0"), ("pelvis_tilt", "hinge", "0 0 1")):
                add_joint(el, coord, kind, axis, osim.coordinate(coord).default)
        else:
            if np.any(joint.orientation):
                raise ValueError(f"{name}: rotated joint frames are not supported")
            pos = joint.offset + (_knee_origin(osim, name) if joint.kind == "CustomJoint" else 0.0)
            attrs["pos"] = _fmt(pos)
            locked = [c for c in joint.coordinates if c.locked]
            if joint.kind == "PinJoint" and locked:
                attrs["quat"] = _quat_z(locked[0].default)
            el = ET.SubElement(parent_el, "body", **attrs)
            side = name[-1]
            if joint.kind == "CustomJoint":
                q = np.array([joint.coordinates[0].default])
                for (_, _, f), axis_name, axis in zip(joint.translations, ("tx", "ty"), ("1 0 0", "0 1 0")):
                    add_joint(el, f"knee_{axis_name}_{side}", "slide", axis, float(f(q)[0] - f(np.zeros(1))[0]))
            if joint.kind in ("PinJoint", "CustomJoint") and not locked:
                add_joint(el, joint.coordinates[0].name, "hinge", "0 0 1", joint.coordinates[0].default)
        inertia = np.maximum(body.inertia, 0.0)
        if not np.any(inertia[:3]):
            inertia[:3] = 1e-6  # a point mass in the .osim; MuJoCo needs some rotational inertia
        ET.SubElement(el, "inertial", pos=_fmt(body.com), mass=_fmt(body.mass), fullinertia=_fmt(inertia, digits=7))
        if name in spheres:
            s = spheres[name]
            ET.SubElement(el, "geom", name=s.name, size=_fmt(s.radius), pos=_fmt(s.location), attrib={"class": "foot"})
        for site_name, pos in sites_by_body.get(name, []):
            ET.SubElement(el, "site", name=site_name, pos=_fmt(pos))
        for muscle in osim.muscles:
            wrap = paths[muscle.name].wrap
            if wrap is not None and wrap[0] == name:
                ET.SubElement(el, "geom", name=f"{muscle.name}_wrap", type="cylinder", pos=_fmt(wrap[1]), size=_fmt(wrap[2], 0.02),
                              contype="0", conaffinity="0", group="3", mass="0")
        for child in children.get(name, []):
            add_body(el, child)

    add_body(world, "pelvis")

    equality = ET.SubElement(root, "equality")
    for name, body in osim.bodies.items():
        if body.joint is not None and body.joint.kind == "CustomJoint":
            side = name[-1]
            coefs = knee_coupling(osim, name)
            for axis, c in zip(("tx", "ty"), coefs):
                ET.SubElement(equality, "joint", name=f"knee_{axis}_{side}_coupling", joint1=f"knee_{axis}_{side}",
                              joint2=body.joint.coordinates[0].name, polycoef=_fmt(c, digits=8),
                              solref=_fmt(COUPLING_SOLREF), solimp=_fmt(COUPLING_SOLIMP))

    tendon = ET.SubElement(root, "tendon")
    actuator = ET.SubElement(root, "actuator")
    for muscle in osim.muscles:
        path = paths[muscle.name]
        spatial = ET.SubElement(tendon, "spatial", name=muscle.name, width="0.004")
        for i in range(len(path.sites)):
            ET.SubElement(spatial, "site", site=f"{muscle.name}_{i}")
            if path.wrap is not None and i == path.wrap_after:
                ET.SubElement(spatial, "geom", geom=f"{muscle.name}_wrap", sidesite=f"{muscle.name}_side")
        c = curves[muscle.name]
        # MuJoCo normalises length as range0 + (L - lengthrange0) / L0 with
        # L0 = (lengthrange1 - lengthrange0) / (range1 - range0); these bounds make the normalised
        # length exactly (L - tendon slack) / optimal fibre length.
        lengthrange = muscle.slack_length + np.array(MUSCLE_RANGE) * muscle.optimal_length
        ET.SubElement(
            actuator, "muscle", name=muscle.name, tendon=muscle.name, ctrlrange="0 1",
            force=_fmt(muscle.max_force), lengthrange=_fmt(lengthrange, digits=8), range=_fmt(MUSCLE_RANGE),
            timeconst=_fmt(muscle.activation_tau, muscle.deactivation_tau), vmax=_fmt(muscle.max_velocity),
            lmin=_fmt(c.lmin, digits=4), lmax=_fmt(c.lmax, digits=4), fpmax=_fmt(c.fpmax, digits=4), fvmax=_fmt(c.fvmax, digits=4),
        )

    keyframe = ET.SubElement(root, "keyframe")
    ET.SubElement(keyframe, "key", name="default", qpos=_fmt(qpos0))
    ET.indent(root, space="  ")
    header = "<!-- Generated by `python -m l2r.sim.convert` from gait9dof18musc.osim (osim-rl, Apache-2.0). Do not edit. -->\n"
    return header + ET.tostring(root, encoding="unicode") + "\n"



CONTACT_IMPEDANCE = (0.9, 0.95, 0.001)  # MuJoCo's default solimp
# MuJoCo softens a joint coupling by the summed inverse weights of both joints, and the light
# shank makes that large; an impedance near 1 keeps the knee translation on its curve.
COUPLING_SOLREF = (2 * TIMESTEP, 1.0)
COUPLING_SOLIMP = (0.9999, 0.9999, 0.001)


def hunt_crossley_sink(osim: Osim) -> float:
    """How far the body, held rigid in its default pose, sinks from it until the .osim's
    Hunt-Crossley spheres carry its weight (negative: it rises). Each sphere pushes with
    4/3 k^1.5 sqrt(R) d^1.5, k = stiffness^(2/3) / 2 for two equally stiff surfaces (Simbody)."""
    pose = {"pelvis_tilt": np.array([osim.coordinate("pelvis_tilt").default])}
    frames = body_frames(osim, pose)
    tilt = _axis_rotation(np.array([0.0, 0.0, 1.0]), pose["pelvis_tilt"][0])[0]
    heights = np.array([osim.coordinate("pelvis_ty").default + (tilt @ _place(frames, s.body, s.location)[0])[1] for s in osim.spheres])
    radius = np.array([s.radius for s in osim.spheres])
    weight = sum(b.mass for b in osim.bodies.values()) * float(np.linalg.norm(osim.gravity))
    k = osim.contact["stiffness"] ** (2 / 3) / 2
    lo, hi = -1.0, 1.0
    for _ in range(80):
        sink = 0.5 * (lo + hi)
        depth = np.maximum(radius - heights + sink, 0.0)
        lo, hi = (sink, hi) if np.sum(4 / 3 * k**1.5 * np.sqrt(radius) * depth**1.5) < weight else (lo, sink)
    return 0.5 * (lo + hi)


def mujoco_sink(model, timeconst: float) -> float:
    """The same test on the MuJoCo body: joints held by stiff springs at the default pose,
    muscles off, foot contacts with this solref time constant, settled for 3 s."""
    import mujoco

    m = model.__copy__()
    m.opt.disableflags |= mujoco.mjtDisableBit.mjDSBL_ACTUATION
    for g in range(m.ngeom):
        m.geom_solref[g, 0] = timeconst
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, 0)
    hinges = m.jnt_type == mujoco.mjtJoint.mjJNT_HINGE
    m.jnt_stiffness[hinges] = 3e4
    m.dof_damping[m.jnt_dofadr[hinges]] = 300.0
    m.qpos_spring[:] = d.qpos
    start = d.qpos[1]
    mujoco.mj_step(m, d, round(3.0 / TIMESTEP))
    return float(start - d.qpos[1])


def tune_contact(osim: Osim, mjcf: str) -> float:
    """The solref time constant (damping ratio 1) under which the MuJoCo body rests at the
    height the Hunt-Crossley contacts hold it: bisection, in log time."""
    import mujoco

    model = mujoco.MjModel.from_xml_string(mjcf)
    target = hunt_crossley_sink(osim)
    lo, hi = np.log(2 * TIMESTEP), np.log(1.0)
    for _ in range(14):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if mujoco_sink(model, float(np.exp(mid))) < target else (lo, mid)
    return round(float(np.exp(0.5 * (lo + hi))), 4)


def generate(osim_path: Path | str = OSIM_PATH) -> str:
    """The MJCF text for an .osim file."""
    osim = read_osim(osim_path)
    paths, curves = {}, {}
    for muscle in osim.muscles:
        paths[muscle.name] = fit_muscle_path(osim, muscle)
        pose = pose_grid(osim, spanned_coordinates(osim, muscle))
        curves[muscle.name] = fit_curves(muscle, opensim_length(osim, muscle, pose))
    contact = {"friction": osim.contact["static_friction"], "timeconst": 0.02}
    contact["timeconst"] = tune_contact(osim, build_mjcf(osim, paths, curves, contact))
    return build_mjcf(osim, paths, curves, contact)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m l2r.sim.convert", description=__doc__.split("\n\n")[0])
    parser.add_argument("--osim", type=Path, default=OSIM_PATH, help="OpenSim model to convert (default: the packaged one)")
    parser.add_argument("--out", type=Path, default=MJCF_PATH, help="MJCF file to write or check (default: the packaged runner.xml)")
    parser.add_argument("--check", action="store_true", help="do not write; exit 1 when OUT differs from a fresh conversion")
    args = parser.parse_args(argv)
    try:
        text = generate(args.osim)
    except ValueError as e:
        print(f"convert: {e}", file=sys.stderr)
        return 2
    if args.check:
        current = args.out.read_text() if args.out.exists() else ""
        if current != text:
            print(f"{args.out} differs from a fresh conversion of {args.osim}; run `python -m l2r.sim.convert`", file=sys.stderr)
            return 1
        print(f"{args.out} is up to date")
        return 0
    args.out.write_text(text)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
