"""A real `l2r-actor` on a real camera task (the suite's cartpole, 16 × 16 frames) sends live frames
that carry its observation's frames, the ones its chunks carry, and only while a viewer's
liveliness token exists."""

from __future__ import annotations

import subprocess
import sys
import threading
import time
import uuid

import numpy as np
import pytest
import zenoh

from l2r.protocol import ExperienceChunk, Frame, Keys, decode, wait_alive
from tests.actors.camera import CAMERA, IMAGE_SIZE, RENDERER, camera_shard, stop_all
from tests.conftest import ROOT, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.skipif(not RENDERER, reason="no EGL or OSMesa to render with")]


def test_a_camera_actor_sends_its_observation_s_frames_live_while_a_viewer_watches(tmp_path):
    run = f"test-live-{uuid.uuid4().hex[:8]}"
    keys = Keys(run)
    replay, session = camera_shard(run, tmp_path)
    chunks: list[ExperienceChunk] = []
    frames: list[Frame] = []
    lock = threading.Lock()

    def on_frame(sample: zenoh.Sample) -> None:
        with lock:
            frames.append(decode(sample.payload, Frame))

    subs = [session.declare_subscriber(keys.experience_of_shard(0), lambda s: chunks.append(decode(s.payload))),
            session.declare_subscriber(keys.all_frames, on_frame)]
    actor = None
    try:
        assert wait_alive(session, keys.alive("replay", 0), timeout=20), replay.log()
        actor = subprocess.Popen(
            [sys.executable, "-m", "l2r.actors", "--run", run, "--connect", replay.endpoint, "--env-id", CAMERA,
             "--num-envs", "2", "--chunk-size", "4", "--action-repeat", "1", "--random-steps", "1000000"],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        assert wait_for(lambda: len(chunks) >= 4, 90), replay.log()[-2000:]
        assert not frames, "no viewer yet: no frames"
        token = session.liveliness().declare_token(keys.alive("viewer", "test"))
        assert wait_for(lambda: len(frames) >= 10, 30), f"{len(frames)} frames"
        token.undeclare()
        time.sleep(1.0)  # frames already on their way
        with lock:
            watched = len(frames)
        time.sleep(1.0)
        assert len(frames) == watched, "frames must stop when the viewer leaves"
    finally:
        out = stop_all(actor, subs, session, replay)
    assert actor.returncode == 0, out

    # Each live frame is one the env returned after a step: the frames the chunks carry.
    assert {f.env_id for f in frames} == {0, 1}
    sent = {(c.env_id, row.tobytes()) for c in chunks
            for rows in (c.obs["pixels"][1:], c.final_obs["pixels"]) for row in rows}  # fmt: skip
    for f in frames:
        image = f.images["pixels"]
        assert image.dtype == np.uint8 and image.shape == (1, 3, IMAGE_SIZE, IMAGE_SIZE)
        assert (f.env_id, image[0].tobytes()) in sent, f"env {f.env_id} step {f.step}: not a frame of its chunks"
        assert f.arrays == {} and set(f.values) == {"reward"}
    assert np.std([f.images["pixels"] for f in frames]) > 10  # real renders
