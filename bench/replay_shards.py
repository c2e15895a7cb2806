"""Replay inserts per second while a learner samples, the experience spread over 1, 2, ... shards.

`l2r up --replay-shards N` starts N replay processes; actor i feeds shard i mod N and the learner
samples the shards in turn. This measures what that buys, each shard count in a phase of its own:
real `l2r-replay` processes over loopback Zenoh, each with its write-ahead log and snapshots in a
temporary directory as under `l2r up`; actor-like publisher processes send chunks of the runner's
transitions (64 each, the actors' default) as fast as the shards take them (congestion control
BLOCK, as actors send), or in bursts at a set rate (`--burst 512 --rate 16500`: an actor stepping
512 worlds at once, whose chunks all fill on the same step); one learner-like client samples
batches (640: the GPU recipe's) with four requests in flight, as fast as they come, and trains
nothing, or (`--learner "--hidden 64,64 ..."`) a real `l2r-learner` with those flags samples and
trains on the CPU. Each publisher also times how long its chunks wait for the shard's
acknowledgement: an actor resends a chunk unacknowledged after 3 s (l2r-actor --resend-delay).

The shards, the publishers and the sampler share the machine's cores: on a machine with few of
them, more shards compete for the same cores, and the figure that says what shards are worth is
the one from a many-core box. Prints one JSON line.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from dataclasses import replace
from pathlib import Path

import numpy as np
import zenoh

from l2r.job_plan import free_ports, loopback
from l2r.protocol import EXPERIENCE_QOS, Keys, ReplayClient, Stats, decode, encode, session_config, wait_alive
from l2r.protocol.messages import ExperienceChunk, ReplayAck

sys.path.insert(0, str(Path(__file__).parent))
from env_speed import cpu_flags, cpu_model  # noqa: E402  (this folder's: the same machine record)

OBS, ACT, STEPS = 41, 18, 64


def publish(actor_id: int, shards: int, endpoints: list[str], run: str, rate: float, burst: int, stop: mp.Event,
            ack_waits: mp.Queue) -> None:
    """An actor-like process: chunks of random transitions to its shard until `stop`, `burst` at a
    time at `rate` transitions/s (0: as fast as they go); then the seconds each chunk waited for
    the shard's acknowledgement, to `ack_waits`."""
    rng = np.random.default_rng(actor_id)
    chunk = ExperienceChunk(actor_id, 0, 1, 0, 0, rng.standard_normal((STEPS + 1, OBS), np.float32),
                            rng.uniform(0, 1, (STEPS, ACT)).astype(np.float32), rng.standard_normal(STEPS, np.float32),
                            np.zeros(STEPS, bool), np.zeros(STEPS, bool), np.zeros((0, OBS), np.float32))
    keys, sent, waits, lock = Keys(run), {}, [], threading.Lock()

    def on_ack(sample: zenoh.Sample) -> None:
        ack, now = decode(sample.payload, ReplayAck), time.perf_counter()
        rows = np.flatnonzero(ack.actor_ids == actor_id)
        with lock:
            for seq in [s for s in sent if rows.size and s <= ack.highest[rows[0]]]:
                waits.append(now - sent.pop(seq))

    with zenoh.open(session_config(connect=endpoints)) as session:
        acks = session.declare_subscriber(keys.replay_ack(actor_id % shards), on_ack)
        publisher = session.declare_publisher(keys.experience(actor_id, shards), **EXPERIENCE_QOS.publisher())
        seq, next_burst = 0, time.perf_counter()
        while not stop.is_set():
            for _ in range(burst):
                with lock:
                    sent[seq] = time.perf_counter()
                publisher.put(encode(replace(chunk, seq=seq)))
                seq += 1
            if rate:
                next_burst += burst * STEPS / rate
                time.sleep(max(0.0, next_burst - time.perf_counter()))
        acks.undeclare()
    ack_waits.put(waits)


def counters(session: zenoh.Session, keys: Keys, shards: int) -> np.ndarray:
    """Each shard's counts of inserted transitions and sampled batches, asked of it now."""
    counts = []
    for shard in range(shards):
        replies = [r for r in session.get(keys.stats("replay", shard), timeout=10) if r.ok is not None]
        values = decode(replies[0].ok.payload, Stats).values
        counts.append((values["inserted"], values["sampled_batches"]))
    return np.array(counts, float)


def sample(session: zenoh.Session, run: str, batch_size: int, done: threading.Event) -> None:
    """A learner-like client: batches as fast as they come until `done`, trained on by nothing."""
    with ReplayClient(session, run, batch_size=batch_size, in_flight=4) as client:
        while not done.is_set():
            client.sample(timeout=60)


def phase(shards: int, args: argparse.Namespace) -> dict:
    """Inserts/s summed over `shards` shards and batches/s drawn, over `args.seconds` after
    `args.warmup`, and how long chunks waited for their acknowledgement over the whole phase."""
    run, ctx = f"bench-{uuid.uuid4().hex[:8]}", mp.get_context("spawn")
    keys, endpoints = Keys(run), [loopback(port) for port in free_ports(shards)]
    stop, ack_waits = ctx.Event(), ctx.Queue()
    with tempfile.TemporaryDirectory() as directory:
        servers = [subprocess.Popen([sys.executable, "-m", "l2r.replay", "--run", run, "--shard", str(k),
                                     "--num-shards", str(shards), "--listen", endpoint,
                                     "--capacity", str(args.capacity // shards), "--min-size", str(args.batch_size),
                                     "--snapshot-dir", directory, "--log-level", "WARNING"])
                   for k, endpoint in enumerate(endpoints)]
        senders = [ctx.Process(target=publish, args=(i, shards, endpoints, run, args.rate, args.burst, stop, ack_waits))
                   for i in range(args.publishers)]
        learner, sampler, done = None, None, threading.Event()
        try:
            with zenoh.open(session_config(connect=endpoints)) as session:
                for k in range(shards):
                    if not wait_alive(session, keys.alive("replay", k), timeout=60):
                        raise SystemExit(f"replay shard {k} did not come up")
                for sender in senders:
                    sender.start()
                if args.learner is None:
                    sampler = threading.Thread(target=sample, args=(session, run, args.batch_size, done))
                    sampler.start()
                else:
                    learner = subprocess.Popen([sys.executable, "-m", "l2r.learner", "--run", run, "--log-level",
                                                "WARNING", *[flag for e in endpoints for flag in ("--connect", e)],
                                                "--batch-size", str(args.batch_size), *args.learner.split()])
                deadline = time.monotonic() + 120  # a learner's start (torch) takes seconds on a loaded box
                while not counters(session, keys, shards)[:, 1].sum() and time.monotonic() < deadline:
                    time.sleep(0.5)
                time.sleep(args.warmup)
                before, start = counters(session, keys, shards), time.perf_counter()
                time.sleep(args.seconds)
                elapsed, after = time.perf_counter() - start, counters(session, keys, shards)
                done.set()
                if sampler is not None:
                    sampler.join(60)
        finally:
            done.set()
            if learner is not None:
                learner.terminate()
                learner.wait(60)
            stop.set()
            waits = np.concatenate([ack_waits.get(timeout=60) for sender in senders if sender.pid] + [[]])
            for sender in senders:
                sender.join(30)
            for server in servers:
                server.terminate()
                server.wait(60)
    inserts, batches = ((after - before) / elapsed).T
    return {"shards": shards, "inserts_per_s": round(inserts.sum()),
            "inserts_per_s_by_shard": [round(x) for x in inserts], "batches_per_s": round(batches.sum(), 1),
            "ack_wait_s_median": round(float(np.median(waits)), 3), "ack_wait_s_max": round(float(waits.max()), 3),
            "chunks_waiting_over_3_s": int((waits > 3.0).sum())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--shards", default="1,2", help="shard counts to measure, one phase each")
    parser.add_argument("--publishers", type=int, default=2, help="actor-like publisher processes (actor ids 0..)")
    parser.add_argument("--capacity", type=int, default=1_000_000, help="replay capacity of the job, split over shards")
    parser.add_argument("--batch-size", type=int, default=640)
    parser.add_argument("--warmup", type=float, default=5.0, help="seconds of each phase not measured")
    parser.add_argument("--seconds", type=float, default=20.0, help="measured seconds of each phase")
    parser.add_argument("--burst", type=int, default=1, help="chunks each publisher sends back to back")
    parser.add_argument("--rate", type=float, default=0.0,
                        help="transitions/s of each publisher, in bursts (0: as fast as the shard takes them)")
    parser.add_argument("--learner", metavar="FLAGS",
                        help="sample with a real l2r-learner given these flags (besides --run, --connect and "
                             "--batch-size), e.g. \"--hidden 64,64 --update-repeat 3\", instead of a client that "
                             "trains nothing")
    args = parser.parse_args()
    phases = [phase(int(n), args) for n in args.shards.split(",")]
    print(json.dumps({"cpu": cpu_model(), "cpu_flags": cpu_flags(), "cores": mp.cpu_count(), "publishers": args.publishers, "capacity": args.capacity,
                      "batch_size": args.batch_size, "transitions_per_chunk": STEPS, "burst": args.burst,
                      "rate": args.rate, "learner": args.learner, "phases": phases}))


if __name__ == "__main__":
    main()
