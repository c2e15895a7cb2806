"""Coloured exploration noise: unit normal draws, correlated in time by colour, a new series per
episode, reproducible from the generator; and a policy explores with the draws it is given."""

import numpy as np
import pytest
import torch

from l2r.actors.noise import COLOURS, ColouredNoise
from l2r.policy import Policy, default_spec, tanh_gaussian_log_prob, to_excitation, to_tanh_space


def series(colour: str, seed: int = 0, steps: int = 334) -> np.ndarray:
    noise = ColouredNoise(colour, 8, 18, steps, np.random.default_rng(seed))
    return np.stack([noise.next() for _ in range(steps)], axis=-1)  # [envs, act_dim, steps]


def lag_one(x: np.ndarray) -> float:
    return float(np.corrcoef(x[..., :-1].ravel(), x[..., 1:].ravel())[0, 1])


@pytest.mark.parametrize("colour, low, high", [("white", -0.1, 0.1), ("pink", 0.4, 0.8), ("red", 0.9, 1.0)])
def test_each_colour_correlates_successive_draws_as_its_spectrum_says(colour, low, high):
    draws = series(colour)
    assert low < lag_one(draws) < high
    assert abs(draws.mean()) < 0.2 and 0.6 < draws.std() < 1.2  # N(0, 1) draws (a red series wanders)


def test_a_new_episode_and_a_used_up_series_start_a_new_one_and_the_generator_repeats_them():
    noise = ColouredNoise("pink", 2, 3, 4, np.random.default_rng(1))
    first = [noise.next() for _ in range(4)]
    fifth = noise.next()  # past the series' 4 steps: a new series, no error
    assert fifth.shape == (2, 3) and not np.allclose(fifth, first[0])
    noise.reset(0)
    again = ColouredNoise("pink", 2, 3, 4, np.random.default_rng(1))
    assert all(np.array_equal(a, b) for a, b in zip(first, [again.next() for _ in range(4)]))
    with pytest.raises(ValueError, match="exploration noise must be one of white, pink, red"):
        ColouredNoise("blue", 1, 1, 4, np.random.default_rng(0))
    assert set(COLOURS) == {"white", "pink", "red"}


def test_a_policy_explores_with_the_draws_it_is_given():
    policy = Policy(default_spec(41, 18))
    obs = torch.randn(5, 41)
    draws = torch.randn(5, 18)
    excitation, log_prob = policy.explore(obs, draws)
    mean, log_std = policy(obs)
    torch.testing.assert_close(excitation, to_excitation(torch.tanh(mean + log_std.exp() * draws)))
    torch.testing.assert_close(log_prob, tanh_gaussian_log_prob(mean, log_std, to_tanh_space(excitation)))
    assert not torch.equal(policy.explore(obs)[0], excitation)  # without draws, its own
