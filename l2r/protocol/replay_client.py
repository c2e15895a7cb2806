"""A learner's side of replay: several sample requests in flight across all shards.

    client = ReplayClient(session, run="exp1", batch_size=256, in_flight=4)
    batch = client.sample()                   # blocks until a batch is there
    client.update_priorities(batch, td_errors)
    client.learner_version = 12               # reported back as policy lag

A background thread keeps ``in_flight`` queries outstanding, spread round-robin over the
replay shards that hold a liveliness token. A "not ready" reply (the rate limiter holds the
learner back) is retried after the delay the server asks for; it is never an error.
"""

from __future__ import annotations

import logging
import queue
import threading
import time

import numpy as np
import zenoh

from l2r.protocol.keys import PRIORITY_QOS, SAMPLE_QOS, Keys, parse_alive
from l2r.protocol.messages import (
    NotReady, PriorityUpdate, ProtocolError, SampleBatch, SampleRequest, decode, encode,
)
from l2r.protocol.session import Rejections

log = logging.getLogger("l2r.replay_client")


class ReplayClient:
    """Samples batches from every live replay shard of a run; see the module docstring."""

    def __init__(
        self,
        session: zenoh.Session,
        run: str,
        batch_size: int = 256,
        prioritized: bool = False,
        in_flight: int = 4,
        timeout: float = 10.0,
    ):
        self.keys = Keys(run)
        self.batch_size = batch_size
        self.prioritized = prioritized
        self.learner_version = -1
        self.rejections = Rejections(log)
        self.waits = 0  # "not ready" replies seen
        self._session = session
        self._in_flight = in_flight
        self._timeout = timeout
        self._ready: queue.Queue[SampleBatch] = queue.Queue()
        self._events: queue.Queue[tuple] = queue.Queue()
        self._shards: set[int] = set()
        self._shards_lock = threading.Lock()
        self._closed = threading.Event()
        self._liveliness = session.liveliness().declare_subscriber(
            self.keys.alive_role("replay"), self._on_alive, history=True)
        self._thread = threading.Thread(target=self._pump, name="replay-client", daemon=True)
        self._thread.start()

    @property
    def shards(self) -> list[int]:
        with self._shards_lock:
            return sorted(self._shards)

    def sample(self, timeout: float | None = None) -> SampleBatch:
        """The next batch; waits while replay is empty or rate-limited. ``queue.Empty`` on timeout."""
        batch = self._ready.get(timeout=timeout)
        self._events.put(("consumed",))  # a free slot: the pump asks for another batch
        return batch

    def __iter__(self):
        while not self._closed.is_set():
            yield self.sample()

    def update_priorities(self, batch: SampleBatch, priorities: np.ndarray) -> None:
        """Send new priorities (e.g. |TD error|) for the slots of ``batch`` back to its shard."""
        update = PriorityUpdate(np.asarray(batch.indices, np.int64), np.asarray(batch.generations, np.int64),
                                np.asarray(priorities, np.float32).reshape(-1))
        self._session.put(self.keys.priorities(batch.shard), encode(update), **PRIORITY_QOS.put())

    def close(self) -> None:
        self._closed.set()
        self._events.put(("closed",))
        self._thread.join(timeout=2.0)
        self._liveliness.undeclare()

    def __enter__(self) -> "ReplayClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- background ---------------------------------------------------------------------
    def _on_alive(self, sample: zenoh.Sample) -> None:
        try:
            shard = int(parse_alive(str(sample.key_expr))[1])
        except ValueError:
            return
        with self._shards_lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._shards.add(shard)
            else:
                self._shards.discard(shard)
        self._events.put(("shards",))

    def _pump(self) -> None:
        pending = 0  # queries sent whose replies have not all arrived
        not_before: dict[int, float] = {}  # shard -> earliest time to ask it again
        turn = 0
        while not self._closed.is_set():
            now = time.monotonic()
            shards = [s for s in self.shards if not_before.get(s, 0.0) <= now]
            while shards and pending + self._ready.qsize() < self._in_flight:
                shard = shards[turn % len(shards)]
                turn += 1
                self._request(shard)
                pending += 1
            waits = [t - now for t in not_before.values() if t > now]
            try:
                event = self._events.get(timeout=min(waits + [0.5]))
            except queue.Empty:
                continue
            if event[0] == "done":
                pending -= 1
            elif event[0] == "wait":
                _, shard, delay = event
                not_before[shard] = time.monotonic() + delay

    def _request(self, shard: int) -> None:
        request = SampleRequest(self.batch_size, 1, self.prioritized, int(self.learner_version))
        state = {"answered": False}

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is None:
                self.rejections.add(f"error reply: {reply.err.payload.to_string()}", f"shard {shard}")
                return
            try:
                message = decode(reply.ok.payload, (SampleBatch, NotReady))
            except ProtocolError as e:
                self.rejections.add(str(e), f"shard {shard}")
                return
            if isinstance(message, NotReady):
                self.waits += 1
                self._events.put(("wait", shard, message.retry_after))
            else:
                self._ready.put(message)
            if not state["answered"]:  # the reply frees the slot; the query's end may come later
                state["answered"] = True
                self._events.put(("done",))

        def on_done() -> None:
            if not state["answered"]:  # timeout, error or shard gone: back off a little
                state["answered"] = True
                self._events.put(("wait", shard, 0.2))
                self._events.put(("done",))

        self._session.get(self.keys.sample(shard), zenoh.handlers.Callback(on_reply, on_done, indirect=False),
                          payload=encode(request), timeout=self._timeout, **SAMPLE_QOS.put())
