"""An actor's logging in miniature: steps the real env and logs through EpisodeLogger.

Run as a process of its own by the tests (``python tests/logs/episode_writer.py DIR ...``);
the tests call ``play`` in-process too, to get what the env produced for the same seeds.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from l2r.sim.env import RunEnv

RUN = "logtest"
DIFFICULTY = 1


def play(env: RunEnv, recorder, seed: int, steps: int, across_resets: bool = False) -> dict:
    """Step ``steps`` times with seeded excitations, logging each step; returns what the env
    produced. ``across_resets``: an episode that ends early restarts and logging goes on."""
    rng = np.random.default_rng(seed)
    obs, info = env.reset(seed=seed)
    out: dict[str, list] = {"obs": [], "action": [], "reward": [], "info": []}
    for t in range(steps):
        action = 0.3 * rng.random(18)
        obs, reward, terminated, truncated, info = env.step(action)
        recorder.log_step(obs, action, reward, info)
        for key, value in (("obs", obs), ("action", action), ("reward", reward), ("info", info)):
            out[key].append(value)
        if terminated or truncated:
            if not across_resets:
                break
            obs, info = env.reset(seed=seed + 1000 + t)
    out["terminated"], out["truncated"] = terminated, truncated
    return out


def meta(env: RunEnv, seed: int) -> dict:
    return {"seed": seed, "difficulty": DIFFICULTY, "policy_version": 7, "evaluation": False, "obstacles": env.obstacles}


def main() -> int:
    from l2r.actors.episode_log import EpisodeLogger, LogPolicy

    parser = argparse.ArgumentParser()
    parser.add_argument("directory")
    parser.add_argument("--episodes", type=int, default=2)
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--block-steps", type=int, default=100)
    parser.add_argument("--chunk-bytes", type=int, default=256 * 1024)
    parser.add_argument("--hang", action="store_true", help="stop mid-episode and wait to be killed")
    args = parser.parse_args()
    logger = EpisodeLogger(args.directory, RUN, actor_id=0, policy=LogPolicy(every=1),
                           block_steps=args.block_steps, chunk_bytes=args.chunk_bytes)  # fmt: skip
    env = RunEnv(difficulty=DIFFICULTY, max_steps=args.steps)
    for seed in range(args.episodes):
        env.reset(seed=seed)
        recorder = logger.begin_episode(meta(env, seed))
        out = play(env, recorder, seed, args.steps, across_resets=args.hang)
        if args.hang:
            print("hanging", flush=True)
            time.sleep(600)
        recorder.end({"return": float(np.sum(out["reward"])), "distance": out["info"][-1]["distance"],
                      "terminated": out["terminated"], "truncated": out["truncated"]})  # fmt: skip
    logger.close()
    print(logger.stats, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
