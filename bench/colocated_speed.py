"""What colocated worlds (l2r.learner.colocated) make a second, against an actor stepping the same worlds.

Three loops over the same worlds, in this process, one after another, each for ``--seconds``:
- ``actor``: a real `Actor` (the actors' path) stepping them as one vector env with uniform random
  excitations (its warm-up): physics, chunks encoded and put on a Zenoh session nobody joins; no
  policy call (the baseline: what the actors' path costs per env step before any learning);
- ``worlds``: the colocated worlds (`colocated_experience`) stepped with the policy, their
  transitions stored in the ring on the device, no update (the colocated path's own cost per env step);
- ``training``: the same with TD3's (or SAC's) update on a batch from the ring after each step of
  every world, as the learner runs it (`--update-repeat` updates a step, compiled as the learner
  would on the device).
``worlds_over_actor`` and ``training_over_worlds`` are the ratios of their env steps a second.

    python bench/colocated_speed.py --worlds 64 --device cpu              # Warp's CPU device
    python bench/colocated_speed.py --worlds 4096 --device cuda --batch-size 32768

Prints one JSON line, with the machine (CPU model and flags, the GPU's name).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import time
from pathlib import Path

import torch
import zenoh

from l2r.actors.actor import Actor, ActorConfig
from l2r.learner import sac, td3
from l2r.learner.colocated import WorldsConfig, colocated_experience
from l2r.learner.steps import GradientSteps, resolve_mode
from l2r.protocol import Keys, session_config
from l2r.spaces import task_spaces

sys.path.insert(0, str(Path(__file__).parent))
from env_speed import cpu_flags, cpu_model  # noqa: E402  (this folder's: the same machine record)

ALGORITHMS = {"td3": (td3, td3.TD3Config), "sac": (sac, sac.SACConfig)}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def actor_rate(args: argparse.Namespace, session: zenoh.Session) -> float:
    config = ActorConfig(run=f"bench-{free_port()}", env_id=args.env_id, num_envs=args.worlds,
                         action_repeat=args.action_repeat, random_steps=10**12, resend_buffer_mb=0,
                         device=args.device)
    actor = Actor(config, session)
    try:
        actor.step()  # the first step compiles what is not cached
        steps, started = actor.steps, time.perf_counter()
        while time.perf_counter() - started < args.seconds:
            actor.step()
        return (actor.steps - steps) / (time.perf_counter() - started)
    finally:
        actor.close()


def colocated_rates(args: argparse.Namespace, session: zenoh.Session, train: bool) -> tuple[float, float]:
    """Env steps and updates a second of colocated worlds, training or not."""
    module, config_type = ALGORITHMS[args.algo]
    device = torch.device(args.device)
    algo = config_type(batch_size=args.batch_size, update_repeat=args.update_repeat,
                       hidden=tuple(int(h) for h in args.hidden.split(",")))
    observation, act_dim = task_spaces(args.env_id)
    state = module.init_state(algo, observation.vector_width, act_dim, device)
    worlds = WorldsConfig(args.env_id, args.worlds, capacity=args.capacity, random_steps=0,
                          min_replay=args.batch_size, action_repeat=args.action_repeat)
    experience = colocated_experience(session, Keys(f"bench-{free_port()}"), worlds, state.actor, args.batch_size,
                                      device, on_policy=False)
    steps = GradientSteps(module.update, algo, resolve_mode(args.compile, device), device, algo.update_repeat,
                          policy_delay=getattr(algo, "policy_delay", None))

    def step() -> None:
        batch = experience.next_batch(timeout=0.0)
        if train and batch is not None:
            steps(state, module.prepare(state, batch.tensors, algo))

    try:
        while len(experience.replay) < 2 * args.batch_size or (train and state.updates < 10):  # and compiled
            step()
        env_steps, updates, started = experience.worlds.steps, state.updates, time.perf_counter()
        while time.perf_counter() - started < args.seconds:
            step()
        if device.type == "cuda":
            torch.cuda.synchronize()
        elapsed = time.perf_counter() - started
        return (experience.worlds.steps - env_steps) / elapsed, (state.updates - updates) / elapsed
    finally:
        experience.close()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--env-id", default="l2r/RunWarp-v0")
    p.add_argument("--worlds", type=int, default=64)
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="the worlds' (Warp's) and the update's")
    p.add_argument("--algo", choices=tuple(ALGORITHMS), default="td3")
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--update-repeat", type=int, default=1)
    p.add_argument("--hidden", default="256,256")
    p.add_argument("--action-repeat", type=int, default=3)
    p.add_argument("--capacity", type=int, default=1_000_000)
    p.add_argument("--compile", default="auto", help="the update's, as l2r-learner --compile")
    p.add_argument("--seconds", type=float, default=30.0, help="each loop's")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    args = p.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    with zenoh.open(session_config(listen=[f"tcp/127.0.0.1:{free_port()}"])) as session:
        actor = actor_rate(args, session)
        worlds, _ = colocated_rates(args, session, train=False)
        training, updates = colocated_rates(args, session, train=True)
    print(json.dumps({
        "bench": "colocated_speed", "env_id": args.env_id, "worlds": args.worlds, "device": args.device,
        "algo": args.algo, "batch_size": args.batch_size, "update_repeat": args.update_repeat, "hidden": args.hidden,
        "action_repeat": args.action_repeat, "compile": resolve_mode(args.compile, torch.device(args.device)),
        "actor_env_steps_per_s": round(actor, 1), "worlds_env_steps_per_s": round(worlds, 1),
        "training_env_steps_per_s": round(training, 1), "training_updates_per_s": round(updates, 1),
        "worlds_over_actor": round(worlds / actor, 3), "training_over_worlds": round(training / worlds, 3),
        "load_1min": round(os.getloadavg()[0], 2), "machine": cpu_model(), "cpu_flags": cpu_flags(),
        "gpu": torch.cuda.get_device_name() if args.device == "cuda" else None}))


if __name__ == "__main__":
    main()
