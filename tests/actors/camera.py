"""A small camera task for actor tests: the suite's cartpole seen in 16 × 16 frames (a render
costs a fraction of an 84 × 84 one), its episodes cut at 6 steps so that a few seconds see resets."""

import ctypes.util

import gymnasium

CAMERA = "tests.actors.camera:SmallCamera-v0"
IMAGE_SIZE = 16
EPISODE_STEPS = 6
RENDERER = bool(ctypes.util.find_library("EGL") or ctypes.util.find_library("OSMesa"))
"""Whether this machine has an OpenGL the control tasks can render with (tests skip without)."""

gymnasium.register("SmallCamera-v0", entry_point="l2r.control.env:ControlEnv", max_episode_steps=EPISODE_STEPS,
                   kwargs={"domain": "cartpole", "task": "swingup", "image_size": IMAGE_SIZE})
