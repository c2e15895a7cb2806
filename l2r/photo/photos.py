"""The photographs the photo tasks work on, their split, and the crops an episode starts from.

No data set can be downloaded where l2r trains, so the tasks use the photographs that ship inside
installed wheels: scikit-image's `skimage.data` (astronaut, chelsea, coffee, rocket, the
motorcycle stereo pair, hubble_deep_field, retina, immunohistochemistry) and matplotlib's sample
portrait of Grace Hopper. They split by source photo, never by crop, so no held-out scene is ever
seen in training: the two motorcycle views are one source. The split is fixed here
(`TEST_SOURCES`): three everyday scenes held out (a cat, a cup of coffee, a portrait), the rest
(a portrait, a street, a rocket, and three scientific images) for training.

An episode works on a random 256 × 256 crop of a photo (`random_crop`), its observations are that
crop's 4 × 4 block means, 64 × 64 (`downsample`).

For users who have MIT-Adobe FiveK, `fivek_pairs` reads its folder layout as image-enhancement
work conventionally stores it: `input/` beside `expertC_gt/` (expert C's retouch, the usual
target; `expertA_gt/` to `expertE_gt/` for the others), one file per photo under the same name;
`fivek_split` holds out the last tenth in name order, which on the full set is the common
4,500 / 500 split (a4501 to a5000 for testing).

Photos are channels-first integer arrays, [3, H, W] uint8 (or uint16 for 16-bit files), until a
crop turns them into float32 in [0, 1].
"""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import numpy as np

WORKING_SIZE = 256
"""The side of the image an episode edits and scores."""
OBSERVATION_SIZE = 64
"""The side of the images an observation holds."""


def _skimage(name: str, index: int | None = None) -> Callable[[], np.ndarray]:
    def load() -> np.ndarray:
        import skimage.data

        image = getattr(skimage.data, name)()
        return image if index is None else image[index]

    return load


def _grace_hopper() -> np.ndarray:
    import imageio.v3 as iio
    import matplotlib.cbook

    return iio.imread(matplotlib.cbook.get_sample_data("grace_hopper.jpg", asfileobj=False))


PHOTOS: dict[str, tuple[str, Callable[[], np.ndarray]]] = {
    # name: (its source scene, its loader returning [H, W, 3] uint8)
    "astronaut": ("astronaut", _skimage("astronaut")),
    "chelsea": ("chelsea", _skimage("chelsea")),
    "coffee": ("coffee", _skimage("coffee")),
    "rocket": ("rocket", _skimage("rocket")),
    "motorcycle_left": ("motorcycle", _skimage("stereo_motorcycle", 0)),
    "motorcycle_right": ("motorcycle", _skimage("stereo_motorcycle", 1)),
    "hubble_deep_field": ("hubble_deep_field", _skimage("hubble_deep_field")),
    "retina": ("retina", _skimage("retina")),
    "immunohistochemistry": ("immunohistochemistry", _skimage("immunohistochemistry")),
    "grace_hopper": ("grace_hopper", _grace_hopper),
}
TEST_SOURCES = ("chelsea", "coffee", "grace_hopper")
SPLITS = {
    "train": tuple(name for name, (source, _) in PHOTOS.items() if source not in TEST_SOURCES),
    "test": tuple(name for name, (source, _) in PHOTOS.items() if source in TEST_SOURCES),
}
"""The photos of each split, by name."""


def scene(name: str) -> str:
    """The scene a photo shows: its source in `PHOTOS` (the motorcycle pair is one scene), or
    its own name for a photo of the user's."""
    return PHOTOS[name][0] if name in PHOTOS else name


def check_split(split: str) -> None:
    if split not in SPLITS:
        raise ValueError(f"split must be one of {', '.join(SPLITS)}, got {split!r}")


def load_photo(name: str) -> np.ndarray:
    """One of `PHOTOS`, as [3, H, W] uint8."""
    if name not in PHOTOS:
        raise ValueError(f"no photo {name!r}; the photos are {', '.join(PHOTOS)}")
    return np.ascontiguousarray(PHOTOS[name][1]().transpose(2, 0, 1))


def load_split(split: str) -> dict[str, np.ndarray]:
    """The photos of a split ("train" or "test"), by name."""
    check_split(split)
    return {name: load_photo(name) for name in SPLITS[split]}


def random_crop(photo: np.ndarray, rng: np.random.Generator, size: int = WORKING_SIZE) -> np.ndarray:
    """A size × size crop at a random place, as float32 [3, size, size] in [0, 1]."""
    height, width = photo.shape[-2:]
    if height < size or width < size:
        raise ValueError(f"a {height} x {width} photo is smaller than the {size} x {size} crop")
    top, left = int(rng.integers(height - size + 1)), int(rng.integers(width - size + 1))
    crop = photo[:, top:top + size, left:left + size]
    return (crop / np.float32(np.iinfo(photo.dtype).max)).astype(np.float32)


def downsample(images: np.ndarray, size: int = OBSERVATION_SIZE) -> np.ndarray:
    """[..., H, W] images as [..., size, size] means of equal blocks (H and W multiples of size)."""
    height, width = images.shape[-2:]
    if height % size or width % size:
        raise ValueError(f"a {height} x {width} image does not split into {size} x {size} equal blocks")
    blocks = images.reshape(*images.shape[:-2], size, height // size, size, width // size)
    return blocks.mean(axis=(-3, -1), dtype=np.float32)


def to_uint8(images: np.ndarray) -> np.ndarray:
    """Float images in [0, 1] as uint8, rounded."""
    return np.rint(np.clip(images, 0.0, 1.0) * 255.0).astype(np.uint8)


FIVEK_INPUT = "input"
IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")


def fivek_pairs(root: str | Path, expert: str = "C") -> list[tuple[Path, Path]]:
    """(input, target) file pairs of a FiveK folder, `root/input/NAME.*` with
    `root/expert<expert>_gt/NAME.*`, in name order; FileNotFoundError when a folder is missing
    or no photo is in both."""
    if expert not in tuple("ABCDE"):
        raise ValueError(f"expert must be one of A, B, C, D, E, got {expert!r}")
    folders = Path(root) / FIVEK_INPUT, Path(root) / f"expert{expert}_gt"
    for folder in folders:
        if not folder.is_dir():
            raise FileNotFoundError(f"{folder} is not a folder; FiveK's layout is {FIVEK_INPUT}/ beside "
                                    f"expert{expert}_gt/, one file per photo under the same name")
    inputs, targets = ({path.stem: path for path in folder.iterdir() if path.suffix.lower() in IMAGE_SUFFIXES}
                       for folder in folders)
    pairs = [(inputs[name], targets[name]) for name in sorted(inputs.keys() & targets.keys())]
    if not pairs:
        raise FileNotFoundError(f"no photo is in both {folders[0]} and {folders[1]}")
    return pairs


def fivek_split(pairs: list[tuple[Path, Path]], split: str) -> list[tuple[Path, Path]]:
    """The pairs of a split: the last tenth in name order (rounded up) for "test", the rest for
    "train"."""
    check_split(split)
    first_test = len(pairs) - math.ceil(len(pairs) / 10)
    return pairs[first_test:] if split == "test" else pairs[:first_test]


def read_image(path: str | Path) -> np.ndarray:
    """An RGB image file (8- or 16-bit) as [3, H, W] uint8 or uint16."""
    import imageio.v3 as iio

    image = iio.imread(path)
    if image.ndim != 3 or image.shape[2] < 3 or image.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"{path}: expected an 8- or 16-bit RGB image, got {image.dtype} {list(image.shape)}")
    return np.ascontiguousarray(image[..., :3].transpose(2, 0, 1))
