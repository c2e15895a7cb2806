"""Actor ids that cannot collide, handed out by replay shard 0 (``l2r-actor --actor-id auto``).

An actor asks on ``actor_ids`` with a name no other running actor process has: its host name
and process id. Shard 0 gives a name it has not seen the next id, 0, 1, 2, ..., and a name it
knows the same id again, so a container that restarts its actor keeps its id (and the shards
keep one sequence record for it, not one per restart). One shard answers, so two names can never
get one id. The names and their ids are kept in ``actor-ids.json`` in the snapshot directory,
written and fsynced before the reply leaves, so a restarted shard never gives an id twice either;
a shard without a snapshot directory could not promise that, so it gives none and says why.
"""

from __future__ import annotations

import json
import logging
import threading
from pathlib import Path

import zenoh

from l2r.config import StartupFailure
from l2r.durable import write_durably
from l2r.protocol import ActorId, ActorIdRequest, ProtocolError, Rejections, decode, encode
from l2r.protocol.limits import ID

FILE_NAME = "actor-ids.json"
log = logging.getLogger("l2r.replay")


class NoActorId(Exception):
    """Why the shard cannot give an id now (its error reply reads ``unavailable: <this>``)."""


class ActorIds:
    """The ids given so far, by name; answers ``actor_ids`` queries."""

    def __init__(self, directory: Path | None, rejections: Rejections):
        self.path = Path(directory) / FILE_NAME if directory is not None else None
        self.ids = _read(self.path) if self.path is not None else {}
        self.rejections = rejections
        self._lock = threading.Lock()  # Zenoh may run two queries' handlers at once

    def id_of(self, name: str) -> int:
        """The id of ``name``: a new one for a new name, on disk before it is returned."""
        with self._lock:
            if name in self.ids:
                return self.ids[name]
            if self.path is None:
                raise NoActorId("replay shard 0 has no --snapshot-dir, so it could not remember the actor ids it "
                                "gave after a restart; give each actor its own --actor-id instead")
            new_id = len(self.ids)
            if new_id > ID[1]:
                raise NoActorId("every actor id of the run has been given")
            ids = {**self.ids, name: new_id}
            try:
                write_durably(self.path, lambda f: f.write(json.dumps(ids, indent=0).encode()))
            except OSError as e:
                raise NoActorId(f"cannot save the actor ids to {self.path}: {e.strerror}") from None
            self.ids = ids
            return new_id

    def on_query(self, query: zenoh.Query) -> None:
        try:
            request = decode(query.payload if query.payload is not None else b"", ActorIdRequest)
        except ProtocolError as e:
            self.rejections.add(e, "actor id query")
            query.reply_err(f"{e.reason}: {e}")
            return
        try:
            answer = ActorId(request.name, self.id_of(request.name))
        except NoActorId as e:
            log.error("no actor id for %s: %s", request.name, e)
            query.reply_err(f"unavailable: {e}")
            return
        query.reply(query.key_expr, encode(answer))


def _read(path: Path) -> dict[str, int]:
    """The ids a shard gave before, checked: one id per name, 0 to n - 1 without a gap."""
    try:
        ids = json.loads(path.read_text())
    except FileNotFoundError:
        return {}
    except (OSError, ValueError) as e:
        raise StartupFailure(f"cannot read the actor ids given so far from {path}: {e}") from None
    if not isinstance(ids, dict) or any(type(i) is not int for i in ids.values()) \
            or sorted(ids.values()) != list(range(len(ids))):
        raise StartupFailure(f"{path} is not a table of actor ids (names to 0, 1, 2, ...); move it aside only once "
                             "no actor that got an id from it runs")
    return ids
