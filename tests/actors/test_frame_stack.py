"""FrameStack: the stacks an actor acts on, padded at resets as the replay pads them at sampling."""

import numpy as np
import pytest

from l2r.actors.frame_stack import FrameStack, frame_stack_of
from l2r.protocol import ObservationSpec, ProtocolError

CAMERA = ObservationSpec.parse("pixels: uint8[3, 4, 2], state: float32[2]")


def frame(value: int) -> dict[str, np.ndarray]:
    """An observation whose every pixel is ``value`` and whose state is (value, -value)."""
    return {"pixels": np.full((3, 4, 2), value, np.uint8), "state": np.array([value, -value], np.float32)}


def values(stack: FrameStack, env: int) -> list[int]:
    """The frames of env ``env``'s stack, oldest first, by their value."""
    pixels = stack.stacked()["pixels"][env].reshape(stack.depth, 3, 4, 2)
    return [int(p[0, 0, 0]) for p in pixels]


def test_a_reset_pads_with_the_first_frame_and_steps_roll_it_out_oldest_first():
    stack = FrameStack(CAMERA, 3, num_envs=1)
    stack.reset(0, frame(7))
    assert values(stack, 0) == [7, 7, 7]
    stack.push(0, frame(8))
    assert values(stack, 0) == [7, 7, 8]
    stack.push(0, frame(9))
    stack.push(0, frame(10))
    assert values(stack, 0) == [8, 9, 10]
    stack.reset(0, frame(1))  # a new episode forgets the last one's frames
    assert values(stack, 0) == [1, 1, 1]


def test_stacks_have_the_policy_s_shapes_and_dtypes():
    stack = FrameStack(CAMERA, 3, num_envs=2)
    stack.reset(0, frame(1))
    stack.reset(1, frame(2))
    stack.push(1, frame(3))
    out = stack.stacked()
    assert out["pixels"].dtype == np.uint8 and out["pixels"].shape == (2, 9, 4, 2)  # [n, k*C, H, W]
    assert out["state"].dtype == np.float32 and out["state"].shape == (2, 6)  # [n, k*width]
    np.testing.assert_array_equal(out["pixels"][1, :, 0, 0], [2, 2, 2, 2, 2, 2, 3, 3, 3])  # channels of a frame together
    np.testing.assert_array_equal(out["state"][1], [2, -2, 2, -2, 3, -3])


def test_environments_keep_stacks_of_their_own():
    stack = FrameStack(CAMERA, 2, num_envs=3)
    for env in range(3):
        stack.reset(env, frame(10 * env))
    stack.push(1, frame(11))
    stack.reset(2, frame(50))
    assert [values(stack, env) for env in range(3)] == [[0, 0], [10, 11], [50, 50]]
    chosen = stack.stacked([2, 0])
    assert chosen["pixels"].shape[0] == 2 and chosen["pixels"][0, 0, 0, 0] == 50 and chosen["pixels"][1, 0, 0, 0] == 0


def test_the_stacks_are_copies_the_next_push_leaves_alone():
    stack = FrameStack(CAMERA, 2, num_envs=1)
    stack.reset(0, frame(1))
    before = stack.stacked()
    stack.push(0, frame(2))
    assert before["pixels"].max() == 1


def test_depth_1_of_the_vector_is_the_vector_matrix_policies_took_before_stacks():
    vector = ObservationSpec.vector(3)
    stack = FrameStack(vector, 1, num_envs=2)
    stack.reset(0, {"state": np.array([1, 2, 3], np.float32)})
    stack.reset(1, {"state": np.array([4, 5, 6], np.float32)})
    stack.push(1, {"state": np.array([7, 8, 9], np.float32)})
    out = stack.stacked()
    assert isinstance(out, np.ndarray) and out.dtype == np.float32
    np.testing.assert_array_equal(out, [[1, 2, 3], [7, 8, 9]])
    deeper = FrameStack(vector, 2, num_envs=1)
    deeper.reset(0, {"state": np.array([1, 2, 3], np.float32)})
    assert deeper.stacked()["state"].shape == (1, 6)  # stacks of the vector are fields, as images are
    one_image = FrameStack(CAMERA, 1, num_envs=1)
    one_image.reset(0, frame(4))
    assert one_image.stacked()["pixels"].shape == (1, 3, 4, 2)  # k = 1 of an image: the frame itself


def test_another_depth_keeps_the_newest_frames_and_pads_with_the_oldest_kept():
    stack = FrameStack(CAMERA, 3, num_envs=1)
    stack.reset(0, frame(1))
    stack.push(0, frame(2))
    stack.push(0, frame(3))
    assert values(stack.with_depth(2), 0) == [2, 3]
    assert values(stack.with_depth(5), 0) == [1, 1, 1, 2, 3]


@pytest.mark.parametrize("spec, depth", [({}, 1), ({"frame_stack": 3}, 3)])
def test_a_policy_spec_says_its_depth(spec, depth):
    assert frame_stack_of(spec) == depth


@pytest.mark.parametrize("depth", [0, 17, 2.0, "3", True])
def test_a_depth_the_replay_cannot_stack_is_a_bad_spec(depth):
    with pytest.raises(ProtocolError) as e:
        frame_stack_of({"frame_stack": depth})
    assert e.value.reason == "bad_spec"
