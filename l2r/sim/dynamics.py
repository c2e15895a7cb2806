"""The MuJoCo body against live OpenSim, driven by the same excitations from the same pose.

    l2r validate --dynamics [--policy CHECKPOINT] [--json]

Each rollout feeds one excitation sequence to `l2r/Run-v0` and `l2r/RunOpenSim-v0` (OpenSim
4.6, integrator accuracy 5e-5) and compares, per horizon (0.1, 0.2, 0.5 s):

- `joint_deg`: largest error of pelvis tilt and the six joint angles, degrees;
- `pelvis_cm`: largest error of pelvis x and y, cm;
- `activation`: largest activation error of any muscle (over the whole rollout);
- `tendon_force_mean` / `_worst`: each muscle's RMS tendon force error over the horizon as a
  fraction of its max isometric force, mean over muscles and worst muscle;
- `grf_bw`: RMS error of each foot's vertical ground reaction (heel and toe spheres) over the
  horizon, in body weights, the worse foot;

and, for the zero-excitation rollout, the step at which the pelvis drops below 0.65 m in each.
Rollouts: zero excitation, all at 0.5, a new uniform draw every step (seeded), and, with
`--policy`, the actions a trained policy takes in the MuJoCo body, replayed open-loop in both.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import gymnasium
import numpy as np

import l2r.sim  # noqa: F401  (registers the environments)
from l2r.sim.env import FALL_HEIGHT, NUM_MUSCLES
from l2r.sim.model import MUSCLES, OSIM_PATH
from l2r.sim.opensim import read_osim

HORIZONS = (0.1, 0.2, 0.5)  # s
STEP_SECONDS = 0.01
ANGLES = [0, 6, 7, 8, 9, 10, 11]  # observation indices: pelvis tilt and the joint angles
FEET = ((0, 1), (2, 3))  # contact_force rows: (r_heel, r_toe), (l_heel, l_toe)
FALL_STEPS = 300  # the zero-excitation rollout runs until both have fallen, or this many steps
TARGETS = {  # (figure, horizon or None for the whole rollout): limit
    ("activation", None): 0.01,
    ("tendon_force_mean", 0.2): 0.05,
    ("tendon_force_worst", 0.2): 0.10,
    ("joint_deg", 0.2): 2.0,
    ("joint_deg", 0.5): 5.0,
    ("pelvis_cm", 0.2): 1.0,
    ("grf_bw", 0.2): 0.10,
}
FALL_STEP_TOLERANCE = 0.05


@dataclass
class Trajectory:
    """What one simulator did along a rollout, one row per step (row 0: the reset state)."""

    observation: np.ndarray  # (n, 41)
    activation: np.ndarray  # (n, 18)
    tendon_force: np.ndarray  # (n, 18), fractions of max isometric force
    foot_force: np.ndarray  # (n, 2), vertical ground reaction per foot, body weights
    fall_step: int | None


def rollout(env_id: str, excitations: np.ndarray, until_fall: bool = False) -> Trajectory:
    """Drive one simulator with these excitations (steps x 18) from its reset state."""
    env = gymnasium.make(env_id, difficulty=0).unwrapped
    try:
        obs, info = env.reset(seed=0)
        max_force, weight = _body_facts()
        rows = [(obs, info)]
        fall = None
        for k, u in enumerate(excitations):
            obs, _, terminated, truncated, info = env.step(u)
            rows.append((obs, info))
            if obs[2] < FALL_HEIGHT and fall is None:
                fall = k + 1
            if terminated or truncated:
                break
        return Trajectory(
            np.array([o for o, _ in rows], float),
            np.array([i["muscle_activation"] for _, i in rows], float),
            np.array([i["muscle_force"] for _, i in rows], float) / max_force,
            np.array([[i["contact_force"][list(f), 1].sum() for f in FEET] for _, i in rows], float) / weight,
            fall,
        )
    finally:
        env.close()


@functools.cache
def _body_facts() -> tuple[np.ndarray, float]:
    """Max isometric forces in action order (N) and body weight (N), from the .osim."""
    osim = read_osim(OSIM_PATH)
    forces = {m.name: m.max_force for m in osim.muscles}
    weight = sum(b.mass for b in osim.bodies.values()) * float(np.linalg.norm(osim.gravity))
    return np.array([forces[n] for n in MUSCLES]), weight


def compare(ours: Trajectory, theirs: Trajectory) -> dict:
    """The figures of one rollout (see the module text); horizons beyond either run are left out."""
    n = min(len(ours.observation), len(theirs.observation))
    out: dict = {"steps": n - 1, "activation": float(np.max(np.abs(ours.activation[:n] - theirs.activation[:n])))}
    for h in HORIZONS:
        k = round(h / STEP_SECONDS) + 1
        if k > n:
            continue
        angle = np.abs(ours.observation[:k, ANGLES] - theirs.observation[:k, ANGLES])
        pelvis = np.abs(ours.observation[:k, 1:3] - theirs.observation[:k, 1:3])
        force = np.sqrt(np.mean((ours.tendon_force[:k] - theirs.tendon_force[:k]) ** 2, axis=0))
        grf = np.sqrt(np.mean((ours.foot_force[:k] - theirs.foot_force[:k]) ** 2, axis=0))
        out[f"{h:g}s"] = {
            "joint_deg": math.degrees(float(angle.max())),
            "pelvis_cm": 100 * float(pelvis.max()),
            "tendon_force_mean": float(force.mean()),
            "tendon_force_worst": float(force.max()),
            "tendon_force_worst_muscle": MUSCLES[int(force.argmax())],
            "grf_bw": float(grf.max()),
        }
    out["fall_step"] = ours.fall_step
    out["opensim_fall_step"] = theirs.fall_step
    return out


def excitation_sequences(seed: int = 0, steps: int = round(max(HORIZONS) / STEP_SECONDS), policy=None) -> dict[str, np.ndarray]:
    """The rollouts' excitations by label: constant 0 (run to the fall), constant 0.5, a uniform
    draw every step, and, given a policy (observation -> action), its deterministic actions
    in the MuJoCo body."""
    sequences = {
        "zero excitation": np.zeros((FALL_STEPS, NUM_MUSCLES)),
        "all at 0.5": np.full((steps, NUM_MUSCLES), 0.5),
        f"random, seed {seed}": np.random.default_rng(seed).uniform(0.0, 1.0, (steps, NUM_MUSCLES)),
    }
    if policy is not None:
        sequences["policy"] = record_policy(policy, steps)
    return sequences


def record_policy(policy, steps: int) -> np.ndarray:
    """A policy's deterministic actions in the MuJoCo body, step by step until it ends."""
    env = gymnasium.make("l2r/Run-v0", difficulty=0).unwrapped
    obs, _ = env.reset(seed=0)
    actions = []
    for _ in range(steps):
        a = np.clip(np.asarray(policy(obs), float), 0.0, 1.0)
        actions.append(a)
        obs, _, terminated, truncated, _ = env.step(a)
        if terminated or truncated:
            break
    return np.array(actions)


def check(sequences: dict[str, np.ndarray], progress=None, env_id: str = "l2r/Run-v0") -> dict:
    """Every rollout's figures for the MuJoCo backend `env_id`, and whether each target holds in
    every rollout."""
    rollouts = {}
    for label, excitations in sequences.items():
        if progress:
            progress(f"rollout '{label}': {len(excitations)} steps in {env_id} and OpenSim")
        rollouts[label] = compare(rollout(env_id, excitations), rollout("l2r/RunOpenSim-v0", excitations))
    return {"rollouts": rollouts, "targets_met": targets_met(rollouts)}


def targets_met(rollouts: dict) -> dict:
    """{figure@horizon: met in every rollout that reaches the horizon} and the fall step."""
    met = {}
    for (figure, horizon), limit in TARGETS.items():
        values = [r[figure] if horizon is None else r[f"{horizon:g}s"][figure]
                  for r in rollouts.values() if horizon is None or f"{horizon:g}s" in r]
        met[figure if horizon is None else f"{figure}@{horizon:g}s"] = bool(values) and max(values) <= limit
    falls = [(r["fall_step"], r["opensim_fall_step"]) for r in rollouts.values() if r["opensim_fall_step"]]
    met["fall_step"] = bool(falls) and all(ours is not None and abs(ours - theirs) <= FALL_STEP_TOLERANCE * theirs for ours, theirs in falls)
    return met


def format_table(report: dict) -> str:
    lines = [f"{'rollout':<18} {'horizon':>7} {'joint deg':>9} {'pelvis cm':>9} {'F mean':>7} {'F worst':>7} {'GRF bw':>7}"]
    for label, r in report["rollouts"].items():
        for h in HORIZONS:
            f = r.get(f"{h:g}s")
            if f:
                lines.append(f"{label[:18]:<18} {h:>6g}s {f['joint_deg']:9.2f} {f['pelvis_cm']:9.2f} "
                             f"{f['tendon_force_mean']:7.3f} {f['tendon_force_worst']:7.3f} {f['grf_bw']:7.3f}")
        lines.append(f"{'':<18} activation max error {r['activation']:.4f}; fall step {r['fall_step']} "
                     f"(OpenSim {r['opensim_fall_step']}) over {r['steps']} steps")
    lines += ["", "targets: " + ", ".join(f"{k} {'yes' if v else 'NO'}" for k, v in report["targets_met"].items())]
    return "\n".join(lines)
