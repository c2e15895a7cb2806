"""MuJoCo Warp against MuJoCo's C step on the runner's MJCF; prints one JSON line.

The model is the env's (`runner.xml` with the env's sensors), from the default pose, its
actuators idle, MuJoCo's collisions off (the feet's forces, on the ground and the obstacles, are
the env's own kernels). Only MuJoCo's rigid-body step is timed here, not the env's muscles.

first_step_s: the first `mujoco_warp.step` on the device, kernel compilation included (cold when
    Warp's kernel cache, ~/.cache/warp, is empty; run with `--clear-cache` to make it so).
c_steps_per_s: `mujoco.mj_step` on one core, the same model and state.
warp_N_steps_per_s: physics steps per second summed over N worlds (and per world), on the device,
    each step's launches replayed as one captured graph; warp_N_eager_steps_per_s: launched
    from Python one by one.
env_N_steps_per_s: `l2r/RunWarp-v0` env steps (0.01 s, `substeps` physics steps with the
    muscles, feet, ligaments and knee kernels) per second summed over N worlds, random
    excitations, at difficulty 0, as the env runs by default (captured graphs);
    env_N_eager_steps_per_s: with graphs=False; env_N_difficultyD_steps_per_s: at difficulty D
    (1: three obstacles per world, the feet's forces on them computed by the env's kernels).
port_env_steps_per_s: `l2r/Run-v0` (numba, one core) the same way, for comparison
    (port_env_difficultyD_steps_per_s at difficulty D).
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path

import gymnasium
import mujoco
import mujoco_warp as mjw
import numpy as np
import warp as wp

import l2r.sim  # noqa: F401  (registers the environments)
from l2r.sim import model as body
from l2r.sim.env import with_sensors

sys.path.insert(0, str(Path(__file__).parent))
from env_speed import cpu_flags, cpu_model  # noqa: E402  (this folder's: the same machine record)


def runner_at_rest() -> tuple[mujoco.MjModel, mujoco.MjData]:
    m = with_sensors(mujoco.MjSpec.from_file(str(body.MODEL_PATH)))
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, m.keyframe(body.DEFAULT_KEYFRAME).id)
    mujoco.mj_forward(m, d)
    return m, d


def c_rate(m: mujoco.MjModel, d: mujoco.MjData, steps: int) -> float:
    d = mujoco.MjData(m)
    mujoco.mj_resetDataKeyframe(m, d, m.keyframe(body.DEFAULT_KEYFRAME).id)
    start = time.perf_counter()
    for _ in range(steps):
        mujoco.mj_step(m, d)
    return steps / (time.perf_counter() - start)


def warp_rate(m: mujoco.MjModel, d: mujoco.MjData, worlds: int, steps: int, graph: bool) -> float:
    model = mjw.put_model(m)
    data = mjw.put_data(m, d, nworld=worlds)
    mjw.step(model, data)  # warm: every kernel this size uses is loaded
    step = lambda: mjw.step(model, data)  # noqa: E731
    if graph:
        with wp.ScopedCapture(force_module_load=False) as capture:
            mjw.step(model, data)
        step = lambda: wp.capture_launch(capture.graph)  # noqa: E731
    wp.synchronize()
    start = time.perf_counter()
    for _ in range(steps):
        step()
    wp.synchronize()
    return worlds * steps / (time.perf_counter() - start)


def env_rate(env_id: str, worlds: int, steps: int, **kwargs) -> float:
    """Env steps per second summed over the worlds, random excitations, resets included."""
    actions = np.random.default_rng(0).uniform(0.0, 1.0, (steps + 1, worlds, 18))
    if worlds == 1 and "device" not in kwargs:
        env = gymnasium.make(env_id, **kwargs).unwrapped
        env.reset(seed=0)
        env.step(actions[-1][0])  # warm: numba's kernels compiled (or loaded from its cache) before timing
        env.reset(seed=0)
        start = time.perf_counter()
        for a in actions[:steps]:
            if any(env.step(a[0])[2:4]):
                env.reset()
        return steps / (time.perf_counter() - start)
    env = gymnasium.make_vec(env_id, num_envs=worlds, **kwargs)
    env.reset(seed=0)
    env.step(actions[-1])  # warm
    start = time.perf_counter()
    for a in actions[:steps]:
        env.step(a)
    return worlds * steps / (time.perf_counter() - start)


def _difficulty(d: int) -> str:
    """The difficulty's part of a result key: none for 0, the keys of earlier runs."""
    return f"_difficulty{d}" if d else ""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu", help="Warp device: cpu, cuda or cuda:N")
    parser.add_argument("--worlds", type=int, nargs="+", default=[1, 16, 256], help="world counts to time")
    parser.add_argument("--steps", type=int, default=50, help="timed physics steps per world count")
    parser.add_argument("--env-steps", type=int, default=10,
                        help="timed env steps of l2r/RunWarp-v0 per world count (0: skip the env)")
    parser.add_argument("--difficulties", type=int, nargs="+", default=[0, 1], choices=[0, 1, 2],
                        help="env difficulties to time (0 flat ground; 1 obstacles)")
    parser.add_argument("--clear-cache", action="store_true",
                        help="empty Warp's kernel cache first, so that first_step_s is a cold compile")
    args = parser.parse_args()

    wp.config.log_level = logging.WARNING  # no line per kernel module loaded: stdout is the JSON line
    wp.init()
    if args.clear_cache:
        wp.clear_kernel_cache()
    m, d = runner_at_rest()
    result = {"bench": "warp_speed", "device": args.device, "cpu": cpu_model(), "cpu_flags": cpu_flags(), "warp": wp.__version__,
              "mujoco_warp": mjw.__version__, "mujoco": mujoco.__version__}
    result["c_steps_per_s"] = round(c_rate(m, d, 2000))
    with wp.ScopedDevice(args.device):
        start = time.perf_counter()
        model, data = mjw.put_model(m), mjw.put_data(m, d, nworld=1)
        mjw.step(model, data)
        wp.synchronize()
        result["first_step_s"] = round(time.perf_counter() - start, 1)
        for n in args.worlds:
            for graph, key in ((True, f"warp_{n}"), (False, f"warp_{n}_eager")):
                rate = warp_rate(m, d, n, args.steps, graph)
                result[f"{key}_steps_per_s"] = round(rate)
                result[f"{key}_per_world_steps_per_s"] = round(rate / n, 1)
        result["substeps"] = gymnasium.make_vec("l2r/RunWarp-v0", num_envs=1, device=args.device).unwrapped.substeps
        for d in args.difficulties if args.env_steps else ():
            for n in args.worlds:
                for graphs in (True, False) if d == 0 else (True,):
                    rate = env_rate("l2r/RunWarp-v0", n, args.env_steps, device=args.device, difficulty=d, graphs=graphs)
                    result[f"env_{n}{_difficulty(d)}{'' if graphs else '_eager'}_steps_per_s"] = round(rate, 1)
                print(json.dumps(result), file=sys.stderr, flush=True)  # so far, should a long run be cut short
    for d in args.difficulties if args.env_steps else ():
        result[f"port_env{_difficulty(d)}_steps_per_s"] = round(env_rate("l2r/Run-v0", 1, 2000, difficulty=d))
    print(json.dumps(result))


if __name__ == "__main__":
    main()
