"""Compare the MuJoCo body with figures OpenSim computed on the original model.

    python -m l2r.sim.validate [--reference FILE] [--json]
    l2r validate [--reference FILE] [--json]

FILE has the format of `assets/opensim_reference.json` (any poses and samples): muscle-tendon
lengths and moment arms per pose, isometric tendon forces at activations 0, 0.5 and 1,
ligament forces, and rollouts from the default pose (a constant `excitation`, or an `excitations`
list of 18 per step, or the excitation named in the label). Lengths are those of the tendon each
muscle's conditional point selects, with moving points placed; moment arms are -dL/dq along the
knee's coupled translation with the pose's path held, as OpenSim differentiates; isometric forces
are the env's Thelen muscles in equilibrium at those lengths. `l2r.sim.dynamics` compares the
two simulators along rollouts.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

import mujoco
import numpy as np

from l2r.config import EXIT_FAILURE, EXIT_USAGE, CommandParser
from l2r.sim import PORT_ID, WARP_ID
from l2r.sim import model as body
from l2r.sim import thelen
from l2r.sim.opensim import read_osim
from l2r.sim.paths import MovingPoints, PathSwitches

DEFAULT_REFERENCE = Path(__file__).parent / "assets" / "opensim_reference.json"
ACTIVATIONS = ("0.0", "0.5", "1.0")
MOMENT_ARM_STEP = 1e-6
SPANS_THRESHOLD = 1e-4  # m: a muscle spans a joint when OpenSim's moment arm ever exceeds this
FALL_HEIGHT = 0.65
TARGETS = {  # from the issue; checked on the muscle-joint pairs each muscle spans
    "moment_arm_median_m": 0.001,
    "moment_arm_worst_m": 0.005,
    "mtu_length_worst_m": 0.005,
    "isometric_force_mean_frac": 0.10,
    "ligament_max_rel_error": 0.01,
    "reset_obs_max_abs_error": 0.001,
    "fall_step_rel_error": 0.05,
}


class ReferenceError(ValueError):
    """The reference file is missing, unreadable or not in the expected format."""


# --------------------------------------------------------------------------- reading the file


def _require(cond: bool, where: str, what: str) -> None:
    if not cond:
        raise ReferenceError(f"{where}: {what}")


def _number(value, where: str) -> float:
    _require(isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value), where, f"expected a finite number, got {value!r}")
    return float(value)


def load_reference(path: Path | str) -> dict:
    """Read and check a reference file; raises ReferenceError saying what is wrong and where."""
    try:
        ref = json.loads(Path(path).read_text())
    except OSError as e:
        raise ReferenceError(f"cannot read {path}: {e.strerror or e}") from e
    except json.JSONDecodeError as e:
        raise ReferenceError(f"{path} is not valid JSON: {e}") from e
    _require(isinstance(ref, dict), str(path), "top level must be a JSON object")
    for key in ("geometry", "isometric_forces", "ligaments", "rollouts"):
        _require(isinstance(ref.get(key), list), str(path), f"missing list {key!r}")
    for i, g in enumerate(ref["geometry"]):
        where = f"geometry[{i}]"
        _require(isinstance(g, dict) and isinstance(g.get("pose"), dict) and isinstance(g.get("muscles"), dict), where, "needs 'pose' and 'muscles' objects")
        for c, v in g["pose"].items():
            _require(c in body.COORDINATES, f"{where}.pose", f"unknown coordinate {c!r}")
            _number(v, f"{where}.pose.{c}")
        for m, entry in g["muscles"].items():
            _require(m in body.MUSCLES, f"{where}.muscles", f"unknown muscle {m!r}")
            _require(isinstance(entry, dict) and isinstance(entry.get("moment_arms"), dict), f"{where}.muscles.{m}", "needs 'mtu_length' and 'moment_arms'")
            _number(entry.get("mtu_length"), f"{where}.muscles.{m}.mtu_length")
            for c, v in entry["moment_arms"].items():
                _require(c in body.COORDINATES, f"{where}.muscles.{m}.moment_arms", f"unknown coordinate {c!r}")
                _number(v, f"{where}.muscles.{m}.moment_arms.{c}")
    for i, s in enumerate(ref["isometric_forces"]):
        where = f"isometric_forces[{i}]"
        _require(isinstance(s, dict) and isinstance(s.get("pose"), dict) and isinstance(s.get("forces"), dict), where, "needs 'pose' and 'forces' objects")
        for m, by_act in s["forces"].items():
            _require(m in body.MUSCLES, f"{where}.forces", f"unknown muscle {m!r}")
            _require(isinstance(by_act, dict) and set(by_act) <= set(ACTIVATIONS), f"{where}.forces.{m}", f"keys must be among {ACTIVATIONS}")
            for a, v in by_act.items():
                _number(v, f"{where}.forces.{m}.{a}")
    for i, s in enumerate(ref["ligaments"]):
        where = f"ligaments[{i}]"
        _require(isinstance(s, dict) and all(isinstance(s.get(k), dict) for k in ("q", "qdot", "forces")), where, "needs 'q', 'qdot' and 'forces' objects")
    for i, r in enumerate(ref["rollouts"]):
        where = f"rollouts[{i}]"
        _require(isinstance(r, dict), where, "must be an object")
        _require(isinstance(r.get("reset_observation"), list) and len(r["reset_observation"]) == 41, where, "'reset_observation' must hold 41 numbers")
        _require(isinstance(r.get("trajectory_first18"), list) and all(isinstance(x, list) and len(x) == 18 for x in r["trajectory_first18"]), where, "'trajectory_first18' must be a list of 18-number rows")
        rollout_excitations(r, len(r["trajectory_first18"]), where)
    return ref


def rollout_excitations(rollout: dict, steps: int, where: str = "rollout") -> np.ndarray:
    """A rollout's excitations, one row of 18 per step (steps x 18): its `excitations` list, one
    row per step of its trajectory, or its constant excitation held for `steps`."""
    if "excitations" not in rollout:
        return np.full((steps, len(body.MUSCLES)), rollout_excitation(rollout, where))
    rows = rollout["excitations"]
    _require(isinstance(rows, list) and all(isinstance(x, list) and len(x) == len(body.MUSCLES) for x in rows),
             f"{where}.excitations", f"must be a list of {len(body.MUSCLES)}-number rows")
    _require(len(rows) >= len(rollout.get("trajectory_first18", [])), f"{where}.excitations", "needs a row for every step of the trajectory")
    return np.array([[_number(v, f"{where}.excitations[{k}]") for v in row] for k, row in enumerate(rows)])


def rollout_excitation(rollout: dict, where: str = "rollout") -> float:
    """The constant excitation of a rollout: its 'excitation' field, else read from its label."""
    if "excitation" in rollout:
        return _number(rollout["excitation"], f"{where}.excitation")
    label = str(rollout.get("label", ""))
    if re.search(r"\bzero excitation\b", label):
        return 0.0
    found = re.search(r"excit\w*\s+(?:at\s+)?([0-9]*\.?[0-9]+)", label)
    _require(found is not None, where, f"no 'excitation' field and none in its label {label!r}")
    return float(found.group(1))


# --------------------------------------------------------------------------- muscle geometry and force


class _Paths:
    """Muscle-tendon lengths of the MuJoCo body at a pose, as the env computes them."""

    def __init__(self, m: mujoco.MjModel):
        osim = read_osim(body.OSIM_PATH)
        muscles = {mu.name: mu for mu in osim.muscles}
        ordered = [muscles[name] for name in body.MUSCLES]
        self.m, self.d = m, mujoco.MjData(m)
        self.switches, self.moving = PathSwitches(m, ordered), MovingPoints(m, osim, ordered)
        self.params = thelen.muscle_parameters(ordered)

    def lengths(self, pose: dict[str, float], tendons: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(lengths in action order, the tendons measured): those the pose selects, or `tendons`."""
        m, d = self.m, self.d
        body.reset_to_default(m, d)
        body.set_pose(m, d, pose)
        self.moving.place(m, d.qpos)
        mujoco.mj_kinematics(m, d)
        mujoco.mj_tendon(m, d)
        tendons = self.switches.tendons(d.qpos) if tendons is None else tendons
        return d.ten_length[tendons].copy(), tendons

    def pose(self) -> dict[str, float]:
        return {c: float(self.d.qpos[self.m.joint(c).qposadr[0]]) for c in body.COORDINATES}


def geometry_errors(m: mujoco.MjModel, samples: list[dict]) -> tuple[dict, dict, dict]:
    """RMS errors of moment arms {muscle: {coordinate: m}} and lengths {muscle: m}, and which
    coordinates each muscle spans {muscle: [coordinate]}."""
    paths = _Paths(m)
    length_err: dict[str, list] = {}
    arm_err: dict[str, dict[str, list]] = {}
    arm_size: dict[str, dict[str, float]] = {}
    for sample in samples:
        lengths, tendons = paths.lengths(sample["pose"])
        pose = paths.pose()  # the whole pose
        shifted = {}
        for c in sorted({c for e in sample["muscles"].values() for c in e["moment_arms"]}):
            up, _ = paths.lengths({**pose, c: pose[c] + MOMENT_ARM_STEP}, tendons)
            down, _ = paths.lengths({**pose, c: pose[c] - MOMENT_ARM_STEP}, tendons)
            shifted[c] = -(up - down) / (2 * MOMENT_ARM_STEP)
        for name, entry in sample["muscles"].items():
            i = body.MUSCLES.index(name)
            length_err.setdefault(name, []).append(lengths[i] - entry["mtu_length"])
            for c, arm in entry["moment_arms"].items():
                arm_err.setdefault(name, {}).setdefault(c, []).append(shifted[c][i] - arm)
                arm_size.setdefault(name, {})[c] = max(arm_size.get(name, {}).get(c, 0.0), abs(arm))
    spans = {name: [c for c, size in arms.items() if size > SPANS_THRESHOLD] for name, arms in arm_size.items()}
    return (
        {name: {c: _rms(e) for c, e in arms.items()} for name, arms in arm_err.items()},
        {name: _rms(e) for name, e in length_err.items()},
        spans,
    )


def _rms(errors: list[float]) -> float:
    return float(np.sqrt(np.mean(np.square(errors))))


def isometric_errors(m: mujoco.MjModel, samples: list[dict]) -> dict:
    """RMS isometric force error per muscle and activation, as a fraction of max force: the
    env's Thelen muscles in equilibrium at the MuJoCo lengths against OpenSim's forces."""
    paths = _Paths(m)
    errors: dict[str, dict[str, list]] = {}
    for sample in samples:
        lengths, _ = paths.lengths(sample["pose"])
        for name, by_act in sample["forces"].items():
            i = body.MUSCLES.index(name)
            p = paths.params[i]
            for act, ref_force in by_act.items():
                force = thelen.tendon_force(thelen.equilibrium_fiber_length(float(act), lengths[i], p), lengths[i], p)
                errors.setdefault(name, {}).setdefault(act, []).append((force - ref_force) / p[thelen.MAX_FORCE])
    return {name: {act: _rms(e) for act, e in acts.items()} for name, acts in errors.items()}


# --------------------------------------------------------------------------- ligaments and rollouts


def ligament_error(samples: list[dict]) -> float | None:
    """Largest ligament force error relative to OpenSim's force (at least 1 N·m), or None when
    the ligament module is missing."""
    try:
        from l2r.sim.ligaments import LIGAMENTS, default_limits, ligament_forces
    except ImportError:
        return None
    if not samples:
        return None
    coords = default_limits().coordinates
    worst = 0.0
    for i, s in enumerate(samples):
        try:
            q = np.array([s["q"][c] for c in coords], float)
            qdot = np.array([s["qdot"][c] for c in coords], float)
            ref = np.array([s["forces"][name] for name in LIGAMENTS], float)
        except KeyError as e:
            raise ReferenceError(f"ligaments[{i}]: missing {e}") from e
        ours = ligament_forces(q, qdot)
        worst = max(worst, float(np.max(np.abs(ours - ref) / np.maximum(np.abs(ref), 1.0))))
    return worst


def _fall_step(trajectory_y: list[float]) -> int | None:
    below = [k + 1 for k, y in enumerate(trajectory_y) if y < FALL_HEIGHT]
    return below[0] if below else None


def rollout_checks(rollouts: list[dict], max_steps: int = 1000) -> dict | None:
    """Reset observation error, fall step of the zero-excitation rollout and per-rollout RMS of
    the first 18 observations; None when the environment module is missing."""
    try:
        from l2r.sim.env import RunEnv
    except ImportError:
        return None
    out = {"reset_obs_max_abs_error": None, "fall_step": None, "reference_fall_step": None, "rollout_rms": {}, "rollout_steps": {}}
    for i, r in enumerate(rollouts):
        reference = np.array(r["trajectory_first18"], float)
        constant = "excitations" not in r
        # a constant zero excitation runs until the fall; every other rollout as long as the reference
        falls = constant and rollout_excitation(r, f"rollouts[{i}]") == 0.0
        excitations = rollout_excitations(r, max_steps if falls else len(reference), f"rollouts[{i}]")
        env = RunEnv(difficulty=0, seed=0)
        obs, _ = env.reset(seed=0)
        err = float(np.max(np.abs(np.asarray(obs, float) - np.array(r["reset_observation"], float))))
        out["reset_obs_max_abs_error"] = max(err, out["reset_obs_max_abs_error"] or 0.0)
        ours, heights = [], []
        for action in excitations:
            obs, _, terminated, truncated, _ = env.step(action)
            ours.append(np.asarray(obs[:18], float))
            heights.append(float(obs[2]))
            if terminated or truncated:
                break
        n = min(len(ours), len(reference))
        label = str(r.get("label", f"rollout {i}"))
        out["rollout_rms"][label] = float(np.sqrt(np.mean((np.array(ours[:n]) - reference[:n]) ** 2)))
        out["rollout_steps"][label] = n
        if falls and out["fall_step"] is None:
            out["fall_step"] = _fall_step(heights)
            out["reference_fall_step"] = r.get("first_step_pelvis_y_below_0_65")
    return out


# --------------------------------------------------------------------------- the report


def validate(reference: Path | str = DEFAULT_REFERENCE, model: mujoco.MjModel | None = None) -> dict:
    """Every figure of the validation, as the --json output holds it."""
    ref = load_reference(reference)
    m = body.load_model() if model is None else model
    arms, lengths, spans = geometry_errors(m, ref["geometry"])
    report = {
        "reference": str(reference),
        "moment_arm_rms_m": arms,
        "mtu_length_rms_m": lengths,
        "spanned_coordinates": spans,
        "isometric_force_rms_frac": isometric_errors(m, ref["isometric_forces"]),
        "ligament_max_rel_error": ligament_error(ref["ligaments"]),
    }
    rollouts = rollout_checks(ref["rollouts"]) if ref["rollouts"] else None
    report.update(rollouts or {"reset_obs_max_abs_error": None, "fall_step": None, "reference_fall_step": None, "rollout_rms": {}})
    report["summary"] = summarize(report)
    return report


def summarize(report: dict) -> dict:
    """Headline figures and whether each target of the issue holds (None: not computed)."""
    pairs = [report["moment_arm_rms_m"][m][c] for m, cs in report["spanned_coordinates"].items() for c in cs]
    iso = [v for acts in report["isometric_force_rms_frac"].values() for v in acts.values()]
    s = {
        "moment_arm_median_m": float(np.median(pairs)) if pairs else None,
        "moment_arm_worst_m": max(pairs) if pairs else None,
        "mtu_length_worst_m": max(report["mtu_length_rms_m"].values()) if report["mtu_length_rms_m"] else None,
        "isometric_force_mean_frac": float(np.mean(iso)) if iso else None,
        "ligament_max_rel_error": report["ligament_max_rel_error"],
        "reset_obs_max_abs_error": report["reset_obs_max_abs_error"],
        "fall_step_rel_error": None,
    }
    if report.get("fall_step") and report.get("reference_fall_step"):
        s["fall_step_rel_error"] = abs(report["fall_step"] - report["reference_fall_step"]) / report["reference_fall_step"]
    s["targets_met"] = {k: (None if s[k] is None else bool(s[k] <= limit)) for k, limit in TARGETS.items()}
    return s


def format_table(report: dict) -> str:
    """The per-muscle table and the headline figures, for people."""

    def mm(v: float) -> str:
        return f"{v * 1000:6.2f}"

    lines = [f"reference: {report['reference']}", "",
             f"{'muscle':<14} {'length':>7}  {'moment arm RMS (mm) per spanned joint':<44} {'force RMS (% max) a=0/0.5/1':>28}"]
    for name in body.MUSCLES:
        if name not in report["mtu_length_rms_m"]:
            continue
        arms = "  ".join(f"{c} {mm(report['moment_arm_rms_m'][name][c])}" for c in report["spanned_coordinates"].get(name, []))
        forces = report["isometric_force_rms_frac"].get(name, {})
        force_text = " / ".join(f"{100 * forces[a]:4.1f}" for a in ACTIVATIONS if a in forces)
        lines.append(f"{name:<14} {mm(report['mtu_length_rms_m'][name])}  {arms:<44} {force_text:>28}")
    s = report["summary"]
    fmt = {
        "moment_arm_median_m": lambda v: f"{v * 1000:.2f} mm", "moment_arm_worst_m": lambda v: f"{v * 1000:.2f} mm",
        "mtu_length_worst_m": lambda v: f"{v * 1000:.2f} mm", "isometric_force_mean_frac": lambda v: f"{100 * v:.1f} % of Fmax",
        "ligament_max_rel_error": lambda v: f"{100 * v:.3g} %", "reset_obs_max_abs_error": lambda v: f"{v:.3g}",
        "fall_step_rel_error": lambda v: f"{100 * v:.0f} % (step {report['fall_step']} vs {report['reference_fall_step']})",
    }
    lines += ["", f"{'figure':<28} {'value':<28} {'target':<12} met"]
    for key, limit in TARGETS.items():
        value = s[key]
        shown = "not computed" if value is None else fmt[key](value)
        target = fmt[key](limit).split(" (")[0] if key != "fall_step_rel_error" else f"{100 * limit:.0f} %"
        met = {None: "-", True: "yes", False: "NO"}[s["targets_met"][key]]
        lines.append(f"{key:<28} {shown:<28} <= {target:<9} {met}")
    if report.get("rollout_rms"):
        lines += ["", "rollouts (RMS of the first 18 observations, no target):"]
        lines += [f"  {label}: {v:.4g} over {report['rollout_steps'][label]} steps" for label, v in report["rollout_rms"].items()]
    return "\n".join(lines)


def format_markdown(report: dict) -> str:
    """The per-muscle table as Markdown, for docs/model.md."""
    lines = ["| muscle | length RMS (mm) | moment arm RMS (mm) | isometric force RMS, % of max (a = 0 / 0.5 / 1) |",
             "|---|---:|---|---:|"]
    for name in body.MUSCLES:
        if name not in report["mtu_length_rms_m"]:
            continue
        arms = ", ".join(f"{c} {1000 * report['moment_arm_rms_m'][name][c]:.2f}" for c in report["spanned_coordinates"].get(name, []))
        forces = report["isometric_force_rms_frac"].get(name, {})
        force_text = " / ".join(f"{100 * forces[a]:.1f}" for a in ACTIVATIONS if a in forces)
        lines.append(f"| {name} | {1000 * report['mtu_length_rms_m'][name]:.2f} | {arms} | {force_text} |")
    return "\n".join(lines)


def cli(argv: list[str] | None = None) -> int:
    parser = CommandParser(prog="l2r validate", description=__doc__.split("\n\n")[0],
                           epilog="Exit status: 0 when the report was made (targets met or not), 1 when --dynamics "
                                  "cannot run (OpenSim not installed, an unreadable --policy checkpoint), 2 on bad "
                                  "usage or a bad reference file.")
    parser.add_argument("--reference", type=Path, default=DEFAULT_REFERENCE, help="OpenSim figures to compare with (default: the packaged ones)")
    output = parser.add_mutually_exclusive_group()
    output.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    output.add_argument("--markdown", action="store_true", help="print the per-muscle table as Markdown")
    parser.add_argument("--dynamics", action="store_true",
                        help="instead, drive the MuJoCo body and live OpenSim (pip install 'l2r[opensim]') with the same "
                             "excitations and compare joint angles, pelvis, activations, tendon forces and ground reactions")
    parser.add_argument("--policy", type=Path, metavar="CHECKPOINT",
                        help="with --dynamics, also replay a trained policy's actions (a checkpoint or `l2r up` run directory)")
    parser.add_argument("--seed", type=int, default=0, help="with --dynamics, the seed of the random excitations")
    parser.add_argument("--env-id", default=PORT_ID, choices=(PORT_ID, WARP_ID),
                        help=f"with --dynamics, the backend compared with OpenSim: {PORT_ID} (MuJoCo with numba kernels, "
                             f"the default) or {WARP_ID} (MuJoCo Warp in float32, one world on Warp's default device)")
    args = parser.parse_args(argv)
    if args.policy and not args.dynamics:
        parser.error("--policy needs --dynamics")
    if args.dynamics:
        return _dynamics(args)
    try:
        report = validate(args.reference)
    except ReferenceError as e:
        print(f"l2r validate: bad reference file: {e}", file=sys.stderr)
        return EXIT_USAGE
    print(json.dumps(report) if args.json else format_markdown(report) if args.markdown else format_table(report))
    return 0


def _dynamics(args: argparse.Namespace) -> int:
    from l2r.sim import dynamics

    policy = None
    if args.policy:
        from l2r.learner.checkpoint import CheckpointError, load_checkpoint

        try:
            checkpoint = load_checkpoint(args.policy)
        except CheckpointError as e:
            print(f"l2r validate: {e}", file=sys.stderr)
            return EXIT_FAILURE
        deterministic = checkpoint.policy()
        policy = lambda obs: deterministic.act(obs[None], deterministic=True)[0]  # noqa: E731
    try:
        report = dynamics.check(dynamics.excitation_sequences(args.seed, policy=policy),
                                progress=lambda line: print(line, file=sys.stderr), env_id=args.env_id)
    except ImportError as e:
        print(f"l2r validate: {e}", file=sys.stderr)
        return EXIT_FAILURE
    print(json.dumps(report) if args.json else dynamics.format_table(report))
    return 0


if __name__ == "__main__":
    sys.exit(cli())
