"""l2r/PhotoTune-v0 on the real photos: spaces against the observation spec, the reward as the PSNR
change, early ends, the split, seeding, bad actions."""

import math

import gymnasium
from gymnasium.utils.env_checker import check_env
import numpy as np
import pytest

import l2r.photo.env  # registers the id (l2r.photo)
from l2r.photo import photos
from l2r.photo.env import (collapsed, comparison_features, detail, detail_features, image_features, image_statistics,
                           psnr_db, transfer_look)
from l2r.photo.pipeline import actions_from_params, finish, params_from_actions
from l2r.protocol.observations import ObservationSpec

DARKEN = np.array([-1, -1, -1, -1, 0, 1, -1, -1, 1], np.float32)
"""-2 EV, the smallest gains, most contrast, highlights and shadows down."""


@pytest.fixture(scope="module")
def env():
    """One env for the module: the first reset loads the photos (about a second)."""
    env = gymnasium.make("l2r/PhotoTune-v0")
    yield env.unwrapped
    env.close()


def psnr(image, goal):
    return -10 * math.log10(np.mean((image.astype(np.float64) - goal) ** 2))


def test_spaces_follow_the_observation_spec(env):
    spec = ObservationSpec.from_space(env.observation_space)
    # In gymnasium's order of a Dict's keys, sorted.
    assert spec == ObservationSpec.parse("goal: uint8[3, 64, 64], pixels: uint8[3, 64, 64], state: float32[16]")
    assert env.action_space == gymnasium.spaces.Box(-1.0, 1.0, (9,), np.float32)
    obs, _ = env.reset(seed=0)
    spec.fields_of(obs)  # raises unless each field has its dtype and shape
    check_env(env, skip_render_check=True)


def test_the_observation_shows_both_images_their_statistics_and_the_parameters(env):
    obs, _ = env.reset(seed=1)
    np.testing.assert_array_equal(obs["pixels"], photos.to_uint8(photos.downsample(env.source)))
    np.testing.assert_array_equal(obs["goal"], photos.to_uint8(photos.downsample(env.goal)))
    small = photos.downsample(np.stack([env.source, env.goal]))
    np.testing.assert_allclose(obs["state"][:6], image_statistics(small).ravel(), atol=1e-6)
    assert obs["state"][6:].tolist() == [0.0] * 10  # neutral parameters, no step taken
    action = np.linspace(-0.9, 0.9, 9, dtype=np.float32)
    obs, *_ = env.step(action)
    np.testing.assert_allclose(obs["state"][6:15], action, atol=1e-5)
    assert obs["state"][15] == pytest.approx(0.1)


def test_image_statistics_by_hand():
    image = np.zeros((1, 3, 2, 2), np.float32)
    image[0, 0] = 1.0  # pure red: luminance 0.27 everywhere, HSL saturation 1 / 1.01
    assert image_statistics(image)[0].tolist() == pytest.approx([0.27, 0.0, 1 / 1.01], abs=1e-6)
    image[0, :, 0, 0] = 1.0  # one white pixel of four
    assert image_statistics(image)[0, :2].tolist() == pytest.approx([0.4525, 3 * 0.1825 ** 2 / 4 + 0.5475 ** 2 / 4])


def test_image_features_by_hand():
    image = np.full((1, 3, 4, 4), 0.5, np.float32)
    image[0, 0] = 0.25  # a flat image: no spread, every percentile its value, one histogram bin, no edges
    features = image_features(image)[0]
    assert features.shape == (25,)
    assert features[:15].tolist() == pytest.approx([0.25, 0, 0.25, 0.25, 0.25] + [0.5, 0, 0.5, 0.5, 0.5] * 2)
    luminance = 0.27 * 0.25 + 0.67 * 0.5 + 0.06 * 0.5  # 0.4325: bin 3 of 8
    assert features[15:23].tolist() == [0, 0, 0, 1, 0, 0, 0, 0]
    assert features[23] == pytest.approx(image_statistics(image)[0, 2]) and features[24] == 0.0
    image[0, :, 1, 1] = 1.0  # a white dot on one of the four inner pixels: 4 (1 - L) there, 1 - L at two neighbours
    assert image_features(image)[0, 24] == pytest.approx(6 * (1 - luminance) / 4, abs=1e-6)


def test_the_statistics_view_observes_both_images_features_and_the_parameters():
    stats = gymnasium.make("l2r/PhotoTuneStats-v0").unwrapped
    assert ObservationSpec.from_space(stats.observation_space) == ObservationSpec.parse("state: float32[60]")
    obs, _ = stats.reset(seed=1)
    small = photos.downsample(np.stack([stats.source, stats.goal]))
    np.testing.assert_allclose(obs["state"][:50], image_features(small).ravel(), atol=1e-6)
    assert obs["state"][50:].tolist() == [0.0] * 10
    action = np.linspace(-0.9, 0.9, 9, dtype=np.float32)
    obs, *_ = stats.step(action)
    np.testing.assert_allclose(obs["state"][50:59], action, atol=1e-5)
    assert obs["state"][59] == pytest.approx(0.1)
    check_env(stats, skip_render_check=True)
    with pytest.raises(ValueError, match="view must be one of images, statistics"):
        gymnasium.make("l2r/PhotoTune-v0", view="histograms")


def test_comparison_features_by_hand():
    image = np.zeros((1, 3, 1, 2), np.float32)
    image[0, :, 0, 0] = [0.05, 0.02, 0.0]  # tone bin 0 (value 0.05), chroma 0.05
    image[0, :, 0, 1] = [0.9, 0.95, 0.6]  # tone bin 7 (value 0.95), chroma 0.35
    goal = image.copy()
    goal[0, :, 0, 1] = [0.5, 0.95, 0.6]  # the bright pixel loses red; the dark one is as it was
    features = comparison_features(image, goal)[0].reshape(8, 5)
    assert features[:, 0].tolist() == [0.5, 0, 0, 0, 0, 0, 0, 0.5]
    assert features[1:7].tolist() == [[0.0] * 5] * 6 and features[0, 1:].tolist() == [0.0] * 4
    ratios = [np.log(0.52 / 0.92), 0.0, 0.0, np.log(0.47 / 0.37)]  # (goal + 0.02) / (image + 0.02): R, G, B, chroma
    assert features[7].tolist() == pytest.approx([0.5] + [0.25 * x for x in ratios], abs=1e-6)


def test_comparison_features_tell_which_way_each_colour_moved():
    rng = np.random.default_rng(0)
    image = rng.uniform(0.05, 0.45, (1, 3, 16, 16)).astype(np.float32)
    assert np.all(comparison_features(image, image)[0].reshape(8, 5)[:, 1:] == 0)
    warmer = image * np.array([1.3, 1.0, 0.8], np.float32).reshape(1, 3, 1, 1)
    ratios = comparison_features(image, warmer)[0].reshape(8, 5)
    occupied = ratios[:, 0] > 0
    assert np.all(ratios[occupied, 1] > 0) and np.all(ratios[occupied, 2] == 0) and np.all(ratios[occupied, 3] < 0)
    brighter = comparison_features(image, image * 2)[0].reshape(8, 5)
    assert np.all(brighter[occupied, 1:] > 0) and np.all(np.abs(brighter[:, 1:]) <= 1)


def side_by_side(wider, narrower):
    """A view and one it extends, from the same seed and actions: after the reset and after a step,
    the wider's `state` and info, and the narrower's `state`."""
    action = np.linspace(-0.9, 0.9, 9, dtype=np.float32)
    (seen, info), (without, _) = wider.reset(seed=3), narrower.reset(seed=3)
    for _ in range(2):
        yield seen["state"], info, without["state"]
        (seen, _, _, _, info), (without, *_) = wider.step(action), narrower.step(action)


def test_the_comparison_view_observes_the_statistics_and_the_pair_compared():
    compare = gymnasium.make("l2r/PhotoTuneCompare-v0").unwrapped
    stats = gymnasium.make("l2r/PhotoTuneStats-v0").unwrapped
    assert ObservationSpec.from_space(compare.observation_space) == ObservationSpec.parse("state: float32[100]")
    for seen, info, statistics in side_by_side(compare, stats):
        current, goal = photos.downsample(np.stack([compare.image, compare.goal]))
        np.testing.assert_array_equal(seen[:50], statistics[:50])
        np.testing.assert_allclose(seen[50:90], comparison_features(current[None], goal[None])[0], atol=1e-6)
        np.testing.assert_array_equal(seen[90:], statistics[50:])
        # The episode log's frames are the images the observation was made of, after each step as after reset.
        assert set(info["frames"]) == {"pixels", "goal"}
        np.testing.assert_array_equal(info["frames"]["pixels"], photos.to_uint8(current))
        np.testing.assert_array_equal(info["frames"]["goal"], photos.to_uint8(goal))
    check_env(compare, skip_render_check=True)
    with pytest.raises(ValueError, match="compares the image with a goal the task does not show"):
        gymnasium.make("l2r/PhotoEnhance-v0", view="comparison")


def test_detail_by_hand():
    # A white line down column 1 of a black 8 x 8 image. Full resolution, of the 6 x 6 inner
    # Laplacians the line's are |4 - 1 - 1 - 0 - 0| = 2 and its right neighbours' |0 - 1| = 1:
    # (6 x 2 + 6 x 1) / 36. Half (2 x 2 means, column 0 at 0.5): of the 2 x 2 inner ones, column 1's
    # are |0 - 0.5|: 2 x 0.5 / 4.
    image = np.zeros((1, 3, 8, 8), np.float32)
    image[:, :, :, 1] = 1.0
    assert detail(image)[0].tolist() == pytest.approx([0.5, 0.25])
    checker = np.zeros((1, 3, 8, 8), np.float32)
    checker[..., ::2, ::2] = checker[..., 1::2, 1::2] = 1.0  # the finest detail there is: gone at half resolution
    assert detail(checker)[0].tolist() == pytest.approx([4.0, 0.0])
    features = detail_features(np.array([[0.1, 0.2]]), np.array([[0.2, 0.2]]))
    assert features.dtype == np.float32
    assert features[0].tolist() == pytest.approx([0.25 * np.log(0.201 / 0.101), np.log(0.201 / 0.101) - 0.0])
    assert detail_features(np.array([[0.0, 0.1]]), np.array([[1.0, 0.1]]))[0].tolist() == [1.0, 1.0]  # clipped


def test_sharpening_shows_in_the_detail_of_the_working_images_alone(env):
    env.reset(seed=4)
    crop = env.source[None]
    neutral, sharp = (finish(crop, params_from_actions(np.array([0] * 8 + [k], np.float32))) for k in (0, 1))
    brighter = finish(crop, params_from_actions(np.array([0.5] + [0] * 8, np.float32)))
    # What the 64-pixel images see of it: nearly nothing, against an exposure change.
    small = image_features(photos.downsample(np.concatenate([neutral, sharp, brighter])))
    assert np.abs(small[1] - small[0]).max() < 0.2 * np.abs(small[2] - small[0]).max()
    finer = detail_features(detail(neutral), detail(sharp))[0]
    assert finer[0] > 0.05 and finer[1] > 0.1
    brighter_detail = detail_features(detail(neutral), detail(brighter))[0]
    assert brighter_detail[0] > 0.05 and abs(brighter_detail[1]) < 0.25 * finer[1]


def test_the_detail_view_adds_the_working_images_detail_compared():
    plain = gymnasium.make("l2r/PhotoTuneCompare-v0").unwrapped
    finer = gymnasium.make("l2r/PhotoTuneCompareDetail-v0").unwrapped
    assert ObservationSpec.from_space(finer.observation_space) == ObservationSpec.parse("state: float32[102]")
    for seen, _, without in side_by_side(finer, plain):
        np.testing.assert_array_equal(seen[:90], without[:90])
        np.testing.assert_allclose(seen[90:92], detail_features(detail(finer.image[None]), detail(finer.goal[None]))[0],
                                   atol=1e-6)
        np.testing.assert_array_equal(seen[92:], without[90:])
    check_env(finer, skip_render_check=True)
    for view, given in (("statistics", True), ("comparison", 1)):
        with pytest.raises(ValueError, match="detail must be true or false, and true with view 'comparison' alone"):
            gymnasium.make("l2r/PhotoTune-v0", view=view, detail=given)


def test_the_reward_is_the_psnr_change_times_a_hundredth(env):
    _, info = env.reset(seed=2)
    previous = psnr(env.source, env.goal)
    assert info["psnr_db"] == pytest.approx(previous)
    rng = np.random.default_rng(0)
    for _ in range(4):
        action = rng.uniform(-0.5, 0.5, 9).astype(np.float32)
        _, reward, terminated, truncated, info = env.step(action)
        now = psnr(finish(env.source[None], params_from_actions(action))[0], env.goal)
        assert reward == pytest.approx(0.01 * (now - previous), abs=1e-7)
        assert info["psnr_db"] == pytest.approx(now) and not terminated and not truncated
        previous = now


def test_the_hidden_parameters_reach_the_goal(env):
    env.reset(seed=3)
    _, reward, *_, info = env.step(actions_from_params(env.goal_params))
    assert info["psnr_db"] == 100.0 and reward > 0  # capped: the image is the goal
    assert psnr_db(np.zeros((1, 3, 2, 2)), np.ones((1, 3, 2, 2))).tolist() == [0.0]


def test_varied_sources_are_other_inputs_whose_goals_the_hidden_parameters_still_reach():
    plain = gymnasium.make("l2r/PhotoTune-v0").unwrapped
    none = gymnasium.make("l2r/PhotoTune-v0", source_variety=0.0).unwrapped
    varied = gymnasium.make("l2r/PhotoTune-v0", source_variety=0.5).unwrapped
    flipped = 0
    for seed in range(8):
        plain.reset(seed=seed), none.reset(seed=seed), varied.reset(seed=seed)
        np.testing.assert_array_equal(none.source, plain.source)  # 0: the photo's own crop, as before
        np.testing.assert_array_equal(none.goal, plain.goal)
        # The same photo and crop are drawn first; the input is then flipped or refinished.
        assert varied.photo_name == plain.photo_name and not np.allclose(varied.source, plain.source)
        np.testing.assert_array_equal(finish(varied.source[None], varied.goal_params)[0], varied.goal)
        # A flip shows in the edges: the varied input's left column is then the crop's right one, refinished.
        left, right = (np.corrcoef(varied.source[:, :, 0].ravel(), plain.source[:, :, col].ravel())[0, 1]
                       for col in (0, -1))
        flipped += right > left
        again = varied.source.copy()
        varied.reset(seed=seed)
        np.testing.assert_array_equal(varied.source, again)
    assert 2 <= flipped <= 6  # even odds over 8 seeds
    for bad in (-0.1, 1.5, True, "0.5"):
        with pytest.raises(ValueError, match="source_variety must be a number in"):
            gymnasium.make("l2r/PhotoTune-v0", source_variety=bad)


def test_an_episode_is_ten_queries(env):
    env.reset(seed=4)
    for step in range(1, 11):
        _, _, terminated, truncated, info = env.step(np.zeros(9, np.float32))
        assert terminated == (step == 10) and not truncated and not info["collapsed"]
    with pytest.raises(RuntimeError, match="call reset"):
        env.step(np.zeros(9, np.float32))


def test_a_collapsed_image_ends_the_episode_early(env):
    env.reset(seed=5)
    _, reward, terminated, _, info = env.step(DARKEN)
    assert terminated and info["collapsed"] and reward < 0
    assert env.image.mean() < 0.01
    with pytest.raises(RuntimeError, match="call reset"):
        env.step(np.zeros(9, np.float32))
    assert collapsed(np.full((3, 2, 2), 0.009)) and collapsed(np.full((3, 2, 2), 0.91))
    assert not collapsed(np.full((3, 2, 2), 0.011)) and not collapsed(np.full((3, 2, 2), 0.89))


def test_goals_and_inputs_are_never_collapsed_themselves(env):
    for seed in range(20):
        env.reset(seed=seed)
        assert not collapsed(env.source) and not collapsed(env.goal)


def test_each_split_draws_only_its_own_photos():
    seen = {}
    for split in ("train", "test"):
        split_env = gymnasium.make("l2r/PhotoTune-v0", split=split)
        seen[split] = {split_env.reset(seed=seed)[1]["photo"] for seed in range(12)}
        split_env.close()
        assert seen[split] <= set(photos.SPLITS[split]) and len(seen[split]) > 1
    with pytest.raises(ValueError, match="split must be one of"):
        gymnasium.make("l2r/PhotoTune-v0", split="val")


def test_the_same_seed_gives_the_same_episode(env):
    def episode(seed):
        obs, _ = env.reset(seed=seed)
        frames, rewards = [obs], []
        for action in np.random.default_rng(7).uniform(-1, 1, (3, 9)).astype(np.float32):
            obs, reward, *_ = env.step(action)
            frames.append(obs)
            rewards.append(reward)
        return frames, rewards

    (first, first_rewards), (again, again_rewards) = episode(11), episode(11)
    assert first_rewards == again_rewards
    for a, b in zip(first, again):
        for name in a:
            np.testing.assert_array_equal(a[name], b[name])
    other, _ = episode(12)
    assert not np.array_equal(first[0]["goal"], other[0]["goal"])


def test_bad_actions_are_refused_in_words(env):
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(3,\), expected \(9,\)"):
        env.step(np.zeros(3))
    with pytest.raises(ValueError, match="non-finite"):
        env.step(np.full(9, np.nan))
    with pytest.raises(ValueError, match="max_steps must be a positive integer"):
        gymnasium.make("l2r/PhotoTune-v0", max_steps=0)


def test_a_given_source_and_goal_replace_the_draw(env):
    rng = np.random.default_rng(0)
    source = photos.random_crop(photos.load_photo("coffee"), rng)
    goal = finish(source[None], params_from_actions(DARKEN * 0.3))[0]
    obs, info = env.reset(seed=1, options={"source": source, "goal": goal})
    assert info["photo"] == "given" and info["psnr_db"] == pytest.approx(psnr(source, goal), abs=1e-3)
    np.testing.assert_array_equal(obs["goal"], photos.to_uint8(photos.downsample(goal)))
    _, _, _, _, info = env.step(DARKEN * 0.3)
    assert info["psnr_db"] == 100.0  # the goal's own parameters reach it exactly
    with pytest.raises(ValueError, match=r"reset option 'goal' must be a finite float image \[3, 256, 256\]"):
        env.reset(options={"source": source, "goal": goal[:, :64, :64]})


def test_photos_given_to_the_env_are_the_ones_it_crops():
    photo = photos.load_photo("rocket")
    given = l2r.photo.env.PhotoTuneEnv(sources={"mine": photo})
    assert {given.reset(seed=seed)[1]["photo"] for seed in range(3)} == {"mine"}
    with pytest.raises(ValueError, match="sources holds no photo"):
        l2r.photo.env.PhotoTuneEnv(sources={})


def lab_statistics(image):
    from skimage.color import rgb2lab

    lab = rgb2lab(np.moveaxis(image, 0, -1))
    return lab.mean(axis=(0, 1)), lab.std(axis=(0, 1))


def test_a_transferred_look_takes_the_reference_s_colour_statistics_and_keeps_the_image_s_shapes():
    rng = np.random.default_rng(5)
    image, reference = (photos.random_crop(photos.load_photo(name), rng) for name in ("coffee", "chelsea"))
    graded = transfer_look(image, reference)
    assert graded.dtype == np.float32 and graded.shape == image.shape and 0.0 <= graded.min() <= graded.max() <= 1.0
    (mean, std), (reference_mean, reference_std) = lab_statistics(graded), lab_statistics(reference)
    np.testing.assert_allclose(mean, reference_mean, atol=1.0)  # (L in 0-100; clipping to RGB moves it a little)
    np.testing.assert_allclose(std, reference_std, rtol=0.1)
    assert np.abs(mean - lab_statistics(image)[0]).max() > 5.0  # a look other than the image's own
    luminance = [x.mean(axis=0).ravel() for x in (image, graded)]
    assert np.corrcoef(*luminance)[0, 1] > 0.9  # the same picture
    np.testing.assert_allclose(transfer_look(image, image), image, atol=1e-4)


def test_goals_of_looks_come_from_another_scene_of_the_split_and_repeat_with_the_seed():
    looks = gymnasium.make("l2r/PhotoTune-v0", split="test", goals="looks").unwrapped
    seen = set()
    for seed in range(12):
        _, info = looks.reset(seed=seed)
        assert info["look"] in photos.SPLITS["test"] and photos.scene(info["look"]) != photos.scene(info["photo"])
        assert looks.goal_params is None and not collapsed(looks.goal)
        seen.add((info["photo"], info["look"]))
        _, again = looks.reset(seed=seed)
        assert again["look"] == info["look"]
    assert len(seen) > 2
    first = looks.reset(seed=3)[0]["goal"]
    np.testing.assert_array_equal(looks.reset(seed=3)[0]["goal"], first)
    assert gymnasium.make("l2r/PhotoTune-v0").reset(seed=0)[1]["look"] is None  # random goals by default


def test_mixed_goals_draw_either_kind_by_the_episode_s_seed():
    mixed = gymnasium.make("l2r/PhotoTune-v0", split="test", goals="mixed").unwrapped
    kinds = []
    for seed in range(16):
        _, info = mixed.reset(seed=seed)
        kinds.append(info["look"] is not None)
        assert (mixed.goal_params is None) == kinds[-1]  # a look, or an edit with known parameters
        assert (mixed.reset(seed=seed)[1]["look"] is not None) == kinds[-1]
    assert 4 <= sum(kinds) <= 12, kinds


def test_looks_are_refused_without_a_second_scene_or_for_the_enhancer():
    pair = {name: photos.load_photo(name) for name in ("motorcycle_left", "motorcycle_right")}  # one scene
    with pytest.raises(ValueError, match="goals='looks' needs photos of two scenes at least"):
        l2r.photo.env.PhotoTuneEnv(sources=pair, goals="looks").reset(seed=0)
    with pytest.raises(ValueError, match="goals must be one of random, looks, mixed, got 'expert'"):
        gymnasium.make("l2r/PhotoTune-v0", goals="expert")
    with pytest.raises(ValueError, match="goals must be one of random, got 'looks'"):
        gymnasium.make("l2r/PhotoEnhance-v0", goals="looks")
