"""``l2r-learner``: command line of the SAC learner (see ``l2r.learner.daemon``)."""

from __future__ import annotations

import os

# Set before torch loads OpenMP: idle OpenMP workers then sleep instead of spinning. The learner
# shares cores with actors; spinning workers waste them, and when the cores are oversubscribed
# every parallel region waits for a descheduled spinner (measured: 3-4x fewer updates/s).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Sequence  # noqa: E402

from l2r.learner.daemon import LearnerConfig, main  # noqa: E402
from l2r.learner.distributed import DeviceUnavailable  # noqa: E402
from l2r.learner.sac import SACConfig  # noqa: E402
from l2r.protocol import add_daemon_arguments, config_from_args, configure_logging, parse_daemon_args  # noqa: E402

DEFAULTS = SACConfig()


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="l2r-learner",
        description="SAC learner of an l2r run: samples batches from the replay server(s) with several "
                    "requests in flight, trains twin critics, a tanh-Gaussian policy and the entropy "
                    "temperature, publishes versioned policy weights for actors, and checkpoints atomically.",
        epilog="Example: l2r-learner --run exp1 --connect tcp/127.0.0.1:7447 --run-dir runs/exp1 --resume\n"
               "Two data-parallel learners: add --world-size 2 --rank 0|1 --dist-url tcp://127.0.0.1:29500",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    add_daemon_arguments(p)

    g = p.add_argument_group("learner process")
    g.add_argument("--run-dir", type=Path, help="run directory; the checkpoint is <run-dir>/learner/checkpoint.pt "
                   "(default: runs/<run>)")
    g.add_argument("--resume", action="store_true", help="continue from the run directory's checkpoint if there "
                   "is one (networks, optimizers, alpha, version, counters)")
    g.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                   help="where to train; auto = CUDA if available (default: %(default)s)")
    g.add_argument("--threads", type=int, default=0, help="torch CPU threads; 0 = torch's default (default: %(default)s)")
    g.add_argument("--obs-dim", type=int, default=41, help="observation width (default: %(default)s)")
    g.add_argument("--act-dim", type=int, default=18, help="action width (default: %(default)s)")
    g.add_argument("--in-flight", type=int, default=4, help="sample requests kept in flight (default: %(default)s)")
    g.add_argument("--prioritized", action="store_true", help="prioritized sampling, |TD error| sent back as priority")
    g.add_argument("--priority-beta", type=float, default=0.4,
                   help="importance-weight exponent under prioritized sampling (default: %(default)s)")
    g.add_argument("--publish-every", type=int, default=50, help="updates between weight publications (default: %(default)s)")
    g.add_argument("--checkpoint-interval", type=float, default=60.0, help="seconds between checkpoints (default: %(default)s)")
    g.add_argument("--keep-checkpoints", type=int, default=3,
                   help="checkpoints kept: checkpoint.pt is the newest, checkpoint-<updates>.pt the newest N "
                        "(default: %(default)s)")
    g.add_argument("--action-repeat", type=int,
                   help="the actors' action repeat; stored in checkpoints so `l2r eval` steps the env as training "
                        "did (the learner itself does not use it)")
    g.add_argument("--metrics-interval", type=float, default=5.0, help="seconds between metrics reports (default: %(default)s)")
    g.add_argument("--max-updates", type=int, default=0, help="stop after this many updates in total; 0 = until stopped")
    g.add_argument("--seed", type=int, help="torch seed (each rank adds its rank)")

    g = p.add_argument_group("data parallel (torch.distributed; gloo on CPU, NCCL on CUDA)")
    g.add_argument("--world-size", type=int, default=int(os.environ.get("WORLD_SIZE", 1)),
                   help="number of learners (default: $WORLD_SIZE or 1)")
    g.add_argument("--rank", type=int, default=int(os.environ.get("RANK", 0)),
                   help="this learner's rank; rank 0 publishes weights and checkpoints (default: $RANK or 0)")
    g.add_argument("--dist-url", help="rendezvous, e.g. tcp://127.0.0.1:29500 (default: env:// with "
                   "$MASTER_ADDR and $MASTER_PORT)")

    g = p.add_argument_group("SAC")
    g.add_argument("--batch-size", type=int, default=DEFAULTS.batch_size, help="transitions per batch (default: %(default)s)")
    g.add_argument("--update-repeat", type=int, default=DEFAULTS.update_repeat,
                   help="gradient steps per sampled batch (default: %(default)s)")
    g.add_argument("--gamma", type=float, default=DEFAULTS.gamma, help="discount (default: %(default)s)")
    g.add_argument("--tau", type=float, default=DEFAULTS.tau, help="Polyak rate of the target critics (default: %(default)s)")
    g.add_argument("--lr", type=float, default=DEFAULTS.actor_lr, help="Adam learning rate of actor, critics and alpha (default: %(default)s)")
    g.add_argument("--hidden", default=",".join(map(str, DEFAULTS.hidden)),
                   help="hidden layer widths, comma-separated (default: %(default)s)")
    g.add_argument("--activation", choices=("elu", "relu", "tanh"), default=DEFAULTS.activation,
                   help="hidden activation (default: %(default)s)")
    g.add_argument("--no-layer-norm", action="store_true", help="no LayerNorm in hidden layers")
    g.add_argument("--reward-scale", type=float, default=DEFAULTS.reward_scale, help="reward multiplier (default: %(default)s)")
    g.add_argument("--target-entropy", type=float, help="entropy target of alpha tuning (default: -act-dim)")
    g.add_argument("--initial-alpha", type=float, default=DEFAULTS.initial_alpha, help="starting temperature (default: %(default)s)")
    g.add_argument("--fixed-alpha", action="store_true", help="keep alpha at --initial-alpha (no tuning)")
    g.add_argument("--relative-x", action="store_true",
                   help="networks see world x coordinates as distances from the pelvis")
    g.add_argument("--normalize-obs", action="store_true",
                   help="networks see observations standardised by running statistics (shipped with the weights)")
    g.add_argument("--mirror", action="store_true",
                   help="swap the legs of a random half of each batch (left-right symmetry as augmentation)")
    g.add_argument("--precision", choices=("auto", "float32", "bfloat16"), default=DEFAULTS.precision,
                   help="hidden-layer matmul precision; auto = bfloat16 where the hardware has it (default: %(default)s)")
    return p


def cli(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parse_daemon_args(parser, argv)
    try:
        hidden = tuple(int(h) for h in str(args.hidden).split(","))
        sac = SACConfig(gamma=args.gamma, tau=args.tau, actor_lr=args.lr, critic_lr=args.lr, alpha_lr=args.lr,
                        batch_size=args.batch_size, hidden=hidden, activation=args.activation,
                        layer_norm=not args.no_layer_norm, reward_scale=args.reward_scale,
                        update_repeat=args.update_repeat, target_entropy=args.target_entropy,
                        initial_alpha=args.initial_alpha, autotune_alpha=not args.fixed_alpha,
                        relative_x=args.relative_x, normalize_obs=args.normalize_obs, mirror=args.mirror,
                        precision=args.precision)
    except ValueError as e:
        parser.error(str(e))
    if not 0 <= args.rank < args.world_size:
        parser.error(f"--rank {args.rank} must be in [0, --world-size {args.world_size})")
    if min(args.in_flight, args.publish_every, args.obs_dim, args.act_dim, args.keep_checkpoints) < 1 or args.threads < 0:
        parser.error("--in-flight, --publish-every, --obs-dim, --act-dim and --keep-checkpoints must be >= 1, "
                     "--threads >= 0")
    if args.action_repeat is not None and args.action_repeat < 1:
        parser.error("--action-repeat must be >= 1")
    configure_logging(args.log_level)
    config = LearnerConfig(
        run=args.run, run_dir=args.run_dir, resume=args.resume, device=args.device, threads=args.threads,
        obs_dim=args.obs_dim, act_dim=args.act_dim, prioritized=args.prioritized,
        priority_beta=args.priority_beta, in_flight=args.in_flight, publish_every=args.publish_every,
        checkpoint_interval=args.checkpoint_interval, keep_checkpoints=args.keep_checkpoints,
        action_repeat=args.action_repeat, metrics_interval=args.metrics_interval,
        max_updates=args.max_updates, seed=args.seed, world_size=args.world_size, rank=args.rank,
        dist_url=args.dist_url)
    try:
        return main(config, sac, config_from_args(args))
    except DeviceUnavailable as e:
        print(f"l2r-learner: {e}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(cli())
