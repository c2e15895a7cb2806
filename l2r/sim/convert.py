"""Generate the MuJoCo body (`assets/runner.xml`) from the OpenSim model it ports.

    python -m l2r.sim.convert [--osim IN] [--out OUT] [--check]

The output depends only on the .osim file: every fitted number comes from OpenSim geometry and
forces computed from it (`l2r.sim.opensim`) over a dense grid of poses (`l2r.sim.fit`), never
from the validation figures. `--check` regenerates in memory and exits 1 when the committed
file differs, so a test can hold the two together.
"""

from __future__ import annotations

import argparse
import sys
import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path

import numpy as np

from l2r.sim.fit import MuscleCurves, MusclePath, fit_curves, fit_muscle_path, knee_coupling, knee_origin, pose_grid, spanned_coordinates
from l2r.sim.opensim import Osim, hunt_crossley_sink, opensim_length, read_osim

ASSETS = Path(__file__).parent / "assets"
OSIM_PATH = ASSETS / "gait9dof18musc.osim"
MJCF_PATH = ASSETS / "runner.xml"
TIMESTEP = 0.005  # two physics steps per 0.01 s env step
OBSTACLE_PARK = (-100.0, -10.0, 0.0)  # far behind and below the start until the env places them
MUSCLE_RANGE = (0.5, 1.6)  # normalised fibre lengths that `lengthrange` maps onto
CONTACT_IMPEDANCE = (0.9, 0.95, 0.001)  # MuJoCo's default solimp
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
    bone = ET.SubElement(default, "default", attrib={"class": "bone"})
    ET.SubElement(bone, "geom", type="capsule", size="0.025", contype="0", conaffinity="0", group="1", mass="0", rgba="0.9 0.85 0.75 1")
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
        for site_name, pos in sites_by_body.get(name, []):
            ET.SubElement(el, "site", name=site_name, pos=_fmt(pos))
        for muscle in osim.muscles:
            wrap = paths[muscle.name].wrap
            if wrap is not None and wrap[0] == name:
                ET.SubElement(el, "geom", name=f"{muscle.name}_wrap", type="cylinder", pos=_fmt(wrap[1]), size=_fmt(wrap[2], 0.02),
                              contype="0", conaffinity="0", group="3", mass="0")
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
    # 1 ms steps move the resting height by about 0.4 mm, and keep the value from flickering
    # with a MuJoCo version's last bits
    return round(float(np.exp(0.5 * (lo + hi))), 3)


def generate(osim_path: Path | str = OSIM_PATH, progress: Callable[[str], None] | None = None) -> str:
    """The MJCF text for an .osim file; `progress` receives a line per stage."""
    osim = read_osim(osim_path)
    paths, curves = {}, {}
    for i, muscle in enumerate(osim.muscles):
        if progress:
            progress(f"fitting muscle {i + 1}/{len(osim.muscles)}: {muscle.name}")
        paths[muscle.name] = fit_muscle_path(osim, muscle)
        pose = pose_grid(osim, spanned_coordinates(osim, muscle))
        curves[muscle.name] = fit_curves(muscle, opensim_length(osim, muscle, pose))
    contact = {"friction": osim.contact["static_friction"], "timeconst": 0.02}
    if progress:
        progress("tuning foot contacts to the Hunt-Crossley resting height")
    contact["timeconst"] = tune_contact(osim, build_mjcf(osim, paths, curves, contact))
    return build_mjcf(osim, paths, curves, contact)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m l2r.sim.convert", description=__doc__.split("\n\n")[0])
    parser.add_argument("--osim", type=Path, default=OSIM_PATH, help="OpenSim model to convert (default: the packaged one)")
    parser.add_argument("--out", type=Path, default=MJCF_PATH, help="MJCF file to write or check (default: the packaged runner.xml)")
    parser.add_argument("--check", action="store_true", help="do not write; exit 1 when OUT differs from a fresh conversion")
    args = parser.parse_args(argv)
    try:
        text = generate(args.osim, progress=lambda line: print(line, file=sys.stderr))
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
