"""Episode files from a real l2r-actor process, replayed against the environment they came from."""

from __future__ import annotations

import os
import subprocess
import sys
import uuid
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import zenoh

import l2r.sim  # noqa: F401  (registers l2r/Run-v0)
from l2r.episodes.read import read_episode
from l2r.protocol.keys import Keys
from l2r.protocol.session import session_config
from l2r.sim.wrappers import ActionRepeat
from tests.logs.test_live import free_port

ROOT = Path(__file__).parents[2]


@pytest.mark.slow
def test_an_actor_process_logs_episodes_that_replay_exactly(tmp_path):
    run, port = f"logs{uuid.uuid4().hex[:8]}", free_port()
    with zenoh.open(session_config(listen=[f"tcp/127.0.0.1:{port}"])) as session:
        token = session.liveliness().declare_token(Keys(run).alive("replay", 0))  # the actor steps only with a replay
        result = subprocess.run(
            [sys.executable, "-m", "l2r.actors", "--run", run, "--connect", f"tcp/127.0.0.1:{port}",
             "--num-envs", "2", "--difficulty", "1", "--max-steps", "400", "--episode-log-dir", str(tmp_path),
             "--log-every", "1"],
            cwd=ROOT, capture_output=True, text=True, timeout=120, env={**os.environ, "PYTHONPATH": str(ROOT)})  # fmt: skip
        token.undeclare()
    assert result.returncode == 0, result.stderr[-3000:]
    files = sorted(tmp_path.glob("*.mcap"))
    assert files and not list(tmp_path.glob("*.part")), "a stopped actor leaves only complete files"

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
