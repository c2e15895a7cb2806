"""Real l2r-replay processes over loopback Zenoh, fed and sampled like actors and learners do."""

from __future__ import annotations

import queue
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import zenoh

from l2r.protocol import EXPERIENCE_QOS, Keys, PriorityUpdate, ReplayClient, encode
from tests.protocol.factories import make_chunk

pytestmark = pytest.mark.slow


def publish(session: zenoh.Session, run: str, chunks, num_shards: int = 1) -> None:
    keys = Keys(run)
    for chunk in chunks:
        session.put(keys.experience(chunk.actor_id, num_shards), encode(chunk), **EXPERIENCE_QOS.put())


def drain(client: ReplayClient, n: int) -> list:
    return [client.sample(timeout=10) for _ in range(n)]


def test_store_sample_duplicates_gaps_rejections_and_lag(start_replay, connect, stats_of, run_name):
    replay = start_replay()
    session = connect(replay)
    stats = stats_of(session)
    token = session.liveliness().declare_token(Keys(run_name).alive("actor", 5))
    chunks = [make_chunk(actor_id=5, seq=s, steps=20, ends=(7,), version=3) for s in (0, 1, 1, 3)]
    publish(session, run_name, chunks)
    session.put(Keys(run_name).experience(5), b"\x93not a message")
    publish(session, run_name, [make_chunk(actor_id=5, seq=9, obs_dim=40)])
    replies = list(session.get(Keys(run_name).sample(0), payload=b"\xc1junk", timeout=5))
    assert len(replies) == 1 and "malformed msgpack" in replies[0].err.payload.to_string()
    values = stats.wait(lambda v: v["inserted"] >= 60 and v["rejected"] >= 3)
    assert (values["size"], values["duplicates"], values["gaps"], values["rejected"]) == (60, 1, 1, 3)
    assert values["actor.5.transitions"] == 60

    with ReplayClient(session, run_name, batch_size=128, in_flight=3) as client:
        client.learner_version = 10
        for batch in drain(client, 5):
            seq, t = np.divmod(batch.obs[:, 0] - 5_000_000, 1000)
            assert set(seq.astype(int)) <= {0, 1, 3}
            want = np.where(t == 7, -(batch.obs[:, 0] + 1), batch.obs[:, 0] + 1)
            np.testing.assert_array_equal(batch.next_obs[:, 0], want)
            np.testing.assert_array_equal(batch.terminated, t == 7)
            assert np.all(batch.policy_versions == 3)
    assert stats.wait(lambda v: v["policy_lag"] == 7.0)
    token.undeclare()
    time.sleep(0.5)
    assert replay.stop() == 0
    log = replay.log()
    assert "actor/5 joined" in log and "actor/5 left" in log and "rejected message" in log


def test_rate_limiter_blocks_the_learner_until_data_arrives(start_replay, connect, run_name):
    replay = start_replay("--min-size", "100", "--samples-per-insert", "1", "--error-buffer", "256")
    session = connect(replay)
    with ReplayClient(session, run_name, batch_size=64, in_flight=2) as client:
        with pytest.raises(queue.Empty):
            client.sample(timeout=0.5)  # empty replay: the learner waits, no error
        publish(session, run_name, [make_chunk(seq=0, steps=100)])
        drain(client, 4)  # 0 inserts past min size + 256 of slack = 4 batches of 64
        with pytest.raises(queue.Empty):
            client.sample(timeout=1.0)
        assert client.waits > 0
        publish(session, run_name, [make_chunk(seq=1, steps=128)])
        drain(client, 2)  # 128 new transitions at 1 sample per insert release 2 batches
        with pytest.raises(queue.Empty):
            client.sample(timeout=0.5)


def test_prioritized_sampling_and_priority_updates(start_replay, connect, stats_of, run_name):
    replay = start_replay("--priority-exponent", "1.0")
    session = connect(replay)
    stats = stats_of(session)
    publish(session, run_name, [make_chunk(seq=0, steps=100)])
    stats.wait(lambda v: v["size"] == 100)
    with ReplayClient(session, run_name, batch_size=100, prioritized=True, in_flight=1) as client:
        batch = client.sample(timeout=10)
        # first 10 steps get priority 9, the other 90 priority 1: they should be half the draws
        priorities = np.where(batch.obs[:, 0] < 10, 9.0, 1.0)
        client.update_priorities(batch, priorities)
        stale = PriorityUpdate(batch.indices, batch.generations - 1, np.full(len(batch.indices), 50.0, np.float32))
        session.put(Keys(run_name).priorities(0), encode(stale))
        stats.wait(lambda v: v["priority_updates"] >= 100 and v["stale_priority_updates"] >= 100)
        client.sample(timeout=10)  # drop a batch that may predate the update
        client.sample(timeout=10)
        obs = np.concatenate([b.obs[:, 0] for b in drain(client, 30)])
        assert abs(np.mean(obs < 10) - 0.5) < 0.06
        assert batch.importance_weights(0.4).max() == 1.0


def test_snapshot_restores_after_kill_9(start_replay, connect, stats_of, run_name, tmp_path):
    args = ("--snapshot-dir", str(tmp_path / "snap"), "--snapshot-interval", "0.5")
    replay = start_replay(*args)
    session = connect(replay)
    publish(session, run_name, [make_chunk(actor_id=2, seq=s, steps=50, version=7) for s in range(4)])
    stats_of(session).wait(lambda v: v["size"] == 200)
    session.close()
    snapshot = tmp_path / "snap" / "replay-shard0.npz"
    deadline = time.time() + 10
    while "snapshot: 200 transitions" not in replay.log():
        assert time.time() < deadline, replay.log()
        time.sleep(0.1)
    replay.proc.kill()  # kill -9: no final snapshot
    replay.proc.wait()
    assert snapshot.exists() and not list(snapshot.parent.glob(".*tmp"))

    again = start_replay(*args, endpoint=replay.endpoint)
    session = connect(again)
    stats = stats_of(session)
    publish(session, run_name, [make_chunk(actor_id=2, seq=3, steps=50)])  # already stored before the kill
    values = stats.wait(lambda v: v["duplicates"] >= 1)
    assert values["size"] == 200 and values["actor.2.transitions"] == 200
    assert values["newest_version"] == 7  # known again, so a learner without its checkpoint starts above it
    with ReplayClient(session, run_name, batch_size=256) as client:
        seqs = np.concatenate([(b.obs[:, 0] - 2_000_000) // 1000 for b in drain(client, 4)])
        assert set(seqs.astype(int)) == {0, 1, 2, 3}
    assert "restored 200 transitions" in again.log()


def test_sigterm_writes_a_final_snapshot(start_replay, connect, stats_of, run_name, tmp_path):
    args = ("--snapshot-dir", str(tmp_path / "snap"), "--snapshot-interval", "3600")
    replay = start_replay(*args)
    session = connect(replay)
    publish(session, run_name, [make_chunk(seq=s, steps=30) for s in range(3)])
    stats_of(session).wait(lambda v: v["size"] == 90)
    assert replay.stop(signal.SIGTERM) == 0
    assert "snapshot: 90 transitions" in replay.log()
    again = start_replay(*args)
    connect(again)
    assert "restored 90 transitions" in again.log()
    assert again.stop() == 0
    other = start_replay(*args, "--capacity", "5000")  # a snapshot of another shape is not cut to fit
    assert other.proc.wait(30) == 2
    assert "this server is configured for (5000" in other.log()


def test_an_unreadable_snapshot_is_kept_aside_and_the_shard_starts_empty(start_replay, connect, tmp_path):
    snap = tmp_path / "snap"
    snap.mkdir()
    (snap / "replay-shard0.npz").write_bytes(b"PK\x03\x04 not really a zip")
    replay = start_replay("--snapshot-dir", str(snap))
    connect(replay)
    assert "is unreadable" in replay.log()
    assert [p.name.split(".corrupt-")[0] for p in snap.glob("*.corrupt-*")] == ["replay-shard0.npz"]


def test_two_shards_split_actors_and_serve_one_learner(start_replay, connect, stats_of, run_name):
    shards = [start_replay("--shard", str(i), "--num-shards", "2") for i in range(2)]
    session = connect(*shards)
    stats = stats_of(session)
    publish(session, run_name, [make_chunk(actor_id=a, seq=0, steps=40) for a in range(4)], num_shards=2)
    for i in range(2):
        values = stats.wait(lambda v: v["size"] == 80, shard=str(i))
        assert {k for k in values if k.startswith("actor.") and k.endswith(".transitions")} == \
            {f"actor.{a}.transitions" for a in range(i, 4, 2)}
    with ReplayClient(session, run_name, batch_size=64, in_flight=4) as client:
        batches = drain(client, 20)
        assert {b.shard for b in batches} == {0, 1}
        for b in batches:
            actors = (b.obs[:, 0] // 1_000_000).astype(int)
            assert set(actors) <= {b.shard, b.shard + 2}
        shards[1].proc.kill()  # a lost shard: the learner goes on with the other
        shards[1].proc.wait()
        time.sleep(0.5)
        assert {b.shard for b in drain(client, 40)[-20:]} == {0}


def test_cli_help_and_bad_flags():
    run = [sys.executable, "-m", "l2r.replay"]
    out = subprocess.run([*run, "--help"], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0 and "--samples-per-insert" in out.stdout and "--zenoh-config" in out.stdout
    bad = subprocess.run([*run, "--shard", "2", "--num-shards", "2"], capture_output=True, text=True, timeout=30)
    assert bad.returncode == 2 and "--shard 2 must be below --num-shards 2" in bad.stderr
