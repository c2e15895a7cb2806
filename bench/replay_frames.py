"""The replay storage with camera observations, in process: what a shard of 84 x 84 RGB frames
does per chunk and per batch, without Zenoh.

Prints one JSON line: decode + insert of chunks of 64 frames (as the server stores them), and
sampling of batches of 256 in the frames form (stacks of 3 frames, one-step and 3-step returns):
the storage's time per batch, the encode time and size of the reply, and the distinct frames it
carries. Memory: bytes per stored transition against one frame's bytes. The chunks come from
episodes of 1,000 steps, so stacks rarely meet an episode start (the case where frames repeat).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np

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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--capacity", type=int, default=16_384, help="slots of the storage (default 16,384: 390 MB)")
    parser.add_argument("--seconds", type=float, default=1.0, help="length of each timed phase")
    args = parser.parse_args()

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
