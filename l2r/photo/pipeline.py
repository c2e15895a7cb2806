"""The photo-finishing pipeline a tuner drives: RLPixTuner's seven filters and nine parameters.

RLPixTuner (Wu et al., "Goal Conditioned Reinforcement Learning for Photo Finishing Tuning",
NeurIPS 2024; github.com/OpenImagingLab/RLPixTuner) tunes a pipeline of seven filters, in this
order (its `envs/run_sb3.py`, pipeline `exp_wb_sat_chs_sharp`), each defined in its
`isp/filters.py`, ranges from its `config.py`:

1. exposure `ExposureFilter`: x * 2^ev, ev in [-2, 2] (`cfg.exposure_range = 2.0`).
2. white balance `ImprovedWhiteBalanceFilter`: each channel times its gain, gains in
   [e^-0.5, e^0.5] (`log_wb_range = 0.5`).
3. saturation `SaturationFilter`: torchvision's `adjust_saturation` with factor 1 + s, s in
   [-1, 1]: a blend (1 + s) x - s gray, gray = 0.2989 R + 0.587 G + 0.114 B.
4. contrast `ContrastFilter`: with L = 0.27 R + 0.67 G + 0.06 B clipped to [0, 1], the image
   scaled to the luminance (1 - cos(pi L)) / 2, x / (L + 1e-6) * that, and blended in by c in
   [-1, 1] (c < 0 flattens).
5. highlights `HighlightFilter`: the HSV value V = max(R, G, B) becomes
   1 - (1 - V)(1 - 13 h m), m = sigmoid(13 (V - 1)), clipped to [0, 1], h in [-1, 1].
6. shadows `ShadowFilter`: V becomes V (1 + 12 s m), m = 1 - sigmoid(12 V), clipped, s in
   [-1, 1].
7. sharpening `SharpenFilter`: torchvision's `adjust_sharpness` with factor k in [0, 2]
   (`usm_sharpen_range`): k x + (1 - k) blurred, blurred the 3 x 3 kernel
   [[1, 1, 1], [1, 5, 1], [1, 1, 1]] / 13 inside the image and x itself on its one-pixel border.

Every filter's output is clipped to [0, 1], as RLPixTuner's `Filter.forward` does. Two
departures, both without effect on the result's meaning: the highlight and shadow filters
replace V by scaling R, G, B by V'/V (what RLPixTuner's round trip through HSV computes, without
its 1e-8 in the saturation), and a black pixel (V = 0) becomes the gray V'; and the white-balance
gains follow their action log-linearly, gain = e^(0.5 a), as the filter's own parameter head
does, so that the action 0 leaves every filter neutral (RLPixTuner's environment maps actions
linearly onto [e^-0.5, e^0.5], where the gain 1 sits at -0.24).

Images are numpy float32 [N, 3, H, W] in [0, 1], parameters float [N, 9] in each filter's own
units (`PARAMETERS`); everything is vectorised over the batch and deterministic.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Parameter:
    """One pipeline parameter: its name, its range and the value that changes nothing."""

    name: str
    low: float
    high: float
    neutral: float


_GAIN_LOW, _GAIN_HIGH = float(np.exp(-0.5)), float(np.exp(0.5))
PARAMETERS = (
    Parameter("exposure_ev", -2.0, 2.0, 0.0),
    Parameter("red_gain", _GAIN_LOW, _GAIN_HIGH, 1.0),
    Parameter("green_gain", _GAIN_LOW, _GAIN_HIGH, 1.0),
    Parameter("blue_gain", _GAIN_LOW, _GAIN_HIGH, 1.0),
    Parameter("saturation", -1.0, 1.0, 0.0),
    Parameter("contrast", -1.0, 1.0, 0.0),
    Parameter("highlights", -1.0, 1.0, 0.0),
    Parameter("shadows", -1.0, 1.0, 0.0),
    Parameter("sharpening", 0.0, 2.0, 1.0),
)
NAMES = tuple(p.name for p in PARAMETERS)
NEUTRAL = np.array([p.neutral for p in PARAMETERS], np.float32)
"""The parameters that leave an image as it is (the actions 0)."""
_GAINS = slice(1, 4)
_EV, _SATURATION, _CONTRAST, _HIGHLIGHTS, _SHADOWS, _SHARPENING = 0, 4, 5, 6, 7, 8
_LOW = np.array([p.low for p in PARAMETERS], np.float32)
_HIGH = np.array([p.high for p in PARAMETERS], np.float32)


def params_from_actions(actions: np.ndarray) -> np.ndarray:
    """Actions in [-1, 1] (clipped there), [..., 9], as parameters: each mapped linearly onto
    its range, but the white-balance gains, e^(0.5 a)."""
    actions = np.clip(np.asarray(actions, np.float32), -1.0, 1.0)
    params = _LOW + (actions + 1.0) * 0.5 * (_HIGH - _LOW)
    params[..., _GAINS] = np.exp(0.5 * actions[..., _GAINS])
    return params


def actions_from_params(params: np.ndarray) -> np.ndarray:
    """The inverse of `params_from_actions`, for parameters inside their ranges."""
    params = np.asarray(params, np.float32)
    actions = 2.0 * (params - _LOW) / (_HIGH - _LOW) - 1.0
    actions[..., _GAINS] = 2.0 * np.log(params[..., _GAINS])
    return actions.astype(np.float32)


def _per_image(values: np.ndarray) -> np.ndarray:
    """[N] values as [N, 1, 1, 1], to scale [N, 3, H, W] images."""
    return np.asarray(values, np.float32).reshape(-1, 1, 1, 1)


def _sigmoid(x: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-x))


def exposure(images: np.ndarray, ev: np.ndarray) -> np.ndarray:
    return images * np.exp2(_per_image(ev))


def white_balance(images: np.ndarray, gains: np.ndarray) -> np.ndarray:
    return images * np.asarray(gains, np.float32).reshape(-1, 3, 1, 1)


def saturation(images: np.ndarray, amount: np.ndarray) -> np.ndarray:
    gray = 0.2989 * images[:, 0:1] + 0.587 * images[:, 1:2] + 0.114 * images[:, 2:3]
    amount = _per_image(amount)
    return (1.0 + amount) * images - amount * gray


def contrast(images: np.ndarray, amount: np.ndarray) -> np.ndarray:
    luminance = np.clip(0.27 * images[:, 0:1] + 0.67 * images[:, 1:2] + 0.06 * images[:, 2:3], 0.0, 1.0)
    contrasted = images / (luminance + 1e-6) * (0.5 - 0.5 * np.cos(np.pi * luminance))
    amount = _per_image(amount)
    return (1.0 - amount) * images + amount * contrasted


def _with_value(images: np.ndarray, value: np.ndarray, new_value: np.ndarray) -> np.ndarray:
    """The images with their HSV value V changed to `new_value`, hue and saturation kept."""
    scale = np.divide(new_value, value, out=np.zeros_like(value), where=value > 0)
    return np.where(value > 0, images * scale, new_value)


def highlights(images: np.ndarray, amount: np.ndarray) -> np.ndarray:
    value = images.max(axis=1, keepdims=True)
    mask = _sigmoid(13.0 * (value - 1.0))
    new_value = np.clip(1.0 - (1.0 - value) * (1.0 - 13.0 * _per_image(amount) * mask), 0.0, 1.0)
    return _with_value(images, value, new_value)


def shadows(images: np.ndarray, amount: np.ndarray) -> np.ndarray:
    value = images.max(axis=1, keepdims=True)
    mask = 1.0 - _sigmoid(12.0 * value)
    new_value = np.clip(value * (1.0 + 12.0 * _per_image(amount) * mask), 0.0, 1.0)
    return _with_value(images, value, new_value)


def sharpen(images: np.ndarray, factor: np.ndarray) -> np.ndarray:
    height, width = images.shape[-2:]
    if height < 3 or width < 3:  # no inside to blur
        return images
    neighbourhood = sum(images[..., dy:height - 2 + dy, dx:width - 2 + dx] for dy in range(3) for dx in range(3))
    blurred = images.copy()
    blurred[..., 1:-1, 1:-1] = (neighbourhood + 4.0 * images[..., 1:-1, 1:-1]) / 13.0
    factor = _per_image(factor)
    return factor * images + (1.0 - factor) * blurred


def finish(images: np.ndarray, params: np.ndarray) -> np.ndarray:
    """The seven filters in RLPixTuner's order, each clipped to [0, 1]: float32 [N, 3, H, W]
    images, [N, 9] parameters (one row for all the images is broadcast)."""
    images = np.asarray(images, np.float32)
    if images.ndim != 4 or images.shape[1] != 3:
        raise ValueError(f"images must be float [N, 3, H, W], got shape {list(images.shape)}")
    params = np.broadcast_to(np.asarray(params, np.float32), (len(images), len(PARAMETERS)))
    steps = (
        (exposure, params[:, _EV]),
        (white_balance, params[:, _GAINS]),
        (saturation, params[:, _SATURATION]),
        (contrast, params[:, _CONTRAST]),
        (highlights, params[:, _HIGHLIGHTS]),
        (shadows, params[:, _SHADOWS]),
        (sharpen, params[:, _SHARPENING]),
    )
    for step, values in steps:
        images = np.clip(step(images, values), 0.0, 1.0, dtype=np.float32)
    return images
