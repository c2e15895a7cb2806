"""`l2r eval`: deterministic episodes of a trained policy, distance per episode."""

from __future__ import annotations

import argparse
import json
import sys
import time

import gymnasium
import torch

import l2r.sim  # noqa: F401  (registers l2r/Run-v0 and l2r/RunOpenSim-v0)
from l2r.actors.actor import run_deterministic
from l2r.config import CommandParser
from l2r.learner.checkpoint import CheckpointError, load_checkpoint
from l2r.sim.wrappers import ActionRepeat

DEFAULT_ACTION_REPEAT = 3  # the runner's recipe's and l2r-actor's; for checkpoints that do not say


def build_parser() -> argparse.ArgumentParser:
    p = CommandParser(
        prog="l2r eval",
        description="Run deterministic episodes (the policy's mean action) of a learner checkpoint "
                    "and print the distance the runner's pelvis travelled in each. Distances to compare "
                    "with the 2017 challenge's are stated with --env-id l2r/RunOpenSim-v0: the episodes "
                    "then run on OpenSim 4.6, the simulator of 2017, rather than on the MuJoCo port.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("checkpoint", metavar="CHECKPOINT_OR_RUN_DIR",
                   help="a checkpoint file, or a run directory of `l2r up` (uses its learner checkpoint)")
    p.add_argument("--episodes", type=int, default=5, help="episodes to run, on seeds S, S+1, ...")
    p.add_argument("--seed", type=int, default=0, help="seed S of the first episode")
    p.add_argument("--difficulty", type=int, choices=(0, 1, 2), default=0,
                   help="0 flat, 1 obstacles, 2 obstacles and random psoas strengths")
    p.add_argument("--action-repeat", type=int,
                   help="0.01 s steps per action; default: what the checkpoint says training used "
                        f"({DEFAULT_ACTION_REPEAT} for checkpoints that do not say)")
    p.add_argument("--env-id", default="l2r/Run-v0",
                   help="gymnasium id of the environment: l2r/Run-v0 (the MuJoCo port) or l2r/RunOpenSim-v0 "
                        "(OpenSim 4.6 as in 2017: about 100 steps/s, 10 s for 1000 steps; pip install 'l2r[opensim]')")
    p.add_argument("--progress-every", type=float, default=10.0, metavar="SECONDS",
                   help="print on stderr how far the episodes have come every this many seconds (0: never)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of lines")
    return p


class Progress:
    """Prints on stderr, at most every `every` seconds, how far a batch of episodes has come."""

    def __init__(self, episodes: int, every: float):
        self.episodes, self.every = episodes, every
        self.steps = self.ended = 0
        self._start = self._shown = time.monotonic()

    def step(self, ended: bool) -> None:
        self.steps += 1
        self.ended += ended
        now = time.monotonic()
        if self.every > 0 and now - self._shown >= self.every:
            self._shown = now
            print(f"l2r eval: {self.ended} of {self.episodes} episodes done, {self.steps} steps of 0.01 s "
                  f"in {now - self._start:.0f} s", file=sys.stderr, flush=True)


class Counted(gymnasium.Wrapper):
    """Tells a Progress about every step of the env it wraps."""

    def __init__(self, env: gymnasium.Env, progress: Progress):
        super().__init__(env)
        self.progress = progress

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.progress.step(terminated or truncated)
        return obs, reward, terminated, truncated, info


def evaluate(policy, episodes: int, seed: int, difficulty: int, action_repeat: int,
             env_id: str = "l2r/Run-v0", progress_every: float = 0.0) -> list[tuple[float, float, int]]:
    """(return, distance, steps) of ``episodes`` deterministic episodes, all stepped as one batch;
    progress on stderr every ``progress_every`` seconds (0: none)."""
    progress = Progress(episodes, progress_every)
    envs = [Counted(gymnasium.make(env_id, difficulty=difficulty), progress) for _ in range(episodes)]
    if action_repeat > 1:
        envs = [ActionRepeat(env, action_repeat) for env in envs]
    try:
        return run_deterministic(policy, envs, [seed + i for i in range(episodes)])
    finally:
        for env in envs:
            env.close()


def cli(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.episodes < 1 or (args.action_repeat is not None and args.action_repeat < 1) or args.progress_every < 0:
        print("l2r eval: --episodes and --action-repeat must be at least 1, --progress-every at least 0",
              file=sys.stderr)
        return 2
    try:
        checkpoint = load_checkpoint(args.checkpoint)
    except CheckpointError as e:
        print(f"l2r eval: {e}", file=sys.stderr)
        return 1
    action_repeat = args.action_repeat or checkpoint.action_repeat or DEFAULT_ACTION_REPEAT
    if checkpoint.action_repeat is None and args.action_repeat is None:
        print(f"l2r eval: {checkpoint.path} does not say which action repeat training used; assuming "
              f"{DEFAULT_ACTION_REPEAT} (--action-repeat sets it)", file=sys.stderr)
    elif args.action_repeat and checkpoint.action_repeat and args.action_repeat != checkpoint.action_repeat:
        print(f"l2r eval: --action-repeat {args.action_repeat}, while training used {checkpoint.action_repeat}",
              file=sys.stderr)
    torch.set_num_threads(1)
    try:
        results = evaluate(checkpoint.policy(), args.episodes, args.seed, args.difficulty, action_repeat,
                           args.env_id, args.progress_every)
    except ImportError as e:  # a simulator that is not installed
        print(f"l2r eval: {e}", file=sys.stderr)
        return 1
    distances = [r[1] for r in results]
    if args.json:
        print(json.dumps({
            "checkpoint": str(checkpoint.path), "version": checkpoint.version, "updates": checkpoint.updates,
            "env_id": args.env_id, "difficulty": args.difficulty, "action_repeat": action_repeat, "seeds": [args.seed + i for i in range(args.episodes)],
            "distances": distances, "returns": [r[0] for r in results], "lengths": [r[2] for r in results],
            "mean_distance": sum(distances) / len(distances),
        }))
        return 0
    print(f"{checkpoint.path}: policy version {checkpoint.version}, {checkpoint.updates} updates, "
          f"{args.env_id}, difficulty {args.difficulty}, action repeat {action_repeat}")
    for i, (ret, distance, length) in enumerate(results):
        print(f"episode {i} (seed {args.seed + i}): distance {distance:7.3f} m  return {ret:8.3f}  steps {length}")
    print(f"mean distance {sum(distances) / len(distances):.3f} m over {len(distances)} episodes")
    return 0
