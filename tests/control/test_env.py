"""ControlEnv on cartpole-swingup: real frames, seeding, action repeat against the suite itself,
the time limit, bad actions."""

import contextlib
import os
import warnings

import gymnasium
from gymnasium.utils.env_checker import check_env
import numpy as np
import pytest

import l2r.control  # noqa: F401  (registers the ids)
from l2r.control import rendering
from l2r.control.env import ControlEnv
from l2r.sim.wrappers import ActionRepeat
from dm_control import suite  # after l2r.control.env, which chooses MUJOCO_GL and patches dm_control


@pytest.fixture(scope="module")
def env():
    """One env for the module: each new one makes a GL context (about 0.3 s of CPU)."""
    env = gymnasium.make("l2r/dmc-cartpole-swingup-v0", with_state=True)
    yield env
    env.close()


@contextlib.contextmanager
def repeating(env, action_repeat):
    """The module's env with another action repeat for a while."""
    env.unwrapped.action_repeat = action_repeat
    try:
        yield env
    finally:
        env.unwrapped.action_repeat = 2


def test_spaces_are_a_single_channels_first_frame_and_the_state(env):
    assert env.observation_space["pixels"] == gymnasium.spaces.Box(0, 255, (3, 84, 84), np.uint8)
    assert env.observation_space["state"].shape == (5,) and env.observation_space["state"].dtype == np.float32
    assert env.action_space == gymnasium.spaces.Box(-1.0, 1.0, (1,), np.float32)
    assert env.unwrapped.action_repeat == 2
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", ".*A Box observation space m.*infinity")  # the state's bounds
        check_env(env.unwrapped, skip_render_check=True)


def test_frames_are_real_renders_that_follow_the_state(env):
    obs, _ = env.reset(seed=0)
    first = obs["pixels"]
    assert first.dtype == np.uint8 and first.shape == (3, 84, 84)
    assert first.std() > 10, "a blank or flat frame"
    assert obs in env.observation_space
    for _ in range(10):  # push the cart hard one way: it moves out of its place in the frame
        obs, *_ = env.step(np.ones(1, np.float32))
    assert np.abs(obs["pixels"].astype(int) - first).mean() > 1.0


def test_the_same_seed_gives_the_same_observations(env):
    def episode_start(seed):
        obs, _ = env.reset(seed=seed)
        after, *_ = env.step(np.full(1, 0.5, np.float32))
        return obs, after

    (a0, a1), (b0, b1) = episode_start(7), episode_start(7)
    for x, y in ((a0, b0), (a1, b1)):
        np.testing.assert_array_equal(x["pixels"], y["pixels"])
        np.testing.assert_array_equal(x["state"], y["state"])
    other, _ = episode_start(8)
    assert not np.array_equal(other["state"], a0["state"])


def test_one_step_is_the_repeat_of_suite_steps_with_their_rewards_summed(env):
    reference = suite.load("cartpole", "swingup")
    with repeating(env, 5):
        env.reset(seed=3)
        reference.reset()
        with reference.physics.reset_context():
            reference.physics.set_state(env.unwrapped.physics.get_state())
        action = np.array([0.6], np.float32)
        obs, reward, *_, info = env.step(action)
    time_steps = [reference.step(action) for _ in range(5)]
    assert info["inner_steps"] == 5
    assert reward == pytest.approx(sum(t.reward for t in time_steps), rel=1e-12)
    assert reward != pytest.approx(time_steps[-1].reward, rel=1e-3), "only the last reward"
    expected_state = np.concatenate([np.ravel(v) for v in time_steps[-1].observation.values()])
    np.testing.assert_allclose(obs["state"], expected_state, rtol=1e-6)


def test_the_episode_is_truncated_after_1000_suite_steps(env):
    with repeating(env, 300):
        env.reset(seed=0)
        steps = [env.step(np.zeros(1, np.float32)) for _ in range(4)]
        assert [s[4]["inner_steps"] for s in steps] == [300, 300, 300, 100]
        assert [(s[2], s[3]) for s in steps] == [(False, False)] * 3 + [(False, True)]
        with pytest.raises(RuntimeError, match="call reset"):
            env.step(np.zeros(1, np.float32))
        env.reset()
        assert env.step(np.zeros(1, np.float32))[3] is False


def test_reading_the_spaces_makes_no_camera_and_no_gl_context():
    # A learner or l2r up's planning reads the spaces on hosts that may have no OpenGL at all.
    fresh = gymnasium.make("l2r/dmc-walker-walk-v0")
    try:
        assert fresh.observation_space["pixels"].shape == (3, 84, 84)
        assert fresh.unwrapped.camera is None and fresh.unwrapped.gl is None
    finally:
        fresh.close()


def test_the_actors_action_repeat_over_the_env_s_own_counts_every_suite_step(env):
    with repeating(env, 300):
        env.reset(seed=0)
        repeated = ActionRepeat(env, 3)
        steps = [repeated.step(np.zeros(1, np.float32)) for _ in range(2)]
        assert [s[4]["inner_steps"] for s in steps] == [900, 100] and steps[1][3]


def test_the_report_names_the_backend_and_the_gl_renderer(env):
    env.reset(seed=0)
    report = rendering.gl_report(env.unwrapped.physics)
    assert report is env.unwrapped.gl
    assert report.backend == os.environ["MUJOCO_GL"] in ("egl", "osmesa")
    assert report.renderer and report.version[0].isdigit()


@pytest.mark.parametrize(
    "action, message",
    [
        ([np.nan], "non-finite"),
        ([np.inf], "non-finite"),
        ([0.1, 0.2], r"shape \(2,\), expected \(1,\)"),
        (0.5, r"shape \(\), expected \(1,\)"),
        (["left"], "not an array of numbers"),
    ],
)
def test_bad_actions_are_refused_with_a_clear_error(env, action, message):
    env.reset(seed=0)
    with pytest.raises(ValueError, match=f"cartpole-swingup: .*{message}"):
        env.step(action)
    env.step(np.zeros(1, np.float32))  # the env is still usable


def test_actions_are_mapped_onto_the_suite_bounds():
    env = ControlEnv("quadruped", "walk")
    try:
        low, high = env.suite_low, env.suite_high
        assert not (np.all(low == -1) and np.all(high == 1)), "the quadruped's bounds are not [-1, 1]"
        env.reset(seed=0)
        env.step(np.ones(env.action_space.shape, np.float32))
        np.testing.assert_allclose(env.physics.data.ctrl, high)
        closer_camera = env.physics.render(84, 84, camera_id=2).transpose(2, 0, 1)  # DrQ-v2's for the quadruped
        np.testing.assert_array_equal(env.pixels(), closer_camera)
    finally:
        env.close()


def test_bad_settings_are_refused():
    with pytest.raises(ValueError, match="no suite task 'cartpole' 'run'"):
        ControlEnv("cartpole", "run")
    with pytest.raises(ValueError, match="action_repeat must be a positive integer, got 0"):
        ControlEnv("cartpole", "swingup", action_repeat=0)
    with pytest.raises(ValueError, match="with_state must be True or False, got 'no'"):
        ControlEnv("cartpole", "swingup", with_state="no")
