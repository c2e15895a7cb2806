"""Fields added to protocol version 1 for on-policy learning and n-step returns: a sender may leave
them out, so the messages of earlier peers still decode, and when present they are checked like
any other."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from l2r.protocol import (
    EpisodeSummary, ExperienceChunk, ProtocolError, ReplayAck, SampleBatch, SampleRequest, decode, encode,
)
from tests.protocol.factories import every_message, make_chunk


def without(message, *names: str) -> bytes:
    """The encoding of ``message`` as a peer from before ``names`` existed sends it."""
    raw = msgpack.unpackb(encode(message))
    for name in names:
        raw.pop(name, None)
    return msgpack.packb(raw, use_bin_type=True)


def n_step_batch() -> SampleBatch:
    batch = next(m for m in every_message() if isinstance(m, SampleBatch))
    batch.discounts = np.linspace(0, 0.97, len(batch.obs)).astype(np.float32)
    return batch


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
    request = decode(without(SampleRequest(64, 1, False, 3, n_step=3, gamma=0.9), "n_step", "gamma"))
    assert request.n_step is None and request.gamma is None
    assert decode(without(n_step_batch(), "discounts")).discounts is None


def test_a_field_left_unset_is_left_out_so_earlier_peers_get_the_bytes_they_know():
    assert b"table" not in encode(SampleRequest(64, 1, False, 3))
    assert b"log_probs" not in encode(make_chunk(steps=3))
    assert b"n_step" not in encode(SampleRequest(64)) and b"gamma" not in encode(SampleRequest(64))


def test_an_episode_summary_carries_a_psnr_from_photo_tasks_alone():
    episode = EpisodeSummary(actor_id=1, env_id=0, episode_return=0.2, distance=0.0, length=10, policy_version=3,
                             difficulty=0, seed=7)
    assert b"psnr_db" not in encode(episode)  # other tasks' summaries are the bytes they were
    episode.psnr_db = 31.5
    assert decode(encode(episode)).psnr_db == 31.5
    assert decode(without(episode, "psnr_db")).psnr_db is None


def test_the_new_fields_round_trip():
    chunk = make_chunk(steps=5)
    chunk.log_probs = np.array([-1.5, 0.25, -7.0, 2.0, 0.0], np.float32)
    np.testing.assert_array_equal(decode(encode(chunk)).log_probs, chunk.log_probs)
    assert decode(encode(SampleRequest(64, 1, False, 3, "queue"))).table == "queue"
    sent = queue_batch()
    back = decode(encode(sent))
    np.testing.assert_array_equal(back.log_probs, sent.log_probs)
    np.testing.assert_array_equal(back.segment_ends, sent.segment_ends)
    request = decode(encode(SampleRequest(64, 1, False, 3, n_step=20, gamma=0.0)))
    assert (request.n_step, request.gamma) == (20, 0.0)
    np.testing.assert_array_equal(decode(encode(n_step_batch())).discounts, n_step_batch().discounts)


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


@pytest.mark.parametrize("fields, reason", [
    ({"n_step": 0, "gamma": 0.9}, "out_of_range"),
    ({"n_step": 21, "gamma": 0.9}, "out_of_range"),
    ({"n_step": 3, "gamma": -0.01}, "out_of_range"),
    ({"n_step": 3, "gamma": 1.5}, "out_of_range"),
    ({"n_step": 3, "gamma": float("nan")}, "not_finite"),
    ({"n_step": 3, "gamma": "0.99"}, "wrong_type"),
    ({"n_step": 3.0, "gamma": 0.9}, "wrong_type"),
    ({"n_step": 3}, "missing_field"),  # a return of several steps needs its discount
])
def test_bad_n_step_requests_are_rejected(fields, reason):
    raw = msgpack.unpackb(encode(SampleRequest(64))) | fields
    with pytest.raises(ProtocolError) as error:
        decode(msgpack.packb(raw, use_bin_type=True), SampleRequest)
    assert error.value.reason == reason


def test_one_step_needs_no_gamma_and_discounts_need_a_row_each():
    assert decode(encode(SampleRequest(64, n_step=1))).gamma is None
    raw = msgpack.unpackb(encode(n_step_batch()))
    raw["discounts"] = dict(raw["discounts"], shape=[3], data=bytes(12))
    with pytest.raises(ProtocolError) as error:
        decode(msgpack.packb(raw, use_bin_type=True))
    assert error.value.reason == "shape_mismatch"
