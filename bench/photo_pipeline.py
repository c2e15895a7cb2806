"""Queries per second of the photo-finishing pipeline (l2r.photo.pipeline) on one core; prints one
JSON line.

A query is one image through all seven filters with one setting of the nine parameters, what a
step of `l2r/PhotoTune-v0` or one evaluation of an optimiser costs. Rates are per second of this
process's CPU time (`time.thread_time`), so other work on a shared machine does not distort them.

queries_per_s_<side>px: one image a call, at 64 and 256 pixels a side (the observation and the
    working image).
batched_queries_per_s_<side>px: 64 images a call, each with its own parameters (a population of
    CMA-ES, or a batch of environments).
env_steps_per_s: `l2r/PhotoTune-v0` steps with random actions, resets included.
compare_env_steps_per_s: the same of `l2r/PhotoTuneCompare-v0`, whose episodes `l2r photo pretrain`
    plays (the statistics of both images and the pair compared).
compare_detail_env_steps_per_s: the same of `l2r/PhotoTuneCompareDetail-v0` (that and the working
    images' detail compared).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import gymnasium
import numpy as np

import l2r.photo  # noqa: F401  (registers the task)
from l2r.photo.pipeline import finish, params_from_actions

sys.path.insert(0, str(Path(__file__).resolve().parent))
from env_speed import cpu_model  # noqa: E402  (this folder's: the same machine record)

BATCH = 64


def query_rate(side: int, batch: int, seconds: float) -> float:
    """Queries per CPU second through the pipeline, `batch` images a call."""
    rng = np.random.default_rng(0)
    images = rng.random((batch, 3, side, side), dtype=np.float32)
    params = params_from_actions(rng.uniform(-1, 1, (16, batch, 9)))
    finish(images, params[0])  # warm-up
    calls, start = 0, time.thread_time()
    while time.thread_time() - start < seconds:
        finish(images, params[calls % 16])
        calls += 1
    return calls * batch / (time.thread_time() - start)


def env_rate(seconds: float, env_id: str = "l2r/PhotoTune-v0") -> float:
    env = gymnasium.make(env_id).unwrapped
    env.reset(seed=0)  # loads the photos, outside the timing
    steps, start = 0, time.thread_time()
    while time.thread_time() - start < seconds:
        if any(env.step(env.action_space.sample())[2:4]):
            env.reset()
        steps += 1
    return steps / (time.thread_time() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=3.0, help="timing window per figure (default 3)")
    parser.add_argument("--quick", action="store_true", help="0.5 s per figure")
    args = parser.parse_args()
    seconds = 0.5 if args.quick else args.seconds
    if hasattr(os, "sched_setaffinity"):  # one core
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    figures = {}
    for side in (64, 256):
        figures[f"queries_per_s_{side}px"] = round(query_rate(side, 1, seconds), 1)
        figures[f"batched_queries_per_s_{side}px"] = round(query_rate(side, BATCH, seconds), 1)
    figures["env_steps_per_s"] = round(env_rate(seconds), 1)
    figures["compare_env_steps_per_s"] = round(env_rate(seconds, "l2r/PhotoTuneCompare-v0"), 1)
    figures["compare_detail_env_steps_per_s"] = round(env_rate(seconds, "l2r/PhotoTuneCompareDetail-v0"), 1)
    figures.update({
        "batch": BATCH,
        "numpy": np.__version__,
        "load_average_1min": round(os.getloadavg()[0], 2),
        "machine": f"{cpu_model()}, {os.cpu_count()} CPUs",
        "seconds_per_figure": seconds,
    })
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
