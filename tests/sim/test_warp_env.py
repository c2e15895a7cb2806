"""`l2r/RunWarp-v0` (MuJoCo Warp, float32, Warp's CPU device here) against `l2r/Run-v0` (numba,
float64) driven by the same excitations from the same reset.

Cost: the first MuJoCo Warp step compiles its kernels, about 4 minutes on a 2-core CPU with an
empty Warp kernel cache (~/.cache/warp), under a second with a warm one.
"""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest

import l2r.sim  # noqa: F401  (registers the environments)
from l2r.sim.layout import JOINTS, OBS_LABELS

STEPS = 20  # 0.2 s
ANGLES = [OBS_LABELS.index(c) for c in ("pelvis_tilt", *JOINTS)]
PELVIS = [OBS_LABELS.index(c) for c in ("pelvis_tx", "pelvis_ty")]


def test_warp_worlds_follow_the_numba_port():
    """Two worlds, one driven as the numba env is and one held at zero excitation: the first
    follows the numba env's joints within 0.01 degrees and its pelvis within 0.01 cm over 0.2 s
    (float32 against float64), the second does not move with it, and both start their next
    episode in the step their last one ended (max_steps 20)."""
    actions = np.random.default_rng(0).uniform(0.0, 1.0, (STEPS, 18))
    port = gymnasium.make("l2r/Run-v0", max_steps=STEPS).unwrapped
    worlds = gymnasium.make_vec("l2r/RunWarp-v0", num_envs=2, max_steps=STEPS, device="cpu")
    obs, info = port.reset(seed=0)
    got, got_info = worlds.reset(seed=0)
    np.testing.assert_allclose(got[0], obs, atol=1e-5)
    np.testing.assert_allclose(got_info["muscle_force"][0], info["muscle_force"], rtol=1e-4, atol=0.01)
    first, first_distance = got.copy(), got_info["distance"].copy()
    for k, a in enumerate(actions):
        obs, reward, terminated, truncated, info = port.step(a)
        got, got_reward, got_terminated, got_truncated, got_info = worlds.step(np.stack([a, np.zeros(18)]))
        last = got_info["final_obs"] if k == STEPS - 1 else got
        assert np.degrees(np.abs(last[0, ANGLES] - obs[ANGLES])).max() < 0.01
        assert 100 * np.abs(last[0, PELVIS] - obs[PELVIS]).max() < 0.01
        assert abs(got_reward[0] - reward) < 1e-5
        assert got_terminated[0] == terminated and got_truncated[0] == truncated
    assert np.degrees(np.abs(last[1, ANGLES] - obs[ANGLES])).max() > 1.0  # the idle world went its own way
    assert got_truncated.all()
    np.testing.assert_allclose(got, first, atol=1e-6)  # both reset in the step they ended
    np.testing.assert_allclose(got_info["distance"], first_distance)  # and report their new episode's info


def test_one_world_env_has_the_single_env_api():
    env = gymnasium.make("l2r/RunWarp-v0", max_steps=2, device="cpu")
    obs, _ = env.reset(seed=0)
    assert obs.shape == (41,) and obs.dtype == np.float32
    obs, reward, terminated, truncated, info = env.step(np.full(18, 0.5))
    assert isinstance(reward, float) and not terminated and not truncated and info["muscle_force"].shape == (18,)
    port = gymnasium.make("l2r/Run-v0").unwrapped
    assert env.unwrapped.body_names == port.body_names and info["body_pos"].shape == (len(port.body_names), 3)
    assert env.step(np.full(18, 0.5))[3]  # truncated at max_steps
    with pytest.raises(RuntimeError):
        env.step(np.full(18, 0.5))
    env.reset()
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(17))
