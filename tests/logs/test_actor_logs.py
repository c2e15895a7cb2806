"""A real l2r-actor process: its episode files replay exactly against the environment, and a
live viewer watching it draws its runners."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import uuid

import gymnasium
import numpy as np
import pytest
import rerun as rr
import zenoh

import l2r.sim  # noqa: F401  (registers l2r/Run-v0)
from l2r.episodes.read import read_episode
from l2r.protocol.keys import Keys
from l2r.protocol.session import session_config, wait_alive
from l2r.sim.wrappers import ActionRepeat
from tests.conftest import ROOT, free_port



@pytest.mark.slow
def test_an_actor_logs_episodes_that_replay_exactly_and_shows_them_live(tmp_path):
    run, port = f"logs{uuid.uuid4().hex[:8]}", free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    env_vars = {**os.environ, "PYTHONPATH": str(ROOT)}
    live_rrd = tmp_path / "live.rrd"
    with zenoh.open(session_config(listen=[endpoint])) as session:
        viewer = subprocess.Popen(
            [sys.executable, "-m", "l2r.cli", "view", "--live", "--run", run, "--connect", endpoint,
             "--save", str(live_rrd)],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env_vars)  # fmt: skip
        try:
            assert wait_alive(session, Keys(run).viewers, timeout=30), "the viewer never came up"
            # The actor steps only while a replay shard is alive: this test plays that part.
            token = session.liveliness().declare_token(Keys(run).alive("replay", 0))
            result = subprocess.run(
                [sys.executable, "-m", "l2r.actors", "--run", run, "--connect", endpoint, "--num-envs", "2",
                 "--difficulty", "1", "--max-steps", "400", "--episode-log-dir", str(tmp_path / "episodes"),
                 "--log-every", "1"],
                cwd=ROOT, capture_output=True, text=True, timeout=120, env=env_vars)  # fmt: skip
            token.undeclare()
            viewer.send_signal(signal.SIGINT)  # Ctrl-C: the viewer saves what it drew and leaves
            _, viewer_err = viewer.communicate(timeout=60)
        finally:
            viewer.kill()
    assert result.returncode == 0, result.stderr[-3000:]
    assert viewer.returncode == 0, viewer_err[-3000:]

    files = sorted((tmp_path / "episodes").glob("*.mcap"))
    assert files and not list((tmp_path / "episodes").glob("*.part")), "a stopped actor leaves only complete files"
    env = ActionRepeat(gymnasium.make("l2r/Run-v0", difficulty=1), 3)
    for path in files[:4]:
        episode = read_episode(path)
        meta, steps = episode.episode, episode.steps
        assert (meta["run"], meta["difficulty"], meta["step_seconds"]) == (run, "1", "0.03")
        assert int(episode.result["length"]) >= len(episode) > 0
        # The same seed and the logged excitations give back every logged number.
        obs, info = env.reset(seed=int(meta["seed"]))
        assert meta["obstacles"] == ";".join(",".join(repr(float(v)) for v in o) for o in env.unwrapped.obstacles)
        for k, action in enumerate(steps["action"]):
            obs, reward, terminated, truncated, info = env.step(action)
            assert np.array_equal(steps["observation"][k], obs) and steps["reward"][k] == reward
            assert np.array_equal(steps["muscle_force"][k], info["muscle_force"])
            assert np.array_equal(episode.pos[k], info["body_pos"][1:])
        assert terminated or truncated
        assert float(episode.result["return"]) == pytest.approx(float(np.sum(steps["reward"])))

    live = {c.entity_path for c in rr.chunk.RrdReader(live_rrd).stream().to_chunks() if not c.is_static}
    assert {"/world/ground/actor0/env0/pelvis", "/world/ground/actor0/env1/pelvis"} <= live
    assert "/world/ground/actor0/env0/muscles" in live and "/plots/reward/actor0_env0" in live
