"""Per-actor chunk sequence numbers: drop duplicates, count gaps.

An actor numbers its chunks 0, 1, 2, ... within one ``epoch`` (one actor process). A chunk
already seen is a duplicate and is not stored again; a jump forward leaves a gap, which a
late (reordered) chunk may still fill. A new epoch means the actor restarted: counting
starts over for it.

``acks`` says, per actor, what is stored of its current epoch, so the actor can resend the rest.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field

MAX_MISSING = 10_000  # gaps remembered per actor; beyond this the oldest are forgotten
MAX_ACK_MISSING = 4096  # missing sequence numbers per actor in one ack


@dataclass
class ActorRecord:
    epoch: int
    highest: int = -1
    missing: set[int] = field(default_factory=set)
    chunks: int = 0
    transitions: int = 0
    duplicates: int = 0
    gaps: int = 0  # sequence numbers skipped and never filled so far (or forgotten)


class SequenceTracker:
    def __init__(self) -> None:
        self.actors: dict[int, ActorRecord] = {}
        self.restarts = 0
        self.received = 0  # chunks seen, duplicates included: an ack is due when this moves

    def accept(self, actor_id: int, epoch: int, seq: int) -> bool:
        """True if chunk ``seq`` of this actor is new; False for a duplicate."""
        self.received += 1
        record = self.actors.get(actor_id)
        if record is None or epoch > record.epoch:
            if record is not None:
                self.restarts += 1
            record = self.actors[actor_id] = ActorRecord(epoch, chunks=record.chunks if record else 0,
                                                         transitions=record.transitions if record else 0,
                                                         duplicates=record.duplicates if record else 0,
                                                         gaps=record.gaps if record else 0)
        elif epoch < record.epoch or seq < 0:
            record.duplicates += 1  # from an earlier incarnation of this actor: already superseded
            return False
        if seq > record.highest:
            skipped = seq - record.highest - 1
            if skipped:
                record.gaps += skipped
                record.missing.update(range(max(record.highest + 1, seq - MAX_MISSING), seq))
                while len(record.missing) > MAX_MISSING:
                    record.missing.remove(min(record.missing))
            record.highest = seq
        elif seq in record.missing:
            record.missing.remove(seq)
            record.gaps -= 1
        else:
            record.duplicates += 1
            return False
        record.chunks += 1
        return True

    def stored(self, actor_id: int, transitions: int) -> None:
        self.actors[actor_id].transitions += transitions

    def acks(self, limit: int = MAX_ACK_MISSING) -> list[tuple[int, int, int, list[int]]]:
        """``(actor_id, epoch, highest, missing)`` per actor: every ``seq <= highest`` is stored
        except ``missing``. With more than ``limit`` missing, ``highest`` is lowered to just below
        the first one left out, so the statement stays true (the actor resends the rest later)."""
        out = []
        for actor, record in self.actors.items():
            highest, missing = record.highest, record.missing
            if len(missing) > limit:
                lowest = heapq.nsmallest(limit + 1, missing)
                highest, missing = lowest[-1] - 1, lowest[:-1]
            else:
                missing = sorted(missing)
            out.append((actor, record.epoch, highest, missing))
        return out

    @property
    def duplicates(self) -> int:
        return sum(r.duplicates for r in self.actors.values())

    @property
    def gaps(self) -> int:
        return sum(r.gaps for r in self.actors.values())

    def state(self) -> dict:
        return {"restarts": self.restarts, "actors": {
            str(a): {"epoch": r.epoch, "highest": r.highest, "missing": sorted(r.missing), "chunks": r.chunks,
                     "transitions": r.transitions, "duplicates": r.duplicates, "gaps": r.gaps}
            for a, r in self.actors.items()}}

    def restore(self, state: dict) -> None:
        self.restarts = state.get("restarts", 0)
        self.actors = {int(a): ActorRecord(r["epoch"], r["highest"], set(r["missing"]), r["chunks"],
                                           r["transitions"], r["duplicates"], r["gaps"])
                       for a, r in state.get("actors", {}).items()}
