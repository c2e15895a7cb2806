"""The replay storage with camera observations, in process: what a shard of 84 x 84 RGB frames
does per chunk and per batch, without Zenoh.

Prints one JSON line: decode + insert of chunks of 64 frames (as the server stores them), and
sampling of batches of 256 in the frames form (stacks of 3 frames, one-step and 3-step returns):
the storage's time per batch, the encode time and size of the reply, and the distinct frames it
carries. Memory: bytes per stored transition against one frame's bytes. The chunks come from
episodes of 1,000 steps, so stacks rarely meet an episode start (the case where frames repeat).

With `--history`, the runner's float32[41] instead (an observation history, `--frame-stack k`):
batches of 256 in the version-1 form (obs and next obs) against the frames form with stacks of
1, 4 and 8, the storage's and the encoder's time per batch and the reply's size.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np
from env_speed import cpu_flags, cpu_model  # this folder's: the same machine record as the speed figures

from l2r.protocol import ExperienceChunk, decode, encode
from l2r.protocol.observations import ObservationSpec
from l2r.replay.storage import Storage, StorageConfig, observation_bytes

SPEC = ObservationSpec.parse("pixels: uint8[3, 84, 84]")
STEPS, EPISODE, ACT = 64, 1000, 6


def chunk_payloads(count: int) -> list[bytes]:
    """``count`` consecutive chunks of one environment's stream, random frames, encoded."""
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (count * STEPS + 1, 3, 84, 84), np.uint8)
    payloads = []
    for seq in range(count):
        steps = np.arange(seq * STEPS, (seq + 1) * STEPS)
        ends = steps % EPISODE == EPISODE - 1
        inner = np.flatnonzero(ends[:-1])
        payloads.append(encode(ExperienceChunk(
            0, 0, 1, seq, 0, {"pixels": frames[seq * STEPS:(seq + 1) * STEPS + 1]},
            rng.random((STEPS, ACT), np.float32), rng.random(STEPS, np.float32), ends, np.zeros(STEPS, bool),
            {"pixels": frames[seq * STEPS + inner + 1]})))
    return payloads


def per_call(fn, seconds: float) -> float:
    """Seconds one call of ``fn`` takes, over about ``seconds``."""
    n, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        fn()
        n += 1
    return (time.perf_counter() - start) / n


def history_figures(seconds: float, capacity: int = 200_000) -> dict:
    """The runner's vector: version-1 batches against stacks of 1, 4 and 8 observations."""
    spec, rng = ObservationSpec.vector(41), np.random.default_rng(0)
    storage = Storage(StorageConfig(capacity=capacity, act_dim=18, observation=spec))
    for seq in range(capacity // STEPS + 8):
        obs = rng.normal(size=(STEPS + 1, 41)).astype(np.float32)
        ends = (np.arange(seq * STEPS, (seq + 1) * STEPS) % EPISODE) == EPISODE - 1
        storage.insert(ExperienceChunk(0, 0, 1, seq, 0, obs, rng.random((STEPS, 18), np.float32),
                                       rng.random(STEPS, np.float32), ends, np.zeros(STEPS, bool),
                                       rng.normal(size=(int(ends[:-1].sum()), 41)).astype(np.float32)))
    figures = {"capacity": capacity, "observation": str(spec), "machine": f"{cpu_model()}, {os.cpu_count()} CPUs",
               "cpu_flags": cpu_flags(), "load_average": os.getloadavg()[0]}
    for stack in (None, 1, 4, 8):
        def draw():
            return storage.sample(256, False, frame_stack=stack)
        batch, form = draw(), f"stack{stack}" if stack else "version1"
        figures |= {f"{form}_sample_us": round(per_call(draw, seconds) * 1e6, 1),
                    f"{form}_encode_us": round(per_call(lambda: encode(batch), seconds) * 1e6, 1),
                    f"{form}_reply_bytes": len(encode(batch))}
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--capacity", type=int, default=16_384, help="slots of the storage (default 16,384: 390 MB)")
    parser.add_argument("--seconds", type=float, default=1.0, help="length of each timed phase")
    parser.add_argument("--history", action="store_true", help="the runner's vector in stacks instead of frames")
    args = parser.parse_args()
    if args.history:
        print(json.dumps(history_figures(args.seconds)))
        return

    storage = Storage(StorageConfig(capacity=args.capacity, act_dim=ACT, observation=SPEC))
    payloads = chunk_payloads(args.capacity // STEPS + 8)
    for payload in payloads:  # fill it, so the timed inserts below overwrite as a full shard does
        storage.insert(decode(payload))
    at = iter(range(10**9))
    insert_s = per_call(lambda: storage.insert(decode(payloads[next(at) % len(payloads)])), args.seconds)
    figures = {"capacity": args.capacity, "observation": str(SPEC), "chunk_steps": STEPS,
               "chunk_bytes": len(payloads[0]), "decode_insert_chunk_us": round(insert_s * 1e6, 1),
               "decode_insert_frames_per_s": round(STEPS / insert_s),
               "bytes_per_transition": round(storage.nbytes / args.capacity, 1),
               "frame_bytes": observation_bytes(SPEC),
               "bytes_per_transition_over_frame": round(storage.nbytes / args.capacity / observation_bytes(SPEC), 3)}
    for n_step in (1, 3):
        def draw():
            return storage.sample(256, False, n_step=n_step, gamma=0.99, frame_stack=3)
        batch = draw()
        figures |= {f"n{n_step}_sample_us": round(per_call(draw, args.seconds) * 1e6, 1),
                    f"n{n_step}_encode_us": round(per_call(lambda: encode(batch), args.seconds) * 1e6, 1),
                    f"n{n_step}_reply_bytes": len(encode(batch)),
                    f"n{n_step}_distinct_frames": len(batch.frames["pixels"])}
    print(json.dumps(figures))


if __name__ == "__main__":
    main()
