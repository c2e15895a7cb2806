"""The ``l2r-replay`` daemon: stores actors' experience and serves learners' sample queries.

One shard of a run: it subscribes to ``experience/<shard>/*``, keeps what arrives in its tables
(the replay table, sampled at random, and the queue table, given out once in order; either may
be left out), answers ``replay/<shard>/sample`` queries, applies ``replay/<shard>/priorities``,
tells its actors what it has stored on ``replay/<shard>/ack`` (they resend the rest; a full
queue also asks them to wait there), publishes its stats and answers queries for them, holds the liveliness token ``alive/replay/<shard>`` and logs who
joins and leaves. With a snapshot directory (and without --no-wal), every chunk stored goes to a
write-ahead log that is fsynced before an ack names it, so what is acknowledged survives a crash.
Zenoh calls the handlers from its own threads; one lock serialises access to the storage (a
reply's frames are gathered straight into its message under it). Large replies go through
shared memory of the shard's own to learners on its host (``SharedMemoryReplies``).
"""

from __future__ import annotations

import logging
import math
import signal
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import zenoh

from l2r.durable import FailureLog, disk_failure
from l2r.protocol import (
    ACK_QOS, MAX_MESSAGE_BYTES, STATS_QOS, ExperienceChunk, Keys, LearnerVersion, NotReady,
    PriorityUpdate, ProtocolError, Rejections, ReplayAck, SampleBatch, SampleRequest, Stats, decode, encode,
    encode_gathered, with_reply_pool,
)
from l2r.protocol.observations import ObservationSpec
from l2r.protocol.session import SharedMemoryReplies
from l2r.replay import snapshot
from l2r.replay.actor_ids import ActorIds
from l2r.replay.queue import QueueConfig, QueueTable
from l2r.replay.rate_limiter import RateLimiter
from l2r.replay.sequences import MAX_ACTORS, SequenceTracker
from l2r.replay.storage import Overtaken, StateCopy, Storage, StorageConfig, observation_bytes
from l2r.replay.wal import SyncPoint, WriteAheadLog

log = logging.getLogger("l2r.replay")

REPLY_OVERHEAD = 4096  # bytes of a sample_batch reply beyond its arrays' data (msgpack framing, names)

Replies = list[tuple[SampleBatch, bytes | bytearray]]
"""Sampled batches, each with its encoded reply."""


def reply_bytes_per_transition(observation: ObservationSpec, act_dim: int, queue: bool = False, n_step: int = 1,
                               frame_stack: int | None = None) -> int:
    """The most one transition adds to a sample_batch: obs and next_obs, or in the frames form
    (stacks of ``frame_stack``) at most min(2k, k + n) distinct frames and two int64 indices per
    frame of its stacks; action and reward (float32), two flags, index, generation, probability
    and policy version (8 bytes each); from the queue also a log-probability (float32) and a flag;
    with n-step returns a discount (float32)."""
    rest = 4 * (act_dim + 1) + 2 + 4 * 8 + (5 if queue else 0) + (4 if n_step > 1 else 0)
    if frame_stack is None:
        return 2 * observation_bytes(observation) + rest
    return min(2 * frame_stack, frame_stack + n_step) * observation_bytes(observation) + 16 * frame_stack + rest


@dataclass
class ServerConfig:
    """Where the shard lives and how often it reports and saves."""

    run: str = "default"
    shard: int = 0
    num_shards: int = 1
    snapshot_dir: Path | None = None
    """Directory for snapshots; None keeps everything in memory only."""
    snapshot_interval: float = 120.0
    """Seconds between snapshots: the most stored data a crash can lose."""
    restore: bool = True
    """Load the shard's snapshot from snapshot_dir at start."""
    stats_interval: float = 10.0
    ack_interval: float = 0.5
    """Seconds between acks to the actors (sent only when experience arrived since the last)."""
    write_ahead_log: bool = True
    """With a snapshot_dir: log every chunk stored and fsync it before acknowledging it."""
    max_actors: int = MAX_ACTORS
    """Actor ids the shard keeps sequence records of; chunks of further ids are rejected."""


class ReplayServer:
    """The shard's state and its message handlers (see the module docstring)."""

    def __init__(self, config: ServerConfig, storage: Storage | None, limiter: RateLimiter,
                 wal: WriteAheadLog | None = None, queue: QueueTable | None = None):
        if storage is None and queue is None:
            raise ValueError("a replay shard needs a table: the replay table, the queue, or both")
        self.config = config
        self.wal = wal
        self.keys = Keys(config.run)
        self.storage = storage
        self.queue = queue
        self.limiter = limiter
        self.sequences = SequenceTracker(config.max_actors)
        self.rejections = Rejections(log)
        self.lock = threading.Lock()
        self.shared_replies = SharedMemoryReplies()
        self.learner_version = -1
        self.newest_stored_version = -1  # of the experience taken (snapshot, log, actors)
        self.sampled_batches = 0
        self.not_ready_replies = 0
        self.priority_updates = [0, 0]  # applied, stale
        self.lag_sum = 0.0
        self.lag_batches = 0
        self.snapshot_pause = 0.0
        self._acked_received = 0  # chunks received when the last ack was built
        self.refused_unlogged = 0  # chunks refused while the write-ahead log failed
        self._refused_before, self._wal_failed_at = 0, 0.0
        self.snapshot_failures = FailureLog(log, "snapshot")
        self._hold_sent: bool | None = None  # the hold flag of the last ack
        self._queue_skipped = 0  # chunks without log-probabilities the replay table took and the queue could not
        self._last = (time.monotonic(), 0, 0)  # time, inserted, sampled batches at the last report

    # -- handlers -----------------------------------------------------------------------
    def on_experience(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        payload = sample.payload.to_bytes()
        try:
            chunk = self._check(payload)
            if key.rsplit("/", 1)[-1] != str(chunk.actor_id):
                raise ProtocolError(f"experience: actor_id {chunk.actor_id} in the payload, but the key says "
                                    f"{key.rsplit('/', 1)[-1]!r}", "actor_id_mismatch")
            self._store(chunk, payload)
        except ProtocolError as e:
            self.rejections.add(e, key)

    def _check(self, payload: bytes) -> ExperienceChunk:
        chunk = decode(payload, ExperienceChunk)
        if self.storage is not None:
            self.storage.check(chunk)
        if self.queue is not None and (self.storage is None or chunk.log_probs is not None):
            self.queue.check(chunk)  # without a replay table, a chunk the queue cannot take is rejected
        return chunk

    def _store(self, chunk: ExperienceChunk, payload: bytes | None) -> None:
        """Store a new chunk and log its ``payload`` (None: it comes from the log); raises
        ProtocolError for a chunk of one actor too many."""
        with self.lock:
            if payload is not None and self.wal is not None and self.wal.failed:
                self.refused_unlogged += 1  # its actor keeps it and sends it again once the log writes
                return
            if not self.sequences.accept(chunk.actor_id, chunk.epoch, chunk.seq):
                return
            if self.storage is not None:
                self.storage.insert(chunk)
            if self.queue is not None and chunk.log_probs is not None:
                self.queue.insert(chunk, self.learner_version)  # a stale chunk is dropped and counted there
            elif self.queue is not None:
                self._skip_in_queue(chunk)
            self.sequences.stored(chunk.actor_id, chunk.size)
            self.newest_stored_version = max(self.newest_stored_version, chunk.policy_version)
            self.limiter.inserted += chunk.size
            if self.wal is not None and payload is not None:
                try:
                    self.wal.append(payload)
                except OSError as e:
                    self._wal_failed(e)

    def _skip_in_queue(self, chunk: ExperienceChunk) -> None:
        self._queue_skipped += 1
        if self._queue_skipped == 1:
            log.warning("actor %d sends experience without log-probabilities (an older l2r-actor): the replay "
                        "table stores it, the queue cannot (counted as queue.no_log_probs)", chunk.actor_id)

    def replay_log(self, wal: WriteAheadLog, first_segment: int) -> tuple[int, int]:
        """Store the chunks of ``wal``'s segments from ``first_segment`` on (at start, after the
        snapshot); return (chunks, transitions) stored. Chunks the snapshot holds are dropped as
        duplicates."""
        chunks, inserted = 0, self.limiter.inserted
        for payload in wal.records(first_segment):
            try:
                chunk = self._check(payload)
                self._store(chunk, None)
            except ProtocolError as e:  # written by a server with other widths or more --max-actors: not ours to store
                self.rejections.add(e, "write-ahead log")
                continue
            chunks += 1
        return chunks, self.limiter.inserted - inserted

    def _wal_failed(self, error: OSError, point: SyncPoint | None = None) -> None:
        """Stop acknowledging and storing until the log writes again (``_retry_wal``); under the lock."""
        self.wal.fail(error, point)
        self._wal_failed_at = time.monotonic()
        log.error("write-ahead log failed (%s): no acks and no new chunks stored until it writes again (tried "
                  "every %.1f s); actors keep their chunks and send them again then",
                  disk_failure(error, self.wal.path(self.wal.segment)), self.config.ack_interval)

    def _retry_wal(self) -> bool:
        """Whether the log writes again: a failed one tries now; under the lock."""
        try:
            written = self.wal.retry()
        except OSError:
            return False
        log.info("write-ahead log writes again after %.1f s (%d chunks stored before it failed are logged now); "
                 "acks resume, %d chunks refused meanwhile come again from their actors",
                 time.monotonic() - self._wal_failed_at, written, self.refused_unlogged - self._refused_before)
        self._refused_before = self.refused_unlogged
        return True

    def on_sample_query(self, query: zenoh.Query) -> None:
        try:
            request = decode(query.payload if query.payload is not None else b"", SampleRequest)
            from_queue = self._from_queue(request)
        except ProtocolError as e:
            self.rejections.add(e, "sample query")
            query.reply_err(f"{e.reason}: {e}")
            return
        with self.lock:
            self.learner_version = max(self.learner_version, request.learner_version)
            batches, reason, size, delay = (self._take_from_queue if from_queue else self._sample_replay)(request)
            if batches:
                self.sampled_batches += len(batches)
                if self.learner_version >= 0:
                    self.lag_sum += sum(self.learner_version - b.policy_versions.mean() for b, _ in batches)
                    self.lag_batches += len(batches)
            else:
                self.not_ready_replies += 1
        if not batches:
            query.reply(query.key_expr, encode(NotReady(self.config.shard, reason, size, delay)))
            return
        for _, payload in batches:
            query.reply(query.key_expr, self.shared_replies.payload(payload))

    def _from_queue(self, request: SampleRequest) -> bool:
        """Whether ``request`` asks for the queue table (else the replay table); ProtocolError if
        this shard lacks the table or cannot send such a batch."""
        table = request.table or "replay"
        if table not in ("replay", "queue"):
            raise ProtocolError(f"sample_request: unknown table {table!r}; l2r-replay keeps 'replay' and 'queue'",
                                "no_table")
        queue, n_step = table == "queue", request.n_step or 1
        if (self.queue if queue else self.storage) is None:
            raise ProtocolError(f"sample_request: shard {self.config.shard} keeps no {table} table "
                                f"({'--queue-capacity' if queue else '--capacity'} 0)", "no_table")
        if queue and (n_step > 1 or request.frame_stack is not None):
            raise ProtocolError(f"sample_request: n_step {request.n_step} or frame_stack {request.frame_stack} from "
                                "the queue table; n-step returns and frame stacks come from the replay table (queue "
                                "batches are whole trajectory pieces of the vector)", "invalid")
        if queue:
            observation, act_dim = ObservationSpec.vector(self.queue.obs_dim), self.queue.act_dim
        else:
            observation, act_dim = self.storage.config.observation, self.storage.config.act_dim
        if request.frame_stack is None and observation.vector_width is None:
            raise ProtocolError(f"sample_request without frame_stack asks for the float32 vector; this shard stores "
                                f"{observation}, sent only in the frames form (set frame_stack)", "frames_only")
        per_transition = reply_bytes_per_transition(observation, act_dim, queue, n_step, request.frame_stack)
        largest = (MAX_MESSAGE_BYTES - REPLY_OVERHEAD) // per_transition
        if queue and self.queue.capacity < largest:
            largest = self.queue.capacity
        if request.batch_size > largest:
            raise ProtocolError(f"sample_request: a batch of {request.batch_size} from the {table} table; at most "
                                f"{largest} (the {MAX_MESSAGE_BYTES}-byte message limit, or the queue's capacity)",
                                "too_large")
        return queue

    def _sample_replay(self, request: SampleRequest) -> tuple[Replies, str, int, float]:
        """Batches drawn from the replay table with their encoded replies (frames gathered into
        them while the lock keeps the storage still), or none and why (reason, size, retry after)."""
        size, wanted = self.storage.live, request.batch_size * request.count
        ok, reason = self.limiter.can_sample(size, wanted)
        if not ok:
            delay = 0.05 if size < self.limiter.min_size else self.limiter.retry_after(wanted, self._insert_rate())
            return [], reason, size, delay
        self.limiter.sampled += wanted
        batches = []
        for _ in range(request.count):
            batch, rows = self.storage.draw(request.batch_size, request.prioritized, self.config.shard,
                                            request.n_step or 1, request.gamma, request.frame_stack)
            payload = encode(batch) if rows is None else encode_gathered(batch, self.storage.all_obs, rows)
            batches.append((batch, payload))
        return batches, "", size, 0.0

    def _take_from_queue(self, request: SampleRequest) -> tuple[Replies, str, int, float]:
        """Up to ``count`` batches taken from the queue with their encoded replies, or none and
        why (reason, size, retry after)."""
        batches = []
        for _ in range(request.count):
            batch = self.queue.take(request.batch_size, self.learner_version, self.config.shard)
            if batch is None:
                break
            batches.append((batch, encode(batch)))
        if batches:
            return batches, "", self.queue.size, 0.0
        rate = self._insert_rate()
        missing = request.batch_size - self.queue.size
        delay = min(0.5, max(0.005, missing / rate)) if rate > 0 else 0.05
        return [], f"the queue holds {self.queue.size} of the {request.batch_size} transitions asked for", \
            self.queue.size, delay

    def on_stats_query(self, query: zenoh.Query) -> None:
        query.reply(query.key_expr, encode(self.report(reset=False)))

    def on_priorities(self, sample: zenoh.Sample) -> None:
        try:
            update = decode(sample.payload, PriorityUpdate)
        except ProtocolError as e:
            self.rejections.add(e, str(sample.key_expr))
            return
        if self.storage is None:
            self.rejections.add(ProtocolError("priority_update: this shard keeps no replay table", "no_table"),
                                str(sample.key_expr))
            return
        with self.lock:
            applied = self.storage.update_priorities(update.indices, update.generations, update.priorities)
            self.priority_updates[0] += applied
            self.priority_updates[1] += len(update.indices) - applied

    def on_learner_version(self, sample: zenoh.Sample) -> None:
        try:
            beacon = decode(sample.payload, LearnerVersion)
        except ProtocolError as e:
            self.rejections.add(e, str(sample.key_expr))
            return
        self.learner_version = max(self.learner_version, beacon.version)

    def on_alive(self, sample: zenoh.Sample) -> None:
        who = str(sample.key_expr).split("/alive/", 1)[-1]
        if who == f"replay/{self.config.shard}":
            return
        log.info("%s %s", who, "joined" if sample.kind == zenoh.SampleKind.PUT else "left")

    def ack(self) -> ReplayAck | None:
        """What is stored of each actor's current epoch, durably when there is a write-ahead log, and
        whether a full queue or the rate limiter (``hold_inserts``) asks the actors to wait; None when
        there is nothing new to say (no chunk came since the last ack, a resent duplicate counting as
        one since its sender has not heard an ack yet; no hold to renew or lift), or when the log has
        failed."""
        with self.lock:
            holds = ([self.queue.holding] if self.queue is not None else []) + \
                    ([self.limiter.inserts_ahead()] if self.limiter.hold_inserts else [])
            hold = any(holds) if holds else None  # None: the field is left out (nothing can hold)
            if self.wal is not None and self.wal.failed and not self._retry_wal():
                return None
            news = self.sequences.received != self._acked_received or hold or hold != self._hold_sent
            if not news:
                return None
            received = self.sequences.received
            rows = self.sequences.acks()
            try:
                durable = self.wal.flush() if self.wal is not None else None
            except OSError as e:
                self._wal_failed(e)
                return None
        if durable is not None:  # fsync outside the lock: inserts go on meanwhile
            try:
                self.wal.sync(durable)
            except OSError as e:
                with self.lock:
                    self._wal_failed(e, durable)
                return None
        self._acked_received, self._hold_sent = received, hold
        actors, epochs, highest, missing = zip(*rows) if rows else ((), (), (), ())
        return ReplayAck(self.config.shard, _int64(actors), _int64(epochs), _int64(highest),
                         _int64([len(m) for m in missing]), _int64([s for m in missing for s in m]), hold)

    # -- reporting ------------------------------------------------------------------------
    def _insert_rate(self) -> float:
        t, inserted, _ = self._last
        return (self.limiter.inserted - inserted) / max(1e-3, time.monotonic() - t)

    def report(self, reset: bool = True) -> Stats:
        """The shard's stats message: ``stats`` now."""
        return Stats("replay", str(self.config.shard), time.time(), self.stats(reset))

    def stats(self, reset: bool = True) -> dict[str, float]:
        """Current figures; rates are over the time since the previous call with ``reset``
        (the periodic report), which starts a new interval."""
        with self.lock:
            now = time.monotonic()
            t, inserted, sampled = self._last
            dt = max(1e-6, now - t)
            main_table = self.storage if self.storage is not None else self.queue
            values = {
                "size": self.storage.live if self.storage is not None else self.queue.size,
                "capacity": main_table.capacity,
                "inserted": self.limiter.inserted,
                "inserts_per_s": (self.limiter.inserted - inserted) / dt,
                "sampled_batches": self.sampled_batches,
                "samples_per_s": (self.sampled_batches - sampled) / dt,
                "not_ready_replies": self.not_ready_replies,
                **self.rejections.counters(),
                "duplicates": self.sequences.total("duplicates"),
                "superseded": self.sequences.total("superseded"),
                "gaps": self.sequences.total("gaps"),
                "given_up": self.sequences.total("given_up"),
                "sequence_jumps": self.sequences.total("jumps"),
                "actor_restarts": self.sequences.restarts,
                "priority_updates": self.priority_updates[0],
                "stale_priority_updates": self.priority_updates[1],
                "learner_version": self.learner_version,
                # What a learner that starts without its checkpoint must publish above.
                "newest_version": max(self.learner_version, self.newest_stored_version),
                "policy_lag": self.lag_sum / self.lag_batches if self.lag_batches else float("nan"),
                "snapshot_pause_s": self.snapshot_pause,
                "refused_unlogged": self.refused_unlogged,
                "log_failed": int(self.wal is not None and self.wal.failed is not None),
            }
            if self.storage is not None:
                values |= {"chunk_links": self.storage.chunk_links, "link_mismatches": self.storage.link_mismatches,
                           "streams": len(self.storage.stream_ends)}
            if self.queue is not None:
                q = self.queue
                values |= {"queue.size": q.size, "queue.capacity": q.capacity, "queue.inserted": q.arrived,
                           "queue.given": q.given, "queue.dropped_stale": q.dropped_stale,
                           "queue.dropped_full": q.dropped_full, "queue.holding": int(q.holding),
                           "queue.no_log_probs": self._queue_skipped}
            for actor, record in self.sequences.actors.items():
                values[f"actor.{actor}.transitions"] = record.transitions
                values[f"actor.{actor}.gaps"] = record.gaps
            if reset:
                self._last = (now, self.limiter.inserted, self.sampled_batches)
                self.lag_sum, self.lag_batches = 0.0, 0
        return values

    # -- persistence ----------------------------------------------------------------------
    def capture(self) -> tuple[dict[str, np.ndarray], dict]:
        """A consistent copy of the state, taken in blocks so inserts and samples go on
        between them; ``snapshot_pause`` is the longest time they were held up. The queue table is
        not kept: after a restart its data would be stale."""
        pauses = []
        with self.lock, _timed(pauses):
            copy = StateCopy(self.storage) if self.storage is not None else None
            meta = self._meta()
            if self.wal is not None and not self.wal.failed:  # what comes from now on goes to a new segment
                try:
                    meta["wal_segment"] = self.wal.rotate()
                except OSError as e:
                    self._wal_failed(e)
        if copy is None:
            self.snapshot_pause = pauses[0]
            return {}, meta
        copy.touch()
        try:
            done = False
            while not done:
                with self.lock, _timed(pauses):
                    done = copy.step()
        except Overtaken as e:  # inserts outran the copy: take it in one go instead
            log.warning("snapshot copy %s; copying under one lock", e)
            return self._capture_at_once()
        self.snapshot_pause = max(pauses)
        return copy.arrays, meta

    def _meta(self) -> dict:
        return {"sequences": self.sequences.state(), "inserted": self.limiter.inserted,
                "sampled": self.limiter.sampled, "learner_version": self.learner_version,
                "shard": self.config.shard, "time": time.time()}

    def _capture_at_once(self) -> tuple[dict[str, np.ndarray], dict]:
        pauses = []
        with self.lock, _timed(pauses):
            arrays = self.storage.state() if self.storage is not None else {}
            meta = self._meta() | ({"wal_segment": self.wal.segment} if self.wal is not None else {})
        self.snapshot_pause = pauses[0]
        return arrays, meta

    def restore(self, arrays: dict[str, np.ndarray], meta: dict) -> None:
        if ("counters" in arrays) != (self.storage is not None):
            raise ValueError(f"the snapshot {'holds' if 'counters' in arrays else 'has no'} replay table, this "
                             f"server {'keeps none (--capacity 0)' if self.storage is None else 'keeps one'}")
        if self.storage is not None:
            self.storage.restore(arrays)
            self.newest_stored_version = int(self.storage.versions.max())
        self.sequences.restore(meta["sequences"])
        self.limiter.inserted, self.limiter.sampled = meta["inserted"], meta["sampled"]
        self.learner_version = meta["learner_version"]


def _int64(values) -> np.ndarray:
    return np.array(values, dtype=np.int64)


@contextmanager
def _timed(durations: list[float]):
    start = time.perf_counter()
    try:
        yield
    finally:
        durations.append(time.perf_counter() - start)


def _guarded(handler):
    """Run a Zenoh handler so that an unexpected error is logged, never raised into Zenoh."""
    def run(item) -> None:
        try:
            handler(item)
        except Exception:
            log.exception("%s failed; the shard goes on", handler.__name__)
    return run


def _direct(handler) -> zenoh.handlers.Callback:
    """Run on Zenoh's receiving thread itself: no hand-over to another thread, and a busy
    shard slows its senders down (experience is published with congestion control BLOCK)."""
    return zenoh.handlers.Callback(_guarded(handler), indirect=False)


def _save(server: ReplayServer, path: Path) -> None:
    arrays, meta = server.capture()
    start = time.perf_counter()
    try:
        size = snapshot.write(path, arrays, meta)
    except OSError as e:
        server.snapshot_failures.failed(e, path, "the previous one is kept (tried again every snapshot interval)")
        return
    server.snapshot_failures.succeeded()
    if "wal_segment" in meta:  # the snapshot is durable: the log before it is not needed any more
        server.wal.delete_before(meta["wal_segment"])
    log.info("snapshot: %d transitions, %.1f MiB to %s in %.2f s (inserts and samples held up %.1f ms at most)",
             int(arrays["counters"][2]) if arrays else 0, size / 2**20, path, time.perf_counter() - start, server.snapshot_pause * 1e3)


def _restore(server: ReplayServer, path: Path, log_on_disk: WriteAheadLog) -> bool:
    """Load the snapshot and replay the write-ahead log after it, even one that an earlier session
    left to a shard that writes none; False if the snapshot does not fit."""
    loaded = snapshot.read(path)
    first_segment = 0
    if loaded:
        try:
            server.restore(*loaded)
        except (ValueError, KeyError) as e:
            log.error("cannot restore %s: %s. Start with matching flags, or move the file away.", path, e)
            return False
        first_segment = loaded[1].get("wal_segment", 0)
        log.info("restored %d transitions from %s", server.storage.live, path)
    start = time.perf_counter()
    chunks, transitions = server.replay_log(log_on_disk, first_segment)
    if chunks:
        log.info("replayed %d chunks (%d transitions new) from the write-ahead log in %.2f s",
                 chunks, transitions, time.perf_counter() - start)
    if server.wal is not None:
        server.wal.start(after=first_segment)
    return True


def main(config: ServerConfig, storage_config: StorageConfig, limiter: RateLimiter,
         zenoh_config: zenoh.Config, stop: threading.Event | None = None, queue_config: QueueConfig | None = None) -> int:
    """Run one replay shard until ``stop`` is set or SIGINT/SIGTERM arrives. A storage capacity of 0
    leaves the replay table out; a queue config with a capacity adds the queue table."""
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: stop.set())

    storage = Storage(storage_config) if storage_config.capacity else None
    queue = QueueTable(queue_config, storage_config.obs_dim, storage_config.act_dim) if (
        queue_config and queue_config.capacity) else None
    path = snapshot.snapshot_path(config.snapshot_dir, config.shard) if config.snapshot_dir else None
    # Read even when this shard writes no log: an earlier session's holds chunks it acknowledged as durable.
    log_on_disk = WriteAheadLog(config.snapshot_dir, config.shard) if path else None
    wal = log_on_disk if config.write_ahead_log else None
    server = ReplayServer(config, storage, limiter, wal, queue)
    actor_ids = ActorIds(config.snapshot_dir, server.rejections) if config.shard == 0 else None
    if storage is not None:
        log.info("replay shard %d/%d of run %r: capacity %d transitions of observation %s, %.1f MiB preallocated "
                 "(%.0f bytes/transition, of which %d bytes a stored observation)", config.shard, config.num_shards,
                 config.run, storage.capacity, storage_config.observation, storage.nbytes / 2**20,
                 storage.nbytes / storage.capacity, observation_bytes(storage_config.observation))
    if queue is not None:
        log.info("replay shard %d/%d of run %r: a queue table of %d transitions (%s when full), dropping data more "
                 "than %d versions behind the learner", config.shard, config.num_shards, config.run, queue.capacity,
                 queue.config.when_full, queue.config.max_lag)
    if path and config.restore:
        if not _restore(server, path, log_on_disk):
            return 2
    elif log_on_disk is not None:
        log_on_disk.delete_before(math.inf)  # the log of a state not restored
        if wal is not None:
            wal.start(after=0)
    if path:
        log.info("snapshots every %.0f s to %s; %s", config.snapshot_interval, path,
                 "acks name only chunks fsynced to the write-ahead log" if wal else
                 "no write-ahead log: a crash loses what came since the last snapshot")

    keys = server.keys
    with zenoh.open(with_reply_pool(zenoh_config)) as session:
        acks = session.declare_publisher(keys.replay_ack(config.shard), **ACK_QOS.publisher())
        entities = [
            session.declare_subscriber(keys.experience_of_shard(config.shard), _direct(server.on_experience)),
            session.declare_queryable(keys.sample(config.shard), _direct(server.on_sample_query)),
            session.declare_queryable(keys.stats("replay", config.shard), _guarded(server.on_stats_query)),
            session.declare_subscriber(keys.priorities(config.shard), _guarded(server.on_priorities)),
            session.declare_subscriber(keys.learner_version, _guarded(server.on_learner_version)),
        ]
        if actor_ids is not None:  # shard 0 hands out the ids of actors started with --actor-id auto
            entities.append(session.declare_queryable(keys.actor_ids, _guarded(actor_ids.on_query)))
        watcher = session.liveliness().declare_subscriber(keys.alive_all, _guarded(server.on_alive), history=True)
        # declared last, so a peer that sees the token finds the handlers above in place
        token = session.liveliness().declare_token(keys.alive("replay", config.shard))
        stats_key = keys.stats("replay", config.shard)
        log.info("serving: experience on %s, samples on %s", keys.experience_of_shard(config.shard),
                 keys.sample(config.shard))

        writer: threading.Thread | None = None
        next_stats = time.monotonic() + config.stats_interval
        next_snapshot = time.monotonic() + config.snapshot_interval
        next_ack = time.monotonic() + config.ack_interval
        while not stop.wait(min(0.2, config.ack_interval)):
            now = time.monotonic()
            if now >= next_ack:
                next_ack = now + config.ack_interval
                ack = server.ack()
                if ack is not None:
                    acks.put(encode(ack))
            if now >= next_stats:
                next_stats = now + config.stats_interval
                report = server.report()
                values = report.values
                session.put(stats_key, encode(report), **STATS_QOS.put())
                log.info("size %d | %.0f inserts/s | %.1f batches/s | lag %.1f | rejected %d | dup %d | gaps %d",
                         values["size"], values["inserts_per_s"], values["samples_per_s"], values["policy_lag"],
                         values["rejected"], values["duplicates"], values["gaps"])
                if "queue.size" in values:
                    log.info("queue %d | given %d | dropped stale %d, full %d | %s", values["queue.size"],
                             values["queue.given"], values["queue.dropped_stale"], values["queue.dropped_full"],
                             "holding the actors" if values["queue.holding"] else "open")
            if path and now >= next_snapshot and not (writer and writer.is_alive()):
                next_snapshot = now + config.snapshot_interval
                writer = threading.Thread(target=_save, args=(server, path), name="snapshot")
                writer.start()

        log.info("stopping: no more inserts or samples")
        for entity in entities:
            entity.undeclare()
        final_ack = server.ack()  # what came since the last one: its senders need not resend it
        if final_ack is not None:
            acks.put(encode(final_ack))
        acks.undeclare()
        watcher.undeclare()
        token.undeclare()
    if writer:
        writer.join()
    if path:
        _save(server, path)  # the final snapshot, after the last insert
    if wal is not None and not wal.failed:
        try:
            wal.close()
        except OSError as e:
            log.error("write-ahead log: %s", e)
    log.info("stopped")
    return 0
