"""ACKTR (actor-critic using Kronecker-factored trust region): settings, training state and the
update, apart from any process.

`update(state, batch, config)` is the whole algorithm on one batch from the replay server's queue
table, top to bottom, as Wu et al. (2017) describe it: PPO's estimates (values, the proximal
policy's log-probabilities, GAE or V-trace advantages and targets, `l2r.learner.ppo.estimate`),
advantages standardised over the batch; one forward pass of policy and value network, recorded
for K-FAC; the Fisher statistics from log-likelihoods of targets sampled from the networks
themselves (actions from the policy; values with unit Gaussian noise: the critic's Gauss-Newton
matrix) taken into the running factors; the actor-critic loss's gradient preconditioned by the
damped Kronecker-factored inverse; the step size min(lr, sqrt(2 max_kl / (d' F d))) for the
natural gradient d of each network (each in its own trust region); one SGD step with momentum;
then, with a `target_kl`, the step size lr adapted to the KL the step measurably made, as the
paper's MuJoCo code adapts it (`adapted_step_size`).
Every Linear layer of both networks gets natural gradients; the statistics and their inverses
are renewed every update.
The K-FAC pieces are `l2r.learner.curvature.KFAC`.

The networks, the batch and the lag correction are PPO's (`l2r.learner.ppo`); the training state
is PPO's with the K-FAC factors added. `state.updates` counts steps, one per batch.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Mapping

import torch

from l2r.learner import ppo
from l2r.learner.curvature import KFAC, gaussian_kl, trust_region_scale
from l2r.learner.ppo import LOG_RATIO_BOUND, Batch, batch_metrics, check_on_policy, estimate
from l2r.policy import tanh_gaussian_log_prob

broadcast_state = ppo.broadcast_state  # for the daemon; l2r-learner runs ACKTR on one rank alone


@dataclass
class ACKTRConfig:
    """Algorithm settings. Defaults: the ACKTR paper's (Wu et al. 2017, and the code it published
    with it, openai/baselines' acktr) for its optimiser; its MuJoCo script's for the rollout."""

    batch_size: int = 2500
    """Transitions per update. The paper's MuJoCo script: timesteps_per_batch 2500."""
    lr: float = 0.03
    """eta_max, the largest step size (SGD with momentum); with `target_kl`, its start. The paper's
    MuJoCo code: 0.03, adapted (its Atari code: 0.25, fixed)."""
    target_kl: float = 0.002
    """After each step, the KL the step made between the policy before and after it, on the batch,
    adapts lr: divided by 1.5 above twice this, multiplied by 1.5 below half of it, kept within
    [1e-8, 1]. The paper's MuJoCo code: 0.002. 0: lr fixed."""
    max_kl: float = 0.001
    """delta, the trust region: the quadratic KL a step may reach. The paper: 0.001."""
    momentum: float = 0.9
    """SGD momentum on the scaled natural gradient. The paper's code: 0.9."""
    kfac_damping: float = 0.01
    """Added to the Kronecker-factored Fisher before inverting it (Tikhonov). The paper's code: 0.01."""
    kfac_decay: float = 0.99
    """Running-average decay of the K-FAC factors (the paper's statistics decay). The paper's code: 0.99."""
    value_coef: float = 1.0
    """Weight of the value loss, half the squared error. The paper's code: vf_coef 0.5 on the squared
    error, which is this 1.0."""
    value_fisher_coef: float = 1.0
    """Weight of the value network's sampled log-likelihood in the Fisher statistics. The paper's code: 1.0."""
    entropy_coef: float = 0.0
    """Weight of the entropy bonus (the pre-tanh Gaussian's). The paper's MuJoCo script: none."""
    gamma: float = 0.99
    """Discount per environment step of the policy. The paper's MuJoCo script: 0.99."""
    gae_lambda: float = 0.97
    """lambda of GAE (and the trace cut of V-trace). The paper's MuJoCo script: 0.97."""
    normalize_advantages: bool = True
    """Advantages standardised over the batch, as the paper's MuJoCo script does."""
    reward_scale: float = 1.0
    """Multiplier on rewards before anything else."""
    lag_correction: str = "ratio"
    """What to do about the actors' policy lag: 'none', 'ratio' or 'vtrace', as PPO's (PPOConfig):
    'ratio' weights the policy gradient by the ratio to the acting policy's probabilities."""
    is_clip: float = 1.0
    """V-trace: the importance ratios' truncation."""
    hidden: tuple[int, ...] = (64, 64)
    """Widths of the hidden layers of policy and value network. The paper's MuJoCo policy: 64, 64."""
    activation: str = "tanh"
    """Hidden activation. The paper's MuJoCo policy: tanh."""
    layer_norm: bool = False
    """Refused: K-FAC here covers Linear layers alone."""
    relative_x: bool = False
    """The networks see world x coordinates as distances from the pelvis (see ObservationFilter)."""
    normalize_obs: bool = False
    """The networks see observations standardised by running statistics (the paper's script filters them)."""

    def __post_init__(self) -> None:
        check_on_policy(self)
        if self.layer_norm:
            raise ValueError("ACKTR's K-FAC covers Linear layers alone: no layer_norm")
        if self.target_kl < 0:
            raise ValueError(f"target_kl must be >= 0 (0: a fixed lr), got {self.target_kl}")
        if self.lr <= 0 or self.max_kl <= 0 or self.kfac_damping <= 0:
            raise ValueError(f"lr, max_kl and kfac_damping must be > 0, got {self.lr}, {self.max_kl}, "
                             f"{self.kfac_damping}")
        if not 0.0 <= self.momentum < 1.0 or not 0.0 <= self.kfac_decay < 1.0:
            raise ValueError(f"need 0 <= momentum, kfac_decay < 1, got {self.momentum}, {self.kfac_decay}")
        if self.batch_size < 2:
            raise ValueError(f"batch_size must be >= 2 (advantages are standardised over it), got {self.batch_size}")

    def to_dict(self) -> dict:
        return {**asdict(self), "hidden": list(self.hidden)}


MIN_STEP_SIZE, MAX_STEP_SIZE, STEP_SIZE_FACTOR = 1e-8, 1.0, 1.5
"""The paper's MuJoCo code's bounds of the adapted step size, and its factor."""


@dataclass
class TrainState(ppo.TrainState):
    """PPO's training state (the optimizer SGD with momentum over both networks), the K-FAC factors
    and the step size lr now (the config's, or where target_kl adapts it, its latest value)."""

    curvature: KFAC = field(kw_only=True)
    step_size: float = field(kw_only=True)

    def set_learning_rates(self, config: ACKTRConfig) -> None:
        """A resumed run takes the command line's lr, unless it adapts its step size: that is trained state."""
        if not config.target_kl:
            self.step_size = config.lr

    def state_dict(self) -> dict:
        return super().state_dict() | {"curvature": self.curvature.state_dict(), "step_size": self.step_size}

    def load_state_dict(self, saved: Mapping) -> None:
        super().load_state_dict(saved)
        self.curvature.load_state_dict(saved["curvature"])
        self.step_size = float(saved.get("step_size", self.step_size))  # (checkpoints from before it: the config's)


def adapted_step_size(step_size: float, kl: float, target_kl: float) -> float:
    """The paper's MuJoCo rule: step_size / 1.5 when the step's measured KL passed 2 * target_kl,
    * 1.5 when it stayed under target_kl / 2, else as it was; within [1e-8, 1]."""
    if kl > 2.0 * target_kl:
        return max(MIN_STEP_SIZE, step_size / STEP_SIZE_FACTOR)
    if kl < 0.5 * target_kl:
        return min(MAX_STEP_SIZE, step_size * STEP_SIZE_FACTOR)
    return step_size


def init_state(config: ACKTRConfig, obs_dim: int, act_dim: int, device: str | torch.device = "cpu",
               seed: int | None = None) -> TrainState:
    """PPO's networks, SGD with momentum over both, and K-FAC over their Linear layers."""
    actor, value = ppo.init_networks(config, obs_dim, act_dim, device, seed)
    optimizer = torch.optim.SGD([*actor.parameters(), *value.parameters()], lr=config.lr, momentum=config.momentum)
    return TrainState(actor, value, optimizer, curvature=KFAC([actor, value], config.kfac_decay, config.kfac_damping),
                      step_size=config.lr)


def update(state: TrainState, batch: Batch, config: ACKTRConfig) -> dict[str, torch.Tensor]:
    """One ACKTR update on one queue batch: one natural-gradient step. Returns metrics."""
    # 1-2. Before any step: values, the proximal policy's log-probabilities, advantages and targets.
    estimates = estimate(state, batch, config)
    advantages = estimates.advantages
    if config.normalize_advantages:
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)

    # 3. One pass through both networks, each Linear layer's input and output kept for K-FAC.
    with state.curvature.recording():
        mean, log_std = state.actor(batch.obs)
        values = state.value(state.actor.observation_filter(batch.obs))

    # 4. The Fisher statistics: log-likelihoods of targets drawn from the networks' own predictions.
    with torch.no_grad():
        sampled = mean + log_std.exp() * torch.randn_like(mean)  # pre-tanh: the tanh adds no parameters
        sampled_values = values + torch.randn_like(values)
    policy_likelihood = (-0.5 * ((sampled - mean) / log_std.exp()).pow(2) - log_std).sum(-1).mean()
    value_likelihood = -0.5 * (values - sampled_values).pow(2).mean()
    state.curvature.update_factors(policy_likelihood + config.value_fisher_coef * value_likelihood)

    # 5. The actor-critic loss: the policy gradient (weighted by the lag's ratio), entropy, value error.
    log_ratio = tanh_gaussian_log_prob(mean, log_std, batch.action) - estimates.old_log_prob
    policy_loss = -(log_ratio.clamp(-LOG_RATIO_BOUND, LOG_RATIO_BOUND).exp() * advantages).mean()
    entropy = (log_std + 0.5 * math.log(2 * math.pi * math.e)).sum(-1).mean()
    value_loss = 0.5 * (values - estimates.targets).pow(2).mean()
    state.optimizer.zero_grad(set_to_none=True)
    (policy_loss - config.entropy_coef * entropy + config.value_coef * value_loss).backward()

    # 6. The natural gradient d of each network, scaled so that lr times it keeps d' F d within its
    #    own trust region (the paper's MuJoCo code steps policy and value network apart, each with
    #    its own bound; one joint bound let the value network's large gradient starve the policy):
    #    the step is min(lr, sqrt(2 max_kl / d' F d)) d, with d' F d = d' g.
    lr = state.step_size
    natural = dict(zip(state.curvature.parameters(), state.curvature.natural_gradient()))
    step_sizes, quadratic_kls = [], []
    for network in (state.actor, state.value):
        pairs = [(p, natural[p]) for p in network.parameters()]
        quadratic = sum((d * p.grad).sum() for p, d in pairs).clamp(min=0.0)  # >= 0 but for rounding
        scale = trust_region_scale(lr ** 2 * quadratic, config.max_kl).clamp(max=1.0)
        for p, d in pairs:
            p.grad = scale * d
        step_sizes.append(lr * scale.detach())
        quadratic_kls.append(0.5 * step_sizes[-1] ** 2 * quadratic.detach())
    for group in state.optimizer.param_groups:
        group["lr"] = lr
    state.optimizer.step()
    state.updates += 1

    # 7. The KL the step made, measured; with a target, the next step size follows it.
    with torch.no_grad():
        kl = gaussian_kl(mean, log_std, *state.actor(batch.obs)).mean()
    if config.target_kl:
        state.step_size = adapted_step_size(lr, float(kl), config.target_kl)
    return {"kl": kl, "lr": torch.tensor(lr), "policy_loss": policy_loss.detach(), "value_loss": value_loss.detach(),
            "entropy": entropy.detach(),
            "step_size": step_sizes[0], "value_step_size": step_sizes[1], "quadratic_kl": quadratic_kls[0],
            "value_quadratic_kl": quadratic_kls[1]} | batch_metrics(estimates, batch)
