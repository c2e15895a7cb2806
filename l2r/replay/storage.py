"""Preallocated FIFO transition storage with uniform and prioritized sampling.

Transitions of one chunk go to consecutive slots of a ring, so the next observation of a
slot is usually the observation of the slot after it and is not stored twice. Only a step
that ends a chunk or an episode keeps its own next observation, in a smaller side ring.
When that side ring wraps over a row a live slot still points to, the slot is evicted
(priority 0, not sampled); size it so this stays rare (default: capacity / 8 rows).

Every write gives a slot a new generation (the running count of transitions stored), so a
priority update computed for an overwritten slot is recognised and ignored. The slot of
generation g is always g % capacity.

Trajectory links: each slot keeps how many generations ahead the next transition of its
trajectory lies (``next_link``, 0: none) and how many back the previous one (``prev_link``,
negative, 0: none). A link is followed only while the slot it reaches still holds that
generation (``follow``), so an overwritten or evicted neighbour ends it. Inside a chunk the
links join consecutive slots and stop at episode ends. Chunks of one environment stream
(actor_id, epoch, env_id) interleave with other streams; the last slot of a stream's newest
chunk is joined to the first of its next chunk when that last step ended no episode and the
next chunk's first observation equals the true next observation stored for it (else a chunk
was lost in between: counted in ``link_mismatches``). Where each stream's newest chunk ended is
remembered for at most ``MAX_STREAMS`` streams and only while that slot is not overwritten.
n-step returns (``sample(n_step=...)``) follow the next links; stacks of frames
(``sample(frame_stack=...)``) follow the previous ones.

Observations are stored per field of the storage's observation spec, one array each in the
field's own dtype (docs/observations.md); the float32 vector is the one field "state".
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from l2r.protocol import ExperienceChunk, ProtocolError, SampleBatch
from l2r.protocol.observations import VECTOR_FIELD, ObservationSpec, as_fields
from l2r.replay.sumtree import SumTree

log = logging.getLogger("l2r.replay")

MAX_STREAMS = 65_536
"""Environment streams whose newest chunk end is remembered for linking (about 260 bytes each,
17 MB at most; a snapshot holds inserts up about 2 us per stream while it copies them); beyond
it the least recently extended stream is forgotten (its next chunk starts unlinked)."""
LINKS = ("next_link", "prev_link")


@dataclass
class StorageConfig:
    """What is stored and how it is sampled."""

    capacity: int = 1_000_000
    """Transitions kept; the oldest are evicted first. Below 2**31 (links are int32)."""
    obs_dim: int = 41
    """Width of the float32 vector observation, when ``observation`` is not given."""
    act_dim: int = 18
    """Action width; chunks of another width are rejected."""
    side_fraction: float = 0.125
    """Rows for next observations at chunk and episode ends, as a fraction of capacity."""
    priority_exponent: float = 0.6
    """alpha of prioritized replay: stored priority = (priority + eps) ** alpha."""
    seed: int = 0
    observation: ObservationSpec | None = None
    """The fields each stored observation has; None: the float32 vector of ``obs_dim``. Chunks
    of another observation are rejected."""

    def __post_init__(self) -> None:
        if self.observation is None:
            self.observation = ObservationSpec.vector(self.obs_dim)
        elif self.observation.vector_width is not None:
            self.obs_dim = self.observation.vector_width


def storage_bytes(config: StorageConfig) -> int:
    """Bytes a `Storage` of ``config`` allocates (its ``nbytes``), known before allocating."""
    c, s = config.capacity, max(1, int(config.capacity * config.side_fraction))
    frame = observation_bytes(config.observation)
    # per slot: obs, actions, reward, terminated and truncated flags, version, generation, next row,
    # next and previous trajectory links
    per_slot = frame + 4 * config.act_dim + 4 + 2 + 3 * 8 + 2 * 4
    per_side_row = frame + 2 * 8  # next obs, owner and its generation
    return c * per_slot + s * per_side_row + SumTree.nbytes_for(c)


def observation_bytes(spec: ObservationSpec) -> int:
    """Bytes of one observation: one row of every field."""
    return sum(field.nbytes for field in spec.fields.values())


class ChunkRejected(ProtocolError):
    """A well-formed chunk this storage cannot hold (other observation fields or action width,
    longer than capacity or its side rows)."""


class Storage:
    """See the module docstring. Not thread-safe: the server serialises access."""

    ARRAYS = ("actions", "rewards", "terminated", "truncated", "versions", "generation", "next_row", *LINKS,
              "side_owner", "side_owner_generation")
    """The arrays beside the observation fields, by attribute; those of the side ring start with "side_"."""

    def __init__(self, config: StorageConfig):
        c, s = config.capacity, max(1, int(config.capacity * config.side_fraction))
        self.config = config
        self.capacity, self.side_capacity = c, s
        # per field, ring rows [0, c) then side rows [c, c + s): one gather fetches any next observation
        self.all_obs = {name: np.zeros((c + s, *field.shape), field.dtype)
                        for name, field in config.observation.fields.items()}
        self.obs = {name: rows[:c] for name, rows in self.all_obs.items()}
        self.side_obs = {name: rows[c:] for name, rows in self.all_obs.items()}
        self.actions = np.zeros((c, config.act_dim), np.float32)
        self.rewards = np.zeros(c, np.float32)
        self.terminated = np.zeros(c, bool)
        self.truncated = np.zeros(c, bool)
        self.versions = np.zeros(c, np.int64)
        self.generation = np.full(c, -1, np.int64)  # -1: empty or evicted
        self.next_row = np.full(c, -1, np.int64)  # side row of the next obs; -1: next slot's obs
        self.next_link = np.zeros(c, np.int32)  # generations ahead to the next step of the trajectory; 0: none
        self.prev_link = np.zeros(c, np.int32)  # generations to the previous step (negative); 0: none
        # (actor_id, epoch, env_id) -> (seq, generation of the last step) of the stream's newest chunk,
        # least recently extended first (so also in the order of those generations)
        self.stream_ends: OrderedDict[tuple[int, int, int], tuple[int, int]] = OrderedDict()
        self.chunk_links = 0  # chunks joined to the one before them in their stream
        self.link_mismatches = 0  # chunks whose stream went on, but whose first observation did not match
        self.side_owner = np.full(s, -1, np.int64)
        self.side_owner_generation = np.full(s, -1, np.int64)
        self.tree = SumTree(c)
        self.rng = np.random.default_rng(config.seed)
        self.written = 0  # transitions ever stored; also the next generation
        self.side_written = 0
        self.live = 0  # slots holding a sampleable transition
        self.max_priority = 1.0
        for array in (*self.all_obs.values(), self.actions, self.rewards, self.terminated, self.truncated,
                      self.versions):
            array.fill(0)  # fault the pages in now: no stalls on first writes, no late OOM

    def named_arrays(self) -> dict[str, np.ndarray]:
        """Everything a snapshot keeps of the rows, by its name there: field f's observations are
        ``obs.f`` (ring) and ``side_obs.f`` (side rows); side-ring names start with "side_"."""
        return ({f"obs.{name}": rows for name, rows in self.obs.items()}
                | {f"side_obs.{name}": rows for name, rows in self.side_obs.items()}
                | {name: getattr(self, name) for name in self.ARRAYS})

    @property
    def nbytes(self) -> int:
        return sum(array.nbytes for array in self.named_arrays().values()) + self.tree.tree.nbytes

    def check(self, chunk: ExperienceChunk) -> None:
        """Raise ChunkRejected if ``chunk`` does not fit this storage: the reasons of
        ``ObservationSpec.check`` for its observations, ``wrong_width`` for its actions."""
        spec, final_obs = self.config.observation, as_fields(chunk.final_obs)
        try:
            spec.check(as_fields(chunk.obs), "experience.obs")
            spec.check(final_obs, "experience.final_obs")
        except ProtocolError as e:
            raise ChunkRejected(f"{e}; this replay stores {spec}", e.reason) from None
        if chunk.actions.shape[1] != self.config.act_dim:
            raise ChunkRejected(f"experience actions of width {chunk.actions.shape[1]}; this replay stores "
                                f"{self.config.act_dim}", "wrong_width")
        final_rows = len(final_obs[next(iter(spec.fields))])
        if chunk.size > self.capacity or final_rows + 1 > self.side_capacity:
            raise ChunkRejected(f"chunk of {chunk.size} transitions exceeds capacity {self.capacity} "
                                f"or side rows {self.side_capacity}", "too_large")

    def insert(self, chunk: ExperienceChunk) -> int:
        """Store all transitions of ``chunk``; return how many."""
        self.check(chunk)
        obs, final_obs = as_fields(chunk.obs), as_fields(chunk.final_obs)
        t, start = chunk.size, self.written % self.capacity
        first = min(t, self.capacity - start)
        # at most two contiguous pieces of the ring: slices are cheaper than index arrays
        for ring, lo, hi in ((start, 0, first), (0, first, t)):
            if lo == hi:
                continue
            at = slice(ring, ring + hi - lo)
            self.live -= int(np.count_nonzero(self.generation[at] >= 0))
            for name, rows in obs.items():
                self.obs[name][at] = rows[lo:hi]
            self.actions[at] = chunk.actions[lo:hi]
            self.rewards[at] = chunk.rewards[lo:hi]
            self.terminated[at] = chunk.terminated[lo:hi]
            self.truncated[at] = chunk.truncated[lo:hi]
            self.versions[at] = chunk.policy_version
            self.generation[at] = np.arange(self.written + lo, self.written + hi)
            self.next_row[at] = -1
            self.next_link[at] = 1  # each step to the next, but for the ends below
            self.prev_link[at] = -1
            self.tree.set_range(ring, hi - lo, self.max_priority)

        ends = np.flatnonzero((chunk.terminated | chunk.truncated)[:-1])
        side_values = {name: np.concatenate([final_obs[name], rows[-1:]]) if len(ends) else rows[-1:]
                       for name, rows in obs.items()}
        side_slots = (start + np.append(ends, t - 1)) % self.capacity
        rows = self._side_write(side_values, side_slots)
        self.next_row[side_slots] = rows
        self.side_owner_generation[rows] = self.generation[side_slots]
        # no link past an episode end, nor (until the stream's next chunk joins) past the chunk's last step
        self.next_link[side_slots] = 0
        self.prev_link[start] = 0
        if len(ends):
            self.prev_link[(start + ends + 1) % self.capacity] = 0
        self._extend_stream(chunk, self.written, {name: rows[0] for name, rows in obs.items()})
        self.written += t
        self.live += t
        self._forget_streams()
        return t

    def _extend_stream(self, chunk: ExperienceChunk, first: int, first_obs: dict[str, np.ndarray]) -> None:
        """Join the chunk just stored from generation ``first`` on to its stream's newest chunk,
        and make it the newest. A late chunk (resent after a loss) is older than the newest: it
        stays unlinked and leaves the newest as it is, so the stream's next chunk still joins."""
        key = (chunk.actor_id, chunk.epoch, chunk.env_id)
        newest = self.stream_ends.pop(key, None)
        if newest is not None and newest[0] > chunk.seq:
            self.stream_ends[key] = newest
            return
        if newest is not None:
            self._join(newest[1], first, first_obs)
        self.stream_ends[key] = (chunk.seq, first + chunk.size - 1)

    def _join(self, end: int, first: int, first_obs: dict[str, np.ndarray]) -> None:
        """Link generation ``end`` (a chunk's last step) to ``first`` if that step is still stored,
        ended no episode, and its true next observation is ``first_obs``."""
        slot = end % self.capacity  # (item() and bytes: numpy scalars and an array comparison took 4x as long)
        if self.generation.item(slot) != end or self.terminated.item(slot) or self.truncated.item(slot):
            return  # overwritten or evicted meanwhile, or the episode ended there: nothing to join
        row = self.next_row.item(slot)
        if any(self.side_obs[name][row].tobytes() != value.tobytes() for name, value in first_obs.items()):
            self.link_mismatches += 1  # a chunk in between was lost (or the stream is not what it claims)
            return
        self.next_link[slot] = first - end
        self.prev_link[first % self.capacity] = end - first
        self.chunk_links += 1

    def _forget_streams(self) -> None:
        """Drop the streams whose newest chunk end is overwritten (nothing can join it any more),
        and the least recently extended beyond MAX_STREAMS."""
        oldest_stored = self.written - self.capacity
        while self.stream_ends and (len(self.stream_ends) > MAX_STREAMS
                                    or next(iter(self.stream_ends.values()))[1] < oldest_stored):
            self.stream_ends.popitem(last=False)

    def follow(self, slots: np.ndarray, links: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The slots ``links`` generations away from the live ``slots`` (their ``next_link`` or
        ``prev_link``), and whether each link holds: set, and its slot still stores that generation."""
        targets = (slots + links) % self.capacity
        holds = (links != 0) & (self.generation.take(targets) == self.generation.take(slots) + links)
        return targets, holds

    def _evict(self, slots: np.ndarray) -> None:
        self.live -= int(np.count_nonzero(self.generation[slots] >= 0))
        self.generation[slots] = -1

    def _side_write(self, values: dict[str, np.ndarray], owners: np.ndarray) -> np.ndarray:
        n = len(owners)
        rows = (self.side_written + np.arange(n)) % self.side_capacity
        old_owner, old_gen = self.side_owner[rows], self.side_owner_generation[rows]
        valid = old_owner >= 0
        stale = valid & (self.generation[np.maximum(old_owner, 0)] == old_gen)
        if stale.any():  # live slots whose next observation is about to be overwritten
            victims = old_owner[stale]
            self._evict(victims)
            self.tree.set(victims, np.zeros(len(victims)))
        for name, rows_of_field in values.items():
            self.side_obs[name][rows] = rows_of_field
        self.side_owner[rows] = owners
        self.side_written += n
        return rows

    def sample(self, batch_size: int, prioritized: bool, shard: int = 0, n_step: int = 1,
               gamma: float | None = None, frame_stack: int | None = None) -> SampleBatch:
        """A batch of live transitions; requires ``live > 0``. With ``n_step`` > 1, each carries
        the return of up to ``n_step`` steps of its trajectory discounted by ``gamma`` (``_n_step``).
        With ``frame_stack`` k, observations come in the frames form (``_frames``), stacks of k;
        without, as ``obs`` and ``next_obs`` of the float32 vector, the only observation that has
        that form (ValueError for another)."""
        batch, rows = self.draw(batch_size, prioritized, shard, n_step, gamma, frame_stack)
        if rows is not None:
            batch.frames = {name: field.take(rows, axis=0) for name, field in self.all_obs.items()}
        return batch

    def draw(self, batch_size: int, prioritized: bool, shard: int = 0, n_step: int = 1,
             gamma: float | None = None, frame_stack: int | None = None) -> tuple[SampleBatch, np.ndarray | None]:
        """``sample``'s batch before the gather of its frames: with ``frame_stack``, ``frames`` is
        None and the rows of ``all_obs`` it holds come beside it (None without), to be gathered
        before the storage changes (a replay shard gathers them into its reply,
        ``messages.encode_gathered``)."""
        if frame_stack is None and self.config.observation.vector_width is None:
            raise ValueError(f"a batch of {self.config.observation} comes in the frames form alone: give frame_stack")
        if prioritized:
            slots, probabilities = self._sample_prioritized(batch_size)
        else:
            slots = self._sample_uniform(batch_size)
            probabilities = np.full(batch_size, 1.0 / self.live)
        if n_step > 1:
            last, rewards, discounts = self._n_step(slots, n_step, gamma)
        else:
            last, rewards, discounts = slots, self.rewards.take(slots), None
        side = self.next_row[last]
        next_rows = np.where(side < 0, (last + 1) % self.capacity, self.capacity + side)
        batch = SampleBatch(
            shard=shard, size=self.live, prioritized=prioritized, obs=None, actions=self.actions.take(slots, axis=0),
            rewards=rewards, next_obs=None, terminated=self.terminated.take(last),
            truncated=self.truncated.take(last), indices=slots, generations=self.generation.take(slots),
            probabilities=probabilities, policy_versions=self.versions.take(slots), discounts=discounts)
        if frame_stack is None:
            vector = self.all_obs[VECTOR_FIELD]
            batch.obs, batch.next_obs = vector.take(slots, axis=0), vector.take(next_rows, axis=0)
            return batch, None
        rows, batch.obs_frames, batch.next_obs_frames = self._frames(slots, last, next_rows, frame_stack)
        return batch, rows

    def _stacks(self, slots: np.ndarray, k: int) -> np.ndarray:
        """(len(slots), k): the rows of each slot's observation and its k - 1 predecessors in its
        trajectory, oldest first, the oldest found repeated where the previous links end (an
        episode's start, a lost chunk, an overwritten slot): the padding an actor applies after
        a reset, so stacks are the ones it acted on."""
        stacks = np.empty((len(slots), k), np.int64)
        at = slots
        for column in range(k - 1, -1, -1):
            stacks[:, column] = at
            if column:
                back, holds = self.follow(at, self.prev_link.take(at))
                at = np.where(holds, back, at)
        return stacks

    def _frames(self, slots: np.ndarray, last: np.ndarray, next_rows: np.ndarray,
                k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The frames form of a batch with stacks of ``k``: each distinct row its stacks use once
        (rows of ``all_obs``), and for every transition the indices into them, oldest first, of its
        observation (the stack ending at ``slots``) and next observation (``next_rows``, preceded
        by the stack ending at the window's ``last`` slot)."""
        obs_rows = self._stacks(slots, k)
        next_obs_rows = np.concatenate([self._stacks(last, k - 1), next_rows[:, None]], axis=1)
        rows, indices = np.unique(np.concatenate([obs_rows.ravel(), next_obs_rows.ravel()]), return_inverse=True)
        return rows, indices[:obs_rows.size].reshape(obs_rows.shape), indices[obs_rows.size:].reshape(obs_rows.shape)

    def _n_step(self, slots: np.ndarray, n: int, gamma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For windows of up to ``n`` steps from ``slots``, following next links (which stop at
        episode ends, lost chunks and overwritten slots): the window's last slot, its discounted
        reward sum, and gamma ** steps, 0 where the last step terminated (a truncation bootstraps)."""
        last = slots.copy()
        rewards = self.rewards.take(slots)
        weight = np.ones(len(slots), np.float32)  # gamma ** (steps in the window so far - 1)
        for _ in range(n - 1):  # a window that stopped stays stopped: its link does not hold now either
            ahead, holds = self.follow(last, self.next_link.take(last))
            ahead = ahead[holds]
            weight[holds] *= gamma
            rewards[holds] += weight[holds] * self.rewards.take(ahead)
            last[holds] = ahead
        discounts = np.where(self.terminated.take(last), np.float32(0), weight * np.float32(gamma))
        return last, rewards, discounts

    def _sample_uniform(self, n: int) -> np.ndarray:
        high = min(self.written, self.capacity)
        slots = self.rng.integers(0, high, n)
        dead = self.generation[slots] < 0
        while dead.any():  # evicted slots are rare; draw again for those
            slots[dead] = self.rng.integers(0, high, int(dead.sum()))
            dead = self.generation[slots] < 0
        return slots

    def _sample_prioritized(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        total = self.tree.total
        # stratified: one draw per equal segment of the total priority mass
        targets = (np.arange(n) + self.rng.random(n)) * (total / n)
        slots = np.minimum(self.tree.find(np.minimum(targets, np.nextafter(total, 0))), self.capacity - 1)
        priorities = self.tree.get(slots)
        bad = (priorities <= 0) | (self.generation[slots] < 0)
        if bad.any():  # rounding at a boundary can land on an empty leaf: fall back to any good one
            good = slots[~bad] if (~bad).any() else self._sample_uniform(1)
            slots[bad] = good[0]
            priorities = self.tree.get(slots)
        return slots, priorities / total

    def update_priorities(self, slots: np.ndarray, generations: np.ndarray, priorities: np.ndarray) -> int:
        """Apply priorities to slots still holding the sampled generation; return how many applied."""
        ok = (slots >= 0) & (slots < self.capacity)
        slots, generations, priorities = slots[ok], generations[ok], priorities[ok]
        current = (self.generation[slots] == generations) & (generations >= 0)
        if not current.any():
            return 0
        values = (priorities[current].astype(np.float64) + 1e-6) ** self.config.priority_exponent
        self.tree.set(slots[current], values)
        self.max_priority = max(self.max_priority, float(values.max()))
        return int(current.sum())

    # -- snapshots ------------------------------------------------------------------------
    def state(self) -> dict[str, np.ndarray]:
        """Copies of everything needed to rebuild this storage, in one go."""
        copy = StateCopy(self)
        while not copy.step(block=self.capacity):
            pass
        return copy.arrays

    def restore(self, state: dict[str, np.ndarray]) -> None:
        """Load a ``state()``; raise ValueError if it was taken with other dimensions."""
        written, side_written, live, capacity, side_capacity, obs_dim, act_dim = (int(x) for x in state["counters"])
        if "observation" in state:
            observation = ObservationSpec.parse(str(state["observation"]))
        else:  # from before observation fields: the float32 vector, as the field "state"
            observation = ObservationSpec.vector(obs_dim)
            state = state | {f"obs.{VECTOR_FIELD}": state["obs"], f"side_obs.{VECTOR_FIELD}": state["side_obs"]}
        mine = (self.capacity, self.side_capacity, str(self.config.observation), self.config.act_dim)
        if (capacity, side_capacity, str(observation), act_dim) != mine:
            raise ValueError(f"snapshot has capacity/side rows/observation/action width "
                             f"{(capacity, side_capacity, str(observation), act_dim)}, this server is configured for "
                             f"{mine}")
        for name, array in self.named_arrays().items():
            if name in LINKS and name not in state:
                continue  # a snapshot from before trajectory links: its transitions stay unlinked
            values = state[name]
            array[:len(values)] = values
        if len(state["priorities"]):
            self.tree.set_range(0, len(state["priorities"]), state["priorities"])
        self.written, self.side_written, self.live = written, side_written, live
        self.max_priority = float(state["max_priority"])
        if "stream_keys" not in state:
            log.info("snapshot from before trajectory links: n-step returns and frame stacks reach only into "
                     "chunks stored from now on")
            return
        self.stream_ends = OrderedDict(zip(map(tuple, state["stream_keys"].tolist()),
                                           map(tuple, state["stream_ends"].tolist())))
        # A chunk stored while the copy was taken may have linked a row not copied yet to a transition the
        # snapshot lacks; without a log to replay, another transition would later take that generation.
        filled = slice(0, min(written, self.capacity))
        beyond = (self.next_link[filled] != 0) & (self.generation[filled] + self.next_link[filled] >= written)
        self.next_link[filled][beyond] = 0


class Overtaken(RuntimeError):
    """Inserts overwrote rows a StateCopy had not copied yet."""


class StateCopy:
    """A consistent copy of a Storage as it was at creation, taken block by block.

    Call ``step()`` under the same lock as inserts until it returns True; inserts may run
    between steps. Rows are copied oldest first, so the write head, which also overwrites
    the oldest rows first, only reaches rows already copied. Should it catch up (inserts
    faster than the copy), ``step`` raises Overtaken.
    """

    def __init__(self, storage: Storage):
        self.storage = storage
        self.written, self.side_written = storage.written, storage.side_written
        filled = min(storage.written, storage.capacity)
        side_filled = min(storage.side_written, storage.side_capacity)
        self.sources = storage.named_arrays()
        self.arrays = {name: np.empty((side_filled if name.startswith("side_") else filled, *array.shape[1:]),
                                      array.dtype) for name, array in self.sources.items()}
        self.arrays["priorities"] = np.empty(filled, np.float64)
        self.arrays["counters"] = np.array([storage.written, storage.side_written, storage.live, storage.capacity,
                                            storage.side_capacity, storage.config.obs_dim, storage.config.act_dim], np.int64)
        self.arrays["max_priority"] = np.array(storage.max_priority)
        self.arrays["observation"] = np.array(str(storage.config.observation))
        self.arrays["stream_keys"] = np.array(list(storage.stream_ends), np.int64).reshape(-1, 3)
        self.arrays["stream_ends"] = np.array(list(storage.stream_ends.values()), np.int64).reshape(-1, 2)
        # offsets from each ring's write head: rows [capacity - filled, capacity) hold data
        self._next = [storage.capacity - filled, storage.side_capacity - side_filled]

    def touch(self) -> None:
        """Fault in the copy's memory (call outside the lock, so steps only copy)."""
        for name in self.sources:
            self.arrays[name].fill(0)
        self.arrays["priorities"].fill(0)

    def step(self, block: int = 1 << 14) -> bool:
        """Copy the next ``block`` rows of each ring; True when the copy is complete."""
        st = self.storage
        rings = ((0, st.capacity, self.written, st.written, [n for n in self.sources if not n.startswith("side_")]),
                 (1, st.side_capacity, self.side_written, st.side_written,
                  [n for n in self.sources if n.startswith("side_")]))
        for ring, capacity, head0, head, names in rings:
            offset = self._next[ring]
            if offset >= capacity:
                continue
            if head - head0 > offset:
                raise Overtaken(f"inserts overwrote rows not yet copied ({head - head0} > {offset})")
            end = min(capacity, offset + block)
            rows = (head0 + np.arange(offset, end)) % capacity
            for name in names:
                self.arrays[name][rows] = self.sources[name][rows]
            if ring == 0:
                self.arrays["priorities"][rows] = st.tree.get(rows)
            self._next[ring] = end
        return all(n >= c for n, c in zip(self._next, (st.capacity, st.side_capacity)))
