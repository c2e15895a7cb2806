"""The photographs from the wheels, the split by source, crops and block means, and FiveK's layout
read from a tiny folder written here."""

import imageio.v3 as iio
import numpy as np
import pytest

from l2r.photo import photos


def test_every_photo_loads_offline_as_a_channels_first_image_a_crop_fits():
    for name in photos.PHOTOS:
        photo = photos.load_photo(name)
        assert photo.dtype == np.uint8 and photo.shape[0] == 3, name
        assert min(photo.shape[1:]) >= photos.WORKING_SIZE, name
        assert photo.std() > 10, f"{name} is flat"


def test_the_split_is_by_source_photo_and_fixed():
    sources = {split: {photos.PHOTOS[name][0] for name in names} for split, names in photos.SPLITS.items()}
    assert not sources["train"] & sources["test"]
    assert set(photos.SPLITS["train"]) | set(photos.SPLITS["test"]) == set(photos.PHOTOS)
    assert photos.SPLITS["test"] == ("chelsea", "coffee", "grace_hopper")
    assert {"motorcycle_left", "motorcycle_right"} <= set(photos.SPLITS["train"])  # two views, one scene
    assert list(photos.load_split("test")) == ["chelsea", "coffee", "grace_hopper"]
    with pytest.raises(ValueError, match="split must be one of train, test"):
        photos.load_split("validation")


def test_a_random_crop_is_seeded_scaled_and_inside_the_photo():
    photo = np.arange(3 * 300 * 400, dtype=np.int64).reshape(3, 300, 400).astype(np.uint16)
    crop = photos.random_crop(photo, np.random.default_rng(5))
    assert crop.shape == (3, 256, 256) and crop.dtype == np.float32
    np.testing.assert_array_equal(crop, photos.random_crop(photo, np.random.default_rng(5)))
    assert not np.array_equal(crop, photos.random_crop(photo, np.random.default_rng(6)))
    top, left = divmod(int(round(crop[0, 0, 0] * 65535)), 400)
    np.testing.assert_allclose(crop, photo[:, top:top + 256, left:left + 256] / 65535, rtol=1e-6)
    with pytest.raises(ValueError, match="smaller than the 256 x 256 crop"):
        photos.random_crop(np.zeros((3, 255, 400), np.uint8), np.random.default_rng(0))


def test_downsampling_takes_the_mean_of_each_block():
    image = np.array([[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10, 11], [12, 13, 14, 15]], np.float32)
    assert photos.downsample(image, 2).tolist() == [[2.5, 4.5], [10.5, 12.5]]
    assert photos.downsample(np.ones((2, 3, 256, 256), np.float32)).shape == (2, 3, 64, 64)
    with pytest.raises(ValueError, match="equal blocks"):
        photos.downsample(np.ones((3, 100, 100), np.float32))
    assert photos.to_uint8(np.array([0.0, 0.5, 1.0, 1.5, -0.1])).tolist() == [0, 128, 255, 255, 0]


def write_fivek(root, names, expert="C"):
    """A FiveK folder: `input/` and `expert<expert>_gt/` each with the same small PNGs."""
    rng = np.random.default_rng(0)
    for folder in ("input", f"expert{expert}_gt"):
        (root / folder).mkdir()
        for name in names:
            iio.imwrite(root / folder / f"{name}.png", rng.integers(0, 256, (8, 12, 3), dtype=np.uint8))


def test_fivek_pairs_inputs_with_targets_by_name_and_holds_out_the_last_tenth(tmp_path):
    names = [f"a{i:04d}-photo" for i in range(1, 22)]
    write_fivek(tmp_path, names)
    iio.imwrite(tmp_path / "input" / "a0099-no-target.png", np.zeros((8, 12, 3), np.uint8))
    (tmp_path / "expertC_gt" / "notes.txt").write_text("not a photo")
    pairs = photos.fivek_pairs(tmp_path)
    assert [(i.parent.name, i.stem, t.parent.name, t.stem) for i, t in pairs] == [
        ("input", name, "expertC_gt", name) for name in names]
    assert [i.stem for i, _ in photos.fivek_split(pairs, "test")] == names[18:]  # 2.1, rounded up
    assert [i.stem for i, _ in photos.fivek_split(pairs, "train")] == names[:18]
    image = photos.read_image(pairs[0][0])
    assert image.shape == (3, 8, 12) and image.dtype == np.uint8
    np.testing.assert_array_equal(image, iio.imread(pairs[0][0]).transpose(2, 0, 1))


def test_fivek_reads_16_bit_tiffs_and_other_experts(tmp_path):
    (tmp_path / "input").mkdir()
    (tmp_path / "expertA_gt").mkdir()
    deep = np.full((6, 7, 3), 40000, np.uint16)
    for folder in ("input", "expertA_gt"):
        iio.imwrite(tmp_path / folder / "a0001.tif", deep)
    [(source, target)] = photos.fivek_pairs(tmp_path, expert="A")
    assert photos.read_image(target).dtype == np.uint16
    assert photos.random_crop(photos.read_image(source), np.random.default_rng(0), 6)[0, 0, 0] == pytest.approx(
        40000 / 65535)


def test_a_folder_not_in_fivek_layout_is_refused_in_words(tmp_path):
    with pytest.raises(FileNotFoundError, match="input/ beside expertC_gt/"):
        photos.fivek_pairs(tmp_path)
    write_fivek(tmp_path, ["a0001"], expert="B")
    (tmp_path / "expertC_gt").mkdir()
    with pytest.raises(FileNotFoundError, match="no photo is in both"):
        photos.fivek_pairs(tmp_path)
    with pytest.raises(ValueError, match="expert must be one of"):
        photos.fivek_pairs(tmp_path, expert="F")
