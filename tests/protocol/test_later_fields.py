"""Fields added to protocol version 1 for on-policy learning: a sender may leave them out, so the
messages of earlier peers still decode, and when present they are checked like any other."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from l2r.protocol import ExperienceChunk, ProtocolError, ReplayAck, SampleBatch, SampleRequest, decode, encode
from tests.protocol.factories import every_message, make_chunk


def without(message, *names: str) -> bytes:
    """The encoding of ``message`` as a peer from before ``names`` existed sends it."""
    raw = msgpack.unpackb(encode(message))
    for name in names:
        raw.pop(name, None)
    return msgpack.packb(raw, use_bin_type=True)


def queue_batch(n: int = 4) -> SampleBatch:
    batch = next(m for m in every_message() if isinstance(m, SampleBatch))
    batch.log_probs, batch.segment_ends = np.linspace(-3, 0, len(batch.obs)).astype(np.float32), \
        np.arange(len(batch.obs)) % n == n - 1
    return batch


def test_messages_of_earlier_peers_decode_with_the_new_fields_none():
    chunk = make_chunk(steps=5)
    chunk.log_probs = np.zeros(5, np.float32)
    assert decode(without(chunk, "log_probs")).log_probs is None
    assert decode(without(SampleRequest(64, 1, False, 3, "queue"), "table")).table is None
    batch = decode(without(queue_batch(), "log_probs", "segment_ends"))
    assert batch.log_probs is None and batch.segment_ends is None
    ack = next(m for m in every_message() if isinstance(m, ReplayAck))
    ack.hold = True
    assert decode(without(ack, "hold")).hold is None


def test_a_field_left_unset_is_left_out_so_earlier_peers_get_the_bytes_they_know():
    assert b"table" not in encode(SampleRequest(64, 1, False, 3))
    assert b"log_probs" not in encode(make_chunk(steps=3))


def test_the_new_fields_round_trip():
    chunk = make_chunk(steps=5)
    chunk.log_probs = np.array([-1.5, 0.25, -7.0, 2.0, 0.0], np.float32)
    np.testing.assert_array_equal(decode(encode(chunk)).log_probs, chunk.log_probs)
    assert decode(encode(SampleRequest(64, 1, False, 3, "queue"))).table == "queue"
    sent = queue_batch()
    back = decode(encode(sent))
    np.testing.assert_array_equal(back.log_probs, sent.log_probs)
    np.testing.assert_array_equal(back.segment_ends, sent.segment_ends)


@pytest.mark.parametrize("log_probs, reason", [
    (np.zeros(4, np.float32), "shape_mismatch"),  # one row short
    (np.array([0, 0, np.nan, 0, 0], np.float32), "not_finite"),
    (np.zeros(5, np.float64), "wrong_dtype"),
])
def test_bad_log_probs_are_rejected(log_probs, reason):
    raw = msgpack.unpackb(encode(make_chunk(steps=5)))
    raw["log_probs"] = {"dtype": log_probs.dtype.str, "shape": list(log_probs.shape), "data": log_probs.tobytes()}
    with pytest.raises(ProtocolError) as error:
        decode(msgpack.packb(raw, use_bin_type=True), ExperienceChunk)
    assert error.value.reason == reason


def test_a_queue_batch_needs_both_of_its_fields():
    with pytest.raises(ProtocolError) as error:
        decode(without(queue_batch(), "segment_ends"))
    assert error.value.reason == "missing_field"
