"""Exploration noise correlated in time: each world's noise a coloured Gaussian series.

A Gaussian policy explores by drawing a standard normal value per action dimension at every
step (white noise). A muscle low-passes its excitation (activation takes 10-40 ms), so white
noise at each 30-ms action largely averages out before it moves a joint. Eberhard et al.
(ICLR 2023, "Pink Noise Is All You Need") replace those draws by a series whose power falls as
1/f^beta over each episode: beta 0 is white, 1 pink, 2 red (Brownian); each value is still
N(0, 1), so the policy's distribution and its log-probability of an action are unchanged, only
successive draws are correlated. Pink was their best default across tasks.

`ColouredNoise` holds one series per world and action dimension, as long as an episode's
actions, drawn by the `colorednoise` package; a world's next episode draws a new one.
"""

from __future__ import annotations

import colorednoise
import numpy as np

COLOURS = {"white": 0.0, "pink": 1.0, "red": 2.0}
"""The exploration noises by name, each its spectrum's exponent beta."""


class ColouredNoise:
    """Standard normal noise for `num_envs` worlds of `act_dim` actions, each world's a series of
    `length` steps whose spectrum falls as 1/f^beta, started anew when the world's episode is."""

    def __init__(self, colour: str, num_envs: int, act_dim: int, length: int, rng: np.random.Generator):
        if colour not in COLOURS:
            raise ValueError(f"exploration noise must be one of {', '.join(COLOURS)}, got {colour!r}")
        if length < 2:
            raise ValueError(f"a noise series needs at least 2 steps, got {length}")
        self.beta, self.act_dim, self.length, self.rng = COLOURS[colour], act_dim, length, rng
        self._series = np.zeros((num_envs, act_dim, length), np.float32)
        self._at = np.zeros(num_envs, np.intp)
        for env in range(num_envs):
            self.reset(env)

    def reset(self, env: int) -> None:
        """World `env`'s episode has begun: a new series."""
        self._series[env] = colorednoise.powerlaw_psd_gaussian(self.beta, (self.act_dim, self.length),
                                                               random_state=self.rng)
        self._at[env] = 0

    def next(self) -> np.ndarray:
        """This step's noise of every world, float32 [num_envs, act_dim]; a world whose series is
        used up (an episode longer than `length`) goes on with a new one."""
        for env in np.flatnonzero(self._at >= self.length):
            self.reset(env)
        noise = self._series[np.arange(len(self._at)), :, self._at]
        self._at += 1
        return noise
