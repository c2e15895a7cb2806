"""Plot a training run: episode return and distance against wall-clock time.

    python bench/learning_curve.py runs/curve-20261121-061500 [--out docs/learning_curve.png]

Reads the run's metrics.jsonl (written by `l2r up`); draws training episodes (stochastic
policy) as a rolling mean, evaluation episodes (deterministic, fixed seeds) as points, and the
random-excitation level for reference (the mean distance of the warm-up episodes, version -1).
Prints one JSON line with what the run reached.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def rolling(values: np.ndarray, window: int) -> np.ndarray:
    if len(values) < window:
        window = max(len(values), 1)
    kernel = np.ones(window) / window
    return np.convolve(values, kernel, mode="valid")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run_dir", type=Path)
    p.add_argument("--out", type=Path, default=Path(__file__).resolve().parents[1] / "docs" / "learning_curve.png")
    p.add_argument("--window", type=int, default=50, help="training episodes per rolling mean")
    args = p.parse_args()

    rows = [json.loads(line) for line in (args.run_dir / "metrics.jsonl").read_text().splitlines() if line.strip()]
    episodes = [r for r in rows if r["type"] == "episode"]
    train = [r for r in episodes if not r["evaluation"]]
    evals = [r for r in episodes if r["evaluation"]]
    random_eps = [r for r in train if r["version"] < 0]
    policy_eps = [r for r in train if r["version"] >= 0]
    status = [r for r in rows if r["type"] == "status"]

    fig, axes = plt.subplots(2, 1, figsize=(9, 7), sharex=True)
    for ax, key, label in ((axes[0], "return", "episode return"), (axes[1], "distance", "distance (m)")):
        if policy_eps:
            t = np.array([r["t"] for r in policy_eps]) / 60
            v = np.array([r[key] for r in policy_eps])
            ax.plot(t, v, ".", color="tab:blue", alpha=0.15, markersize=3)
            w = min(args.window, len(v))
            ax.plot(t[w - 1:], rolling(v, w), color="tab:blue", label=f"training episodes (mean of {w})")
        if evals:
            ax.plot([r["t"] / 60 for r in evals], [r[key] for r in evals], "o", color="tab:orange",
                    markersize=4, label="evaluation episodes (deterministic)")
        if random_eps:
            ax.axhline(float(np.mean([r[key] for r in random_eps])), color="gray", linestyle="--",
                       label="random excitations (warm-up)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(loc="upper left", fontsize=8)
    axes[1].set_xlabel("wall-clock time (min)")
    last = status[-1] if status else {}
    fig.suptitle(f"l2r up on {args.run_dir.name}: {last.get('env_steps', 0):,} env steps, "
                 f"{last.get('updates', 0):,} updates", fontsize=10)
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=110)

    def mean_of(eps, key, n=50):
        return float(np.mean([r[key] for r in eps[-n:]])) if eps else None

    print(json.dumps({
        "minutes": (status[-1]["elapsed"] / 60) if status else 0.0,
        "env_steps": last.get("env_steps"), "updates": last.get("updates"),
        "random_distance": mean_of(random_eps, "distance", len(random_eps) or 1),
        "final_train_distance": mean_of(policy_eps, "distance"),
        "final_train_return": mean_of(policy_eps, "return"),
        "best_train_distance": max((r["distance"] for r in policy_eps), default=None),
        "final_eval_distance": mean_of(evals, "distance", 4),
        "best_eval_distance": max((r["distance"] for r in evals), default=None),
        "plot": str(args.out),
    }))


if __name__ == "__main__":
    main()
