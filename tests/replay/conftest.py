"""Real ``l2r-replay`` processes on loopback Zenoh, with a fresh run name per test."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path

import pytest
import zenoh

from l2r.protocol import Keys, ReplayAck, Stats, decode, session_config, wait_alive
from tests.conftest import free_port


class Replay:
    """One server process; ``log()`` is what it has written so far."""

    def __init__(self, run: str, endpoint: str, log_path: Path, args: list[str]):
        self.run, self.endpoint, self.log_path = run, endpoint, log_path
        self.shard = int(args[args.index("--shard") + 1]) if "--shard" in args else 0
        self.log_file = open(log_path, "ab")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "l2r.replay", "--run", run, "--listen", endpoint, "--stats-interval", "0.3",
             "--capacity", "10000", "--min-size", "1", *args],
            stdout=self.log_file, stderr=subprocess.STDOUT)

    def log(self) -> str:
        return self.log_path.read_text()

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 15.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        code = self.proc.wait(timeout)
        self.log_file.close()
        return code


@pytest.fixture
def run_name() -> str:
    return f"test-{uuid.uuid4().hex[:10]}"


@pytest.fixture
def start_replay(run_name, tmp_path):
    """``start_replay(*args)`` starts a server and waits until it is reachable from ``session``."""
    started: list[Replay] = []

    def start(*args: str, endpoint: str | None = None) -> Replay:
        replay = Replay(run_name, endpoint or f"tcp/127.0.0.1:{free_port()}", tmp_path / f"replay{len(started)}.log",
                        list(args))
        started.append(replay)
        return replay

    yield start
    for replay in started:
        if replay.proc.poll() is None:
            replay.proc.kill()
            replay.proc.wait()


@pytest.fixture
def connect(run_name):
    """``connect(*replays)`` opens a session to the servers and waits for their liveliness tokens."""
    sessions: list[zenoh.Session] = []

    def open_to(*replays: Replay) -> zenoh.Session:
        session = zenoh.open(session_config(connect=[r.endpoint for r in replays]))
        sessions.append(session)
        for r in replays:
            assert wait_alive(session, Keys(run_name).alive("replay", r.shard), timeout=20), r.log()
        return session

    yield open_to
    for session in sessions:
        session.close()


class StatsWatch:
    """The latest stats each replay shard published."""

    def __init__(self, session: zenoh.Session, run: str):
        self.latest: dict[str, dict] = {}
        self._changed = threading.Condition()
        self._sub = session.declare_subscriber(Keys(run).all_stats, self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        stats = decode(sample.payload, Stats)
        with self._changed:
            self.latest[stats.instance] = stats.values
            self._changed.notify_all()

    def wait(self, predicate, shard: str = "0", timeout: float = 15.0) -> dict:
        deadline = time.monotonic() + timeout
        with self._changed:
            while not (shard in self.latest and predicate(self.latest[shard])):
                left = deadline - time.monotonic()
                assert left > 0, f"stats never matched; last: {self.latest.get(shard)}"
                self._changed.wait(left)
            return self.latest[shard]


@pytest.fixture
def stats_of(run_name):
    return lambda session: StatsWatch(session, run_name)




@pytest.fixture
def ask_stats(run_name):
    """``ask_stats(session, shard=0)``: the shard's stats now, from a query on its stats key
    (None if it does not answer)."""
    def ask(session: zenoh.Session, shard: int = 0) -> dict | None:
        for reply in session.get(Keys(run_name).stats("replay", shard), timeout=5.0):
            if reply.ok is not None:
                return decode(reply.ok.payload, Stats).values
        return None
    return ask


class AckWatch:
    """Every ack one shard publishes, decoded."""

    def __init__(self, session: zenoh.Session, run: str, shard: int = 0):
        self.acks: list[ReplayAck] = []
        self._changed = threading.Condition()
        self._sub = session.declare_subscriber(Keys(run).replay_ack(shard), self._on)

    def _on(self, sample: zenoh.Sample) -> None:
        ack = decode(sample.payload, ReplayAck)
        with self._changed:
            self.acks.append(ack)
            self._changed.notify_all()

    def wait(self, predicate, timeout: float = 15.0) -> ReplayAck:
        """The first ack from now on (or the latest) for which ``predicate(ack)`` holds."""
        deadline = time.monotonic() + timeout
        with self._changed:
            while not (self.acks and predicate(self.acks[-1])):
                left = deadline - time.monotonic()
                assert left > 0, f"no ack matched; last: {self.acks[-1] if self.acks else None}"
                self._changed.wait(left)
            return self.acks[-1]


@pytest.fixture
def acks_of(run_name):
    return lambda session, shard=0: AckWatch(session, run_name, shard)
