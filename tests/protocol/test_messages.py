"""The wire format: round trips of every message, every rejection, and a fuzzed decoder."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from l2r.protocol import (
    MAX_MESSAGE_BYTES, PROTOCOL_VERSION, ExperienceChunk, Message, ProtocolError, ReplayAck, SampleRequest,
    Weights,
    decode, encode,
)
from l2r.protocol.messages import _KINDS
from tests.protocol.factories import every_message, make_chunk


def assert_same(a: Message, b: Message) -> None:
    assert type(a) is type(b)
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y), f.name
        elif isinstance(x, dict) and x and isinstance(next(iter(x.values())), np.ndarray):
            assert x.keys() == y.keys() and all(np.array_equal(x[k], y[k]) and x[k].dtype == y[k].dtype
                                                and x[k].shape == y[k].shape for k in x)
        else:
            assert x == y, f.name


def test_every_kind_has_an_example():
    assert {m.KIND for m in every_message()} == set(_KINDS)


@pytest.mark.parametrize("message", every_message(), ids=lambda m: m.KIND)
def test_round_trip(message):
    assert_same(decode(encode(message)), message)


def test_arrays_are_views_of_the_payload():
    payload = encode(make_chunk(steps=50))
    chunk = decode(payload)
    assert not chunk.obs.flags.owndata and not chunk.obs.flags.writeable


def test_next_obs_across_episode_ends():
    chunk = make_chunk(steps=6, ends=(1, 5), truncate=(3,))
    nxt = decode(encode(chunk)).next_obs()[:, 0]
    # steps 1 and 3 end inside the chunk: their next observation is the final one, not the reset
    assert nxt.tolist() == [1, -2, 3, -4, 5, 6]


def wire(message: Message) -> dict:
    return msgpack.unpackb(encode(message), raw=False)


def pack(raw: dict) -> bytes:
    return msgpack.packb(raw, use_bin_type=True)


def rejected(payload: bytes, *, match: str) -> None:
    with pytest.raises(ProtocolError, match=match):
        decode(payload)


def test_rejects_other_protocol_version():
    raw = wire(make_chunk())
    raw["v"] = PROTOCOL_VERSION + 1
    rejected(pack(raw), match="protocol version")


def test_rejects_unknown_kind():
    raw = wire(make_chunk())
    raw["kind"] = "telepathy"
    rejected(pack(raw), match="unknown message kind")


def test_rejects_unexpected_kind_where_another_is_expected():
    with pytest.raises(ProtocolError, match="unexpected message kind"):
        decode(encode(SampleRequest()), ExperienceChunk)


@pytest.mark.parametrize("cut", [1, 10, 100, -1])
def test_rejects_truncated(cut):
    payload = encode(make_chunk())
    rejected(payload[:cut], match="malformed|missing|needs")


def test_rejects_oversized():
    rejected(b"\x00" * (MAX_MESSAGE_BYTES + 1), match="oversized")


def test_rejects_inconsistent_shapes():
    raw = wire(make_chunk(steps=10))
    raw["rewards"]["shape"] = [9]
    raw["rewards"]["data"] = raw["rewards"]["data"][:36]
    rejected(pack(raw), match="rewards has 9 rows")


def test_rejects_obs_without_the_extra_row():
    chunk = make_chunk(steps=10)
    chunk.obs = chunk.obs[:-1]
    with pytest.raises(ProtocolError, match="T\\+1"):
        encode(chunk)


def test_rejects_missing_final_obs():
    raw = wire(make_chunk(steps=10, ends=(3,)))
    raw["final_obs"] = {"dtype": "<f4", "shape": [0, 41], "data": b""}
    rejected(pack(raw), match="final_obs has 0 rows")


def test_rejects_data_that_does_not_match_the_shape():
    raw = wire(make_chunk(steps=10))
    raw["obs"]["shape"] = [11, 40]
    rejected(pack(raw), match="needs")


def test_rejects_wrong_dtype():
    raw = wire(make_chunk(steps=10))
    raw["rewards"] = {"dtype": "<f8", "shape": [10], "data": np.zeros(10).tobytes()}
    rejected(pack(raw), match="dtype <f8, expected float32")


def test_rejects_big_endian_and_nonsense_dtypes():
    raw = wire(make_chunk(steps=10))
    raw["rewards"] = {"dtype": ">f4", "shape": [10], "data": np.zeros(10, ">f4").tobytes()}
    rejected(pack(raw), match="little-endian")
    raw["rewards"] = {"dtype": "no such", "shape": [10], "data": b""}
    rejected(pack(raw), match="dtype no such, expected float32")


def test_rejects_nan_actions():
    raw = wire(make_chunk(steps=10))
    actions = np.zeros((10, 18), np.float32)
    actions[3, 2] = np.nan
    raw["actions"]["data"] = actions.tobytes()
    rejected(pack(raw), match="NaN")


def test_rejects_wrong_scalar_types_and_missing_fields():
    raw = wire(make_chunk())
    raw["seq"] = "7"
    rejected(pack(raw), match="seq: expected int")
    raw = wire(make_chunk())
    del raw["epoch"]
    rejected(pack(raw), match="epoch: missing")
    raw = wire(SampleRequest())
    raw["prioritized"] = 1
    rejected(pack(raw), match="expected bool")


def test_ack_parts_belong_to_their_actor_and_must_add_up():
    ack = ReplayAck(0, np.array([3, 5, 8]), np.array([1, 1, 2]), np.array([40, 9, 2]), np.array([2, 0, 1]),
                    np.array([7, 31, 0]))
    assert decode(encode(ack)).of(3, 1)[0] == 40 and list(ack.of(3, 1)[1]) == [7, 31]
    assert ack.of(5, 1)[0] == 9 and len(ack.of(5, 1)[1]) == 0
    assert list(ack.of(8, 2)[1]) == [0]
    assert ack.of(8, 1) is None and ack.of(4, 1) is None  # another epoch, another actor: nothing said
    raw = wire(ack)
    raw["missing_counts"]["data"] = np.array([2, 0, 2], np.int64).tobytes()
    rejected(pack(raw), match="missing_counts sum to 4")


def test_rejects_weights_of_integer_dtype():
    raw = wire(Weights(1, {"w": np.zeros(3, np.float32)}))
    raw["params"]["w"] = {"dtype": "<i8", "shape": [3], "data": np.zeros(3, np.int64).tobytes()}
    rejected(pack(raw), match="params.w: dtype")


def test_rejects_non_map_messages():
    rejected(msgpack.packb([1, 2, 3]), match="expected a map")


VALID = [encode(m) for m in every_message()]


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.binary(max_size=512))
def test_fuzz_random_bytes(data):
    try:
        decode(data)
    except ProtocolError:
        pass


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(which=st.integers(0, len(VALID) - 1), flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 255)), max_size=8),
       cut=st.integers(0, 10**6))
def test_fuzz_mutated_messages(which, flips, cut):
    payload = bytearray(VALID[which])
    for pos, value in flips:
        payload[pos % len(payload)] = value
    payload = bytes(payload[: max(1, cut % (len(payload) + 1))])
    try:
        message = decode(payload)
    except ProtocolError:
        return
    encode(message)  # anything accepted is a valid message again


leaf = st.one_of(st.none(), st.booleans(), st.integers(-2**63, 2**64 - 1), st.floats(), st.text(max_size=8),
                 st.binary(max_size=16))
values = st.recursive(leaf, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
                      max_leaves=12)


@settings(max_examples=300, deadline=None)
@given(kind=st.sampled_from(sorted(_KINDS)), fields=st.dictionaries(st.text(max_size=12), values, max_size=6))
def test_fuzz_structured_garbage(kind, fields):
    raw = {"v": PROTOCOL_VERSION, "kind": kind, **fields}
    try:
        decode(msgpack.packb(raw, use_bin_type=True))
    except ProtocolError:
        pass
