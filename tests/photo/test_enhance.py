"""The enhancer's task l2r/PhotoEnhance-v0 on the real photos (the degradation hidden, seeded, split
by photo; the reward as the PSNR change to the original) and its baselines (l2r.photo.enhance,
`l2r photo enhance`) on a real crop."""

import json
import math

import gymnasium
from gymnasium.utils.env_checker import check_env
import numpy as np
import pytest

from l2r.learner.checkpoint import load_checkpoint
from l2r.photo import ENHANCE_ID, ENHANCE_IDS, ENHANCE_STATS_ID, enhance, photos, tune
from l2r.photo.env import PhotoEnhanceEnv, image_features, image_statistics
from l2r.photo.pipeline import finish, params_from_actions
from l2r.protocol.observations import ObservationSpec
from tests.photo.test_tune import l2r_photo, untrained_policy_checkpoint


@pytest.fixture(scope="module")
def env():
    """One env for the module: the first reset loads the photos (about a second)."""
    env = gymnasium.make(ENHANCE_ID)
    yield env.unwrapped
    env.close()


def psnr(image, original):
    return -10 * math.log10(np.mean((image.astype(np.float64) - original) ** 2))


def test_the_observation_shows_the_current_image_alone_never_the_original():
    spaces = {env_id: gymnasium.make(env_id).observation_space for env_id in ENHANCE_IDS}
    assert ObservationSpec.from_space(spaces[ENHANCE_ID]) == ObservationSpec.parse(
        "pixels: uint8[3, 64, 64], state: float32[13]")
    assert ObservationSpec.from_space(spaces[ENHANCE_STATS_ID]) == ObservationSpec.parse("state: float32[35]")
    for env_id in ENHANCE_IDS:
        task = gymnasium.make(env_id).unwrapped
        obs, _ = task.reset(seed=1)
        current = photos.downsample(task.source)[None]
        statistics = image_statistics(current) if env_id == ENHANCE_ID else image_features(current)
        np.testing.assert_allclose(obs["state"][:-10], statistics.ravel(), atol=1e-6)
        assert obs["state"][-10:].tolist() == [0.0] * 10  # neutral parameters, no step taken: not the degradation's
        # The same degraded crop with another original behind it looks the same.
        again, _ = task.reset(options={"source": task.source, "goal": np.zeros_like(task.goal)})
        for name in obs:
            np.testing.assert_array_equal(obs[name], again[name])
        check_env(task, skip_render_check=True)


def test_the_degradation_is_the_pipeline_with_hidden_parameters_and_repeats_with_its_seed(env):
    _, info = env.reset(seed=3)
    original, degraded, degradation = env.goal.copy(), env.source.copy(), env.degradation.copy()
    np.testing.assert_array_equal(degraded, finish(original[None], degradation)[0])
    assert info["psnr_db"] == pytest.approx(psnr(degraded, original))
    env.reset(seed=3)
    np.testing.assert_array_equal(env.source, degraded)
    np.testing.assert_array_equal(env.degradation, degradation)
    env.reset(seed=4)
    assert not np.array_equal(env.degradation, degradation)
    # The original is the photo's crop as it is: of a photo of the crop's size, all of it.
    side = photos.WORKING_SIZE
    photo = photos.load_photo("rocket")[:, :side, :side]
    whole = PhotoEnhanceEnv(sources={"rocket": photo})
    whole.reset(seed=0)
    np.testing.assert_array_equal(whole.goal, photo / np.float32(255))


def test_the_reward_is_the_psnr_change_to_the_original_times_a_hundredth(env):
    _, info = env.reset(seed=2)
    previous = psnr(env.source, env.goal)
    rng = np.random.default_rng(0)
    for step in range(1, 11):
        action = rng.uniform(-0.1, 0.1, 9).astype(np.float32)
        _, reward, terminated, truncated, info = env.step(action)
        now = psnr(finish(env.source[None], params_from_actions(action))[0], env.goal)
        assert reward == pytest.approx(0.01 * (now - previous), abs=1e-7)
        assert info["psnr_db"] == pytest.approx(now) and terminated == (step == 10) and not truncated
        previous = now


def test_each_split_degrades_only_its_own_photos():
    for split in ("train", "test"):
        split_env = PhotoEnhanceEnv(split=split)
        seen = {split_env.reset(seed=seed)[1]["photo"] for seed in range(12)}
        assert seen <= set(photos.SPLITS[split]) and len(seen) > 1, seen


def test_auto_levels_stretch_each_channel_and_the_baselines_score_by_hand():
    problem = tune.held_out_problems(1, seed=0, task=PhotoEnhanceEnv)[0]
    assert problem.name.split("@")[0] in photos.SPLITS["test"]
    levelled = enhance.auto_levels(problem.source)
    for channel, result in zip(problem.source, levelled):
        low, high = np.percentile(channel, (2, 98))
        np.testing.assert_allclose(result, np.clip((channel - low) / (high - low), 0, 1), atol=1e-6)
    # A uniform darkening and a colour cast are undone; what stays is what the percentiles cut.
    original = problem.goal
    cast = finish(original[None], params_from_actions(np.array([-0.2, 0.3, -0.2, 0.1, 0, 0, 0, 0, 0])))[0]
    np.testing.assert_allclose(enhance.auto_levels(cast), enhance.auto_levels(original), atol=1e-5)
    equalized = enhance.equalized(problem.source)
    assert all(abs(np.mean(channel <= 0.5) - 0.5) < 0.02 for channel in equalized)  # each channel's median at 0.5

    result = enhance.compare([problem])
    for name, image in (("input", problem.source), ("auto_levels", levelled), ("equalized", equalized)):
        assert result[f"{name}_psnr_db"] == pytest.approx(psnr(image, original), abs=1e-6), name
        assert result[f"{name}_ssim"] == pytest.approx(tune.ssim(image, original)), name
    assert result["policy_psnr_db"] is None and result["photos"] == 1


def test_enhance_json_is_one_line_with_every_method_and_the_policy_s_edits(tmp_path):
    checkpoint = untrained_policy_checkpoint(tmp_path / "best.pt", ENHANCE_STATS_ID)
    run = l2r_photo("enhance", "--photos", "1", "--seed", "2", "--checkpoint", str(checkpoint), "--json")
    assert run.returncode == 0, run.stderr
    [line] = run.stdout.splitlines()
    result = json.loads(line)
    problem = tune.held_out_problems(1, seed=2, task=PhotoEnhanceEnv)[0]
    assert result["problems"] == [problem.name] and result["photos"] == 1
    assert result["input_psnr_db"] == pytest.approx(psnr(problem.source, problem.goal))
    for name in ("auto_levels", "equalized", "policy"):
        assert isinstance(result[f"{name}_psnr_db"], float) and 0 < result[f"{name}_ssim"] < 1, name
    tuner = load_checkpoint(untrained_policy_checkpoint(tmp_path / "tuner.pt")).policy()  # it wants a goal shown
    with pytest.raises(ValueError, match=r"l2r/PhotoEnhanceStats-v0 gives \{state: float32\[35\]\}"):
        enhance.compare([problem], tuner)
