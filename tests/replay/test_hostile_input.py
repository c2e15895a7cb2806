"""What another team's client might send a real l2r-replay over loopback Zenoh: every integer
field at its limits and beyond, and each kind of message the issue found quietly accepted.
After each message the server must still answer; afterwards both its write-ahead log and its
snapshot must restore what it stored, and it must go on storing."""

from __future__ import annotations

import signal
import time

import msgpack
import numpy as np
import pytest
import zenoh

from l2r.protocol import EXPERIENCE_QOS, Keys, SampleBatch, SampleRequest, decode, encode
from l2r.protocol.limits import INTEGER_LIMITS
from l2r.replay import snapshot
from tests.conftest import wait_for
from tests.protocol.factories import make_chunk, make_image_chunk, stream_chunk

pytestmark = pytest.mark.slow

EXTREMES = (-2**63, 2**63, 2**64 - 1)  # msgpack's ends; 2**63 as a uint64 once killed the server


def edge_values(low: int, high: int) -> list[int]:
    return sorted({low - 1, low, high, high + 1, *EXTREMES})


def put_raw(session: zenoh.Session, key: str, raw: dict) -> None:
    session.put(key, msgpack.packb(raw, use_bin_type=True), **EXPERIENCE_QOS.put())


def test_experience_integers_at_their_limits_and_beyond(start_replay, connect, ask_stats, acks_of, run_name, tmp_path):
    args = ("--snapshot-dir", str(tmp_path / "snap"), "--snapshot-interval", "3600")
    replay = start_replay(*args)
    session = connect(replay)
    acks = acks_of(session)
    keys = Keys(run_name)
    stored, rejected, actor = {}, 0, 100
    for name, (low, high) in INTEGER_LIMITS["experience"].items():
        for value in edge_values(low, high):
            actor += 1  # a fresh actor each time, so one extreme seq or epoch does not shadow the next
            raw = msgpack.unpackb(encode(make_chunk(actor_id=actor, seq=3, steps=5)), raw=False)
            raw[name] = value
            key_actor = value if name == "actor_id" and low <= value <= high else actor
            raw["actor_id"] = raw["actor_id"] if name == "actor_id" else actor
            put_raw(session, f"{keys.root}/experience/0/{key_actor}", raw)
            if low <= value <= high:
                stored[raw["actor_id"]] = raw["epoch"]
            else:
                rejected += 1
            stats = ask_stats(session)
            assert stats is not None, f"{name}={value} silenced the server\n{replay.log()[-3000:]}"
    # every accepted extreme is acknowledged: building acks from them no longer overflows
    ack = acks.wait(lambda a: all(a.of(k, e) is not None for k, e in stored.items()))
    stats = ask_stats(session)
    assert (stats["size"], stats["rejected.out_of_range"]) == (5 * len(stored), rejected), stats
    assert ack.shard == 0

    replay.proc.kill()  # kill -9: the write-ahead log alone brings back what was acknowledged
    replay.proc.wait()
    again = start_replay(*args, endpoint=replay.endpoint)
    session = connect(again)
    assert ask_stats(session)["size"] == 5 * len(stored), again.log()[-3000:]
    assert again.stop(signal.SIGTERM) == 0  # and the final snapshot holds them
    third = start_replay(*args, endpoint=replay.endpoint)
    session = connect(third)
    assert ask_stats(session)["size"] == 5 * len(stored), third.log()[-3000:]
    session.put(keys.experience(1), encode(make_chunk(actor_id=1, seq=0, steps=5)), **EXPERIENCE_QOS.put())
    acks_of(session).wait(lambda a: a.of(1, 1) is not None)
    assert ask_stats(session)["size"] == 5 * len(stored) + 5


def test_what_was_quietly_accepted_is_rejected_with_its_reason(start_replay, connect, ask_stats, run_name):
    replay = start_replay()
    session = connect(replay)
    keys = Keys(run_name)
    chunk = msgpack.unpackb(encode(make_chunk(actor_id=4, steps=4)), raw=False)
    cases = {
        "version": [dict(chunk, v=1.0), dict(chunk, v=True)],
        "out_of_range": [dict(chunk, seq=-1)],
        "bad_bool": [dict(chunk, terminated=dict(chunk["terminated"], data=bytes([0, 2, 0, 0])))],
        "not_finite": [dict(chunk, rewards=dict(chunk["rewards"], data=b"\x00\x00\xc0\x7f" * 4))],
        "empty_chunk": [dict(chunk, **{k: dict(chunk[k], shape=[0, *chunk[k]["shape"][1:]], data=b"")
                                       for k in ("actions", "rewards", "terminated", "truncated")},
                             obs=dict(chunk["obs"], shape=[1, 41], data=bytes(164)))],
    }
    for raws in cases.values():
        for raw in raws:
            put_raw(session, keys.experience(4), raw)
    put_raw(session, keys.experience(5), chunk)  # actor 4's chunk under actor 5's key
    image = msgpack.unpackb(encode(make_image_chunk()), raw=False)  # camera frames, to a shard of the vector
    put_raw(session, keys.experience(image["actor_id"]), image)
    stats = wait_for(lambda: (values := ask_stats(session)) and values["rejected"] >= 8 and values)
    assert stats["size"] == 0 and stats["rejected"] == 8, stats
    reasons = (*cases, "actor_id_mismatch", "unknown_field")
    assert {reason: stats.get(f"rejected.{reason}") for reason in reasons} == {
        "version": 2, "out_of_range": 1, "bad_bool": 1, "not_finite": 1, "empty_chunk": 1, "actor_id_mismatch": 1,
        "unknown_field": 1}
    log = replay.log()
    assert "Traceback" not in log
    for reason in reasons:  # the first of each reason is logged, whatever came before
        assert f"({reason}: 1 so far" in log, reason


def test_chunks_of_more_actor_ids_than_max_actors_are_rejected(start_replay, connect, ask_stats, run_name):
    replay = start_replay("--max-actors", "3")
    session = connect(replay)
    keys = Keys(run_name)
    for actor in range(1, 7):  # a peer inventing actor ids: from the fourth on, each is one too many
        session.put(keys.experience(actor), encode(make_chunk(actor_id=actor, steps=5)), **EXPERIENCE_QOS.put())
    # until each of the six chunks of 5 transitions is stored or rejected
    stats = wait_for(lambda: (v := ask_stats(session)) and v["size"] + 5 * v["rejected"] == 30 and v)
    assert (stats["size"], stats["rejected"], stats.get("rejected.too_many_actors")) == (15, 3, 3), stats
    assert [name for name in stats if name.endswith(".transitions")] == [f"actor.{a}.transitions" for a in (1, 2, 3)]
    assert "(too_many_actors: 1 so far" in replay.log()
    # the actors it tracks go on
    session.put(keys.experience(2), encode(make_chunk(actor_id=2, seq=1, steps=5)), **EXPERIENCE_QOS.put())
    assert wait_for(lambda: (values := ask_stats(session)) and values["size"] == 20), ask_stats(session)


def sample(session: zenoh.Session, keys: Keys, **fields) -> list:
    raw = msgpack.unpackb(encode(SampleRequest(batch_size=4)), raw=False) | fields
    return list(session.get(keys.sample(0), payload=msgpack.packb(raw), timeout=10,
                            consolidation=zenoh.ConsolidationMode.NONE))


def test_sample_requests_at_their_limits_and_beyond(start_replay, connect, ask_stats, run_name):
    replay = start_replay()
    session = connect(replay)
    keys = Keys(run_name)
    session.put(keys.experience(0), encode(make_chunk(steps=50)), **EXPERIENCE_QOS.put())
    assert len(sample(session, keys)) == 1
    for name, (low, high) in INTEGER_LIMITS["sample_request"].items():
        for value in edge_values(low, high):
            replies = sample(session, keys, **{name: value}, **({"gamma": 0.9} if name == "n_step" else {}))
            assert replies, f"{name}={value}: no answer\n{replay.log()[-3000:]}"
            if not low <= value <= high:
                assert replies[0].err.payload.to_string().startswith("out_of_range: "), (name, value)
            elif name == "batch_size" and value == high:  # 2**20 runner transitions exceed a message
                assert replies[0].err.payload.to_string().startswith("too_large: "), replies[0].err.payload.to_string()
            else:
                assert all(r.ok is not None for r in replies), (name, value)
                assert len(replies) == (value if name == "count" else 1)  # one reply per batch, unconsolidated
    assert ask_stats(session)["learner_version"] == 2**63 - 1


def test_sequence_jumps_neither_stall_the_shard_nor_fill_its_snapshot(start_replay, connect, ask_stats, run_name,
                                                                      tmp_path):
    snap = tmp_path / "snap"
    replay = start_replay("--snapshot-dir", str(snap), "--snapshot-interval", "3600")
    session = connect(replay)
    seqs = [10_000 * k for k in range(1, 31)] + [10**15]  # 10,000 missing, then a jump of 10^4 or more each
    for seq in seqs:
        payload = encode(make_chunk(actor_id=3, seq=seq, steps=2))
        session.put(Keys(run_name).experience(3), payload, **EXPERIENCE_QOS.put())
    start = time.monotonic()
    stats = wait_for(lambda: (v := ask_stats(session)) and v["actor.3.transitions"] == 2 * len(seqs) and v)
    assert stats and time.monotonic() - start < 5, f"stalled: {stats}"  # each jump cost 6-8 s before
    assert 2**20 <= stats["gaps"] < 31 * 2**20 and stats["sequence_jumps"] == 1, stats
    assert replay.stop() == 0
    saved = snapshot.read(snapshot.snapshot_path(snap, 0))[1]["sequences"]["actors"]["3"]
    assert saved["gaps"] == stats["gaps"] and len(saved["missing_runs"]) == 1


def test_bad_n_step_requests_and_streams_that_do_not_join_are_counted(start_replay, connect, ask_stats, run_name):
    replay = start_replay("--obs-dim", "2", "--act-dim", "1", "--queue-capacity", "100")
    session = connect(replay)
    keys = Keys(run_name)
    honest, liar = stream_chunk(0, 8, seq=0, actor_id=1), stream_chunk(8, 8, seq=1, actor_id=1)
    liar.obs[0] = 99.0  # claims to go on where the stream's last chunk ended, but starts elsewhere
    liar.log_probs = honest.log_probs = np.zeros(8, np.float32)
    for chunk in (honest, liar):
        session.put(keys.experience(1), encode(chunk), **EXPERIENCE_QOS.put())
    assert wait_for(lambda: (v := ask_stats(session)) and v["size"] == 16), ask_stats(session)
    bad = {"out_of_range": [{"n_step": 0, "gamma": 0.9}, {"n_step": 21, "gamma": 0.9}, {"n_step": 3, "gamma": 1.01},
                            {"n_step": 3, "gamma": -1.0}],
           "not_finite": [{"n_step": 3, "gamma": float("inf")}],
           "wrong_type": [{"n_step": "3", "gamma": 0.9}, {"n_step": 3, "gamma": None}],
           "missing_field": [{"n_step": 3}],
           "invalid": [{"n_step": 3, "gamma": 0.9, "table": "queue"}]}
    for reason, requests in bad.items():
        for fields in requests:
            replies = sample(session, keys, **fields)
            assert len(replies) == 1 and replies[0].err.payload.to_string().startswith(f"{reason}: "), fields
    stats = ask_stats(session)
    assert {reason: stats.get(f"rejected.{reason}") for reason in bad} == {r: len(q) for r, q in bad.items()}, stats
    assert (stats["chunk_links"], stats["link_mismatches"]) == (0, 1), stats
    good = decode(sample(session, keys, n_step=3, gamma=0.5, batch_size=200)[0].ok.payload, SampleBatch)
    by_obs = dict(zip(good.obs[:, 0], zip(good.rewards, good.discounts)))
    assert by_obs[7] == (8, 0.5)  # the honest chunk's last step is not joined to the liar's first
    assert by_obs[5] == (6 + 0.5 * 7 + 0.25 * 8, 0.125)
