"""Rendering and stepping speed of the camera control tasks (l2r.control) on one core; prints one JSON line.

Rates are per second of this process's CPU time, all its threads counted (llvmpipe, Mesa's CPU
renderer behind EGL here, draws on threads of its own), with the process pinned to one core;
`wall_*` gives the same figures by the wall clock. The ways of rendering are timed in turns,
interleaved, so that they compare under the same load.

Per task (image_size × image_size frames, the suite's default visuals):
renders_per_s: frames the env renders (`ControlEnv.pixels`: one reused camera, an offscreen
    buffer of the frame's size).
env_steps_per_s: gymnasium steps (action_repeat suite steps and one frame each) with uniform
    random actions, resets included; frames_per_s is that times the action repeat, the rate at
    which papers count frames.
suite_steps_per_s: the suite's own steps, no rendering.
levers: renders/s of each way to render, and how its frame differs from the first one's (the
    largest difference of any value, and the share of values that differ):
    physics_render: dm_control's `physics.render` for every frame (a new scene each time) with the
        model's 640×480 offscreen buffer, as DrQ-v2's pixel wrapper renders;
    one_camera: one dm_control Camera kept and reused;
    one_camera_small_buffer: that and a buffer of the frame's size (the env's way);
    no_multisampling: one_camera_small_buffer without 4× multisampling (changes the picture);
    small_shadow_map: one_camera_small_buffer with a 512² shadow map instead of the suite's 2048²
        (sharper or blurrier shadow edges in a few pixels).
LP_NUM_THREADS (llvmpipe's thread count) is recorded: run the bench with it set to compare.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from typing import Callable

import numpy as np

from l2r.control import rendering
from l2r.control.env import IMAGE_SIZE, ControlEnv  # before dm_control: it chooses MUJOCO_GL first

from dm_control import suite  # noqa: E402
from dm_control.mujoco.engine import Camera  # noqa: E402
from env_speed import cpu_flags, cpu_model  # noqa: E402  (this folder's: the same machine record)

TASKS = ("cartpole-swingup", "walker-walk", "cheetah-run")
ROUNDS = 10  # turns each way of rendering gets, interleaved with the others


def rate(call: Callable[[], object], seconds: float) -> tuple[float, float]:
    """(CPU, wall) calls per second of `call`, timed for `seconds` of CPU time after one warm-up."""
    return interleaved_rates({"call": call}, seconds, rounds=1)["call"]


def interleaved_rates(calls: dict[str, Callable[[], object]], seconds: float, rounds: int) -> dict[str, tuple[float, float]]:
    """(CPU, wall) calls per second of each of `calls`, timed in turn for `seconds / rounds` of CPU
    time each, `rounds` times over, so that a change of load on a shared machine falls on all alike."""
    counts = dict.fromkeys(calls, 0)
    cpu_spent, wall_spent = dict.fromkeys(calls, 0.0), dict.fromkeys(calls, 0.0)
    for call in calls.values():
        call()  # warm-up
    for _ in range(rounds):
        for name, call in calls.items():
            cpu, wall = time.process_time(), time.perf_counter()
            while time.process_time() - cpu < seconds / rounds:
                call()
                counts[name] += 1
            cpu_spent[name] += time.process_time() - cpu
            wall_spent[name] += time.perf_counter() - wall
    return {name: (counts[name] / cpu_spent[name], counts[name] / wall_spent[name]) for name in calls}


def lever_cameras(env: ControlEnv, domain: str, task: str, size: int) -> dict[str, Callable[[], np.ndarray]]:
    """Renderers of env's current state, one per lever, each on a suite env of its own."""

    def suite_copy(**quality):
        """A suite env in env's state, with the model's visual quality settings changed."""
        copy = suite.load(domain, task)
        copy.reset()
        with copy.physics.reset_context():
            copy.physics.set_state(env.physics.get_state())
        for name, value in quality.items():
            setattr(copy.physics.model.vis.quality, name, value)
        return copy.physics

    def small_buffer(physics):
        physics.model.vis.global_.offwidth = physics.model.vis.global_.offheight = size
        return physics

    camera_id = env.camera_id
    default = suite_copy()
    one_camera = Camera(suite_copy(), size, size, camera_id)
    no_multisampling = Camera(small_buffer(suite_copy(offsamples=0)), size, size, camera_id)
    small_shadow_map = Camera(small_buffer(suite_copy(shadowsize=512)), size, size, camera_id)
    return {
        "physics_render": lambda: default.render(size, size, camera_id=camera_id),
        "one_camera": one_camera.render,
        "one_camera_small_buffer": env.camera.render,
        "no_multisampling": no_multisampling.render,
        "small_shadow_map": small_shadow_map.render,
    }


def measure(name: str, seconds: float, size: int) -> tuple[rendering.GLReport, dict]:
    domain, task = name.split("-")
    env = ControlEnv(domain, task, image_size=size)
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (4096, *env.action_space.shape)).astype(np.float32)
    step_count = [0]

    def env_step():
        *_, truncated, _ = env.step(actions[step_count[0] % len(actions)])
        step_count[0] += 1
        if truncated:
            env.reset()

    env.reset(seed=0)
    steps, wall_steps = rate(env_step, seconds)
    suite_env = suite.load(domain, task)
    suite_env.reset()
    suite_action = np.zeros(env.action_space.shape)

    def suite_step():
        if suite_env.step(suite_action).last():
            suite_env.reset()

    suite_steps, _ = rate(suite_step, seconds)

    env.reset(seed=1)
    for action in actions[:20]:  # a pose away from the start, so that frames differ where levers do
        env.step(action)
    cameras = lever_cameras(env, domain, task, size)
    reference = cameras["physics_render"]().astype(int)
    rates = interleaved_rates({"env": env.pixels, **cameras}, seconds, rounds=ROUNDS)
    renders, wall_renders = rates.pop("env")
    levers = {}
    for lever, (cpu, wall) in rates.items():
        render = cameras[lever]
        difference = np.abs(render().astype(int) - reference)
        levers[lever] = {
            "renders_per_s": round(cpu, 1),
            "wall_renders_per_s": round(wall, 1),
            "max_pixel_difference": int(difference.max()),
            "share_of_values_differing": round(float((difference > 0).mean()), 4),
        }
    env.close()
    return env.gl, {
        "action_repeat": env.action_repeat,
        "renders_per_s": round(renders, 1),
        "env_steps_per_s": round(steps, 1),
        "frames_per_s": round(steps * env.action_repeat, 1),
        "suite_steps_per_s": round(suite_steps, 1),
        "wall_renders_per_s": round(wall_renders, 1),
        "wall_env_steps_per_s": round(wall_steps, 1),
        "levers": levers,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=3.0, help="CPU seconds timed per figure (default 3)")
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), help="suite tasks as domain-task (default: %(default)s)")
    parser.add_argument("--image-size", type=int, default=IMAGE_SIZE, help="frame height and width in pixels (default 84)")
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):  # one core: the figures are per core
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})

    tasks = {}
    for name in args.tasks:
        gl, tasks[name] = measure(name, args.seconds, args.image_size)
    print(
        json.dumps(
            {
                "tasks": tasks,
                "image_size": args.image_size,
                "backend": gl.backend,
                "gl_renderer": gl.renderer,
                "gl_version": gl.version,
                "lp_num_threads": os.environ.get("LP_NUM_THREADS"),
                "load_average_1min": round(os.getloadavg()[0], 2),
                "machine": f"{cpu_model()}, {os.cpu_count()} CPUs",
                "cpu_flags": cpu_flags(),
                "seconds_per_figure": args.seconds,
            }
        )
    )


if __name__ == "__main__":
    main()
