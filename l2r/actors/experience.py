"""Cutting one environment's stream of transitions into `ExperienceChunk`s.

A chunk holds T steps and T+1 observations: consecutive steps share their observation rows.
When an episode ends inside a chunk, the step's true next observation goes to ``final_obs``
and the chunk continues from the first observation of the next episode.

`ResendBuffer` keeps the encoded chunks a replay shard has not acknowledged yet, so that the
ones lost in flight (a cut link, a restarted shard) are sent again.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from l2r.protocol import ExperienceChunk, ObservationSpec
from l2r.protocol.messages import Observations
from l2r.protocol.observations import VECTOR_FIELD


class ChunkBuilder:
    """Accumulates the steps of one environment; `take` hands them over as a chunk.

    Observations are the fields of ``observation`` (`ObservationSpec.fields_of`), kept in each
    field's own dtype: a frame stays uint8 from the environment to the wire. A chunk of the
    float32 vector holds it as one matrix, the version-1 form; any other spec's chunk holds a
    map of field to rows, the version-2 form (docs/observations.md)."""

    def __init__(self, actor_id: int, env_id: int, epoch: int, capacity: int, observation: ObservationSpec):
        self.actor_id, self.env_id, self.epoch = actor_id, env_id, epoch
        self.capacity = capacity
        self.observation = observation
        self._obs: list[Mapping[str, np.ndarray]] = []
        self._actions: list[np.ndarray] = []
        self._rewards: list[float] = []
        self._terminated: list[bool] = []
        self._truncated: list[bool] = []
        self._log_probs: list[float] = []
        self._final_obs: list[Mapping[str, np.ndarray]] = []
        self.started_at = 0.0  # wall-clock time of the chunk's first step

    def __len__(self) -> int:
        return len(self._actions)

    @property
    def full(self) -> bool:
        return len(self._actions) >= self.capacity

    def begin(self, obs: Mapping[str, np.ndarray]) -> None:
        """The observation the next step starts from (after a reset, or after `take`)."""
        self._obs = [obs]

    def add(self, action: np.ndarray, reward: float, terminated: bool, truncated: bool,
            next_obs: Mapping[str, np.ndarray], start_obs: Mapping[str, np.ndarray] | None, now: float,
            log_prob: float) -> None:
        """One step. ``start_obs`` is the first observation of the next episode when this step
        ended one (the env was reset), else None; ``log_prob`` is the acting policy's
        log-probability of ``action``."""
        if not self._actions:
            self.started_at = now
        self._actions.append(np.asarray(action, np.float32))
        self._rewards.append(float(reward))
        self._terminated.append(bool(terminated))
        self._truncated.append(bool(truncated))
        self._log_probs.append(float(log_prob))
        if start_obs is None:
            self._obs.append(next_obs)
        else:
            self._final_obs.append(next_obs)
            self._obs.append(start_obs)

    def take(self, seq: int, policy_version: int) -> ExperienceChunk | None:
        """The steps so far as one chunk (None if there are none); the builder starts afresh
        from the current observation."""
        if not self._actions:
            return None
        final_obs = self._final_obs
        if self._terminated[-1] or self._truncated[-1]:
            # The last step ended an episode: its true next observation closes the chunk and
            # the first observation of the next episode opens the next chunk.
            obs = self._rows(self._obs[:-1] + final_obs[-1:])
            final_obs = final_obs[:-1]
        else:
            obs = self._rows(self._obs)
        chunk = ExperienceChunk(
            actor_id=self.actor_id, env_id=self.env_id, epoch=self.epoch, seq=seq,
            policy_version=policy_version, obs=obs,
            actions=np.stack(self._actions),
            rewards=np.asarray(self._rewards, np.float32),
            terminated=np.asarray(self._terminated, bool),
            truncated=np.asarray(self._truncated, bool),
            final_obs=self._rows(final_obs),
            log_probs=np.asarray(self._log_probs, np.float32),
        )
        current = self._obs[-1]
        self._actions, self._rewards, self._terminated, self._truncated, self._final_obs = [], [], [], [], []
        self._log_probs = []
        self._obs = [current]
        return chunk

    def _rows(self, observations: list[Mapping[str, np.ndarray]]) -> Observations:
        """Observations as rows per field, in the chunk's form: the vector's matrix, or the map."""
        rows = {name: np.stack([o[name] for o in observations]) if observations
                else np.zeros((0, *field.shape), field.dtype) for name, field in self.observation.fields.items()}
        return rows[VECTOR_FIELD] if self.observation.vector_width is not None else rows


@dataclass
class _Sent:
    payload: bytes
    sent_at: float  # monotonic time of the last send
    wait: float  # seconds after sent_at before the next resend


class ResendBuffer:
    """Sent chunks by sequence number until a replay shard acknowledges them.

    At most ``max_bytes`` of payloads are kept; beyond that the oldest are dropped (and counted).
    An unacknowledged chunk is due again ``delay`` seconds after it was last sent, and each
    resend doubles its wait up to ``max_delay``, so a shard that never acknowledges (an older
    one) is not flooded. A chunk the shard reports missing is due ``delay`` after its last send
    again: the shard is there and still lacks it. Thread-safe: chunks are added by the stepping
    loop, acks arrive on Zenoh's threads and resends go out from another thread.
    """

    def __init__(self, max_bytes: int, delay: float = 3.0, max_delay: float = 30.0):
        self.max_bytes, self.delay, self.max_delay = max_bytes, delay, max_delay
        self._chunks: OrderedDict[int, _Sent] = OrderedDict()  # in sending order = by seq
        self._lock = threading.Lock()
        self.nbytes = 0
        self.acked = 0
        self.resent = 0
        self.dropped = 0  # unacknowledged chunks given up to stay within max_bytes

    def __len__(self) -> int:
        return len(self._chunks)

    def add(self, seq: int, payload: bytes, now: float) -> None:
        """Keep chunk ``seq`` (just sent) until it is acknowledged."""
        with self._lock:
            if len(payload) > self.max_bytes:
                self.dropped += 1
                return
            self._chunks[seq] = _Sent(payload, now, self.delay)
            self.nbytes += len(payload)
            while self.nbytes > self.max_bytes:
                _, oldest = self._chunks.popitem(last=False)
                self.nbytes -= len(oldest.payload)
                self.dropped += 1

    def ack(self, highest: int, missing) -> int:
        """Forget every chunk up to ``highest`` except those in ``missing``; returns how many."""
        missing = set(int(s) for s in missing)
        done = []
        with self._lock:
            for seq, sent in self._chunks.items():
                if seq > highest:
                    break
                if seq in missing:
                    sent.wait = self.delay
                else:
                    done.append(seq)
            for seq in done:
                self.nbytes -= len(self._chunks.pop(seq).payload)
            self.acked += len(done)
        return len(done)

    def due(self, now: float) -> list[bytes]:
        """Payloads to send again now (oldest first); each one's wait doubles."""
        out = []
        with self._lock:
            for sent in self._chunks.values():
                if now - sent.sent_at >= sent.wait:
                    out.append(sent.payload)
                    sent.sent_at = now
                    sent.wait = min(2 * sent.wait, self.max_delay)
            self.resent += len(out)
        return out
