"""`l2r eval`: deterministic episodes of a trained policy, the task's score per episode (l2r.families):
the distance on the runner, the last image's PSNR to its goal on a photo task, the return on another task."""

from __future__ import annotations

import argparse
import json
import sys
import time

import gymnasium
import numpy as np
import torch

import l2r.sim  # noqa: F401  (registers l2r/Run-v0 and l2r/RunOpenSim-v0)
from l2r.actors.actor import (
    ActorConfig, EpisodeResult, ObservationError, make_task, observation_spec, run_deterministic,
)
from l2r.actors.frame_stack import frame_stack_of
from l2r.config import CommandParser
from l2r.families import PIXELS, RUNNER, family_of, score_of
from l2r.learner.checkpoint import CheckpointError, load_checkpoint
from l2r.photo.env import GOALS
from l2r.protocol import ObservationSpec, ProtocolError
from l2r.sim.wrappers import ActionRepeat
from l2r.spaces import photo_goals_option

DEFAULT_ACTION_REPEAT = 3  # the runner's recipe's and l2r-actor's; for checkpoints that do not say


def build_parser() -> argparse.ArgumentParser:
    p = CommandParser(
        prog="l2r eval",
        description="Run deterministic episodes (the policy's mean action) of a learner checkpoint "
                    "and print the score of each: the distance the runner's pelvis travelled, the last image's "
                    "PSNR to its goal on a photo task (l2r/PhotoTune-v0), or the return on another task "
                    "(--env-id Hopper-v5). Distances to compare with the 2017 challenge's are stated with "
                    "--env-id l2r/RunOpenSim-v0: the episodes then run on OpenSim 4.6, the simulator of 2017, "
                    "rather than on the MuJoCo port.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    p.add_argument("checkpoint", metavar="CHECKPOINT_OR_RUN_DIR",
                   help="a checkpoint file, or a run directory of `l2r up` (uses its learner checkpoint)")
    p.add_argument("--episodes", type=int, default=5, help="episodes to run, on seeds S, S+1, ...")
    p.add_argument("--seed", type=int, default=0, help="seed S of the first episode")
    p.add_argument("--difficulty", type=int, choices=(0, 1, 2), default=0,
                   help="the runner's: 0 flat, 1 obstacles, 2 obstacles and random psoas strengths")
    p.add_argument("--action-repeat", type=int,
                   help="env steps per action (of 0.01 s on the runner); default: what the checkpoint says training "
                        f"used ({DEFAULT_ACTION_REPEAT} for checkpoints that do not say)")
    p.add_argument("--env-id", default="l2r/Run-v0",
                   help="gymnasium id of the environment: l2r/Run-v0 (the MuJoCo port), l2r/RunOpenSim-v0 "
                        "(OpenSim 4.6 as in 2017: about 100 steps/s, 10 s for 1000 steps; pip install 'l2r[opensim]'), "
                        "or the task another checkpoint was trained on (`l2r up --env-id`), such as Hopper-v5")
    p.add_argument("--progress-every", type=float, default=10.0, metavar="SECONDS",
                   help="print on stderr how far the episodes have come every this many seconds (0: never)")
    p.add_argument("--photo-goals", choices=GOALS,
                   help="the photo tuner's goals: random, looks (another scene's look) or mixed; unset, the task's "
                        "own, random")
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
            print(f"l2r eval: {self.ended} of {self.episodes} episodes done, {self.steps} env steps "
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


class WrongTask(ValueError):
    """A policy for other observations or actions than the task's: a checkpoint of another task."""


def evaluate(policy, episodes: int, seed: int, difficulty: int, action_repeat: int,
             env_id: str = "l2r/Run-v0", progress_every: float = 0.0,
             photo_goals: str | None = None) -> list[EpisodeResult]:
    """The results of ``episodes`` deterministic episodes, all stepped as one batch
    as an evaluator of `l2r up` steps them; progress on stderr every ``progress_every`` seconds (0: none);
    the photo tuner's goals ``photo_goals`` (None: its own)."""
    progress = Progress(episodes, progress_every)
    trained = (ObservationSpec.from_policy_spec(policy.spec), policy.spec["act_dim"])
    frames = trained[0].fields.get("pixels")
    # A camera task renders frames of the size the policy was trained on (l2r up --image-size).
    image_size = frames.shape[-1] if family_of(env_id) == PIXELS and frames is not None else None
    envs = [Counted(make_task(env_id, difficulty, image_size=image_size, photo_goals=photo_goals), progress)
            for _ in range(episodes)]
    if action_repeat > 1:
        envs = [ActionRepeat(env, action_repeat) for env in envs]
    try:
        task = (observation_spec(envs[0], env_id), int(np.prod(envs[0].action_space.shape)))
        if task != trained:
            raise WrongTask(f"the policy takes observations {trained[0]} and gives {trained[1]} actions, "
                            f"{env_id} gives {task[0]} and takes {task[1]}: --env-id names the task it trained on")
        # The runner's blow-up check, as in training; `l2r up` turns it off on other tasks.
        max_speed = ActorConfig.max_speed if family_of(env_id) == RUNNER else 0.0
        return run_deterministic(policy, envs, [seed + i for i in range(episodes)], max_speed=max_speed,
                                 frame_stack=frame_stack_of(policy.spec), env_id=env_id)
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
        photo_goals_option(args.env_id, args.photo_goals)
    except ValueError as e:
        print(f"l2r eval: --photo-goals {args.photo_goals}: {e}", file=sys.stderr)
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
        episodes = evaluate(checkpoint.policy(), args.episodes, args.seed, args.difficulty, action_repeat,
                            args.env_id, args.progress_every, args.photo_goals)
    except ImportError as e:  # a simulator that is not installed
        print(f"l2r eval: {e}", file=sys.stderr)
        return 1
    except (WrongTask, ProtocolError) as e:  # a policy of another task, or a spec that says no task
        print(f"l2r eval: {checkpoint.path}: {e}", file=sys.stderr)
        return 1
    except ObservationError as e:
        print(f"l2r eval: {e}", file=sys.stderr)
        return 1
    score = score_of(args.env_id)
    mean = sum(map(score.of, episodes)) / len(episodes)
    if args.json:
        print(json.dumps({
            "checkpoint": str(checkpoint.path), "version": checkpoint.version, "updates": checkpoint.updates,
            "env_id": args.env_id, "difficulty": args.difficulty, "action_repeat": action_repeat, "seeds": [args.seed + i for i in range(args.episodes)],
            "distances": [e.distance for e in episodes], "returns": [e.episode_return for e in episodes],
            "lengths": [e.length for e in episodes],
            **({"psnrs_db": [e.psnr_db for e in episodes]} if score.field == "psnr_db" else {}),
            "score": score.name, f"mean_{score.name}": mean,
        }))
        return 0
    runner = family_of(args.env_id) == RUNNER
    print(f"{checkpoint.path}: policy version {checkpoint.version}, {checkpoint.updates} updates, "
          f"{args.env_id}{f', difficulty {args.difficulty}' if runner else ''}, action repeat {action_repeat}")
    for i, e in enumerate(episodes):
        also = "" if score.name == "return" else f"  return {e.episode_return:8.3f}"
        print(f"episode {i} (seed {args.seed + i}): {score.text(score.of(e), '7.3f')}{also}  steps {e.length}")
    print(f"mean {score.text(mean, '.3f')} over {len(episodes)} episodes")
    return 0
