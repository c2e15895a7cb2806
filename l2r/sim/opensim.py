"""The OpenSim side of the port: the parts of an .osim model the MuJoCo body needs, and the
path geometry OpenSim would compute from them, in numpy.

Everything here follows OpenSim 4 (`SimmSpline`, `CustomJoint`, conditional and moving path
points), so that the converter and the env can follow OpenSim without running OpenSim.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


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
    contact_elements: dict[str, str]
    """Each contact sphere's Hunt-Crossley force element (`foot_r` holds r_heel and r_toe against
    the platform): Simbody lists an element's contacts together and stops at a contact with no force."""

    def coordinate(self, name: str) -> Coordinate:
        for body in self.bodies.values():
            for c in body.joint.coordinates if body.joint else ():
                if c.name == name:
                    return c
        raise ValueError(f"the model has no coordinate {name!r}")


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
    try:
        return _read_model(model)
    except (AttributeError, TypeError, StopIteration) as e:  # a missing element somewhere
        raise ValueError(f"{path}: not a complete OpenSim model ({type(e).__name__}: {e})") from e


def _read_model(model: ET.Element) -> Osim:
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
    force = next(model.iter("HuntCrossleyForce"))
    hc = next(force.iter("HuntCrossleyForce__ContactParameters"))
    contact = {k: _num(hc, k) for k in ("stiffness", "dissipation", "static_friction", "dynamic_friction", "viscous_friction")}
    contact["transition_velocity"] = _num(force, "transition_velocity")
    names = {s.name for s in spheres}
    elements = {geometry: f.get("name") for f in model.iter("HuntCrossleyForce")
                for parameters in f.iter("HuntCrossleyForce__ContactParameters")
                for geometry in parameters.findtext("geometry").split() if geometry in names}
    return Osim(_vec(model, "gravity"), bodies, muscles, spheres, contact, elements)


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


def place(frames: dict, body: str, local) -> np.ndarray:
    r, p = frames[body]
    local = np.asarray(local, float)
    return p + (np.einsum("nij,nj->ni", r, local) if local.ndim == 2 else np.einsum("nij,j->ni", r, local))


def to_body(frames: dict, body: str, points: np.ndarray) -> np.ndarray:
    r, p = frames[body]
    return np.einsum("nji,nj->ni", r, points - p)


def opensim_length(osim: Osim, muscle: Muscle, pose: dict[str, np.ndarray], switch_pose: dict | None = None) -> np.ndarray:
    """Muscle-tendon length along OpenSim's path: fixed points, conditional points only
    inside their coordinate range (judged at `switch_pose`, default `pose`, so that moment
    arms can hold the path's points fixed as OpenSim does), moving points at their spline
    positions for the coordinate clamped to its range, as OpenSim 4.6 evaluates them."""
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
                q = np.clip(q, *osim.coordinate(point.coordinate).range)
                local = np.stack([f(q) for f in point.moving], axis=1)
        position = place(frames, point.body, local)
        if previous is None:
            previous = position
            continue
        length += np.where(active, np.linalg.norm(position - previous, axis=1), 0.0)
        previous = np.where(active[:, None], position, previous)
    return length
