"""A learner's side of replay: several sample requests in flight across all shards.

    client = ReplayClient(session, run="exp1", batch_size=256, in_flight=4)
    batch = client.sample()                   # blocks until a batch is there
    client.update_priorities(batch, td_errors)
    client.learner_version = 12               # reported back as policy lag
    queue = ReplayClient(session, run="exp1", batch_size=2048, in_flight=1, table="queue")  # on-policy
    n3 = ReplayClient(session, run="exp1", n_step=3, gamma=0.99)  # 3-step returns, with batch.discounts
    pixels = ReplayClient(session, run="exp1", frame_stack=3)  # the frames form, stacks of 3

Up to ``in_flight`` queries are kept outstanding, spread round-robin over the replay shards
that hold a liveliness token; each batch taken sends the next query, so while the learner
trains, the next batches are on their way. A "not ready" reply (the rate limiter holds the
learner back) is retried after the delay the server asks for; it is never an error. With
``n_step`` > 1 every batch must carry ``discounts``: one without (from a shard older than n-step
returns, which ignores ``n_step``) is rejected and counted (``no_discounts``), and that shard is
left alone for a second. With ``frame_stack`` set, the same holds of a batch without ``frames``
(``no_frames``: a shard from before the frames form answers in the version-1 form).
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time

import numpy as np
import zenoh

from l2r.protocol.keys import PRIORITY_QOS, SAMPLE_QOS, Keys, parse_alive
from l2r.protocol.messages import (
    NotReady, PriorityUpdate, ProtocolError, SampleBatch, SampleRequest, Stats, decode, encode,
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
        table: str | None = None,
        n_step: int = 1,
        gamma: float | None = None,
        frame_stack: int | None = None,
    ):
        self.keys = Keys(run)
        self.batch_size = batch_size
        self.prioritized = prioritized
        self.table = table  # None: the replay table, as for servers older than the queue
        self.n_step, self.gamma = n_step, gamma  # left out of requests for n_step 1: older shards get what they know
        self.frame_stack = frame_stack  # None: the version-1 form of the float32 vector
        self.learner_version = -1
        self.rejections = Rejections(log)
        self.waits = 0  # "not ready" replies seen
        self._session = session
        self._in_flight = in_flight
        self._timeout = timeout
        self._ready: queue.Queue[SampleBatch] = queue.Queue()
        self._lock = threading.Lock()  # guards the fields below, shared with Zenoh's threads
        self._shards: set[int] = set()
        self._pending = 0  # queries sent and not answered yet
        self._not_before: dict[int, float] = {}  # shard -> earliest time to ask it again
        self._turn = 0
        encode(self._sample_request())  # a bad batch_size, n_step or gamma raises ProtocolError here, not per query
        self._liveliness = session.liveliness().declare_subscriber(
            self.keys.alive_role("replay"), self._on_alive, history=True)

    @property
    def shards(self) -> list[int]:
        with self._lock:
            return sorted(self._shards)

    def sample(self, timeout: float | None = None) -> SampleBatch:
        """The next batch; waits while replay is empty or rate-limited. ``queue.Empty`` on timeout."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            self._top_up()
            wait = 0.01 if deadline is None else min(0.01, deadline - time.monotonic())
            try:
                batch = self._ready.get(timeout=max(0.0, wait))
            except queue.Empty:
                if deadline is not None and time.monotonic() >= deadline:
                    raise
                continue
            self._top_up()
            return batch

    def __iter__(self):
        while True:
            yield self.sample()

    def newest_version(self, stop: threading.Event) -> int:
        """The newest policy version the live replay shards have seen, in the experience they hold
        or from a learner, once a first shard is alive (-1: none, or ``stop`` was set first). A
        learner that starts without its checkpoint publishes above it, so versions never go back."""
        if not self.shards:
            log.info("waiting for a replay shard, to publish above the newest policy version it has seen")
        while not self.shards:
            if stop.wait(0.05):
                return -1
        newest = -1
        for shard in self.shards:
            for reply in self._session.get(self.keys.stats("replay", shard), timeout=self._timeout):
                if reply.ok is None:
                    continue
                try:
                    values = decode(reply.ok.payload, Stats).values
                except ProtocolError as e:
                    self.rejections.add(e, f"stats of replay shard {shard}")
                    continue
                # A shard older than `newest_version` still knows the learner versions it heard of.
                seen = values.get("newest_version", values.get("learner_version", -1))
                if math.isfinite(seen):
                    newest = max(newest, int(seen))
        return newest

    def update_priorities(self, batch: SampleBatch, priorities: np.ndarray) -> None:
        """Send new priorities (e.g. |TD error|) for the slots of ``batch`` back to its shard."""
        update = PriorityUpdate(np.asarray(batch.indices, np.int64), np.asarray(batch.generations, np.int64),
                                np.asarray(priorities, np.float32).reshape(-1))
        self._session.put(self.keys.priorities(batch.shard), encode(update), **PRIORITY_QOS.put())

    def close(self) -> None:
        self._liveliness.undeclare()

    def __enter__(self) -> "ReplayClient":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # -- requests ---------------------------------------------------------------------
    def _on_alive(self, sample: zenoh.Sample) -> None:
        try:
            shard = int(parse_alive(str(sample.key_expr))[1])
        except ValueError:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._shards.add(shard)
            else:
                self._shards.discard(shard)

    def _top_up(self) -> None:
        """Send queries until ``in_flight`` are outstanding or waiting to be taken."""
        while True:
            with self._lock:
                now = time.monotonic()
                shards = sorted(s for s in self._shards if self._not_before.get(s, 0.0) <= now)
                if not shards or self._pending + self._ready.qsize() >= self._in_flight:
                    return
                shard = shards[self._turn % len(shards)]
                self._turn += 1
                self._pending += 1
            self._request(shard)

    def _answered(self, query: dict, shard: int, retry_after: float) -> None:
        """Free the query's slot, once, on its first answer or on its end."""
        with self._lock:
            if query["answered"]:
                return
            query["answered"] = True
            self._pending -= 1
            if retry_after:
                self._not_before[shard] = time.monotonic() + retry_after

    def _sample_request(self) -> SampleRequest:
        n_step = None if self.n_step == 1 else self.n_step
        return SampleRequest(self.batch_size, 1, self.prioritized, int(self.learner_version), self.table, n_step,
                             self.gamma if n_step else None, self.frame_stack)

    def _request(self, shard: int) -> None:
        request = self._sample_request()
        query = {"answered": False}

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is None:
                self.rejections.add(ProtocolError(f"error reply: {reply.err.payload.to_string()}", "error_reply"),
                                    f"shard {shard}")
                return
            try:
                message = decode(reply.ok.payload, (SampleBatch, NotReady))
            except ProtocolError as e:
                self.rejections.add(e, f"shard {shard}")
                return
            if isinstance(message, NotReady):
                self.waits += 1
                self._answered(query, shard, message.retry_after)
            elif request.frame_stack and message.frames is None:
                self.rejections.add(ProtocolError(f"a batch without frames in answer to frame_stack "
                                                  f"{request.frame_stack}: is the shard an l2r-replay from before the "
                                                  "frames form?", "no_frames"), f"shard {shard}")
                self._answered(query, shard, 1.0)
            elif request.n_step and message.discounts is None:
                self.rejections.add(ProtocolError(f"a one-step batch in answer to n_step {request.n_step}: is the "
                                                  "shard an l2r-replay from before n-step returns?", "no_discounts"),
                                    f"shard {shard}")
                self._answered(query, shard, 1.0)
            else:
                self._ready.put(message)
                self._answered(query, shard, 0.0)

        def on_done() -> None:  # the query ended; if it had no answer, back off a little
            self._answered(query, shard, 0.2)

        # direct callbacks: replies are handled on Zenoh's thread, in order, without a hop
        self._session.get(self.keys.sample(shard), zenoh.handlers.Callback(on_reply, on_done, indirect=False),
                          payload=encode(request), timeout=self._timeout, **SAMPLE_QOS.put())
