"""Replay shard 0 gives actor ids (``l2r-actor --actor-id auto``): one per actor process, never
twice, and the same again to the same name, across a restart of the shard; real processes on
loopback Zenoh."""

from __future__ import annotations

import subprocess
import sys
import threading
import time

import msgpack
import zenoh

from l2r.actors.actor_id import ask_actor_id
from l2r.config import EXIT_CANNOT_START
from l2r.protocol import PROTOCOL_VERSION, ActorId, ActorIdRequest, Keys, decode, encode, session_config
from tests.conftest import free_port

# A process asking as an actor does: prints its name and the id it got, twice.
ASK = """
import sys, threading, zenoh
from l2r.actors.actor_id import ask_actor_id, process_name
from l2r.protocol import Keys, session_config
with zenoh.open(session_config(connect=[sys.argv[1]])) as session:
    keys, stop = Keys(sys.argv[2]), threading.Event()
    print(process_name(), ask_actor_id(session, keys, stop), ask_actor_id(session, keys, stop))
"""


def ask_from_new_processes(endpoint: str, run: str, n: int) -> dict[str, int]:
    """Start ``n`` processes at once that ask for an id; each one's name and id."""
    procs = [subprocess.Popen([sys.executable, "-c", ASK, endpoint, run], stdout=subprocess.PIPE, text=True)
             for _ in range(n)]
    ids = {}
    for proc in procs:
        name, first, again = proc.communicate(timeout=60)[0].split()
        assert proc.returncode == 0 and first == again, "a process asking twice must get its id again"
        ids[name] = int(first)
    return ids


def test_each_actor_process_gets_an_id_of_its_own_and_keeps_it_across_a_shard_restart(start_replay, connect,
                                                                                       tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    snapshots = ["--snapshot-dir", str(tmp_path / "snapshots")]
    replay = start_replay(*snapshots, endpoint=endpoint)
    first = ask_from_new_processes(endpoint, replay.run, 6)  # they start before the shard listens, and wait
    assert sorted(first.values()) == list(range(6)), first
    assert replay.stop() == 0, replay.log()

    replay = start_replay(*snapshots, endpoint=endpoint)
    later = ask_from_new_processes(endpoint, replay.run, 3)
    assert sorted(later.values()) == [6, 7, 8], "a restarted shard gave an id twice"
    # A container restarting its actor asks with the same name again, and gets its id back.
    name, actor_id = next(iter(first.items()))
    (reply,) = connect(replay).get(Keys(replay.run).actor_ids, payload=encode(ActorIdRequest(name)), timeout=5)
    assert decode(reply.ok.payload, ActorId) == ActorId(name, actor_id)


def test_a_shard_without_snapshots_gives_no_id_and_the_actor_says_why(start_replay, connect):
    replay = start_replay()
    session = connect(replay)
    empty_name = msgpack.packb({"v": PROTOCOL_VERSION, "kind": "actor_id_request", "name": ""})
    (reply,) = session.get(Keys(replay.run).actor_ids, payload=empty_name, timeout=5)
    assert reply.err.payload.to_string().startswith("invalid: "), "an empty name must be refused"
    actor = subprocess.run([sys.executable, "-m", "l2r.actors", "--actor-id", "auto", "--run", replay.run,
                            "--connect", replay.endpoint], capture_output=True, text=True, timeout=120)
    assert actor.returncode == EXIT_CANNOT_START, actor.stderr
    assert actor.stderr.strip().splitlines()[-1] == (
        "l2r-actor: replay shard 0 gave no actor id: unavailable: replay shard 0 has no --snapshot-dir, so it could "
        "not remember the actor ids it gave after a restart; give each actor its own --actor-id instead")


def test_an_actor_waiting_for_shard_0_stops_when_told():
    stop, got = threading.Event(), []
    with zenoh.open(session_config(listen=[f"tcp/127.0.0.1:{free_port()}"])) as session:
        asking = threading.Thread(target=lambda: got.append(ask_actor_id(session, Keys("nobody-here"), stop)))
        asking.start()
        time.sleep(0.5)
        assert asking.is_alive(), "it must wait while no shard 0 answers"
        stop.set()
        asking.join(timeout=5)
        assert not asking.is_alive() and got == [None]
