"""Observation fields in the replay storage and the frames form of its batches, checked against
stacks worked out by hand: step k of a stream sees the frame whose every byte is k (+ 100 per
environment), an episode that ends at step k has the final frame 200 + k (``frame_chunk``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from l2r.protocol import ProtocolError
from l2r.protocol.observations import ObservationSpec
from l2r.replay.storage import ChunkRejected, Storage, StorageConfig, storage_bytes
from tests.protocol.factories import stream_chunk

PIXELS = ObservationSpec.parse("pixels: uint8[3, 2, 2]")


def frames_of(values) -> np.ndarray:
    return np.broadcast_to(np.asarray(values, np.uint8)[:, None, None, None], (len(values), 3, 2, 2)).copy()


def frame_chunk(first: int, size: int, seq: int, env_id: int = 0, ends=()):
    """``stream_chunk``'s steps with frames for observations (numbers as in the module docstring)."""
    chunk = stream_chunk(first, size, seq, env_id, ends, obs_dim=1, act_dim=1)

    def number(rows: np.ndarray) -> np.ndarray:
        v = rows[:, 0].astype(int)
        return np.where(v >= 0, v - 1000 * env_id + 100 * env_id, 200 + (-v - 1) % 1000)

    return dataclasses.replace(chunk, obs={"pixels": frames_of(number(chunk.obs))},
                               final_obs={"pixels": frames_of(number(chunk.final_obs))})


def storage_of(*chunks, capacity: int = 100) -> Storage:
    storage = Storage(StorageConfig(capacity=capacity, act_dim=1, side_fraction=0.5, observation=PIXELS))
    for chunk in chunks:
        storage.insert(chunk)
    return storage


def stacks(storage: Storage, k: int = 3, n_step: int = 1) -> dict[int, tuple[tuple, tuple]]:
    """Frame number of each stored observation -> (its obs stack, its next obs stack), as frame
    numbers oldest first, from a batch large enough to hold every stored slot."""
    batch = storage.sample(4000, False, n_step=n_step, gamma=0.5, frame_stack=k)
    assert len(np.unique(batch.indices)) == storage.live and batch.obs is None and batch.next_obs is None
    numbers = batch.frames["pixels"][:, 0, 0, 0].astype(int)
    return {int(numbers[o[-1]]): (tuple(numbers[o]), tuple(numbers[x]))
            for o, x in zip(batch.obs_frames, batch.next_obs_frames)}


def test_stacks_inside_a_chunk_repeat_the_first_frame_of_an_episode():
    got = stacks(storage_of(frame_chunk(0, 10, seq=0, ends=(4,))))
    assert got[2] == ((0, 1, 2), (1, 2, 3))
    assert got[0] == ((0, 0, 0), (0, 0, 1))  # the episode's first frame, repeated as after a reset
    assert got[1] == ((0, 0, 1), (0, 1, 2))
    assert got[4] == ((2, 3, 4), (3, 4, 204))  # the episode ends: its final frame, from the side rows
    assert got[5] == ((5, 5, 5), (5, 5, 6))  # the next episode starts over
    assert got[9] == ((7, 8, 9), (8, 9, 10))  # the chunk's last step: its next frame from the side rows


def test_stacks_cross_into_the_previous_chunk_of_their_stream_past_another_stream():
    storage = storage_of(frame_chunk(0, 4, seq=0), frame_chunk(0, 4, seq=1, env_id=1), frame_chunk(4, 4, seq=2))
    got = stacks(storage)
    assert got[3] == ((1, 2, 3), (2, 3, 4))
    assert got[4] == ((2, 3, 4), (3, 4, 5))
    assert got[5] == ((3, 4, 5), (4, 5, 6))
    assert got[101] == ((100, 100, 101), (100, 101, 102))  # the other stream's stacks stay its own
    assert storage.chunk_links == 1


def test_a_stack_stops_where_a_chunk_of_its_stream_was_lost():
    storage = storage_of(frame_chunk(0, 4, seq=0), frame_chunk(8, 4, seq=2))  # steps 4..7 never came
    got = stacks(storage)
    assert got[8] == ((8, 8, 8), (8, 8, 9))
    assert got[3] == ((1, 2, 3), (2, 3, 4))
    assert storage.link_mismatches == 1


def test_a_stack_stops_at_an_overwritten_predecessor():
    storage = storage_of(frame_chunk(0, 6, seq=0), frame_chunk(6, 6, seq=1), capacity=10)  # slots of 0, 1 reused
    got = stacks(storage)
    assert got[3] == ((2, 2, 3), (2, 3, 4))  # step 1 is gone: 2 is the oldest frame found
    assert got[7] == ((5, 6, 7), (6, 7, 8))


def test_n_step_next_stacks_end_after_the_window():
    got = stacks(storage_of(frame_chunk(0, 10, seq=0, ends=(4,))), n_step=3)
    assert got[1] == ((0, 0, 1), (2, 3, 4))  # window 1..3: the stack ending at step 3's next frame
    assert got[3] == ((1, 2, 3), (3, 4, 204))  # the window stops at the episode's end
    assert got[8] == ((6, 7, 8), (8, 9, 10))  # and at the chunk's end


def test_each_frame_is_sent_once_however_many_stacks_use_it():
    storage = storage_of(frame_chunk(0, 10, seq=0))
    batch = storage.sample(4000, False, frame_stack=3)
    # 10 stored frames and the chunk's last next frame, for 4000 transitions of 6 stack entries each
    assert sorted(batch.frames["pixels"][:, 0, 0, 0].tolist()) == list(range(11))
    assert batch.obs_frames.shape == batch.next_obs_frames.shape == (4000, 3)
    assert batch.obs_frames.dtype == np.int64


def test_frames_have_no_version_1_form():
    storage = Storage(StorageConfig(capacity=10, act_dim=1, observation=ObservationSpec.parse(
        "pixels: uint8[3, 2, 2], state: float32[1]")))  # a state beside the frames is not the vector alone
    with pytest.raises(ValueError, match="frames form alone"):
        storage.sample(4, False)


def test_fields_are_stored_in_their_own_dtype_and_counted_per_field():
    spec = ObservationSpec.parse("{pixels: uint8[3, 84, 84], state: float32[24]}")
    config = StorageConfig(capacity=64, act_dim=6, side_fraction=0.125, observation=spec)
    storage = Storage(config)
    assert storage.all_obs["pixels"].dtype == np.uint8 and storage.all_obs["pixels"].shape == (72, 3, 84, 84)
    assert storage.all_obs["state"].dtype == np.float32 and storage.all_obs["state"].shape == (72, 24)
    assert storage_bytes(config) == storage.nbytes
    # per slot: one observation, 6 actions, reward, 2 flags, version, generation, next row, 2 links;
    # per side row: one observation, its owner and the owner's generation
    frame = 3 * 84 * 84 + 4 * 24
    assert storage.nbytes == 64 * (frame + 4 * 6 + 4 + 2 + 24 + 8) + 8 * (frame + 16) + storage.tree.tree.nbytes


@pytest.mark.parametrize("change, reason", [
    (lambda obs: {"pixels": obs["pixels"].astype(np.float32)}, "wrong_dtype"),
    (lambda obs: {"pixels": obs["pixels"][:, :, :1]}, "wrong_shape"),
    (lambda obs: {"pixels": obs["pixels"], "depth": obs["pixels"]}, "unknown_field"),
    (lambda obs: {"frame": obs["pixels"]}, "unknown_field"),
    (lambda obs: obs["pixels"][:, 0, 0, :].astype(np.float32), "unknown_field"),  # a vector chunk: "state"
])
def test_a_chunk_of_other_fields_is_rejected_with_its_reason(change, reason):
    storage = storage_of()
    good = frame_chunk(0, 4, seq=0, ends=(1,))
    for field in ("obs", "final_obs"):
        chunk = dataclasses.replace(good, **{field: change(getattr(good, field))})
        with pytest.raises(ChunkRejected) as rejected:
            storage.insert(chunk)
        assert rejected.value.reason == reason, rejected.value
    assert storage.live == 0 and storage.written == 0


def test_a_chunk_with_more_episode_ends_than_side_rows_is_too_large():
    storage = Storage(StorageConfig(capacity=10, act_dim=1, side_fraction=0.3, observation=PIXELS))  # 3 side rows
    with pytest.raises(ChunkRejected) as rejected:
        storage.insert(frame_chunk(0, 6, seq=0, ends=(0, 1, 2)))  # 3 final frames and the last next frame
    assert rejected.value.reason == "too_large" and storage.side_written == 0
    storage.insert(frame_chunk(0, 6, seq=0, ends=(0, 1)))
    assert storage.side_written == 3


def test_a_missing_field_is_rejected():
    storage = Storage(StorageConfig(capacity=10, act_dim=1, observation=ObservationSpec.parse(
        "pixels: uint8[3, 2, 2], state: float32[1]")))
    with pytest.raises(ChunkRejected) as rejected:
        storage.insert(frame_chunk(0, 4, seq=0))
    assert rejected.value.reason == "missing_field"


def test_image_fields_survive_a_state_round_trip():
    storage = storage_of(frame_chunk(0, 10, seq=0, ends=(4,)), frame_chunk(10, 10, seq=1), capacity=16)
    copy = storage_of(capacity=16)
    copy.restore(storage.state())
    for name, array in storage.named_arrays().items():
        np.testing.assert_array_equal(copy.named_arrays()[name], array)
    assert stacks(copy) == stacks(storage)
    with pytest.raises(ValueError, match="configured for"):  # a shard of another observation refuses it
        Storage(StorageConfig(capacity=16, act_dim=1, side_fraction=0.5, observation=ObservationSpec.parse(
            "pixels: uint8[3, 2, 3]"))).restore(storage.state())


def test_a_vector_snapshot_from_before_fields_restores_as_the_field_state():
    vector = Storage(StorageConfig(capacity=40, obs_dim=1, act_dim=1))
    vector.insert(stream_chunk(0, 10, seq=0, ends=(4,), obs_dim=1))
    state = vector.state()
    # what such a snapshot held: the vector as "obs" and "side_obs", no "observation"
    old = {name: values for name, values in state.items() if not name.startswith(("obs.", "side_obs.", "observation"))}
    old |= {"obs": state["obs.state"], "side_obs": state["side_obs.state"]}
    restored = Storage(StorageConfig(capacity=40, obs_dim=1, act_dim=1))
    restored.restore(old)
    np.testing.assert_array_equal(restored.all_obs["state"], vector.all_obs["state"])
    batch = restored.sample(200, False)
    np.testing.assert_array_equal(batch.next_obs[:, 0], np.where(batch.obs[:, 0] == 4, -5, batch.obs[:, 0] + 1))


def test_a_vector_shard_sends_stacks_of_its_vector_when_asked():
    storage = Storage(StorageConfig(capacity=40, obs_dim=2, act_dim=1))
    storage.insert(stream_chunk(0, 5, seq=0))
    batch = storage.sample(200, False, frame_stack=2)
    state = batch.frames["state"]
    assert batch.obs is None and state.dtype == np.float32 and state.shape[1:] == (2,)
    by_obs = {float(state[o[-1], 0]): (state[o, 0].tolist(), state[x, 0].tolist())
              for o, x in zip(batch.obs_frames, batch.next_obs_frames)}
    assert by_obs[0] == ([0, 0], [0, 1]) and by_obs[3] == ([2, 3], [3, 4]) and by_obs[4] == ([3, 4], [4, 5])


@pytest.mark.parametrize("text, reason", [
    ("pixels uint8[3]", "bad_spec"), ("pixels: int8[3]", "wrong_dtype"), ("pixels: uint8[3, x]", "wrong_shape"),
    ("pixels: uint8[3] state: float32[2]", "bad_spec"), ("a: uint8[3], a: uint8[2]", "bad_field"),
    ("pixels: uint8[0]", "wrong_shape"), ("", "bad_spec"),
])
def test_the_text_form_is_parsed_back_and_bad_text_refused_with_a_reason(text, reason):
    spec = ObservationSpec.parse("{pixels: uint8[3, 84, 84], state: float32[24]}")
    assert ObservationSpec.parse(str(spec)) == spec and ObservationSpec.parse("state: float32[41]") == \
        ObservationSpec.vector(41)
    with pytest.raises(ProtocolError) as refused:
        ObservationSpec.parse(text)
    assert refused.value.reason == reason
