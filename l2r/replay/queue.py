"""The queue table: experience for on-policy learners, first in, first out, each transition given once.

Reverb's queue, for l2r's chunks:

- **Items are chunks**: the consecutive steps of one environment, as an actor sent them. A batch
  takes transitions from the head; where the batch ends inside a chunk, the chunk is split and its
  rest stays at the head. Each transition leaves the queue once, in a batch or dropped.
- **Batches keep trajectories whole**: a batch is pieces of chunks, one after the other, with
  ``segment_ends`` marking the last transition of each piece, so a learner can run GAE over it.
  Each transition carries the acting policy's log-probability (``log_probs``): chunks without
  one (from older actors) cannot enter.
- **Staleness bound**: a transition acted by a policy more than ``max_lag`` versions older than
  the newest the learner has published is dropped, on arrival or while waiting, and counted in
  ``dropped_stale``.
- **When full** (``capacity`` transitions waiting), ``hold``: the shard asks its actors to wait
  (``ReplayAck.hold``) until the learner has taken a batch; what still arrives is kept up to twice
  the capacity. ``drop``: nothing waits, and the oldest chunks make room for new ones. Either way,
  chunks pushed out are counted in ``dropped_full``.

The queue lives in memory only: after a restart its data would be stale anyway.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from l2r.protocol import ExperienceChunk, SampleBatch
from l2r.replay.storage import ChunkRejected

WHEN_FULL = ("hold", "drop")


@dataclass
class QueueConfig:
    capacity: int = 0
    """Transitions waiting before the queue holds its actors back or drops; 0: no queue table."""
    max_lag: int = 3
    """Transitions acted by a policy more than this many versions behind the learner's are dropped."""
    when_full: str = "hold"
    """'hold': actors are asked to wait while the queue is full; 'drop': the oldest chunks go."""

    def __post_init__(self) -> None:
        if self.when_full not in WHEN_FULL:
            raise ValueError(f"when_full must be one of {WHEN_FULL}, got {self.when_full!r}")


class _Item:
    """A chunk in the queue: its steps from ``start`` on are still waiting."""

    __slots__ = ("chunk", "start", "first_index")

    def __init__(self, chunk: ExperienceChunk, first_index: int):
        self.chunk, self.start, self.first_index = chunk, 0, first_index

    @property
    def waiting(self) -> int:
        return self.chunk.size - self.start


class QueueTable:
    """See the module docstring. Not thread-safe: the server serialises access."""

    def __init__(self, config: QueueConfig, obs_dim: int, act_dim: int):
        self.config, self.obs_dim, self.act_dim = config, obs_dim, act_dim
        self._items: deque[_Item] = deque()
        self.size = 0  # transitions waiting
        self.arrived = 0  # transitions ever offered: given, dropped or waiting
        self.enqueued = 0  # transitions ever accepted (not stale on arrival); also the index of the next one
        self.given = 0
        self.dropped_stale = 0
        self.dropped_full = 0
        self._lag_checked_at = -1  # learner version of the last sweep for stale chunks

    @property
    def capacity(self) -> int:
        return self.config.capacity

    @property
    def holding(self) -> bool:
        """Whether actors should wait: a holding queue that is full."""
        return self.config.when_full == "hold" and self.size >= self.capacity

    def check(self, chunk: ExperienceChunk) -> None:
        """Raise ChunkRejected if ``chunk`` cannot enter this queue."""
        if not isinstance(chunk.obs, np.ndarray):  # fields (docs/observations.md): version 2's map
            raise ChunkRejected(f"experience with observation fields {sorted(chunk.obs)}; the queue table keeps the "
                                "float32 vector observation alone", "unknown_field")
        if chunk.obs.shape[1] != self.obs_dim or chunk.actions.shape[1] != self.act_dim:
            raise ChunkRejected(f"experience widths obs {chunk.obs.shape[1]}, actions {chunk.actions.shape[1]}; "
                                f"this queue takes obs {self.obs_dim}, actions {self.act_dim}", "wrong_width")
        if chunk.size > self.capacity:
            raise ChunkRejected(f"chunk of {chunk.size} transitions exceeds the queue's capacity {self.capacity}",
                                "too_large")
        if chunk.log_probs is None:
            raise ChunkRejected("experience without log_probs (an actor older than the queue table): on-policy "
                                "learners need the acting policy's log-probabilities", "no_log_probs")

    def insert(self, chunk: ExperienceChunk, learner_version: int) -> int:
        """Append ``chunk`` (checked) unless it is stale; return the transitions accepted."""
        self.check(chunk)
        self.arrived += chunk.size
        self._drop_stale(learner_version)
        if self._stale(chunk, learner_version):
            self.dropped_stale += chunk.size
            return 0
        bound = self.capacity * (2 if self.config.when_full == "hold" else 1)
        while self._items and self.size + chunk.size > bound:
            oldest = self._items.popleft()
            self.size -= oldest.waiting
            self.dropped_full += oldest.waiting
        self._items.append(_Item(chunk, self.enqueued))
        self.size += chunk.size
        self.enqueued += chunk.size
        return chunk.size

    def take(self, batch_size: int, learner_version: int, shard: int) -> SampleBatch | None:
        """The oldest ``batch_size`` fresh transitions as one batch, removed from the queue; None
        while fewer are waiting."""
        self._drop_stale(learner_version)
        if self.size < batch_size:
            return None
        out = _BatchArrays(batch_size, self.obs_dim, self.act_dim)
        filled, size = 0, self.size
        while filled < batch_size:
            item = self._items[0]
            n = min(item.waiting, batch_size - filled)
            out.add(filled, item, n)
            item.start += n
            filled += n
            if not item.waiting:
                self._items.popleft()
        self.size -= batch_size
        self.given += batch_size
        return out.batch(shard, size)

    def _stale(self, chunk: ExperienceChunk, learner_version: int) -> bool:
        return learner_version - chunk.policy_version > self.config.max_lag

    def _drop_stale(self, learner_version: int) -> None:
        """Sweep the queue for chunks the learner's newest version made stale (once per version)."""
        if learner_version <= self._lag_checked_at:
            return
        self._lag_checked_at = learner_version
        fresh = deque(item for item in self._items if not self._stale(item.chunk, learner_version))
        dropped = self.size - sum(item.waiting for item in fresh)
        self.dropped_stale += dropped
        self.size -= dropped
        self._items = fresh


class _BatchArrays:
    """The arrays of one queue batch, filled piece by piece (one copy of each value)."""

    def __init__(self, n: int, obs_dim: int, act_dim: int):
        self.obs = np.empty((n, obs_dim), np.float32)
        self.next_obs = np.empty((n, obs_dim), np.float32)
        self.actions = np.empty((n, act_dim), np.float32)
        self.rewards = np.empty(n, np.float32)
        self.terminated = np.empty(n, bool)
        self.truncated = np.empty(n, bool)
        self.log_probs = np.empty(n, np.float32)
        self.versions = np.empty(n, np.int64)
        self.indices = np.empty(n, np.int64)
        self.segment_ends = np.zeros(n, bool)

    def add(self, at: int, item: _Item, n: int) -> None:
        chunk, lo = item.chunk, item.start
        rows, steps = slice(at, at + n), slice(lo, lo + n)
        self.obs[rows] = chunk.obs[steps]
        # next observations: the following rows, except where an episode ended inside the chunk
        self.next_obs[rows] = chunk.obs[lo + 1:lo + n + 1]
        ends = np.flatnonzero((chunk.terminated | chunk.truncated)[:-1])  # one final_obs row each
        inside = (ends >= lo) & (ends < lo + n)
        self.next_obs[at + ends[inside] - lo] = chunk.final_obs[inside]
        self.actions[rows] = chunk.actions[steps]
        self.rewards[rows] = chunk.rewards[steps]
        self.terminated[rows] = chunk.terminated[steps]
        self.truncated[rows] = chunk.truncated[steps]
        self.log_probs[rows] = chunk.log_probs[steps]
        self.versions[rows] = chunk.policy_version
        self.indices[rows] = np.arange(item.first_index + lo, item.first_index + lo + n)
        self.segment_ends[at + n - 1] = True

    def batch(self, shard: int, size: int) -> SampleBatch:
        n = len(self.obs)
        return SampleBatch(shard=shard, size=size, prioritized=False, obs=self.obs, actions=self.actions,
                           rewards=self.rewards, next_obs=self.next_obs, terminated=self.terminated,
                           truncated=self.truncated, indices=self.indices, generations=self.indices,
                           probabilities=np.ones(n), policy_versions=self.versions, log_probs=self.log_probs,
                           segment_ends=self.segment_ends)
