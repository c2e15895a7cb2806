"""The queue table of a real l2r-replay over loopback Zenoh: each transition given once, in order,
with its trajectory's ends marked; stale ones dropped and counted; a full queue holding its actors
(a real l2r-actor among them) or dropping its oldest; peers from before the queue kept working."""

from __future__ import annotations

import queue
import signal
import subprocess
import sys
import threading

import numpy as np
import pytest
import zenoh

from l2r.protocol import EXPERIENCE_QOS, Keys, ReplayClient, SampleRequest, Stats, decode, encode
from tests.conftest import ROOT, wait_for
from tests.protocol.factories import make_chunk

pytestmark = pytest.mark.slow

QUEUE_ONLY = ("--capacity", "0", "--queue-capacity")


def chunk(actor_id: int = 1, seq: int = 0, steps: int = 20, version: int = 0, log_probs: bool = True, **kw):
    """A factory chunk whose log-probabilities are minus its observations' row ids."""
    c = make_chunk(actor_id=actor_id, seq=seq, steps=steps, version=version, **kw)
    c.log_probs = -c.obs[:-1, 0] if log_probs else None
    return c


def publish(session: zenoh.Session, run: str, *chunks) -> None:
    for c in chunks:
        session.put(Keys(run).experience(c.actor_id), encode(c), **EXPERIENCE_QOS.put())


def take(session: zenoh.Session, run: str, batch_size: int, n: int, learner_version: int = -1) -> list:
    with ReplayClient(session, run, batch_size, in_flight=1, table="queue") as client:
        client.learner_version = learner_version
        return [client.sample(timeout=10) for _ in range(n)]


def test_each_transition_is_given_once_in_order_with_its_trajectory_ends(start_replay, connect, ask_stats, run_name):
    replay = start_replay(*QUEUE_ONLY, "1000")
    session = connect(replay)
    sent = [chunk(actor, seq, ends=(7,), truncate=(12,)) for seq in range(3) for actor in (1, 2)]
    publish(session, run_name, *sent)
    assert wait_for(lambda: ask_stats(session)["queue.size"] == 120)
    with ReplayClient(session, run_name, 50, in_flight=1, table="queue") as client:
        batches = [client.sample(timeout=10) for _ in range(2)]
        with pytest.raises(queue.Empty):  # 20 left: not a batch of 50
            client.sample(timeout=1.0)
        publish(session, run_name, chunk(1, 3, steps=30))
        batches.append(client.sample(timeout=10))

    rows = np.concatenate([b.obs[:, 0] for b in batches])
    order = np.concatenate([c.obs[:-1, 0] for c in [*sent, chunk(1, 3, steps=30)]])
    np.testing.assert_array_equal(rows, order)  # every transition once, first in first out
    indices = np.concatenate([b.indices for b in batches])
    np.testing.assert_array_equal(indices, np.arange(150))
    for b in batches:
        seq, t = np.divmod(b.obs[:, 0] % 1_000_000, 1000)
        terminated, truncated = (t == 7) & (seq < 3), (t == 12) & (seq < 3)  # the last chunk ends no episode
        np.testing.assert_array_equal(b.log_probs, -b.obs[:, 0])
        np.testing.assert_array_equal(b.next_obs[:, 0], np.where(terminated | truncated, -(b.obs[:, 0] + 1),
                                                                 b.obs[:, 0] + 1))
        assert (b.terminated == terminated).all() and (b.truncated == truncated).all()
    # a piece ends where its chunk ends, and where the batch cuts a chunk
    ends = np.concatenate([b.segment_ends for b in batches])
    assert np.flatnonzero(ends).tolist() == [19, 39, 49, 59, 79, 99, 119, 149]
    values = ask_stats(session)
    assert (values["queue.given"], values["queue.size"], values["queue.dropped_stale"]) == (150, 0, 0)


def test_stale_transitions_are_dropped_and_counted(start_replay, connect, ask_stats, run_name):
    replay = start_replay(*QUEUE_ONLY, "1000", "--queue-max-lag", "1")
    session = connect(replay)
    publish(session, run_name, *[chunk(seq=v, steps=10, version=v) for v in range(4)])
    assert wait_for(lambda: ask_stats(session)["queue.size"] == 40)
    (batch,) = take(session, run_name, 20, 1, learner_version=3)  # versions 0 and 1 are more than 1 behind
    assert sorted(set(batch.policy_versions.tolist())) == [2, 3]
    publish(session, run_name, chunk(seq=4, steps=10, version=1))  # stale on arrival
    values = wait_for(lambda: (v := ask_stats(session))["queue.dropped_stale"] == 30 and v)
    assert values["queue.size"] == 0 and values["queue.given"] == 20, values


def test_a_full_queue_holds_its_actors_until_the_learner_takes_a_batch(start_replay, connect, acks_of, run_name):
    replay = start_replay(*QUEUE_ONLY, "40")
    session = connect(replay)
    acks = acks_of(session)
    publish(session, run_name, chunk(seq=0), chunk(seq=1))
    assert acks.wait(lambda a: a.hold is True).hold
    take(session, run_name, 40, 1)
    assert acks.wait(lambda a: a.hold is False).hold is False


def test_a_dropping_queue_makes_room_with_its_oldest(start_replay, connect, ask_stats, run_name):
    replay = start_replay(*QUEUE_ONLY, "40", "--queue-when-full", "drop")
    session = connect(replay)
    publish(session, run_name, *[chunk(seq=s) for s in range(5)])
    assert wait_for(lambda: ask_stats(session)["queue.dropped_full"] == 60)
    (batch,) = take(session, run_name, 40, 1)
    assert set((batch.obs[:, 0] % 1_000_000 // 1000).astype(int).tolist()) == {3, 4}  # the last two chunks


def test_peers_from_before_the_queue_keep_working_or_are_told_why(start_replay, connect, ask_stats, run_name):
    both = start_replay("--queue-capacity", "100")
    session = connect(both)
    publish(session, run_name, chunk(seq=0, log_probs=False))  # an older actor: no log-probabilities
    values = wait_for(lambda: (v := ask_stats(session))["size"] == 20 and v)
    assert values["queue.size"] == 0 and values["queue.no_log_probs"] == 1
    old_request = SampleRequest(8, 1, False, -1)  # no table: the replay table, as before
    replies = [r.ok for r in session.get(Keys(run_name).sample(0), payload=encode(old_request), timeout=5)]
    batch = decode(replies[0].payload)
    assert batch.KIND == "sample_batch" and batch.log_probs is None and len(batch.obs) == 8

    assert both.stop() == 0

    queue_only = start_replay(*QUEUE_ONLY, "100")
    session = connect(queue_only)
    publish(session, run_name, chunk(seq=0, log_probs=False))
    assert wait_for(lambda: ask_stats(session).get("rejected.no_log_probs") == 1)
    replies = list(session.get(Keys(run_name).sample(0), payload=encode(old_request), timeout=5))
    assert "no_table: sample_request: shard 0 keeps no replay table" in replies[0].err.payload.to_string()
    assert queue_only.stop() == 0


def test_a_real_actor_waits_while_the_queue_is_full_and_goes_on_when_a_batch_is_taken(start_replay, connect,
                                                                                       run_name):
    replay = start_replay(*QUEUE_ONLY, "64")
    session = connect(replay)
    stats: list[dict] = []
    session.declare_subscriber(Keys(run_name).stats("actor", 0),
                               lambda sample: stats.append(decode(sample.payload, Stats).values))
    actor = subprocess.Popen(
        [sys.executable, "-m", "l2r.actors", "--run", run_name, "--connect", replay.endpoint, "--env-id",
         "tests.actors.standin:StandIn-v0", "--num-envs", "2", "--chunk-size", "8", "--random-steps", "0",
         "--stats-interval", "0.2"], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        assert wait_for(lambda: stats and stats[-1]["held_s"] > 1.0, timeout=30), stats[-1:]
        steps = stats[-1]["env_steps"]
        assert wait_for(lambda: stats[-1]["held_s"] > 2.0) and stats[-1]["env_steps"] == steps  # held: no steps
        threading.Thread(target=take, args=(session, run_name, 64, 2), daemon=True).start()
        assert wait_for(lambda: stats[-1]["env_steps"] > steps, timeout=15), "the actor never went on"
    finally:
        actor.send_signal(signal.SIGTERM)
        out, _ = actor.communicate(timeout=20)
    assert actor.returncode == 0, out
