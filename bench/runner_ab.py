"""A/B runs of the runner's recipe, judged by OpenSim: one JSON line per arm.

    python bench/runner_ab.py --seed 2 --seconds 3600 --arm recipe= --arm hist="--frame-stack 8"
    python bench/runner_ab.py --seed 2 --arm recipe= --arm before="--randomize '' --target-entropy-per-action -1"
    python bench/runner_ab.py --judge RUN_DIR [RUN_DIR ...]      # judge runs made before
    python bench/runner_ab.py --plot docs/ab.png RUN_DIR [RUN_DIR ...]   # their evaluations, a panel each
    python bench/runner_ab.py --plot docs/staged.png RUN RUN-opensim    # a staged job's two stages in one

Each arm is the 2-core recipe (`l2r up --evaluators 2 --eval-env-id l2r/RunOpenSim-v0 --eval-env-id
l2r/Run-v0 --eval-episodes 1 --eval-interval 60`) with the arm's flags, all arms started **at
once** on this host, so that they share the machine alike: on 2 cores, two arms get about one
core each, about what one run alone makes in half the time (every process at equal priority,
`l2r up`'s default `--actor-nice 0`: with the learners first, two would take both cores from the
actors). The levers and the reasons for judging this way: docs/training.md, "Levers for
robustness".

What each line holds, from the run's metrics/ and from `l2r eval` afterwards (arms judged at once):
- `first_opensim_6m`: minutes and updates at the first OpenSim evaluation of 6 m or more;
- `best_opensim`, `best_port`: the best evaluation in each simulator (metres, version, minute);
- `opensim_over_port`: after `--after` minutes (default 30), each OpenSim evaluation over the
  port's of the nearest version (at most `--within` apart, default 10, where the port's ran over
  1 m): least, median, count;
- `parting_0.7_minute`: the minute at which `l2r up --opensim-stage-parting 0.7` would have ended
  the port's stage on these evaluations (None: never);
- `kept` (learner/best.pt) and `newest` (the run's checkpoint): OpenSim and port distances at
  difficulty 0 (seed 0, `opensim_d0`, `port_d0`) and the mean over seeds 0-19 at difficulty 2;
- `updates`, `env_steps`, and the temperature and entropy the learner last reported.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shlex
import statistics
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from env_speed import cpu_flags, cpu_model  # this folder's: the same machine record as the speed figures

from l2r.opensim_stage import Parting, run_dir_of
from l2r.run_metrics import RunCounters

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ["--evaluators", "2", "--eval-env-id", "l2r/RunOpenSim-v0", "--eval-env-id", "l2r/Run-v0",
          "--eval-episodes", "1", "--eval-interval", "60"]
SIMULATORS = {"opensim": "l2r/RunOpenSim-v0", "port": "l2r/Run-v0"}
OBSTACLE_SEEDS = 20
PARTING = 0.7  # the bound on OpenSim over the port


def rows(path: Path) -> list[dict]:
    with open(path) as f:
        return list(csv.DictReader(f))


def evaluations(run_dir: Path, env_id: str) -> list[tuple[float, int, float, int]]:
    """(seconds, version, distance, updates) of each evaluation in `env_id`."""
    return [(float(r["time"]), int(r["version"]), float(r["distance"]), int(r["updates"]))
            for r in rows(run_dir / "metrics" / "evaluation.csv") if r["simulator"] == env_id]


def parting_minute(run_dir: Path, episodes_per_round: int) -> float | None:
    """The minute at which `l2r up --opensim-stage-parting 0.7` (the same rule) would have ended
    the port's stage, or None."""
    parting = Parting(PARTING, episodes_per_round, simulators={})
    for r in rows(run_dir / "metrics" / "evaluation.csv"):
        parting.add(r["simulator"], int(r["version"]), float(r["distance"]))
        if parting.verdict:
            return round(float(r["time"]) / 60, 1)
    return None


def curve_figures(run_dir: Path, after_s: float, within: int) -> dict:
    opensim, port = (evaluations(run_dir, SIMULATORS[s]) for s in ("opensim", "port"))
    episodes_per_round = json.loads((run_dir / "launch.json").read_text())["args"].get("eval_episodes", 1)
    first = next(((round(t / 60, 1), u) for t, _, d, u in opensim if d >= 6.0), None)
    ratios = []
    for t, version, distance, _ in opensim:
        near = min(port, key=lambda p: abs(p[1] - version), default=None)
        if t >= after_s and near and abs(near[1] - version) <= within and near[2] > 1.0:
            ratios.append(distance / near[2])

    def best(evals):
        top = max(evals, key=lambda e: e[2], default=None)
        return top and {"m": round(top[2], 2), "version": top[1], "minute": round(top[0] / 60, 1)}

    learner = [r for r in rows(run_dir / "metrics" / "learner.csv") if r["entropy"]]
    last = learner[-1] if learner else {}
    return {"first_opensim_6m": first and {"minute": first[0], "updates": first[1]},
            "best_opensim": best(opensim), "best_port": best(port),
            "opensim_over_port": {"least": round(min(ratios), 2), "median": round(statistics.median(ratios), 2),
                                  "count": len(ratios)} if ratios else None,
            f"parting_{PARTING:g}_minute": parting_minute(run_dir, episodes_per_round),
            "evaluations": len(opensim), "updates": int(last.get("updates", 0)),
            "env_steps": int(last.get("env_steps", 0)), "alpha": float(last.get("alpha", "nan")),
            "entropy": float(last.get("entropy", "nan"))}


def distance(checkpoint: Path, env_id: str, difficulty: int, episodes: int) -> float:
    out = subprocess.run([sys.executable, "-m", "l2r.cli", "eval", str(checkpoint), "--env-id", env_id,
                          "--difficulty", str(difficulty), "--episodes", str(episodes), "--json",
                          "--progress-every", "0"], cwd=ROOT, capture_output=True, text=True, check=True)
    return round(json.loads(out.stdout)["mean_distance"], 2)


def judge(run_dir: Path, after_s: float, within: int) -> dict:
    policies = {"kept": run_dir / "learner" / "best.pt", "newest": run_dir}
    episodes = {0: 1, 2: OBSTACLE_SEEDS}
    judged = {name: {f"{sim}_d{difficulty}": distance(path, env_id, difficulty, episodes[difficulty])
                     for difficulty in (0, 2) for sim, env_id in SIMULATORS.items()}
              for name, path in policies.items()}
    launch = json.loads((run_dir / "launch.json").read_text())["args"]
    return {"run_dir": str(run_dir), "seed": launch.get("seed"), "seconds": launch.get("seconds"),
            **curve_figures(run_dir, after_s, within), **judged}


def plot(run_dirs: list[Path], out: Path) -> None:
    """Each run's evaluations in both simulators against its minutes of training, a panel each; a
    staged job's OpenSim stage (`RUN-opensim`, given beside `RUN`) drawn on in its port stage's
    panel from where that stage ended."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stages = {run_dir_of(d): d for d in run_dirs}
    panels = [d for d in run_dirs if d not in stages]
    fig, axes = plt.subplots(len(panels), 1, figsize=(9, 2.6 * len(panels)), sharex=True, squeeze=False)
    for ax, run_dir in zip(axes[:, 0], panels):
        stage = run_dir_of(run_dir)
        parts = [(run_dir, 0.0)] + ([(stage, RunCounters.read(run_dir / "metrics").time)] if stage in run_dirs else [])
        for part, (directory, offset) in enumerate(parts):
            for sim, colour in (("port", "tab:orange"), ("opensim", "tab:red")):
                evals = evaluations(directory, SIMULATORS[sim])
                ax.plot([(offset + t) / 60 for t, *_ in evals], [d for _, _, d, _ in evals], "o-", color=colour,
                        markersize=3, linewidth=0.8, label=SIMULATORS[sim] if part == 0 else None)
            if offset:
                ax.axvline(offset / 60, color="black", linewidth=0.8)
                ax.text(offset / 60, ax.get_ylim()[1], " OpenSim's stage", fontsize=8, va="top")
        ax.axhline(6.0, color="gray", linestyle=":", linewidth=0.8)
        ax.set_title(run_dir.name, fontsize=9)
        ax.set_ylabel("distance (m)")
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="upper left", fontsize=8)
    axes[-1, 0].set_xlabel("minutes of training")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--arm", action="append", default=[], metavar="NAME=FLAGS",
                        help="an arm: its name and the l2r up flags it adds (none for the recipe itself)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--seconds", type=int, default=3600, help="each arm's l2r up --seconds")
    parser.add_argument("--after", type=float, default=30.0, help="minutes after which OpenSim is held to the port")
    parser.add_argument("--within", type=int, default=10, help="most policy versions between an OpenSim evaluation and "
                        "the port's it is held to")
    parser.add_argument("--runs-dir", type=Path, default=ROOT / "runs")
    parser.add_argument("--judge", type=Path, nargs="+", metavar="RUN_DIR", help="judge these runs instead")
    parser.add_argument("--plot", type=Path, metavar="PNG", help="draw the evaluations of the runs given (--judge "
                        "or positional) instead of judging them")
    parser.add_argument("runs", type=Path, nargs="*", metavar="RUN_DIR", help="runs to --plot")
    args = parser.parse_args()
    if args.plot:
        plot(args.runs or args.judge or [], args.plot)
        return
    machine = {"machine": f"{cpu_model()}, {os.cpu_count()} CPUs", "cpu_flags": cpu_flags()}

    run_dirs, arms = args.judge or [], {}
    if not run_dirs:
        if not args.arm:
            parser.error("give at least one --arm, or --judge")
        arms = dict(arm.split("=", 1) for arm in args.arm)
        started = time.strftime("%Y%m%d-%H%M%S")
        jobs = []
        for name, flags in arms.items():
            run_name = f"ab-{name}-s{args.seed}-{started}"
            command = [sys.executable, "-m", "l2r.cli", "up", "--seconds", str(args.seconds), "--seed", str(args.seed),
                       "--name", run_name, "--runs-dir", str(args.runs_dir), "--status-interval", "60", *RECIPE,
                       *shlex.split(flags)]
            jobs.append(subprocess.Popen(command, cwd=ROOT))
        if any(job.wait() for job in jobs):
            sys.exit("an arm's l2r up failed: its run directory's logs say why")
        run_dirs = [max(args.runs_dir.glob(f"ab-{name}-s{args.seed}-{started}-*")) for name in arms]

    with ThreadPoolExecutor(len(run_dirs)) as pool:
        results = list(pool.map(lambda d: judge(d, args.after * 60, args.within), run_dirs))
    for name, result in zip(arms or [d.name for d in run_dirs], results):
        print(json.dumps({"bench": "runner_ab", "arm": name, "flags": arms.get(name), **result, **machine}))


if __name__ == "__main__":
    main()
