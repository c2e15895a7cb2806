"""DrQ-v2's update in l2r's learner (TD3 on 3 stacked 84 x 84 frames, `l2r up`'s pixels recipe):
updates per second on a device, fed the way the learner daemon is fed. `--encoder dual` times the
same update through RLPixTuner's dual-path encoder instead of DrQ-v2's.

A batch arrives in the replay's frames form: each distinct uint8 frame once (here 6 per transition,
what a stack of 3 and n-step 3 touch when no frames are shared), the obs and next-obs stacks as
rows into them, all read-only as a decoded reply's arrays are. `batch_from_frames` copies the
frames to the device and stacks them there; the update shifts every image (pad 4) and steps the
encoder, critics and actor.

Prints one JSON line. Figures:
  fed_updates_per_s           a fresh batch each update: the copy to the device, the stacking, the update
  resident_updates_per_s      the same update on one batch already stacked on the device: the update alone
  fed_range, resident_range   the slowest and fastest round of each
  batch_frame_bytes           bytes of a batch's distinct frames (what crosses to the device per batch)
  frames_to_500k_s            seconds the update alone needs for DrQ-v2's 500k frames (125,000 updates:
                              action repeat 2, an update every 2 env steps), at resident_updates_per_s
  peak_memory_mib             the device's peak allocation (CUDA only)
  compile, warmup_s           how the update ran (--compile, resolved) and the seconds before timing
                              (compilation and the CUDA graph's capture, where they run)
On CPU the figures are seconds per update: use small --size and --batch-size for a smoke run.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np
import torch

from env_speed import cpu_flags, cpu_model  # this folder's: the same machine record as the other figures
from l2r.encoders import DRQ, IMAGE_VIEWS
from l2r.learner.sac import batch_from_frames
from l2r.learner.steps import COMPILE_MODES, WARMUP_CALLS, GradientSteps, resolve_mode
from l2r.learner.td3 import TD3Config, init_state, update
from l2r.protocol import ObservationSpec

ACT_DIM, STACK, FRAMES_PER_TRANSITION = 6, 3, 6  # cheetah-run's 6 actions; obs and next-obs stacks apart
UPDATES_TO_500K_FRAMES = 500_000 // 2 // 2


def drqv2_config(batch_size: int, encoder: str) -> TD3Config:
    """The learner's TD3 as `l2r up --env-id l2r/dmc-...` configures it (l2r.recipes, PIXELS), with
    this `--encoder`."""
    return TD3Config(hidden=(1024, 1024), activation="relu", layer_norm=False, batch_size=batch_size,
                     actor_lr=1e-4, critic_lr=1e-4, tau=0.01, reward_scale=1.0, update_repeat=1, n_step=3,
                     policy_delay=1, target_noise=None, noise_clip=0.3, exploration_std_start=1.0,
                     exploration_std_end=0.1, exploration_std_updates=50_000, precision="float32",
                     frame_stack=STACK, augment_pad=4, encoder=encoder)


class FramesBatches:
    """Batches in the frames form from a pool of random frames on the host, read-only as the
    learner's decoded replies are (views of the message's bytes)."""

    def __init__(self, size: int, batch_size: int, device: str, pool: int = 4):
        rng = np.random.default_rng(0)
        n = FRAMES_PER_TRANSITION * batch_size
        self.frames = [rng.integers(0, 256, (n, 3, size, size), dtype=np.uint8) for _ in range(pool)]
        rows = np.arange(n).reshape(batch_size, FRAMES_PER_TRANSITION)
        self.obs_rows, self.next_rows = rows[:, :STACK], rows[:, STACK:]
        self.action = rng.random((batch_size, ACT_DIM), dtype=np.float32)
        self.reward = rng.random(batch_size, dtype=np.float32)
        self.terminated = np.zeros(batch_size, bool)
        self.discounts = np.full(batch_size, 0.99 ** 3, np.float32)
        for a in (*self.frames, self.obs_rows, self.next_rows, self.action, self.reward, self.terminated,
                  self.discounts):
            a.setflags(write=False)
        self.device, self.calls = device, 0

    def next(self):
        self.calls += 1
        return batch_from_frames({"pixels": self.frames[self.calls % len(self.frames)]}, self.obs_rows,
                                 self.next_rows, self.action, self.reward, self.terminated, device=self.device,
                                 discounts=self.discounts)


def synchronize(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


def rate(run_one, n: int, device: str) -> float:
    synchronize(device)
    started = time.perf_counter()
    for _ in range(n):
        run_one()
    synchronize(device)
    return n / (time.perf_counter() - started)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--device", choices=("cpu", "cuda"), default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--size", type=int, default=84, help="image side in pixels (default: %(default)s)")
    p.add_argument("--batch-size", type=int, default=256, help="transitions per batch (default: %(default)s)")
    p.add_argument("--updates", type=int, default=50, help="updates per timing round (default: %(default)s)")
    p.add_argument("--rounds", type=int, default=3, help="interleaved rounds; the median counts (default: %(default)s)")
    p.add_argument("--encoder", choices=tuple(IMAGE_VIEWS), default=DRQ,
                   help="the learner's --encoder: DrQ-v2's convolutions, or RLPixTuner's dual path "
                        "(default: %(default)s)")
    p.add_argument("--threads", type=int, default=torch.get_num_threads(), help="torch threads (default: all)")
    p.add_argument("--compile", choices=COMPILE_MODES, default="auto",
                   help="how the update runs (default: auto, as the learner daemon runs it: graphs on CUDA, eager on "
                        "CPU; the learner refuses the inductor modes for images, timed here all the same)")
    args = p.parse_args()
    if args.device == "cuda" and not torch.cuda.is_available():
        p.error("--device cuda: torch sees no CUDA device")
    torch.set_num_threads(args.threads)
    config = drqv2_config(args.batch_size, args.encoder)
    observation = ObservationSpec.parse(f"pixels: uint8[3, {args.size}, {args.size}]")
    state = init_state(config, observation, ACT_DIM, args.device, seed=0)
    mode = resolve_mode(args.compile, torch.device(args.device), images=True)
    steps = GradientSteps(update, config, mode, args.device, policy_delay=config.policy_delay)
    batches = FramesBatches(args.size, args.batch_size, args.device)
    resident = batches.next()

    def fed():
        steps(state, batches.next())

    def on_device():
        steps(state, resident)

    started = time.perf_counter()
    # Allocator, cuDNN's algorithm choice, lazy imports; compilation and the graph's capture after
    # its WARMUP_CALLS eager calls.
    for run_one in (fed, on_device):
        rate(run_one, WARMUP_CALLS + 1, args.device)
    warmup_s = time.perf_counter() - started
    rates: dict[str, list[float]] = {"fed": [], "resident": []}
    for _ in range(args.rounds):
        rates["fed"].append(rate(fed, args.updates, args.device))
        rates["resident"].append(rate(on_device, args.updates, args.device))
    result = {"bench": "pixel_update", "device": args.device, "torch": torch.__version__, "encoder": args.encoder,
              "compile": steps.mode, "warmup_s": round(warmup_s, 1), "size": args.size,
              "frame_stack": STACK, "batch_size": args.batch_size, "hidden": list(config.hidden),
              "threads": args.threads, "cpu": cpu_model(), "cpu_flags": cpu_flags(),
              "batch_frame_bytes": int(batches.frames[0].nbytes)}
    if args.device == "cuda":
        result["gpu"] = torch.cuda.get_device_name()
        result["peak_memory_mib"] = round(torch.cuda.max_memory_allocated() / 2**20)
    for name, values in rates.items():
        result[f"{name}_updates_per_s"] = round(statistics.median(values), 2)
        result[f"{name}_range"] = [round(min(values), 2), round(max(values), 2)]
    result["frames_to_500k_s"] = round(UPDATES_TO_500K_FRAMES / result["resident_updates_per_s"])
    result["seconds"] = round(time.perf_counter() - started, 1)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
