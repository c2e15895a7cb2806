"""The enhancer's task (`l2r/PhotoEnhance-v0`) against what needs no training: how close to their
originals the degraded held-out crops come as they are, after scikit-image's automatic levels
and histogram equalisation, and after a trained policy's edits.

Both automatic methods work on each channel alone, as levels tools do: a colour cast from the
white-balance gains is undone only where each channel is stretched on its own.
"""

from __future__ import annotations

import numpy as np

from l2r.photo import ENHANCE_IDS, tune
from l2r.photo.env import psnr_db

AUTO_LEVELS_PERCENTILES = (2.0, 98.0)
"""The percentiles of each channel that automatic levels stretch to 0 and 1."""


def auto_levels(image: np.ndarray) -> np.ndarray:
    """A float [3, H, W] image in [0, 1] with each channel's 2nd to 98th percentile stretched onto
    [0, 1], what lies outside clipped (scikit-image's `exposure.rescale_intensity`)."""
    from skimage import exposure

    levels = [tuple(np.percentile(channel, AUTO_LEVELS_PERCENTILES)) for channel in image]
    return np.stack([exposure.rescale_intensity(channel, in_range=in_range, out_range=(0.0, 1.0))
                     for channel, in_range in zip(image, levels)]).astype(np.float32)


def equalized(image: np.ndarray) -> np.ndarray:
    """A float [3, H, W] image in [0, 1] with each channel's histogram equalised (scikit-image's
    `exposure.equalize_hist`, 256 bins)."""
    from skimage import exposure

    return np.stack([exposure.equalize_hist(channel) for channel in image]).astype(np.float32)


AUTOMATIC = {"auto_levels": auto_levels, "equalized": equalized}


def compare(problems: list[tune.Problem], policy=None) -> dict:
    """Mean PSNR (dB) and SSIM to the originals (the problems' goals) over the problems: of the
    degraded input (their sources), of each automatic method, and of the policy's last image after
    its 10 queries through the enhancer's task (None without a policy)."""
    scores: dict[str, list[tuple[float, float]]] = {}
    for problem in problems:
        images = {"input": problem.source} | {name: method(problem.source) for name, method in AUTOMATIC.items()}
        if policy is not None:
            images["policy"] = tune.finished(problem, tune.policy_tune(policy, problem, ENHANCE_IDS).actions[-1])
        for name, image in images.items():
            scores.setdefault(name, []).append(
                (float(psnr_db(image[None], problem.goal[None])[0]), tune.ssim(image, problem.goal)))
    result: dict = {"photos": len(problems), "policy_queries": tune.POLICY_QUERIES}
    for name in ("input", *AUTOMATIC, "policy"):
        means = np.mean(scores[name], axis=0).tolist() if name in scores else (None, None)
        result[f"{name}_psnr_db"], result[f"{name}_ssim"] = means
    return result
