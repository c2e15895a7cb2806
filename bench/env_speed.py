"""Single-core speed of `RunEnv` against raw MuJoCo and OpenSim; prints one JSON line.

env_steps_per_s_d0 / _d2: env steps (0.01 s each) per second with uniform random excitations,
    resets included (random excitations make the body fall within ~1-2 s).
mj_steps_per_s: raw `mujoco.mj_step` rate on the same model and controls, no Python in the loop.
physics_share_d0: the fraction of an env step spent inside MuJoCo (substeps / mj rate / env rate).
speedup_vs_opensim_low / _high: env_steps_per_s_d0 over OpenSim's fastest / slowest rate for the
    same 0.01 s step, as recorded with the reference figures (about 110 and 40 steps/s).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import mujoco
import numpy as np

from l2r.sim.env import RunEnv

REFERENCE = Path(__file__).resolve().parents[1] / "l2r" / "sim" / "assets" / "opensim_reference.json"


def env_rate(difficulty: int, seconds: float, seed: int = 0) -> float:
    env = RunEnv(difficulty=difficulty, seed=seed)
    actions = np.random.default_rng(seed).uniform(0.0, 1.0, (4096, env.action_space.shape[0]))
    env.reset()
    for a in actions[:50]:  # warm-up
        if any(env.step(a)[2:4]):
            env.reset()
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        for a in actions[steps % 3072 : steps % 3072 + 1024]:
            _, _, terminated, truncated, _ = env.step(a)
            if terminated or truncated:
                env.reset()
        steps += 1024
    return steps / (time.perf_counter() - start)


def mj_rate(seconds: float, seed: int = 0) -> tuple[float, int]:
    """Raw mj_step rate on the env's model (obstacles parked), 100 substeps per call."""
    env = RunEnv(difficulty=0, seed=seed)
    env.reset()
    m, d = env.model, env.data
    rng = np.random.default_rng(seed)
    steps, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        mujoco.mj_resetData(m, d)
        d.ctrl[:] = rng.uniform(0.0, 1.0, m.nu)
        mujoco.mj_step(m, d, 100)
        steps += 100
    return steps / (time.perf_counter() - start), env.substeps


def opensim_rates() -> tuple[float, float]:
    rollouts = json.loads(REFERENCE.read_text())["rollouts"]
    rates = [r["opensim_steps_per_second"] for r in rollouts]
    return min(rates), max(rates)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=5.0, help="timing window per figure (default 5)")
    parser.add_argument("--quick", action="store_true", help="1 s per figure")
    args = parser.parse_args()
    seconds = 1.0 if args.quick else args.seconds
    if hasattr(os, "sched_setaffinity"):  # one core, as the goal is stated
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

    mj, substeps = mj_rate(seconds)
    d0 = env_rate(0, seconds)
    d2 = env_rate(2, seconds)
    slow, fast = opensim_rates()
    print(
        json.dumps(
            {
                "env_steps_per_s_d0": round(d0, 1),
                "env_steps_per_s_d2": round(d2, 1),
                "mj_steps_per_s": round(mj, 1),
                "substeps_per_env_step": substeps,
                "physics_bound_env_steps_per_s": round(mj / substeps, 1),
                "physics_share_d0": round(d0 * substeps / mj, 3),
                "opensim_steps_per_s": [round(slow, 1), round(fast, 1)],
                "speedup_vs_opensim_low": round(d0 / fast, 1),
                "speedup_vs_opensim_high": round(d0 / slow, 1),
                "mujoco": mujoco.__version__,
                "machine": f"{platform.machine()} {platform.processor() or platform.node()}",
                "seconds_per_figure": seconds,
            }
        )
    )


if __name__ == "__main__":
    main()
