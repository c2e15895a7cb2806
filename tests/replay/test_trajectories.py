"""Trajectory links in the replay storage and the n-step returns built on them, checked against
values worked out by hand (gamma 0.5, n 3; step k of a stream earns reward k + 1)."""

from __future__ import annotations

import numpy as np
import pytest

from l2r.replay import storage as storage_module
from l2r.replay.storage import LINKS, StateCopy, Storage, StorageConfig
from tests.protocol.factories import stream_chunk as steps

OBS, ACT = 2, 1


def storage_of(*chunks: ExperienceChunk, capacity: int = 100, side_fraction: float = 0.5) -> Storage:
    storage = Storage(StorageConfig(capacity=capacity, obs_dim=OBS, act_dim=ACT, side_fraction=side_fraction))
    for chunk in chunks:
        storage.insert(chunk)
    return storage


def windows(storage: Storage, n_step: int = 3, gamma: float = 0.5) -> dict[float, tuple]:
    """Observation -> (reward, discount, next observation, terminated, truncated) of the n-step
    transition starting there, from a batch large enough to hold every stored slot."""
    batch = storage.sample(4000, False, n_step=n_step, gamma=gamma)
    assert len(np.unique(batch.indices)) == storage.live
    return {float(o): (float(r), float(d), float(x), bool(te), bool(tr)) for o, r, d, x, te, tr in zip(
        batch.obs[:, 0], batch.rewards, batch.discounts, batch.next_obs[:, 0], batch.terminated, batch.truncated)}


def test_a_window_inside_a_chunk_and_one_cut_short_by_its_end():
    got = windows(storage_of(steps(0, 10, seq=0)))
    assert got[2] == (3 + 0.5 * 4 + 0.25 * 5, 0.125, 5, False, False)
    assert got[8] == (9 + 0.5 * 10, 0.25, 10, False, False)  # the stream's next chunk has not come yet
    assert got[9] == (10, 0.5, 10, False, False)


def test_a_window_crosses_into_the_next_chunk_of_its_stream_past_another_stream():
    storage = storage_of(steps(0, 4, seq=0), steps(0, 4, seq=1, env_id=1), steps(4, 4, seq=2))
    got = windows(storage)
    assert got[2] == (3 + 0.5 * 4 + 0.25 * 5, 0.125, 5, False, False)
    assert got[3] == (4 + 0.5 * 5 + 0.25 * 6, 0.125, 6, False, False)
    assert got[1002] == (3 + 0.5 * 4, 0.25, 1004, False, False)  # the other stream's window stays its own
    assert (storage.chunk_links, storage.link_mismatches) == (1, 0)


@pytest.mark.parametrize("kind", ["terminated", "truncated"])
def test_a_window_stops_where_its_episode_ends(kind):
    end = {"ends": (4,)} if kind == "terminated" else {"truncate": (4,)}
    got = windows(storage_of(steps(0, 8, seq=0, **end)))
    terminated = kind == "terminated"
    assert got[3] == (4 + 0.5 * 5, 0.0 if terminated else 0.25, -5, terminated, not terminated)
    assert got[4] == (5, 0.0 if terminated else 0.5, -5, terminated, not terminated)
    assert got[5] == (6 + 0.5 * 7 + 0.25 * 8, 0.125, 8, False, False)  # the next episode


def test_an_episode_that_ends_with_its_chunk_is_not_joined_to_the_next():
    storage = storage_of(steps(0, 4, seq=0, ends=(3,)), steps(4, 4, seq=1))
    assert windows(storage)[2] == (3 + 0.5 * 4, 0.0, -4, True, False)
    assert (storage.chunk_links, storage.link_mismatches) == (0, 0)


def test_a_window_stops_where_a_chunk_of_its_stream_was_lost():
    storage = storage_of(steps(0, 4, seq=0), steps(8, 4, seq=2))  # steps 4..7 never came
    got = windows(storage)
    assert got[2] == (3 + 0.5 * 4, 0.25, 4, False, False)
    assert got[8] == (9 + 0.5 * 10 + 0.25 * 11, 0.125, 11, False, False)
    assert (storage.chunk_links, storage.link_mismatches) == (0, 1)


def test_a_window_stops_at_a_slot_evicted_for_its_next_observation():
    # 3 side rows: three more chunks of another stream overwrite the side row of step 4, the last of its chunk
    storage = storage_of(steps(0, 5, seq=0), *[steps(10 * i, 5, seq=i, env_id=1) for i in (1, 2, 3)],
                         side_fraction=0.03)
    got = windows(storage)
    assert 4 not in got and storage.live == 19
    assert got[2] == (3 + 0.5 * 4, 0.25, 4, False, False)  # step 3's next observation is still in the ring


def test_a_late_chunk_stays_unlinked_and_the_stream_goes_on_from_its_newest():
    storage = storage_of(steps(0, 4, seq=0), steps(8, 4, seq=2), steps(4, 4, seq=1), steps(12, 4, seq=3))
    got = windows(storage)
    assert got[6] == (7 + 0.5 * 8, 0.25, 8, False, False)  # the late chunk's end: not joined to steps 8..
    assert got[10] == (11 + 0.5 * 12 + 0.25 * 13, 0.125, 13, False, False)
    assert (storage.chunk_links, storage.link_mismatches) == (1, 1)


def test_one_step_batches_are_as_before():
    chunks = [steps(0, 6, seq=0, ends=(2,)), steps(6, 6, seq=1)]
    one, plain = storage_of(*chunks), storage_of(*chunks)
    for prioritized in (False, True):
        a, b = one.sample(64, prioritized, n_step=1, gamma=0.5), plain.sample(64, prioritized)
        assert a.discounts is None and b.discounts is None
        for name in ("obs", "rewards", "next_obs", "terminated", "truncated", "indices", "probabilities"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        np.testing.assert_array_equal(a.rewards, a.obs[:, 0] + 1)
        np.testing.assert_array_equal(a.next_obs[:, 0], np.where(a.obs[:, 0] == 2, -3, a.obs[:, 0] + 1))


def test_previous_links_lead_back_across_chunks_until_the_slot_is_overwritten():
    storage = storage_of(steps(0, 4, seq=0), steps(0, 3, seq=1, env_id=1), steps(4, 4, seq=2), capacity=12)
    first = np.array([7])  # step 4: the first of its chunk
    back, holds = storage.follow(first, storage.prev_link[first])
    assert holds.all() and storage.obs['state'][back, 0] == 3
    back, holds = storage.follow(back, storage.prev_link[back])
    assert holds.all() and storage.obs['state'][back, 0] == 2
    storage.insert(steps(0, 5, seq=3, env_id=2))  # wraps round onto steps 0..3
    assert not storage.follow(first, storage.prev_link[first])[1].any()


def test_previous_links_stop_at_an_episode_start_and_at_another_stream():
    storage = storage_of(steps(0, 4, seq=0), steps(0, 6, seq=1, env_id=1, ends=(2,)))
    starts = np.array([4, 7])  # the other stream's first step, and the step after its episode end
    assert list(storage.obs['state'][starts, 0]) == [1000, 1003]
    assert not storage.follow(starts, storage.prev_link[starts])[1].any()
    back, holds = storage.follow(np.array([6]), storage.prev_link[[6]])
    assert holds.all() and storage.obs['state'][back, 0] == 1001


def test_streams_are_forgotten_once_overwritten_or_beyond_the_cap(monkeypatch):
    storage = storage_of(steps(0, 4, seq=0), steps(0, 20, seq=1, env_id=1), capacity=20)
    assert list(storage.stream_ends) == [(0, 1, 1)]  # env 0's last step is overwritten: nothing can join it
    monkeypatch.setattr(storage_module, "MAX_STREAMS", 3)
    for env in range(2, 6):
        storage.insert(steps(0, 1, seq=env, env_id=env))
    assert list(storage.stream_ends) == [(0, 1, env) for env in (3, 4, 5)]


def test_links_and_streams_survive_a_snapshot():
    storage = storage_of(steps(0, 4, seq=0), steps(4, 4, seq=1), steps(0, 4, seq=2, env_id=1))
    restored = storage_of()
    restored.restore(storage.state())
    for chunk in (steps(8, 4, seq=3), steps(4, 4, seq=4, env_id=1)):  # joined through the restored stream ends
        storage.insert(chunk)
        restored.insert(chunk)
    assert windows(restored) == windows(storage)
    assert windows(restored)[7] == (8 + 0.5 * 9 + 0.25 * 10, 0.125, 10, False, False)
    assert restored.chunk_links == 2


def test_a_snapshot_from_before_links_restores_unlinked():
    storage = storage_of(steps(0, 4, seq=0), steps(4, 4, seq=1))
    old = {name: values for name, values in storage.state().items()
           if name not in (*LINKS, "stream_keys", "stream_ends")}
    restored = storage_of()
    restored.restore(old)
    restored.insert(steps(8, 4, seq=2))
    got = windows(restored)
    assert got[3] == (4, 0.5, 4, False, False) and got[7] == (8, 0.5, 8, False, False)
    assert got[9] == (10 + 0.5 * 11 + 0.25 * 12, 0.125, 12, False, False)


def test_a_link_made_while_the_snapshot_was_copied_is_not_restored():
    storage = storage_of(steps(0, 4, seq=0))
    copy = StateCopy(storage)
    storage.insert(steps(4, 4, seq=1))  # joins step 3, whose row the copy has not taken yet
    while not copy.step(block=2):
        pass
    restored = storage_of()
    restored.restore(copy.arrays)
    restored.insert(steps(0, 4, seq=1, env_id=1))  # another stream takes the generations of steps 4..7
    assert windows(restored)[2] == (3 + 0.5 * 4, 0.25, 4, False, False)
