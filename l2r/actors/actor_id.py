"""``l2r-actor --actor-id auto``: the actor's id, asked of replay shard 0 (``l2r.replay.actor_ids``).

The actor names itself by its host name and process id. No two running processes share both as
long as host names are unique, which containers (their ids) and Kubernetes pods (their names) are;
and a container that restarts its actor gives the same name again (the same host name, and the
same process id in a new process namespace), so it gets its id back.
"""

from __future__ import annotations

import logging
import os
import socket
import threading

import zenoh

from l2r.config import StartupFailure
from l2r.protocol import ActorId, ActorIdRequest, Keys, ProtocolError, decode, encode

log = logging.getLogger("l2r.actor")

ASK_TIMEOUT = 5.0  # seconds one query waits for shard 0's reply
ASK_AGAIN_AFTER = 1.0  # seconds between queries while no shard 0 answers


def process_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def ask_actor_id(session: zenoh.Session, keys: Keys, stop: threading.Event) -> int | None:
    """This process's id, from replay shard 0, waiting for it as long as it takes; None when
    ``stop`` is set first. A refusal from the shard is a StartupFailure with its reason."""
    name = process_name()
    request = encode(ActorIdRequest(name))
    waiting = False
    while not stop.is_set():
        for reply in session.get(keys.actor_ids, payload=request, timeout=ASK_TIMEOUT):
            if reply.err is not None:
                raise StartupFailure(f"replay shard 0 gave no actor id: {reply.err.payload.to_string()}")
            try:
                answer = decode(reply.ok.payload, ActorId)
            except ProtocolError as e:
                log.warning("ignored a reply to the actor id query: %s", e)
                continue
            if answer.name == name:
                log.info("actor id %d from replay shard 0, for %s", answer.actor_id, name)
                return answer.actor_id
        if not waiting:
            log.info("waiting for replay shard 0 to give this actor (%s) its id", name)
            waiting = True
        stop.wait(ASK_AGAIN_AFTER)
    return None
