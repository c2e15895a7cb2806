"""What a replay shard's acknowledgement is worth: kill -9 at random moments under steady ingest.

    python bench/replay_durability.py [--kills 20] [--contrast-kills 5] [--rate 1800] [--quick]

Prints one JSON line. Phases, all in one run:
  kills     a feeder that behaves like an actor (numbered chunks, a resend buffer, acks) sends
            --rate transitions/s to a real replay shard with snapshots every --snapshot-interval s
            and the write-ahead log on; the shard is killed with SIGKILL --kills times, each at a
            random moment, and restarted at once. At the end every chunk the shard ever
            acknowledged is looked for in its final snapshot: the acknowledged transitions lost
            (the goal is 0), and how long each restarted shard took to acknowledge new inserts.
  contrast  the same with the write-ahead log off (acks meant "in memory"), --contrast-kills times
  ingest    chunks of 64 transitions sent as fast as one publisher can to a fresh shard, with the
            log and without, alternating, --rounds times each: transitions/s end to end, and the
            shard's own CPU time per chunk in-process (decode, insert, log append; an ack thread
            fsyncs every 0.5 s as the shard does), with the fsync times it saw.
"""

from __future__ import annotations

import argparse
import json
import os
import random
import re
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import uuid
from pathlib import Path

import numpy as np
import zenoh
from replay_throughput import free_endpoint, make_payloads  # this folder's

from l2r.actors.experience import ResendBuffer
from l2r.protocol import (
    EXPERIENCE_QOS, ExperienceChunk, Keys, ReplayAck, Stats, configure_logging, decode, encode, session_config,
    wait_alive,
)
from l2r.replay import snapshot
from l2r.replay.rate_limiter import RateLimiter
from l2r.replay.server import ReplayServer, ServerConfig
from l2r.replay.server import main as serve
from l2r.replay.storage import Storage, StorageConfig
from l2r.replay.wal import WriteAheadLog

OBS, ACT = 41, 18
ACTOR, EPOCH = 1, 1


# -- the shard under test -----------------------------------------------------------------

def shard_command(endpoint: str, run: str, directory: Path, capacity: int, snapshot_interval: float,
                  wal: bool) -> list[str]:
    return [sys.executable, __file__, "--serve", json.dumps({
        "endpoint": endpoint, "run": run, "directory": str(directory), "capacity": capacity,
        "snapshot_interval": snapshot_interval, "wal": wal})]


def run_shard(spec: dict) -> int:
    """The shard as ``l2r-replay`` runs it, with the write-ahead log on or off (as --no-wal turns it off)."""
    configure_logging()
    config = ServerConfig(run=spec["run"], snapshot_dir=Path(spec["directory"]),
                          snapshot_interval=spec["snapshot_interval"], stats_interval=3600,
                          write_ahead_log=spec["wal"])
    return serve(config, StorageConfig(capacity=spec["capacity"]), RateLimiter(min_size=1),
                 session_config(listen=[spec["endpoint"]]))


class Shard:
    def __init__(self, command: list[str], log: Path):
        self.command, self.log = command, log
        self.proc: subprocess.Popen | None = None

    def start(self) -> float:
        with open(self.log, "ab") as out:
            self.proc = subprocess.Popen(self.command, stdout=out, stderr=subprocess.STDOUT)
        return time.monotonic()

    def kill(self) -> None:
        self.proc.kill()
        self.proc.wait()

    def stop(self) -> None:
        self.proc.send_signal(signal.SIGTERM)
        if self.proc.wait(120) != 0:
            raise RuntimeError(f"shard exited with {self.proc.returncode}:\n{self.log.read_text()[-3000:]}")


# -- kill -9 under steady ingest ------------------------------------------------------------

def numbered_chunk(seq: int, steps: int) -> bytes:
    """Observation row t of chunk seq holds (seq, t): the final snapshot says which transitions it has."""
    obs = np.zeros((steps + 1, OBS), np.float32)
    obs[:, 0], obs[:, 1] = seq, np.arange(steps + 1)
    return encode(ExperienceChunk(ACTOR, 0, EPOCH, seq, 0, obs, np.full((steps, ACT), 0.5, np.float32),
                                  np.zeros(steps, np.float32), np.zeros(steps, bool), np.zeros(steps, bool),
                                  np.zeros((0, OBS), np.float32)))


class Feeder:
    """An actor's sending side: numbered chunks at a steady rate, a resend buffer, acks; it
    remembers every chunk any ack ever named as stored."""

    def __init__(self, session: zenoh.Session, run: str, rate: float, steps: int, max_chunks: int):
        keys = Keys(run)
        self.steps, self.interval = steps, steps / rate
        self.buffer = ResendBuffer(256 * 2**20, delay=1.0, max_delay=2.0)
        self.acked = np.zeros(max_chunks, bool)
        self.next_seq = 0
        self.last_ack_at = 0.0  # monotonic time of the latest ack
        self._lock = threading.Lock()
        self._publisher = session.declare_publisher(keys.experience(ACTOR), **EXPERIENCE_QOS.publisher())
        self._acks = session.declare_subscriber(keys.replay_ack(0), self._on_ack)
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._send, daemon=True),
                         threading.Thread(target=self._resend, daemon=True)]
        for thread in self._threads:
            thread.start()

    def _on_ack(self, sample: zenoh.Sample) -> None:
        self.last_ack_at = time.monotonic()
        row = decode(sample.payload, ReplayAck).of(ACTOR, EPOCH)
        if row is None:
            return
        highest, missing = row
        self.buffer.ack(highest, missing)
        with self._lock:
            named = np.zeros(min(highest + 1, len(self.acked)), bool)
            named[:] = True
            named[missing[missing < len(named)]] = False
            self.acked[:len(named)] |= named

    def _send(self) -> None:
        due = time.monotonic()
        while not self._stop.is_set() and self.next_seq < len(self.acked):
            payload = numbered_chunk(self.next_seq, self.steps)
            self.buffer.add(self.next_seq, payload, time.monotonic())
            self._publisher.put(payload)
            self.next_seq += 1
            due += self.interval
            self._stop.wait(max(0.0, due - time.monotonic()))

    def _resend(self) -> None:
        while not self._stop.wait(0.1):
            for payload in self.buffer.due(time.monotonic()):
                self._publisher.put(payload)

    def stop_sending(self) -> None:
        self._stop.set()
        self._threads[0].join()
        self._stop.clear()
        self._threads[1] = threading.Thread(target=self._resend, daemon=True)
        self._threads[1].start()

    def close(self) -> None:
        self._stop.set()
        self._acks.undeclare()
        self._publisher.undeclare()


def stored_transitions(path: Path) -> np.ndarray:
    """(seq, t) of every live transition in a snapshot, one row each."""
    arrays, _ = snapshot.read(path)
    live = arrays["generation"] >= 0
    return arrays["obs"][live][:, :2].astype(np.int64)


def kill_cycles(kills: int, wal: bool, rate: float, steps: int, snapshot_interval: float, capacity: int,
                workdir: Path) -> dict:
    run, endpoint = f"bench-{uuid.uuid4().hex[:8]}", free_endpoint()
    directory = workdir / f"shard-{'wal' if wal else 'nowal'}"
    expected = capacity // steps  # chunks at most: nothing is evicted, so the snapshot shows every loss
    shard = Shard(shard_command(endpoint, run, directory, capacity, snapshot_interval, wal),
                  workdir / f"shard-{'wal' if wal else 'nowal'}.log")
    shard.start()
    with zenoh.open(session_config(connect=[endpoint])) as session:
        if not wait_alive(session, Keys(run).alive("replay", 0), timeout=60):
            raise RuntimeError(shard.log.read_text()[-3000:])
        feeder = Feeder(session, run, rate, steps, expected)
        back_after = []
        for _ in range(kills):
            time.sleep(random.uniform(0.5, 2 * snapshot_interval))  # any moment of the snapshot cycle
            shard.kill()
            started = shard.start()
            while feeder.last_ack_at < started:  # the new process acknowledges only what it stored
                if time.monotonic() - started > 60:
                    raise RuntimeError("restarted shard never acknowledged\n" + shard.log.read_text()[-3000:])
                time.sleep(0.01)
            back_after.append(time.monotonic() - started)
        feeder.stop_sending()
        sent = feeder.next_seq
        deadline = time.monotonic() + 60
        while len(feeder.buffer) and time.monotonic() < deadline:  # every chunk acknowledged in the end
            time.sleep(0.1)
        acked = np.flatnonzero(feeder.acked[:sent])
        feeder.close()
    shard.stop()
    stored = stored_transitions(snapshot.snapshot_path(directory, 0))
    keys, counts = np.unique(stored[:, 0] * steps + stored[:, 1], return_counts=True)
    have = np.zeros(sent * steps, np.int64)
    have[keys[keys < len(have)]] = counts[keys < len(have)]
    per_chunk = (have.reshape(sent, steps) > 0).sum(axis=1)
    return {
        "kills": kills,
        "chunks_sent": sent,
        "acknowledged_transitions": int(len(acked) * steps),
        "acknowledged_transitions_lost": int((steps - per_chunk[acked]).sum()),
        "transitions_stored_twice": int((counts > 1).sum()),
        "unacknowledged_chunks_at_end": len(feeder.buffer),
        "accepting_again_after_restart_s": summary(back_after),
        "of_which_restore_s": summary(restore_times(shard.log.read_text())[1:]),  # [0]: the first start
        "of_which_log_replay_s": summary([float(t) for t in re.findall(
            r"from the write-ahead log in ([\d.]+) s", shard.log.read_text())]),
    }


def restore_times(log: str) -> list[float]:
    """Seconds from each start's first log line (storage allocated) to serving (snapshot and log restored)."""
    stamps = re.findall(r"^(\S+ \S+) INFO l2r.replay: (replay shard|serving)", log, re.MULTILINE)
    times = [(time.mktime(time.strptime(t[:19], "%Y-%m-%d %H:%M:%S")) + int(t[20:]) / 1e3, what) for t, what in stamps]
    return [b[0] - a[0] for a, b in zip(times, times[1:]) if a[1] == "replay shard" and b[1] == "serving"]


def summary(values: list[float]) -> dict:
    return {"median": round(statistics.median(values), 3), "max": round(max(values), 3)} if values else {}


# -- ingest cost ---------------------------------------------------------------------------

def end_to_end_ingest(wal: bool, payloads: list[bytes], steps: int, workdir: Path) -> float:
    """Transitions/s from the first put to the last insert, one publisher, a fresh shard."""
    run, endpoint = f"bench-{uuid.uuid4().hex[:8]}", free_endpoint()
    with tempfile.TemporaryDirectory(dir=workdir) as directory:
        shard = Shard(shard_command(endpoint, run, Path(directory), 200_000, 3600, wal), workdir / "ingest.log")
        shard.start()
        with zenoh.open(session_config(connect=[endpoint])) as session:
            if not wait_alive(session, Keys(run).alive("replay", 0), timeout=60):
                raise RuntimeError(shard.log.read_text()[-3000:])
            publisher = session.declare_publisher(Keys(run).experience(0), **EXPERIENCE_QOS.publisher())
            start = time.perf_counter()
            for payload in payloads:
                publisher.put(payload)
            while True:
                reply = next(iter(session.get(Keys(run).stats("replay", 0), timeout=10)))
                if decode(reply.ok.payload, Stats).values["inserted"] >= len(payloads) * steps:
                    break
                time.sleep(0.005)
            elapsed = time.perf_counter() - start
            publisher.undeclare()
        shard.stop()
    return len(payloads) * steps / elapsed


class FakeSample:
    def __init__(self, key: str, payload: bytes):
        self.key_expr, self.payload = key, zenoh.ZBytes(payload)


def in_process_ingest(wal: bool, payloads: list[bytes], workdir: Path) -> tuple[float, list[float]]:
    """CPU microseconds of the shard's own work per chunk (on_experience: CPU time of the thread,
    so other processes on a loaded machine do not count), and the ack fsyncs' wall times."""
    with tempfile.TemporaryDirectory(dir=workdir) as directory:
        log = WriteAheadLog(Path(directory), 0) if wal else None
        if log is not None:
            log.start(after=0)
        server = ReplayServer(ServerConfig(), Storage(StorageConfig(capacity=200_000)), RateLimiter(), log)
        samples = [FakeSample(Keys("default").experience(0), p) for p in payloads]
        syncs: list[float] = []
        done = threading.Event()

        def acks() -> None:  # as the shard's main loop does, every 0.5 s
            while not done.wait(0.5):
                start = time.perf_counter()
                server.ack()
                syncs.append(time.perf_counter() - start)

        thread = threading.Thread(target=acks)
        thread.start()
        start = time.thread_time()
        for sample in samples:
            server.on_experience(sample)
        elapsed = time.thread_time() - start
        done.set()
        thread.join()
        if log is not None:
            log.close()
    return elapsed / len(payloads) * 1e6, syncs


def ingest_cost(rounds: int, chunks: int, steps: int, workdir: Path) -> dict:
    payloads = make_payloads(0, chunks, steps)
    end_to_end = {True: [], False: []}
    per_chunk = {True: [], False: []}
    fsyncs: list[float] = []
    for _ in range(rounds + 1):  # the first round warms up (page cache, imports) and is not counted
        for wal in (False, True):  # alternating, so drifts of a shared machine hit both alike
            os.sync()  # the previous round's log is not written back during this one
            end_to_end[wal].append(end_to_end_ingest(wal, payloads, steps, workdir))
            os.sync()
            us, syncs = in_process_ingest(wal, payloads, workdir)
            per_chunk[wal].append(us)
            if wal:
                fsyncs += syncs
    for figures in (*end_to_end.values(), *per_chunk.values()):
        del figures[0]
    off, on = statistics.median(end_to_end[False]), statistics.median(end_to_end[True])
    us_off, us_on = statistics.median(per_chunk[False]), statistics.median(per_chunk[True])
    return {
        "chunk_transitions": steps, "chunk_bytes": len(payloads[0]), "chunks_per_round": chunks, "rounds": rounds,
        "end_to_end_transitions_per_s": {"without_log": round(off), "with_log": round(on),
                                         "ratio": round(on / off, 3)},
        "shard_cpu_us_per_chunk": {"without_log": round(us_off, 1), "with_log": round(us_on, 1),
                                    "ratio": round(us_on / us_off, 3)},
        "ack_fsync_ms": {"median": round(1e3 * statistics.median(fsyncs), 2), "max": round(1e3 * max(fsyncs), 2),
                         "count": len(fsyncs)} if fsyncs else {},
    }


def filesystem(path: Path) -> str:
    """The mount the logs were written to: what an fsync costs depends on it."""
    best = ("", "?", "?")
    for line in Path("/proc/mounts").read_text().splitlines():
        device, mount, kind = line.split()[:3]
        if str(path.resolve()).startswith(mount) and len(mount) > len(best[0]):
            best = (mount, kind, device)
    return f"{best[1]} ({best[2]}) at {best[0]}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--kills", type=int, default=20)
    parser.add_argument("--contrast-kills", type=int, default=5, help="kills with the write-ahead log off")
    parser.add_argument("--rate", type=float, default=1800.0, help="steady ingest, transitions/s")
    parser.add_argument("--chunk-steps", type=int, default=16, help="transitions per chunk in the kill phases")
    parser.add_argument("--snapshot-interval", type=float, default=3.0)
    parser.add_argument("--rounds", type=int, default=5, help="ingest rounds with and without the log")
    parser.add_argument("--dir", type=Path, default=None, help="where shards write (default: a temporary dir)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--quick", action="store_true", help="3 kills, 1 contrast kill, 1 ingest round")
    parser.add_argument("--serve", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve:
        sys.exit(run_shard(json.loads(args.serve)))
    if args.quick:
        args.kills, args.contrast_kills, args.rounds = 3, 1, 1
    # imported here, not above: it loads the simulator, which the shards started with --serve do not need
    from env_speed import cpu_flags, cpu_model  # the same machine record as the speed figures
    random.seed(args.seed)
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        workdir = Path(tmp)
        # room for every transition of the longer phase (kills at most 2 intervals apart, restarts, the end)
        capacity = int(args.rate * (max(args.kills, args.contrast_kills) * (2 * args.snapshot_interval + 10) + 60))
        out = {
            "machine": f"{cpu_model()}, {os.cpu_count()} CPUs", "cpu_flags": cpu_flags(),
            "filesystem": filesystem(workdir),
            "rate_transitions_per_s": args.rate, "snapshot_interval_s": args.snapshot_interval,
            "capacity": capacity,
            "with_log": kill_cycles(args.kills, True, args.rate, args.chunk_steps, args.snapshot_interval, capacity,
                                    workdir),
        }
        if args.contrast_kills:
            out["without_log"] = kill_cycles(args.contrast_kills, False, args.rate, args.chunk_steps,
                                             args.snapshot_interval, capacity, workdir)
        out["ingest"] = ingest_cost(args.rounds, 3000, 64, workdir)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
