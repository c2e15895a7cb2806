"""`ControlEnv`: a DeepMind Control suite task seen through a camera, as a gymnasium environment.

One gymnasium step is one policy step: the action is held for `action_repeat` steps of the suite
(2 for every task, as DrQ-v2 trains them), the rewards are summed and one frame is rendered at
the end. The observation is a dict: `pixels`, a single 3×84×84 uint8 frame, channels first
(stacking frames is the replay's job), and with `with_state=True` also `state`, the suite's
observation flattened to float32. Episodes end after the suite's 1000 steps as a truncation.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from l2r.control import rendering
from l2r.spaces import checked_action

rendering.choose_backend()  # before mujoco and dm_control are imported: both read MUJOCO_GL then

import mujoco  # noqa: E402
from dm_control import suite  # noqa: E402
from dm_control.mujoco.engine import Camera  # noqa: E402
from dm_control.mujoco.wrapper.mjbindings import sizes  # noqa: E402

ACTION_REPEAT = 2  # DrQ-v2's cfgs/config.yaml, for every task
IMAGE_SIZE = 84
CAMERAS = {"quadruped": 2}  # DrQ-v2's camera for the quadruped, closer in; camera 0 elsewhere


def forget_arrays_mujoco_lacks() -> list[str]:
    """Drop from dm_control's table of MuJoCo arrays those this MuJoCo does not have; return them.

    dm-control 1.0.50 generated the table from MuJoCo 3.17's headers, and MuJoCo 4.0 removed nine
    flex-vertex arrays from it: dm_control's Physics looks every entry up and fails on any model.
    No suite task has a flex, so nothing the tasks use goes missing.
    """
    empty = mujoco.MjModel.from_xml_string("<mujoco/>")
    dropped = []
    for struct_name, struct in (("mjmodel", empty), ("mjdata", mujoco.MjData(empty))):
        table = sizes.array_sizes[struct_name]
        for name in [name for name in table if not hasattr(struct, name)]:
            del table[name]
            dropped.append(name)
    return dropped


DROPPED_ARRAYS = forget_arrays_mujoco_lacks()


class ControlEnv(gym.Env):
    """A suite task with camera observations.

    domain, task: the suite's names (`dm_control.suite.ALL_TASKS`), e.g. "cartpole", "swingup".
    action_repeat: suite steps per policy step; `info["inner_steps"]` says how many a step took
        (fewer only at the end of an episode), the frames papers count.
    image_size: the frame's height and width in pixels.
    with_state: add `state`, the suite's own observation flattened to float32.
    """

    metadata = {"render_modes": []}

    def __init__(
        self,
        domain: str,
        task: str,
        action_repeat: int = ACTION_REPEAT,
        image_size: int = IMAGE_SIZE,
        with_state: bool = False,
    ):
        if (domain, task) not in suite.ALL_TASKS:
            raise ValueError(f"no suite task {domain!r} {task!r}; the suite has {sorted(suite.ALL_TASKS)}")
        for name, value in (("action_repeat", action_repeat), ("image_size", image_size)):
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        if not isinstance(with_state, bool):
            raise ValueError(f"with_state must be True or False, got {with_state!r}")
        self.name = f"{domain}-{task}"
        self.action_repeat = action_repeat
        self.with_state = with_state
        self.control_env = suite.load(domain, task, visualize_reward=False)
        self.physics = self.control_env.physics
        # An offscreen buffer of the frame's size instead of the model's 640×480: the same
        # pixels, rendered faster (bench/render_speed.py); set before the first render makes it.
        self.physics.model.vis.global_.offwidth = image_size
        self.physics.model.vis.global_.offheight = image_size
        self.camera_id, self.image_size = CAMERAS.get(domain, 0), image_size
        # Made at the first reset, so a process that reads the spaces alone (a learner, l2r up's
        # planning) needs no OpenGL.
        self.camera: Camera | None = None
        self.gl: rendering.GLReport | None = None

        spec = self.control_env.action_spec()
        self.suite_low, self.suite_high = spec.minimum, spec.maximum
        # [-1, 1] mapped onto the suite's bounds, as DrQ-v2 does: the identity but for the quadruped.
        self.action_space = gym.spaces.Box(-1.0, 1.0, spec.shape, np.float32)
        spaces = {"pixels": gym.spaces.Box(0, 255, (3, image_size, image_size), np.uint8)}
        if with_state:
            size = sum(int(np.prod(s.shape)) for s in self.control_env.observation_spec().values())
            spaces["state"] = gym.spaces.Box(-np.inf, np.inf, (size,), np.float32)
        self.observation_space = gym.spaces.Dict(spaces)
        self.episode_over = True

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict[str, np.ndarray], dict]:
        super().reset(seed=seed)
        if seed is not None:
            # The suite draws the initial state from the task's RandomState, which takes 32-bit seeds.
            self.control_env.task.random.seed(int(self.np_random.integers(2**32)))
        if self.camera is None:
            self.camera = Camera(self.physics, height=self.image_size, width=self.image_size, camera_id=self.camera_id)
            self.gl = rendering.gl_report(self.physics)
        time_step = self.control_env.reset()
        self.episode_over = False
        return self.observation(time_step.observation), {}

    def step(self, action: Any) -> tuple[dict[str, np.ndarray], float, bool, bool, dict[str, Any]]:
        if self.episode_over:
            raise RuntimeError(f"{self.name}: step() before the first reset() or after the episode ended; call reset()")
        action = checked_action(self.name, action, self.action_space.shape, np.float64)
        suite_action = self.suite_low + (action + 1.0) * 0.5 * (self.suite_high - self.suite_low)
        reward = 0.0
        for inner_steps in range(1, self.action_repeat + 1):
            time_step = self.control_env.step(suite_action)
            reward += time_step.reward
            if time_step.last():
                break
        # The suite ends its episodes at the time limit with discount 1; a task that ends one
        # early (none of the registered ones) gives discount 0.
        terminated = time_step.last() and time_step.discount == 0.0
        truncated = time_step.last() and not terminated
        self.episode_over = time_step.last()
        return self.observation(time_step.observation), reward, terminated, truncated, {"inner_steps": inner_steps}

    def pixels(self) -> np.ndarray:
        """The camera's view of the current state, uint8, channels first."""
        return np.ascontiguousarray(self.camera.render().transpose(2, 0, 1))

    def observation(self, suite_observation: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        observation = {"pixels": self.pixels()}
        if self.with_state:
            observation["state"] = np.concatenate(
                [np.asarray(value, np.float32).ravel() for value in suite_observation.values()]
            )
        return observation

    def close(self) -> None:
        self.physics.free()  # its GL context, now rather than at interpreter exit
