"""Live frames of camera tasks: a frame carries the observation's camera frames in their own dtype
and shape (version 2), a runner's frame stays the version-1 bytes it was, and every bad image is
rejected with its reason, by the sender and by the viewer."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from l2r.episodes.live import frame
from l2r.protocol import Frame, ProtocolError, decode, encode

SIDE = 32


def camera_observation() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {"pixels": rng.integers(0, 256, (3, SIDE, SIDE), np.uint8), "state": rng.random(5, np.float32)}


def test_a_camera_frame_carries_the_observation_s_images_in_their_own_dtype():
    obs = camera_observation()
    sent = frame(3, 1, 7, 40, obs, 0.25, {"inner_steps": 2})
    payload = encode(sent)
    raw = msgpack.unpackb(payload)
    assert raw["v"] == 2 and raw["values"] == {"reward": 0.25}  # a task without a body has no distance
    assert list(raw["images"]) == ["pixels"]  # the camera field alone, not the float state
    assert raw["images"]["pixels"]["dtype"] == "|u1" and raw["images"]["pixels"]["shape"] == [1, 3, SIDE, SIDE]
    assert len(payload) < 3 * SIDE * SIDE + 200  # one byte a pixel
    back = decode(payload, Frame)
    assert back.images["pixels"].dtype == np.uint8
    np.testing.assert_array_equal(back.images["pixels"][0], obs["pixels"])


def test_a_runner_frame_has_no_images_and_stays_version_1():
    info = {"body_pos": np.zeros((3, 3)), "body_quat": np.ones((3, 4)), "distance": 1.5}
    payload = encode(frame(0, 0, 1, 2, {"state": np.zeros(41, np.float32)}, -0.5, info))
    raw = msgpack.unpackb(payload)
    assert raw["v"] == 1 and b"images" not in payload  # a version-1 viewer gets the bytes it knew
    assert raw["values"] == {"reward": -0.5, "distance": 1.5}
    assert decode(payload, Frame).images is None


def with_images(images, version: int = 2) -> bytes:
    """A camera frame's payload with its images field replaced, as a faulty peer could send it."""
    raw = msgpack.unpackb(encode(frame(0, 0, 0, 0, camera_observation(), 0.0, {})))
    raw["images"], raw["v"] = images, version
    return msgpack.packb(raw, use_bin_type=True)


def wire(shape, dtype="|u1", data: bytes | None = None) -> dict:
    size = int(np.prod(shape)) * np.dtype(dtype).itemsize
    return {"dtype": dtype, "shape": list(shape), "data": bytes(size) if data is None else data}


@pytest.mark.parametrize("images, reason", [
    ({"pixels": wire([1, 3, SIDE, SIDE], "<f4")}, "wrong_dtype"),  # an observation dtype, but no image
    ({"pixels": wire([1, 3, SIDE, SIDE], "<i8")}, "wrong_dtype"),
    ({"pixels": wire([1, 3, SIDE, SIDE], data=b"\x00" * 100)}, "bad_array"),  # bytes that are not its shape
    ({"pixels": b"not an array"}, "bad_array"),
    ({"pixels": wire([3, SIDE, SIDE])}, "shape_mismatch"),  # without its row: 3 rows of grey images
    ({"pixels": wire([2, 3, SIDE, SIDE])}, "shape_mismatch"),
    ({"pixels": wire([1, 4, SIDE, SIDE])}, "wrong_shape"),  # not RGB
    ({"pixels": wire([1, SIDE, SIDE])}, "wrong_shape"),
    ({"pixels": wire([1, 3, 0, SIDE])}, "wrong_shape"),
    ({"pixels": wire([1, 3, 1200, 1200])}, "oversized"),  # 4.1 MiB: larger than any observation field
    ({"pix els": wire([1, 3, SIDE, SIDE])}, "bad_field"),
    ({}, "bad_field"),
    ({f"f{i}": wire([1, 3, 2, 2]) for i in range(9)}, "bad_field"),
    ([1, 2, 3], "wrong_type"),
])
def test_a_bad_image_is_rejected_with_its_reason(images, reason):
    with pytest.raises(ProtocolError) as error:
        decode(with_images(images), Frame)
    assert error.value.reason == reason, error.value


def test_images_in_a_version_1_frame_are_rejected_as_a_version_mismatch():
    with pytest.raises(ProtocolError) as error:
        decode(with_images({"pixels": wire([1, 3, SIDE, SIDE])}, version=1), Frame)
    assert error.value.reason == "version"


@pytest.mark.parametrize("image, reason", [
    (np.zeros((1, 3, SIDE, SIDE), np.float32), "wrong_dtype"),
    (np.zeros((1, 1, SIDE, SIDE), np.uint8), "wrong_shape"),
    (np.zeros((1, 3, 1200, 1200), np.uint8), "oversized"),
])
def test_a_sender_cannot_send_a_bad_image(image, reason):
    with pytest.raises(ProtocolError) as error:
        encode(Frame(0, 0, 0, 0, {}, {"reward": 0.0}, {"pixels": image}))
    assert error.value.reason == reason
