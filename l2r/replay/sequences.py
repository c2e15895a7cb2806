"""Per-actor chunk sequence numbers: drop duplicates, remember gaps, say what is stored.

An actor numbers its chunks 0, 1, 2, ... within one ``epoch`` (one actor process). A chunk
already seen is a duplicate and is not stored again; a jump forward leaves a gap, which a
late (reordered or resent) chunk may still fill. A new epoch means the actor restarted:
counting starts over for it, and chunks of its older epochs are dropped (superseded).

Missing numbers are kept as runs ``[start, stop)``, so a jump of any size costs one run, and
what one actor can make the shard remember is bounded: numbers more than ``MAX_MISSING_SPAN``
below its highest, and the oldest runs beyond ``MAX_MISSING_RUNS``, are given up (a late
chunk with such a number is then dropped like a duplicate). Both bounds are far beyond what an
actor's resend buffer holds, so no chunk an actor can still resend is given up. How many actors
a shard tracks is bounded too: a chunk of a new actor id beyond ``max_actors`` is rejected
(``too_many_actors``), so a peer inventing ids cannot grow the shard's records without end.

``acks`` says, per actor, what is stored of its current epoch, so the actor can resend the rest.
"""

from __future__ import annotations

import logging
from bisect import bisect_right
from dataclasses import dataclass, field

from l2r.protocol import ProtocolError
from l2r.protocol.limits import COUNT, ID

log = logging.getLogger("l2r.replay")

MAX_MISSING_SPAN = 2**20  # sequence numbers below an actor's highest that the shard still waits for
MAX_MISSING_RUNS = 16_384  # runs of missing numbers remembered per actor
MAX_ACK_MISSING = 4096  # missing sequence numbers per actor in one ack
MAX_ACTORS = 4096  # actor ids one shard tracks by default


class MissingRuns:
    """Sorted, disjoint runs ``[start, stop)`` of missing sequence numbers, and how many they hold."""

    def __init__(self, runs: list[tuple[int, int]] = ()):
        self.starts = [start for start, _ in runs]
        self.stops = [stop for _, stop in runs]
        self.count = sum(stop - start for start, stop in runs)

    def __len__(self) -> int:
        return self.count

    @property
    def runs(self) -> list[tuple[int, int]]:
        return list(zip(self.starts, self.stops))

    def append(self, start: int, stop: int) -> None:
        """Add ``[start, stop)``, which lies above every run held."""
        self.starts.append(start)
        self.stops.append(stop)
        self.count += stop - start

    def discard(self, seq: int) -> bool:
        """Remove ``seq``; False if it was not missing."""
        i = bisect_right(self.starts, seq) - 1
        if i < 0 or seq >= self.stops[i]:
            return False
        start, stop = self.starts[i], self.stops[i]
        if stop - start == 1:
            del self.starts[i], self.stops[i]
        elif seq == start:
            self.starts[i] = seq + 1
        elif seq == stop - 1:
            self.stops[i] = seq
        else:  # split the run around seq
            self.stops[i] = seq
            self.starts.insert(i + 1, seq + 1)
            self.stops.insert(i + 1, stop)
        self.count -= 1
        return True

    def forget_below(self, floor: int) -> int:
        """Give up every number below ``floor``; return how many."""
        i = bisect_right(self.starts, floor - 1)  # runs [0, i) start below floor
        if i == 0:
            return 0
        dropped = sum(b - a for a, b in zip(self.starts[:i - 1], self.stops[:i - 1]))
        last_start, last_stop = self.starts[i - 1], self.stops[i - 1]
        if last_stop > floor:  # the last of them straddles floor: keep its upper part
            dropped += floor - last_start
            self.starts[i - 1] = floor
            i -= 1
        else:
            dropped += last_stop - last_start
        del self.starts[:i], self.stops[:i]
        self.count -= dropped
        return dropped

    def forget_oldest_runs(self, keep: int) -> int:
        """Give up the oldest runs beyond ``keep``; return how many numbers."""
        excess = len(self.starts) - keep
        if excess <= 0:
            return 0
        dropped = sum(b - a for a, b in zip(self.starts[:excess], self.stops[:excess]))
        del self.starts[:excess], self.stops[:excess]
        self.count -= dropped
        return dropped

    def first(self, n: int) -> list[int]:
        """The ``n`` lowest missing numbers (fewer if fewer are missing), ascending."""
        out: list[int] = []
        for start, stop in zip(self.starts, self.stops):
            out.extend(range(start, min(stop, start + n - len(out))))
            if len(out) >= n:
                break
        return out


@dataclass
class ActorRecord:
    epoch: int
    highest: int = -1
    missing: MissingRuns = field(default_factory=MissingRuns)
    chunks: int = 0
    transitions: int = 0
    duplicates: int = 0
    superseded: int = 0  # chunks of an older epoch, dropped
    gaps: int = 0  # numbers the shard waited for and never got (still missing, or given up)
    given_up: int = 0  # of those, the ones no longer waited for (beyond the bounds above)
    jumps: int = 0  # jumps forward of more than MAX_MISSING_SPAN; the numbers below the span are not counted

    COUNTERS = ("chunks", "transitions", "duplicates", "superseded", "gaps", "given_up", "jumps")


class SequenceTracker:
    def __init__(self, max_actors: int = MAX_ACTORS) -> None:
        self.actors: dict[int, ActorRecord] = {}
        self.max_actors = max_actors
        self.restarts = 0
        self.received = 0  # chunks seen, duplicates included: an ack is due when this moves

    def accept(self, actor_id: int, epoch: int, seq: int) -> bool:
        """True if chunk ``seq`` of this actor is new; False for a duplicate or a superseded epoch.
        Raises ProtocolError (``too_many_actors``) for a new actor id once ``max_actors`` are tracked."""
        record = self.actors.get(actor_id)
        if record is None and len(self.actors) >= self.max_actors:
            raise ProtocolError(f"experience: actor {actor_id} would be one more than the {self.max_actors} actor "
                                f"ids this shard tracks (--max-actors)", "too_many_actors")
        self.received += 1
        if record is None or epoch > record.epoch:
            if record is not None:
                self.restarts += 1
            counters = {name: getattr(record, name) for name in ActorRecord.COUNTERS} if record else {}
            record = self.actors[actor_id] = ActorRecord(epoch, **counters)
        elif epoch < record.epoch:
            record.superseded += 1  # from an earlier incarnation of this actor
            return False
        if seq > record.highest:
            self._skip_to(record, seq)
        elif record.missing.discard(seq):
            record.gaps -= 1
        else:
            record.duplicates += 1
            return False
        record.chunks += 1
        return True

    @staticmethod
    def _skip_to(record: ActorRecord, seq: int) -> None:
        """Make ``seq`` the highest; the numbers skipped within the span become missing."""
        floor = max(record.highest + 1, seq - MAX_MISSING_SPAN)
        if floor > record.highest + 1:
            record.jumps += 1
        if seq > floor:
            record.missing.append(floor, seq)
            record.gaps += seq - floor
        record.highest = seq
        record.given_up += record.missing.forget_below(seq - MAX_MISSING_SPAN)
        record.given_up += record.missing.forget_oldest_runs(MAX_MISSING_RUNS)

    def stored(self, actor_id: int, transitions: int) -> None:
        self.actors[actor_id].transitions += transitions

    def acks(self, limit: int = MAX_ACK_MISSING) -> list[tuple[int, int, int, list[int]]]:
        """``(actor_id, epoch, highest, missing)`` per actor: every ``seq <= highest`` is stored
        or given up, except ``missing``. With more than ``limit`` missing, ``highest`` is lowered
        to just below the first one left out, so the statement stays true (the actor resends the
        rest later)."""
        out = []
        for actor, record in self.actors.items():
            missing = record.missing.first(limit + 1)
            highest = record.highest
            if len(missing) > limit:
                highest, missing = missing[-1] - 1, missing[:-1]
            out.append((actor, record.epoch, highest, missing))
        return out

    def total(self, counter: str) -> int:
        return sum(getattr(r, counter) for r in self.actors.values())

    def state(self) -> dict:
        return {"restarts": self.restarts, "actors": {
            str(a): {"epoch": r.epoch, "highest": r.highest, "missing_runs": r.missing.runs,
                     **{name: getattr(r, name) for name in ActorRecord.COUNTERS}}
            for a, r in self.actors.items()}}

    def restore(self, state: dict) -> None:
        """Load a ``state()``. A record with values no valid sequence of chunks produces (a snapshot
        written by an older server that accepted anything) is dropped with a warning: that actor
        starts afresh, instead of the shard failing on it later."""
        self.restarts = state.get("restarts", 0)
        self.actors = {}
        for key, r in state.get("actors", {}).items():
            try:
                self.actors[int(key)] = _record(int(key), r)
            except (ValueError, TypeError, KeyError) as e:
                log.warning("snapshot: sequence record of actor %s dropped (%s)", key[:40], e)


def _record(actor_id: int, r: dict) -> ActorRecord:
    """An ActorRecord from its saved form, checked, and held to today's bounds; snapshots of
    older servers list ``missing`` numbers instead of runs."""
    runs = [(int(a), int(b)) for a, b in r["missing_runs"]] if "missing_runs" in r \
        else [(s, s + 1) for s in sorted(int(s) for s in r["missing"])]
    record = ActorRecord(int(r["epoch"]), int(r["highest"]), MissingRuns(runs),
                         **{name: int(r.get(name, 0)) for name in ActorRecord.COUNTERS})
    _within("actor id", actor_id, ID)
    _within("epoch", record.epoch, COUNT)
    _within("highest", record.highest, (-1, COUNT[1]))
    for name in ActorRecord.COUNTERS:
        _within(name, getattr(record, name), COUNT)
    bounds = [b for run in runs for b in run]
    if bounds != sorted(bounds) or any(a >= b for a, b in runs) or (runs and not (
            runs[0][0] >= 0 and runs[-1][1] <= record.highest)):
        raise ValueError("missing numbers out of order or above the highest")
    record.given_up += record.missing.forget_below(record.highest - MAX_MISSING_SPAN)
    record.given_up += record.missing.forget_oldest_runs(MAX_MISSING_RUNS)
    return record


def _within(what: str, value: int, limits: tuple[int, int]) -> None:
    if not limits[0] <= value <= limits[1]:
        raise ValueError(f"{what} {value} not in [{limits[0]}, {limits[1]}]")
