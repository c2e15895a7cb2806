"""Integer ranges, the protocol version's type, boolean bytes, and rejections counted and logged
by reason: a decoder that lets nothing through that a receiver could overflow on."""

from __future__ import annotations

import logging

import msgpack
import numpy as np
import pytest

from l2r.protocol import PROTOCOL_VERSION, ProtocolError, Rejections, decode, encode
from l2r.protocol.limits import INTEGER_LIMITS
from l2r.protocol.messages import _KINDS
from tests.protocol.factories import every_message, make_chunk

EXAMPLES = {m.KIND: m for m in every_message()}
INTEGER_FIELDS = [(kind, name) for kind, cls in sorted(_KINDS.items())
                  for name, spec in cls.SCHEMA.items() if spec in ("int", "int?")]


def wire(message) -> dict:
    return msgpack.unpackb(encode(message), raw=False)


def reason_of(raw: dict) -> str:
    with pytest.raises(ProtocolError) as e:
        decode(msgpack.packb(raw, use_bin_type=True))
    return e.value.reason


def test_every_integer_field_has_limits_and_every_limit_a_field():
    assert {(kind, name) for kind, fields in INTEGER_LIMITS.items() for name in fields} == set(INTEGER_FIELDS)
    assert set(INTEGER_LIMITS) == set(_KINDS)


@pytest.mark.parametrize("kind, name", INTEGER_FIELDS)
def test_each_integer_field_is_accepted_at_its_limits_and_rejected_beyond(kind, name):
    low, high = INTEGER_LIMITS[kind][name]
    raw = wire(EXAMPLES[kind])
    for value in (low, high):
        raw[name] = value
        assert getattr(decode(msgpack.packb(raw, use_bin_type=True)), name) == value
    # just beyond, and msgpack's extremes (2**63 as a uint64 once killed the replay server)
    for value in (low - 1, high + 1, -2**63, 2**63, 2**64 - 1):
        if not low <= value <= high and -2**63 <= value < 2**64:
            raw[name] = value
            assert reason_of(raw) == "out_of_range", value


def test_a_sender_cannot_encode_what_a_receiver_would_reject():
    with pytest.raises(ProtocolError, match="experience.seq"):
        encode(make_chunk(seq=-1))


def test_integers_in_a_numbers_map_are_int64():
    raw = wire(EXAMPLES["stats"])
    raw["values"]["huge"] = 2**63
    assert reason_of(raw) == "out_of_range"
    values = {"sum": 2**70, "size": 3}  # a sender's sum beyond int64 travels as a float
    assert decode(encode(EXAMPLES["stats"].__class__("replay", "0", 1.0, values))).values == {"sum": 2.0**70, "size": 3}


@pytest.mark.parametrize("version", [1.0, True, "1", None, PROTOCOL_VERSION + 1])
def test_the_protocol_version_is_the_integer_1(version):
    raw = wire(make_chunk())
    raw["v"] = version
    assert reason_of(raw) == "version"


def test_booleans_are_the_bytes_0_and_1():
    raw = wire(make_chunk(steps=4))
    raw["terminated"]["data"] = bytes([0, 1, 2, 0])
    assert reason_of(raw) == "bad_bool"


@pytest.mark.parametrize("change, reason", [
    (lambda raw: raw.update(seq="7"), "wrong_type"),
    (lambda raw: raw.pop("epoch"), "missing_field"),
    (lambda raw: raw.update(kind="telepathy"), "unknown_kind"),
    (lambda raw: raw["rewards"].update(dtype="<f8"), "wrong_dtype"),
    (lambda raw: raw["obs"].update(shape=[2**40, 2**40]), "bad_array"),
    (lambda raw: raw["rewards"].update(shape=[3], data=bytes(12)), "shape_mismatch"),
    (lambda raw: raw["actions"].update(data=np.full((4, 18), np.nan, np.float32).tobytes()), "not_finite"),
    (lambda raw: [raw[k].update(shape=[0] + raw[k]["shape"][1:], data=b"")
                  for k in ("actions", "rewards", "terminated", "truncated")] + [
                  raw["obs"].update(shape=[1, 41], data=bytes(164))], "empty_chunk"),
])
def test_each_rejection_names_its_reason(change, reason):
    raw = wire(make_chunk(steps=4))
    change(raw)
    assert reason_of(raw) == reason


def test_rejections_are_counted_and_logged_per_reason(caplog):
    rejections = Rejections(logging.getLogger("test.rejections"), interval=3600)
    with caplog.at_level(logging.WARNING, "test.rejections"):
        for _ in range(1000):
            rejections.add(ProtocolError("experience: obs contains NaN or infinity", "not_finite"))
        rejections.add(ProtocolError("experience: empty chunk", "empty_chunk"))
    # one line per reason: a flood of one reason does not hide the first of another
    assert [r.getMessage().split(": ", 1)[0] for r in caplog.records] == [
        "rejected message (not_finite", "rejected message (empty_chunk"]
    assert rejections.counters() == {"rejected": 1001, "rejected.not_finite": 1000, "rejected.empty_chunk": 1}
