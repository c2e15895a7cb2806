"""Camera frames through l2r's replay over loopback Zenoh, against raw Zenoh and DrQ-v2's replay.

Prints one JSON line. Phases, one after another in one run, each ``--seconds`` long:
  ingest    actor-like processes publish chunks of 64 steps of 84 x 84 RGB frames (1.4 MB each)
            to a real ``l2r-replay`` process (``--observation "pixels: uint8[3, 84, 84]"``,
            ``--side-fraction 0.0625``): frames stored per second
  sample    a learner-like process asks that shard for batches of 256 transitions with stacks
            of 3 frames (9 x 84 x 84 observations and next observations, in the frames form),
            ``--in-flight`` queries outstanding, and decodes every reply
  raw       bare Zenoh between two processes of the same kinds: a queryable answering each
            query with a payload of one batch's bytes, a querier with the same queries in flight;
            sample and raw take ``--rounds`` turns each, ``--seconds`` in all between them, and
            the figures are the turns' medians, with the CPU time shard and learner spent per batch
  baseline  DrQ-v2's replay design (facebookresearch/drqv2, replay_buffer.py), rebuilt here:
            actor processes save each episode (500 steps, as DrQ-v2's 1,000 environment steps
            at action repeat 2) of stacked observations as a compressed .npz file; the worker
            processes of a torch DataLoader load the files, draw transitions with n-step
            returns and hand batches of 256 to the learner-like main process

The frames are image-like (blocks of 4 x 4 pixels of one value, plus a little noise), so the
baseline's compression sees something closer to a camera's frames than noise; l2r sends them
uncompressed. Phases run one at a time so that each has the machine's cores to itself; on a
shared machine compare the ratios of one run rather than figures of different runs.

    python bench/pixels.py [--seconds 10] [--rounds 3] [--actors 2] [--in-flight 2] [--n-step 1]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import random
import socket
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import zenoh

from l2r.protocol import (
    EXPERIENCE_QOS, SAMPLE_QOS, ExperienceChunk, Keys, SampleBatch, SampleRequest, Stats, decode, encode,
    reuse_large_buffers, session_config, wait_alive, with_reply_pool,
)
from l2r.protocol.observations import ObservationSpec
from l2r.replay.storage import StorageConfig, observation_bytes, storage_bytes

sys.path.insert(0, str(Path(__file__).parent))
from env_speed import cpu_flags, cpu_model  # noqa: E402  (this folder's: the same machine record)
from replay_throughput import rss_bytes  # noqa: E402

SPEC = ObservationSpec.parse("pixels: uint8[3, 84, 84]")
FRAME_STACK, BATCH, STEPS, ACT = 3, 256, 64, 6
SIDE_FRACTION = 0.0625  # the side rows that meet the 1.1x memory budget (docs/observations.md)
POOL = 4 * STEPS  # distinct frames an actor cycles through
EPISODE = 500  # DrQ-v2's episodes: 1,000 environment steps at action repeat 2


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def image_like(rng: np.random.Generator, n: int) -> np.ndarray:
    """``n`` frames of 3 x 84 x 84: 21 x 21 random blocks of 4 x 4 pixels, plus noise of 0-3."""
    blocks = rng.integers(0, 252, (n, 3, 21, 21), np.uint8).repeat(4, axis=2).repeat(4, axis=3)
    return blocks + rng.integers(0, 4, blocks.shape, np.uint8)


# -- l2r ------------------------------------------------------------------------------------

def actor(actor_id: int, endpoint: str, run: str, seconds: float, go, results) -> None:
    """Publishes chunks of one environment stream as fast as the shard takes them (congestion
    control BLOCK, as l2r-actor publishes); each chunk starts where the one before it ended."""
    rng = np.random.default_rng(actor_id)
    pool = image_like(rng, POOL + 1)
    pool[POOL] = pool[0]
    actions = rng.uniform(-1, 1, (STEPS, ACT)).astype(np.float32)
    rewards = rng.standard_normal(STEPS).astype(np.float32)
    running, no_end = np.zeros(STEPS, bool), {"pixels": pool[:0]}
    with zenoh.open(session_config(connect=[endpoint])) as session:
        publisher = session.declare_publisher(Keys(run).experience(actor_id), **EXPERIENCE_QOS.publisher())
        epoch = time.time_ns()
        go.wait()
        start, seq = time.time(), 0
        while time.time() - start < seconds:
            at = seq * STEPS % POOL
            publisher.put(encode(ExperienceChunk(actor_id, 0, epoch, seq, 0, {"pixels": pool[at:at + STEPS + 1]},
                                                 actions, rewards, running, running, no_end)))
            seq += 1
        results.put((start, seq * STEPS))
        go.wait()  # a closing session drops what it still queues: stay until the shard has it all


def querier(endpoint: str, key: str, request: bytes, seconds: float, in_flight: int, decode_batches: bool,
            results) -> None:
    """A learner-like process: ``in_flight`` queries outstanding; each reply is decoded as a
    batch of frames (``decode_batches``) or only counted (raw Zenoh). Puts (replies per s, bytes per s,
    mean reply bytes, this process's CPU seconds per reply) measured after the first two replies, and the
    replies in all."""
    if decode_batches:
        reuse_large_buffers()  # as a pixel learner's process does
    lock, slots = threading.Lock(), threading.Semaphore(in_flight)
    counts = {"replies": 0, "bytes": 0, "errors": 0, "start": None, "at_start": (0, 0, 0.0)}

    def on_reply(reply: zenoh.Reply) -> None:
        if reply.ok is None:
            with lock:
                counts["errors"] += 1
            return
        size = len(reply.ok.payload)
        wrong = decode_batches and decode(reply.ok.payload, SampleBatch).obs_frames.shape != (BATCH, FRAME_STACK)
        with lock:
            counts["errors"] += wrong
            counts["replies"] += 1
            counts["bytes"] += size
            if counts["replies"] == 2:  # the first replies include the connection's warm-up
                counts["start"], counts["at_start"] = time.perf_counter(), (2, counts["bytes"], time.process_time())

    with zenoh.open(session_config(connect=[endpoint])) as session:
        deadline = None
        while deadline is None or time.perf_counter() < deadline:
            if not slots.acquire(timeout=1.0):
                continue
            session.get(key, zenoh.handlers.Callback(on_reply, slots.release, indirect=False), payload=request,
                        timeout=30.0, **SAMPLE_QOS.put())
            with lock:
                if deadline is None and counts["start"] is not None:
                    deadline = counts["start"] + seconds
        for _ in range(in_flight):  # the last replies, before the session closes
            slots.acquire(timeout=30.0)
        with lock:
            elapsed, cpu = time.perf_counter() - counts["start"], time.process_time() - counts["at_start"][2]
            replies, size = counts["replies"] - 2, counts["bytes"] - counts["at_start"][1]
    if counts["errors"]:
        raise SystemExit(f"{counts['errors']} error replies or batches without stacks of {FRAME_STACK}")
    results.put((replies / elapsed, size / elapsed, size / max(1, replies), cpu / max(1, replies), counts["replies"]))


def raw_server(endpoint: str, key: str, reply_bytes: int, ready) -> None:
    """Answers every query on ``key`` with the same ``reply_bytes`` bytes, no encoding, with the
    shared-memory pool a replay shard has."""
    payload = zenoh.ZBytes(os.urandom(reply_bytes))
    with zenoh.open(with_reply_pool(session_config(listen=[endpoint]))) as session:  # the shard's pool
        queryable = session.declare_queryable(
            key, zenoh.handlers.Callback(lambda q: q.reply(q.key_expr, payload), indirect=False))
        ready.set()
        threading.Event().wait()  # until terminated
        queryable.undeclare()


def cpu_seconds(pid: int) -> float:
    """User and system CPU time process ``pid`` has used."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def measure_l2r(args, ctx) -> dict:
    run, endpoint = f"bench-{uuid.uuid4().hex[:8]}", free_endpoint()
    keys = Keys(run)
    shard = subprocess.Popen(
        [sys.executable, "-m", "l2r.replay", "--run", run, "--listen", endpoint, "--capacity", str(args.capacity),
         "--observation", str(SPEC), "--act-dim", str(ACT), "--side-fraction", str(SIDE_FRACTION),
         "--min-size", "1", "--stats-interval", "0.1", "--log-level", "WARNING"])
    try:
        with zenoh.open(session_config(connect=[endpoint])) as session:
            if not wait_alive(session, keys.alive("replay", 0), timeout=60):
                raise SystemExit("the replay shard did not come up")
            inserted: list[tuple[float, int]] = []  # (shard's clock, transitions stored) of each stats report

            def on_stats(sample: zenoh.Sample) -> None:
                report = decode(sample.payload, Stats)
                inserted.append((report.time, report.values["inserted"]))

            stats = session.declare_subscriber(keys.stats("replay", 0), on_stats)
            go, sent = ctx.Barrier(args.actors + 1), ctx.Queue()
            actors = [ctx.Process(target=actor, args=(i, endpoint, run, args.seconds, go, sent))
                      for i in range(args.actors)]
            for p in actors:
                p.start()
            go.wait()
            starts, frames = zip(*(sent.get(timeout=args.seconds + 120) for _ in actors))
            total = sum(frames)
            deadline = time.time() + 120
            while not (inserted and inserted[-1][1] >= total) and time.time() < deadline:
                time.sleep(0.05)
            go.wait()
            for p in actors:
                p.join()
            done = next((t for t, n in inserted if n >= total), None)
            if done is None:
                raise SystemExit(f"the shard stored {inserted[-1][1] if inserted else 0} of {total} frames sent")
            stats.undeclare()
        resident = rss_bytes(shard.pid)
        request = encode(SampleRequest(BATCH, 1, False, -1, None, args.n_step if args.n_step > 1 else None,
                                       0.99 if args.n_step > 1 else None, FRAME_STACK))
        sampled, raw = take_turns(args, ctx, endpoint, keys, request, shard.pid)
    finally:
        shard.terminate()
        shard.wait(60)
    stored = storage_bytes(StorageConfig(capacity=args.capacity, act_dim=ACT, side_fraction=SIDE_FRACTION,
                                         observation=SPEC))
    (batches_per_s, bytes_per_s, batch_bytes, learner_cpu, shard_cpu), (raw_replies_per_s, raw_bytes_per_s, _,
                                                                      raw_querier_cpu, raw_server_cpu) = (
        np.median(sampled, axis=0), np.median(raw, axis=0))
    return {"ingest_frames_per_s": round(total / (done - min(starts))), "frames_sent": total,
            "stacked_batches_per_s": round(batches_per_s, 1), "batch_bytes": round(batch_bytes),
            "sample_bytes_per_s": round(bytes_per_s), "raw_zenoh_bytes_per_s": round(raw_bytes_per_s),
            "raw_zenoh_replies_per_s": round(raw_replies_per_s, 1),
            "shard_cpu_ms_per_batch": round(shard_cpu * 1e3, 1),
            "learner_cpu_ms_per_batch": round(learner_cpu * 1e3, 1),
            "raw_server_cpu_ms_per_reply": round(raw_server_cpu * 1e3, 1),
            "raw_querier_cpu_ms_per_reply": round(raw_querier_cpu * 1e3, 1),
            "sample_fraction_of_raw_zenoh": round(float(np.median([s[1] / r[1] for s, r in zip(sampled, raw)])), 3),
            "stacked_batches_per_s_by_round": [round(s[0], 1) for s in sampled],
            "raw_zenoh_replies_per_s_by_round": [round(r[0], 1) for r in raw],
            "replay_bytes_per_frame": round(stored / args.capacity), "replay_resident_bytes": resident}


def take_turns(args, ctx, endpoint: str, keys: Keys, request: bytes, shard: int) -> tuple[list, list]:
    """``--rounds`` turns of the learner-like process sampling the shard, then the raw querier
    asking the raw server for replies of the batch's size, each ``--seconds`` / ``--rounds``
    long: on a shared machine, the load changes less within a turn than across a whole phase.
    Returns each turn's (replies per s, bytes per s, bytes per reply, querier's and server's CPU
    seconds per reply), sampled and raw."""
    raw_endpoint, raw_key, ready, results = free_endpoint(), f"{keys.root}/bench/raw", ctx.Event(), ctx.Queue()
    seconds, sampled, raw, server = args.seconds / args.rounds, [], [], None
    try:
        for _ in range(args.rounds):
            learner = ctx.Process(target=querier, args=(endpoint, keys.sample(0), request, seconds, args.in_flight,
                                                        True, results))
            before = cpu_seconds(shard)
            learner.start()
            sampled.append(with_server_cpu(results.get(timeout=seconds + 120), cpu_seconds(shard) - before))
            learner.join()
            if server is None:  # replies of the size of the first turn's batches
                server = ctx.Process(target=raw_server, args=(raw_endpoint, raw_key, round(sampled[0][2]), ready))
                server.start()
                ready.wait(60)
            querying = ctx.Process(target=querier, args=(raw_endpoint, raw_key, request, seconds, args.in_flight,
                                                         False, results))
            before = cpu_seconds(server.pid)
            querying.start()
            raw.append(with_server_cpu(results.get(timeout=seconds + 120), cpu_seconds(server.pid) - before))
            querying.join()
    finally:
        if server is not None:
            server.terminate()
            server.join(30)
    return sampled, raw


def with_server_cpu(turn: tuple, server_cpu: float) -> tuple:
    """A querier's figures with the server's CPU seconds per reply in place of the reply count."""
    *figures, replies = turn
    return (*figures, server_cpu / replies)


# -- DrQ-v2's replay design -----------------------------------------------------------------

def episode_writer(actor_id: int, actors: int, directory: str, seconds: float, go, results) -> None:
    """An actor as DrQ-v2's: each step's observation is the stack of its last 3 frames (its
    environment wrapper stacks them); at an episode's end the whole episode is saved as one
    compressed .npz file, named with its index and length as DrQ-v2 names them."""
    rng = np.random.default_rng(actor_id)
    frames = image_like(rng, EPISODE + 1)
    stacked = np.concatenate([frames[np.maximum(np.arange(EPISODE + 1) - lag, 0)] for lag in (2, 1, 0)], axis=1)
    episode = {"observation": stacked, "action": rng.uniform(-1, 1, (EPISODE + 1, ACT)).astype(np.float32),
               "reward": rng.standard_normal((EPISODE + 1, 1)).astype(np.float32),
               "discount": np.ones((EPISODE + 1, 1), np.float32)}
    go.wait()
    start, saved = time.time(), 0
    while saved == 0 or time.time() - start < seconds:  # one episode at least, so every loader worker has one
        index = actor_id + actors * saved
        path = Path(directory) / f"{index:06d}_{index}_{EPISODE}.npz"
        np.savez_compressed(path.with_suffix(".tmp.npz"), **episode)
        path.with_suffix(".tmp.npz").rename(path)  # (a reader never loads half a file)
        saved += 1
    results.put((start, time.time(), saved * EPISODE))


class EpisodeReplay:
    """DrQ-v2's sampling in each loader worker: it loads the episode files of its share (index
    modulo the workers) every ``fetch_every`` samples, keeps up to ``max_size`` transitions, and
    draws an episode, then a step, with the n-step return; torch's DataLoader batches the draws."""

    def __init__(self, directory: str, max_size: int, n_step: int, discount: float = 0.99, fetch_every: int = 1000):
        self.directory, self.max_size, self.n_step, self.discount = Path(directory), max_size, n_step, discount
        self.fetch_every = fetch_every
        self.episodes: dict[Path, dict[str, np.ndarray]] = {}
        self.size, self.since_fetch = 0, fetch_every

    def __iter__(self):
        import torch.utils.data
        info = torch.utils.data.get_worker_info()
        worker, workers = (info.id, info.num_workers) if info else (0, 1)
        while True:
            yield self.draw(worker, workers)

    def fetch(self, worker: int, workers: int) -> None:
        for path in sorted(self.directory.glob("*_*_*.npz"), reverse=True):  # newest first
            if path.name.endswith(".tmp.npz"):
                continue  # still being written
            index, length = (int(x) for x in path.stem.split("_")[1:])
            if index % workers != worker:
                continue
            if path in self.episodes:
                break
            with np.load(path) as loaded:
                self.episodes[path] = {name: loaded[name] for name in loaded.files}
            self.size += length
            while self.size > self.max_size:  # the oldest episodes go first
                self.size -= len(self.episodes.pop(min(self.episodes))["reward"]) - 1

    def draw(self, worker: int, workers: int):
        if self.since_fetch >= self.fetch_every:
            self.since_fetch = 0
            self.fetch(worker, workers)
        self.since_fetch += 1
        episode = self.episodes[random.choice(list(self.episodes))]
        i = np.random.randint(0, len(episode["reward"]) - self.n_step) + 1  # step 0: the first observation only
        reward, discount = np.zeros(1, np.float32), np.ones(1, np.float32)
        for step in range(self.n_step):
            reward += discount * episode["reward"][i + step]
            discount *= episode["discount"][i + step] * self.discount
        return (episode["observation"][i - 1], episode["action"][i], reward, discount,
                episode["observation"][i + self.n_step - 1])


def measure_baseline(args, ctx) -> dict:
    import torch.utils.data

    class Dataset(EpisodeReplay, torch.utils.data.IterableDataset):
        pass

    with tempfile.TemporaryDirectory(prefix="drqv2-replay-") as directory:
        go, results = ctx.Barrier(args.actors + 1), ctx.Queue()
        writers = [ctx.Process(target=episode_writer, args=(i, args.actors, directory, args.seconds, go, results))
                   for i in range(args.actors)]
        for p in writers:
            p.start()
        go.wait()
        spans = [results.get(timeout=args.seconds + 300) for _ in writers]
        for p in writers:
            p.join()
        ingest = sum(frames for _, _, frames in spans) / (max(e for _, e, _ in spans) - min(s for s, _, _ in spans))
        dataset = Dataset(directory, args.capacity // args.loader_workers, args.n_step)
        loader = torch.utils.data.DataLoader(dataset, batch_size=BATCH, num_workers=args.loader_workers,
                                             worker_init_fn=_seed_worker, multiprocessing_context="fork")
        batches = iter(loader)
        for _ in range(2):  # the workers' start and their first load of the files
            obs, *_ = next(batches)
        n, start = 0, time.perf_counter()
        while time.perf_counter() - start < args.seconds:
            obs, action, reward, discount, next_obs = next(batches)
            n += 1
        rate = n / (time.perf_counter() - start)
        del batches
        step_bytes = sum(int(np.prod(a.shape[1:])) * a.element_size() for a in (obs, action, reward, discount))
    return {"baseline_ingest_frames_per_s": round(ingest), "baseline_stacked_batches_per_s": round(rate, 1),
            "baseline_episodes_saved": sum(frames for _, _, frames in spans) // EPISODE,
            "baseline_replay_bytes_per_frame": step_bytes, "baseline_stacked_obs_shape": list(obs.shape[1:])}


def _seed_worker(worker: int) -> None:
    np.random.seed(worker)
    random.seed(worker)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=10.0, help="length of each phase (default 10)")
    parser.add_argument("--actors", type=int, default=2, help="actor-like processes in the ingest phases (default 2)")
    parser.add_argument("--rounds", type=int, default=3,
                        help="turns of sampling and raw Zenoh, --seconds between them (default 3)")
    parser.add_argument("--in-flight", type=int, default=2,
                        help="sample queries the learner-like process keeps outstanding (default 2)")
    parser.add_argument("--n-step", type=int, default=1, help="steps of the returns sampled, both designs (default 1)")
    parser.add_argument("--capacity", type=int, default=16_384,
                        help="transitions kept, by the shard and by the baseline's loader workers together "
                             "(default 16,384: 370 MB in the shard)")
    parser.add_argument("--loader-workers", type=int, default=2,
                        help="the baseline's DataLoader worker processes (default 2; DrQ-v2's default is 4)")
    args = parser.parse_args()
    ctx = mp.get_context("spawn")
    load_before = os.getloadavg()
    figures = measure_l2r(args, ctx)
    figures |= measure_baseline(args, ctx)
    frame = observation_bytes(SPEC)
    print(json.dumps({
        **figures,
        "frame_bytes": frame,
        "replay_bytes_over_frame": round(figures["replay_bytes_per_frame"] / frame, 3),
        "baseline_replay_bytes_over_frame": round(figures["baseline_replay_bytes_per_frame"] / frame, 3),
        "ingest_vs_baseline": round(figures["ingest_frames_per_s"] / figures["baseline_ingest_frames_per_s"], 2),
        "sample_vs_baseline": round(figures["stacked_batches_per_s"] / figures["baseline_stacked_batches_per_s"], 2),
        "seconds": args.seconds, "actors": args.actors, "in_flight": args.in_flight, "n_step": args.n_step,
        "frame_stack": FRAME_STACK, "batch_size": BATCH, "chunk_steps": STEPS, "capacity": args.capacity,
        "machine": f"{cpu_model()}, {os.cpu_count()} CPUs", "cpu_flags": cpu_flags(),
        "load_average_before_after": [round(load_before[0], 2), round(os.getloadavg()[0], 2)],
    }))


if __name__ == "__main__":
    main()
