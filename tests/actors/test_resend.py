"""The actor's resend buffer: what an ack drops, what is sent again and when, and its byte bound."""

import signal
import socket
import subprocess
import sys
import uuid

import pytest
import zenoh

from l2r.actors.experience import ResendBuffer
from l2r.protocol import Keys, decode, session_config
from tests.conftest import ROOT, free_port, wait_for

STANDIN = "tests.actors.standin:StandIn-v0"


def filled(n: int, size: int = 100, max_bytes: int = 10_000) -> ResendBuffer:
    buffer = ResendBuffer(max_bytes, delay=3.0, max_delay=30.0)
    for seq in range(n):
        buffer.add(seq, bytes([seq]) * size, now=0.0)
    return buffer


def test_an_ack_drops_what_is_stored_and_keeps_the_missing_and_the_newer():
    buffer = filled(10)
    assert buffer.ack(highest=6, missing=[2, 5]) == 5  # 0, 1, 3, 4, 6
    assert len(buffer) == 5 and buffer.nbytes == 500 and buffer.acked == 5
    assert buffer.due(now=3.0) == [bytes([s]) * 100 for s in (2, 5, 7, 8, 9)]
    assert buffer.ack(highest=9, missing=[]) == 5 and len(buffer) == 0 and buffer.nbytes == 0


def test_nothing_is_resent_before_the_delay_and_each_resend_doubles_the_wait():
    buffer = filled(2)
    assert buffer.due(now=2.9) == []
    resent_at = [t for t in range(0, 200) if buffer.due(now=float(t))]
    assert resent_at == [3, 9, 21, 45, 75, 105, 135, 165, 195]  # waits 3, 6, 12, 24, then at most 30
    assert buffer.resent == 2 * len(resent_at)


def test_a_chunk_reported_missing_is_resent_soon_again():
    buffer = filled(3)
    for t in (3.0, 9.0, 21.0):
        buffer.due(now=t)
    buffer.ack(highest=2, missing=[1])  # the shard is there and still lacks chunk 1
    assert buffer.due(now=23.0) == []
    assert buffer.due(now=24.0) == [bytes([1]) * 100]


def test_the_byte_bound_drops_the_oldest_and_counts_them():
    buffer = filled(25, size=1000, max_bytes=10_000)  # a shard that never acknowledges
    assert len(buffer) == 10 and buffer.nbytes == 10_000 and buffer.dropped == 15
    assert buffer.due(now=3.0)[0] == bytes([15]) * 1000
    buffer.add(99, b"x" * 20_000, now=4.0)  # larger than the whole buffer: not kept
    assert len(buffer) == 10 and buffer.dropped == 16


def test_acks_for_chunks_no_longer_held_change_nothing():
    buffer = filled(25, size=1000, max_bytes=10_000)
    assert buffer.ack(highest=5, missing=[1, 2]) == 0
    assert len(buffer) == 10


# -- real processes: a router, an actor and a replay server that starts late ------------------

def port_open(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


@pytest.mark.slow
def test_chunks_sent_while_no_replay_server_listened_are_resent_and_stored_without_gaps(tmp_path):
    keys = Keys(f"test-resend-{uuid.uuid4().hex[:8]}")
    port = free_port()
    router = f"tcp/127.0.0.1:{port}"
    procs: list[subprocess.Popen] = []

    def start(name: str, *argv: str) -> subprocess.Popen:
        with open(tmp_path / f"{name}.log", "wb") as log:
            procs.append(subprocess.Popen([sys.executable, "-m", *argv], cwd=ROOT, stdout=log, stderr=subprocess.STDOUT))
        return procs[-1]

    def logs() -> str:
        return "\n".join(f"--- {p.name}\n{p.read_text()[-2000:]}" for p in tmp_path.glob("*.log"))

    start("router", "l2r.cli", "router", "-l", router)
    assert wait_for(lambda: port_open(port), 20), "the router never listened"
    session = zenoh.open(session_config(connect=[router]))
    stats: dict[str, dict] = {}

    def actor() -> dict:
        return stats.get(keys.stats("actor", 0), {})

    def replay() -> dict:
        return stats.get(keys.stats("replay", 0), {})

    try:
        session.declare_subscriber(keys.all_stats, lambda s: stats.update({str(s.key_expr): decode(s.payload).values}))
        # A token that says the actor's replay shard is there, with nobody subscribed to experience:
        # every chunk the actor sends now goes nowhere. (Zenoh reports the key alive while either
        # this token or the real shard's holds it.)
        standby = session.liveliness().declare_token(keys.alive("replay", 0))
        start("actor", "l2r.actors", "--run", keys.run, "--connect", router, "--env-id", STANDIN, "--num-envs", "3",
              "--chunk-size", "16", "--stats-interval", "0.2", "--resend-delay", "1")
        assert wait_for(lambda: actor().get("chunks_sent", 0) >= 30, 30), "no chunks sent into the void\n" + logs()
        lost = actor()["chunks_sent"]
        assert actor()["chunks_acked"] == 0

        start("replay", "l2r.replay", "--run", keys.run, "--connect", router, "--capacity", "200000",
              "--min-size", "1", "--stats-interval", "0.3")
        assert wait_for(lambda: replay().get("actor.0.gaps") == 0 and actor().get("chunks_acked", 0) >= lost + 20, 40), \
            f"not every chunk stored\n{replay()}\n{actor()}\n{logs()}"
        standby.undeclare()
        assert actor()["chunks_resent"] >= lost and actor()["resend_dropped"] == 0
        assert replay()["gaps"] == 0 and replay()["rejected"] == 0
    finally:
        session.close()
        for proc in reversed(procs):
            proc.send_signal(signal.SIGTERM)
        for proc in reversed(procs):
            try:
                assert proc.wait(timeout=20) == 0, logs()
            except subprocess.TimeoutExpired:
                proc.kill()
                raise AssertionError(f"{proc.args[2:4]} still running 20 s after SIGTERM\n{logs()}") from None
