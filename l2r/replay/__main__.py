"""``l2r-replay``: command line of the replay server (see ``l2r.replay.server``)."""

from __future__ import annotations

import os
import sys
from typing import Literal, Sequence

from l2r.config import (
    CommandParser, FilePath, StartupFailure, UsageError, load, run_command, setting, settings_parser,
)
from l2r.protocol import DaemonSettings, ProtocolError, configure_logging, reuse_large_buffers
from l2r.protocol.observations import ObservationSpec
from l2r.replay.queue import QueueConfig
from l2r.replay.rate_limiter import RateLimiter
from l2r.replay.sequences import MAX_ACTORS
from l2r.replay.server import ServerConfig, main
from l2r.replay.storage import StorageConfig, storage_bytes

SHARD, STORAGE, LIMITER, PERSISTENCE = "shard", "storage", "rate limiter", "persistence and reporting"
QUEUE = "queue table (on-policy learners: first in, first out, each transition given once)"
QUEUE_DEFAULTS = QueueConfig()


class ReplaySettings(DaemonSettings):
    shard: int = setting(0, "index of this shard; actor i feeds shard i % num-shards", group=SHARD, ge=0)
    num_shards: int = setting(1, "number of replay shards of the run", group=SHARD, ge=1)
    max_actors: int = setting(MAX_ACTORS, "actor ids this shard keeps sequence records of; chunks of further "
                              "ids are rejected (too_many_actors), so a peer inventing ids cannot exhaust "
                              "its memory", group=SHARD, ge=1)
    capacity: int = setting(1_000_000, "transitions the replay table keeps, oldest evicted first, at most "
                            "2^31 - 1 (trajectory links are 32-bit); 0: no replay table (a shard with the queue "
                            "alone)", group=STORAGE, ge=0, lt=2**31)
    obs_dim: int = setting(41, "width of the float32 vector observation (the field state), when --observation is "
                           "not given; chunks of another width are rejected", group=STORAGE, ge=1)
    observation: str | None = setting(
        None, "the observation stored, as fields 'name: dtype[shape]' separated by commas, dtype uint8 or float32, "
        "images channels first, e.g. 'pixels: uint8[3, 84, 84], state: float32[24]'; chunks of other fields, "
        "dtypes or shapes are rejected. Default: 'state: float32[<obs-dim>]'", group=STORAGE, metavar="SPEC")
    act_dim: int = setting(18, "action width; other widths are rejected", group=STORAGE, ge=1)
    side_fraction: float = setting(0.125, "rows for next observations at chunk and episode ends, as a fraction "
                                   "of capacity", group=STORAGE, gt=0, le=1)
    priority_exponent: float = setting(0.6, "alpha of prioritized sampling", group=STORAGE, ge=0)
    seed: int = setting(0, "sampling seed", group=STORAGE)
    min_size: int = setting(1000, "transitions stored before sampling starts", group=LIMITER, ge=0)
    samples_per_insert: float = setting(0.0, "sampled transitions allowed per inserted one; 0 = no ratio limit",
                                        group=LIMITER, ge=0)
    error_buffer: float = setting(10_000.0, "slack around the ratio, in sampled transitions", group=LIMITER, ge=0)
    hold_actors: bool = setting(False, "with --samples-per-insert: ask the actors to wait while they are more "
                                "than twice the error buffer ahead of the learner, so the ratio holds both ways",
                                group=LIMITER)
    queue_capacity: int = setting(QUEUE_DEFAULTS.capacity, "transitions the queue table holds before it holds "
                                  "the actors back or drops (see --queue-when-full); 0: no queue table",
                                  group=QUEUE, ge=0)
    queue_max_lag: int = setting(QUEUE_DEFAULTS.max_lag, "transitions acted by a policy more than this many "
                                 "versions behind the learner's newest are dropped (and counted)", group=QUEUE, ge=0)
    queue_when_full: Literal["hold", "drop"] = setting(
        QUEUE_DEFAULTS.when_full, "hold: ask the actors to wait until the learner takes a batch (what still arrives "
        "is kept up to twice the capacity); drop: the oldest chunks make room", group=QUEUE)
    snapshot_dir: FilePath | None = setting(None, "directory for snapshots (default: none, memory only)",
                                            group=PERSISTENCE)
    snapshot_interval: float = setting(120.0, "seconds between snapshots = the most experience a crash can lose",
                                       group=PERSISTENCE, gt=0)
    no_restore: bool = setting(False, "do not load the snapshot at start", group=PERSISTENCE)
    no_wal: bool = setting(False, "write no write-ahead log, for speed over durability: acks then mean stored in "
                           "memory, and a crash loses what came since the last snapshot", group=PERSISTENCE)
    stats_interval: float = setting(10.0, "seconds between stats reports", group=PERSISTENCE, gt=0)

    def check(self) -> None:
        if self.shard >= self.num_shards:
            raise UsageError(f"--shard {self.shard} must be below --num-shards {self.num_shards}")
        if self.capacity == 1 or not (self.capacity or self.queue_capacity):
            raise UsageError(f"--capacity {self.capacity}: the replay table needs at least 2 transitions, and a "
                             f"shard with --capacity 0 needs a queue (--queue-capacity)")
        observation = self.observation_spec()
        if self.queue_capacity and observation.vector_width is None:
            raise UsageError(f"--queue-capacity {self.queue_capacity}: the queue table keeps the float32 vector "
                             f"alone, not --observation {observation}")

    def observation_spec(self) -> ObservationSpec:
        if self.observation is None:
            return ObservationSpec.vector(self.obs_dim)
        try:
            return ObservationSpec.parse(self.observation)
        except ProtocolError as e:
            raise UsageError(f"--observation: {e}") from None


def build_parser() -> CommandParser:
    return settings_parser(
        ReplaySettings, "l2r-replay",
        "Replay server of an l2r run: stores experience chunks from actors and answers learners' sample "
        "queries over Zenoh (uniform or prioritized), with a samples-per-insert rate limiter and periodic "
        "atomic snapshots.",
        "Example: l2r-replay --run exp1 --listen tcp/0.0.0.0:7447 --snapshot-dir runs/exp1/replay")


def parse_settings(argv: Sequence[str] | None = None) -> ReplaySettings:
    return load(ReplaySettings, build_parser(), argv)


def available_memory() -> int:
    """Bytes a new allocation can have without swapping: MemAvailable on Linux, else physical memory."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def cli(argv: Sequence[str] | None = None) -> int:
    return run_command("l2r-replay", lambda: serve(parse_settings(argv)))


def serve(s: ReplaySettings) -> int:
    configure_logging(s.log_level)
    storage = StorageConfig(s.capacity, s.obs_dim, s.act_dim, s.side_fraction, s.priority_exponent, s.seed,
                            s.observation_spec())
    # The storage is allocated and touched at start: more than the free memory is an OOM kill, not an error.
    needed, available = storage_bytes(storage), available_memory()
    if needed > available:
        raise StartupFailure(f"--capacity {s.capacity} needs {needed / 2**30:.1f} GiB of memory; "
                             f"{available / 2**30:.1f} GiB is available")
    server = ServerConfig(s.run, s.shard, s.num_shards, s.snapshot_dir, s.snapshot_interval, not s.no_restore,
                          s.stats_interval, write_ahead_log=not s.no_wal, max_actors=s.max_actors)
    limiter = RateLimiter(s.min_size, s.samples_per_insert, s.error_buffer, s.hold_actors)
    queue = QueueConfig(s.queue_capacity, s.queue_max_lag, s.queue_when_full)
    reuse_large_buffers()  # before Zenoh's threads start: replies of camera frames are 20-30 MB each
    return main(server, storage, limiter, s.zenoh_session_config(), queue_config=queue)


if __name__ == "__main__":
    sys.exit(cli())
