"""Synchronous advantage actor-critic (A2C): PPO's update with one gradient step per batch.

A2C's update on one queue batch, top to bottom, is `l2r.learner.ppo.update` with `epochs` 1 and
`minibatches` 1 (the same function the learner daemon and the tests call):

1. the values V(s) and V(s') of the batch, then advantages A = G - V(s) against n-step returns G:
   GAE with lambda 1 is the discounted rewards to the end of each trajectory piece plus the
   discounted V of the observation after it (nothing after a termination);
2. one gradient step on the policy loss, the value loss (V(s) - G)^2 / 2 and the entropy bonus,
   the gradient norm clipped, by RMSprop.

PPO's clipped surrogate is A2C's policy loss there: at the only step the learner's policy is the
one the batch's advantages were computed with, so with `lag_correction` 'none' the ratio is 1 and
the surrogate's gradient is the policy gradient -A grad log pi(a|s). l2r's actors act with weights
a version or two older than the learner's (Stable-Baselines3's A2C has no such lag: its rollout
comes from the policy it updates), so the default 'ratio' weights each action by pi/mu, the
learner's probability over the acting policy's, clipped to 1 +- clip as PPO's ratio is. V-trace
('vtrace') is the other correction.
"""

from __future__ import annotations

from dataclasses import dataclass

from l2r.learner.ppo import PPOConfig


@dataclass
class A2CConfig(PPOConfig):
    """PPO's settings at A2C's values: Stable-Baselines3's A2C defaults, which RL Baselines3 Zoo keeps
    for the MuJoCo tasks (its hyperparams/a2c.yml sets `normalize: true` and nothing else for
    Hopper, HalfCheetah, Walker2d and Ant). Hidden layers (64, 64) with tanh, gamma 0.99, entropy
    coefficient 0 and a gradient-norm clip of 0.5 are PPO's and Stable-Baselines3's alike."""

    batch_size: int = 5
    """Transitions per update: Stable-Baselines3's n_steps 5 of the zoo's one environment."""
    epochs: int = 1
    """One pass..."""
    minibatches: int = 1
    """... in one gradient step on the whole batch."""
    lr: float = 7e-4
    """Stable-Baselines3's learning rate, constant (the zoo's MuJoCo entries keep it)."""
    gae_lambda: float = 1.0
    """Stable-Baselines3's: n-step returns, to the end of each trajectory piece."""
    value_coef: float = 1.0
    """Stable-Baselines3's vf_coef 0.5 on the squared error (V - G)^2, which is this 1.0 on l2r's
    (and CleanRL's) value loss of half the squared error."""
    normalize_advantages: bool = False
    """Stable-Baselines3's normalize_advantage default."""
    optimizer: str = "rmsprop"
    """Stable-Baselines3's use_rms_prop default: RMSprop, alpha 0.99, eps 1e-5."""
