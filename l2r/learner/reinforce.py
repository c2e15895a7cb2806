"""REINFORCE with a learnt value baseline: PPO's update with one gradient step per batch on
Monte-Carlo returns.

REINFORCE's update on one queue batch, top to bottom, is `l2r.learner.ppo.update` with `epochs` 1,
`minibatches` 1 and `gae_lambda` 1 (the same function the learner daemon and the tests call):

1. the returns G[t] = r[t] + gamma * r[t+1] + ... to the end of each episode, and the baseline's
   advantages A = G - V(s): GAE with lambda 1. A queue batch is pieces of trajectories, so an
   episode the batch cuts (or a time limit) ends its return with the discounted V of the
   observation after the cut, the one bootstrap left; a termination ends it with nothing;
2. one gradient step on -A log pi(a|s), A standardised over the batch, and on the baseline's
   regression to the returns, (V(s) - G)^2 / 2, by Adam.

With `lag_correction` 'none' the ratio is 1 at that step and the clipped surrogate's gradient is
REINFORCE's -A grad log pi(a|s); the default 'ratio' weights each action by the importance ratio
pi/mu of the learner's policy to the acting one, clipped to 1 +- clip (the actors act with weights
a version or two behind; see l2r.learner.a2c).

The settings are Spinning Up's vanilla policy gradient (VPG: 4,000 environment steps per update,
one policy step at 3e-4 by Adam, (64, 64) tanh networks, advantages standardised), but for its
GAE lambda 0.97, here 1 (Monte-Carlo returns), and its value baseline, fitted there by 80 separate
Adam steps at 1e-3 per batch and here by the same single step as the policy.
"""

from __future__ import annotations

from dataclasses import dataclass

from l2r.learner.ppo import PPOConfig


@dataclass
class ReinforceConfig(PPOConfig):
    """PPO's settings at REINFORCE's values (module docstring); the rest are PPO's: gamma 0.99,
    (64, 64) tanh networks, value coefficient 0.5, no entropy bonus, a gradient-norm clip of 0.5."""

    batch_size: int = 4000
    """Transitions per update: Spinning Up VPG's steps per epoch."""
    epochs: int = 1
    """One pass..."""
    minibatches: int = 1
    """... in one gradient step on the whole batch."""
    lr: float = 3e-4
    """Spinning Up VPG's policy learning rate (Adam)."""
    gae_lambda: float = 1.0
    """Monte-Carlo returns."""
    normalize_advantages: bool = True
    """Spinning Up VPG's: advantages standardised over the batch."""
