"""Zenoh session configuration and the settings every l2r daemon shares."""

from __future__ import annotations

import ctypes
import json
import logging
import threading
import time
from collections import Counter
from pathlib import Path
from typing import Annotated, Literal, Sequence

import zenoh
from pydantic import AfterValidator, field_validator

from l2r.config import ONE_OR_MANY, FilePath, Settings, setting, zenoh_error_text
from l2r.protocol.keys import check_name
from l2r.protocol.messages import Message, ProtocolError, decode

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def session_config(
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    mode: str | None = "peer",
    config_file: str | Path | None = None,
) -> zenoh.Config:
    """A Zenoh config: ``config_file`` (Zenoh's own JSON5) if given, with the arguments on top.

    Explicit endpoints turn multicast scouting off, so a process only talks to the
    endpoints it was given. ``mode=None`` keeps the file's mode.
    """
    conf = zenoh.Config.from_file(str(config_file)) if config_file else zenoh.Config()
    if mode:
        conf.insert_json5("mode", json.dumps(mode))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect or listen:
        conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


SHARED_MEMORY_POOL = "transport/shared_memory/transport_optimization/pool_size"
ZENOH_DEFAULT_POOL_BYTES = 16 * 2**20
REPLY_POOL_BYTES = 256 * 2**20
"""The shared memory a replay shard gives Zenoh for its replies to processes on its host.

Zenoh copies a message above 3 KB once into a pool of shared memory and sends a peer on the same
host only a reference to it. Its default pool of 16 MiB is too small for a batch of camera
frames (20-30 MB), which then goes through TCP in 64 KB fragments instead: 8-14 replies of 20 MB
a second between two processes here, against 80-100 through a pool of 128 MiB
(docs/performance.md). 256 MiB holds eight such replies in flight, or one of the largest message.
The pool is made at its first use and in /dev/shm; peers on other hosts get TCP as before."""


def with_reply_pool(conf: zenoh.Config, pool_bytes: int = REPLY_POOL_BYTES) -> zenoh.Config:
    """``conf`` with Zenoh's shared-memory pool raised to ``pool_bytes``, unless a config file
    chose a size of its own (anything but Zenoh's default)."""
    if json.loads(conf.get_json(SHARED_MEMORY_POOL)) == ZENOH_DEFAULT_POOL_BYTES:
        conf.insert_json5(SHARED_MEMORY_POOL, str(pool_bytes))
    return conf


class SharedMemoryReplies:
    """Large replies copied once into shared memory of this process's own, which Zenoh hands
    to a peer on the same host as a reference and copies for one elsewhere.

    A reply given to Zenoh as bytes is copied twice before a peer on the host can read it: into
    Zenoh's buffer, then into its shared-memory pool (``with_reply_pool``); a reply already in
    shared memory is copied by neither. The memory (``pool_bytes``, in /dev/shm) is made at the
    first large reply; where it cannot be made, or is full of replies not yet read, a reply goes
    as bytes, as before. zenoh-python's shared-memory API is marked unstable."""

    def __init__(self, pool_bytes: int = REPLY_POOL_BYTES, smallest: int = 1 << 20):
        self.pool_bytes, self.smallest = pool_bytes, smallest
        self._provider, self._policy, self._tried = None, None, False
        self._lock = threading.Lock()
        self.sent_as_bytes = 0
        """Large replies sent as bytes (the memory full or not to be had)."""

    def payload(self, message: bytes | bytearray) -> bytes | bytearray | zenoh.ZBytes:
        """``message`` as the payload of a reply: in shared memory when it is large."""
        if len(message) < self.smallest:
            return message
        provider = self._provider_once()
        try:
            buffer = provider.alloc(len(message), self._policy) if provider else None
        except zenoh.ZError:  # no room until readers free theirs
            buffer = None
        if buffer is None:
            self.sent_as_bytes += 1
            return message
        buffer[0:len(message)] = message  # (the only copy: its __setitem__ takes bytes or bytearray alone)
        return zenoh.ZBytes(buffer)

    def _provider_once(self):
        """The shared memory, made on the first call; None where it cannot be had (logged once)."""
        with self._lock:
            if not self._tried:
                self._tried = True
                try:
                    import zenoh.shm  # (a ModuleNotFoundError from a build without shared memory)
                    self._provider = zenoh.shm.ShmProvider.default_backend(self.pool_bytes)
                    self._policy = zenoh.shm.GarbageCollect()  # frees what readers have let go, never blocks
                except (ImportError, zenoh.ZError) as e:  # no shared memory in this build, or /dev/shm full
                    logging.getLogger("l2r.protocol").warning(
                        "no shared memory of %d MiB for replies (%s): they go as bytes", self.pool_bytes >> 20, e)
            return self._provider


def reuse_large_buffers() -> bool:
    """Have this process's C allocator keep freed buffers of up to 32 MiB for reuse; False where
    it is not glibc's (nothing changes then). Call it before opening a Zenoh session.

    A process that sends or receives batches of camera frames makes buffers of 20-30 MB per
    batch (the gathered frames, the message, Zenoh's copy of it), most of them on Zenoh's
    threads. glibc gives each thread an arena of its own and hands such buffers back to the
    system when they are freed, so every batch faulted in 5,000 to 11,000 fresh pages: a replay
    shard spent 30-40 ms of CPU per batch, mostly in the kernel, for 7 ms of copying and
    gathering. With one arena (threads then share its lock, which these processes hardly
    contend for), buffers up to glibc's largest mmap threshold (32 MiB) taken from the heap,
    and up to 256 MiB of freed heap kept, the buffers are reused (docs/performance.md)."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except AttributeError:
        return False
    m_trim_threshold, m_mmap_threshold, m_arena_max = -1, -3, -8  # glibc's malloc.h
    settings = ((m_arena_max, 1), (m_mmap_threshold, 32 * 2**20), (m_trim_threshold, 256 * 2**20))
    return all(mallopt(option, value) == 1 for option, value in settings)


NETWORK = "run and network (common to all l2r daemons)"


def _endpoint(endpoint: str) -> str:
    try:  # Zenoh's own parser decides what an endpoint is
        zenoh.Config().insert_json5("connect/endpoints", json.dumps([endpoint]))
    except zenoh.ZError:
        raise ValueError("not a Zenoh endpoint (<protocol>/<address>, e.g. tcp/127.0.0.1:7447)") from None
    return endpoint


Endpoints = Annotated[list[Annotated[str, AfterValidator(_endpoint)]], ONE_OR_MANY]
"""Zenoh endpoints; one string is a list of one."""


class DaemonSettings(Settings):
    """What every daemon takes: run name, Zenoh endpoints and config file, log level."""

    run: str = setting("default", "run name; keys are l2r/<run>/..., so runs never mix", group=NETWORK)
    connect: Endpoints = setting([], "Zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)",
                                 group=NETWORK, metavar="ENDPOINT")
    listen: Endpoints = setting([], "Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)",
                                group=NETWORK, metavar="ENDPOINT")
    mode: Literal["peer", "client", "router"] | None = setting(
        None, "Zenoh mode (default: the --zenoh-config file's, else peer)", group=NETWORK)
    zenoh_config: FilePath | None = setting(None, "Zenoh JSON5 config file; the flags above apply on top",
                                            group=NETWORK, metavar="FILE")
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = setting("INFO", "log level", group=NETWORK)

    @field_validator("run")
    @classmethod
    def _run_name(cls, run: str) -> str:
        check_name(run)
        return run

    @field_validator("zenoh_config")
    @classmethod
    def _readable_zenoh_config(cls, path: Path | None) -> Path | None:
        if path is not None:
            try:
                zenoh.Config.from_file(str(path))
            except zenoh.ZError as e:
                raise ValueError(zenoh_error_text(e)) from None
        return path

    def zenoh_session_config(self) -> zenoh.Config:
        """The Zenoh config these settings describe."""
        mode = self.mode or (None if self.zenoh_config else "peer")
        return session_config(self.connect, self.listen, mode=mode, config_file=self.zenoh_config)


def wait_until_stopped(stop: threading.Event, seconds: float | None = None) -> None:
    """Wait until ``stop`` is set (by a signal handler, say), or ``seconds`` pass when given.

    The wait is cut into short slices. A signal sent to the process may be delivered to one of
    Zenoh's threads; Python then runs its handler only once the main thread runs Python again,
    which a main thread blocked in one untimed wait never does: a router, sent SIGTERM while
    idle, once waited for ever."""
    deadline = None if seconds is None else time.monotonic() + seconds
    while not stop.is_set():
        left = 0.25 if deadline is None else min(0.25, deadline - time.monotonic())
        if left <= 0:
            return
        stop.wait(left)


def configure_logging(level: str = "INFO") -> None:
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO), format=LOG_FORMAT)


class Rejections:
    """Counts rejected messages by reason (``ProtocolError.reason``) and logs them without
    flooding the log: the first of each reason at once, then at most one line per reason every
    ``interval`` seconds, so one noisy reason never hides another."""

    def __init__(self, logger: logging.Logger, interval: float = 10.0):
        self._log = logger
        self._interval = interval
        self._lock = threading.Lock()
        self.by_reason: Counter[str] = Counter()
        self._last_line: dict[str, tuple[float, int]] = {}  # reason -> (time, count) of its last log line
        self.total = 0

    def add(self, error: ProtocolError, source: str = "") -> None:
        reason, now = error.reason, time.monotonic()
        with self._lock:
            self.total += 1
            self.by_reason[reason] += 1
            n = self.by_reason[reason]
            last = self._last_line.get(reason)
            if last is not None and now - last[0] < self._interval:
                return
            self._last_line[reason] = (now, n)
        self._log.warning("rejected message%s (%s: %d so far, %d since the last line): %s",
                          f" from {source}" if source else "", reason, n, n - last[1] if last else 1, error)

    def counters(self) -> dict[str, int]:
        """``rejected`` and ``rejected.<reason>`` for a daemon's stats."""
        with self._lock:
            return {"rejected": self.total, **{f"rejected.{r}": n for r, n in self.by_reason.items()}}


def watched(sample: zenoh.Sample, expected: type[Message]) -> Message | None:
    """The message of a sample a watcher (status, metrics) listens to, or None when it is
    malformed: rejecting and counting it is its receiver's job, so here it is a debug line."""
    try:
        return decode(sample.payload, expected)
    except ProtocolError as e:
        logging.getLogger("l2r.protocol").debug("ignored %s on %s: %s", expected.KIND, sample.key_expr, e)
        return None


LISTENER_GRACE = 5.0
"""Seconds after its start that a sender of one-off messages waits for a listener (`await_listener`)."""


def await_listener(publisher: zenoh.Publisher, deadline: float) -> None:
    """Wait until someone subscribes to what `publisher` sends, or until `time.monotonic()` reaches
    `deadline`. A new peer learns of others' subscriptions a moment after it joins, and what it puts
    before then reaches no one: a sender of messages that are not repeated (episode summaries)
    waits here until its start plus LISTENER_GRACE; a run without a listener goes on after that."""
    while time.monotonic() < deadline and not publisher.matching_status.matching:
        time.sleep(0.01)


def wait_alive(session: zenoh.Session, key_expr: str, timeout: float = 10.0) -> list[str]:
    """Wait until a liveliness token matches ``key_expr``; return the matching keys ([] on timeout)."""
    deadline = time.monotonic() + timeout
    while True:
        found = [str(r.ok.key_expr) for r in session.liveliness().get(key_expr, timeout=1.0) if r.ok]
        if found or time.monotonic() >= deadline:
            return found
        time.sleep(0.05)
