"""What MCAP episode logging costs an actor: bytes per step, and env-stepping throughput.

An actor's loop (the real env, random excitations, the actor's action repeat) runs in
interleaved rounds: without logging, with ``EpisodeLogger`` logging every 10th episode, and
logging every 10th episode while keeping every other one in memory for "best so far".
Episodes are 1000 env steps long (the 2017 limit) whatever the body does: when the env ends an episode sooner it is reset and the logged
episode goes on, so the figures describe full-length episodes, not how soon the current
body falls. A logging round ends with ``close()``, so all of its writing is measured.

The cost is the CPU time spent logging — ``log_step`` calls on the stepping thread plus the
writer thread's CPU time, both read from per-thread clocks — per env step, as a fraction of
the CPU time per env step of the rounds without logging. On a shared machine this is far
steadier than the difference of two throughputs, which is reported too (``*_ratio``: CPU time
and wall-clock time per env step with logging over without).

Prints one JSON line: ``mcap_bytes_per_step``, ``cost_fraction_every_10`` (goal < 0.05),
``cost_fraction_every_10_repeat_1`` (no action repeat: a logged step per env step),
``cost_fraction_best_so_far``, the ratios, ``steps_per_s_*``, ``episodes_skipped``, settings.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np
from mcap.reader import make_reader

from l2r.actors.episode_log import NULL_RECORDER, EpisodeLogger, LogPolicy
from l2r.episodes.schema import TOPIC_STEP
from l2r.sim.env import RunEnv
from l2r.sim.wrappers import ActionRepeat

POLICIES = {"none": None, "every_10": LogPolicy(every=10), "best": LogPolicy(every=10, best=True)}


def run_round(env, episodes: int, episode_steps: int, logger: EpisodeLogger | None, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    actions = 0.3 * rng.random((episode_steps, 18))
    env_steps, resets, logging_cpu = 0, 0, 0.0
    clock = time.thread_time
    wall, cpu = time.perf_counter(), time.process_time()
    for episode in range(episodes):
        env.reset(seed=seed + episode)
        recorder = logger.begin_episode({"seed": seed + episode, "difficulty": 0}) if logger else NULL_RECORDER
        total = 0.0
        for action in actions:
            obs, reward, terminated, truncated, info = env.step(action)
            if recorder is NULL_RECORDER:  # not logged: a no-op call, not worth two clock reads
                recorder.log_step(obs, action, reward, info)
            else:
                start = clock()
                recorder.log_step(obs, action, reward, info)
                logging_cpu += clock() - start
            total += reward
            env_steps += info.get("inner_steps", 1)
            if terminated or truncated:
                resets += 1
                env.reset(seed=seed + episode + 10_000 * resets)
        recorder.end({"return": total, "distance": info["distance"]})
    if logger:
        logger.close()
        logging_cpu += logger.stats["writer_cpu_s"]
    return {"wall": time.perf_counter() - wall, "cpu": time.process_time() - cpu, "env_steps": env_steps,
            "logging_cpu": logging_cpu, "env_episode_steps": env_steps / (resets + episodes)}  # fmt: skip


def logged_steps(directory: Path) -> tuple[int, int]:
    """(bytes, /step messages) of the episode files in ``directory``."""
    size = steps = 0
    for path in directory.glob("*.mcap"):
        size += path.stat().st_size
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
        channel = next(c.id for c in summary.channels.values() if c.topic == TOPIC_STEP)
        steps += summary.statistics.channel_message_counts.get(channel, 0)
    return size, steps


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--episodes", type=int, default=20, help="episodes per round (default: %(default)s)")
    parser.add_argument("--rounds", type=int, default=3, help="rounds of each kind, interleaved (default: %(default)s)")
    parser.add_argument("--action-repeat", type=int, default=3, help="as the actor steps (default: %(default)s)")
    parser.add_argument("--quick", action="store_true", help="a short run: 10 episodes, 2 rounds")
    args = parser.parse_args()
    if args.quick:
        args.episodes, args.rounds = 10, 2
    env_steps = 1000
    kinds = {  # name: (logging policy, action repeat)
        "none": (None, args.action_repeat), "every_10": (POLICIES["every_10"], args.action_repeat),
        "best": (POLICIES["best"], args.action_repeat),
        "none_repeat_1": (None, 1), "every_10_repeat_1": (POLICIES["every_10"], 1),
    }  # fmt: skip
    results: dict[str, list[dict]] = {k: [] for k in kinds}
    size = steps = skipped = 0
    base = RunEnv(difficulty=0)
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for kind, (policy, repeat) in kinds.items():
                env = ActionRepeat(base, repeat) if repeat > 1 else base
                directory = Path(tmp) / f"{kind}{r}"
                logger = (EpisodeLogger(directory, "bench", 0, policy, disk_budget_bytes=1 << 40, step_seconds=0.01 * repeat)
                          if policy else None)  # fmt: skip
                results[kind].append(run_round(env, args.episodes, env_steps // repeat, logger, seed=1000 * r))
                if logger:
                    skipped += logger.stats["episodes_skipped"]
                if kind == "every_10":
                    s, n = logged_steps(directory)
                    size, steps = size + s, steps + n

    def cpu_per_step(kind: str) -> float:
        return statistics.median(x["cpu"] / x["env_steps"] for x in results[kind])

    def wall_rate(kind: str) -> float:
        return statistics.median(x["env_steps"] / x["wall"] for x in results[kind])

    def logging_share(kind: str, baseline: str) -> float:
        """CPU spent logging (log_step calls + writer thread) per env step, over a round without logs."""
        return statistics.median(x["logging_cpu"] / x["env_steps"] for x in results[kind]) / cpu_per_step(baseline)

    print(json.dumps({
        "mcap_bytes_per_step": round(size / max(steps, 1), 1),
        "steps_per_s_no_log": round(wall_rate("none")),
        "steps_per_s_log_every_10": round(wall_rate("every_10")),
        "cost_fraction_every_10": round(logging_share("every_10", "none"), 4),
        "cost_fraction_every_10_repeat_1": round(logging_share("every_10_repeat_1", "none_repeat_1"), 4),
        "cost_fraction_best_so_far": round(logging_share("best", "none"), 4),
        "cpu_ratio_every_10": round(cpu_per_step("every_10") / cpu_per_step("none"), 4),
        "cpu_ratio_every_10_repeat_1": round(cpu_per_step("every_10_repeat_1") / cpu_per_step("none_repeat_1"), 4),
        "wall_ratio_every_10": round(wall_rate("none") / wall_rate("every_10"), 4),
        "env_cpu_us_per_step": round(1e6 * cpu_per_step("none_repeat_1"), 1),
        "episodes_skipped": skipped, "logged_steps": steps,
        "env_episode_steps": round(statistics.mean(x["env_episode_steps"] for x in results["none"]), 1),
        "episodes_per_round": args.episodes, "rounds": args.rounds, "action_repeat": args.action_repeat,
    }))


if __name__ == "__main__":
    main()
