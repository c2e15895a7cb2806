"""Wrappers around `RunEnv`."""

from __future__ import annotations

from typing import Any

import gymnasium as gym


class ActionRepeat(gym.Wrapper):
    """Apply each action `repeat` times (the 2017 reference solution used 3).

    Rewards are summed; the repeat stops early when the episode terminates or is truncated.
    The observation and info are those of the last inner step; `info["inner_steps"]` says how
    many inner steps were taken (the sum of the inner env's own `inner_steps`, where it has them).
    """

    def __init__(self, env: gym.Env, repeat: int = 3):
        super().__init__(env)
        if repeat < 1:
            raise ValueError(f"repeat must be at least 1, got {repeat}")
        self.repeat = repeat

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        total, inner_steps = 0.0, 0
        for _ in range(self.repeat):
            obs, reward, terminated, truncated, info = self.env.step(action)
            total += reward
            inner_steps += int(info.get("inner_steps", 1))  # an env that repeats actions itself counts its own
            if terminated or truncated:
                break
        info["inner_steps"] = inner_steps
        return obs, total, terminated, truncated, info
