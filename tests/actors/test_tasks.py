"""An actor steps tasks other than the runner: gymnasium's own, with Box actions in other bounds,
and the camera tasks, by their ids alone; `l2r eval` tells a policy of other observations apart."""

import warnings

import numpy as np
import pytest
from gymnasium.wrappers import RescaleAction

from l2r.actors.__main__ import parse_settings
from l2r.actors.actor import ActorConfig, make_env, observation_spec
from l2r.config import UsageError
from l2r.evaluate import WrongTask, evaluate
from l2r.evaluate import cli as eval_cli
from l2r.learner.td3 import TD3Config, init_state
from l2r.policy import build_policy
from l2r.protocol import ObservationSpec
from l2r.sim.randomize import Randomization
from l2r.sim.wrappers import ActionNoise, ActionRepeat, ObservationNoise
from tests.actors.camera import CAMERA, RENDERER

DMC_CARTPOLE = "l2r/dmc-cartpole-swingup-v0"


def test_another_task_takes_the_policy_s_excitations_rescaled_to_its_action_bounds():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # gymnasium warned of bounds rescaled in float64
        env = make_env(ActorConfig(env_id="Hopper-v5", action_repeat=1), seed=0)
    assert (env.action_space.low.tolist(), env.action_space.high.tolist()) == ([0.0] * 3, [1.0] * 3)
    assert env.action_space.dtype == np.float32
    np.testing.assert_allclose(env.action(np.array([0.0, 0.5, 1.0], np.float32)), [-1.0, 0.0, 1.0])
    obs, _ = env.reset(seed=0)
    assert obs.shape == (11,) and env.step(np.full(3, 0.5, np.float32))[0].shape == (11,)


def test_the_runner_takes_its_difficulty_and_seed_and_keeps_its_excitations():
    env = make_env(ActorConfig(env_id="l2r/Run-v0", action_repeat=1, difficulty=2), seed=5)
    assert env.unwrapped.difficulty == 2
    assert (env.action_space.low.min(), env.action_space.high.max()) == (0.0, 1.0)
    assert not isinstance(env, RescaleAction)


@pytest.mark.skipif(not RENDERER, reason="no EGL or OSMesa to render with")
def test_a_camera_task_is_known_by_its_id_and_declares_its_frames():
    env = make_env(ActorConfig(env_id="l2r/dmc-cartpole-swingup-v0", action_repeat=1), seed=0)
    try:
        assert observation_spec(env, "l2r/dmc-cartpole-swingup-v0") == ObservationSpec.parse("pixels: uint8[3, 84, 84]")
        assert (env.action_space.low.tolist(), env.action_space.high.tolist()) == ([0.0], [1.0])
    finally:
        env.close()


@pytest.mark.skipif(not RENDERER, reason="no EGL or OSMesa to render with")
def test_a_camera_task_renders_frames_of_the_size_asked_and_l2r_eval_the_size_its_policy_was_trained_on():
    env = make_env(ActorConfig(env_id=DMC_CARTPOLE, action_repeat=1, image_size=20), seed=0)
    try:
        assert observation_spec(env, DMC_CARTPOLE) == ObservationSpec.parse("pixels: uint8[3, 20, 20]")
        frame = env.reset(seed=0)[0]["pixels"]
        assert frame.shape == (3, 20, 20) and frame.std() > 0  # a rendered picture, not a blank
    finally:
        env.close()
    # A policy of 16-pixel frames and 2 actions: l2r eval renders its frames' size (the actions
    # tell it from the task, refused before an episode is stepped).
    observation = ObservationSpec.parse("pixels: uint8[3, 16, 16]")
    policy = init_state(TD3Config(hidden=(8,), frame_stack=1), observation, 2, seed=0).actor
    with pytest.raises(WrongTask, match=r"l2r/dmc-cartpole-swingup-v0 gives \{pixels: uint8\[3, 16, 16\]\} and takes 1"):
        evaluate(policy, episodes=1, seed=0, difficulty=0, action_repeat=1, env_id=DMC_CARTPOLE)
    with pytest.raises(ValueError, match="an image size is for the camera tasks"):
        make_env(ActorConfig(env_id="Hopper-v5", image_size=20), seed=0)
    with pytest.raises(UsageError, match="--image-size 20: an image size is for the camera tasks"):
        parse_settings(["--env-id", "Hopper-v5", "--image-size", "20"])


def test_the_photo_tuner_draws_the_goals_asked_for_training_and_l2r_eval():
    env = make_env(ActorConfig(env_id="l2r/PhotoTuneStats-v0", action_repeat=1, photo_goals="looks"), seed=0)
    try:
        assert env.reset(seed=0)[1]["look"] is not None  # another scene's look, not a random edit
    finally:
        env.close()
    policy = init_state(TD3Config(hidden=(8,)), 60, 9, seed=0).actor  # the statistics view: 60 values, 9 actions
    (result,) = evaluate(policy, episodes=1, seed=0, difficulty=0, action_repeat=1, env_id="l2r/PhotoTuneStats-v0",
                         photo_goals="looks")
    random_goal = evaluate(policy, episodes=1, seed=0, difficulty=0, action_repeat=1, env_id="l2r/PhotoTuneStats-v0")
    assert result.psnr_db != random_goal[0].psnr_db  # another goal for the same seed
    assert eval_cli(["runs/none", "--env-id", "Hopper-v5", "--photo-goals", "looks"]) == 2


@pytest.mark.skipif(not RENDERER, reason="no EGL or OSMesa to render with")
def test_l2r_eval_refuses_a_vector_policy_on_a_camera_task_naming_both_observations():
    policy = build_policy({"obs_dim": 41, "act_dim": 1, "hidden": [8], "activation": "elu", "layer_norm": False})
    with pytest.raises(WrongTask, match=r"the policy takes observations \{state: float32\[41\]\} and gives 1 "
                                        r"actions, tests.actors.camera:SmallCamera-v0 gives \{pixels: uint8\[3, 16, 16\]\}"):
        evaluate(policy, episodes=1, seed=0, difficulty=0, action_repeat=1, env_id=CAMERA)


def wrapper_types(env):
    """The types of the wrappers around an env, outermost first."""
    types = []
    while hasattr(env, "env"):
        types.append(type(env))
        env = env.env
    return types


def test_the_runner_takes_the_robustness_levers_configured_and_only_those():
    plain = make_env(ActorConfig(env_id="l2r/Run-v0", action_repeat=3), seed=0)
    assert not plain.unwrapped.randomize
    assert not {ObservationNoise, ActionNoise} & set(wrapper_types(plain))
    config = ActorConfig(env_id="l2r/Run-v0", action_repeat=3, randomize=Randomization(mass=0.1),
                         observation_noise=0.01, action_noise=0.02)
    env = make_env(config, seed=0)
    assert env.unwrapped.randomize == Randomization(mass=0.1)
    assert wrapper_types(env)[:3] == [ActionRepeat, ObservationNoise, ActionNoise]
    assert (env.env.noise.std, env.env.env.noise.std) == (0.01, 0.02)
    with pytest.raises(ValueError, match="randomisation is l2r/Run-v0 and l2r/RunWarp-v0's, not l2r/RunOpenSim-v0's"):
        make_env(ActorConfig(env_id="l2r/RunOpenSim-v0", randomize=Randomization(mass=0.1)), seed=0)
