"""What MCAP episode logging costs an actor: bytes per step, and env-stepping throughput.

An actor's loop (real env, random excitations, episodes as the env ends them) runs in
alternating rounds without logging and with ``EpisodeLogger`` logging every 10th episode;
a third kind of round also keeps every episode in memory for "best so far". CPU time counts
both threads of the process (the writer thread's work is the actor's cost); each logging
round ends with ``close()``, so all of its writing is inside the measurement.

Prints one JSON line: ``mcap_bytes_per_step``, ``steps_per_s_no_log``, ``steps_per_s_log_every_10``,
``cost_fraction_every_10`` (extra CPU per env step over no logging; goal < 0.05),
``cost_fraction_every_10_wall``, ``cost_fraction_best_so_far``, ``mean_episode_steps``, ...
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from l2r.actors.episode_log import NULL_RECORDER, EpisodeLogger, LogPolicy
from l2r.sim.env import RunEnv


def run_round(env: RunEnv, steps: int, logger: EpisodeLogger | None, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    actions = 0.3 * rng.random((steps, 18))
    wall, cpu = time.perf_counter(), time.process_time()
    episode, episodes, obs_ret = seed, 0, 0.0
    env.reset(seed=episode)
    recorder = logger.begin_episode({"seed": episode, "difficulty": env.difficulty}) if logger else NULL_RECORDER
    for t in range(steps):
        obs, reward, terminated, truncated, info = env.step(actions[t])
        recorder.log_step(obs, actions[t], reward, info)
        obs_ret += reward
        if terminated or truncated:
            recorder.end({"return": obs_ret, "distance": info["distance"]})
            episode, episodes, obs_ret = episode + 1, episodes + 1, 0.0
            env.reset(seed=episode)
            recorder = logger.begin_episode({"seed": episode, "difficulty": env.difficulty}) if logger else NULL_RECORDER
    recorder.end({"return": obs_ret})
    if logger:
        logger.close()
    return {"wall": time.perf_counter() - wall, "cpu": time.process_time() - cpu, "episodes": episodes}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=20_000, help="env steps per round (default: %(default)s)")
    parser.add_argument("--rounds", type=int, default=3, help="rounds of each kind, interleaved (default: %(default)s)")
    parser.add_argument("--quick", action="store_true", help="a short run (5,000 steps, 2 rounds)")
    args = parser.parse_args()
    if args.quick:
        args.steps, args.rounds = 5_000, 2
    env = RunEnv(difficulty=0)
    results: dict[str, list[dict]] = {"none": [], "every_10": [], "best": []}
    logged_bytes = logged_steps = 0
    with tempfile.TemporaryDirectory() as tmp:
        run_round(env, 500, None, seed=0)  # warm-up
        for r in range(args.rounds):
            for kind in results:
                directory = Path(tmp) / f"{kind}{r}"
                policy = {"none": None, "every_10": LogPolicy(every=10), "best": LogPolicy(every=10, best=True)}[kind]
                logger = EpisodeLogger(directory, "bench", 0, policy, disk_budget_bytes=1 << 40) if policy else None
                results[kind].append(run_round(env, args.steps, logger, seed=1000 * r))
                if kind == "every_10":
                    files = list(directory.glob("*.mcap"))
                    logged_bytes += sum(p.stat().st_size for p in files)
                    logged_steps += sum(_steps(p) for p in files)
                    skipped = logger.stats["episodes_skipped"]

    def per_step(kind: str, key: str) -> float:
        return statistics.median(x[key] for x in results[kind]) / args.steps

    base_cpu, base_wall = per_step("none", "cpu"), per_step("none", "wall")
    episodes = statistics.median(x["episodes"] for x in results["none"])
    print(json.dumps({
        "mcap_bytes_per_step": round(logged_bytes / max(logged_steps, 1), 1),
        "steps_per_s_no_log": round(1 / base_wall),
        "steps_per_s_log_every_10": round(1 / per_step("every_10", "wall")),
        "cost_fraction_every_10": round(per_step("every_10", "cpu") / base_cpu - 1, 4),
        "cost_fraction_every_10_wall": round(per_step("every_10", "wall") / base_wall - 1, 4),
        "cost_fraction_best_so_far": round(per_step("best", "cpu") / base_cpu - 1, 4),
        "mean_episode_steps": round(args.steps / max(episodes, 1), 1),
        "logged_steps": logged_steps, "episodes_skipped": skipped,
        "steps_per_round": args.steps, "rounds": args.rounds,
    }))


def _steps(path: Path) -> int:
    from mcap.reader import make_reader

    from l2r.episodes.schema import TOPIC_STEP

    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    step = next(c.id for c in summary.channels.values() if c.topic == TOPIC_STEP)
    return summary.statistics.channel_message_counts.get(step, 0)


if __name__ == "__main__":
    main()
