"""Compressed frames on the wire (protocol version 3): a chunk's uint8 fields go zstd-compressed
and decode to the very arrays sent; a compressed field that is corrupt, that declares another
size than its dtype and shape (a lying header, a decompression bomb), or of an unknown codec is
rejected with its reason before anything beyond its declared size is allocated; peers of
version 2 reject such a chunk as ``version``; chunks without frames keep their bytes."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
import zstandard

from l2r.protocol import FrameCompressor, ProtocolError, decode, encode, messages
from tests.protocol.factories import make_chunk, make_frames_batch, make_image_chunk
from tests.protocol.test_observation_messages import pack, reason_of


def wire(payload: bytes) -> dict:
    return msgpack.unpackb(payload, raw=False)


def compressed_chunk() -> dict:
    """make_image_chunk's 6 steps of 8 x 8 frames (an episode ends at step 2), compressed, as a map."""
    return wire(encode(make_image_chunk(side=8), FrameCompressor()))


def test_compressed_frames_decode_to_the_arrays_sent_and_the_state_stays_raw():
    chunk = make_image_chunk(steps=64, ends=(10,), side=84)
    payload = encode(chunk, FrameCompressor())
    raw = wire(payload)
    assert raw["v"] == 3
    assert raw["obs"]["pixels"]["codec"] == "zstd" and raw["final_obs"]["pixels"]["codec"] == "zstd"
    assert "codec" not in raw["obs"]["state"]  # float32 fields are not frames
    assert len(payload) < len(encode(chunk)) / 50  # rows of one value each: a few bytes a frame
    back = decode(payload)
    for name in ("pixels", "state"):
        np.testing.assert_array_equal(back.obs[name], chunk.obs[name])
        np.testing.assert_array_equal(back.final_obs[name], chunk.final_obs[name])
        assert back.obs[name].dtype == chunk.obs[name].dtype


def test_chunks_without_frames_are_the_bytes_they_were():
    vector = make_chunk(obs_dim=5, act_dim=6)
    assert encode(vector, FrameCompressor()) == encode(vector)
    assert wire(encode(vector, FrameCompressor()))["v"] == 1


def test_a_peer_of_version_2_rejects_a_compressed_chunk_as_version(monkeypatch):
    payload = encode(make_image_chunk(side=8), FrameCompressor())
    monkeypatch.setattr(messages, "PROTOCOL_VERSION", 2)
    with pytest.raises(ProtocolError, match="protocol version 3, this side speaks 1 to 2") as error:
        decode(payload)
    assert error.value.reason == "version"


def test_a_corrupt_frame_is_rejected_as_corrupt():
    raw = compressed_chunk()
    data = bytearray(raw["obs"]["pixels"]["data"])
    data[len(data) // 2] ^= 0xFF
    raw["obs"]["pixels"]["data"] = bytes(data)
    assert reason_of(pack(raw)) == "corrupt"
    raw["obs"]["pixels"]["data"] = b"not zstd at all"
    assert reason_of(pack(raw)) == "corrupt"
    raw = compressed_chunk()
    raw["obs"]["pixels"]["data"] += raw["final_obs"]["pixels"]["data"]  # a second frame after the first
    assert reason_of(pack(raw)) == "corrupt"


def test_a_frame_of_another_size_than_its_shape_is_rejected_before_it_is_decompressed():
    raw = compressed_chunk()
    pixels = raw["obs"]["pixels"]
    pixels["data"] = zstandard.ZstdCompressor().compress(bytes(np.prod(pixels["shape"]) * 4))  # 4 times the bytes
    with pytest.raises(ProtocolError, match="declares 5376 bytes, its dtype and shape need 1344") as error:
        decode(pack(raw))
    assert error.value.reason == "bad_array"
    pixels["data"] = zstandard.ZstdCompressor(write_content_size=False).compress(bytes(1344))
    with pytest.raises(ProtocolError, match="declares no size") as error:
        decode(pack(raw))
    assert error.value.reason == "bad_array"


def test_a_field_declared_beyond_what_a_message_may_hold_is_refused_before_any_decompression():
    raw = compressed_chunk()
    raw["obs"]["pixels"]["shape"] = [2**20, 3, 84, 84]  # 22 GB of frames, claimed by a few bytes
    raw["obs"]["pixels"]["data"] = b"\x28\xb5\x2f\xfd"
    assert reason_of(pack(raw)) == "oversized"


def test_the_fields_of_one_message_share_one_bound(monkeypatch):
    chunk = make_image_chunk(side=8)
    two = {"left": chunk.obs["pixels"], "right": chunk.obs["pixels"]}  # 1,344 bytes each
    chunk.obs, chunk.final_obs = two, {"left": chunk.final_obs["pixels"], "right": chunk.final_obs["pixels"]}
    payload = encode(chunk, FrameCompressor())
    monkeypatch.setattr(messages, "MAX_MESSAGE_BYTES", 2000)
    with pytest.raises(ProtocolError, match="compressed fields of more than 2000 bytes") as error:
        decode(payload)
    assert error.value.reason == "oversized"
    monkeypatch.setattr(messages, "MAX_MESSAGE_BYTES", 2 * 1344 + 2 * 192)
    assert decode(payload).obs["right"].shape == (7, 3, 8, 8)


def test_an_unknown_codec_is_rejected_as_unknown_codec():
    raw = compressed_chunk()
    raw["obs"]["pixels"]["codec"] = "lz4"
    with pytest.raises(ProtocolError, match="codec 'lz4', this side decompresses zstd") as error:
        decode(pack(raw))
    assert error.value.reason == "unknown_codec"


def test_a_codec_is_read_only_where_compressed_frames_may_be():
    raw = compressed_chunk()
    raw["v"] = 2  # a version-2 chunk has raw arrays alone
    assert reason_of(pack(raw)) == "bad_array"
    batch = wire(encode(make_frames_batch(side=8)))
    batch["v"] = 3
    pixels = batch["frames"]["pixels"]
    batch["frames"]["pixels"] = pixels | {"codec": "zstd", "data": zstandard.ZstdCompressor().compress(pixels["data"])}
    assert reason_of(pack(batch)) == "bad_array"  # batches of frames are never compressed
