"""Messages with large arrays (batches of camera frames, image chunks, weights): the encoder
joins their data into the message in one copy, and the result is the bytes msgpack itself
writes, so every peer reads them as before; decoding hands out read-only views of the payload."""

from __future__ import annotations

import numpy as np
import pytest

from l2r.protocol import SampleBatch, Weights, decode, encode, messages
from tests.protocol.factories import make_frames_batch, make_image_chunk


def msgpack_bytes(message, monkeypatch) -> bytes:
    """``message`` as msgpack packs it whole (no array counts as large)."""
    with monkeypatch.context() as patch:
        patch.setattr(messages, "LARGE_ARRAY_BYTES", 2**62)
        return encode(message)


def weights_with(*sizes: int) -> Weights:
    """Weights whose float32 parameters hold ``sizes`` values each, the first a strided view."""
    rng = np.random.default_rng(1)
    params = {f"p{i}": rng.standard_normal(n, np.float32) for i, n in enumerate(sizes)}
    params["p0"] = np.repeat(params["p0"], 2)[::2]  # not contiguous: the encoder makes it so
    return Weights(3, params, {"obs_dim": 41})


@pytest.mark.parametrize("threshold", [1, 64 * 1024])  # 1: every array joined, bin 8, 16 and 32 headers alike
def test_large_arrays_encode_to_the_bytes_msgpack_writes(threshold, monkeypatch):
    monkeypatch.setattr(messages, "LARGE_ARRAY_BYTES", threshold)
    # data of 0, 255, 256, 65,535, 65,536 and 65,540 bytes: either side of each header's limit
    for message in (make_frames_batch(b=5, k=3), make_image_chunk(),
                    weights_with(0, 63, 64, 16_383, 16_384, 16_385), weights_with(1, 1)):
        assert encode(message) == msgpack_bytes(message, monkeypatch)


def test_a_large_batch_of_frames_round_trips_as_read_only_views_of_the_payload():
    rng = np.random.default_rng(0)
    sent = make_frames_batch(b=32, k=3)
    sent.frames["pixels"] = rng.integers(0, 256, sent.frames["pixels"].shape, np.uint8)
    payload = encode(sent)
    assert isinstance(payload, bytes) and len(payload) > 35 * 3 * 84 * 84  # one copy of every frame in it
    batch = decode(payload, SampleBatch)
    frames = batch.frames["pixels"]
    np.testing.assert_array_equal(frames, sent.frames["pixels"])
    np.testing.assert_array_equal(batch.obs_frames, sent.obs_frames)
    np.testing.assert_array_equal(batch.next_obs_frames, sent.next_obs_frames)
    assert not frames.flags.owndata and not frames.flags.writeable  # no copy, and none can change the bytes
    with pytest.raises(ValueError):
        frames[0, 0, 0, 0] = 1
    stacks = frames[batch.obs_frames].reshape(32, 9, 84, 84)  # what the learner builds
    np.testing.assert_array_equal(stacks[:, 3:6], sent.frames["pixels"][1:33])
