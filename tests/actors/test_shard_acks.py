"""A real `l2r-actor` and the replay shard it feeds, played by this test: the actor waits for its
own shard, and on shutdown for the acks of its last chunks."""

from __future__ import annotations

import threading
import time
import uuid

import numpy as np
import pytest

from l2r.protocol import ACK_QOS, ReplayAck, encode
from tests.actors.test_actor import Peer, stop
from tests.conftest import wait_for

pytestmark = pytest.mark.slow


@pytest.fixture
def peer():
    p = Peer(f"test-acks-{uuid.uuid4().hex[:8]}")
    yield p
    p.close()


class SlowShard:
    """Acknowledges every chunk it received, ``delay`` seconds after receiving it."""

    def __init__(self, peer: Peer, delay: float):
        self.peer, self.delay = peer, delay
        self._publisher = peer.session.declare_publisher(peer.keys.replay_ack(0), **ACK_QOS.publisher())
        self._stop = threading.Event()
        self._arrived: dict[int, float] = {}
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.wait(0.1):
            now, chunks = time.monotonic(), list(self.peer.chunks)
            for chunk in chunks:
                self._arrived.setdefault(chunk.seq, now)
            old = sorted(s for s, t in self._arrived.items() if now - t >= self.delay)
            if old:  # every chunk up to the first one still too young
                highest = next((s - 1 for i, s in enumerate(old) if s != i), old[-1])
                epoch = chunks[0].epoch
                self._publisher.put(encode(ReplayAck(0, np.array([0]), np.array([epoch]), np.array([highest]),
                                                     np.array([0]), np.array([], np.int64))))

    def close(self) -> None:
        self._stop.set()
        self._thread.join()


def test_an_actor_waits_for_its_own_shard_and_stops_only_once_its_last_chunks_are_acknowledged(peer):
    other = peer.session.liveliness().declare_token(peer.keys.alive("replay", 1))  # not the actor's shard
    shard = SlowShard(peer, delay=1.0)
    proc = peer.actor("--num-shards", "2", "--chunk-delay", "60")  # actor 0 feeds shard 0; only full chunks
    try:
        assert wait_for(lambda: peer.last_stats().get("waiting_for_replay") == 1), "actor not waiting"
        time.sleep(0.5)
        assert not peer.chunks, "chunks sent while only another shard was alive"
        peer.replay_up(True)
        assert wait_for(lambda: peer.last_stats().get("chunks_acked", 0) >= 3), "no acks heard"
    finally:
        other.undeclare()
        out = stop(proc)  # the last, partial chunks go out now, and their acks come a second later
        shard.close()
    assert "no replay server alive for shard 0" in out
    assert "the replay shard acknowledged the last" in out, out[-2000:]
