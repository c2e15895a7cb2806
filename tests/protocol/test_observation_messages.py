"""Observation fields in messages: a vector chunk keeps version 1's bytes, image chunks and
batches of frames travel as version 2 in their own dtype, every bad field is rejected with its
reason, and no payload makes the decoder raise anything but ProtocolError."""

from __future__ import annotations

import hashlib

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from l2r.protocol import ExperienceChunk, ProtocolError, SampleBatch, as_fields, decode, encode
from tests.protocol.factories import every_message, make_chunk, make_frames_batch, make_image_chunk

T = 6  # steps of make_image_chunk, whose step 2 ends an episode inside the chunk


def wire(message) -> dict:
    return msgpack.unpackb(encode(message), raw=False)


def pack(raw: dict) -> bytes:
    return msgpack.packb(raw, use_bin_type=True)


def reason_of(payload: bytes) -> str:
    with pytest.raises(ProtocolError) as error:
        decode(payload)
    return error.value.reason


def array(a: np.ndarray) -> dict:
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}


# -- the vector observation: version 1, byte for byte -------------------------------------

# sha256 of encodings made by the version-1 encoder (before observation fields existed)
VERSION_1_CHUNK = "fdfe57cbe5b5716383f497e0e7585ad5e264a3be3ac48488c7412b5771e361c0"
VERSION_1_BATCH = "f0cc20323d636e19db9348ccb0f0b8e9a97e3efd72d8f1cfd87670615be67575"


def test_a_vector_chunk_and_batch_encode_to_the_bytes_of_version_1():
    chunk = make_chunk(3, 7, steps=12, ends=(4,), truncate=(11,))
    assert hashlib.sha256(encode(chunk)).hexdigest() == VERSION_1_CHUNK
    batch = next(m for m in every_message() if isinstance(m, SampleBatch))
    assert hashlib.sha256(encode(batch)).hexdigest() == VERSION_1_BATCH
    # the one-field map is the same observation, and goes as the same bytes
    chunk.obs, chunk.final_obs = {"state": chunk.obs}, {"state": chunk.final_obs}
    assert hashlib.sha256(encode(chunk)).hexdigest() == VERSION_1_CHUNK


def test_a_version_1_chunk_decodes_as_before():
    sent = make_chunk(steps=12, ends=(4,))
    chunk = decode(encode(sent))
    assert isinstance(chunk.obs, np.ndarray) and chunk.obs.dtype == np.float32 and chunk.obs.shape == (13, 41)
    assert not chunk.obs.flags.writeable and not chunk.obs.flags.owndata
    np.testing.assert_array_equal(chunk.obs, sent.obs)
    np.testing.assert_array_equal(chunk.final_obs, sent.final_obs)
    assert as_fields(chunk.obs)["state"] is chunk.obs  # the same rows, seen as the field "state"


def test_a_version_2_peer_may_send_the_vector_as_fields():
    raw = wire(make_chunk(steps=5, ends=(1,)))
    raw["v"], raw["obs"], raw["final_obs"] = 2, {"state": raw["obs"]}, {"state": raw["final_obs"]}
    chunk = decode(pack(raw))
    assert list(chunk.obs) == ["state"]
    np.testing.assert_array_equal(chunk.obs["state"], make_chunk(steps=5, ends=(1,)).obs)
    assert encode(chunk) == encode(make_chunk(steps=5, ends=(1,)))  # and it goes on as version 1


# -- images: version 2, in their own dtype --------------------------------------------------

def test_an_image_chunk_travels_as_version_2_in_its_own_dtype():
    sent = make_image_chunk()
    payload = encode(sent)
    raw = msgpack.unpackb(payload)
    assert raw["v"] == 2  # what a version-1 replay rejects ("version"), instead of misreading it
    assert raw["obs"]["pixels"]["dtype"] == "|u1" and raw["obs"]["pixels"]["shape"] == [T + 1, 3, 84, 84]
    assert raw["obs"]["state"]["dtype"] == "<f4" and raw["final_obs"]["pixels"]["shape"] == [1, 3, 84, 84]
    frames = (T + 1 + 1) * 3 * 84 * 84
    assert frames < len(payload) < frames + 2000  # one byte a pixel, no float copies
    chunk = decode(payload, ExperienceChunk)
    assert list(chunk.obs) == ["pixels", "state"]
    for name in chunk.obs:
        for got, want in ((chunk.obs[name], sent.obs[name]), (chunk.final_obs[name], sent.final_obs[name])):
            assert got.dtype == want.dtype and np.array_equal(got, want)
            assert not got.flags.writeable and not got.flags.owndata  # views of the payload
    nxt = chunk.next_obs()
    assert nxt["pixels"][:, 0, 0, 0].tolist() == [1, 2, 202, 4, 5, 6]  # step 2 ended an episode
    assert nxt["state"][:, 0].tolist() == [1, 2, -3, 4, 5, 6]


def test_observations_in_the_form_of_the_other_version_are_rejected():
    raw = wire(make_image_chunk())
    raw["v"] = 1  # fields where version 1 has an array
    assert reason_of(pack(raw)) == "bad_array"
    raw = wire(make_chunk(steps=3))
    raw["v"] = 2  # an array where version 2 has fields
    assert reason_of(pack(raw)) == "bad_array"


def image_raw(**change) -> dict:
    """The wire form of an image chunk with ``part`` or ``part__field`` replaced, or left out (None)."""
    raw = wire(make_image_chunk())
    for where, value in change.items():
        part, _, name = where.partition("__")
        within, key = (raw[part], name) if name else (raw, part)
        if value is None:
            del within[key]
        else:
            within[key] = value
    return raw


PIXELS = np.zeros((T + 1, 3, 84, 84), np.uint8)


@pytest.mark.parametrize("change, reason", [
    ({"obs__pixels": array(PIXELS.astype(np.float64))}, "wrong_dtype"),
    ({"obs__pixels": array(PIXELS.astype(np.int32))}, "wrong_dtype"),
    ({"obs__pixels": array(PIXELS.astype(">f4"))}, "wrong_dtype"),
    ({"obs__state": array(np.zeros((T + 1, 5), np.float16))}, "wrong_dtype"),
    ({"obs__pixels": {**array(PIXELS), "data": b"\0" * 10}}, "bad_array"),
    ({"obs__pixels": array(PIXELS[:, None])}, "bad_array"),  # 5 dimensions
    ({"obs__pixels": [1, 2, 3]}, "bad_array"),
    ({"obs__pixels": array(np.zeros((T + 1, 0, 84, 84), np.uint8))}, "wrong_shape"),
    ({"obs__pixels": array(np.zeros(T + 1, np.uint8))}, "wrong_shape"),  # no shape past the rows
    ({"obs__pixels": array(np.zeros((T + 1, 3, 1025, 1366), np.uint8))}, "oversized"),
    ({"obs__bad name": array(PIXELS)}, "bad_field"),
    ({"obs": {f"camera{i}": array(PIXELS) for i in range(9)}}, "bad_field"),
    ({"obs": {}}, "bad_field"),
    ({"obs": [array(PIXELS)]}, "wrong_type"),
    ({"obs__pixels": array(PIXELS[:-1])}, "shape_mismatch"),  # T rows, not T+1
    ({"obs__state": array(np.zeros((T + 2, 5), np.float32))}, "shape_mismatch"),
    ({"final_obs__pixels": array(PIXELS[:2])}, "shape_mismatch"),  # one episode ends inside: one row
    ({"final_obs__state": None}, "shape_mismatch"),  # final rows of other fields than obs
    ({"final_obs__pixels": array(np.zeros((1, 3, 84, 85), np.uint8))}, "shape_mismatch"),
    ({"final_obs": None}, "missing_field"),
    ({"obs__state": array(np.full((T + 1, 5), np.nan, np.float32))}, "not_finite"),
    ({"final_obs__state": array(np.full((1, 5), np.inf, np.float32))}, "not_finite"),
])
def test_every_bad_field_of_an_image_chunk_is_rejected_with_its_reason(change, reason):
    decode(pack(image_raw()))  # unchanged, it is fine
    assert reason_of(pack(image_raw(**change))) == reason


def test_a_sender_cannot_encode_bad_fields():
    chunk = make_image_chunk()
    chunk.obs = {**chunk.obs, "pixels": chunk.obs["pixels"] / 255.0}  # scaled too early: float64
    with pytest.raises(ProtocolError, match="experience.obs.pixels: dtype float64"):
        encode(chunk)
    chunk = make_image_chunk()
    chunk.final_obs = {"pixels": chunk.final_obs["pixels"]}
    with pytest.raises(ProtocolError, match="final_obs rows are \\{pixels: uint8\\[3, 84, 84\\]\\}"):
        encode(chunk)


# -- batches of frames ----------------------------------------------------------------------

def test_a_batch_of_frames_carries_each_frame_once_and_the_learner_stacks_them():
    sent = make_frames_batch(b=4, k=3)
    payload = encode(sent)
    raw = msgpack.unpackb(payload)
    assert raw["v"] == 2 and "obs" not in raw and "next_obs" not in raw
    assert raw["frames"]["pixels"]["shape"] == [7, 3, 84, 84] and raw["obs_frames"]["shape"] == [4, 3]
    assert 7 * 3 * 84 * 84 < len(payload) < 7 * 3 * 84 * 84 + 2000  # 7 frames, not 4 x (3 + 3)
    batch = decode(payload, SampleBatch)
    assert batch.frames["pixels"].dtype == np.uint8 and not batch.frames["pixels"].flags.writeable
    obs = batch.frames["pixels"][batch.obs_frames].reshape(4, 9, 84, 84)  # k frames of 3 channels: 9
    nxt = batch.frames["pixels"][batch.next_obs_frames].reshape(4, 9, 84, 84)
    assert obs[:, ::3, 0, 0].tolist() == [[0, 1, 2], [1, 2, 3], [2, 3, 4], [3, 4, 5]]
    assert nxt[:, ::3, 0, 0].tolist() == [[1, 2, 3], [2, 3, 4], [3, 4, 5], [4, 5, 6]]


@pytest.mark.parametrize("change, reason", [
    ({"obs_frames": array(np.array([[0, 1, 2], [1, 2, 3], [2, 3, 4], [3, 4, 7]]))}, "out_of_range"),
    ({"next_obs_frames": array(np.array([[1, 2, 3], [2, 3, 4], [3, 4, 5], [-1, 5, 6]]))}, "out_of_range"),
    ({"obs_frames": array(np.zeros((4, 2), np.int64))}, "shape_mismatch"),  # stacks of 2 and of 3
    ({"obs_frames": array(np.zeros((4, 0), np.int64)), "next_obs_frames": array(np.zeros((4, 0), np.int64))},
     "shape_mismatch"),
    ({"obs_frames": array(np.zeros((3, 3), np.int64))}, "shape_mismatch"),
    ({"obs_frames": array(np.zeros(4, np.int64))}, "shape_mismatch"),
    ({"obs_frames": array(np.zeros((4, 3), np.int32))}, "wrong_dtype"),
    ({"frames": {"pixels": array(np.zeros((7, 3, 84, 84), np.float64))}}, "wrong_dtype"),
    ({"frames": {"pixels": array(np.zeros((7, 3, 84, 84), np.uint8)),
                 "state": array(np.zeros((6, 5), np.float32))}}, "shape_mismatch"),
    ({"frames": {}}, "bad_field"),
    ({"obs_frames": None}, "missing_field"),
    ({"frames": None}, "missing_field"),
    ({"frames": None, "obs_frames": None, "next_obs_frames": None}, "missing_field"),  # no observations at all
    ({"obs": array(np.zeros((4, 5), np.float32)), "next_obs": array(np.zeros((4, 5), np.float32))}, "invalid"),
    ({"v": 1}, "version"),  # frames need version 2
])
def test_every_bad_part_of_a_batch_of_frames_is_rejected_with_its_reason(change, reason):
    raw = wire(make_frames_batch())
    for name, value in change.items():
        if value is None:
            del raw[name]
        else:
            raw[name] = value
    assert reason_of(pack(raw)) == reason


# -- hostile payloads -----------------------------------------------------------------------

SMALL = [encode(make_image_chunk(side=4)), encode(make_frames_batch(side=4))]


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(which=st.integers(0, len(SMALL) - 1), flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)),
                                                             max_size=8), cut=st.integers(0, 10**6))
def test_fuzz_mutated_observation_messages(which, flips, cut):
    payload = bytearray(SMALL[which])
    for pos, value in flips:
        payload[pos % len(payload)] = value
    try:
        message = decode(bytes(payload[: max(1, cut % (len(payload) + 1))]))
    except ProtocolError:
        return
    encode(message)  # anything accepted is a valid message again


names = st.sampled_from(["pixels", "state", "", "bad name", "x" * 40, "dtype", "0"])
dtypes = st.sampled_from(["|u1", "<f4", "<f8", ">f4", "|b1", "<i8", "nonsense", 3])
array_maps = st.one_of(
    st.fixed_dictionaries({"dtype": dtypes, "shape": st.lists(st.integers(-2, 8), max_size=6),
                           "data": st.binary(max_size=300)}),
    st.builds(lambda shape, fill: array(np.full(shape, *fill)), st.lists(st.integers(0, 5), min_size=1, max_size=5),
              st.sampled_from([(0, np.uint8), (255, np.uint8), (0.5, np.float32), (np.nan, np.float32),
                               (np.inf, np.float32), (0, np.float64)])),
    st.integers(-2**63, 2**64 - 1), st.none(), st.binary(max_size=8),
)
field_maps = st.one_of(st.dictionaries(names, array_maps, max_size=10), st.lists(array_maps, max_size=2), st.text())


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(obs=field_maps, final_obs=field_maps, frames=field_maps, rows=array_maps, version=st.sampled_from([1, 2]))
def test_fuzz_hostile_observation_fields(obs, final_obs, frames, rows, version):
    chunk, batch = wire(make_image_chunk(side=4)), wire(make_frames_batch(side=4))
    chunk.update(v=version, obs=obs, final_obs=final_obs)
    batch.update(v=version, frames=frames, obs_frames=rows)
    for raw in (chunk, batch):
        try:
            message = decode(pack(raw))
        except ProtocolError:
            continue
        encode(message)
