"""The observation spec and action width of a task, read off its gymnasium spaces.

`l2r up` plans its daemons by them and `l2r-learner --env-id` builds its networks by them; both
ask here, so a task either trains everywhere or is refused in the same words.
"""

from __future__ import annotations

import functools
import math

from typing import Any

import gymnasium
import numpy as np

from l2r.families import PIXELS, family_of
from l2r.protocol.observations import ObservationSpec


@functools.cache  # l2r up asks several times at start (checks, daemon flags, disk estimate); each makes the env
def task_spaces(env_id: str, image_size: int | None = None) -> tuple[ObservationSpec, int]:
    """The observation spec and action width of a gymnasium task (l2r's own ids included), a
    camera task's at `image_size` (None: its own); ValueError, saying why, for one l2r cannot train on."""
    import l2r.control  # noqa: F401  (registers the camera tasks' ids)
    import l2r.photo  # noqa: F401  (registers the photo tasks')
    import l2r.sim  # noqa: F401  (registers the runner's)

    try:
        env = gymnasium.make(env_id, **image_size_option(env_id, image_size))
    except gymnasium.error.Error as e:
        raise ValueError(str(e)) from None
    try:
        if not isinstance(env.action_space, gymnasium.spaces.Box):
            raise ValueError(f"its actions are {env.action_space}; l2r takes a Box")
        return ObservationSpec.from_space(env.observation_space), int(math.prod(env.action_space.shape))
    finally:
        env.close()


def image_size_option(env_id: str, image_size: int | None) -> dict[str, int]:
    """The keyword that makes a camera task render frames of `image_size` pixels a side (none for
    None); ValueError for another task, which has no frames to size."""
    if image_size is None:
        return {}
    if family_of(env_id) != PIXELS:
        raise ValueError(f"an image size is for the camera tasks (l2r/dmc-...), not {env_id}")
    return {"image_size": image_size}


def photo_goals_option(env_id: str, goals: str | None) -> dict[str, str]:
    """The keyword that makes the photo tuner draw its goals as `goals` says (l2r.photo.env.GOALS;
    none for None); ValueError for another task, which has no goals to draw."""
    from l2r.photo import TUNE_IDS  # (l2r.photo imports this module)

    if goals is None:
        return {}
    if env_id not in TUNE_IDS:
        raise ValueError(f"goals are the photo tuner's ({', '.join(TUNE_IDS)}), not {env_id}'s")
    return {"goals": goals}


def checked_action(task: str, action: Any, shape: tuple[int, ...], dtype: type = np.float32) -> np.ndarray:
    """`action` as an array of `dtype` clipped to [-1, 1], or a ValueError naming `task` and what is
    wrong with it (not numbers, another shape than `shape`, non-finite entries): what l2r's own
    tasks, whose actions all lie in [-1, 1], check in `step`."""
    try:
        action = np.asarray(action, dtype=dtype)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{task}: the action is not an array of numbers ({e})") from None
    if action.shape != shape:
        raise ValueError(f"{task}: the action has shape {action.shape}, expected {shape}")
    if not np.isfinite(action).all():
        raise ValueError(f"{task}: the action has non-finite entries: {action.tolist()}")
    return np.clip(action, -1.0, 1.0)
