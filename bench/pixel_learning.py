"""DrQ-v2 (or DrQ) through `l2r up` on a camera task, on this host, beside DrQ-v2's published curve at the same frames.

    python bench/pixel_learning.py                                    # cartpole-swingup, 48 x 48 frames, one hour
    python bench/pixel_learning.py --task cartpole-balance            # the same on cartpole-balance
    python bench/pixel_learning.py --task cartpole-balance --algo sac # DrQ: SAC's pixels recipe
    python bench/pixel_learning.py --task cheetah-run --image-size 84 --batch-size 256 --seconds 470 \
        --up-arg=--device=cuda --up-arg=--actors=5 --up-arg=--replay-shards=3   # DrQ-v2's own sizes, a GPU box
    python bench/pixel_learning.py --run-dir RUN --plot docs/pixel_curve.png         # a run already made

The job is `l2r up --env-id l2r/dmc-<task>-v0 --algo td3` (the pixels recipe, DrQ-v2's
values; `--algo sac`, DrQ's) with `--image-size`, `--batch-size` and `--samples-per-insert` half
the batch, so that the learner makes one update per 2 env steps whatever the batch, as DrQ-v2
does (DrQ makes one per env step). On a CPU DrQ-v2's update at 84 x 84 and batch 256 makes
about 0.9 updates/s on 2 threads (bench/pixel_update.py), a tenth of what an hour's learning
needs; 48 x 48 frames and batches of 128 make about 4 on one thread. Evaluation: 5 deterministic episodes (seeds 0-4) of each new policy at most every
`--eval-interval` seconds.

Frames are the suite's steps, as DrQ-v2 counts them: 2 per env step (the task holds each action
for 2). At each milestone the newest evaluation round by then is set against DrQ-v2's 10 seeds
at that frame (bench/drqv2_curves.csv, read off their repository's curves/dmc_<task>.csv: median,
mean and range of the evaluation return every 20,000 frames; 84 x 84 frames, batch 256, on a GPU).

Prints one JSON line: the run, frames and updates reached and their rates, the evaluation
returns at each milestone beside the published ones, the machine (CPU model and flags, load
average over the run's last minute as the kernel reports it at the end).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

from env_speed import cpu_flags, cpu_model
from learning_curve import read_rows, rolling

ROOT = Path(__file__).resolve().parents[1]
FRAMES_PER_STEP = 2  # the camera tasks' action repeat (l2r.control.env.ACTION_REPEAT), DrQ-v2's
# DrQ-v2's evaluation return over its 10 seeds at every 20,000 frames (from its repository's
# curves/dmc_<task>.csv): task -> frames -> (median, mean, lowest, highest).
CURVES_CSV = Path(__file__).with_name("drqv2_curves.csv")


def published_curves() -> dict[str, dict[int, tuple[float, float, float, float]]]:
    curves: dict[str, dict[int, tuple[float, float, float, float]]] = {}
    for row in read_rows(CURVES_CSV):
        curves.setdefault(row["task"], {})[int(row["frames"])] = (
            row["median"], row["mean"], row["lowest"], row["highest"])
    return curves


DRQV2 = published_curves()


def run_job(args: argparse.Namespace) -> Path:
    name = f"{args.task}-{args.algo}-{args.image_size}px"
    subprocess.run([sys.executable, "-m", "l2r.cli", "up", "--env-id", f"l2r/dmc-{args.task}-v0", "--algo", args.algo,
                    "--image-size", str(args.image_size), "--batch-size", str(args.batch_size),
                    "--samples-per-insert", str(args.batch_size / 2), "--seconds", str(args.seconds),
                    "--eval-episodes", "5", "--eval-interval", str(args.eval_interval), "--seed", str(args.seed),
                    "--name", name, "--runs-dir", str(args.runs_dir), "--status-interval", "30", *args.up_arg],
                   cwd=ROOT, check=True)
    return max(args.runs_dir.glob(f"{name}-*"))


def evaluation_rounds(run_dir: Path) -> list[tuple[int, float]]:
    """(frames when the round began, mean return) of each evaluation round, by policy version."""
    rounds: dict[int, list[dict]] = {}
    for row in read_rows(run_dir / "metrics" / "evaluation.csv"):
        rounds.setdefault(int(row["version"]), []).append(row)
    return sorted((int(min(r["env_steps"] for r in rows)) * FRAMES_PER_STEP,
                   statistics.fmean(r["return"] for r in rows)) for rows in rounds.values())


def task_of(launch: dict) -> str:
    """The suite task of a run's camera id, `cartpole-swingup` of `l2r/dmc-cartpole-swingup-v0`."""
    return launch["env_id"].removeprefix("l2r/dmc-").removesuffix("-v0")


def summary(run_dir: Path) -> dict:
    done = json.loads((run_dir / "summary.json").read_text())
    launch = json.loads((run_dir / "launch.json").read_text())["args"]
    rounds = evaluation_rounds(run_dir)
    frames = done["env_steps"] * FRAMES_PER_STEP
    at = {}
    for milestone, (median, mean, lowest, highest) in DRQV2[task_of(launch)].items():
        reached = [ret for f, ret in rounds if f <= milestone]
        if milestone <= frames and reached:
            at[milestone] = {"l2r_eval": round(reached[-1], 1), "drqv2_median": median, "drqv2_mean": mean,
                             "drqv2_range": [lowest, highest]}
    seconds = max(done["time"], 1e-9)
    return {"bench": "pixel_learning", "run_dir": str(run_dir), "env_id": launch["env_id"], "algo": launch["algo"],
            "image_size": launch.get("image_size"), "batch_size": launch.get("batch_size"),
            "seconds": round(done["time"], 1), "frames": frames, "frames_per_s": round(frames / seconds, 1),
            "updates": done["updates"], "updates_per_s": round(done["updates"] / seconds, 2),
            "best_eval_return": round(max(ret for _, ret in rounds), 1) if rounds else None,
            "last_eval_return": round(rounds[-1][1], 1) if rounds else None, "at_frames": at,
            "cpu_model": cpu_model(), "cpu_flags": cpu_flags(), "cpus": os.cpu_count(),
            "load_average_1min_at_end": round(os.getloadavg()[0], 2)}


def plot(run_dir: Path, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    launch = json.loads((run_dir / "launch.json").read_text())["args"]
    frames = np.array(list(DRQV2[task_of(launch)]))
    published = np.array(list(DRQV2[task_of(launch)].values()))
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.fill_between(frames, published[:, 2], published[:, 3], color="0.85", label="DrQ-v2, 10 seeds: range")
    ax.plot(frames, published[:, 0], color="0.4", label="DrQ-v2: median (84 x 84, batch 256, GPU)")
    episodes = read_rows(run_dir / "metrics" / "episodes.csv")
    if len(episodes) >= 5:
        steps = np.array([r["env_steps"] for r in episodes]) * FRAMES_PER_STEP
        ax.plot(steps[4:], rolling(np.array([r["return"] for r in episodes]), 5), color="tab:blue", alpha=0.5,
                label="l2r: training episodes (mean of 5)")
    rounds = np.array(evaluation_rounds(run_dir))
    if len(rounds):
        ax.plot(rounds[:, 0], rounds[:, 1], "o-", color="tab:blue", label="l2r: evaluation (5 episodes)")
    ax.set_title(f"{task_of(launch)} from pixels: l2r {launch['algo'].upper()} {launch.get('image_size') or 84} x "
                 f"{launch.get('image_size') or 84}, batch {launch.get('batch_size')}")
    ax.set_xlabel("frames (suite steps)")
    ax.set_ylabel("episode return")
    ax.set_xlim(0, max(rounds[-1, 0] if len(rounds) else 0, 20_000) * 1.05)
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=110)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--run-dir", type=Path, help="summarise this run instead of running one")
    p.add_argument("--task", choices=tuple(DRQV2), default="cartpole-swingup", help="the suite task (default: %(default)s)")
    p.add_argument("--algo", choices=("td3", "sac"), default="td3",
                   help="td3: DrQ-v2's recipe (pixels/td3); sac: DrQ's (pixels/sac) (default: %(default)s)")
    p.add_argument("--image-size", type=int, default=48, help="frames' side in pixels (default: %(default)s)")
    p.add_argument("--batch-size", type=int, default=128, help="transitions per update (default: %(default)s)")
    p.add_argument("--seconds", type=float, default=3600, help="the job's time budget (default: %(default)s)")
    p.add_argument("--eval-interval", type=float, default=120, help="least seconds between evaluation rounds "
                   "(default: %(default)s; each round renders 5 episodes of 500 env steps)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--runs-dir", type=Path, default=ROOT / "runs")
    p.add_argument("--up-arg", action="append", default=[], help="another flag for l2r up (--up-arg=--learner-threads=2)")
    p.add_argument("--plot", type=Path, help="also draw the run's curve beside DrQ-v2's into this PNG")
    args = p.parse_args()
    run_dir = args.run_dir or run_job(args)
    if args.plot:
        plot(run_dir, args.plot)
    print(json.dumps(summary(run_dir)))


if __name__ == "__main__":
    main()
