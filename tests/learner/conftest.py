"""Shared parts of the learner tests: one torch thread, real daemon processes, a replay server
on loopback with an actor-like feeder."""

import signal
import subprocess
import sys
import threading
import time
import uuid
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import zenoh

from l2r.protocol import (
    EXPERIENCE_QOS, ExperienceChunk, Keys, ObservationSpec, Stats, Weights, decode, encode, session_config,
)
from l2r.protocol.session import wait_alive
from tests.conftest import free_port


@pytest.fixture(autouse=True)
def one_torch_thread():
    """On a busy two-core machine two spinning torch threads slow small networks tenfold."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


# Small networks and one thread, so a daemon test trains hundreds of updates in seconds.
SMALL_LEARNER = ["--threads", "1", "--hidden", "32,32", "--batch-size", "64", "--update-repeat", "2",
                 "--metrics-interval", "1", "--log-level", "INFO"]


class Daemon:
    """A real daemon process (`python -m MODULE ...`) logging to a file."""

    def __init__(self, module: str, args: list[str], log_path: Path):
        self.log_path = log_path
        self._log = open(log_path, "ab")
        self.proc = subprocess.Popen([sys.executable, "-m", module, *args], stdout=self._log,
                                     stderr=subprocess.STDOUT)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 30.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        code = self.proc.wait(timeout)
        self._log.close()
        return code


class Feeder:
    """An actor-like publisher: random transitions into replay, in chunks, until stopped: the runner's
    41 observations and 18 actions, or random fields of `observation` and `act_dim` actions, as if
    acted by the policy of `policy_version`."""

    def __init__(self, session: zenoh.Session, run: str, chunk: int = 50, period: float = 0.02,
                 observation: ObservationSpec | None = None, act_dim: int = 18, policy_version: int = 0):
        self._publisher = session.declare_publisher(Keys(run).experience(0), **EXPERIENCE_QOS.publisher())
        self._stop = threading.Event()
        self._chunk, self._period = chunk, period
        self._observation, self._act_dim = observation, act_dim
        self._policy_version = policy_version
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _observations(self, rng: np.random.Generator, rows: int):
        if self._observation is None:  # the runner's vector, in the version-1 form
            return rng.normal(size=(rows, 41)).astype(np.float32)
        return {name: rng.integers(0, 256, (rows, *field.shape), dtype=np.uint8) if field.dtype == np.uint8
                else rng.normal(size=(rows, *field.shape)).astype(np.float32)
                for name, field in self._observation.fields.items()}

    def _run(self) -> None:
        rng, seq, epoch = np.random.default_rng(0), 0, time.time_ns()
        while not self._stop.is_set():
            t = self._chunk
            chunk = ExperienceChunk(
                actor_id=0, env_id=0, epoch=epoch, seq=seq, policy_version=self._policy_version,
                obs=self._observations(rng, t + 1),
                actions=rng.random((t, self._act_dim), dtype=np.float32), rewards=rng.normal(size=t).astype(np.float32),
                terminated=np.zeros(t, bool), truncated=np.zeros(t, bool),
                final_obs=self._observations(rng, 0))
            self._publisher.put(encode(chunk))
            seq += 1
            self._stop.wait(self._period)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)


class WeightsWatcher:
    """Collects every published weights version, and checks the weights build a policy.

    A learner publishes its first weights once, at start, perhaps before Zenoh has linked it to
    this session (peers link through gossip, later on a busy machine); until it has heard some,
    the watcher asks for the latest, as an actor does."""

    def __init__(self, session, run: str):
        self.versions: list[int] = []
        self.metrics: list[dict] = []
        self.last: Weights | None = None
        self._last_replied = False
        self._lock = threading.Lock()
        self._session, self._keys = session, Keys(run)
        self._subs = [session.declare_subscriber(self._keys.weights, self._on_weights),
                      session.declare_subscriber(self._keys.all_metrics, self._on_metrics)]

    def _on_weights(self, sample, replied: bool = False) -> None:
        weights = decode(sample.payload, Weights)
        with self._lock:
            # A reply and a publication of the same weights, heard in either order, are one version;
            # a reply that comes after newer publications adds nothing.
            if replied and self.versions and weights.version <= self.versions[-1]:
                return
            if not (self._last_replied and weights.version == self.versions[-1]):
                self.versions.append(weights.version)
                self.last = weights
            self._last_replied = replied

    def _ask_for_the_latest(self) -> None:
        for reply in self._session.get(self._keys.weights_query, timeout=1.0):
            if reply.ok:
                self._on_weights(reply.ok, replied=True)

    def _on_metrics(self, sample) -> None:
        self.metrics.append(decode(sample.payload, Stats).values)

    def wait(self, predicate, timeout: float, what: str, daemon) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self._lock:
                if predicate(list(self.versions)):
                    return
                heard = bool(self.versions)
            assert daemon.proc.poll() is None, f"learner exited early:\n{daemon.log()}"
            if not heard:
                self._ask_for_the_latest()
            time.sleep(0.05)
        raise AssertionError(f"timed out waiting for {what}; versions {self.versions}\n{daemon.log()}")


def learner_args(network, run_dir, *extra: str) -> list[str]:
    return ["--run", network.run, "--connect", network.endpoint, "--run-dir", str(run_dir), "--device", "cpu",
            "--publish-every", "20", *SMALL_LEARNER, *extra]


@pytest.fixture
def network(tmp_path, request):
    """A replay server on a free loopback port, a test session connected to it, and cleanup. Indirect
    parametrisation gives the server's extra arguments (a queue table, say)."""
    run = f"test-{uuid.uuid4().hex[:10]}"
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    started: list[Daemon] = []

    def start(module: str, *args: str, name: str) -> Daemon:
        daemon = Daemon(module, [*args], tmp_path / f"{name}.log")
        started.append(daemon)
        return daemon

    def start_replay() -> Daemon:
        return start("l2r.replay", "--run", run, "--listen", endpoint, "--capacity", "20000", "--min-size", "200",
                     "--stats-interval", "5", *getattr(request, "param", ()), name=f"replay{len(started)}")

    replay = start_replay()
    session = zenoh.open(session_config(connect=[endpoint]))
    assert wait_alive(session, Keys(run).alive("replay", 0), timeout=30), replay.log()

    yield SimpleNamespace(run=run, endpoint=endpoint, session=session, replay=replay, start=start,
                          start_replay=start_replay)
    session.close()
    for daemon in started:
        if daemon.proc.poll() is None:
            daemon.proc.kill()
            daemon.proc.wait()
