"""`l2r-actor`: command line of the actor daemon (see `l2r.actors.actor`)."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from pathlib import Path

from l2r.actors.actor import ActorConfig, main
from l2r.protocol import add_daemon_arguments, config_from_args, configure_logging, parse_daemon_args

DEFAULTS = ActorConfig()


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="l2r-actor",
        description="Step several Learning to Run environments with the learner's newest policy and "
                    "send the experience to the replay server(s) of a run. Stops cleanly on SIGINT/SIGTERM.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    a = p.add_argument_group("acting")
    a.add_argument("--actor-id", type=int, default=DEFAULTS.actor_id,
                   help="this actor's number; unique within the run (it names its keys and picks its replay shard)")
    a.add_argument("--num-envs", type=int, default=DEFAULTS.num_envs,
                   help="environments stepped together, their observations batched into one policy call")
    a.add_argument("--env-id", default=DEFAULTS.env_id,
                   help="gymnasium id of the environment: l2r/Run-v0 (the MuJoCo port) or l2r/RunOpenSim-v0 "
                        "(OpenSim 4.6, the 2017 simulator: about 100 steps/s; pip install 'l2r[opensim]')")
    a.add_argument("--difficulty", type=int, choices=(0, 1, 2), default=DEFAULTS.difficulty,
                   help="0 flat ground, 1 obstacles, 2 obstacles and random psoas strengths")
    a.add_argument("--action-repeat", type=int, default=DEFAULTS.action_repeat,
                   help="environment steps (0.01 s each) per policy action")
    a.add_argument("--random-steps", type=int, default=DEFAULTS.random_steps,
                   help="uniform random excitations for this many of the actor's first steps "
                        "(skipped when the run's policy is already past version 0)")
    a.add_argument("--seed", type=int, default=DEFAULTS.seed, help="base seed of episodes and random actions")
    a.add_argument("--torch-threads", type=int, default=DEFAULTS.torch_threads, help="torch CPU threads for inference")
    a.add_argument("--max-speed", type=float, default=DEFAULTS.max_speed,
                   help="pelvis speed (m/s) above which a step is a simulation blow-up: the episode ends before "
                        "it, as a terminal step without reward, and it is counted (0: off)")
    a.add_argument("--stats-interval", type=float, default=DEFAULTS.stats_interval, help="seconds between stats reports")
    a.add_argument("--max-steps", type=int, default=DEFAULTS.max_steps, help="stop after this many steps (0: never)")
    e = p.add_argument_group("experience")
    e.add_argument("--chunk-size", type=int, default=DEFAULTS.chunk_size, help="transitions per experience chunk")
    e.add_argument("--chunk-delay", type=float, default=DEFAULTS.chunk_delay,
                   help="seconds after which a partial chunk is sent anyway")
    e.add_argument("--num-shards", type=int, default=DEFAULTS.num_shards,
                   help="replay shards of the run; this actor feeds shard actor-id %% num-shards")
    e.add_argument("--resend-buffer-mb", type=float, default=DEFAULTS.resend_buffer_mb,
                   help="sent chunks kept until the replay shard acknowledges them, and sent again when lost in "
                        "flight (a cut link, a restarted shard); beyond this the oldest are given up (0: no resends)")
    e.add_argument("--resend-delay", type=float, default=DEFAULTS.resend_delay,
                   help="seconds after its last send before an unacknowledged chunk is sent again; the wait "
                        "doubles with each resend, up to 30 s")
    v = p.add_argument_group("evaluation role")
    v.add_argument("--evaluate", action="store_true",
                   help="run deterministic episodes on fixed seeds for each new policy, report them as "
                        "evaluation episodes, and send no experience")
    v.add_argument("--eval-episodes", type=int, default=DEFAULTS.eval_episodes,
                   help="episodes per evaluation round, on seeds seed, seed+1, ...")
    v.add_argument("--eval-interval", type=float, default=DEFAULTS.eval_interval,
                   help="least seconds between the starts of two evaluation rounds")
    m = p.add_argument_group("episode logs (MCAP)")
    m.add_argument("--episode-log-dir", type=Path, default=None,
                   help="write logged episodes as MCAP files here (default: no logs)")
    m.add_argument("--log-every", type=int, default=10,
                   help="log every Nth training episode (0: none); evaluation episodes are always logged")
    m.add_argument("--log-budget-mb", type=float, default=1024, help="disk budget of this actor's logs, oldest removed first")
    add_daemon_arguments(p)
    return p


def config_from(args: argparse.Namespace) -> ActorConfig:
    if args.resend_buffer_mb < 0 or args.resend_delay <= 0:
        raise SystemExit("l2r-actor: --resend-buffer-mb must be at least 0 and --resend-delay above 0")
    for name in ("num_envs", "action_repeat", "chunk_size", "num_shards", "eval_episodes", "torch_threads"):
        if getattr(args, name) < 1:
            raise SystemExit(f"l2r-actor: --{name.replace('_', '-')} must be at least 1")
    episode_log = {}
    if args.episode_log_dir is not None:
        episode_log = {"directory": args.episode_log_dir, "every": args.log_every,
                       "disk_budget_bytes": int(args.log_budget_mb * 2**20)}
    return ActorConfig(
        run=args.run, actor_id=args.actor_id, num_envs=args.num_envs, env_id=args.env_id,
        difficulty=args.difficulty, action_repeat=args.action_repeat, random_steps=args.random_steps,
        chunk_size=args.chunk_size, chunk_delay=args.chunk_delay, seed=args.seed,
        num_shards=args.num_shards, evaluate=args.evaluate, eval_episodes=args.eval_episodes,
        eval_interval=args.eval_interval, torch_threads=args.torch_threads, max_steps=args.max_steps,
        stats_interval=args.stats_interval, max_speed=args.max_speed,
        resend_buffer_mb=args.resend_buffer_mb, resend_delay=args.resend_delay,
        episode_log=episode_log,
    )


def cli(argv: list[str] | None = None) -> int:
    args = parse_daemon_args(build_parser(), argv)
    configure_logging(args.log_level)
    config = config_from(args)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return main(config, config_from_args(args), stop)


if __name__ == "__main__":
    sys.exit(cli())
