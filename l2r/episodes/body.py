"""What a viewer needs to draw the runner, read once from the MuJoCo model.

``BodyModel`` holds each body's shapes (the model's own geoms: spheres, capsules, boxes,
cylinders, ellipsoids; not the surfaces tendons wrap around) in the body's frame, and each
muscle's path as the sites it runs through (drawn straight from site to site: where a tendon
wraps a surface the line cuts across it; a muscle with a conditional point is drawn through it
even while the env pulls it along its second path, and moving points where they sit at knee
angle 0). A body without a visual geom is drawn as bones:
capsules to its children.

It travels inside every episode file as JSON, so an old log still draws after the model
changes, and renders itself as URDF (for Rerun) and as a ``foxglove.SceneUpdate`` (for
Foxglove). Poses are in the model's frame (y up); obstacles are ``(x, y, r)`` spheres.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from xml.sax.saxutils import quoteattr

import mujoco
import numpy as np
from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate

from l2r.episodes.schema import GROUND_FRAME, WORLD_FRAME
from l2r.sim.paths import OFF

_KINDS = {
    mujoco.mjtGeom.mjGEOM_SPHERE: "sphere",
    mujoco.mjtGeom.mjGEOM_CAPSULE: "capsule",
    mujoco.mjtGeom.mjGEOM_ELLIPSOID: "ellipsoid",
    mujoco.mjtGeom.mjGEOM_CYLINDER: "cylinder",
    mujoco.mjtGeom.mjGEOM_BOX: "box",
}
BONE_RADIUS = 0.025  # m
BONE_RGBA = (0.85, 0.8, 0.7, 1.0)
LEAF_RADIUS = 0.08  # m
GROUND_RGBA = (0.55, 0.6, 0.55, 1.0)
OBSTACLE_RGBA = (0.45, 0.35, 0.3, 1.0)
# The ground drawn as a slab whose top is y = 0: from 5 m behind the start to 45 m ahead.
GROUND_X, GROUND_LENGTH, GROUND_WIDTH, GROUND_THICKNESS = 20.0, 50.0, 2.0, 0.02


@dataclass
class Shape:
    """One primitive in a body's frame. ``size``: sphere (r,), capsule and cylinder
    (r, half length along local z), ellipsoid (rx, ry, rz), box (half x, y, z)."""

    body: str
    kind: str
    size: tuple[float, ...]
    pos: tuple[float, float, float]
    quat: tuple[float, float, float, float]  # w x y z
    rgba: tuple[float, float, float, float]


@dataclass
class BodyModel:
    bodies: tuple[str, ...]  # every body but the world, in model order (the logged order)
    shapes: list[Shape]
    muscles: tuple[str, ...]
    # For each muscle, the sites of its path: (index into bodies, position in that body's frame).
    paths: list[list[tuple[int, tuple[float, float, float]]]]

    # ------------------------------------------------------------------------ construction

    @classmethod
    def from_model(cls, m: mujoco.MjModel) -> BodyModel:
        bodies = tuple(m.body(i).name for i in range(1, m.nbody))
        shapes: list[Shape] = []
        drawn = set()
        # Surfaces tendons wrap around are part of the muscle model, not of the body's look.
        surfaces = (int(mujoco.mjtWrap.mjWRAP_CYLINDER), int(mujoco.mjtWrap.mjWRAP_SPHERE))
        wraps = {int(g) for g, kind in zip(m.wrap_objid, m.wrap_type) if int(kind) in surfaces}
        for g in range(m.ngeom):
            b, kind = int(m.geom_bodyid[g]), _KINDS.get(int(m.geom_type[g]))
            if b == 0 or kind is None or g in wraps:
                continue
            n = {"sphere": 1, "capsule": 2, "cylinder": 2}.get(kind, 3)
            shapes.append(Shape(bodies[b - 1], kind, _floats(m.geom_size[g][:n]), _floats(m.geom_pos[g]),
                                _floats(m.geom_quat[g]), _floats(m.geom_rgba[g])))  # fmt: skip
            if m.geom_contype[g] == 0 and m.geom_conaffinity[g] == 0:
                drawn.add(b)
        for child in range(1, m.nbody):
            parent = int(m.body_parentid[child])
            if parent and parent not in drawn:
                shapes.append(_bone(bodies[parent - 1], np.asarray(m.body_pos[child], float)))
        drawn_bodies = {s.body for s in shapes}
        for body in [b for b in bodies if b not in drawn_bodies]:  # a leaf with nothing to draw: a ball
            shapes.append(Shape(body, "sphere", (LEAF_RADIUS,), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), BONE_RGBA))
        muscles, paths = [], []
        for t in range(m.ntendon):
            if m.tendon(t).name.endswith(OFF):  # a muscle's second path: drawn as its first
                continue
            start, count = int(m.tendon_adr[t]), int(m.tendon_num[t])
            sites = [int(s) for s, kind in zip(m.wrap_objid[start : start + count], m.wrap_type[start : start + count])
                     if int(kind) == int(mujoco.mjtWrap.mjWRAP_SITE)]  # fmt: skip
            muscles.append(m.tendon(t).name)
            paths.append([(int(m.site_bodyid[s]) - 1, _floats(m.site_pos[s])) for s in sites if m.site_bodyid[s]])
        return cls(bodies, shapes, tuple(muscles), paths)

    def to_json(self) -> str:
        return json.dumps({"bodies": self.bodies, "shapes": [asdict(s) for s in self.shapes],
                           "muscles": self.muscles, "paths": self.paths})  # fmt: skip

    @classmethod
    def from_json(cls, text: str) -> BodyModel:
        d = json.loads(text)
        shapes = [Shape(s["body"], s["kind"], *(tuple(s[k]) for k in ("size", "pos", "quat", "rgba"))) for s in d["shapes"]]
        paths = [[(int(b), tuple(p)) for b, p in path] for path in d["paths"]]
        return cls(tuple(d["bodies"]), shapes, tuple(d["muscles"]), paths)

    # ---------------------------------------------------------------------------- geometry

    def muscle_points(self, pos: np.ndarray, quat: np.ndarray) -> list[np.ndarray]:
        """Each muscle's path in the ground frame: pos (..., bodies, 3), quat (..., bodies, 4)
        wxyz -> one array (..., sites, 3) per muscle."""
        out = []
        for path in self.paths:
            idx = np.array([b for b, _ in path], dtype=int)
            local = np.array([p for _, p in path], dtype=float).reshape(-1, 3)
            out.append(pos[..., idx, :] + rotate(quat[..., idx, :], local))
        return out

    # ------------------------------------------------------------------------ URDF (Rerun)

    def urdf(self, obstacles: list[tuple[float, float, float]] = ()) -> str:
        """The body as URDF: a floating link per body under ``ground``, which hangs from
        ``world`` rotated so that the model's y-up becomes z-up."""
        links = [f"<link name={quoteattr(WORLD_FRAME)}/>", _urdf_link(GROUND_FRAME, self.ground_shapes(obstacles))]
        joints = [_urdf_joint(GROUND_FRAME, "fixed", WORLD_FRAME, GROUND_FRAME, rpy=(math.pi / 2, 0.0, 0.0))]
        for body in self.bodies:
            links.append(_urdf_link(body, [s for s in self.shapes if s.body == body]))
            joints.append(_urdf_joint(body, "floating", GROUND_FRAME, body))
        return "\n".join(['<robot name="runner">', *links, *joints, "</robot>"])

    # --------------------------------------------------------------- SceneUpdate (Foxglove)

    def scene_update(self, time_ns: int, obstacles: list[tuple[float, float, float]] = ()) -> SceneUpdate:
        """One entity per body (locked to its frame, drawn for the whole episode) and one for
        the ground and obstacles."""
        scene = SceneUpdate()
        groups = [(GROUND_FRAME, self.ground_shapes(obstacles))]
        groups += [(body, [s for s in self.shapes if s.body == body]) for body in self.bodies]
        for frame, shapes in groups:
            entity = scene.entities.add(frame_id=frame, id=frame, frame_locked=True)
            entity.timestamp.FromNanoseconds(time_ns)
            for s in shapes:
                _add_primitive(entity, s)
        return scene

    def ground_shapes(self, obstacles: list[tuple[float, float, float]] = ()) -> list[Shape]:
        """The floor (a slab whose top is y = 0) and the obstacle spheres, in the ground frame."""
        half = (GROUND_LENGTH / 2, GROUND_THICKNESS / 2, GROUND_WIDTH / 2)
        ground = Shape(GROUND_FRAME, "box", half, (GROUND_X, -half[1], 0.0), (1.0, 0.0, 0.0, 0.0), GROUND_RGBA)
        balls = [Shape(GROUND_FRAME, "sphere", (r,), (x, y, 0.0), (1.0, 0.0, 0.0, 0.0), OBSTACLE_RGBA)
                 for x, y, r in obstacles]  # fmt: skip
        return [ground, *balls]


def rotate(quat: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate vectors ``v`` by unit quaternions ``quat`` (wxyz), broadcasting."""
    w, q = quat[..., :1], quat[..., 1:]
    t = 2.0 * np.cross(q, v)
    return v + w * t + np.cross(q, t)


def _floats(values) -> tuple[float, ...]:
    return tuple(float(v) for v in values)


def _bone(body: str, to: np.ndarray) -> Shape:
    """A capsule from the body's origin to ``to`` (a child's origin in the body's frame)."""
    length = float(np.linalg.norm(to))
    if length < 1e-6:
        return Shape(body, "sphere", (BONE_RADIUS,), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), BONE_RGBA)
    quat = np.zeros(4)
    mujoco.mju_quatZ2Vec(quat, to / length)  # capsules lie along their local z
    return Shape(body, "capsule", (BONE_RADIUS, length / 2), _floats(to / 2), _floats(quat), BONE_RGBA)


def _rpy(quat: tuple[float, ...]) -> tuple[float, float, float]:
    """URDF roll-pitch-yaw (fixed x, y, z axes) of a wxyz quaternion."""
    w, x, y, z = quat
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


def _urdf_geometry(s: Shape) -> str:
    if s.kind == "sphere":
        return f'<sphere radius="{s.size[0]:.6g}"/>'
    if s.kind in ("capsule", "cylinder"):
        return f'<{s.kind} radius="{s.size[0]:.6g}" length="{2 * s.size[1]:.6g}"/>'
    if s.kind == "box":
        return '<box size="{:.6g} {:.6g} {:.6g}"/>'.format(*(2 * h for h in s.size))
    return f'<sphere radius="{sum(s.size) / 3:.6g}"/>'  # URDF has no ellipsoid


def _urdf_link(name: str, shapes: list[Shape]) -> str:
    visuals = "".join(
        "<visual><origin xyz=\"{:.6g} {:.6g} {:.6g}\" rpy=\"{:.6g} {:.6g} {:.6g}\"/>".format(*s.pos, *_rpy(s.quat))
        + f"<geometry>{_urdf_geometry(s)}</geometry>"
        + f'<material name="{name}_{i}">'
        + '<color rgba="{:.3g} {:.3g} {:.3g} {:.3g}"/></material></visual>'.format(*s.rgba)
        for i, s in enumerate(shapes)
    )
    return f"<link name={quoteattr(name)}>{visuals}</link>"


def _urdf_joint(name: str, kind: str, parent: str, child: str, rpy=(0.0, 0.0, 0.0)) -> str:
    return (f"<joint name={quoteattr(name)} type=\"{kind}\"><parent link={quoteattr(parent)}/>"
            f"<child link={quoteattr(child)}/><origin rpy=\"{rpy[0]:.9g} {rpy[1]:.9g} {rpy[2]:.9g}\"/></joint>")  # fmt: skip


def _add_primitive(entity, s: Shape) -> None:
    """Foxglove primitives: a capsule is a cylinder with a sphere at each end."""
    r = s.size[0]
    if s.kind in ("capsule", "cylinder"):
        _set(entity.cylinders.add(), s, (0.0, 0.0, 0.0), (2 * r, 2 * r, 2 * s.size[1]))
        if s.kind == "capsule":
            for end in (-s.size[1], s.size[1]):
                _set(entity.spheres.add(), s, (0.0, 0.0, end), (2 * r,) * 3)
    elif s.kind == "box":
        _set(entity.cubes.add(), s, (0.0, 0.0, 0.0), tuple(2 * h for h in s.size))
    else:
        _set(entity.spheres.add(), s, (0.0, 0.0, 0.0), tuple(2 * v for v in (s.size * 3)[:3]))


def _set(primitive, s: Shape, offset: tuple[float, float, float], size: tuple[float, ...]) -> None:
    """Place ``primitive`` at the shape's pose shifted by ``offset`` along the shape's axes."""
    shift = np.zeros(3)
    mujoco.mju_rotVecQuat(shift, np.asarray(offset, float), np.asarray(s.quat, float))
    pos = np.asarray(s.pos) + shift
    p = primitive.pose
    p.position.x, p.position.y, p.position.z = (float(v) for v in pos)
    p.orientation.w, p.orientation.x, p.orientation.y, p.orientation.z = s.quat
    primitive.size.x, primitive.size.y, primitive.size.z = size
    primitive.color.r, primitive.color.g, primitive.color.b, primitive.color.a = s.rgba
