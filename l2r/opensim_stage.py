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
import json
import logging
import threading
from pathlib import Path

import zenoh

from l2r.learner.checkpoint import find_checkpoint
from l2r.protocol import EpisodeSummary, Keys, watched
from l2r.run_metrics import RunCounters
from l2r.sim import OPENSIM_ID, PORT_ID
from l2r.sim.opensim_env import MISSING_OPENSIM

log = logging.getLogger("l2r.up")

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


def parting_refusal(args: argparse.Namespace, evaluator_env_ids: list[str | None]) -> str | None:
    """Why a job cannot take --opensim-stage-parting (given the env id of each of its evaluators),
    in one line, or None."""
    ratio = args.opensim_stage_parting
    if not ratio:
        return None
    if not 0 < ratio <= 1:
        return f"--opensim-stage-parting is a fraction of the port's distance in (0, 1], got {ratio:g}"
    if not args.opensim_stage:
        return "--opensim-stage-parting ends the port's stage early: give its latest end as --opensim-stage SECONDS"
    if not {OPENSIM_ID, PORT_ID} <= set(evaluator_env_ids):
        return (f"--opensim-stage-parting sets OpenSim's evaluations against the port's: give evaluators in both, "
                f"--evaluators 2 --eval-env-id {OPENSIM_ID} --eval-env-id {PORT_ID}")
    return None


def run_dir_of(port_run: Path) -> Path:
    return port_run.with_name(port_run.name + SUFFIX)


def port_stage_over(args: argparse.Namespace, counters: RunCounters) -> bool:
    """Whether a job with an OpenSim stage has spent the port's time, by its port run's counters."""
    return bool(args.opensim_stage) and counters.time >= args.opensim_stage


def port_stage_ended(args: argparse.Namespace, port_run: Path) -> bool:
    """Whether the port's stage is over: its time spent, or its gait parted from OpenSim."""
    return port_stage_over(args, RunCounters.read(port_run / "metrics")) or parted(port_run)


def parted(port_run: Path) -> bool:
    """Whether the port's stage ended as its gait parted from OpenSim (--opensim-stage-parting), by
    the outcome in its summary.json."""
    try:
        return json.loads((port_run / "summary.json").read_text())["outcome"].startswith(PARTED)
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return False


def stage_args(args: argparse.Namespace, port_run: Path) -> argparse.Namespace:
    """The OpenSim stage's flags: the job's, the stage's settings over them, the rest of --seconds
    after the port's stage (which parting may have ended early), the learner from the port's
    checkpoint, the course from a port actor's share of its env steps, and --resume of the stage's
    directory once it exists."""
    run_dir = run_dir_of(port_run)
    started = (run_dir / "launch.json").exists()
    port = RunCounters.read(port_run / "metrics")
    return argparse.Namespace(**vars(args) | STAGE | dict(
        seconds=args.seconds - min(args.opensim_stage, port.time) if args.seconds else 0.0,
        opensim_stage=0.0, opensim_stage_parting=0.0,
        init_from=find_checkpoint(port_run).resolve(), resume=run_dir if started else None,
        course_steps_before=port.env_steps // args.actors))


PARTED = "the port's gait parted from OpenSim"
"""How a port's stage ended early by --opensim-stage-parting begins, in summary.json's outcome."""
PARTED_ROUNDS = 3  # OpenSim's rounds in a row under the fraction: single dips come and go (6 of 98 in two runs)
PAIRED_WITHIN = 10  # policy versions between an OpenSim round and the port's it is set against
GAIT = 6.0  # metres the port's round must average for there to be a gait to part from


class Parting:
    """Sets each round of OpenSim's evaluators against the port's round of the nearest policy
    version (at most PAIRED_WITHIN apart) and says when PARTED_ROUNDS in a row, where the port's ran
    a gait, fell under `ratio` of the port's: the moment the port's gait no longer carries over."""

    def __init__(self, ratio: float, episodes_per_round: int, simulators: dict[int, str]):
        self.ratio, self.episodes_per_round = ratio, episodes_per_round
        self.simulators = simulators  # actor id -> env id
        self.rounds: dict[str, dict[int, list[float]]] = {OPENSIM_ID: {}, PORT_ID: {}}  # version -> distances
        self.waiting: list[int] = []  # OpenSim's complete rounds not yet set against the port's, by version
        self.under = 0  # OpenSim's rounds in a row under the ratio
        self.verdict: str | None = None
        self._lock = threading.Lock()

    def listen(self, session: zenoh.Session, keys: Keys) -> zenoh.Subscriber:
        return session.declare_subscriber(keys.all_episodes, self._on_episode)

    def _on_episode(self, sample: zenoh.Sample) -> None:
        episode = watched(sample, EpisodeSummary)
        if episode is not None and episode.evaluation:
            self.add(self.simulators.get(episode.actor_id), episode.policy_version, episode.distance)

    def add(self, simulator: str | None, version: int, distance: float) -> None:
        """One evaluation episode of `simulator`'s evaluators."""
        if simulator not in self.rounds:
            return
        with self._lock:
            distances = self.rounds[simulator].setdefault(version, [])
            distances.append(distance)
            if len(distances) != self.episodes_per_round:
                return
            if simulator == OPENSIM_ID:
                self.waiting = sorted(self.waiting + [version])
            self._judge()

    def _judge(self) -> None:
        port = {v: sum(d) / len(d) for v, d in self.rounds[PORT_ID].items() if len(d) == self.episodes_per_round}
        while self.waiting and port:
            version = self.waiting[0]
            nearest = min(port, key=lambda v: (abs(v - version), v))
            if abs(nearest - version) > PAIRED_WITHIN and max(port) < version + PAIRED_WITHIN:
                return  # the port's rounds come in rising versions: one near it may still come
            self.waiting.pop(0)
            if abs(nearest - version) > PAIRED_WITHIN or port[nearest] < GAIT:
                continue
            opensim = sum(self.rounds[OPENSIM_ID][version]) / self.episodes_per_round
            self.under = self.under + 1 if opensim < self.ratio * port[nearest] else 0
            if self.under:
                log.info("OpenSim's evaluation of v%d, %.2f m, under %g of the port's of v%d, %.2f m: %d of %d in a row "
                         "ends the port's stage", version, opensim, self.ratio, nearest, port[nearest], self.under,
                         PARTED_ROUNDS)
            if self.under >= PARTED_ROUNDS and self.verdict is None:
                self.verdict = (f"{PARTED}: {self.under} OpenSim evaluations in a row under {self.ratio:g} of the "
                                f"port's, the last v{version} {opensim:.2f} m against v{nearest} {port[nearest]:.2f} m")
