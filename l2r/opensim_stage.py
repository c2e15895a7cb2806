"""The runner's OpenSim stage (`l2r up --opensim-stage SECONDS`): the port's actors while the gait
forms, then the learner goes on from its checkpoint on OpenSim's body alone.

A gait formed on the MuJoCo port parts from OpenSim as it speeds up: its small errors grow into a
fall in the simulator that judges (docs/training.md). A few thousand OpenSim steps, learnt from
hard (an empty replay, many samples per step), put the two back in agreement; what the port's
fast actors do best, forming the gait, they do first. The stage is a run of its own beside the
port's, RUN_DIR-opensim: its own replay, metrics and best.pt, its learner started from the port
stage's newest checkpoint (networks, optimizers, temperature). Its actor goes on along the job's
course from where the port's actors left it: with flat ground alone, two runs from scratch kept
policies of 14-17 m in OpenSim that had lost the obstacle course the port's stage had learnt.
"""

from __future__ import annotations

import argparse
import importlib.util
from pathlib import Path

from l2r.learner.checkpoint import find_checkpoint
from l2r.run_metrics import RunCounters
from l2r.sim import PORT_ID
from l2r.sim.opensim_env import MISSING_OPENSIM

SUFFIX = "-opensim"
"""The OpenSim stage's run directory is the port stage's, named with this after it."""

# What the stage trains with, whatever the port's stage was given (docs/training.md, "OpenSim's own
# experience once the port's gait has parted"): one actor, on OpenSim; an OpenSim actor steps its
# four bodies at 10-16 env steps/s on 2 cores, so learning starts after 2,000 of its transitions
# and takes 128 samples of each one, the actor held back while it is ahead.
STAGE = dict(actors=1, opensim_actors=1, replay_shards=1, min_replay=2_000, samples_per_insert=128.0,
             hold_actors=True)


def refusal(args: argparse.Namespace) -> str | None:
    """Why a job cannot take --opensim-stage, in one line, or None."""
    stage = args.opensim_stage
    if stage < 0:
        return f"--opensim-stage is seconds of the port's stage, at least 0, got {stage:g}"
    if not stage:
        return None
    if args.env_id != PORT_ID:
        return f"--opensim-stage goes on from the port ({PORT_ID}) to OpenSim, not from {args.env_id}"
    if args.algo not in ("sac", "td3") or args.colocated:
        return "--opensim-stage goes on through a replay table: --algo sac or td3, not --colocated"
    if args.env_steps:
        return "--opensim-stage counts time: give the job's budget as --seconds, not --env-steps"
    if args.seconds and args.seconds <= stage:
        return f"--opensim-stage {stage:g} leaves no time of --seconds {args.seconds:g} for OpenSim's stage"
    if importlib.util.find_spec("opensim") is None:
        return f"--opensim-stage: {MISSING_OPENSIM}"
    return None


def run_dir_of(port_run: Path) -> Path:
    return port_run.with_name(port_run.name + SUFFIX)


def port_stage_over(args: argparse.Namespace, counters: RunCounters) -> bool:
    """Whether a job with an OpenSim stage has spent the port's time, by its port run's counters."""
    return bool(args.opensim_stage) and counters.time >= args.opensim_stage


def stage_args(args: argparse.Namespace, port_run: Path) -> argparse.Namespace:
    """The OpenSim stage's flags: the job's, the stage's settings over them, the rest of --seconds,
    the learner from the port's checkpoint, the course from a port actor's share of its env steps,
    and --resume of the stage's directory once it exists."""
    run_dir = run_dir_of(port_run)
    started = (run_dir / "launch.json").exists()
    return argparse.Namespace(**vars(args) | STAGE | dict(
        seconds=args.seconds - args.opensim_stage if args.seconds else 0.0, opensim_stage=0.0,
        init_from=find_checkpoint(port_run).resolve(), resume=run_dir if started else None,
        course_steps_before=RunCounters.read(port_run / "metrics").env_steps // args.actors))
