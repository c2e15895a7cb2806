"""PPO, SAC and TD3 through `l2r up` on gymnasium's MuJoCo tasks, against published curves and SB3.

    python bench/standard_tasks.py                          # Hopper-v5 and Walker2d-v5, PPO and SAC, 1M env steps each
    python bench/standard_tasks.py --tasks Hopper-v5 --algos ppo --env-steps 300000
    python bench/standard_tasks.py --quick                  # every job for 30 s: does it run at all
    python bench/standard_tasks.py --algos sac --env-steps 100000 --sb3
    python bench/standard_tasks.py --tasks Hopper-v5,Walker2d-v5,HalfCheetah-v5 --algos sac,td3 --env-steps 100000 --sb3
    python bench/standard_tasks.py --algos sac --env-steps 100000 --up-arg=--recipe=runner   # the runner's recipe
    python bench/standard_tasks.py --plot docs/standard_tasks.png --results out.jsonl RUN_DIR ...   # curves only

Each (task, algorithm) is one job, run one after the other on this host:
`l2r up --env-id TASK --algo ALGO --action-repeat 1 --env-steps N --evaluators 1`, each algorithm
with its standard recipe (docs/training.md, "Recipes"). The job's metrics (metrics/episodes.csv and
evaluation.csv) give, at each milestone of env steps, the mean return of the training episodes
that ended in the last tenth before it and of the evaluation episodes (deterministic, seeds 0-4)
of the newest policy evaluated by then. Published figures to set them against are the
Stable-Baselines3 and CleanRL ones docs/training.md names; this script does not fetch them.

`--up-arg` hands a flag to every `l2r up` (`--up-arg=--recipe=runner`: the runner's recipe
instead of the standard one; `--up-arg=--reward-scale=5`: one value of the recipe replaced).
`--sb3` also trains Stable-Baselines3 (the dev extra; TRPO from sb3-contrib, REINFORCE and ACKTR
have none there) with its defaults for the same env steps in
this process (TD3 given Gaussian exploration noise of 0.1, without which SB3's TD3 does not explore), one thread per core, evaluating 5 deterministic episodes at each milestone: the
baseline in the same run, on the same machine.

With `--plot`, draws the given run directories instead: return against env steps, one panel per
task (training episodes as a rolling mean, evaluations as points), with the published figures
below and the Stable-Baselines3 points of `--results` (this script's JSON lines) as markers.

Prints one JSON line: per job its run directory, seconds, env steps, env steps per second, updates,
what the replay server's queue dropped (PPO), and the returns at each milestone.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from learning_curve import read_rows, rolling

ROOT = Path(__file__).resolve().parents[1]
MILESTONES = (100_000, 300_000, 1_000_000)
# Published returns at 1M env steps, mean +- std over seeds of the training episodes' return (CleanRL's
# benchmark pages: ppo_continuous_action on the v4 tasks, sac_continuous_action on the v2 tasks).
PUBLISHED = {("Hopper", "ppo"): (2382.86, 271.74), ("Walker2d", "ppo"): (2287.95, 571.78),
             ("Hopper", "sac"): (2310.46, 342.82), ("Walker2d", "sac"): (3591.45, 911.33)}
COLOURS = {"ppo": "tab:blue", "sac": "tab:green", "td3": "tab:purple", "a2c": "tab:orange", "reinforce": "tab:brown",
           "trpo": "tab:red", "acktr": "tab:olive", "a3c": "tab:pink"}
# The package whose class of the algorithm's name (upper case) is its --sb3 baseline.
BASELINE_PACKAGES = {"ppo": "stable_baselines3", "sac": "stable_baselines3", "td3": "stable_baselines3",
                     "a2c": "stable_baselines3", "trpo": "sb3_contrib"}


def run_job(task: str, algo: str, env_steps: int, seconds: float, runs_dir: Path, up_args: list[str]) -> Path:
    name = f"{task.lower().replace('/', '-')}-{algo}"
    subprocess.run([sys.executable, "-m", "l2r.cli", "up", "--env-id", task, "--algo", algo, "--action-repeat", "1",
                    "--env-steps", str(env_steps), "--seconds", str(seconds), "--evaluators", "1",
                    "--eval-episodes", "5", "--eval-interval", "30", "--name", name, "--runs-dir", str(runs_dir),
                    "--status-interval", "30", *up_args], cwd=ROOT, check=True)
    return max(runs_dir.glob(f"{name}-*"))


def sb3_job(task: str, algo: str, milestones: list[int], seed: int = 0) -> dict:
    """Stable-Baselines3's own algorithm, its defaults, for the same env steps, evaluated at each milestone."""
    import gymnasium as gym
    import numpy as np
    import torch
    from stable_baselines3.common.callbacks import BaseCallback
    from stable_baselines3.common.evaluation import evaluate_policy
    from stable_baselines3.common.noise import NormalActionNoise

    torch.set_num_threads(os.cpu_count() or 1)
    env = gym.make(task)
    # SB3's TD3 explores with no noise unless given some; N(0, 0.1) is the TD3 paper's and RL Zoo's choice.
    noise = {"action_noise": NormalActionNoise(np.zeros(env.action_space.shape), np.full(env.action_space.shape, 0.1))
             } if algo == "td3" else {}
    package = importlib.import_module(BASELINE_PACKAGES[algo])
    model = getattr(package, algo.upper())("MlpPolicy", env, seed=seed, device="cpu", **noise)
    eval_env, returns = gym.make(task), {}

    class AtMilestones(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps in milestones:
                mean, _ = evaluate_policy(self.model, eval_env, n_eval_episodes=5, deterministic=True)
                returns[self.num_timesteps] = {"eval_return": round(float(mean), 1)}
            return True

    started = time.time()
    model.learn(total_timesteps=milestones[-1], callback=AtMilestones())
    seconds = time.time() - started
    return {"library": f"{package.__name__.replace('_', '-')} {package.__version__}", "seed": seed,
            "seconds": round(seconds, 1), "env_steps": milestones[-1],
            "env_steps_per_s": round(milestones[-1] / seconds, 1), "returns": returns}


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
            "updates_per_s": round(done["updates"] / max(done["time"], 1e-9), 1),
            "queue_dropped_stale": replay.get("queue.dropped_stale"), "queue_given": replay.get("queue.given"),
            **traffic(run_dir), "returns": at}


def traffic(run_dir: Path) -> dict:
    """What the actors sent per update: A3C's gradients (their bytes as sent), else the experience of the
    same env steps (a chunk of the task's widths encoded as the actors encode it)."""
    import numpy as np

    from l2r.protocol import ExperienceChunk, encode
    from l2r.spaces import task_spaces

    args = json.loads((run_dir / "launch.json").read_text())["args"]
    actors = read_rows(run_dir / "metrics" / "actors.csv")
    last = {}  # each actor's last row: its counters
    for row in actors:
        if row.get("role") == "actor":
            last[row["instance"]] = row
    observation, act_dim = task_spaces(args["env_id"])
    steps = 64
    chunk = ExperienceChunk(0, 0, 0, 0, 0, np.zeros((steps + 1, observation.vector_width), np.float32),
                            np.zeros((steps, act_dim), np.float32), np.zeros(steps, np.float32), np.zeros(steps, bool),
                            np.zeros(steps, bool), np.zeros((0, observation.vector_width), np.float32),
                            np.zeros(steps, np.float32))
    per_step = len(encode(chunk)) / steps
    gradients = sum(float(r.get("gradients_sent") or 0) for r in last.values())
    sent = sum(float(r.get("gradient_bytes_sent") or 0) for r in last.values())
    return {"experience_bytes_per_env_step": round(per_step, 1), "gradients_sent": int(gradients),
            "gradient_bytes_per_update": round(sent / gradients, 1) if gradients else None}


def plot(run_dirs: list[Path], results: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    runs = [(json.loads((d / "launch.json").read_text())["args"], d) for d in run_dirs]
    tasks = sorted({args["env_id"] for args, _ in runs})
    fig, axes = plt.subplots(1, len(tasks), figsize=(6 * len(tasks), 4.2), squeeze=False)
    for ax, task in zip(axes[0], tasks):
        for args, d in (r for r in runs if r[0]["env_id"] == task):
            algo, colour = args["algo"], COLOURS[args["algo"]]
            episodes = read_rows(d / "metrics" / "episodes.csv")
            steps = np.array([r["env_steps"] for r in episodes])
            returns = np.array([r["return"] for r in episodes])
            window = max(1, len(returns) // 50)  # a trailing mean: each point the episodes ended by then
            ax.plot(steps[window - 1:], rolling(returns, window), color=colour, lw=1,
                    label=f"l2r {algo}, training episodes")
            evaluations = read_rows(d / "metrics" / "evaluation.csv")
            ax.scatter([r["env_steps"] for r in evaluations], [r["return"] for r in evaluations], s=6,
                       color=colour, alpha=0.5, label=f"l2r {algo}, evaluations")
            if (task.split("-")[0], algo) not in PUBLISHED:
                continue
            mean, std = PUBLISHED[(task.split("-")[0], algo)]
            ax.errorbar([1_000_000], [mean], [std], fmt="s", color=colour, capsize=4,
                        label=f"CleanRL {algo} at 1M (published)")
        for result in results:
            for name, job in result["jobs"].items():
                if name.startswith(task + " ") and name.endswith(" sb3"):
                    algo = name.split()[1]
                    at = [(int(k), v["eval_return"]) for k, v in job["returns"].items()]
                    ax.scatter(*zip(*at), marker="*", s=120, color=COLOURS[algo], edgecolor="black",
                               label=f"SB3 {algo}, this machine")
        ax.set(title=task, xlabel="env steps", ylabel="episode return")
        ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(out, dpi=110)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tasks", default="Hopper-v5,Walker2d-v5", help="gymnasium ids, comma-separated")
    p.add_argument("--algos", default="ppo,sac",
                   help="comma-separated, of ppo, sac, td3, a2c, reinforce, trpo and acktr")
    p.add_argument("--env-steps", type=int, default=MILESTONES[-1], help="env steps of each job")
    p.add_argument("--seconds", type=float, default=0, help="wall-clock limit of each job (0: none)")
    p.add_argument("--runs-dir", type=Path, help="where the jobs' run directories go (default: a temporary one)")
    p.add_argument("--quick", action="store_true", help="every job for 30 s only")
    p.add_argument("--up-arg", action="append", default=[], metavar="FLAG",
                   help="a flag for every l2r up, e.g. --up-arg=--recipe=runner (repeatable)")
    p.add_argument("--sb3", action="store_true", help="also train Stable-Baselines3 for the same env steps")
    p.add_argument("--plot", type=Path, metavar="PNG", help="draw RUN_DIRs' curves to PNG instead of training")
    p.add_argument("--results", type=Path, help="with --plot: this script's earlier output, for the SB3 points")
    p.add_argument("run_dirs", nargs="*", type=Path, help="with --plot: the runs to draw")
    args = p.parse_args()
    if args.quick and args.sb3:
        p.error("--sb3 trains for --env-steps, not for 30 s: leave out --quick")
    if args.plot:
        results = [json.loads(line) for line in args.results.read_text().splitlines()
                   if line.startswith("{")] if args.results else []
        plot(args.run_dirs, results, args.plot)
        return
    seconds = 30 if args.quick else args.seconds
    runs_dir = args.runs_dir or Path(tempfile.mkdtemp(prefix="standard-tasks-"))
    milestones = [m for m in MILESTONES if m < args.env_steps] + [args.env_steps]
    started, results = time.time(), {}
    for task in args.tasks.split(","):
        for algo in args.algos.split(","):
            results[f"{task} {algo}"] = summary(run_job(task, algo, args.env_steps, seconds, runs_dir, args.up_arg),
                                                milestones)
            if args.sb3 and algo in BASELINE_PACKAGES:
                results[f"{task} {algo} sb3"] = sb3_job(task, algo, milestones)
    print(json.dumps({"bench": "standard_tasks", "host_cpus": os.cpu_count(), "up_args": args.up_arg,
                      "seconds": round(time.time() - started, 1), "jobs": results}))


if __name__ == "__main__":
    main()
