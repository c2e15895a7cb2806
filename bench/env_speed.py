"""Single-core speed of `l2r/Run-v0` against raw MuJoCo and `l2r/RunOpenSim-v0`; prints one JSON line.

Rates are per second of this process's CPU time on one core (`time.thread_time`), so other work
on a shared machine does not distort them; `wall_*` gives the same figures by the wall clock.

env_steps_per_s_d0 / _d2: env steps (0.01 s each) per second with uniform random excitations,
    resets included (random excitations make the body fall within ~1-2 s).
mj_steps_per_s: raw `mujoco.mj_step` rate on the same model and controls, no Python in the loop.
physics_share_d0: the fraction of an env step spent inside MuJoCo (substeps / mj rate / env rate).
opensim_env_steps_per_s_d0: `l2r/RunOpenSim-v0` measured here, in this run, the same way.
speedup_vs_opensim: env_steps_per_s_d0 over that (the issue's 100x is against this figure).
speedup_vs_opensim_low / _high: env_steps_per_s_d0 over OpenSim's fastest / slowest rate for the
    same 0.01 s step, as recorded with the reference figures (about 110 and 40 steps/s).
same_work: the two reference rollouts OpenSim timed, run here, with their own speedups.
With --randomize: randomized_env_steps_per_s_d0 / _d2, the port with that per-episode
    randomisation, and randomization_cost_d0 / _d2, 1 - randomized / plain: medians of rounds
    that alternate the two envs, so that both see the same machine.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import gymnasium
import mujoco
import numpy as np

import l2r.sim  # noqa: F401  (registers the environments)
from l2r.sim.env import RunEnv
from l2r.sim.randomize import Randomization

REFERENCE = Path(__file__).resolve().parents[1] / "l2r" / "sim" / "assets" / "opensim_reference.json"


class Clock:
    """CPU and wall time since construction."""

    def __init__(self):
        self.cpu, self.wall = time.thread_time(), time.perf_counter()

    def elapsed(self) -> tuple[float, float]:
        return time.thread_time() - self.cpu, time.perf_counter() - self.wall


def env_rate(difficulty: int, seconds: float, seed: int = 0, env_id: str = "l2r/Run-v0", chunk: int = 1024,
             randomize: Randomization | None = None) -> tuple[float, float]:
    """(CPU, wall) env steps per second with random excitations, resets included; the clock is
    read every `chunk` steps."""
    options = {"randomize": randomize} if randomize else {}
    env = gymnasium.make(env_id, difficulty=difficulty, seed=seed, **options).unwrapped
    actions = np.random.default_rng(seed).uniform(0.0, 1.0, (4096, env.action_space.shape[0]))
    env.reset()
    for a in actions[:50]:  # warm-up
        if any(env.step(a)[2:4]):
            env.reset()
    steps, clock = 0, Clock()
    while clock.elapsed()[0] < seconds:
        start = steps % 3072
        for a in actions[start : start + chunk]:
            _, _, terminated, truncated, _ = env.step(a)
            if terminated or truncated:
                env.reset()
        steps += chunk
    cpu, wall = clock.elapsed()
    return steps / cpu, steps / wall


def mj_rate(seconds: float, seed: int = 0) -> tuple[float, float, int]:
    """(CPU, wall) raw mj_step rate on the env's model, 100 substeps per call, and the substeps
    per env step. Random controls, restarting from the default pose every 100 substeps."""
    env = RunEnv(difficulty=0, seed=seed)
    env.reset()
    m, d = env.model, env.data
    rng = np.random.default_rng(seed)
    steps, clock = 0, Clock()
    while clock.elapsed()[0] < seconds:
        mujoco.mj_resetDataKeyframe(m, d, m.keyframe("default").id)
        d.ctrl[:] = rng.uniform(0.0, 1.0, m.nu)
        mujoco.mj_step(m, d, 100)
        steps += 100
    cpu, wall = clock.elapsed()
    return steps / cpu, steps / wall, env.substeps


def same_work(repeats: int) -> dict[str, dict[str, float]]:
    """The reference rollouts OpenSim timed (constant excitation from the default pose), run
    here: steps per CPU second against OpenSim's recorded rate for the same rollout."""
    out = {}
    env = RunEnv()
    for rollout in json.loads(REFERENCE.read_text())["rollouts"]:
        excitation = 0.0 if rollout["label"].startswith("zero") else 0.5
        action = np.full(env.action_space.shape, excitation)
        steps, clock = 0, Clock()
        for _ in range(repeats):
            env.reset(seed=0)
            for _ in range(rollout["steps"]):
                steps += 1
                if any(env.step(action)[2:4]):
                    break
        rate = steps / clock.elapsed()[0]
        opensim = rollout["opensim_steps_per_second"]
        out[rollout["label"]] = {
            "steps_per_s": round(rate, 1),
            "opensim": round(opensim, 1),
            "speedup": round(rate / opensim, 1),
        }
    return out


def randomization_cost(randomize: Randomization, seconds: float, rounds: int = 3) -> dict[str, float]:
    """The port's CPU rate with `randomize` against the plain one's, in alternating rounds."""
    out = {}
    for difficulty in (0, 2):
        plain, randomized = [], []
        for _ in range(rounds):
            plain.append(env_rate(difficulty, seconds)[0])
            randomized.append(env_rate(difficulty, seconds, randomize=randomize)[0])
        plain_rate, randomized_rate = float(np.median(plain)), float(np.median(randomized))
        out[f"randomized_env_steps_per_s_d{difficulty}"] = round(randomized_rate, 1)
        out[f"plain_env_steps_per_s_d{difficulty}"] = round(plain_rate, 1)
        out[f"randomization_cost_d{difficulty}"] = round(1.0 - randomized_rate / plain_rate, 4)
    return out


def cpu_flags() -> str:
    """The vector extensions this CPU has, of those that decide numeric speed."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                have = set(line.split(":", 1)[1].split())
                return " ".join(f for f in ("sse4_2", "avx", "avx2", "fma", "avx512f", "avx512_bf16", "amx_bf16") if f in have)
    except OSError:
        pass
    return "unknown"


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--seconds", type=float, default=5.0, help="timing window per figure (default 5)")
    parser.add_argument("--quick", action="store_true", help="1 s per figure")
    parser.add_argument("--randomize", metavar="NAME=FRACTION,...",
                        help="also time the port with this per-episode randomisation (RunEnv(randomize=...), "
                             "e.g. strength=0.1,mass=0.1,delay=1) against the plain port, in three alternating rounds")
    args = parser.parse_args()
    try:
        randomize = Randomization.parse(args.randomize or "")
    except ValueError as e:
        parser.error(str(e))
    seconds = 1.0 if args.quick else args.seconds
    if hasattr(os, "sched_setaffinity"):  # one core, as the goal is stated
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

    mj, wall_mj, substeps = mj_rate(seconds)
    d0, wall_d0 = env_rate(0, seconds)
    d2, wall_d2 = env_rate(2, seconds)
    same = same_work(repeats=10 if args.quick else 50)
    opensim, wall_opensim = env_rate(0, max(seconds, 5.0), env_id="l2r/RunOpenSim-v0", chunk=10)
    randomized = randomization_cost(randomize, seconds) if randomize else {}
    slow = min(r["opensim"] for r in same.values())
    fast = max(r["opensim"] for r in same.values())
    print(
        json.dumps(
            {
                "env_steps_per_s_d0": round(d0, 1),
                "env_steps_per_s_d2": round(d2, 1),
                "mj_steps_per_s": round(mj, 1),
                "substeps_per_env_step": substeps,
                "physics_bound_env_steps_per_s": round(mj / substeps, 1),
                "physics_share_d0": round(d0 * substeps / mj, 3),
                "opensim_env_steps_per_s_d0": round(opensim, 1),
                "speedup_vs_opensim": round(d0 / opensim, 1),
                "opensim_steps_per_s": [round(slow, 1), round(fast, 1)],
                "speedup_vs_opensim_low": round(d0 / fast, 1),
                "speedup_vs_opensim_high": round(d0 / slow, 1),
                "same_work": same,
                **randomized,
                "wall_env_steps_per_s_d0": round(wall_d0, 1),
                "wall_env_steps_per_s_d2": round(wall_d2, 1),
                "wall_mj_steps_per_s": round(wall_mj, 1),
                "wall_opensim_env_steps_per_s_d0": round(wall_opensim, 1),
                "load_average_1min": round(os.getloadavg()[0], 2),
                "mujoco": mujoco.__version__,
                "machine": f"{cpu_model()}, {os.cpu_count()} CPUs",
                "cpu_flags": cpu_flags(),
                "seconds_per_figure": seconds,
            }
        )
    )


if __name__ == "__main__":
    main()
