"""Trust Region Policy Optimization: settings, training state and the update, apart from any process.

`update(state, batch, config)` is the whole algorithm on one batch from the replay server's queue
table, top to bottom, as sb3-contrib's TRPO does it: PPO's estimates (values, the proximal
policy's log-probabilities, GAE or V-trace advantages and targets, `l2r.learner.ppo.estimate`),
advantages standardised over the batch; then one policy step, the natural gradient of the
surrogate mean(ratio * A) found by conjugate gradients on Fisher-vector products of the mean KL
from the proximal policy, scaled to the trust region's edge and backtracked until the surrogate
improves within `max_kl` (or not taken); then the value network by Adam, `value_epochs` passes in
minibatches of `value_minibatch_size`. The pieces of the natural gradient are `l2r.learner.curvature`'s.

The networks, the batch, the training state and the lag correction are PPO's (`l2r.learner.ppo`):
the TrainState's optimizer is the value network's alone, since the policy moves by line search.
`state.updates` counts policy steps, one per batch.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch

from l2r.learner import ppo
from l2r.learner.common import adam
from l2r.learner.curvature import (
    conjugate_gradients, fisher_vector_product, flat_grad, gaussian_kl, line_search, trust_region_scale,
)
from l2r.learner.ppo import LOG_RATIO_BOUND, Batch, TrainState, batch_metrics, check_on_policy, estimate

broadcast_state = ppo.broadcast_state  # for the daemon; l2r-learner runs TRPO on one rank alone
from l2r.policy import tanh_gaussian_log_prob


@dataclass
class TRPOConfig:
    """Algorithm settings. Defaults: RL Baselines3 Zoo's for sb3-contrib's TRPO on MuJoCo tasks
    (hyperparams/trpo.yml, the pybullet defaults its Hopper-v4 and Walker2d-v4 entries take), else
    sb3-contrib's TRPO defaults, but for the lag correction."""

    batch_size: int = 2048
    """Transitions per update. Zoo: n_steps 1024 x n_envs 2."""
    max_kl: float = 0.01
    """The trust region: the mean KL from the proximal policy a step may reach. sb3-contrib's
    target_kl (the Zoo keeps it but for HalfCheetah, 0.04)."""
    cg_steps: int = 25
    """Conjugate-gradient steps for the natural gradient. Zoo: cg_max_steps 25 (sb3-contrib: 15)."""
    cg_damping: float = 0.1
    """Multiple of the identity added to the Fisher. Zoo and sb3-contrib: cg_damping 0.1."""
    line_search_shrink: float = 0.8
    """Each backtracking try takes this fraction of the last. sb3-contrib's line_search_shrinking_factor."""
    line_search_steps: int = 10
    """Backtracking tries before the step is given up. sb3-contrib's line_search_max_iter."""
    value_epochs: int = 20
    """Passes of the value network over each batch. Zoo: n_critic_updates 20 (sb3-contrib: 10)."""
    value_minibatch_size: int = 128
    """Transitions per value-network step. Zoo and sb3-contrib: batch_size 128."""
    lr: float = 1e-3
    """Adam learning rate of the value network. Zoo and sb3-contrib: learning_rate 1e-3."""
    gamma: float = 0.99
    """Discount per environment step of the policy. Zoo: 0.99."""
    gae_lambda: float = 0.95
    """lambda of GAE (and the trace cut of V-trace). Zoo: 0.95."""
    normalize_advantages: bool = True
    """Advantages standardised over the batch. sb3-contrib's normalize_advantage."""
    reward_scale: float = 1.0
    """Multiplier on rewards before anything else (the Zoo's VecNormalize also scales rewards; l2r does not)."""
    lag_correction: str = "ratio"
    """What to do about the actors' policy lag: 'none', 'ratio' or 'vtrace', as PPO's (PPOConfig):
    'ratio' divides the surrogate's ratio by the acting policy's probabilities. sb3-contrib has no lag."""
    is_clip: float = 1.0
    """V-trace: the importance ratios' truncation."""
    hidden: tuple[int, ...] = (64, 64)
    """Widths of the hidden layers of policy and value network. sb3's MlpPolicy: 64, 64."""
    activation: str = "tanh"
    """Hidden activation. sb3's MlpPolicy: tanh."""
    layer_norm: bool = False
    """LayerNorm after each hidden Linear, before the activation."""
    relative_x: bool = False
    """The networks see world x coordinates as distances from the pelvis (see ObservationFilter)."""
    normalize_obs: bool = False
    """The networks see observations standardised by running statistics (the Zoo: normalize true)."""

    def __post_init__(self) -> None:
        check_on_policy(self)
        if self.max_kl <= 0 or self.cg_damping < 0 or not 0.0 < self.line_search_shrink < 1.0:
            raise ValueError(f"need max_kl > 0, cg_damping >= 0 and 0 < line_search_shrink < 1, got {self.max_kl}, "
                             f"{self.cg_damping}, {self.line_search_shrink}")
        if min(self.cg_steps, self.line_search_steps, self.value_epochs, self.value_minibatch_size) < 1:
            raise ValueError("cg_steps, line_search_steps, value_epochs and value_minibatch_size must be >= 1")
        if self.batch_size < 2:
            raise ValueError(f"batch_size must be >= 2 (advantages are standardised over it), got {self.batch_size}")

    def to_dict(self) -> dict:
        return {**asdict(self), "hidden": list(self.hidden)}


def init_state(config: TRPOConfig, obs_dim: int, act_dim: int, device: str | torch.device = "cpu",
               seed: int | None = None) -> TrainState:
    """PPO's networks; Adam over the value network alone (eps as sb3's policies set it)."""
    actor, value = ppo.init_networks(config, obs_dim, act_dim, device, seed)
    return TrainState(actor, value, adam(value.parameters(), config.lr, torch.device(device), eps=1e-5))


def update(state: TrainState, batch: Batch, config: TRPOConfig) -> dict[str, torch.Tensor]:
    """One TRPO update on one queue batch: one policy step, then the value network's. Returns metrics."""
    # 1-2. Before any step: values, the proximal policy's log-probabilities, advantages and targets.
    estimates = estimate(state, batch, config)
    advantages = estimates.advantages
    if config.normalize_advantages:
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)

    # 3. The surrogate and the mean KL from the proximal policy, as functions of the policy's parameters.
    params = list(state.actor.parameters())
    with torch.no_grad():
        proximal_mean, proximal_log_std = state.actor(batch.obs)

    def surrogate_and_kl() -> tuple[torch.Tensor, torch.Tensor]:
        mean, log_std = state.actor(batch.obs)
        log_ratio = tanh_gaussian_log_prob(mean, log_std, batch.action) - estimates.old_log_prob
        surrogate = (log_ratio.clamp(-LOG_RATIO_BOUND, LOG_RATIO_BOUND).exp() * advantages).mean()
        return surrogate, gaussian_kl(proximal_mean, proximal_log_std, mean, log_std).mean()

    # 4. The natural gradient F^-1 g by conjugate gradients, scaled so its quadratic KL is max_kl.
    surrogate, kl = surrogate_and_kl()
    gradient = flat_grad(surrogate, params, retain_graph=True)
    fisher = fisher_vector_product(kl, params, config.cg_damping)
    direction = conjugate_gradients(fisher, gradient, config.cg_steps)
    step = trust_region_scale(direction @ fisher(direction), config.max_kl) * direction

    # 5. Backtracking: the first fraction of the step that improves the surrogate within max_kl, or none.
    search = line_search(params, step.detach(), surrogate_and_kl, float(surrogate.detach()), config.max_kl,
                         config.line_search_shrink, config.line_search_steps)
    state.updates += 1

    # 6. The value network: epochs of Adam minibatch steps on the squared error to the targets.
    n, size = len(batch.obs), min(config.value_minibatch_size, len(batch.obs))
    filtered_obs = state.actor.observation_filter(batch.obs)
    value_loss_sum, value_steps = torch.zeros((), device=filtered_obs.device), 0
    for _ in range(config.value_epochs):
        order = torch.randperm(n, device=filtered_obs.device)
        for start in range(0, n, size):
            mb = order[start:start + size]
            value_loss = (state.value(filtered_obs[mb]) - estimates.targets[mb]).pow(2).mean()
            state.optimizer.zero_grad(set_to_none=True)
            value_loss.backward()
            state.optimizer.step()
            value_loss_sum += value_loss.detach()
            value_steps += 1

    with torch.no_grad():
        entropy = state.actor.evaluate(batch.obs, batch.action)[1]
    return {"surrogate": torch.tensor(search.surrogate), "kl": torch.tensor(search.kl),
            "step_fraction": torch.tensor(search.fraction), "value_loss": value_loss_sum / value_steps,
            "entropy": entropy.mean()} | batch_metrics(estimates, batch)

