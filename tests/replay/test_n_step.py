"""n-step returns from a real l2r-replay over loopback Zenoh, asked for by the protocol's
ReplayClient: the values worked out by hand (gamma 0.5, n 3; step k of a stream earns reward
k + 1, see ``stream_chunk``), links that survive a snapshot and the write-ahead log, and a client
that tells a shard from before n-step returns."""

from __future__ import annotations

import queue
import signal
import time

import numpy as np
import pytest
import zenoh

from l2r.protocol import EXPERIENCE_QOS, Keys, ReplayClient, SampleBatch, encode, session_config
from tests.conftest import free_port
from tests.protocol.factories import stream_chunk

pytestmark = pytest.mark.slow

SMALL = ("--obs-dim", "2", "--act-dim", "1")


def send(session: zenoh.Session, run: str, *chunks) -> None:
    for chunk in chunks:
        session.put(Keys(run).experience(chunk.actor_id), encode(chunk), **EXPERIENCE_QOS.put())


def windows(session: zenoh.Session, run: str, stored: int, n_step: int = 3, gamma: float = 0.5) -> dict[float, tuple]:
    """Observation -> (reward, discount, next observation, terminated, truncated) of every one of
    the ``stored`` transitions, from batches the client samples."""
    got: dict[float, tuple] = {}
    with ReplayClient(session, run, batch_size=256, in_flight=2, n_step=n_step, gamma=gamma) as client:
        while len(got) < stored:
            batch = client.sample(timeout=10)
            got |= {float(o): (float(r), float(d), float(x), bool(te), bool(tr)) for o, r, d, x, te, tr in zip(
                batch.obs[:, 0], batch.rewards, batch.discounts, batch.next_obs[:, 0], batch.terminated,
                batch.truncated)}
    assert len(got) == stored
    return got


def test_n_step_batches_follow_each_stream_and_stop_where_it_breaks(start_replay, connect, ask_stats, run_name):
    replay = start_replay(*SMALL)
    session = connect(replay)
    send(session, run_name,
         stream_chunk(0, 4, seq=0, actor_id=1),
         stream_chunk(0, 4, seq=1, actor_id=1, env_id=1),  # another environment of the same actor, in between
         stream_chunk(4, 4, seq=2, actor_id=1, ends=(6,)),
         stream_chunk(8, 4, seq=3, actor_id=1, truncate=(9,)),
         stream_chunk(16, 4, seq=5, actor_id=1))  # steps 12..15 (seq 4) were lost
    got = windows(session, run_name, stored=20)
    assert got[0] == (1 + 0.5 * 2 + 0.25 * 3, 0.125, 3, False, False)  # inside a chunk
    assert got[2] == (3 + 0.5 * 4 + 0.25 * 5, 0.125, 5, False, False)  # across the first chunk's end
    assert got[3] == (4 + 0.5 * 5 + 0.25 * 6, 0.125, 6, False, False)
    assert got[5] == (6 + 0.5 * 7, 0.0, -7, True, False)  # stops at the termination: no bootstrap
    assert got[7] == (8 + 0.5 * 9 + 0.25 * 10, 0.125, -10, False, True)  # ends at the truncation: bootstraps
    assert got[9] == (10, 0.5, -10, False, True)
    assert got[10] == (11 + 0.5 * 12, 0.25, 12, False, False)  # the next chunk of the stream never came
    assert got[1002] == (3 + 0.5 * 4, 0.25, 1004, False, False)
    stats = ask_stats(session)
    assert (stats["chunk_links"], stats["link_mismatches"], stats["streams"]) == (2, 1, 2), stats

    with ReplayClient(session, run_name, batch_size=64, in_flight=1, gamma=0.5) as one_step:
        batch = one_step.sample(timeout=10)
        assert batch.discounts is None
        np.testing.assert_array_equal(batch.rewards, np.abs(batch.obs[:, 0]) % 1000 + 1)


def test_links_survive_a_snapshot_and_the_write_ahead_log(start_replay, connect, acks_of, run_name, tmp_path):
    args = (*SMALL, "--snapshot-dir", str(tmp_path / "snap"), "--snapshot-interval", "3600")
    replay = start_replay(*args)
    session = connect(replay)
    acks = acks_of(session)
    send(session, run_name, stream_chunk(0, 4, seq=0), stream_chunk(4, 4, seq=1))
    acks.wait(lambda ack: ack.of(0, 1) is not None and ack.of(0, 1)[0] == 1)
    assert replay.stop(signal.SIGTERM) == 0  # the final snapshot holds both chunks and their link

    again = start_replay(*args, endpoint=replay.endpoint)
    session = connect(again)
    acks = acks_of(session)
    send(session, run_name, stream_chunk(8, 4, seq=2))  # joined to steps 4..7 through the restored stream end
    acks.wait(lambda ack: ack.of(0, 1) is not None and ack.of(0, 1)[0] == 2)
    again.proc.kill()  # kill -9: only the write-ahead log holds the third chunk
    again.proc.wait()

    third = start_replay(*args, endpoint=replay.endpoint)
    got = windows(connect(third), run_name, stored=12)
    assert got[3] == (4 + 0.5 * 5 + 0.25 * 6, 0.125, 6, False, False)  # the snapshot's link
    assert got[6] == (7 + 0.5 * 8 + 0.25 * 9, 0.125, 9, False, False)  # rebuilt from the log


def alone() -> zenoh.Session:
    """A session on a port of its own (no scouting): it reaches only its own queryables."""
    return zenoh.open(session_config(listen=[f"tcp/127.0.0.1:{free_port()}"]))


@pytest.mark.parametrize("asked, reason", [({"n_step": 3, "gamma": 0.99}, "no_discounts"),
                                           ({"frame_stack": 3}, "no_frames")])
def test_a_shard_from_before_n_step_returns_and_frames_is_told_apart_and_left_alone(run_name, asked, reason):
    """A shard that ignores n_step and frame_stack answers one-step batches of the vector (played
    here by a queryable, as no such l2r-replay is at hand): the client rejects them and counts
    why, and asks that shard only about once a second."""
    keys, questions = Keys(run_name), []

    def old_shard(query: zenoh.Query) -> None:
        questions.append(time.monotonic())
        b = 4
        query.reply(query.key_expr, encode(SampleBatch(
            0, 100, False, np.zeros((b, 2), np.float32), np.zeros((b, 1), np.float32), np.zeros(b, np.float32),
            np.zeros((b, 2), np.float32), np.zeros(b, bool), np.zeros(b, bool), np.arange(b), np.arange(b),
            np.full(b, 0.01), np.zeros(b, np.int64))))

    session = alone()
    try:
        queryable = session.declare_queryable(keys.sample(0), old_shard)
        token = session.liveliness().declare_token(keys.alive("replay", 0))
        with ReplayClient(session, run_name, batch_size=4, in_flight=4, **asked) as client:
            with pytest.raises(queue.Empty):
                client.sample(timeout=2.5)
            # each of the 4 query slots waits a second after such a batch
            assert 1 <= client.rejections.by_reason[reason] <= len(questions) <= 4 * 3
        token.undeclare()
        queryable.undeclare()
    finally:
        session.close()


def test_a_client_with_an_impossible_n_step_fails_at_once(run_name):
    session = alone()
    try:
        with pytest.raises(ValueError, match="n_step: 21 not in"):
            ReplayClient(session, run_name, n_step=21, gamma=0.9)
        with pytest.raises(ValueError, match="needs gamma"):
            ReplayClient(session, run_name, n_step=3)
    finally:
        session.close()
