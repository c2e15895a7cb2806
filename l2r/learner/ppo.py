"""Proximal Policy Optimization: settings, training state and the update, apart from any process.

`update(state, batch, config)` is the whole algorithm on one batch from the replay server's queue
table, top to bottom: the batch's values and the proximal policy's log-probabilities, advantages
and value targets (GAE(lambda), or V-trace), then `epochs` passes over the batch in minibatches,
each one gradient step on the clipped surrogate, the value loss and the entropy bonus, with
advantages normalised per minibatch and the gradient norm clipped. The learner daemon and the
tests call this same function. Its first steps, `estimate` (values, log-probabilities, advantages
and targets), and the networks of `init_networks` are TRPO's and ACKTR's too.

A queue batch is pieces of trajectories laid end to end (`ends` marks where each stops: an episode
ended, or the piece did), with the true next observation of every step. So a time-limit
truncation bootstraps from the value of its final observation, a termination does not, and the
end of a piece bootstraps from the value of the observation after it.

Actors act with slightly older weights than the learner's (the lag asynchronous actors make).
`lag_correction` says what to do about it: 'none' treats the data as on-policy (the proximal
policy is the learner's at the start of the update); 'ratio' puts the acting policy's
log-probabilities in PPO's ratio, whose clipping then also truncates the lag's importance ratio;
'vtrace' computes advantages and value targets by V-trace (IMPALA), with importance ratios of the
proximal to the acting policy truncated at `is_clip`.

The policy is the tanh-Gaussian of `l2r.policy` (the family SAC trains, published the same way);
the value network has the same hidden layers and sees the observation through the policy's filter.
Everything runs in float32: PPO's ratios compare the learner's log-probabilities with the actors'.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Mapping

import numpy as np
import torch
from torch import nn

from l2r.learner.common import Transitions, adam, float_tensor, load_adam_state, policy_spec
from l2r.learner.distributed import average_gradients, broadcast, sum_over_ranks
from l2r.policy import ACTIVATIONS, LOG_STD_MAX, LOG_STD_MIN, Policy, mlp_trunk, to_tanh_space
from l2r.protocol import SampleBatch

LAG_CORRECTIONS = ("none", "ratio", "vtrace")
OPTIMIZERS = ("adam", "rmsprop")
LOG_RATIO_BOUND = 20.0


@dataclass
class PPOConfig:
    """Algorithm settings (defaults: CleanRL's and Stable-Baselines3's for MuJoCo tasks, but for the lag)."""

    batch_size: int = 2048
    """Transitions taken from the queue for one update (the rollout of synchronous PPO)."""
    epochs: int = 10
    """Passes over each batch."""
    minibatches: int = 32
    """Minibatches per pass: one gradient step each."""
    lr: float = 3e-4
    """Learning rate of policy and value network."""
    gamma: float = 0.99
    """Discount per environment step of the policy (one action-repeated step)."""
    gae_lambda: float = 0.95
    """lambda of GAE (and the trace cut of V-trace)."""
    clip: float = 0.2
    """The ratio's clip range: 1 - clip to 1 + clip."""
    value_coef: float = 0.5
    """Weight of the value loss."""
    entropy_coef: float = 0.0
    """Weight of the entropy bonus (the pre-tanh Gaussian's entropy)."""
    max_grad_norm: float = 0.5
    """Gradients are scaled down to at most this norm (policy and value together)."""
    normalize_advantages: bool = True
    """Advantages standardised within each minibatch."""
    reward_scale: float = 1.0
    """Multiplier on rewards before anything else."""
    lag_correction: str = "ratio"
    """What to do about the actors' policy lag: 'none', 'ratio' or 'vtrace' (module docstring).
    'ratio', not CleanRL's on-policy 'none': actors act two or three versions behind, and taking
    their data as on-policy let the policy's spread run away until its ratios overflowed (Hopper
    through the daemons, docs/training.md)."""
    is_clip: float = 1.0
    """V-trace: the importance ratios' truncation (rho-bar and c-bar)."""
    hidden: tuple[int, ...] = (64, 64)
    """Widths of the hidden layers, the same for policy and value network."""
    activation: str = "tanh"
    """Hidden activation: 'tanh', 'relu' or 'elu'."""
    layer_norm: bool = False
    """LayerNorm after each hidden Linear, before the activation."""
    relative_x: bool = False
    """The networks see world x coordinates as distances from the pelvis (see ObservationFilter)."""
    normalize_obs: bool = False
    """The networks see observations standardised by running statistics of the batches."""
    optimizer: str = "adam"
    """'adam' (eps 1e-5, as CleanRL and Stable-Baselines3 set it for PPO) or 'rmsprop' (alpha 0.99,
    eps 1e-5, as Stable-Baselines3 sets it for A2C)."""

    def __post_init__(self) -> None:
        check_on_policy(self)
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        if self.minibatches < 1 or self.epochs < 1 or self.batch_size < self.minibatches:
            raise ValueError(f"need epochs >= 1 and 1 <= minibatches <= batch_size, got {self.epochs}, "
                             f"{self.minibatches}, {self.batch_size}")
        if self.clip <= 0 or self.max_grad_norm <= 0:
            raise ValueError("clip and max_grad_norm must be > 0")

    def to_dict(self) -> dict:
        return {**asdict(self), "hidden": list(self.hidden)}


def check_on_policy(config) -> None:
    """The checks the on-policy configs (PPOConfig, TRPOConfig, ACKTRConfig) share, the hidden
    widths made a tuple of ints first; ValueError saying what is wrong."""
    config.hidden = tuple(int(h) for h in config.hidden)
    if config.activation not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {config.activation!r}")
    if config.lag_correction not in LAG_CORRECTIONS:
        raise ValueError(f"lag_correction must be one of {LAG_CORRECTIONS}, got {config.lag_correction!r}")
    if not 0.0 <= config.gamma <= 1.0 or not 0.0 <= config.gae_lambda <= 1.0:
        raise ValueError(f"need 0 <= gamma, gae_lambda <= 1, got {config.gamma}, {config.gae_lambda}")
    if config.is_clip <= 0:
        raise ValueError(f"is_clip must be > 0, got {config.is_clip}")


class ValueNetwork(nn.Module):
    """State value V(s) of filtered observations: the policy's hidden layers, one output."""

    def __init__(self, obs_dim: int, hidden: tuple[int, ...], activation: str, layer_norm: bool):
        super().__init__()
        self.trunk = mlp_trunk(obs_dim, hidden, activation, layer_norm)
        self.head = nn.Linear(hidden[-1], 1)

    def forward(self, filtered_obs: torch.Tensor) -> torch.Tensor:
        return self.head(self.trunk(filtered_obs)).squeeze(-1)


@dataclass
class TrainState:
    """Everything training changes: networks, optimizer and counters."""

    actor: Policy
    value: ValueNetwork
    optimizer: torch.optim.Optimizer
    updates: int = 0
    """Gradient steps taken so far (minibatch steps, over the whole run, across resumes)."""
    version: int = 0
    """Version of the last weights published; increases with every publication."""
    extra: dict = field(default_factory=dict)
    """Counters the hosting process wants checkpointed with the networks (plain values)."""

    def parameters(self) -> list[torch.Tensor]:
        return [*self.actor.parameters(), *self.value.parameters()]

    def set_learning_rates(self, config: PPOConfig) -> None:
        """Apply the config's learning rate (a resumed run takes the command line's, not the saved one)."""
        for group in self.optimizer.param_groups:
            group["lr"] = config.lr

    def state_dict(self) -> dict:
        return {"actor": self.actor.state_dict(), "value": self.value.state_dict(),
                "optimizer": self.optimizer.state_dict(), "updates": self.updates, "version": self.version,
                "extra": dict(self.extra)}

    def load_state_dict(self, saved: Mapping) -> None:
        self.actor.load_state_dict(saved["actor"])
        self.value.load_state_dict(saved["value"])
        load_adam_state(self.optimizer, saved["optimizer"])  # RMSprop's too: it has the same `capturable`
        self.updates, self.version = int(saved["updates"]), int(saved["version"])
        self.extra = dict(saved.get("extra", {}))


def init_networks(config, obs_dim: int, act_dim: int, device: str | torch.device = "cpu",
                  seed: int | None = None) -> tuple[Policy, ValueNetwork]:
    """Freshly initialised policy and value network on `device`, of the architecture a config of
    the on-policy family (PPOConfig, TRPOConfig, ACKTRConfig) names."""
    device = torch.device(device)
    if seed is not None:
        torch.manual_seed(seed)
    actor = Policy(policy_spec(config, obs_dim, act_dim))
    with torch.no_grad():
        # A near-zero head: every state starts at mean 0 and log-std 0 (a pre-tanh std of 1),
        # so early updates move the policy evenly from a broad start.
        actor.head.weight.mul_(0.01)
        actor.head.bias.zero_()
        actor.head.bias[act_dim:] = math.atanh(-LOG_STD_MIN / (0.5 * (LOG_STD_MAX - LOG_STD_MIN)) - 1.0)
    value = ValueNetwork(obs_dim, config.hidden, config.activation, config.layer_norm)
    return actor.to(device), value.to(device)


def init_state(config: PPOConfig, obs_dim: int, act_dim: int, device: str | torch.device = "cpu",
               seed: int | None = None) -> TrainState:
    """Freshly initialised networks and optimizer on `device`."""
    actor, value = init_networks(config, obs_dim, act_dim, device, seed)
    params = [*actor.parameters(), *value.parameters()]
    if config.optimizer == "rmsprop":
        optimizer = torch.optim.RMSprop(params, lr=config.lr, alpha=0.99, eps=1e-5)
    else:
        optimizer = adam(params, config.lr, torch.device(device), eps=1e-5)
    return TrainState(actor, value, optimizer)


@dataclass
class Batch(Transitions):
    """Pieces of trajectories laid end to end."""

    ends: torch.Tensor
    """1.0 where the next row does not continue this trajectory: the episode ended (terminated or
    truncated), or the piece did (chunk or batch end)."""
    behaviour_log_prob: torch.Tensor
    """log mu(action | obs) under the policy that acted."""


def batch_from_sample(batch: SampleBatch, device: str | torch.device = "cpu") -> Batch:
    """A Batch from a queue table's sample_batch (which must carry log_probs and segment_ends)."""
    ends = batch.terminated | batch.truncated | batch.segment_ends
    return Batch(float_tensor(batch.obs, device), to_tanh_space(float_tensor(batch.actions, device)),
                 float_tensor(batch.rewards, device), float_tensor(batch.next_obs, device),
                 float_tensor(batch.terminated, device), float_tensor(ends, device),
                 float_tensor(batch.log_probs, device))


def discounted_sums(x: np.ndarray, carry: np.ndarray) -> np.ndarray:
    """y[t] = x[t] + carry[t] * y[t+1], from the end (y[T] = 0)."""
    y = np.empty_like(x)
    running = 0.0
    for t in range(len(x) - 1, -1, -1):
        running = x[t] + carry[t] * running
        y[t] = running
    return y


def gae(rewards: np.ndarray, values: np.ndarray, next_values: np.ndarray, terminated: np.ndarray,
        ends: np.ndarray, gamma: float, lam: float) -> np.ndarray:
    """GAE(lambda) advantages of trajectory pieces laid end to end:
    delta[t] = r[t] + gamma * (1 - terminated[t]) * V(next_obs[t]) - V(obs[t]),
    A[t] = delta[t] + gamma * lam * (1 - ends[t]) * A[t+1]."""
    deltas = rewards + gamma * (1.0 - terminated) * next_values - values
    return discounted_sums(deltas, gamma * lam * (1.0 - ends))


def vtrace(rewards: np.ndarray, values: np.ndarray, next_values: np.ndarray, terminated: np.ndarray,
           ends: np.ndarray, log_rhos: np.ndarray, gamma: float, lam: float,
           clip: float) -> tuple[np.ndarray, np.ndarray]:
    """V-trace value targets v and policy advantages of trajectory pieces laid end to end, with
    log_rhos = log pi(a|s) - log mu(a|s), rho = min(clip, e^log_rhos), c = lam * min(clip, e^log_rhos):
    v[t] = V(s[t]) + rho[t] * delta[t] + gamma * c[t] * (1 - ends[t]) * (v[t+1] - V(s[t+1])),
    A[t] = rho[t] * (r[t] + gamma * (1 - terminated[t]) * v'[t] - V(s[t])), v'[t] being v[t+1] where
    the trajectory goes on and V(next_obs[t]) where it stops."""
    rho = np.minimum(clip, np.exp(log_rhos))
    deltas = rho * (rewards + gamma * (1.0 - terminated) * next_values - values)
    corrections = discounted_sums(deltas, gamma * lam * rho * (1.0 - ends))
    targets = values + corrections
    following = np.append(corrections[1:], 0.0) * (1.0 - ends)  # v[t+1] - V(s[t+1]) where it goes on
    advantages = rho * (rewards + gamma * (1.0 - terminated) * (next_values + following) - values)
    return targets, advantages


def clipped_surrogate(log_prob: torch.Tensor, old_log_prob: torch.Tensor, advantages: torch.Tensor,
                      clip: float) -> tuple[torch.Tensor, torch.Tensor]:
    """PPO's policy loss mean(max(-A * r, -A * clip(r, 1 - clip, 1 + clip))), r = pi / pi_old,
    and the ratios r."""
    # Bounded before exp: an action at the edge of (-1, 1) far from the policy's mean has a
    # log-probability of hundreds below zero, whose change in one step overflowed float32 (NaN
    # weights on the runner after 26 minutes). Past the bound the ratio is clipped anyway.
    ratio = (log_prob - old_log_prob).clamp(-LOG_RATIO_BOUND, LOG_RATIO_BOUND).exp()
    loss = torch.max(-advantages * ratio, -advantages * ratio.clamp(1.0 - clip, 1.0 + clip)).mean()
    return loss, ratio


@dataclass
class Estimates:
    """What an on-policy update knows of its batch before any step."""

    values: torch.Tensor
    """V(s) of every step."""
    proximal_log_prob: torch.Tensor
    """log pi_old(a|s): the learner's policy as the update starts."""
    old_log_prob: torch.Tensor
    """The log-probabilities a policy's ratio divides by: the acting policy's under lag_correction
    'ratio', else the proximal policy's."""
    advantages: torch.Tensor
    targets: torch.Tensor
    """The value targets."""


def estimate(state: TrainState, batch: Batch, config) -> Estimates:
    """The observation statistics take the batch in (normalize_obs, as SAC's prepare does); then
    values, the proximal policy's log-probabilities, and advantages and value targets by GAE(lambda)
    or V-trace, as `config.lag_correction` says (any config of the on-policy family)."""
    state.actor.observation_filter.update(batch.obs, sum_over_ranks)
    reward = config.reward_scale * batch.reward
    with torch.no_grad():
        values = state.value(state.actor.observation_filter(batch.obs))
        next_values = state.value(state.actor.observation_filter(batch.next_obs))
        proximal_log_prob = state.actor.evaluate(batch.obs, batch.action)[0]
    old_log_prob = batch.behaviour_log_prob if config.lag_correction == "ratio" else proximal_log_prob

    r, v, v_next, term, ends = (t.double().cpu().numpy()
                                for t in (reward, values, next_values, batch.terminated, batch.ends))
    if config.lag_correction == "vtrace":
        log_rhos = (proximal_log_prob - batch.behaviour_log_prob).double().cpu().numpy()
        targets, advantages = vtrace(r, v, v_next, term, ends, log_rhos, config.gamma, config.gae_lambda,
                                     config.is_clip)
    else:
        advantages = gae(r, v, v_next, term, ends, config.gamma, config.gae_lambda)
        targets = advantages + v
    return Estimates(values, proximal_log_prob, old_log_prob,
                     torch.as_tensor(advantages, dtype=torch.float32, device=values.device),
                     torch.as_tensor(targets, dtype=torch.float32, device=values.device))


def batch_metrics(estimates: Estimates, batch: Batch) -> dict[str, torch.Tensor]:
    """What every on-policy update reports of its batch's estimates."""
    values, targets = estimates.values, estimates.targets
    return {"value_mean": values.mean(), "advantage_mean": estimates.advantages.mean(),
            "explained_variance": 1.0 - (targets - values).var() / targets.var().clamp(min=1e-8),
            # KL(acting || proximal) estimated on the batch: how far the lag moved the policy
            "lag_kl": (batch.behaviour_log_prob - estimates.proximal_log_prob).mean()}


def update(state: TrainState, batch: Batch, config: PPOConfig) -> dict[str, torch.Tensor]:
    """One PPO update on one queue batch: `epochs` x `minibatches` gradient steps. Returns metrics."""
    # 1-2. Before any step: values, the proximal policy's log-probabilities, advantages and targets.
    estimates = estimate(state, batch, config)
    n = len(batch.obs)

    # 3. Epochs of minibatch steps: clipped surrogate, value loss, entropy bonus; one optimizer step each.
    size = n // config.minibatches
    sums = {name: torch.zeros((), device=estimates.values.device)
            for name in ("policy_loss", "value_loss", "entropy", "approx_kl", "clip_fraction")}
    for _ in range(config.epochs):
        order = torch.randperm(n, device=estimates.values.device)
        for start in range(0, size * config.minibatches, size):
            loss, parts = minibatch_loss(state, batch, estimates, order[start:start + size], config)
            state.optimizer.zero_grad(set_to_none=True)
            loss.backward()
            gradient_step(state, config)
            for name, value in parts.items():
                sums[name] += value

    steps = config.epochs * config.minibatches
    return {name: total / steps for name, total in sums.items()} | batch_metrics(estimates, batch)


def minibatch_loss(state: TrainState, batch: Batch, estimates: Estimates, rows: torch.Tensor | slice,
                   config: PPOConfig) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """The loss of one gradient step on the batch's `rows`: the clipped surrogate on the advantages
    (normalised over the rows if the config says so), the value loss (V(s) - target)^2 / 2 and the
    entropy bonus; and its parts, detached, for the metrics. A3C's actors compute their gradients
    of this same loss (`l2r.learner.a3c`)."""
    log_prob, entropy = state.actor.evaluate(batch.obs[rows], batch.action[rows])
    adv = estimates.advantages[rows]
    if config.normalize_advantages:
        adv = (adv - adv.mean()) / (adv.std(correction=0) + 1e-8)
    policy_loss, ratio = clipped_surrogate(log_prob, estimates.old_log_prob[rows], adv, config.clip)
    values = state.value(state.actor.observation_filter(batch.obs[rows]))
    value_loss = 0.5 * (values - estimates.targets[rows]).pow(2).mean()
    loss = policy_loss - config.entropy_coef * entropy.mean() + config.value_coef * value_loss
    with torch.no_grad():
        log_ratio = ratio.log()
        parts = {"policy_loss": policy_loss.detach(), "value_loss": value_loss.detach(),
                 "entropy": entropy.mean().detach(), "approx_kl": (ratio - 1.0 - log_ratio).mean(),
                 "clip_fraction": ((ratio - 1.0).abs() > config.clip).float().mean()}
    return loss, parts


def gradient_step(state: TrainState, config: PPOConfig) -> torch.Tensor:
    """One optimizer step on the gradients the parameters hold: averaged over data-parallel ranks,
    their norm clipped to `max_grad_norm` (policy and value together). Returns the norm before the clip."""
    params = state.parameters()
    average_gradients(params)
    norm = nn.utils.clip_grad_norm_(params, config.max_grad_norm)
    state.optimizer.step()
    state.updates += 1
    return norm


def broadcast_state(state: TrainState) -> None:
    """Give every data-parallel rank the weights of rank 0, so all start identical."""
    broadcast([state.actor, state.value])
