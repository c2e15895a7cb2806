"""SAC gradient steps per second: l2r's update against Stable-Baselines3's SAC.train().

Same shapes (41 observations, 18 actions, 3 hidden layers of 512), same device, same torch
threads, one process, measured in interleaved rounds so a busy machine slows both alike.
Every gradient step runs on a freshly sampled batch, sampling included, on both sides.

Prints one JSON line. Figures:
  updates_per_s_bB            l2r as it trains by default (ELU + LayerNorm, --precision), eager
  fp32_updates_per_s_bB       the same network with float32 matmuls (left out where l2r runs float32 already:
                              --precision float32, or auto on CUDA or a CPU without native bfloat16)
  MODE_updates_per_s_bB       the default network with its update run by --compile MODE (l2r.learner.steps:
                              graphs_, inductor_, inductor_graphs_); MODE_compile_s_bB: the seconds its
                              warm-up took (torch.compile's compilation, the graph's capture)
  same_net_updates_per_s_bB   SB3's network exactly (ReLU, no LayerNorm), --precision
  baseline_updates_per_s_bB   SB3 2.x SAC.train(), net_arch 3 x 512, float32
  *range_bB                   the slowest and fastest round of each
  *ratio_bB                   each of the above over the baseline
  *gflops_bB                  matmul GFLOP/s achieved: updates/s times the matmul FLOPs of one step
  *gflop_per_update_bB        those FLOPs, counted by torch's FlopCounterMode from the shapes of the
                              matmuls one step runs (forward and backward, actor, critics, target)
  peak_gflops, peak_basis     the CPU's float32 peak on the cores the threads can use (see cpu_peak)
  matmul_gflops               what one float32 batched matmul of the critics' shape, (2 x 640 x 512) x
                              (512 x 512), reaches on the same threads: the practical ceiling (CPU only)
  *kernels_per_update_bB      with --profile DIR (CUDA): GPU kernels one update runs, and
  *gpu_ms_per_update_bB       the milliseconds they keep the GPU busy, from a torch.profiler trace of
                              PROFILE_STEPS updates written to DIR as NAMEbB.json.gz
With --clock cpu (for a machine other work is loading) every rate is updates per second of this
process's CPU time rather than of wall-clock time, and GFLOP/s are per CPU-second: per core, if the
threads kept their cores busy. Compare those with the peak per core (peak_gflops / cores).
"""

from __future__ import annotations

import os

# As l2r-learner does (see l2r/learner/__main__.py); both sides run in this one process.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse  # noqa: E402
import gzip  # noqa: E402
import json  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from torch.utils.flop_counter import FlopCounterMode  # noqa: E402

from l2r.learner.steps import COMPILE_MODES, WARMUP_CALLS  # noqa: E402

OBS_DIM, ACT_DIM, HIDDEN, BUFFER = 41, 18, (512, 512, 512), 20_000
PROFILE_STEPS = 10


class L2RStepper:
    """l2r's update on batches sampled from a numpy buffer (what the replay reply carries)."""

    def __init__(self, batch_size: int, device: str, compile: str = "off", **config):
        from l2r.learner.sac import SACConfig, init_state, update
        from l2r.learner.steps import GradientSteps

        self.config = SACConfig(hidden=HIDDEN, batch_size=batch_size, update_repeat=1, **config)
        self.state = init_state(self.config, OBS_DIM, ACT_DIM, device, seed=0)
        self.update = GradientSteps(update, self.config, compile, device)
        self.device = device
        rng = np.random.default_rng(0)
        self.data = {"obs": rng.normal(size=(BUFFER, OBS_DIM)).astype(np.float32),
                     "action": rng.random((BUFFER, ACT_DIM), dtype=np.float32),
                     "reward": rng.normal(size=BUFFER).astype(np.float32),
                     "next_obs": rng.normal(size=(BUFFER, OBS_DIM)).astype(np.float32),
                     "terminated": (rng.random(BUFFER) < 0.01)}
        self.rng, self.batch_size = rng, batch_size

    def steps(self, n: int) -> None:
        from l2r.learner.sac import batch_from_numpy

        for _ in range(n):
            i = self.rng.integers(0, BUFFER, self.batch_size)
            d = self.data
            batch = batch_from_numpy(d["obs"][i], d["action"][i], d["reward"][i], d["next_obs"][i],
                                     d["terminated"][i], device=self.device)
            metrics = self.update(self.state, batch)
        float(metrics["critic_loss"])  # wait for the last step (a no-op on CPU, a sync on CUDA)

    def warm_up(self) -> None:
        """Allocator, lazy imports, kernels; compilation and a graph's capture where the mode has them."""
        self.steps(1 if self.update.mode == "off" else WARMUP_CALLS + 1)


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

    def warm_up(self) -> None:
        self.steps(1)


def cpu_peak(threads: int, cpuinfo: str = "/proc/cpuinfo") -> dict:
    """The CPU's model, its vector-math flags and its float32 peak on min(threads, cores) cores.

    Peak = cores x clock x FLOPs per cycle per core, where FLOPs per cycle = 2 FMA units x float32
    lanes (16 with avx512f, 8 with avx2 + fma, and 8 on AMD family 25 with avx512f: Zen 4 runs
    512-bit FMAs as two 256-bit halves) x 2 (an FMA is a multiply and an add). The number of FMA
    units is not in /proc/cpuinfo: two is what server cores since Skylake-SP Gold and AMD Zen 2
    have, but some Xeon Silver/Bronze have one 512-bit unit (half the peak given here). The clock
    is /proc/cpuinfo's "cpu MHz", the nominal clock in a VM; turbo may run above it.
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
    # AMD family 25 is Zen 3 and Zen 4; of those only Zen 4 has AVX-512, on 256-bit units.
    halves = lanes == 16 and fields.get("vendor_id") == "AuthenticAMD" and fields.get("cpu family") == "25"
    lanes = 8 if halves else lanes
    n_cores = min(threads, len(cores) or os.cpu_count() or 1)
    mhz = float(fields.get("cpu MHz", 0))
    info = {"cpu": fields.get("model name", "unknown"), "cpu_family": fields.get("cpu family"),
            "cpu_model": fields.get("model"), "cpu_flags": [f for f in flags if f.startswith(("avx", "amx", "fma"))]}
    if not lanes or not mhz:
        return info | {"peak_gflops": None, "peak_basis": "no avx2+fma or no clock in /proc/cpuinfo"}
    per_cycle = 2 * lanes * 2
    return info | {"peak_gflops": round(n_cores * mhz / 1000 * per_cycle, 1),
                   "peak_basis": f"{n_cores} cores x {mhz:.0f} MHz x {per_cycle} FLOP/cycle "
                                 f"(2 FMA units x {lanes} float32 lanes x 2"
                                 f"{'; AVX-512 as two 256-bit halves (AMD Zen 4)' if halves else ''})"}


def matmul_gflops(clock, seconds: float = 1.0) -> float:
    """float32 GFLOP/s of the critics' hidden-layer matmul, (2, 640, 512) x (2, 512, 512), on this
    thread count, per second of `clock`."""
    x, w, b = torch.randn(2, 640, 512), torch.randn(2, 512, 512), torch.randn(2, 1, 512)
    torch.baddbmm(b, x, w)
    n, started = 0, clock()
    while clock() - started < seconds:
        torch.baddbmm(b, x, w)
        n += 1
    return round(n * 2 * x.numel() * w.shape[-1] / (clock() - started) / 1e9, 1)


def step_flops(stepper) -> int:
    """Matmul FLOPs of one gradient step, counted while it runs (elementwise work not included)."""
    with FlopCounterMode(display=False) as counter:
        stepper.steps(1)
    return counter.get_total_flops()


def gpu_profile(stepper, path: str) -> dict:
    """Kernels per update and their GPU milliseconds, from a trace of PROFILE_STEPS updates
    (written to `path`, gzipped): where a GPU update's time goes, launches against work."""
    with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU,
                                            torch.profiler.ProfilerActivity.CUDA]) as profiler:
        stepper.steps(PROFILE_STEPS)
    trace = path.removesuffix(".gz")
    profiler.export_chrome_trace(trace)
    with open(trace, "rb") as raw, gzip.open(path, "wb") as packed:
        packed.write(raw.read())
    os.remove(trace)
    with gzip.open(path, "rt") as f:
        kernels = [e for e in json.load(f)["traceEvents"] if e.get("cat") == "kernel"]
    return {"kernels_per_update": round(len(kernels) / PROFILE_STEPS, 1),
            "gpu_ms_per_update": round(sum(e.get("dur", 0) for e in kernels) / PROFILE_STEPS / 1000, 3)}


def rate(stepper, n: int, clock) -> float:
    started = clock()
    stepper.steps(n)
    return n / (clock() - started)


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
    p.add_argument("--compile", default=None,
                   help="comma-separated modes of running the update to time besides eager (off): "
                        f"{', '.join(m for m in COMPILE_MODES if m not in ('auto', 'off'))}; 'none' for none "
                        "(default: all three with --device cuda, none on CPU, where inductor compiles for minutes)")
    p.add_argument("--clock", choices=("wall", "cpu"), default="wall",
                   help="wall: updates per second; cpu: per second of this process's CPU time, for a machine "
                        "loaded by other work (default: %(default)s)")
    p.add_argument("--profile", metavar="DIR", help="CUDA: trace each l2r update and SB3's with torch.profiler into "
                                                    "DIR and report kernels and GPU time per update")
    args = p.parse_args()
    if args.profile and args.device != "cuda":
        p.error("--profile counts GPU kernels: it needs --device cuda")
    if args.device == "cuda" and not torch.cuda.is_available():
        p.error("--device cuda: torch sees no CUDA device")
    if args.compile is None:
        args.compile = "graphs,inductor,inductor-graphs" if args.device == "cuda" else "none"
    modes = [] if args.compile == "none" else args.compile.split(",")
    if not set(modes) <= set(COMPILE_MODES) - {"auto", "off"}:
        p.error(f"--compile {args.compile}: modes are graphs, inductor and inductor-graphs")
    if args.device == "cpu" and any(m.endswith("graphs") for m in modes):
        p.error("--compile: graphs are CUDA graphs; on CPU only inductor")
    # Several compiled learners in one process: each new state and batch size recompiles the
    # update; past torch's default limit of 8 it would quietly run eager.
    torch._dynamo.config.recompile_limit = 64
    if args.quick:
        args.rounds, args.steps = 1, 4
    torch.set_num_threads(args.threads)
    started = time.perf_counter()
    clock = time.process_time if args.clock == "cpu" else time.perf_counter
    result: dict = {"bench": "learner_speed", "device": args.device, "threads": args.threads, "obs_dim": OBS_DIM,
                    "act_dim": ACT_DIM, "hidden": list(HIDDEN), "clock": args.clock, "torch": torch.__version__,
                    "omp_wait_policy": os.environ["OMP_WAIT_POLICY"], **cpu_peak(args.threads),
                    "load_average": os.getloadavg()[0]}
    if args.device == "cuda":
        result |= {"gpu": torch.cuda.get_device_name()}
    else:
        result["matmul_gflops"] = matmul_gflops(clock)
    for batch_size in (int(b) for b in args.batch_sizes.split(",")):
        steppers = {"": L2RStepper(batch_size, args.device, precision=args.precision)}
        if steppers[""].state.bfloat16:  # else the default stepper is the float32 one
            steppers["fp32_"] = L2RStepper(batch_size, args.device, precision="float32")
        for mode in modes:
            steppers[mode.replace("-", "_") + "_"] = L2RStepper(batch_size, args.device, mode, precision=args.precision)
        steppers["same_net_"] = L2RStepper(batch_size, args.device, precision=args.precision, activation="relu",
                                           layer_norm=False)
        steppers["baseline_"] = SB3Stepper(batch_size, args.device)
        n = args.steps * (2 if batch_size == 256 else 1)
        flops = {}
        for name, stepper in list(steppers.items()):
            warm_up_started = time.perf_counter()
            try:
                stepper.warm_up()
            except Exception as error:  # a mode that fails on this machine is reported, the others still timed
                result[f"{name}error_b{batch_size}"] = f"{type(error).__name__}: {error}"[:500]
                del steppers[name]
                continue
            if name[:-1] in (m.replace("-", "_") for m in modes):
                result[f"{name}compile_s_b{batch_size}"] = round(time.perf_counter() - warm_up_started, 1)
                flops[name] = flops[""]  # the default network's; the counter cannot see into compiled code
            else:
                flops[name] = step_flops(stepper)
        rates: dict[str, list[float]] = {name: [] for name in steppers}
        for _ in range(args.rounds):
            for name, stepper in steppers.items():
                rates[name].append(rate(stepper, n, clock))
        for name, values in rates.items():
            result[f"{name}updates_per_s_b{batch_size}"] = round(statistics.median(values), 2)
            result[f"{name}range_b{batch_size}"] = [round(min(values), 2), round(max(values), 2)]
            result[f"{name}gflop_per_update_b{batch_size}"] = round(flops[name] / 1e9, 3)
            result[f"{name}gflops_b{batch_size}"] = round(statistics.median(values) * flops[name] / 1e9, 1)
        if args.profile:
            os.makedirs(args.profile, exist_ok=True)
            for name, stepper in steppers.items():
                for key, value in gpu_profile(stepper, os.path.join(args.profile,
                                                                    f"{name or 'default_'}b{batch_size}.json.gz")).items():
                    result[f"{name}{key}_b{batch_size}"] = value
        baseline = result[f"baseline_updates_per_s_b{batch_size}"]
        for name in steppers:
            if name != "baseline_":
                result[f"{name}ratio_b{batch_size}"] = round(result[f"{name}updates_per_s_b{batch_size}"] / baseline, 2)
        result["precision"] = "bfloat16" if steppers[""].state.bfloat16 else "float32"
    result["seconds"] = round(time.perf_counter() - started, 1)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
