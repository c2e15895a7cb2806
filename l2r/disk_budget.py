"""What a run of `l2r up` may write, estimated before it starts, and the free space it keeps.

The estimate is the most each part can grow to, from the run's flags (docs/training.md, "Disk use"):

    replay        for each replay shard, 3 x its table's bytes (l2r.replay.storage.storage_bytes)
                  for its --capacity transitions, or --env-steps if fewer, or what a run of
                  --seconds can make at MAX_ENV_STEPS_PER_S per actor that feeds it if fewer
                  still: the snapshot, the next one written beside it before the rename, and the
                  write-ahead log between them
    episodes      each actor's and evaluator's log budget (l2r-actor --log-budget-mb, 256 MB
                  unless an --actor-arg sets it), or what it can write in --seconds at
                  MAX_EPISODE_BYTES_PER_S if less: none with --no-episode-logs or on a task whose
                  episodes are not logged
    checkpoints   --keep-checkpoints, the one being written and best.pt, each four float32 copies
                  of the vector networks' parameters (the networks, their targets or Adam's two
                  moments); a camera task's encoder is not counted
    metrics       16 MB an hour of --seconds (a 30-minute run of the runner's recipe wrote 8 MB),
                  an hour's worth when the run has no time limit

`l2r up` refuses a run whose estimate exceeds the free space (less what a resumed run directory
already holds), unless --force. While it runs, its status line shows the free space once it is
below `LOW_FACTOR` reserves, and it stops the job when the free space falls below
`reserve_bytes`: room for the learner's last checkpoint, so that the newest one is whole. In
between, the run sheds what it needs least (`Shedding`): below `LOW_FACTOR` reserves the actors
begin no logged episode (l2r-actor --log-min-free-mb), below `EVENTS_FACTOR` reserves no
TensorBoard events are written (the CSV files go on); checkpoints and the replay's log are written
to the end.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from l2r.actors.__main__ import parse_settings as actor_settings
from l2r.durable import MB
from l2r.learner.checkpoint import checkpoint_path
from l2r.protocol.keys import shard_of
from l2r.replay.__main__ import ReplaySettings
from l2r.replay.__main__ import parse_settings as replay_settings
from l2r.replay.storage import StorageConfig, storage_bytes
from l2r.spaces import task_spaces
from l2r.supervise import Child

log = logging.getLogger(__name__)

METRICS_BYTES_PER_HOUR = 16 * MB
# Ceilings of a time-limited run (docs/training.md): the fastest actor measured made 5,073 env
# steps/s (PPO on Hopper-v5, four envs; the runner's ~2,000), and the runner's job logged 454 MB
# of episodes in 30 minutes, 0.25 MB/s for its three processes: four times that per process.
MAX_ENV_STEPS_PER_S = 5_000
MAX_EPISODE_BYTES_PER_S = 1 * MB
RESERVE_MARGIN = 1 * MB  # beyond the last checkpoint: summary.json, the last log lines
LOW_FACTOR = 10  # the status line shows the free space once it is below this many reserves, and episodes are shed
EVENTS_FACTOR = 5  # below this many reserves TensorBoard events are shed too


def _mlp_parameters(widths: list[int]) -> int:
    return sum(a * b + b for a, b in zip(widths, widths[1:]))


def checkpoint_bytes(obs_dim: int, act_dim: int, hidden: str) -> int:
    """A checkpoint's size: four float32 copies of an actor (mean and log-std heads) and twin critics."""
    layers = [int(w) for w in hidden.split(",")]
    actor = _mlp_parameters([obs_dim, *layers, 2 * act_dim])
    critics = 2 * _mlp_parameters([obs_dim + act_dim, *layers, 1])
    return 4 * 4 * (actor + critics)


def estimate(args: argparse.Namespace, recipe: dict, children: list[Child]) -> dict[str, int]:
    """Bytes the run may write, by part (see the module docstring), from the processes' command lines."""
    actors = [actor_settings(c.argv[3:]) for c in children if c.argv[2] == "l2r.actors"]
    training = [s for s in actors if not s.evaluate]
    replay = 0
    for shard in (replay_settings(c.argv[3:]) for c in children if c.argv[2] == "l2r.replay"):
        feeding = sum(1 for s in training if shard_of(s.actor_id, s.num_shards) == shard.shard)
        replay += 3 * _table_bytes(shard, feeding, args)
    budgets = [int(s.log_budget_mb * 2**20) for s in actors if s.episode_log_dir is not None]
    if args.seconds:
        budgets = [min(budget, int(args.seconds * MAX_EPISODE_BYTES_PER_S)) for budget in budgets]
    episodes = sum(budgets)
    checkpoints = (args.keep_checkpoints + 2) * task_checkpoint_bytes(args.env_id, recipe["hidden"])
    metrics = int(METRICS_BYTES_PER_HOUR * (args.seconds or 3600) / 3600)
    return {"replay": replay, "episode logs": episodes, "checkpoints": checkpoints, "metrics": metrics}


def _table_bytes(shard: ReplaySettings, actors: int, args: argparse.Namespace) -> int:
    """The bytes of a replay shard's table once it holds what `actors` can send it in the run's budget."""
    transitions = min(shard.capacity, args.env_steps) if args.env_steps else shard.capacity
    if args.seconds:  # a run of a few minutes cannot fill a large table
        transitions = min(transitions, int(args.seconds * MAX_ENV_STEPS_PER_S * actors))
    if not transitions:  # no replay table (the queue alone, which is not snapshotted)
        return 0
    return storage_bytes(StorageConfig(transitions, shard.obs_dim, shard.act_dim, shard.side_fraction,
                                       observation=shard.observation_spec()))


def already_written(run_dir: Path | None) -> int:
    """Bytes of the files a resumed run directory holds (they count in its estimate)."""
    if run_dir is None or not run_dir.is_dir():
        return 0
    return sum(p.stat().st_size for p in run_dir.rglob("*") if p.is_file())


def task_checkpoint_bytes(env_id: str, hidden: str) -> int:
    """`checkpoint_bytes` of a task's networks."""
    observation, act_dim = task_spaces(env_id)
    return checkpoint_bytes(observation.vector_width or 0, act_dim, hidden)


def reserve_bytes(run_dir: Path, estimated_checkpoint: int) -> int:
    """Free space below which the run stops: its newest checkpoint's size (or the estimate before
    there is one) and a margin, so that the learner's last save can be written whole."""
    newest = checkpoint_path(run_dir)
    size = newest.stat().st_size if newest.is_file() else estimated_checkpoint
    return size + int(RESERVE_MARGIN)


def describe(parts: dict[str, int]) -> str:
    """`1.2 GB (replay 870 MB, episode logs 2147 MB, ...)`."""
    return f"{sum(parts.values()) / MB:,.0f} MB (" + ", ".join(
        f"{name} {size / MB:,.0f} MB" for name, size in parts.items()) + ")"


class Shedding:
    """What the run stops writing as its disk fills, what it needs least first; each change is
    logged once."""

    PARTS = (("episode logs", LOW_FACTOR), ("TensorBoard events", EVENTS_FACTOR))

    def __init__(self, where: Path):
        self.where = where
        self.shed: set[str] = set()

    def update(self, free: int, reserve: int) -> set[str]:
        """The parts shed at `free` bytes free, the learner's last checkpoint taking `reserve`."""
        for part, factor in self.PARTS:
            floor = factor * reserve
            if free < floor and part not in self.shed:
                self.shed.add(part)
                log.warning("disk low at %s: %.1f MB free, below %.1f MB: %s are not written until there is room "
                            "(checkpoints and the replay's log go on)", self.where, free / MB, floor / MB, part)
            elif free >= floor and part in self.shed:
                self.shed.discard(part)
                log.info("%.1f MB free at %s again: writing %s", free / MB, self.where, part)
        return self.shed
