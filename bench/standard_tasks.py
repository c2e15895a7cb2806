"""PPO and SAC through `l2r up` on gymnasium's MuJoCo tasks, for comparison with published curves.

    python bench/standard_tasks.py                          # Hopper-v5 and Walker2d-v5, PPO and SAC, 1M env steps each
    python bench/standard_tasks.py --tasks Hopper-v5 --algos ppo --env-steps 300000
    python bench/standard_tasks.py --quick                  # every job for 30 s: does it run at all

Each (task, algorithm) is one job, run one after the other on this host:
`l2r up --env-id TASK --algo ALGO --action-repeat 1 --env-steps N --evaluators 1`, each algorithm
with its `l2r up` defaults (docs/training.md). The job's metrics (metrics/episodes.csv and
evaluation.csv) give, at each milestone of env steps, the mean return of the training episodes
that ended in the last tenth before it and of the evaluation episodes (deterministic, seeds 0-4)
of the newest policy evaluated by then. Published figures to set them against are the
Stable-Baselines3 and CleanRL ones docs/training.md names; this script does not fetch them.

Prints one JSON line: per job its run directory, seconds, env steps, env steps per second, updates,
what the replay server's queue dropped (PPO), and the returns at each milestone.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from learning_curve import read_rows

ROOT = Path(__file__).resolve().parents[1]
MILESTONES = (100_000, 300_000, 1_000_000)


def run_job(task: str, algo: str, env_steps: int, seconds: float, runs_dir: Path) -> Path:
    name = f"{task.lower().replace('/', '-')}-{algo}"
    subprocess.run([sys.executable, "-m", "l2r.cli", "up", "--env-id", task, "--algo", algo, "--action-repeat", "1",
                    "--env-steps", str(env_steps), "--seconds", str(seconds), "--evaluators", "1",
                    "--eval-episodes", "5", "--eval-interval", "30", "--name", name, "--runs-dir", str(runs_dir),
                    "--status-interval", "30"], cwd=ROOT, check=True)
    return max(runs_dir.glob(f"{name}-*"))


def returns_at(rows: list[dict], steps: int, window: float) -> float | None:
    chosen = [r["return"] for r in rows if steps - window <= r["env_steps"] <= steps]
    return round(sum(chosen) / len(chosen), 1) if chosen else None


def summary(run_dir: Path, milestones: list[int]) -> dict:
    done = json.loads((run_dir / "summary.json").read_text())
    episodes = read_rows(run_dir / "metrics" / "episodes.csv")
    evaluations = read_rows(run_dir / "metrics" / "evaluation.csv")
    replay = (read_rows(run_dir / "metrics" / "replay.csv") or [{}])[-1]
    at = {}
    for steps in (m for m in milestones if m <= done["env_steps"]):  # milestones the job reached
        newest = [r for r in evaluations if r["env_steps"] <= steps]
        last = max((r["version"] for r in newest), default=None)
        evaluated = [r["return"] for r in newest if r["version"] == last]
        at[steps] = {"train_return": returns_at(episodes, steps, steps / 10),
                     "eval_return": round(sum(evaluated) / len(evaluated), 1) if evaluated else None}
    return {"run_dir": str(run_dir), "seconds": round(done["time"], 1), "env_steps": done["env_steps"],
            "env_steps_per_s": round(done["env_steps"] / max(done["time"], 1e-9), 1), "updates": done["updates"],
            "queue_dropped_stale": replay.get("queue.dropped_stale"), "queue_given": replay.get("queue.given"),
            "returns": at}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", default="Hopper-v5,Walker2d-v5", help="gymnasium ids, comma-separated")
    p.add_argument("--algos", default="ppo,sac", help="comma-separated")
    p.add_argument("--env-steps", type=int, default=MILESTONES[-1], help="env steps of each job")
    p.add_argument("--seconds", type=float, default=0, help="wall-clock limit of each job (0: none)")
    p.add_argument("--runs-dir", type=Path, help="where the jobs' run directories go (default: a temporary one)")
    p.add_argument("--quick", action="store_true", help="every job for 30 s only")
    args = p.parse_args()
    seconds = 30 if args.quick else args.seconds
    runs_dir = args.runs_dir or Path(tempfile.mkdtemp(prefix="standard-tasks-"))
    milestones = [m for m in MILESTONES if m < args.env_steps] + [args.env_steps]
    started, results = time.time(), {}
    for task in args.tasks.split(","):
        for algo in args.algos.split(","):
            results[f"{task} {algo}"] = summary(run_job(task, algo, args.env_steps, seconds, runs_dir), milestones)
    print(json.dumps({"bench": "standard_tasks", "host_cpus": os.cpu_count(),
                      "seconds": round(time.time() - started, 1), "jobs": results}))


if __name__ == "__main__":
    main()
