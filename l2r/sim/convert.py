"""Generate the MuJoCo body (`assets/runner.xml`) from the OpenSim model it ports.

    python -m l2r.sim.convert [--osim IN] [--out OUT] [--check]

The output depends only on the .osim file: every fitted number comes from OpenSim geometry and
forces computed from it (`l2r.sim.opensim`) over a dense grid of poses (`l2r.sim.fit`), never
from the validation figures. `--check` regenerates in memory and exits 1 when the committed
file differs beyond the last digits a CPU's floating point moves (`model_differences`), so a
test can hold the two together on any machine.
"""

from __future__ import annotations

import argparse
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from l2r.sim.fit import MusclePaths, knee_coupling, knee_origin, muscle_paths
from l2r.sim.model import OSIM_PATH
from l2r.sim.opensim import Osim, read_osim
from l2r.sim.paths import MOVING_TORQUE, OFF

ASSETS = Path(__file__).parent / "assets"
MJCF_PATH = ASSETS / "runner.xml"
TIMESTEP = 0.0025  # four physics steps per 0.01 s env step (docs/model.md: what a longer step costs in accuracy)
OBSTACLE_PARK = (-100.0, -10.0, 0.0)  # far behind and below the start until the env places them
# The feet meet the ground and the obstacles through the env's Hunt-Crossley forces
# (`l2r.sim.contact`): MuJoCo's collision detection is off and its geoms are for drawing.
GROUND_SITE = "ground_origin"
# MuJoCo softens a joint coupling by the summed inverse weights of both joints, and the light
# shank makes that large; an impedance near 1 keeps the knee translation on its curve.
COUPLING_SOLREF = (2 * TIMESTEP, 1.0)
COUPLING_SOLIMP = (0.9999, 0.9999, 0.001)


def _fmt(*values: float, digits: int = 6) -> str:
    out = []
    for v in np.ravel(values):
        s = f"{float(v):.{digits}f}".rstrip("0").rstrip(".")
        out.append("0" if s in ("-0", "") else s)
    return " ".join(out)


def _quat_z(angle: float) -> str:
    return _fmt(np.cos(angle / 2), 0, 0, np.sin(angle / 2), digits=9)


def build_mjcf(osim: Osim, paths: dict[str, MusclePaths]) -> str:
    """The MJCF text of the body: planar joints, welded lumbar, coupled knee translation,
    spatial tendons with a force actuator each (the env computes the muscles; a muscle with a
    conditional path point has a second tendon without it), foot spheres with a contact site and
    an x and a y force actuator each, ground and parked obstacles.

    Actuators: the 18 muscles in action order, the 8 contact forces, the `_off` paths, then
    one per coordinate that moves path points, for the work of that motion (`l2r.sim.paths`)."""
    root = ET.Element("mujoco", model="l2r_runner")
    ET.SubElement(root, "compiler", angle="radian", autolimits="true")
    option = ET.SubElement(root, "option", timestep=_fmt(TIMESTEP), gravity=_fmt(osim.gravity), integrator="implicitfast")
    ET.SubElement(option, "flag", contact="disable")
    default = ET.SubElement(root, "default")
    ET.SubElement(default, "joint", limited="false", armature="0", damping="0")
    ET.SubElement(default, "site", size="0.005", group="3")
    ET.SubElement(default, "geom", contype="0", conaffinity="0")
    foot = ET.SubElement(default, "default", attrib={"class": "foot"})
    ET.SubElement(foot, "geom", type="sphere", rgba="0.8 0.3 0.3 1")
    bone = ET.SubElement(default, "default", attrib={"class": "bone"})
    ET.SubElement(bone, "geom", type="capsule", size="0.025", group="1", mass="0", rgba="0.9 0.85 0.75 1")
    world_geom = ET.SubElement(default, "default", attrib={"class": "world"})
    ET.SubElement(world_geom, "geom", rgba="0.6 0.6 0.6 1")

    world = ET.SubElement(root, "worldbody")
    ET.SubElement(world, "geom", name="ground", type="plane", size="0 0 1", zaxis="0 1 0", attrib={"class": "world"})
    ET.SubElement(world, "site", name=GROUND_SITE)
    for i in range(3):
        ET.SubElement(world, "geom", name=f"obstacle_{i}", type="sphere", size="0.05", pos=_fmt(OBSTACLE_PARK), attrib={"class": "world"})

    children: dict[str, list[str]] = {}
    for name, body in osim.bodies.items():
        if body.joint is not None and name != "pelvis":
            children.setdefault(body.joint.parent, []).append(name)
    spheres = {s.body: s for s in osim.spheres}
    sites_by_body: dict[str, list] = {}
    tendons = {}  # tendon name: its path
    for muscle in osim.muscles:
        tendons[muscle.name] = paths[muscle.name].on
        if paths[muscle.name].off is not None:
            tendons[muscle.name + OFF] = paths[muscle.name].off
    for name, path in tendons.items():
        for i, (body, pos) in enumerate(path.sites):
            sites_by_body.setdefault(body, []).append((f"{name}_{i}", pos))

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
            pos = joint.offset + (knee_origin(osim, name) if joint.kind == "CustomJoint" else 0.0)
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
            # where the ground's force acts; the env moves it to the contact point every step
            ET.SubElement(el, "site", name=f"{s.name}_contact", pos=_fmt(s.location - np.array([0.0, s.radius, 0.0])))
        for site_name, pos in sites_by_body.get(name, []):
            ET.SubElement(el, "site", name=site_name, pos=_fmt(pos))
        # bones to look at, from each joint to the next; they neither collide nor weigh
        for child in children.get(name, []):
            joint = osim.bodies[child].joint
            end = joint.offset + (knee_origin(osim, child) if joint.kind == "CustomJoint" else 0.0)
            ET.SubElement(el, "geom", attrib={"class": "bone"}, fromto=_fmt(np.zeros(3), end))
        if not children.get(name):
            ET.SubElement(el, "geom", attrib={"class": "bone"}, type="sphere", size="0.08" if name == "head" else "0.02")
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
    for name, path in tendons.items():
        spatial = ET.SubElement(tendon, "spatial", name=name, width="0.004")
        for i in range(len(path.sites)):
            ET.SubElement(spatial, "site", site=f"{name}_{i}")
    # the env sets the tendon force (negative: pulling) and its stiffness as damping
    for muscle in osim.muscles:
        ET.SubElement(actuator, "general", name=muscle.name, tendon=muscle.name, biastype="affine")
    for sphere in osim.spheres:
        for axis, gear in (("x", "1 0 0 0 0 0"), ("y", "0 1 0 0 0 0")):
            ET.SubElement(actuator, "general", name=f"{sphere.name}_{axis}", site=f"{sphere.name}_contact",
                          refsite=GROUND_SITE, gear=gear, biastype="affine")
    for name in tendons:
        if name.endswith(OFF):
            ET.SubElement(actuator, "general", name=name, tendon=name, biastype="affine")
    moving = sorted({p.coordinate for muscle in osim.muscles for p in muscle.points if p.kind == "moving"})
    for coordinate in moving:
        ET.SubElement(actuator, "general", name=coordinate + MOVING_TORQUE, joint=coordinate)

    keyframe = ET.SubElement(root, "keyframe")
    ET.SubElement(keyframe, "key", name="default", qpos=_fmt(qpos0))
    ET.indent(root, space="  ")
    header = "<!-- Generated by `python -m l2r.sim.convert` from gait9dof18musc.osim (osim-rl, Apache-2.0). Do not edit. -->\n"
    return header + ET.tostring(root, encoding="unicode") + "\n"


def generate(osim_path: Path | str = OSIM_PATH) -> str:
    """The MJCF text for an .osim file."""
    osim = read_osim(osim_path)
    return build_mjcf(osim, {muscle.name: muscle_paths(muscle) for muscle in osim.muscles})


# The fit is least squares over floating-point sums whose order depends on the CPU's vector
# width: an AVX2 machine puts some path points 1e-5 m from where an AVX-512 one does. A check that
# the committed model is what the converter makes therefore compares numbers within this much of
# the committed value (5 times that difference; 0.05 mm on a length), and everything else exactly.
CHECK_ATOL, CHECK_RTOL = 5e-5, 1e-3


def model_differences(committed: str, generated: str) -> list[str]:
    """Where two MJCF texts differ: element tags, attribute names and words exactly, numbers
    beyond CHECK_ATOL + CHECK_RTOL * |committed|; [] when they agree. Comments are not compared."""
    ours, fresh = ET.fromstring(committed), ET.fromstring(generated)
    ours_elements, fresh_elements = list(ours.iter()), list(fresh.iter())
    if [e.tag for e in ours_elements] != [e.tag for e in fresh_elements]:
        return ["the elements differ (one was added, removed or moved)"]
    found = []
    for a, b in zip(ours_elements, fresh_elements):
        where = f"<{a.tag} name={a.get('name')!r}>" if a.get("name") else f"<{a.tag}>"
        for key in sorted(set(a.keys()) | set(b.keys())):
            x, y = a.get(key), b.get(key)
            if x != y and not _numbers_close(x, y):
                found.append(f"{where} {key}: {x!r} committed, {y!r} generated")
    return found


def _numbers_close(committed: str | None, generated: str | None) -> bool:
    try:
        x = np.array(committed.split(), float)
        y = np.array(generated.split(), float)
    except (AttributeError, ValueError):  # an attribute on one side only, or words
        return False
    return x.shape == y.shape and bool(np.all(np.abs(x - y) <= CHECK_ATOL + CHECK_RTOL * np.abs(x)))


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
        if not args.out.exists():
            print(f"{args.out} does not exist; run `python -m l2r.sim.convert`", file=sys.stderr)
            return 1
        differences = model_differences(args.out.read_text(), text)
        if differences:
            print(f"{args.out} differs from a fresh conversion of {args.osim} ({len(differences)} places, first: "
                  f"{differences[0]}); run `python -m l2r.sim.convert`", file=sys.stderr)
            return 1
        print(f"{args.out} is up to date (numbers within {CHECK_ATOL:g} + {100 * CHECK_RTOL:g} %)")
        return 0
    args.out.write_text(text)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
