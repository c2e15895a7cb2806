"""The photo-finishing pipeline, filter by filter, against pixels worked out by hand."""

import math

import numpy as np
import pytest

from l2r.photo import pipeline
from l2r.photo.pipeline import NEUTRAL, finish


def pixel(r, g, b):
    """One RGB pixel as a [1, 3, 1, 1] image."""
    return np.array([r, g, b], np.float32).reshape(1, 3, 1, 1)


def rgb(image):
    return image.reshape(3).tolist()


def sigmoid(x):
    return 1.0 / (1.0 + math.exp(-x))


def test_exposure_doubles_per_ev():
    assert rgb(pipeline.exposure(pixel(0.25, 0.1, 0.4), [1.0])) == pytest.approx([0.5, 0.2, 0.8])
    assert rgb(pipeline.exposure(pixel(0.5, 0.5, 0.5), [-2.0])) == pytest.approx([0.125] * 3)


def test_white_balance_scales_each_channel():
    out = pipeline.white_balance(pixel(0.5, 0.5, 0.5), [[math.exp(0.5), 1.0, math.exp(-0.5)]])
    assert rgb(out) == pytest.approx([0.5 * 1.648721, 0.5, 0.5 * 0.606531], abs=1e-6)


def test_saturation_blends_with_the_gray():
    gray = 0.2989 * 0.6 + 0.587 * 0.4 + 0.114 * 0.2  # 0.43694
    assert rgb(pipeline.saturation(pixel(0.6, 0.4, 0.2), [-1.0])) == pytest.approx([0.43694] * 3, abs=1e-6)
    assert rgb(pipeline.saturation(pixel(0.6, 0.4, 0.2), [0.5])) == pytest.approx(
        [0.9 - 0.5 * gray, 0.6 - 0.5 * gray, 0.3 - 0.5 * gray], abs=1e-6)  # 0.68153, 0.38153, 0.08153


def test_contrast_moves_luminance_along_the_cosine_curve():
    curved = 0.5 - 0.5 * math.cos(math.pi * 0.25)  # 0.146447: a quarter gray, darker
    assert rgb(pipeline.contrast(pixel(0.25, 0.25, 0.25), [1.0])) == pytest.approx([curved] * 3, abs=1e-5)
    assert rgb(pipeline.contrast(pixel(0.25, 0.25, 0.25), [-1.0])) == pytest.approx([0.5 - curved] * 3, abs=1e-5)
    assert rgb(pipeline.contrast(pixel(0.5, 0.5, 0.5), [1.0])) == pytest.approx([0.5] * 3, abs=1e-5)  # the fixed point


def test_highlights_lift_or_lower_the_value_near_white():
    mask = sigmoid(13 * (0.9 - 1))  # 0.214165
    lowered = 1 - 0.1 * (1 + 13 * mask)  # 0.621585
    assert rgb(pipeline.highlights(pixel(0.9, 0.45, 0.0), [-1.0])) == pytest.approx(
        [lowered, lowered / 2, 0.0], abs=1e-6)
    # 1 - 0.1 (1 - 13 m) = 1.178 is clipped to a value of 1: hue and saturation kept.
    assert rgb(pipeline.highlights(pixel(0.9, 0.45, 0.0), [1.0])) == pytest.approx([1.0, 0.5, 0.0], abs=1e-6)


def test_shadows_lift_or_crush_the_value_near_black():
    mask = 1 - sigmoid(12 * 0.1)  # 0.231475
    lifted = 0.1 * (1 + 12 * mask)  # 0.377770
    assert rgb(pipeline.shadows(pixel(0.1, 0.05, 0.0), [1.0])) == pytest.approx([lifted, lifted / 2, 0.0], abs=1e-6)
    assert rgb(pipeline.shadows(pixel(0.1, 0.05, 0.0), [-1.0])) == pytest.approx([0.0, 0.0, 0.0])
    assert rgb(pipeline.shadows(pixel(0.0, 0.0, 0.0), [1.0])) == [0.0, 0.0, 0.0]


def test_sharpening_blends_with_the_3x3_blur_inside_the_border():
    dot = np.zeros((1, 3, 3, 3), np.float32)
    dot[..., 1, 1] = 1.0  # blurred: the centre keeps 5/13, each neighbour gets 1/13
    blurred = pipeline.sharpen(dot, [0.0])
    assert blurred[0, :, 1, 1] == pytest.approx([5 / 13] * 3)
    assert (blurred[..., 0, :] == 0).all() and (blurred[..., :, 0] == 0).all()  # the border is the image's own
    assert pipeline.sharpen(dot, [2.0])[0, :, 1, 1] == pytest.approx([2 - 5 / 13] * 3)
    corner = np.zeros((1, 3, 3, 3), np.float32)
    corner[..., 0, 0] = 1.0
    assert pipeline.sharpen(corner, [0.0])[0, :, 1, 1] == pytest.approx([1 / 13] * 3)
    assert pipeline.sharpen(corner, [0.0])[0, :, 0, 0] == pytest.approx([1.0] * 3)


def test_neutral_parameters_leave_images_as_they_are():
    images = np.random.default_rng(0).random((4, 3, 16, 16), dtype=np.float32)
    np.testing.assert_allclose(finish(images, NEUTRAL), images, atol=1e-6)
    np.testing.assert_array_equal(pipeline.params_from_actions(np.zeros(9)), NEUTRAL)


def test_actions_map_onto_each_range_and_back():
    params = pipeline.params_from_actions(np.stack([-np.ones(9), np.ones(9)]))
    assert params[0].tolist() == pytest.approx([p.low for p in pipeline.PARAMETERS], abs=1e-6)
    assert params[1].tolist() == pytest.approx([p.high for p in pipeline.PARAMETERS], abs=1e-6)
    assert pipeline.params_from_actions(np.full(9, 5.0)).tolist() == pytest.approx(params[1].tolist())  # clipped
    actions = np.random.default_rng(1).uniform(-1, 1, (5, 9)).astype(np.float32)
    np.testing.assert_allclose(pipeline.actions_from_params(pipeline.params_from_actions(actions)), actions, atol=1e-5)


def test_filters_run_in_order_each_clipped():
    # +1 EV clips 0.8 to 1 before the red gain e^-0.5 scales it: 0.6065, not 0.8 * 2 * 0.6065.
    params = NEUTRAL.copy()
    params[0], params[1] = 1.0, math.exp(-0.5)
    assert finish(pixel(0.8, 0.2, 0.2), params)[0, :, 0, 0].tolist() == pytest.approx([0.606531, 0.4, 0.4], abs=1e-6)


def test_each_image_of_a_batch_gets_its_own_parameters():
    rng = np.random.default_rng(2)
    images = rng.random((3, 3, 8, 8), dtype=np.float32)
    params = pipeline.params_from_actions(rng.uniform(-1, 1, (3, 9)))
    batch = finish(images, params)
    for i in range(3):
        np.testing.assert_array_equal(batch[i], finish(images[i:i + 1], params[i])[0])
    assert batch.dtype == np.float32 and 0 <= batch.min() and batch.max() <= 1
    np.testing.assert_array_equal(finish(images, params), batch)  # deterministic


def test_images_of_another_shape_are_refused():
    with pytest.raises(ValueError, match=r"\[N, 3, H, W\]"):
        finish(np.zeros((3, 8, 8), np.float32), NEUTRAL)
