"""`l2r view --live`: a real viewer process, frames over loopback Zenoh, sent only while it watches:
a runner's body, or a camera task's frames as images; bad frames are rejected with their reason."""

from __future__ import annotations

import subprocess
import sys
import time
import uuid

import gymnasium
import msgpack
import numpy as np
import pytest
import rerun as rr
import zenoh

import l2r.control  # noqa: F401  (registers the camera tasks)
from l2r.episodes.live import LiveFrames, frame
from l2r.photo import TUNE_ID
from l2r.protocol.keys import Keys
from l2r.protocol.messages import Frame, decode, encode
from l2r.protocol.session import session_config
from l2r.sim.env import RunEnv
from tests.actors.camera import RENDERER
from tests.conftest import free_port, wait_for
from tests.logs.recording import view_origins


def start_viewer(run: str, port: int, out) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "l2r.cli", "view", "--live", "--run", run, "--connect", f"tcp/127.0.0.1:{port}",
         "--save", str(out), "--duration", "4"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip


@pytest.mark.slow
def test_live_viewer_draws_frames_that_actors_send_only_while_it_watches(tmp_path):
    run, port = f"live{uuid.uuid4().hex[:8]}", free_port()
    out = tmp_path / "live.rrd"
    env = RunEnv(difficulty=0)
    obs, info = env.reset(seed=0)
    with zenoh.open(session_config(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        live = LiveFrames(session, Keys(run), actor_id=5, rate_hz=1000)
        assert not live.publish(0, 0, 0, {"state": obs}, 0.0, info), "no viewer: nothing is sent"
        viewer = start_viewer(run, port, out)
        try:
            assert wait_for(lambda: live.watched, 30), "the viewer's liveliness token never arrived"
            rewards = []
            for step in range(20):
                obs, reward, terminated, truncated, info = env.step(np.full(18, 0.1))
                assert live.publish(0, 0, step, {"state": obs}, reward, info)
                rewards.append(reward)
                time.sleep(0.02)
                if terminated or truncated:
                    obs, info = env.reset(seed=step)
            _, err = viewer.communicate(timeout=60)
        finally:
            viewer.kill()
        assert viewer.returncode == 0, err
        assert wait_for(lambda: not live.watched, 10), "frames must stop when the viewer leaves"
        live.close()

    chunks = rr.chunk.RrdReader(out).stream().to_chunks()
    logged = [v[0] for c in chunks if c.entity_path == "/plots/reward/actor5_env0" and not c.is_static
              for v in c.to_record_batch().column("Scalars:scalars").to_pylist()]  # fmt: skip
    assert logged and set(logged) <= set(rewards)
    root = "/world/ground/actor5/env0"
    assert any(c.entity_path == f"{root}/pelvis" and not c.is_static for c in chunks)
    assert any(c.entity_path == f"{root}/pelvis/shape/capsules" for c in chunks)
    assert any(c.entity_path == f"{root}/muscles" and not c.is_static for c in chunks)


def with_image(payload: bytes, image: dict) -> bytes:
    """A frame's payload with its pixels replaced by ``image`` (an array map), as a faulty peer sends it."""
    raw = msgpack.unpackb(payload)
    raw["images"]["pixels"] = image
    return msgpack.packb(raw, use_bin_type=True)


@pytest.mark.slow
@pytest.mark.skipif(not RENDERER, reason="no EGL or OSMesa to render with")
def test_live_viewer_draws_a_camera_task_s_frames_as_images_and_rejects_bad_ones(tmp_path):
    run, port, side = f"live{uuid.uuid4().hex[:8]}", free_port(), 32
    out = tmp_path / "live.rrd"
    env = gymnasium.make("l2r/dmc-cartpole-swingup-v0", image_size=side)
    obs, info = env.reset(seed=0)
    with zenoh.open(session_config(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        live = LiveFrames(session, Keys(run), actor_id=5, rate_hz=1000)
        assert not live.publish(0, 0, 0, obs, 0.0, info), "no viewer: nothing is sent"
        viewer = start_viewer(run, port, out)
        try:
            assert wait_for(lambda: live.watched, 30), "the viewer's liveliness token never arrived"
            good = encode(frame(5, 1, 0, 0, obs, 0.0, info))
            bad = [with_image(good, {"dtype": "<f4", "shape": [1, 3, side, side], "data": bytes(12 * side * side)}),
                   with_image(good, {"dtype": "|u1", "shape": [1, 3, 1200, 1200], "data": bytes(3 * 1200 * 1200)}),
                   with_image(good, {"dtype": "|u1", "shape": [1, 3, side, side], "data": b"\x00" * 10})]
            for payload in bad:  # from another env of the same actor; blocking, so that none is dropped on the way
                session.put(Keys(run).frames(5, 1), payload, congestion_control=zenoh.CongestionControl.BLOCK)
            sent = {}
            for step in range(1, 16):
                obs, reward, *_, info = env.step(env.action_space.sample())
                assert live.publish(0, 0, step, obs, reward, info)
                sent[step] = (obs["pixels"].copy(), reward)
                time.sleep(0.02)
            _, err = viewer.communicate(timeout=60)
        finally:
            viewer.kill()
            env.close()
        live.close()
    assert viewer.returncode == 0, err
    for reason in ("wrong_dtype", "oversized", "bad_array"):  # each logged with its reason, none a crash
        assert f"({reason}: 1 so far" in err, err
    assert "3 rejected" in err, err

    reader = rr.chunk.RrdReader(out)
    chunks = [c for c in reader.stream().to_chunks() if not c.is_static]
    assert not any(c.entity_path.startswith("/world/ground/actor5") for c in chunks)  # no runner to draw
    drawn = []
    for chunk in chunks:
        if chunk.entity_path.startswith("/images/"):
            assert chunk.entity_path == "/images/pixels/actor5_env0"
            batch = chunk.to_record_batch()
            drawn += zip(batch.column("step").to_pylist(), batch.column("Image:buffer").to_pylist(),
                         batch.column("Image:format").to_pylist())  # fmt: skip
    assert len(drawn) > len(sent) // 2  # best effort, but loopback loses few if any
    for step, buffer, image_format in drawn:  # each the frame the env returned from that step
        assert (image_format[0]["width"], image_format[0]["height"]) == (side, side)
        image = np.frombuffer(bytes(buffer[0]), np.uint8).reshape(side, side, 3)
        np.testing.assert_array_equal(image, sent[step][0].transpose(1, 2, 0))
    assert np.std([np.frombuffer(bytes(b[0]), np.uint8) for _, b, _ in drawn]) > 10  # a real render
    rewards = {step: v[0] for c in chunks if c.entity_path == "/plots/reward/actor5_env0"
               for step, v in zip(c.to_record_batch().column("step").to_pylist(),
                                  c.to_record_batch().column("Scalars:scalars").to_pylist())}  # fmt: skip
    assert rewards and all(np.float64(sent[step][1]) == value for step, value in rewards.items())
    assert not any(c.entity_path.startswith("/plots/distance") for c in chunks)  # the cartpole has no distance
    assert "/images/pixels/actor5_env0" in view_origins(reader)  # a view of its own, beside the reward


def test_a_photo_task_s_frame_carries_its_photo_and_goal_as_the_env_returned_them():
    env = gymnasium.make(TUNE_ID)
    env.reset(seed=0)
    obs, reward, *_, info = env.step(env.action_space.sample())
    env.close()
    sent = decode(encode(frame(2, 3, 0, 1, obs, reward, info)), Frame)
    assert sent.images.keys() == {"pixels", "goal"}  # the float state is no image
    for name, image in sent.images.items():
        assert image.dtype == np.uint8 and image.shape == (1, *obs[name].shape)
        np.testing.assert_array_equal(image[0], obs[name])
    assert sent.values == {"reward": reward}
