"""What compressing a camera chunk's frames costs and saves (l2r-actor --compress-frames).

    python bench/frame_compression.py [--episodes 3] [--steps 256] [--repeats 3]

Renders ``--episodes`` episodes of ``--steps`` random actions of each camera task (84 x 84
frames, kept in memory) and cuts them into chunks of 64 steps as an actor does (65 frames: a
chunk starts where the one before ended). For each chunk, raw and compressed (zstd at levels 1,
2 and 3 over the field's rows, the wire form; and, for comparison, each frame alone at level 1):

- bytes per frame (the encoded chunk over its 64 steps);
- the actor's CPU per chunk to encode it (``encode``, compression included);
- the replay shard's CPU per chunk to decode it (decompression included), and to take it in
  whole as a shard with a write-ahead log does (``on_experience``: the copy out of the Zenoh
  sample, decode, checks, insert, the log's CRC and write; an ack thread fsyncs every 0.5 s),
  per-thread CPU clocks, so other processes on a shared machine do not count.

From these: the frames a second one core of a shard ingests; the frames a second two cores
render, encode and ingest together (actors rendering, the shard ingesting, each frame once),
and encode and ingest alone (frames made at no cost: the bound where rendering is not the
work); and the frames a second a 1 Gbit/s link carries. Prints one JSON line, with the machine (``cpu_model``,
``cpu_flags``) and the load average before and after (the figures are CPU times, but a loaded
machine's caches are shared).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh
from env_speed import cpu_flags, cpu_model  # this folder's

from l2r.actors.actor import make_task
from l2r.protocol import ExperienceChunk, Keys, ObservationSpec, decode, encode
from l2r.protocol.frames_codec import FrameCompressor
from l2r.replay.rate_limiter import RateLimiter
from l2r.replay.server import ReplayServer, ServerConfig
from l2r.replay.storage import Storage, StorageConfig
from l2r.replay.wal import WriteAheadLog

TASKS = ("l2r/dmc-cartpole-swingup-v0", "l2r/dmc-walker-walk-v0")
STEPS_PER_CHUNK = 64
LEVELS = (1, 2, 3)
LINK_BYTES_PER_S = 1e9 / 8


def render(env_id: str, episodes: int, steps: int) -> tuple[list[np.ndarray], int, float]:
    """Each episode's frames (steps + 1, 3, 84, 84), the action width, and the process CPU
    seconds per rendered step (the renderer's threads count)."""
    env = make_task(env_id)
    rng = np.random.default_rng(0)
    out = []
    start = time.process_time()
    for episode in range(episodes):
        obs, _ = env.reset(seed=episode)
        frames = [obs["pixels"]]
        for _ in range(steps):
            obs, *_ = env.step(rng.random(env.action_space.shape).astype(np.float32))
            frames.append(obs["pixels"])
        out.append(np.stack(frames))
    cpu = (time.process_time() - start) / (episodes * steps)
    act_dim = env.action_space.shape[0]
    env.close()
    return out, act_dim, cpu


def chunks_of(episodes: list[np.ndarray], act_dim: int) -> list[ExperienceChunk]:
    rng = np.random.default_rng(1)
    chunks = []
    for frames in episodes:
        for start in range(0, len(frames) - STEPS_PER_CHUNK, STEPS_PER_CHUNK):
            pixels = frames[start:start + STEPS_PER_CHUNK + 1]
            chunks.append(ExperienceChunk(
                actor_id=0, env_id=0, epoch=1, seq=len(chunks), policy_version=0, obs={"pixels": pixels},
                actions=rng.random((STEPS_PER_CHUNK, act_dim), np.float32),
                rewards=rng.random(STEPS_PER_CHUNK, np.float32), terminated=np.zeros(STEPS_PER_CHUNK, bool),
                truncated=np.zeros(STEPS_PER_CHUNK, bool), final_obs={"pixels": pixels[:0]}))
    return chunks


def cpu_ms(work, items: list, repeats: int) -> float:
    """Median over ``repeats`` of the thread's CPU milliseconds per item of ``work(item)``."""
    times = []
    for _ in range(repeats):
        start = time.thread_time()
        for item in items:
            work(item)
        times.append((time.thread_time() - start) / len(items))
    return 1e3 * statistics.median(times)


class Sample:
    """What a Zenoh subscriber hands the shard: a key and the payload as ZBytes."""

    def __init__(self, payload: bytes):
        self.key_expr, self.payload = Keys("default").experience(0), zenoh.ZBytes(payload)


def ingest_ms(payloads: list[bytes], act_dim: int, repeats: int) -> float:
    """The shard's CPU milliseconds per chunk to take ``payloads`` in, with a write-ahead log
    (median over ``repeats`` fresh shards)."""
    spec = ObservationSpec.parse("pixels: uint8[3, 84, 84]")
    times = []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as directory:
            log = WriteAheadLog(Path(directory), 0)
            log.start(after=0)
            server = ReplayServer(ServerConfig(), Storage(StorageConfig(
                capacity=len(payloads) * STEPS_PER_CHUNK, act_dim=act_dim, observation=spec)), RateLimiter(), log)
            done = threading.Event()

            def acks() -> None:  # as the shard's main loop does
                while not done.wait(0.5):
                    server.ack()

            acker = threading.Thread(target=acks)
            acker.start()
            samples = [Sample(p) for p in payloads]
            start = time.thread_time()
            for sample in samples:
                server.on_experience(sample)
            times.append((time.thread_time() - start) / len(payloads))
            done.set()
            acker.join()
            log.close()
            assert server.rejections.total == 0, server.rejections.counters()
    return 1e3 * statistics.median(times)


def measure(env_id: str, episodes: int, steps: int, repeats: int) -> dict:
    frames, act_dim, render_s = render(env_id, episodes, steps)
    chunks = chunks_of(frames, act_dim)
    forms = {"raw": None, **{f"zstd{level}": FrameCompressor(level) for level in LEVELS}}
    out: dict = {"frames": sum(len(f) for f in frames), "chunks": len(chunks),
                 "render_ms_per_frame": round(1e3 * render_s, 2)}
    for name, compressor in forms.items():
        payloads = [encode(c, compressor) for c in chunks]
        bytes_per_frame = sum(map(len, payloads)) / (len(chunks) * STEPS_PER_CHUNK)
        encode_ms = cpu_ms(lambda c: encode(c, compressor), chunks, repeats)
        decode_ms = cpu_ms(decode, payloads, repeats)
        shard_ms = ingest_ms(payloads, act_dim, repeats)
        per_frame_s = (encode_ms + shard_ms) / 1e3 / STEPS_PER_CHUNK
        out[name] = {
            "bytes_per_frame": round(bytes_per_frame), "encode_ms_per_chunk": round(encode_ms, 3),
            "decode_ms_per_chunk": round(decode_ms, 3), "shard_ingest_ms_per_chunk": round(shard_ms, 3),
            "shard_frames_per_s_one_core": round(STEPS_PER_CHUNK / (shard_ms / 1e3)),
            "two_cores_frames_per_s": round(2 / (render_s + per_frame_s), 1),
            "two_cores_without_rendering_frames_per_s": round(2 / per_frame_s),
            "link_1gbit_frames_per_s": round(LINK_BYTES_PER_S / bytes_per_frame),
        }
    compressor = FrameCompressor(1)
    alone = [len(compressor.compress(frame)) for c in chunks for frame in c.obs["pixels"][1:]]
    out["zstd1_each_frame_alone_bytes_per_frame"] = round(statistics.mean(alone))
    out["zstd1_ratio"] = round(out["raw"]["bytes_per_frame"] / out["zstd1"]["bytes_per_frame"], 2)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=3, help="episodes rendered per task")
    parser.add_argument("--steps", type=int, default=256, help="random-action steps per episode")
    parser.add_argument("--repeats", type=int, default=3, help="timed passes over the chunks (median)")
    args = parser.parse_args()
    load_before = os.getloadavg()
    results = {env_id: measure(env_id, args.episodes, args.steps, args.repeats) for env_id in TASKS}
    print(json.dumps({
        "cpu_model": cpu_model(), "cpu_flags": cpu_flags(), "cpus": os.cpu_count(),
        "load_average_before": [round(x, 2) for x in load_before],
        "load_average_after": [round(x, 2) for x in os.getloadavg()],
        "frame_shape": [3, 84, 84], "steps_per_chunk": STEPS_PER_CHUNK, **results,
    }))


if __name__ == "__main__":
    main()
