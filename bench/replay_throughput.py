"""Replay server throughput over loopback Zenoh, against raw Zenoh and a manager-proxy baseline.

Prints one JSON line. Phases, all in one run:
  raw      actor-like publisher processes send encoded chunks to a bare Zenoh subscriber process
  ingest   the same processes send the same bytes to a real ``l2r-replay`` process (it fills up)
  sample   a learner-like client samples batches of 256 from it, several requests in flight
           (one-step, prioritized, and 3-step returns)
  numpy    plain in-process numpy sampling of the same batch (the limit for sampling)
  baseline a multiprocessing manager proxy around a list: one transition per push call,
           ``random.sample`` per batch (the reference solution's replay design)
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import random
import socket
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from multiprocessing.managers import BaseManager
from pathlib import Path

import numpy as np
import zenoh

from l2r.protocol import EXPERIENCE_QOS, Keys, ReplayClient, Stats, decode, encode, session_config, wait_alive
from l2r.protocol.messages import ExperienceChunk

OBS, ACT = 41, 18


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def make_payloads(actor_id: int, chunks: int, steps: int) -> list[bytes]:
    rng = np.random.default_rng(actor_id)
    obs = rng.standard_normal((steps + 1, OBS), np.float32)
    obs[-1] = obs[0]  # each chunk starts where the one before ended, so the shard links them as an actor's
    actions = rng.uniform(0, 1, (steps, ACT)).astype(np.float32)
    rewards = rng.standard_normal(steps, np.float32)
    done = np.zeros(steps, bool)
    done[steps // 2] = True
    final = rng.standard_normal((1, OBS), np.float32)
    return [encode(ExperienceChunk(actor_id, 0, 1, seq, 0, obs, actions, rewards, done, np.zeros(steps, bool), final))
            for seq in range(chunks)]


def publisher(actor_id: int, endpoints: list[str], run: str, chunks: int, steps: int, go: mp.Barrier) -> None:
    """An actor-like process: sends its chunks to the raw sink, then to replay."""
    payloads = make_payloads(actor_id, chunks, steps)
    keys = Keys(run)
    with zenoh.open(session_config(connect=endpoints)) as session:
        for key in (f"{keys.root}/bench/raw/{actor_id}", keys.experience(actor_id)):
            pub = session.declare_publisher(key, **EXPERIENCE_QOS.publisher())
            go.wait()
            for payload in payloads:
                pub.put(payload)
            go.wait()
            pub.undeclare()


def raw_sink(endpoint: str, run: str, expected_bytes: int, results: mp.Queue, ready: mp.Event) -> None:
    """A bare Zenoh subscriber process: counts bytes, no decoding, no storing."""
    state = {"bytes": 0, "first": None}
    done = threading.Event()

    def on_sample(sample: zenoh.Sample) -> None:
        state["first"] = state["first"] or time.perf_counter()
        state["bytes"] += len(sample.payload)
        if state["bytes"] >= expected_bytes:
            state["last"] = time.perf_counter()
            done.set()

    with zenoh.open(session_config(listen=[endpoint])) as session:
        sub = session.declare_subscriber(f"{Keys(run).root}/bench/raw/*", on_sample)
        ready.set()
        done.wait(300)
        sub.undeclare()
    results.put(state["bytes"] / (state["last"] - state["first"]))


def rss_bytes(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    return 0


class ListBuffer:
    """The baseline's buffer: a Python list of transition tuples."""

    def __init__(self, capacity: int):
        self.capacity, self.items, self.position = capacity, [], 0

    def push(self, transition) -> None:
        if len(self.items) < self.capacity:
            self.items.append(transition)
        else:
            self.items[self.position] = transition
        self.position = (self.position + 1) % self.capacity

    def sample(self, batch_size: int):
        return random.sample(self.items, batch_size)

    def size(self) -> int:
        return len(self.items)


class BufferManager(BaseManager):
    pass


BufferManager.register("ListBuffer", ListBuffer)


def measure_baseline(pushers: int, seconds: float, capacity: int) -> tuple[float, float]:
    manager = BufferManager()
    manager.start()
    buffer = manager.ListBuffer(capacity)
    ctx = mp.get_context("spawn")
    counts = ctx.Queue()
    procs = [ctx.Process(target=baseline_push, args=(buffer, seconds, counts)) for _ in range(pushers)]
    for p in procs:
        p.start()
    pushed = sum(counts.get() for _ in procs)
    for p in procs:
        p.join()
    ingest = pushed / seconds
    batches, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        items = buffer.sample(256)
        [np.stack(column) for column in zip(*items)]  # what a learner does next
        batches += 1
    sample = batches / (time.perf_counter() - start)
    manager.shutdown()
    return ingest, sample


def baseline_push(buffer, seconds: float, counts: mp.Queue) -> None:
    rng = np.random.default_rng()
    obs, action = rng.standard_normal(OBS).astype(np.float32), rng.uniform(0, 1, ACT).astype(np.float32)
    n, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        buffer.push((obs, action, 0.5, obs, False))
        n += 1
    counts.put(n)


def numpy_sampling(capacity: int, seconds: float) -> float:
    rng = np.random.default_rng(0)
    obs, nxt = np.zeros((capacity, OBS), np.float32), np.zeros((capacity, OBS), np.float32)
    act, rew, done = np.zeros((capacity, ACT), np.float32), np.zeros(capacity, np.float32), np.zeros(capacity, bool)
    batches, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        i = rng.integers(0, capacity, 256)
        obs[i], act[i], rew[i], nxt[i], done[i]
        batches += 1
    return batches / (time.perf_counter() - start)


def in_process_figures(capacity: int, steps: int) -> dict:
    """In-process figures on a full storage: decode + insert speed without Zenoh (the
    server's own ceiling), and a snapshot: how long inserts are held up, copy and write."""
    from l2r.replay import snapshot
    from l2r.replay.rate_limiter import RateLimiter
    from l2r.replay.server import ReplayServer, ServerConfig
    from l2r.replay.storage import Storage, StorageConfig

    server = ReplayServer(ServerConfig(), Storage(StorageConfig(capacity=capacity)), RateLimiter())
    payload = make_payloads(0, 1, steps)[0]
    for _ in range(capacity // steps + 1):  # fill it, so the timed inserts below overwrite
        server.storage.insert(decode(payload))
    start, n = time.perf_counter(), 0
    while time.perf_counter() - start < 1.0:  # the server's work per chunk, without Zenoh
        server.storage.insert(decode(payload))
        n += 1
    in_process = n * steps / (time.perf_counter() - start)
    sample_us = {n_step: sample_time(server.storage, n_step) * 1e6 for n_step in (1, 3)}
    start = time.perf_counter()
    arrays, meta = server.capture()
    copied = time.perf_counter()
    with tempfile.TemporaryDirectory() as directory:
        size = snapshot.write(Path(directory) / "replay-shard0.npz", arrays, meta)
    written = time.perf_counter()
    return {"in_process_decode_insert_transitions_per_s": round(in_process),
            "snapshot_longest_hold_up_s": round(server.snapshot_pause, 4), "snapshot_copy_s": round(copied - start, 3),
            "snapshot_write_s": round(written - copied, 3), "snapshot_bytes": size,
            "bytes_per_transition": round(server.storage.nbytes / capacity, 1),
            "in_process_sample_us": round(sample_us[1], 1), "in_process_n_step_3_sample_us": round(sample_us[3], 1)}


def sample_time(storage, n_step: int, seconds: float = 1.0) -> float:
    """Seconds the storage takes to draw one uniform batch of 256 (n-step returns with gamma 0.99)."""
    n, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        storage.sample(256, False, n_step=n_step, gamma=0.99)
        n += 1
    return (time.perf_counter() - start) / n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="smaller capacity and shorter phases")
    parser.add_argument("--capacity", type=int, help="replay capacity (default 1,000,000; --quick 200,000)")
    parser.add_argument("--publishers", type=int, default=2)
    parser.add_argument("--steps", type=int, default=1000, help="transitions per chunk")
    parser.add_argument("--seconds", type=float, default=3.0, help="length of each timed sampling phase")
    args = parser.parse_args()
    capacity = args.capacity or (200_000 if args.quick else 1_000_000)
    seconds = 1.5 if args.quick else args.seconds
    # send 1.5x capacity so the server is full (and evicting) by the end
    chunks = max(1, int(1.5 * capacity / args.steps / args.publishers))
    run = f"bench-{uuid.uuid4().hex[:8]}"
    keys = Keys(run)
    replay_ep, sink_ep = free_endpoint(), free_endpoint()
    ctx = mp.get_context("spawn")

    server = subprocess.Popen(
        [sys.executable, "-m", "l2r.replay", "--run", run, "--listen", replay_ep, "--capacity", str(capacity),
         "--min-size", "1", "--stats-interval", "0.1", "--log-level", "WARNING"])
    results, sink_ready = ctx.Queue(), ctx.Event()
    payload_bytes = len(make_payloads(0, 1, args.steps)[0])
    sink = ctx.Process(target=raw_sink, args=(sink_ep, run, payload_bytes * chunks * args.publishers, results, sink_ready))
    sink.start()
    try:
        with zenoh.open(session_config(connect=[replay_ep])) as session:
            if not wait_alive(session, keys.alive("replay", 0), timeout=30):
                raise SystemExit("replay server did not come up")
            sink_ready.wait(30)
            stats: list[tuple[float, dict]] = []
            session.declare_subscriber(keys.stats("replay", 0),
                                       lambda s: stats.append((decode(s.payload, Stats).time, decode(s.payload, Stats).values)))
            go = ctx.Barrier(args.publishers + 1)
            pubs = [ctx.Process(target=publisher, args=(i, [replay_ep, sink_ep], run, chunks, args.steps, go))
                    for i in range(args.publishers)]
            for p in pubs:
                p.start()
            # publishers keep their sessions open until everything arrived: closing a
            # session drops what is still queued in it
            go.wait()  # raw phase
            raw_bytes_per_s = results.get(timeout=300)
            go.wait()
            sink.join()
            go.wait()  # ingest phase
            total = chunks * args.steps * args.publishers
            deadline = time.time() + 120
            while not (stats and stats[-1][1]["inserted"] >= total) and time.time() < deadline:
                time.sleep(0.05)
            go.wait()
            for p in pubs:
                p.join()
            moving = [(t, v["inserted"]) for t, v in stats if v["inserted"] > 0]
            t0, n0 = next((t, n) for t, n in moving)
            if moving[-1][1] < total:
                raise SystemExit(f"replay stored {moving[-1][1]} of {total} transitions sent; last stats {stats[-1][1]}")
            t1, n1 = next((t, n) for t, n in moving if n >= total)
            # the first report already holds what arrived during its interval
            ingest = n1 / (t1 - t0 + 0.1) if n0 else float("nan")
            resident = rss_bytes(server.pid)
            size = stats[-1][1]["size"]

            def batches_per_s(prioritized: bool, n_step: int = 1) -> float:
                with ReplayClient(session, run, batch_size=256, in_flight=16, prioritized=prioritized,
                                  n_step=n_step, gamma=0.99) as client:
                    client.sample(timeout=30)
                    n, start = 0, time.perf_counter()
                    while time.perf_counter() - start < seconds:
                        client.sample(timeout=30)
                        n += 1
                    return n / (time.perf_counter() - start)

            sample_rate = batches_per_s(prioritized=False)
            prioritized_rate = batches_per_s(prioritized=True)
            n_step_rate = batches_per_s(prioritized=False, n_step=3)
    finally:
        server.terminate()
        server.wait(60)
        if sink.is_alive():
            sink.kill()

    numpy_rate = numpy_sampling(capacity, seconds)
    base_ingest, base_sample = measure_baseline(args.publishers, seconds, capacity)
    snapshots = in_process_figures(capacity, args.steps)
    ingest_bytes_per_s = ingest * payload_bytes / args.steps
    print(json.dumps({
        "capacity": capacity,
        "size_at_end": size,
        "publishers": args.publishers,
        "transitions_per_chunk": args.steps,
        "chunk_bytes": payload_bytes,
        "ingest_transitions_per_s": round(ingest),
        "ingest_bytes_per_s": round(ingest_bytes_per_s),
        "raw_zenoh_bytes_per_s": round(raw_bytes_per_s),
        "ingest_fraction_of_raw_zenoh": round(ingest_bytes_per_s / raw_bytes_per_s, 3),
        "sample_batches_per_s": round(sample_rate, 1),
        "prioritized_sample_batches_per_s": round(prioritized_rate, 1),
        "n_step_3_sample_batches_per_s": round(n_step_rate, 1),
        "numpy_sample_batches_per_s": round(numpy_rate, 1),
        "sample_fraction_of_numpy": round(sample_rate / numpy_rate, 3),
        "baseline_ingest_transitions_per_s": round(base_ingest),
        "baseline_sample_batches_per_s": round(base_sample, 1),
        "ingest_vs_baseline": round(ingest / base_ingest, 1),
        "sample_vs_baseline": round(sample_rate / base_sample, 1),
        "resident_bytes_at_capacity": resident,
        **snapshots,
    }))


if __name__ == "__main__":
    main()
