"""``l2r-replay``: command line of the replay server (see ``l2r.replay.server``)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

from l2r.protocol import (
    DefaultsHelpFormatter, add_daemon_arguments, config_from_args, configure_logging, parse_daemon_args,
)
from l2r.replay.rate_limiter import RateLimiter
from l2r.replay.server import ServerConfig, main
from l2r.replay.storage import StorageConfig


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="l2r-replay", formatter_class=DefaultsHelpFormatter,
        description="Replay server of an l2r run: stores experience chunks from actors and answers "
                    "learners' sample queries over Zenoh (uniform or prioritized), with a "
                    "samples-per-insert rate limiter and periodic atomic snapshots.",
        epilog="Example: l2r-replay --run exp1 --listen tcp/0.0.0.0:7447 --snapshot-dir runs/exp1/replay")
    add_daemon_arguments(p)
    g = p.add_argument_group("shard")
    g.add_argument("--shard", type=int, default=0, help="index of this shard; actor i feeds shard i %% num-shards")
    g.add_argument("--num-shards", type=int, default=1, help="number of replay shards of the run")
    g = p.add_argument_group("storage")
    g.add_argument("--capacity", type=int, default=1_000_000, help="transitions kept, oldest evicted first")
    g.add_argument("--obs-dim", type=int, default=41, help="observation width; other widths are rejected")
    g.add_argument("--act-dim", type=int, default=18, help="action width; other widths are rejected")
    g.add_argument("--side-fraction", type=float, default=0.125,
                   help="rows for next observations at chunk and episode ends, as a fraction of capacity")
    g.add_argument("--priority-exponent", type=float, default=0.6, help="alpha of prioritized sampling")
    g.add_argument("--seed", type=int, default=0, help="sampling seed")
    g = p.add_argument_group("rate limiter")
    g.add_argument("--min-size", type=int, default=1000, help="transitions stored before sampling starts")
    g.add_argument("--samples-per-insert", type=float, default=0.0,
                   help="sampled transitions allowed per inserted one; 0 = no ratio limit")
    g.add_argument("--error-buffer", type=float, default=10_000.0,
                   help="slack around the ratio, in sampled transitions")
    g = p.add_argument_group("persistence and reporting")
    g.add_argument("--snapshot-dir", type=Path, help="directory for snapshots (none: memory only)")
    g.add_argument("--snapshot-interval", type=float, default=120.0,
                   help="seconds between snapshots = the most experience a crash can lose")
    g.add_argument("--no-restore", action="store_true", help="do not load the snapshot at start")
    g.add_argument("--stats-interval", type=float, default=10.0, help="seconds between stats reports")
    return p


def cli(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parse_daemon_args(parser, argv)
    if not 0 <= args.shard < args.num_shards:
        parser.error(f"--shard {args.shard} must be in [0, --num-shards {args.num_shards})")
    if args.capacity < 2 or args.obs_dim < 1 or args.act_dim < 1 or not 0 < args.side_fraction <= 1:
        parser.error("--capacity >= 2, --obs-dim and --act-dim >= 1, 0 < --side-fraction <= 1")
    configure_logging(args.log_level)
    server = ServerConfig(args.run, args.shard, args.num_shards, args.snapshot_dir, args.snapshot_interval,
                          not args.no_restore, args.stats_interval)
    storage = StorageConfig(args.capacity, args.obs_dim, args.act_dim, args.side_fraction,
                            args.priority_exponent, args.seed)
    limiter = RateLimiter(args.min_size, args.samples_per_insert, args.error_buffer)
    return main(server, storage, limiter, config_from_args(args))


if __name__ == "__main__":
    sys.exit(cli())
