"""`l2r view --live`: a real viewer process, frames over loopback Zenoh, sent only while it watches."""

from __future__ import annotations

import subprocess
import sys
import time
import uuid

import numpy as np
import pytest
import rerun as rr
import zenoh

from l2r.episodes.live import LiveFrames
from l2r.protocol.keys import Keys
from l2r.protocol.session import session_config
from l2r.sim.env import RunEnv
from tests.conftest import free_port, wait_for


@pytest.mark.slow
def test_live_viewer_draws_frames_that_actors_send_only_while_it_watches(tmp_path):
    run, port = f"live{uuid.uuid4().hex[:8]}", free_port()
    out = tmp_path / "live.rrd"
    env = RunEnv(difficulty=0)
    _, info = env.reset(seed=0)
    with zenoh.open(session_config(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        live = LiveFrames(session, Keys(run), actor_id=5, rate_hz=1000)
        assert not live.publish(0, 0, 0, 0.0, info), "no viewer: nothing is sent"
        viewer = subprocess.Popen(
            [sys.executable, "-m", "l2r.cli", "view", "--live", "--run", run, "--connect", f"tcp/127.0.0.1:{port}",
             "--save", str(out), "--duration", "4"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
        try:
            assert wait_for(lambda: live.watched, 30), "the viewer's liveliness token never arrived"
            rewards = []
            for step in range(20):
                _, reward, terminated, truncated, info = env.step(np.full(18, 0.1))
                assert live.publish(0, 0, step, reward, info)
                rewards.append(reward)
                time.sleep(0.02)
                if terminated or truncated:
                    _, info = env.reset(seed=step)
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
