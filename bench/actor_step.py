"""What an actor's stepping loop costs per env step, and the frames a camera actor renders a second.

A real `Actor` (l2r/actors/actor.py) in this process, on a Zenoh session of its own that nobody
joins, steps its environments with uniform random excitations (its warm-up) for ``--steps`` env
steps after ``--warmup`` of them: everything an actor does per step but the policy call, chunks
encoded and put included. The figure that survives a shared machine is the CPU time of the
stepping thread per env step (a per-thread clock); the whole process's CPU time (Zenoh's
threads, and llvmpipe's, which rasterise a camera task's frames) and wall-clock rates are
reported beside it.
Run it against another checkout (PYTHONPATH) on the same machine to compare two versions.
`--env-id l2r/RunWarp-v0 --num-envs 256` times an actor that steps its worlds as one vector env
(`--device cuda` on a GPU); ``load_1min`` records how busy the machine was.

Prints one JSON line: ``cpu_us_per_env_step``, ``process_cpu_us_per_env_step``,
``env_steps_per_s``, ``load_1min``, on a camera task
``frames_per_s`` (suite steps, as papers count frames), and the settings.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import sys
import time
from pathlib import Path

import zenoh

from l2r.actors.actor import Actor, ActorConfig
from l2r.actors.worlds import VectorWorlds
from l2r.protocol import session_config

sys.path.insert(0, str(Path(__file__).parent))
from env_speed import cpu_flags, cpu_model  # noqa: E402  (this folder's: the same machine record)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--env-id", default="l2r/Run-v0", help="the actor's task (a camera task: l2r/dmc-cartpole-swingup-v0)")
    p.add_argument("--num-envs", type=int, default=4, help="environments stepped together")
    p.add_argument("--action-repeat", type=int, default=3, help="the actor's --action-repeat (1 for a camera task)")
    p.add_argument("--vector-env", choices=("auto", "on", "off"), default="auto",
                   help="the actor's --vector-env: one vector env for all (auto: where the id registers one)")
    p.add_argument("--device", default="cpu", help="the actor's --device (the policy's, and RunWarp's worlds')")
    p.add_argument("--steps", type=int, default=4000, help="env steps measured, over all environments")
    p.add_argument("--warmup", type=int, default=400, help="env steps before measuring")
    args = p.parse_args()
    config = ActorConfig(run=f"bench-{free_port()}", env_id=args.env_id, num_envs=args.num_envs,
                         action_repeat=args.action_repeat, random_steps=10**9, resend_buffer_mb=0, device=args.device,
                         vector_env={"auto": None, "on": True, "off": False}[args.vector_env],
                         max_speed=20.0 if args.env_id.startswith("l2r/Run") else 0.0)
    with zenoh.open(session_config(listen=[f"tcp/127.0.0.1:{free_port()}"])) as session:
        actor = Actor(config, session)
        try:
            while actor.steps < args.warmup:
                actor.step()
            steps, frames = actor.steps, getattr(actor, "frames", 0)
            wall, cpu, process = time.perf_counter(), time.thread_time(), time.process_time()
            while actor.steps - steps < args.steps:
                actor.step()
            cpu, process, wall = time.thread_time() - cpu, time.process_time() - process, time.perf_counter() - wall
            done, rendered = actor.steps - steps, getattr(actor, "frames", 0) - frames
        finally:
            actor.close()
    result = {"bench": "actor_step", "env_id": args.env_id, "num_envs": args.num_envs,
              "action_repeat": args.action_repeat, "vector_env": isinstance(actor.worlds, VectorWorlds),
              "device": args.device, "env_steps": done,
              "cpu_us_per_env_step": round(1e6 * cpu / done, 1),
              "process_cpu_us_per_env_step": round(1e6 * process / done, 1), "env_steps_per_s": round(done / wall, 1),
              "load_1min": round(os.getloadavg()[0], 2),
              "machine": cpu_model(), "cpu_flags": cpu_flags()}
    if getattr(actor, "camera", False):
        result["frames_per_s"] = round(rendered / wall, 1)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
