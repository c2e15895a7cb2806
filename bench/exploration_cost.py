"""What each way of exploring costs an actor per policy call: the plain Gaussian draws, a coloured
noise series (`--exploration-noise pink`) and perturbed weights (`--parameter-noise`).

The actor's own call (`l2r.policy.act_with_log_prob`) on the runner's policy (41 observations,
18 excitations, the recipe's 256 × 256 ELU + LayerNorm, relative x and standardised inputs) for
``--num-envs`` worlds, one torch thread as an actor has; the three in interleaved rounds, so a
busy machine slows them alike; CPU time of this thread per call (the median round), which
survives a shared machine.

Prints one JSON line: ``plain_us_per_call``, ``pink_us_per_call``, ``parameter_noise_us_per_call``,
each over the plain one as ``*_ratio``, the settings and the machine.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from l2r.actors.noise import ColouredNoise
from l2r.actors.parameter_noise import ParameterNoise
from l2r.policy import act_with_log_prob, build_policy, default_spec

sys.path.insert(0, str(Path(__file__).parent))
from env_speed import cpu_flags, cpu_model  # noqa: E402  (this folder's: the same machine record)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--num-envs", type=int, default=4, help="worlds one call acts for (the recipe's actor: 4)")
    p.add_argument("--hidden", default="256,256")
    p.add_argument("--calls", type=int, default=2000, help="calls per round")
    p.add_argument("--rounds", type=int, default=5)
    args = p.parse_args()
    torch.set_num_threads(1)
    spec = default_spec(41, 18) | {"hidden": [int(h) for h in args.hidden.split(",")], "layer_norm": True,
                                   "relative_x": True, "normalize_obs": True}
    policy = build_policy(spec)
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(args.num_envs, 41)).astype(np.float32)
    pink = ColouredNoise("pink", args.num_envs, 18, 334, rng)
    perturbed = ParameterNoise(0.2, args.num_envs, seed=0)
    ways = {
        "plain": lambda: act_with_log_prob(policy, obs),
        "pink": lambda: act_with_log_prob(policy, obs, pink.next()),
        "parameter_noise": lambda: act_with_log_prob(policy, obs, None,
                                                     functools.partial(perturbed.explore, policy)),
    }
    rounds: dict[str, list[float]] = {name: [] for name in ways}
    for name, call in ways.items():  # warm-up
        for _ in range(50):
            call()
    for _ in range(args.rounds):
        for name, call in ways.items():
            start = time.thread_time()
            for _ in range(args.calls):
                call()
            rounds[name].append((time.thread_time() - start) / args.calls * 1e6)
    us = {name: statistics.median(values) for name, values in rounds.items()}
    print(json.dumps({
        "bench": "exploration_cost", **{f"{name}_us_per_call": round(v, 1) for name, v in us.items()},
        **{f"{name}_ratio": round(v / us["plain"], 2) for name, v in us.items() if name != "plain"},
        "num_envs": args.num_envs, "hidden": args.hidden, "torch_threads": 1, "rounds": args.rounds,
        "load_1min": round(os.getloadavg()[0], 2), "cpu": cpu_model(), "cpu_flags": cpu_flags(),
    }))


if __name__ == "__main__":
    main()
