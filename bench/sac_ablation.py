"""What each difference between the runner's SAC recipe and the standard one costs on a MuJoCo task.

    python bench/sac_ablation.py                                  # Hopper-v5, 50k env steps, every variant, seed 0
    python bench/sac_ablation.py --variants standard,runner --seeds 0,1,2 --results ab.jsonl
    python bench/sac_ablation.py --task Walker2d-v5 --env-steps 100000

Each variant is one `l2r up` job through the daemons at one gradient step per env step (the
replay's samples-per-insert limit held both ways, as Stable-Baselines3 trains): `standard` is the
recipe SB3 and CleanRL use (2 x 256 ReLU, no LayerNorm, reward scale 1, temperature learnt from 1.0,
raw observations, learning from 5,000 steps on, actors acting with the weights of every update);
every other variant changes one of those values to the runner's, and `runner` changes them all.
Every value is given as an explicit flag, so the variants mean the same whatever `l2r up` picks by
default. The runs go one after the other on this host; `--results FILE` appends each job's JSON
line as it finishes, so a long sweep keeps what it measured.

Prints one JSON line: per variant and seed the run directory, time, env steps, updates and the
training and evaluation returns at each milestone (bench/standard_tasks.py's summary).
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from pathlib import Path

from env_speed import cpu_flags, cpu_model
from standard_tasks import run_job, sb3_job, summary

# The standard recipe as l2r up flags and learner settings; each variant replaces some of them.
STANDARD = {"batch-size": 256, "hidden": "256,256", "update-repeat": 1, "samples-per-insert": 256,
            "envs-per-actor": 1, "random-steps": 5000, "min-replay": 5000, "normalize-obs": False}
STANDARD_LEARNER = {"reward-scale": 1, "initial-alpha": 1.0, "activation": "relu", "layer-norm": False,
                    "publish-every": 1}
# One difference from the runner's recipe each (docs/training.md, "The recipe").
VARIANTS = {
    "standard": ({}, {}),
    "reward_scale_10": ({}, {"reward-scale": 10}),
    "initial_alpha_0.1": ({}, {"initial-alpha": 0.1}),
    "elu_layernorm": ({}, {"activation": "elu", "layer-norm": True}),
    "normalize_obs": ({"normalize-obs": True}, {}),
    "warmup_10k": ({"random-steps": 10_000, "min-replay": 10_000}, {}),
    "publish_every_50": ({}, {"publish-every": 50}),
}
VARIANTS["runner"] = tuple({k: v for changes in VARIANTS.values() for k, v in changes[i].items()} for i in (0, 1))


def flags(up: dict, learner: dict, seed: int) -> list[str]:
    """The l2r up command line of one variant."""
    args = ["--replay-arg=--hold-actors", "--seed", str(seed), f"--learner-arg=--seed={seed}"]
    for name, value in up.items():
        args += [f"--{name}" if value else f"--no-{name}"] if isinstance(value, bool) else [f"--{name}", str(value)]
    for name, value in learner.items():
        if isinstance(value, bool):
            args.append(f"--learner-arg=--{name}" if value else f"--learner-arg=--no-{name}")
        else:
            args.append(f"--learner-arg=--{name}={value}")
    return args


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--task", default="Hopper-v5", help="gymnasium id")
    p.add_argument("--env-steps", type=int, default=50_000, help="env steps of each job")
    p.add_argument("--variants", default=",".join(VARIANTS),
                   help=f"comma-separated, of {', '.join(VARIANTS)} (empty: none, e.g. with --sb3 alone)")
    p.add_argument("--seeds", default="0", help="comma-separated seeds; each variant runs once per seed")
    p.add_argument("--runs-dir", type=Path, help="where the jobs' run directories go (default: a temporary one)")
    p.add_argument("--results", type=Path, help="append each job's JSON line here as it finishes")
    p.add_argument("--sb3", action="store_true",
                   help="also train Stable-Baselines3's SAC (its defaults) for the same env steps, once per seed")
    args = p.parse_args()
    variants = [name for name in args.variants.split(",") if name]
    unknown = set(variants) - set(VARIANTS)
    if unknown:
        p.error(f"unknown variants {sorted(unknown)}; known: {', '.join(VARIANTS)}")
    runs_dir = args.runs_dir or Path(tempfile.mkdtemp(prefix="sac-ablation-"))
    milestones = [m for m in (25_000, 50_000, 100_000) if m < args.env_steps] + [args.env_steps]
    started, jobs = time.time(), {}
    for seed in map(int, args.seeds.split(",")):
        for name in variants + (["sb3"] if args.sb3 else []):
            if name == "sb3":
                job = {"variant": name, **sb3_job(args.task, "sac", milestones, seed)}
            else:
                up, learner = VARIANTS[name]
                argv = flags(STANDARD | up, STANDARD_LEARNER | learner, seed)
                run_dir = run_job(args.task, "sac", args.env_steps, 0, runs_dir, argv)
                job = {"variant": name, "seed": seed, "flags": argv, **summary(run_dir, milestones)}
            jobs[f"{name} seed {seed}"] = job
            if args.results:
                with args.results.open("a") as f:
                    f.write(json.dumps(job) + "\n")
    print(json.dumps({"bench": "sac_ablation", "task": args.task, "cpu": cpu_model(), "cpu_flags": cpu_flags(), "host_cpus": os.cpu_count(),
                      "seconds": round(time.time() - started, 1), "jobs": jobs}))


if __name__ == "__main__":
    main()
