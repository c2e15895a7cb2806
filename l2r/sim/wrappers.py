"""Wrappers around `RunEnv` (the noise wrappers take any env with a Box space)."""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np


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


class _GaussianNoise:
    """Noise of one standard deviation from a generator of the wrapper's own, seeded by each
    seeded reset (a stream of its own, apart from the env's episode draws), so that a seed
    repeats the noise too."""

    def __init__(self, std: float, stream: int):
        if type(std) not in (int, float) or not math.isfinite(std) or std < 0:
            raise ValueError(f"noise std must be a number from 0 up, got {std!r}")
        self.std, self._stream = float(std), stream
        self._rng = np.random.default_rng()

    def seed(self, seed: int | None) -> None:
        if seed is not None:
            self._rng = np.random.default_rng([seed, self._stream])

    def added(self, values: np.ndarray) -> np.ndarray:
        return (values + self._rng.normal(0.0, self.std, values.shape)).astype(values.dtype, copy=False)


def _box(space: gym.Space, what: str) -> None:
    if not isinstance(space, gym.spaces.Box):
        raise ValueError(f"{what} noise needs a Box {what} space, got {space}")


class ObservationNoise(gym.ObservationWrapper):
    """Add N(0, std²) to every value the agent observes (the observation's own units: m, rad,
    m/s, rad/s on the runner); the simulation is untouched."""

    def __init__(self, env: gym.Env, std: float):
        super().__init__(env)
        _box(env.observation_space, "observation")
        self.noise = _GaussianNoise(std, stream=1)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[Any, dict[str, Any]]:
        self.noise.seed(seed)
        return super().reset(seed=seed, options=options)

    def observation(self, observation: np.ndarray) -> np.ndarray:
        return self.noise.added(observation)


class ActionNoise(gym.ActionWrapper):
    """Add N(0, std²) to every value of the action before the env takes it (the runner clips the
    excitations to [0, 1] after): a disturbance of the actuation, which the agent does not see."""

    def __init__(self, env: gym.Env, std: float):
        super().__init__(env)
        _box(env.action_space, "action")
        self.noise = _GaussianNoise(std, stream=2)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[Any, dict[str, Any]]:
        self.noise.seed(seed)
        return super().reset(seed=seed, options=options)

    def action(self, action: np.ndarray) -> np.ndarray:
        return self.noise.added(np.asarray(action, dtype=np.float64))
