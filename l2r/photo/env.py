"""`PhotoTuneEnv` (`l2r/PhotoTune-v0`): find the pipeline parameters that turn a photo into a goal;
`PhotoEnhanceEnv` (`l2r/PhotoEnhance-v0`): the same with the images swapped and the goal unseen,
bring a photo degraded by hidden pipeline parameters back towards its original.

RLPixTuner's goal-conditioned tuning task (its `envs/isp_env.py`) in the "FiveK-Random" setting:
each episode crops a 256 × 256 working image from a photo of the split and makes its goal by
running the pipeline (l2r.photo.pipeline) on it with hidden parameters, each action drawn
uniformly in [-1, 1]; a crop or goal that is itself collapsed (below) is drawn again. With
`goals="looks"` the goal is instead the crop with another scene's look (`transfer_look`: the
colour statistics of a crop of a photo of another scene of the same split), a colour grade the
pipeline can approach but, unlike a random edit, not always reach (as a retoucher's target);
`goals="mixed"` draws one kind or the other with even odds each episode.

The action is a complete setting of the nine parameters, each in [-1, 1] mapped onto its range,
not a change to the current one: as in RLPixTuner (`isp_inp_original`), each step runs the
pipeline on the untouched input with the action's parameters, so a step is one query of the
pipeline, the unit in which the tuner is compared with optimisers such as CMA-ES, and the
observation carries the parameters of the last query for the policy to refine. (Deltas would make
what a step can reach depend on the path taken and stick at the ends of the ranges.)

The observation holds three fields: `pixels`, the current image, and `goal`, the goal image, each
uint8[3, 64, 64] (the 4 × 4 block means of the working images), and `state`, float32[16]:
luminance, contrast and saturation of the current image, the same of the goal (RLPixTuner's
per-image statistics, on the 64 × 64 images, `image_statistics`), the current parameters as
actions, and the fraction of the episode's steps taken (gymnasium orders a Dict's fields by name:
the spec reads `goal, pixels, state`). An episode starts from the input with
neutral parameters.

With `view="statistics"` (`l2r/PhotoTuneStats-v0`) the observation is `state` alone,
float32[60]: `image_features` of the current image and of the goal (per channel the mean, the
standard deviation and the 10th, 50th and 90th percentiles, an 8-bin luminance histogram, the
saturation and the sharpness), the current parameters and the steps taken. No convolution then
reads the images, so a tuner trains at the speed of a small MLP: what a 2-core machine can do,
where the image encoder makes a fraction of an update a second.

With `view="comparison"` (`l2r/PhotoTuneCompare-v0`) `state` is float32[100]: the statistics
view's 60 values and `comparison_features` of the current image against the goal, which read
both images on the same pixels: how the edits between them changed each tone and each colour,
what the separate statistics of two images of the same scene leave the policy to guess.
`l2r/PhotoTuneCompareDetail-v0` (`detail=True`) adds two values, float32[102]: `detail_features`, how
much more detail the goal's working image has than the current one's at 256 pixels, and how
much more of it at 256 than at 128. Sharpening's 3 x 3 kernel acts on the working image and is
averaged away in the 64-pixel images every other feature reads.

The reward is the change in PSNR to the goal (on the working images, capped at 100 dB) times
0.01. An episode ends after 10 steps, or early when the image collapses, its mean brightness
below 0.01 or above 0.9; both are terminations, the count of steps being in the observation and
a collapse forfeiting the steps left. `info["psnr_db"]` is the PSNR of the current image; with
either view of statistics, `info["frames"]` holds the images the observation leaves out (`pixels` and
`goal`, as the images view shows them), which episode logs record.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np

from l2r.photo import photos
from l2r.photo.pipeline import NEUTRAL, PARAMETERS, actions_from_params, finish, params_from_actions
from l2r.spaces import checked_action

MAX_STEPS = 10
REWARD_SCALE = 0.01
DARKEST, BRIGHTEST = 0.01, 0.9
"""The mean brightness outside which an image has collapsed."""
MAX_PSNR_DB = 100.0
"""PSNR where the image equals its goal (the mean squared error floored at 1e-10)."""
MAX_DRAWS = 100
VIEWS = ("images", "statistics", "comparison")
"""What an observation holds: both images and three statistics of each; `image_features` of
each; or those features and `comparison_features` of the pair (the tuner's alone)."""
GOAL_SETS = ("random", "looks")
"""The two kinds of goal: the crop finished with hidden random parameters, or the crop with
another scene's look (`transfer_look`)."""
GOALS = (*GOAL_SETS, "mixed")
"""What a tuner's episodes take: one kind, or either with even odds each episode."""


def psnr_db(images: np.ndarray, goals: np.ndarray) -> np.ndarray:
    """PSNR in dB of float images in [0, 1] against their goals, per image of [N, 3, H, W]."""
    mse = np.mean(np.square(images - goals, dtype=np.float64), axis=(1, 2, 3))
    return 10.0 * np.log10(1.0 / np.maximum(mse, 10 ** (-MAX_PSNR_DB / 10)))


def collapsed(image: np.ndarray) -> bool:
    """Whether an image's mean brightness is below 0.01 or above 0.9."""
    return not DARKEST <= float(image.mean()) <= BRIGHTEST


HISTOGRAM_BINS = 8
FEATURES_PER_IMAGE = 3 * 5 + HISTOGRAM_BINS + 2


def luminance(images: np.ndarray) -> np.ndarray:
    """[N, H, W]: 0.27 R + 0.67 G + 0.06 B of float images [N, 3, H, W]."""
    return 0.27 * images[:, 0] + 0.67 * images[:, 1] + 0.06 * images[:, 2]


def mean_abs_laplacian(planes: np.ndarray) -> np.ndarray:
    """[N]: the mean absolute 4-neighbour Laplacian of [N, H, W] planes over their inner pixels."""
    return np.abs(4 * planes[:, 1:-1, 1:-1] - planes[:, :-2, 1:-1] - planes[:, 2:, 1:-1]
                  - planes[:, 1:-1, :-2] - planes[:, 1:-1, 2:]).mean(axis=(1, 2))


def image_features(images: np.ndarray) -> np.ndarray:
    """[N, 25] of float images [N, 3, H, W] in [0, 1]: per channel the mean, the standard
    deviation and the 10th, 50th and 90th percentiles (exposure, white balance, contrast); the
    luminance's histogram in 8 equal bins, as fractions (highlights and shadows); the saturation
    of `image_statistics`; the mean absolute 4-neighbour Laplacian of the luminance (sharpness).
    Each in [0, 1]."""
    n = len(images)
    pixels = images.reshape(n, 3, -1)
    percentiles = np.percentile(pixels, (10, 50, 90), axis=2).transpose(1, 2, 0)  # [N, 3, 3]
    channels = np.concatenate([pixels.mean(axis=2)[..., None], pixels.std(axis=2)[..., None], percentiles], axis=2)
    lit = luminance(images)
    bins = np.minimum((lit.reshape(n, -1) * HISTOGRAM_BINS).astype(np.int64), HISTOGRAM_BINS - 1)
    histogram = np.stack([np.bincount(row, minlength=HISTOGRAM_BINS) for row in bins]) / bins.shape[1]
    sharpness = np.minimum(mean_abs_laplacian(lit), 1.0)
    return np.concatenate([channels.reshape(n, -1), histogram, image_statistics(images)[:, 2:3], sharpness[:, None]],
                          axis=1)


TONE_BINS = 8
COMPARISON_FEATURES = TONE_BINS * 5
_RATIO_FLOOR = 0.02
"""Added to both means of a ratio, so that near-black tones give finite ratios of little weight."""
_RATIO_SCALE = 0.25
"""Log-ratios times this lie in [-1, 1] (|log(1.02 / 0.02)| < 4)."""


def comparison_features(images: np.ndarray, goals: np.ndarray) -> np.ndarray:
    """[N, 40] of float images and their goals [N, 3, H, W] in [0, 1], the same scene pixel for
    pixel: the pixels in 8 equal bins of the image's HSV value (its tones), and per bin the share
    of pixels in it, then the log of (the goal's mean + 0.02) / (the image's mean + 0.02) of R, G
    and B and of the chroma (max - min of R, G, B), each times 0.25: the change that would take
    each tone to the goal's, in colour and in saturation (a tone no pixel has: share and ratios 0)."""
    n = len(images)
    image, goal = images.reshape(n, 3, -1), goals.reshape(n, 3, -1)
    tones = np.minimum((image.max(axis=1) * TONE_BINS).astype(np.int64), TONE_BINS - 1)
    in_bin = tones[:, None, :] == np.arange(TONE_BINS)[None, :, None]  # [N, bins, pixels]
    counts = in_bin.sum(axis=2)
    weights = in_bin / np.maximum(counts, 1)[..., None]

    def means(values: np.ndarray) -> np.ndarray:  # [N, C, pixels] -> [N, bins, C]
        return np.einsum("nbp,ncp->nbc", weights, values)

    def chroma(x: np.ndarray) -> np.ndarray:
        return (x.max(axis=1) - x.min(axis=1))[:, None]

    ratios = np.log((means(np.concatenate([goal, chroma(goal)], axis=1)) + _RATIO_FLOOR)
                    / (means(np.concatenate([image, chroma(image)], axis=1)) + _RATIO_FLOOR))
    share = counts / image.shape[2]
    return np.concatenate([share[..., None], _RATIO_SCALE * ratios], axis=2).reshape(n, -1).astype(np.float32)


DETAIL_FEATURES = 2
_DETAIL_FLOOR = 1e-3
"""Added to both details of a ratio: a flat image's detail is 0."""


def detail(images: np.ndarray) -> np.ndarray:
    """[N, 2] of float images [N, 3, H, W] in [0, 1] (H and W even): the mean absolute 4-neighbour
    Laplacian of the luminance at full resolution and at half (2 x 2 means)."""
    lit = luminance(images)
    n, height, width = lit.shape
    halved = lit.reshape(n, height // 2, 2, width // 2, 2).mean(axis=(2, 4))
    return np.stack([mean_abs_laplacian(lit), mean_abs_laplacian(halved)], axis=1)


def detail_features(image_detail: np.ndarray, goal_detail: np.ndarray) -> np.ndarray:
    """[N, 2] of the `detail` of images and of their goals. With r the log of (the goal's + 0.001)
    / (the image's + 0.001) at each resolution: r at full resolution times 0.25, and r at full
    resolution less r at half, each clipped to [-1, 1]. The tone filters scale detail at both
    resolutions alike, sharpening the full resolution's most: the second reads sharpening."""
    ratios = np.log((goal_detail + _DETAIL_FLOOR) / (image_detail + _DETAIL_FLOOR))
    features = np.stack([_RATIO_SCALE * ratios[:, 0], ratios[:, 0] - ratios[:, 1]], axis=1)
    return np.clip(features, -1.0, 1.0).astype(np.float32)


def image_statistics(images: np.ndarray) -> np.ndarray:
    """[N, 3]: per image the mean luminance (0.27 R + 0.67 G + 0.06 B), the variance of that
    luminance (its contrast) and the mean of (max - min) / (min(max + min, 2 - max - min) + 0.01)
    over R, G, B (its saturation, HSL's but for the 0.01): each in [0, 1]."""
    lit = luminance(images)
    high, low = images.max(axis=1), images.min(axis=1)
    saturation = (high - low) / (np.minimum(high + low, 2.0 - high - low) + 0.01)
    return np.stack([lit.mean(axis=(1, 2)), lit.var(axis=(1, 2)), saturation.mean(axis=(1, 2))], axis=1)


def transfer_look(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``image`` (float [3, H, W] in [0, 1]) with ``reference``'s look: each CIELAB channel shifted
    and scaled to the reference's mean and standard deviation (Reinhard et al.'s colour transfer,
    2001), back in RGB clipped to [0, 1]. A linear map of each channel, so it grades without the
    posterising of histogram matching between photos of different content."""
    from skimage.color import lab2rgb, rgb2lab

    source, target = (rgb2lab(np.moveaxis(x, 0, -1)) for x in (image, reference))
    spread = target.std(axis=(0, 1)) / np.maximum(source.std(axis=(0, 1)), 1e-6)
    graded = (source - source.mean(axis=(0, 1))) * spread + target.mean(axis=(0, 1))
    with warnings.catch_warnings():  # lab2rgb warns of each colour outside the gamut, which it clips
        warnings.simplefilter("ignore", UserWarning)
        return np.moveaxis(np.clip(lab2rgb(graded), 0.0, 1.0), -1, 0).astype(np.float32)


class PhotoTuneEnv(gym.Env):
    """The goal-conditioned photo-finishing tuner's task.

    split: "train" or "test", the photos episodes are cropped from (l2r.photo.photos.SPLITS).
    max_steps: steps (pipeline queries) per episode.
    sources: photos to crop from instead of the split's, by name ([3, H, W] uint8 or uint16: a
        FiveK folder's, say).
    view: "images" (both images and their statistics), "statistics" (`image_features` alone) or
        "comparison" (those and `comparison_features` of the current image against the goal).
    detail: with view "comparison", `detail_features` of the working images too
        (`l2r/PhotoTuneCompareDetail-v0`).
    goals: "random" (RLPixTuner's FiveK-Random), "looks" (another scene's look; the tuner's task alone)
        or "mixed" (either, drawn with even odds each episode: a tuner trained on both).
    source_variety: each random goal's input crop first flipped left-right with even odds and
        finished with random parameters within this fraction of each one's range about neutral
        (0: the photo's own crop; at most 1), so that a few training photos show many colourings
        and exposures; the goal is then that varied input finished with the hidden parameters.
    """

    metadata = {"render_modes": []}
    shows_goal = True
    """Whether the observation shows the goal (the tuner's task) or the current image alone."""
    task = "PhotoTune"
    """The name errors begin with."""
    goal_kinds = GOALS

    def __init__(self, split: str = "train", max_steps: int = MAX_STEPS,
                 sources: Mapping[str, np.ndarray] | None = None, view: str = "images", goals: str = "random",
                 source_variety: float = 0.0, detail: bool = False):
        photos.check_split(split)
        if view not in VIEWS:
            raise ValueError(f"{self.task}: view must be one of {', '.join(VIEWS)}, got {view!r}")
        if goals not in self.goal_kinds:
            raise ValueError(f"{self.task}: goals must be one of {', '.join(self.goal_kinds)}, got {goals!r}")
        if not isinstance(max_steps, int) or isinstance(max_steps, bool) or max_steps < 1:
            raise ValueError(f"max_steps must be a positive integer, got {max_steps!r}")
        if view == "comparison" and not self.shows_goal:
            raise ValueError(f"{self.task}: view 'comparison' compares the image with a goal the task does not show")
        if not isinstance(detail, bool) or detail and view != "comparison":
            raise ValueError(f"{self.task}: detail must be true or false, and true with view 'comparison' alone, "
                             f"got {detail!r} with view {view!r}")
        if sources is not None and not sources:
            raise ValueError(f"{self.task}: sources holds no photo")
        if isinstance(source_variety, bool) or not isinstance(source_variety, (int, float)) \
                or not 0.0 <= source_variety <= 1.0:
            raise ValueError(f"{self.task}: source_variety must be a number in [0, 1], got {source_variety!r}")
        self.split, self.max_steps, self.view, self.goals, self.detail = split, max_steps, view, goals, detail
        self.source_variety = float(source_variety)
        # loaded at the first reset: the spaces need none
        self.photos: dict[str, np.ndarray] | None = None if sources is None else dict(sources)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (len(PARAMETERS),), np.float32)
        images_shown = 2 if self.shows_goal else 1
        statistics = 3 if view == "images" else FEATURES_PER_IMAGE
        comparison = (COMPARISON_FEATURES if view == "comparison" else 0) + (DETAIL_FEATURES if detail else 0)
        self.parameters_at = images_shown * statistics + comparison
        """Where `state` holds the current parameters as actions (a residual policy's last action)."""
        state = gym.spaces.Box(-1.0, 1.0, (self.parameters_at + len(PARAMETERS) + 1,), np.float32)
        image = gym.spaces.Box(0, 255, (3, photos.OBSERVATION_SIZE, photos.OBSERVATION_SIZE), np.uint8)
        fields = {"state": state} if view != "images" else \
            {"pixels": image, "state": state} | ({"goal": image} if self.shows_goal else {})
        self.observation_space = gym.spaces.Dict(fields)
        self.episode_over = True

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict[str, np.ndarray], dict]:
        """A new episode on a crop and goal drawn from the split; `options={"source": S, "goal": G}`
        tunes S towards G instead (float32 [3, 256, 256] in [0, 1]: `l2r photo tune`'s way).
        `info["look"]` names the photo whose look the goal has (None: not a borrowed look)."""
        super().reset(seed=seed)
        self.look = None
        if options and "goal" in options:
            self.photo_name = "given"
            self.source, self.goal = (self.check_image(options, name) for name in ("source", "goal"))
        else:
            self.draw()
        self.goal_small = photos.downsample(self.goal) if self.shows_goal else None
        self.goal_detail = detail(self.goal[None]) if self.detail else None
        self.image, self.params, self.steps = self.source, NEUTRAL, 0
        self.seen()
        self.psnr = float(psnr_db(self.source[None], self.goal[None])[0])
        self.episode_over = False
        return self.observation(), {"psnr_db": self.psnr, "photo": self.photo_name, "look": self.look,
                                    **self.frames()}

    def draw(self) -> None:
        """The episode's input, a crop of a photo of the split, and its goal: that crop edited with
        hidden random parameters, or given another scene's look."""
        if self.goals == "looks" or (self.goals == "mixed" and self.np_random.random() < 0.5):
            self.photo_name, self.source, self.look, self.goal = self.borrowed_look()
            self.goal_params = None  # no parameters are known to reach it
        else:
            self.photo_name, self.source, self.goal_params, self.goal = self.random_edit()

    def loaded(self) -> dict[str, np.ndarray]:
        """The photos episodes crop from, by name, loaded at the first call."""
        if self.photos is None:
            self.photos = photos.load_split(self.split)
        return self.photos

    def random_edit(self) -> tuple[str, np.ndarray, np.ndarray, np.ndarray]:
        """A photo of the split by name, a random crop of it, parameters drawn uniformly as actions
        in [-1, 1], and the crop finished with them: neither image collapsed."""
        names = list(self.loaded())
        for _ in range(MAX_DRAWS):
            name = names[int(self.np_random.integers(len(names)))]
            crop = self.varied(photos.random_crop(self.photos[name], self.np_random))
            params = params_from_actions(self.np_random.uniform(-1.0, 1.0, len(PARAMETERS)))
            edited = finish(crop[None], params)[0]
            if not collapsed(crop) and not collapsed(edited):
                return name, crop, params, edited
        raise RuntimeError(f"{MAX_DRAWS} crops of the {self.split} photos and their edits in a row were collapsed")

    def varied(self, crop: np.ndarray) -> np.ndarray:
        """The crop as `source_variety` says: itself at 0, else flipped left-right with even odds and
        finished with random actions uniform within ± source_variety."""
        if not self.source_variety:
            return crop
        if self.np_random.random() < 0.5:
            crop = np.ascontiguousarray(crop[:, :, ::-1])
        actions = self.np_random.uniform(-self.source_variety, self.source_variety, len(PARAMETERS))
        return finish(crop[None], params_from_actions(actions))[0]

    def borrowed_look(self) -> tuple[str, np.ndarray, str, np.ndarray]:
        """A photo of the split by name, a random crop of it, a photo of another scene by name, and
        the crop with the look of a random crop of that photo: neither the crop nor its goal
        collapsed."""
        names = list(self.loaded())
        for _ in range(MAX_DRAWS):
            name = names[int(self.np_random.integers(len(names)))]
            others = [other for other in names if photos.scene(other) != photos.scene(name)]
            if not others:
                raise ValueError(f"{self.task}: goals={self.goals!r} needs photos of two scenes at least; "
                                 f"the photos are {', '.join(names)}")
            look = others[int(self.np_random.integers(len(others)))]
            crop = photos.random_crop(self.photos[name], self.np_random)
            reference = photos.random_crop(self.photos[look], self.np_random)
            goal = transfer_look(crop, reference)
            if not collapsed(crop) and not collapsed(goal):
                return name, crop, look, goal
        raise RuntimeError(f"{MAX_DRAWS} crops of the {self.split} photos and their looks in a row were collapsed")

    def check_image(self, options: dict, name: str) -> np.ndarray:
        side = photos.WORKING_SIZE
        image = np.asarray(options.get(name), dtype=np.float32)
        if image.shape != (3, side, side) or not np.isfinite(image).all():
            raise ValueError(f"{self.task}: reset option {name!r} must be a finite float image [3, {side}, {side}], "
                             f"got shape {list(image.shape)}")
        return np.clip(image, 0.0, 1.0)

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        if self.episode_over:
            raise RuntimeError(f"{self.task}: step() before the first reset() or after the episode ended; call reset()")
        self.params = params_from_actions(checked_action(self.task, action, self.action_space.shape))
        self.image = finish(self.source[None], self.params)[0]
        self.seen()
        psnr = float(psnr_db(self.image[None], self.goal[None])[0])
        reward = REWARD_SCALE * (psnr - self.psnr)
        self.psnr, self.steps = psnr, self.steps + 1
        ruined = collapsed(self.image)
        self.episode_over = ruined or self.steps >= self.max_steps
        return self.observation(), reward, self.episode_over, False, {"psnr_db": psnr, "collapsed": ruined,
                                                                      **self.frames()}

    def seen(self) -> None:
        """What the observation reads of the current image, made once for each image."""
        self.image_small = photos.downsample(self.image)
        self.image_detail = detail(self.image[None]) if self.detail else None

    def frames(self) -> dict[str, dict[str, np.ndarray]]:
        """The images an observation of statistics leaves out, as the images view would show them,
        for episode logs (`info["frames"]`); nothing where the observation shows them."""
        if self.view == "images":
            return {}
        shown = {"pixels": self.image_small} | ({"goal": self.goal_small} if self.shows_goal else {})
        return {"frames": {name: photos.to_uint8(image) for name, image in shown.items()}}

    def observation(self) -> dict[str, np.ndarray]:
        current = self.image_small
        shown = np.stack([current, self.goal_small]) if self.shows_goal else current[None]
        statistics = image_statistics(shown) if self.view == "images" else image_features(shown)
        compared = comparison_features(current[None], self.goal_small[None]) if self.view == "comparison" else []
        finer = detail_features(self.image_detail, self.goal_detail) if self.detail else []
        state = np.concatenate([statistics.ravel(), np.ravel(compared), np.ravel(finer),
                                actions_from_params(self.params), [self.steps / self.max_steps]])
        if self.view != "images":
            return {"state": state.astype(np.float32)}
        images = {"pixels": photos.to_uint8(current)} | (
            {"goal": photos.to_uint8(self.goal_small)} if self.shows_goal else {})
        return images | {"state": np.clip(state, -1.0, 1.0).astype(np.float32)}


class PhotoEnhanceEnv(PhotoTuneEnv):
    """The enhancer's task: bring a photo degraded by hidden random edits back to its original,
    which the observation does not show.

    The tuner's task with its two images swapped: the episode's input is a crop of a photo of the
    split finished with hidden random parameters (`degradation`), its goal that crop untouched.
    Actions, reward (the change in PSNR to the original x 0.01), ends, `info["psnr_db"]` and
    `reset(options={"source": DEGRADED, "goal": ORIGINAL})` are the tuner's; the observation is
    the tuner's without the goal: `pixels: uint8[3, 64, 64], state: float32[13]` (the current
    image's luminance, contrast and saturation, the parameters, the steps taken) or, with
    `view="statistics"` (`l2r/PhotoEnhanceStats-v0`), `state: float32[35]` (`image_features` of
    the current image, the parameters, the steps taken).
    """

    shows_goal = False
    task = "PhotoEnhance"
    goal_kinds = ("random",)

    def draw(self) -> None:
        self.photo_name, self.goal, self.degradation, self.source = self.random_edit()
