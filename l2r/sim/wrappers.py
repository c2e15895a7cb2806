"""Wrappers around `RunEnv`."""

from __future__ import annotations

from typing import Any

import gymnasium as gym


class ActionRepeat(gym.Wrapper):
    """Apply each action `repeat` times (the 2017 reference solution used 3).

    Rewards are summed; the repeat stops early when the episode terminates or is truncated.
    The observation and info are those of the last inner step; `info["inner_steps"]` says how
    many inner steps were taken.
    """

    def __init__(self, env: gym.Env, repeat: int = 3):
        super().__init__(env)
        if repeat < 1:
            raise ValueError(f"repeat must be at least 1, got {repeat}")
        self.repeat = repeat

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        total = 0.0
        for i in range(self.repeat):
            obs, reward, terminated, truncated, info = self.env.step(action)
            total += reward
            if terminated or truncated:
                break
        info["inner_steps"] = i + 1
        return obs, total, terminated, truncated, info
