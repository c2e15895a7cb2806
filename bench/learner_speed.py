"""SAC gradient steps per second: l2r's update against Stable-Baselines3's SAC.train().

Same shapes (41 observations, 18 actions, 3 hidden layers of 512), same device, same torch
threads, one process, measured in interleaved rounds so a busy machine slows both alike.
Every gradient step runs on a freshly sampled batch, sampling included, on both sides.

Prints one JSON line. Figures:
  updates_per_s_bB            l2r as it trains by default (ELU + LayerNorm, --precision)
  fp32_updates_per_s_bB       the same network with float32 matmuls (left out where l2r runs float32 already:
                              --precision float32, or auto on CUDA or a CPU without native bfloat16)
  same_net_updates_per_s_bB   SB3's network exactly (ReLU, no LayerNorm), --precision
  baseline_updates_per_s_bB   SB3 2.x SAC.train(), net_arch 3 x 512, float32
  *ratio_bB                   each of the above over the baseline
  *gflops_bB                  matmul GFLOP/s achieved: updates/s times the matmul FLOPs of one step
  *gflop_per_update_bB        those FLOPs, counted by torch's FlopCounterMode from the shapes of the
                              matmuls one step runs (forward and backward, actor, critics, target)
  peak_gflops, peak_basis     the CPU's float32 peak on the cores the threads can use (see cpu_peak)
"""

from __future__ import annotations

import os

# As l2r-learner does (see l2r/learner/__main__.py); both sides run in this one process.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from torch.utils.flop_counter import FlopCounterMode  # noqa: E402

OBS_DIM, ACT_DIM, HIDDEN, BUFFER = 41, 18, (512, 512, 512), 20_000


class L2RStepper:
    """l2r's update on batches sampled from a numpy buffer (what the replay reply carries)."""

    def __init__(self, batch_size: int, device: str, **config):
        from l2r.learner.sac import SACConfig, init_state

        self.config = SACConfig(hidden=HIDDEN, batch_size=batch_size, update_repeat=1, **config)
        self.state = init_state(self.config, OBS_DIM, ACT_DIM, device, seed=0)
        self.device = device
        rng = np.random.default_rng(0)
        self.data = {"obs": rng.normal(size=(BUFFER, OBS_DIM)).astype(np.float32),
                     "action": rng.random((BUFFER, ACT_DIM), dtype=np.float32),
                     "reward": rng.normal(size=BUFFER).astype(np.float32),
                     "next_obs": rng.normal(size=(BUFFER, OBS_DIM)).astype(np.float32),
                     "terminated": (rng.random(BUFFER) < 0.01)}
        self.rng, self.batch_size = rng, batch_size

    def steps(self, n: int) -> None:
        from l2r.learner.sac import batch_from_numpy, update

        for _ in range(n):
            i = self.rng.integers(0, BUFFER, self.batch_size)
            d = self.data
            batch = batch_from_numpy(d["obs"][i], d["action"][i], d["reward"][i], d["next_obs"][i],
                                     d["terminated"][i], device=self.device)
            metrics = update(self.state, batch, self.config)
        float(metrics["critic_loss"])  # wait for the last step (a no-op on CPU, a sync on CUDA)


class SB3Stepper:
    """Stable-Baselines3 SAC with a replay buffer of random data of the same shapes."""

    def __init__(self, batch_size: int, device: str):
        import gymnasium as gym
        from stable_baselines3 import SAC
        from stable_baselines3.common.logger import configure

        class Shapes(gym.Env):
            observation_space = gym.spaces.Box(-np.inf, np.inf, (OBS_DIM,), np.float32)
            action_space = gym.spaces.Box(0.0, 1.0, (ACT_DIM,), np.float32)

        self.model = SAC("MlpPolicy", Shapes(), buffer_size=BUFFER, batch_size=batch_size, learning_starts=0,
                         policy_kwargs={"net_arch": list(HIDDEN)}, device=device, seed=0)
        self.model.set_logger(configure(None, []))
        buffer, rng = self.model.replay_buffer, np.random.default_rng(0)
        buffer.observations[:] = rng.normal(size=buffer.observations.shape)
        buffer.next_observations[:] = rng.normal(size=buffer.next_observations.shape)
        buffer.actions[:] = rng.uniform(-1, 1, size=buffer.actions.shape)
        buffer.rewards[:] = rng.normal(size=buffer.rewards.shape)
        buffer.dones[:] = rng.random(buffer.dones.shape) < 0.01
        buffer.full, buffer.pos = True, 0
        self.batch_size = batch_size

    def steps(self, n: int) -> None:
        self.model.train(gradient_steps=n, batch_size=self.batch_size)


def cpu_peak(threads: int, cpuinfo: str = "/proc/cpuinfo") -> dict:
    """The CPU's model, its vector-math flags and its float32 peak on min(threads, cores) cores.

    Peak = cores x clock x FLOPs per cycle per core, where FLOPs per cycle = 2 FMA units x float32
    lanes (16 with avx512f, 8 with avx2 + fma) x 2 (an FMA is a multiply and an add). The number of
    FMA units is not in /proc/cpuinfo: two is what server cores since Skylake-SP Gold and AMD Zen 2
    have, but some Xeon Silver/Bronze have one 512-bit unit and Zen 4 runs 512-bit FMAs as two
    256-bit halves (half the peak given here). The clock is /proc/cpuinfo's "cpu MHz", the nominal
    clock in a VM; turbo may run above it.
    """
    fields: dict[str, str] = {}
    cores = set()  # (physical id, core id): hyperthreads share their core's FMA units
    for block in open(cpuinfo).read().split("\n\n"):
        cpu = dict((k.strip(), v.strip()) for k, _, v in (line.partition(":") for line in block.splitlines()))
        fields = fields or cpu
        if "core id" in cpu:
            cores.add((cpu.get("physical id"), cpu["core id"]))
    flags = fields.get("flags", "").split()
    lanes = 16 if "avx512f" in flags else 8 if {"avx2", "fma"} <= set(flags) else 0
    n_cores = min(threads, len(cores) or os.cpu_count() or 1)
    mhz = float(fields.get("cpu MHz", 0))
    info = {"cpu": fields.get("model name", "unknown"),
            "cpu_flags": [f for f in flags if f.startswith(("avx", "amx", "fma"))]}
    if not lanes or not mhz:
        return info | {"peak_gflops": None, "peak_basis": "no avx2+fma or no clock in /proc/cpuinfo"}
    per_cycle = 2 * lanes * 2
    return info | {"peak_gflops": round(n_cores * mhz / 1000 * per_cycle, 1),
                   "peak_basis": f"{n_cores} cores x {mhz:.0f} MHz x {per_cycle} FLOP/cycle "
                                 f"(2 FMA units x {lanes} float32 lanes x 2)"}


def step_flops(stepper) -> int:
    """Matmul FLOPs of one gradient step, counted while it runs (elementwise work not included)."""
    with FlopCounterMode(display=False) as counter:
        stepper.steps(1)
    return counter.get_total_flops()


def rate(stepper, n: int) -> float:
    started = time.perf_counter()
    stepper.steps(n)
    return n / (time.perf_counter() - started)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--threads", type=int, default=2, help="torch threads for both sides (default: %(default)s)")
    p.add_argument("--rounds", type=int, default=3, help="interleaved timing rounds; the median counts (default: %(default)s)")
    p.add_argument("--steps", type=int, default=12, help="gradient steps per round at batch 640, more at 256 (default: %(default)s)")
    p.add_argument("--quick", action="store_true", help="one round of few steps (a smoke run)")
    p.add_argument("--precision", choices=("auto", "float32", "bfloat16"), default="auto",
                   help="l2r's matmul precision (SACConfig.precision; default: %(default)s)")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                   help="where both sides train; the batch is sampled on the host and copied over, as the "
                        "learner's replay reply is (default: %(default)s)")
    p.add_argument("--batch-sizes", default="256,640", help="comma-separated (default: %(default)s)")
    args = p.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        p.error("--device cuda: torch sees no CUDA device")
    if args.quick:
        args.rounds, args.steps = 1, 4
    torch.set_num_threads(args.threads)
    started = time.perf_counter()
    result: dict = {"bench": "learner_speed", "device": args.device, "threads": args.threads, "obs_dim": OBS_DIM,
                    "act_dim": ACT_DIM, "hidden": list(HIDDEN),
                    "omp_wait_policy": os.environ["OMP_WAIT_POLICY"], **cpu_peak(args.threads)}
    if args.device == "cuda":
        result |= {"gpu": torch.cuda.get_device_name(), "torch": torch.__version__}
    for batch_size in (int(b) for b in args.batch_sizes.split(",")):
        steppers = {"": L2RStepper(batch_size, args.device, precision=args.precision)}
        if steppers[""].state.bfloat16:  # else the default stepper is the float32 one
            steppers["fp32_"] = L2RStepper(batch_size, args.device, precision="float32")
        steppers["same_net_"] = L2RStepper(batch_size, args.device, precision=args.precision, activation="relu",
                                           layer_norm=False)
        steppers["baseline_"] = SB3Stepper(batch_size, args.device)
        n = args.steps * (2 if batch_size == 256 else 1)
        flops = {}
        for name, stepper in steppers.items():
            stepper.steps(1)  # warm-up: allocator, lazy imports, kernels
            flops[name] = step_flops(stepper)
        rates: dict[str, list[float]] = {name: [] for name in steppers}
        for _ in range(args.rounds):
            for name, stepper in steppers.items():
                rates[name].append(rate(stepper, n))
        for name, values in rates.items():
            result[f"{name}updates_per_s_b{batch_size}"] = round(statistics.median(values), 2)
            result[f"{name}gflop_per_update_b{batch_size}"] = round(flops[name] / 1e9, 3)
            result[f"{name}gflops_b{batch_size}"] = round(statistics.median(values) * flops[name] / 1e9, 1)
        baseline = result[f"baseline_updates_per_s_b{batch_size}"]
        for name in steppers:
            if name != "baseline_":
                result[f"{name}ratio_b{batch_size}"] = round(result[f"{name}updates_per_s_b{batch_size}"] / baseline, 2)
        result["precision"] = "bfloat16" if steppers[""].state.bfloat16 else "float32"
    result["seconds"] = round(time.perf_counter() - started, 1)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
