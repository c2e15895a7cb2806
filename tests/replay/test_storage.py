"""Storage, sum-tree, the server's acks and the rate limiter, as plain functions."""

from __future__ import annotations

import numpy as np
import pytest

from l2r.protocol import decode, encode
from l2r.replay.queue import QueueConfig, QueueTable
from l2r.replay.rate_limiter import RateLimiter
from l2r.replay.server import ReplayServer, ServerConfig
from l2r.replay.storage import ChunkRejected, Overtaken, StateCopy, Storage, StorageConfig
from l2r.replay.sumtree import SumTree
from tests.protocol.factories import make_chunk


def expected_next(obs_value: float, final_steps: set[float]) -> float:
    return -(obs_value + 1) if obs_value in final_steps else obs_value + 1


def check_batch(batch, finals: set[float]) -> None:
    """Every sampled transition's next observation is the one its chunk said."""
    obs, nxt = batch.obs[:, 0], batch.next_obs[:, 0]
    want = np.array([expected_next(o, finals) for o in obs])
    np.testing.assert_array_equal(nxt, want)
    np.testing.assert_array_equal(batch.rewards, obs)  # reward t of a chunk was written as obs t


def test_next_observations_across_chunks_episodes_and_wrap_around():
    storage = Storage(StorageConfig(capacity=50, side_fraction=0.5))
    finals = set()
    for seq in range(12):  # 12 chunks of 7: the ring wraps around several times
        chunk = make_chunk(seq=seq, steps=7, ends=(2,), truncate=(5,))
        finals |= {float(seq * 1000 + t) for t in (2, 5)}
        storage.insert(chunk)
    assert storage.live == 50 and storage.written == 84
    for prioritized in (False, True):
        check_batch(storage.sample(500, prioritized), finals)


def test_fifo_keeps_the_newest():
    storage = Storage(StorageConfig(capacity=30))
    for seq in range(10):
        storage.insert(make_chunk(seq=seq, steps=10))
    seqs = set((storage.sample(1000, False).obs[:, 0] // 1000).astype(int))
    assert seqs == {7, 8, 9}


def test_side_ring_overflow_evicts_instead_of_corrupting():
    # many episode ends and a tiny side ring: old slots lose their next observation
    storage = Storage(StorageConfig(capacity=100, side_fraction=0.1))
    finals = set()
    for seq in range(30):
        storage.insert(make_chunk(seq=seq, steps=5, ends=(0, 1, 2)))
        finals |= {float(seq * 1000 + t) for t in (0, 1, 2)}
    assert storage.live < 100
    check_batch(storage.sample(400, False), finals)
    check_batch(storage.sample(400, True), finals)


def test_wrong_widths_are_rejected():
    storage = Storage(StorageConfig(capacity=100, obs_dim=41, act_dim=18))
    with pytest.raises(ChunkRejected, match=r"shape \[11, 40\], expected \[rows, 41\]") as rejected:
        storage.insert(make_chunk(obs_dim=40))
    assert rejected.value.reason == "wrong_shape"  # the observation spec's check, as for any field
    with pytest.raises(ChunkRejected, match="actions of width 17") as rejected:
        storage.insert(make_chunk(act_dim=17))
    assert rejected.value.reason == "wrong_width"
    with pytest.raises(ChunkRejected, match="exceeds capacity"):
        storage.insert(make_chunk(steps=101))
    assert storage.live == 0


def test_prioritized_sampling_follows_priorities():
    storage = Storage(StorageConfig(capacity=1000, priority_exponent=1.0))
    storage.insert(make_chunk(steps=4))
    batch = storage.sample(4, True)
    order = np.argsort(batch.indices)
    storage.update_priorities(batch.indices[order], batch.generations[order], np.array([1.0, 2.0, 3.0, 4.0]))
    sampled = np.concatenate([storage.sample(256, True).indices for _ in range(40)])
    share = np.bincount(sampled, minlength=4)[:4] / len(sampled)
    np.testing.assert_allclose(share, np.array([1, 2, 3, 4]) / 10, atol=0.02)
    probs = storage.sample(8, True)
    np.testing.assert_allclose(probs.probabilities, (probs.indices + 1 + 1e-6) / (10 + 4e-6), rtol=1e-5)


def test_stale_priority_updates_are_ignored():
    storage = Storage(StorageConfig(capacity=10, side_fraction=0.5, priority_exponent=1.0))
    storage.insert(make_chunk(seq=0, steps=10))
    old = storage.sample(10, True)
    storage.insert(make_chunk(seq=1, steps=5))  # overwrites slots 0..4
    applied = storage.update_priorities(old.indices, old.generations, np.full(10, 100.0))
    still_there = old.indices >= 5
    assert applied == len(np.unique(old.indices[still_there]))
    assert np.all(storage.tree.get(np.arange(5)) == 1.0)  # new data keeps its initial priority


def test_state_round_trip():
    storage = Storage(StorageConfig(capacity=40, side_fraction=0.5))
    for seq in range(7):
        storage.insert(make_chunk(seq=seq, steps=9, ends=(3,)))
    copy = Storage(StorageConfig(capacity=40, side_fraction=0.5))
    copy.restore(storage.state())
    for name, array in storage.named_arrays().items():
        np.testing.assert_array_equal(copy.named_arrays()[name], array)
    np.testing.assert_array_equal(copy.tree.tree, storage.tree.tree)
    with pytest.raises(ValueError, match="configured for"):
        Storage(StorageConfig(capacity=41)).restore(storage.state())


def test_sumtree_matches_a_cumulative_sum():
    rng = np.random.default_rng(1)
    tree = SumTree(37)
    values = rng.random(37)
    tree.set_range(0, 20, values[:20])
    tree.set(np.arange(20, 37), values[20:])
    assert tree.total == pytest.approx(values.sum())
    targets = rng.random(1000) * values.sum()
    np.testing.assert_array_equal(tree.find(targets), np.searchsorted(np.cumsum(values), targets, side="right"))


def test_the_server_builds_an_ack_only_when_chunks_came():
    server = ReplayServer(ServerConfig(shard=1), Storage(StorageConfig(capacity=100)), RateLimiter())
    assert server.ack() is None
    for seq in (0, 2):
        server.sequences.accept(7, 5, seq)
    ack = decode(encode(server.ack()))
    assert ack.shard == 1 and ack.of(7, 5)[0] == 2 and list(ack.of(7, 5)[1]) == [1]
    assert server.ack() is None
    server.sequences.accept(7, 5, 2)  # a duplicate: its sender has not heard the ack
    assert server.ack().of(7, 5)[0] == 2


def test_rate_limiter_reverb_semantics():
    limiter = RateLimiter(min_size=100, samples_per_insert=2.0, error_buffer=64)
    assert not limiter.can_sample(size=99, batch_size=32)[0]
    limiter.inserted = 100
    assert limiter.can_sample(100, 64)[0] and not limiter.can_sample(100, 65)[0]
    limiter.sampled = 64
    limiter.inserted = 116  # 16 more inserts allow 32 more samples
    assert limiter.can_sample(116, 32)[0] and not limiter.can_sample(116, 33)[0]
    assert RateLimiter(min_size=10).can_sample(10, 10**6)[0]  # ratio off: only the minimum size


def server_with_200_stored(limiter: RateLimiter, queue: QueueTable | None = None) -> ReplayServer:
    server = ReplayServer(ServerConfig(shard=0), Storage(StorageConfig(capacity=1000, obs_dim=3, act_dim=2)), limiter,
                          queue=queue)
    for seq in range(2):
        server._store(make_chunk(actor_id=1, seq=seq, steps=100, obs_dim=3, act_dim=2), None)
    return server


def test_a_limiter_that_holds_inserts_asks_the_actors_to_wait_while_they_are_ahead_and_releases_them():
    limiter = RateLimiter(min_size=100, samples_per_insert=2.0, error_buffer=64, hold_inserts=True)
    server = server_with_200_stored(limiter)  # the learner may sample 264, so the actors are 264 ahead (> 2 x 64)
    assert server.ack().hold is True
    limiter.sampled = 200  # the learner caught up to 64 ahead
    assert server.ack().hold is False
    assert server.ack() is None  # nothing new: no chunk came and the hold is lifted already
    quiet = server_with_200_stored(RateLimiter(min_size=100, samples_per_insert=2.0, error_buffer=64))
    assert quiet.ack().hold is None  # inserts are not held unless asked: the field is left out
    both = server_with_200_stored(RateLimiter(min_size=100, samples_per_insert=2.0, error_buffer=64, hold_inserts=True),
                                  QueueTable(QueueConfig(capacity=1000), obs_dim=3, act_dim=2))
    assert both.ack().hold is True  # a queue with room does not lift the limiter's hold


@pytest.mark.parametrize("prefill", [3, 12])  # a ring partly filled, and one that has wrapped
def test_block_copy_is_the_state_at_its_start_while_inserts_go_on(prefill):
    storage = Storage(StorageConfig(capacity=100, side_fraction=0.5))
    for seq in range(prefill):
        storage.insert(make_chunk(seq=seq, steps=9, ends=(4,)))
    expected = storage.state()
    copy = StateCopy(storage)
    copy.touch()
    seq = prefill
    while not copy.step(block=10):
        storage.insert(make_chunk(seq=seq, steps=3))  # slower than the copy: never overtakes
        seq += 1
    assert storage.written > expected["counters"][0]
    for name, values in expected.items():
        np.testing.assert_array_equal(copy.arrays[name], values, err_msg=name)


def test_block_copy_notices_when_inserts_overtake_it():
    storage = Storage(StorageConfig(capacity=100, side_fraction=0.5))
    for seq in range(12):
        storage.insert(make_chunk(seq=seq, steps=9))
    copy = StateCopy(storage)
    copy.step(block=10)
    storage.insert(make_chunk(seq=12, steps=30))
    with pytest.raises(Overtaken):
        copy.step(block=10)


def test_sumtree_sums_stay_right_across_many_lazy_range_updates():
    rng = np.random.default_rng(2)
    tree = SumTree(100)
    values = np.zeros(100)
    for _ in range(300):  # more ranges than the tree keeps apart, some overlapping the others
        start, count = int(rng.integers(0, 90)), int(rng.integers(1, 10))
        values[start:start + count] = rng.random()
        tree.set_range(start, count, values[start:start + count])
        if rng.random() < 0.1:
            slot = int(rng.integers(0, 100))
            values[slot] = rng.random()
            tree.set(np.array([slot]), values[slot:slot + 1])
    assert tree.total == pytest.approx(values.sum())
    level = tree.tree[tree.leaves // 2:tree.leaves]
    np.testing.assert_allclose(level, tree.tree[tree.leaves::2] + tree.tree[tree.leaves + 1::2])
