"""A real l2r-replay of camera observations over loopback Zenoh: chunks of observation fields
stored and sampled as stacks of frames (values worked out by hand from ``make_image_chunk``:
pixel row t is all t, the final observation after step t all 200 + t), chunks of other fields
rejected and counted, image fields kept through a snapshot, kill -9 and restore, and a vector
snapshot from before observation fields restored."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import zenoh

from l2r.protocol import EXPERIENCE_QOS, Keys, NotReady, SampleBatch, SampleRequest, decode, encode
from l2r.replay import snapshot
from l2r.replay.rate_limiter import RateLimiter
from l2r.replay.server import ReplayServer, ServerConfig
from l2r.replay.storage import Storage, StorageConfig
from tests.conftest import wait_for
from tests.protocol.factories import make_chunk, make_image_chunk, stream_chunk

pytestmark = pytest.mark.slow

CAMERA = ("--observation", "pixels: uint8[3, 8, 8], state: float32[5]", "--act-dim", "6")
ACTOR, EPOCH = 4, 9  # make_image_chunk's


def chunk(seq: int = 0, plus: int = 0):
    """make_image_chunk's 6 steps (an episode ends at step 2) with ``plus`` added to every pixel."""
    c = make_image_chunk(side=8, seq=seq)
    return dataclasses.replace(c, obs={**c.obs, "pixels": c.obs["pixels"] + np.uint8(plus)},
                               final_obs={**c.final_obs, "pixels": c.final_obs["pixels"] + np.uint8(plus)})


def send(session: zenoh.Session, run: str, *chunks) -> None:
    for c in chunks:
        session.put(Keys(run).experience(c.actor_id), encode(c), **EXPERIENCE_QOS.put())


def ask(session: zenoh.Session, run: str, request: SampleRequest):
    """The shard's reply: a SampleBatch, a NotReady, or the text of an error reply."""
    for reply in session.get(Keys(run).sample(0), payload=encode(request), timeout=10.0):
        if reply.ok is None:
            return reply.err.payload.to_string()
        message = decode(reply.ok.payload)
        assert isinstance(message, (SampleBatch, NotReady))
        return message
    raise AssertionError("no reply")


def stacks(session: zenoh.Session, run: str, stored: int) -> dict[int, tuple[tuple, tuple]]:
    """Pixel value of each stored observation -> (its stack of 3, its next stack), oldest first."""
    got = {}
    for _ in range(50):
        batch = ask(session, run, SampleRequest(batch_size=256, frame_stack=3))
        if not isinstance(batch, SampleBatch):
            continue
        pixels = batch.frames["pixels"]
        assert pixels.dtype == np.uint8 and pixels.shape[1:] == (3, 8, 8) and batch.obs is None
        assert len(np.unique(pixels[:, 0, 0, 0])) == len(pixels)  # every frame once
        numbers = pixels[:, 0, 0, 0].astype(int)
        state = np.where(numbers >= 200, -((numbers - 200) % 50 + 1), numbers % 50)  # the frame's own state row
        np.testing.assert_array_equal(batch.frames["state"], np.repeat(state[:, None], 5, axis=1))
        got |= {int(numbers[o[-1]]): (tuple(numbers[o]), tuple(numbers[x]))
                for o, x in zip(batch.obs_frames, batch.next_obs_frames)}
        if len(got) == stored:
            return got
    raise AssertionError(f"sampled {sorted(got)}, expected {stored} observations")


FIRST_CHUNK = {0: ((0, 0, 0), (0, 0, 1)), 1: ((0, 0, 1), (0, 1, 2)), 2: ((0, 1, 2), (1, 2, 202)),
               3: ((3, 3, 3), (3, 3, 4)), 4: ((3, 3, 4), (3, 4, 5)), 5: ((3, 4, 5), (4, 5, 6))}


def test_camera_chunks_come_back_as_stacks_and_other_chunks_are_rejected(start_replay, connect, ask_stats,
                                                                         run_name):
    replay = start_replay(*CAMERA)
    session = connect(replay)
    wrong_dtype = chunk()
    wrong_dtype.obs = {**wrong_dtype.obs, "pixels": wrong_dtype.obs["pixels"].astype(np.float32)}
    wrong_dtype.final_obs = {**wrong_dtype.final_obs, "pixels": wrong_dtype.final_obs["pixels"].astype(np.float32)}
    send(session, run_name, make_image_chunk(side=4, seq=7), wrong_dtype,
         make_chunk(actor_id=ACTOR, seq=8, obs_dim=5, act_dim=6),  # the vector: no pixels
         chunk(seq=0))
    assert stacks(session, run_name, stored=6) == FIRST_CHUNK
    stats = ask_stats(session)
    assert (stats["rejected.wrong_shape"], stats["rejected.wrong_dtype"], stats["rejected.missing_field"]) == \
        (1, 1, 1), stats
    assert stats["size"] == 6 and replay.proc.poll() is None

    refused = ask(session, run_name, SampleRequest(batch_size=8))
    assert isinstance(refused, str) and refused.startswith("frames_only:"), refused
    too_large = ask(session, run_name, SampleRequest(batch_size=300_000, frame_stack=3))
    assert isinstance(too_large, str) and too_large.startswith("too_large:"), too_large
    assert "capacity 10000 transitions of observation {pixels: uint8[3, 8, 8], state: float32[5]}" in replay.log()


def test_image_fields_survive_a_snapshot_and_the_log_through_kill_9(start_replay, connect, acks_of, run_name,
                                                                    tmp_path):
    args = (*CAMERA, "--snapshot-dir", str(tmp_path / "snap"), "--snapshot-interval", "0.3")

    def acknowledged(seq: int):
        return lambda ack: ack.of(ACTOR, EPOCH) is not None and ack.of(ACTOR, EPOCH)[0] >= seq

    replay = start_replay(*args)
    session = connect(replay)
    send(session, run_name, chunk(seq=0))
    acks_of(session).wait(acknowledged(0))
    assert wait_for(lambda: "snapshot: 6 transitions" in replay.log()), replay.log()
    replay.proc.kill()
    replay.proc.wait()

    again = start_replay(*args[:-1], "3600", endpoint=replay.endpoint)  # from the snapshot
    session = connect(again)
    assert stacks(session, run_name, stored=6) == FIRST_CHUNK, again.log()
    send(session, run_name, chunk(seq=1, plus=50))  # after the last snapshot: only the log has it
    acks_of(session).wait(acknowledged(1))
    again.proc.kill()
    again.proc.wait()

    last = start_replay(*args[:-1], "3600", endpoint=replay.endpoint)
    session = connect(last)
    second = {pixel + 50: ((a + 50, b + 50, c + 50), (d + 50, e + 50, f + 50))
              for pixel, ((a, b, c), (d, e, f)) in FIRST_CHUNK.items()}
    assert stacks(session, run_name, stored=12) == FIRST_CHUNK | second, last.log()


def test_a_vector_snapshot_from_before_fields_restores(start_replay, connect, ask_stats, run_name, tmp_path):
    server = ReplayServer(ServerConfig(), Storage(StorageConfig(capacity=10000, obs_dim=2, act_dim=1)), RateLimiter())
    server._store(stream_chunk(0, 8, seq=0, ends=(3,)), None)
    arrays, meta = server.capture()
    # the arrays such a snapshot held: the vector as "obs" and "side_obs", no "observation"
    old = {name: values for name, values in arrays.items() if not name.startswith(("obs.", "side_obs.", "observation"))}
    old |= {"obs": arrays["obs.state"], "side_obs": arrays["side_obs.state"]}
    snapshot.write(snapshot.snapshot_path(tmp_path, 0), old, meta)

    replay = start_replay("--obs-dim", "2", "--act-dim", "1", "--snapshot-dir", str(tmp_path))
    session = connect(replay)
    assert ask_stats(session)["size"] == 8, replay.log()
    batch = ask(session, run_name, SampleRequest(batch_size=64))
    assert isinstance(batch, SampleBatch), batch
    np.testing.assert_array_equal(batch.next_obs[:, 0], np.where(batch.obs[:, 0] == 3, -4, batch.obs[:, 0] + 1))
    np.testing.assert_array_equal(batch.rewards, batch.obs[:, 0] + 1)


def test_frames_of_a_reply_past_a_megabyte_come_back_whole(start_replay, connect, run_name):
    """Gathered straight into the message, sent through the shard's shared memory."""
    replay = start_replay("--observation", "pixels: uint8[3, 84, 84], state: float32[5]", "--act-dim", "6")
    session = connect(replay)
    send(session, run_name, make_image_chunk(steps=60, ends=(), side=84))

    def batch() -> SampleBatch | None:
        reply = ask(session, run_name, SampleRequest(batch_size=256, frame_stack=3))
        return reply if isinstance(reply, SampleBatch) else None

    sampled = wait_for(batch)
    pixels = sampled.frames["pixels"]
    assert pixels.nbytes > 2**20
    numbers = pixels[:, 0, 0, 0]
    assert (pixels == numbers[:, None, None, None]).all()  # every frame whole, each pixel row t all t
    np.testing.assert_array_equal(sampled.frames["state"], np.repeat(numbers[:, None], 5, axis=1).astype(np.float32))
    last = numbers[sampled.obs_frames[:, -1]].astype(int)
    np.testing.assert_array_equal(numbers[sampled.obs_frames], np.maximum(last[:, None] + [-2, -1, 0], 0))
    np.testing.assert_array_equal(numbers[sampled.next_obs_frames], np.maximum(last[:, None] + [-1, 0, 1], 0))
