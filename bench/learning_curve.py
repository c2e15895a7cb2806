"""Plot a training run: episode return and distance against wall-clock time, per simulator.

    python bench/learning_curve.py runs/curve-20261121-061500 [--out docs/learning_curve.png]

Reads the CSV files `l2r up` writes under the run's metrics/ (docs/training.md): training
episodes (stochastic policy) as a rolling mean, evaluation episodes (deterministic, fixed
seeds) as points, one colour per simulator, so a run with `--eval-env-id l2r/Run-v0
--eval-env-id l2r/RunOpenSim-v0` shows the port's and OpenSim's distances of the same policies;
and the random-excitation level for reference (the warm-up episodes, policy version -1).
Prints one JSON line with what the run reached, per simulator.
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

PORT = "l2r/Run-v0"
COLOURS = {"l2r/Run-v0": "tab:orange", "l2r/RunOpenSim-v0": "tab:red"}


def read_rows(path: Path) -> list[dict]:
    """A metrics CSV as dicts with numbers where the values are numbers."""
    if not path.exists():
        return []

    def value(v: str):
        try:
            return float(v)
        except ValueError:
            return v

    with open(path, newline="") as f:
        return [{k: value(v) for k, v in row.items()} for row in csv.DictReader(f)]


def rolling(values: np.ndarray, window: int) -> np.ndarray:
    return np.convolve(values, np.ones(window) / window, mode="valid")


def by_simulator(episodes: list[dict]) -> dict[str, list[dict]]:
    groups: dict[str, list[dict]] = {}
    for row in episodes:
        groups.setdefault(row.get("simulator") or PORT, []).append(row)
    return groups


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run_dir", type=Path)
    p.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "docs" / "learning_curve.png")
    p.add_argument("--window", type=int, default=50, help="training episodes per rolling mean")
    args = p.parse_args()

    metrics = args.run_dir / "metrics"
    train = read_rows(metrics / "episodes.csv")
    evals = by_simulator(read_rows(metrics / "evaluation.csv"))
    status = read_rows(metrics / "status.csv")
    if not train and not evals:
        raise SystemExit(f"learning_curve: no episodes in {metrics} (a run of `l2r up` writes them there)")
    random_eps = [r for r in train if r["version"] < 0]
    policy_eps = by_simulator([r for r in train if r["version"] >= 0])

    fig, axes = plt.subplots(2, 1, figsize=(9, 7), sharex=True)
    for ax, key, label in ((axes[0], "return", "episode return"), (axes[1], "distance", "distance (m)")):
        for simulator, eps in policy_eps.items():
            t = np.array([r["time"] for r in eps]) / 60
            v = np.array([r[key] for r in eps])
            ax.plot(t, v, ".", color="tab:blue", alpha=0.15, markersize=3)
            w = min(args.window, len(v))
            ax.plot(t[w - 1:], rolling(v, w), color="tab:blue", label=f"training episodes in {simulator} (mean of {w})")
        for simulator, eps in evals.items():
            ax.plot([r["time"] / 60 for r in eps], [r[key] for r in eps], "o", markersize=4,
                    color=COLOURS.get(simulator, "tab:green"), label=f"evaluation in {simulator} (deterministic)")
        if random_eps:
            ax.axhline(float(np.mean([r[key] for r in random_eps])), color="gray", linestyle="--",
                       label="random excitations (warm-up)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper left", fontsize=8)
    axes[1].set_xlabel("wall-clock time (min)")
    last = status[-1] if status else {}
    fig.suptitle(f"l2r up on {args.run_dir.name}: {int(last.get('env_steps', 0)):,} env steps, "
                 f"{int(last.get('updates', 0)):,} updates", fontsize=10)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)

    def mean_of(eps, n):
        return float(np.mean([r["distance"] for r in eps[-n:]])) if eps else None

    print(json.dumps({
        "minutes": last.get("time", 0.0) / 60, "env_steps": last.get("env_steps"), "updates": last.get("updates"),
        "random_distance": mean_of(random_eps, len(random_eps)),
        "final_train_distance": {s: mean_of(eps, 50) for s, eps in policy_eps.items()},
        "final_eval_distance": {s: mean_of(eps, 4) for s, eps in evals.items()},
        "best_eval_distance": {s: max(r["distance"] for r in eps) for s, eps in evals.items()},
        "plot": str(args.out),
    }))


if __name__ == "__main__":
    main()
