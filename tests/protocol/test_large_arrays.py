"""Messages with large arrays (batches of camera frames, image chunks, weights): the encoder
joins their data into the message in one copy, and the result is the bytes msgpack itself
writes, so every peer reads them as before; a replay shard's reply gathers the frames straight
into the message, to the same bytes; decoding hands out read-only views of the payload."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest

from l2r.protocol import ProtocolError, SampleBatch, Weights, decode, encode, encode_gathered, messages
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


def test_large_array_data_decodes_as_views_of_the_payload_and_the_rest_as_msgpack_reads_it():
    weights = weights_with(16_384, 3)
    weights.spec["table"] = {"data": b"\0" * 70_000, "n": [1, {"data": 2}]}  # a free-form map like an array map
    for message in (make_frames_batch(b=32, k=3), make_image_chunk(), weights):
        payload = encode(message)
        views = messages._unpackb(payload)
        assert views == msgpack.unpackb(payload, raw=False)  # a memoryview equals the bytes it shows
        large = [v for v in leaves(views) if isinstance(v, memoryview)]
        assert large and all(v.obj is payload and len(v) >= messages.LARGE_ARRAY_BYTES for v in large)


def leaves(value):
    if isinstance(value, dict):
        for item in value.values():
            yield from leaves(item)
    else:
        yield value


def test_a_damaged_large_message_is_read_or_rejected_as_msgpack_alone_reads_or_rejects_it(monkeypatch):
    payload = encode(make_frames_batch(b=4, k=3))  # 148 KB of frames
    rng = np.random.default_rng(2)
    header = payload.index(b"frames") + 60  # the maps and headers before the frames' data
    damaged = [payload[:n] for n in (1, 10, header, len(payload) - 1)] + [payload + b"\0"]
    for at in [*range(header), *rng.integers(0, len(payload), 20)]:
        for byte in (0x00, 0xc6, 0xdf, int(rng.integers(256))):
            damaged.append(payload[:at] + bytes([byte]) + payload[at + 1:])

    def outcome(data: bytes) -> str | bytes:
        try:
            return encode(decode(data, SampleBatch))
        except ProtocolError as e:
            return e.reason

    walked = [outcome(d) for d in damaged]
    assert 100 < sum(isinstance(o, bytes) for o in walked) < len(damaged) - 100  # read and rejected alike
    monkeypatch.setattr(messages, "_WALK_ITEMS", 0)  # every payload read by msgpack whole
    assert walked == [outcome(d) for d in damaged]


def test_frames_gathered_into_the_message_are_the_bytes_of_the_batch_gathered_first():
    rng = np.random.default_rng(3)
    sources = {"pixels": rng.integers(0, 256, (60, 3, 84, 84), np.uint8),
               "state": rng.standard_normal((60, 201), np.float32),  # large, at an odd offset in the message
               "small": rng.standard_normal((60, 5), np.float32),
               "strided": rng.integers(0, 256, (60, 3, 84, 168), np.uint8)[..., ::2]}  # gathered first
    rows = np.array([7, 3, 59, 0, 12, 13, 14, 40, 41, 42, 43, 30, 31, 32, 33, 2, 5], np.int64)
    batch = make_frames_batch(b=10, k=3)
    gathered = dataclasses.replace(batch, frames={name: source.take(rows, axis=0) for name, source in sources.items()})
    assert encode_gathered(dataclasses.replace(batch, frames=None), sources, rows) == encode(gathered)
    small = {"small": sources["small"]}  # nothing large: msgpack packs it all
    small_frames = dataclasses.replace(batch, frames={"small": small["small"][rows]})
    assert encode_gathered(batch, small, rows) == encode(small_frames)
