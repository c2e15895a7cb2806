"""Chunks with compressed frames at a replay shard: stored exactly as their raw form is;
corrupt ones, ones that decompress to another size and ones of an unknown codec rejected with
their reasons and counted while the shard goes on (a real l2r-replay over loopback Zenoh); and
the write-ahead log, which holds them as they came, restoring them after kill -9."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
import zenoh

from l2r.protocol import EXPERIENCE_QOS, FrameCompressor, Keys, ObservationSpec, encode
from l2r.replay.rate_limiter import RateLimiter
from l2r.replay.server import ReplayServer, ServerConfig
from l2r.replay.storage import Storage, StorageConfig
from l2r.replay.wal import WriteAheadLog
from tests.protocol.factories import make_image_chunk
from tests.replay.test_image_replay import ACTOR, CAMERA, EPOCH, FIRST_CHUNK, chunk, stacks

pytestmark = pytest.mark.slow

SPEC = ObservationSpec.parse("pixels: uint8[3, 84, 84], state: float32[5]")  # make_image_chunk's


def compressed(c) -> bytes:
    return encode(c, FrameCompressor())


def put(session: zenoh.Session, run: str, *payloads: bytes) -> None:
    for payload in payloads:
        session.put(Keys(run).experience(ACTOR), payload, **EXPERIENCE_QOS.put())


def altered(seq: int, change) -> bytes:
    """Chunk ``seq`` compressed, its obs.pixels map changed by ``change``."""
    raw = msgpack.unpackb(compressed(chunk(seq=seq)), raw=False)
    change(raw["obs"]["pixels"])
    return msgpack.packb(raw, use_bin_type=True)


def flip_a_byte(pixels: dict) -> None:
    data = bytearray(pixels["data"])
    data[len(data) // 2] ^= 0xFF
    pixels["data"] = bytes(data)


def test_a_compressed_chunk_is_stored_byte_for_byte_as_its_raw_form():
    chunks = [make_image_chunk(steps=40, ends=(12,), side=84, seq=seq) for seq in range(3)]
    noise = np.random.default_rng(0).integers(0, 256, chunks[1].obs["pixels"].shape, np.uint8)
    chunks[1].obs["pixels"][:] = noise  # frames zstd cannot shrink, beside ones it shrinks a thousandfold
    assert len(compressed(chunks[0])) < len(encode(chunks[0])) / 100
    stored = []
    for frames in (None, FrameCompressor()):
        server = ReplayServer(ServerConfig(), Storage(StorageConfig(capacity=1000, act_dim=6, observation=SPEC)),
                              RateLimiter())
        for c in chunks:
            server._store(server._check(encode(c, frames)), None)
        stored.append(server.capture()[0])
    raw, unpacked = stored
    assert raw.keys() == unpacked.keys() and {"obs.pixels", "side_obs.pixels"} <= raw.keys()
    assert raw["obs.pixels"][:120].any()
    for name in raw:
        np.testing.assert_array_equal(unpacked[name], raw[name], err_msg=name)


def test_bad_compressed_chunks_are_rejected_and_counted_and_the_shard_goes_on(start_replay, connect, ask_stats,
                                                                             run_name):
    replay = start_replay(*CAMERA)
    session = connect(replay)
    put(session, run_name,
        altered(5, flip_a_byte),
        altered(6, lambda pixels: pixels.update(shape=[6, 3, 8, 8])),  # decompresses to a row more than it says
        altered(7, lambda pixels: pixels.update(codec="brotli")),
        compressed(chunk(seq=0)))
    assert stacks(session, run_name, stored=6) == FIRST_CHUNK
    stats = ask_stats(session)
    assert (stats["rejected.corrupt"], stats["rejected.bad_array"], stats["rejected.unknown_codec"]) == (1, 1, 1), \
        stats
    assert stats["rejected"] == 3 and stats["size"] == 6 and replay.proc.poll() is None
    assert "codec 'brotli', this side decompresses zstd" in replay.log()


def test_the_log_holds_compressed_chunks_as_they_came_and_restores_them_after_kill_9(start_replay, connect, acks_of,
                                                                                     run_name, tmp_path):
    args = (*CAMERA, "--snapshot-dir", str(tmp_path), "--snapshot-interval", "3600")
    replay = start_replay(*args)
    session = connect(replay)
    payloads = [compressed(chunk(seq=0)), compressed(chunk(seq=1, plus=50))]
    put(session, run_name, *payloads)
    acks_of(session).wait(lambda ack: ack.of(ACTOR, EPOCH) is not None and ack.of(ACTOR, EPOCH)[0] >= 1)
    replay.proc.kill()
    replay.proc.wait()
    log = WriteAheadLog(tmp_path, 0)
    assert list(log.records(0)) == payloads  # as they came: compressed

    again = start_replay(*args, endpoint=replay.endpoint)
    session = connect(again)
    second = {pixel + 50: ((a + 50, b + 50, c + 50), (d + 50, e + 50, f + 50))
              for pixel, ((a, b, c), (d, e, f)) in FIRST_CHUNK.items()}
    assert stacks(session, run_name, stored=12) == FIRST_CHUNK | second, again.log()
