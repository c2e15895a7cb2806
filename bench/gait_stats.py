"""How a run's gait moves, in the port and in OpenSim: one JSON line per run, from its evaluation episodes.

    python bench/gait_stats.py RUN_DIR [RUN_DIR ...] [--min-distance 6] [--within 10]

Each port evaluation at difficulty 0 that ran `--min-distance` metres or more is paired with the
OpenSim evaluation of the nearest policy version (at most `--within` versions apart), both read
from the run's episode logs (episodes/*-eval.mcap, written by `l2r up`'s evaluators). Per episode:
  distance, seconds      how far it ran and how long it lasted (the episode's steps x step seconds)
  saturated              the share of excitations within 0.05 of 0 or 1 (bang-bang control)
  chatter                the mean change of an excitation from one step to the next
  activation             the muscles' mean activation
  pelvis, pelvis_sd      the pelvis height's mean and standard deviation over the episode (m)
  flight                 the share of steps with neither foot on the ground (no vertical contact force)
  ground_n_p95           the 95th percentile of the feet's vertical ground force summed, newtons
The line holds each figure's median over the pairs, port and OpenSim, the pairs' count and
policy versions. A gait that moves alike in both simulators keeps its figures; one that falls
in OpenSim shows it in `seconds` first, and the port's figures say what kind of gait it is.
"""

from __future__ import annotations

import argparse
import json
import statistics
from pathlib import Path

import numpy as np

from l2r.episodes.read import episode_metadata, read_episode

FIGURES = ("distance", "seconds", "saturated", "chatter", "activation", "pelvis", "pelvis_sd", "flight", "ground_n_p95")
VERTICAL = 1  # of each contact's (x, y, z) force in the episode logs: the planar body's y is up
PORT, OPENSIM = "l2r/Run-v0", "l2r/RunOpenSim-v0"


def episode_figures(path: Path) -> dict:
    episode = read_episode(path)
    excitation = episode.steps["action"]
    pelvis = episode.steps["pelvis_height"]
    contacts = episode.steps["contact_force"].reshape(len(excitation), -1, 3)
    ground = contacts[:, :, VERTICAL].clip(min=0).sum(axis=1)
    return {"version": int(episode.episode["policy_version"]),
            "distance": float(episode.steps["distance"][-1]),
            "seconds": len(excitation) * float(episode.episode["step_seconds"]),
            "saturated": float(np.mean((excitation < 0.05) | (excitation > 0.95))),
            "chatter": float(np.abs(np.diff(excitation, axis=0)).mean()),
            "activation": float(episode.steps["muscle_activation"].mean()),
            "pelvis": float(pelvis.mean()), "pelvis_sd": float(pelvis.std()),
            "flight": float(np.mean(ground < 1.0)), "ground_n_p95": float(np.percentile(ground, 95))}


def evaluations(run_dir: Path) -> dict[str, list[dict]]:
    """The figures of each flat-ground evaluation episode of the run, by simulator."""
    found: dict[str, list[dict]] = {PORT: [], OPENSIM: []}
    for path in sorted((run_dir / "episodes").glob("*-eval.mcap")):
        meta = episode_metadata(path)["episode"]
        if meta.get("difficulty") == "0" and meta.get("env_id") in found:
            found[meta["env_id"]].append(episode_figures(path))
    return found


def run_line(run_dir: Path, min_distance: float, within: int) -> dict:
    found = evaluations(run_dir)
    pairs = []
    for port in (e for e in found[PORT] if e["distance"] >= min_distance):
        opensim = min(found[OPENSIM], key=lambda e: abs(e["version"] - port["version"]), default=None)
        if opensim is not None and abs(opensim["version"] - port["version"]) <= within:
            pairs.append((port, opensim))
    line = {"bench": "gait_stats", "run_dir": str(run_dir), "pairs": len(pairs),
            "versions": [pairs[0][0]["version"], pairs[-1][0]["version"]] if pairs else None}
    for side, name in ((0, "port"), (1, "opensim")):
        line[name] = {f: round(statistics.median(p[side][f] for p in pairs), 3) for f in FIGURES} if pairs else None
    return line


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("runs", nargs="+", type=Path, help="run directories of l2r up")
    p.add_argument("--min-distance", type=float, default=6.0,
                   help="port evaluations that ran at least this far, in metres (default: %(default)s)")
    p.add_argument("--within", type=int, default=10,
                   help="most policy versions between a port evaluation and its OpenSim one (default: %(default)s)")
    args = p.parse_args()
    for run_dir in args.runs:
        if not (run_dir / "episodes").is_dir():
            p.error(f"{run_dir}: no episodes/ folder in it: not a run directory of l2r up")
    for run_dir in args.runs:
        print(json.dumps(run_line(run_dir, args.min_distance, args.within)))


if __name__ == "__main__":
    main()
