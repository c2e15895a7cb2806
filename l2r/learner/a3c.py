"""Asynchronous advantage actor-critic (A3C): the actors compute A2C's gradient on their own rollouts
and send it; the learner applies each one and publishes weights.

An actor's side (`l2r.actors.gradients` hosts it), per rollout of `batch_size` steps of one
environment, all acted with the weights of one version:

1. `replica_of`, `load_weights`: the policy and value network of those weights (A3C's learner
   publishes the value network and its settings with the policy), loaded afresh for every rollout;
2. `gradient`: A2C's loss on the rollout and its gradient, by the functions A2C's update runs:
   `ppo.estimate` (the rollout merged into the observation statistics, values, n-step advantages)
   and `ppo.minibatch_loss` on every row (policy loss, value loss, entropy bonus). The rollout is
   the replica's own, so its log-probabilities are the replica's and every lag correction leaves
   A2C's loss (ratio 1);
3. the gradient, flattened, goes out stamped with the version it was computed at (protocol's
   Gradient), with the rollout's observation moments where the networks standardise observations.

The learner's side, per gradient in arrival order, top to bottom (`apply`):

1. `check`: a gradient of another size than the parameters', or computed at weights more than
   `max_gradient_staleness` versions behind the newest, is refused (a ProtocolError the daemon
   logs and counts, like any malformed message);
2. the observation moments merged into the running statistics (normalize_obs);
3. one RMSprop step on it, its norm clipped, as A2C's update takes (`ppo.gradient_step`);
then the daemon publishes weights, a new version, after every gradient.

A gradient is as large as the networks whatever the rollout: 10,300 float32 values for Hopper's
(64, 64) policy and value network, 41.5 KB a message. The experience it replaces is 72 bytes a step
on Hopper (a chunk's observation, action, reward, flags and log-probability), 360 bytes for A2C's
5 steps: a gradient costs the link about 115 times the experience (docs/training.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from l2r.learner import ppo
from l2r.learner.a2c import A2CConfig
from l2r.policy import Policy, load_policy_state, to_tanh_space
from l2r.protocol import ExperienceChunk, Gradient, ObservationSpec, ProtocolError, Weights


@dataclass
class A3CConfig(A2CConfig):
    """A2C's settings, and how stale a gradient the learner still applies."""

    batch_size: int = 5
    """Environment steps of one actor's rollout per gradient: A2C's n_steps, A3C's t_max of 5."""
    max_gradient_staleness: int = 4
    """A gradient computed at weights more than this many versions behind the learner's is refused:
    it was taken at a policy the learner has since moved away from."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.max_gradient_staleness < 0:
            raise ValueError(f"max_gradient_staleness must be >= 0, got {self.max_gradient_staleness}")
        if self.epochs != 1 or self.minibatches != 1:
            raise ValueError(f"A3C takes one gradient per rollout: epochs and minibatches 1, got {self.epochs} "
                             f"and {self.minibatches}")


@dataclass
class Replica:
    """An actor's copy of the networks of one weights version: what `ppo.estimate` and
    `ppo.minibatch_loss` read of a training state."""

    actor: Policy
    value: ppo.ValueNetwork

    def parameters(self) -> list[torch.Tensor]:
        return [*self.actor.parameters(), *self.value.parameters()]


def replica_of(weights: Weights) -> tuple[Replica, A3CConfig]:
    """The networks and settings an A3C learner's weights carry; ValueError when they carry no value
    network or settings, or weights that do not fit the networks the settings describe."""
    if weights.value_params is None or weights.training is None:
        raise ValueError(f"weights v{weights.version} carry no value network and settings: not an A3C learner's")
    config = A3CConfig(**weights.training)
    width = ObservationSpec.from_policy_spec(weights.spec).vector_width
    if width is None:
        raise ValueError("A3C trains on vector observations")
    replica = Replica(*ppo.init_networks(config, width, int(weights.spec["act_dim"])))
    load_weights(replica, weights)
    return replica, config


def load_weights(replica: Replica, weights: Weights) -> None:
    """Copy the weights into the replica (ValueError where they do not fit)."""
    load_policy_state(replica.actor, weights.params)
    load_policy_state(replica.value, weights.value_params)  # (any module's state: the same checks)


def batch_from_chunk(chunk: ExperienceChunk) -> ppo.Batch:
    """One rollout as A2C's batch: a trajectory piece that ends with the chunk (or earlier, where
    an episode ended). The behaviour log-probabilities are `gradient`'s to fill in."""
    def tensor(a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.asarray(a, np.float32))

    ends = chunk.terminated | chunk.truncated
    ends[-1] = True
    return ppo.Batch(tensor(chunk.obs[:-1]), to_tanh_space(tensor(chunk.actions)), tensor(chunk.rewards),
                     tensor(chunk.next_obs()), tensor(chunk.terminated), tensor(ends),
                     behaviour_log_prob=torch.zeros(chunk.size))


def gradient(replica: Replica, batch: ppo.Batch, config: A3CConfig) -> tuple[np.ndarray, np.ndarray | None]:
    """A2C's loss gradient on one rollout at the replica's weights, flattened (the policy's
    parameters, then the value network's, in `parameters()` order), and the rollout's observation
    moments (None unless the networks standardise observations). Changes the replica's statistics."""
    moments = replica.actor.observation_filter.moments(batch.obs) if config.normalize_obs else None
    with torch.no_grad():
        batch.behaviour_log_prob = replica.actor.evaluate(batch.obs, batch.action)[0]
    estimates = ppo.estimate(replica, batch, config)
    loss, _ = ppo.minibatch_loss(replica, batch, estimates, slice(None), config)
    grads = torch.autograd.grad(loss, replica.parameters())
    flat = torch.cat([g.reshape(-1) for g in grads]).numpy()
    return flat, None if moments is None else moments.numpy()


def check(state: ppo.TrainState, message: Gradient, config: A3CConfig) -> None:
    """ProtocolError unless the learner applies `message`: of its parameters' size, with moments
    of its observations' width where it standardises them, and at most `max_gradient_staleness`
    versions behind the newest weights (`stale`), and not ahead of them (`ahead`: computed at
    weights this learner never published, so it restarted from an older checkpoint)."""
    size = sum(p.numel() for p in state.parameters())
    if len(message.gradient) != size:
        raise ProtocolError(f"gradient of {len(message.gradient)} values, this learner's networks have {size}",
                            "wrong_size")
    moments = None if not config.normalize_obs else 1 + 2 * len(state.actor.observation_filter.mean)
    got = None if message.obs_moments is None else len(message.obs_moments)
    if got != moments:
        raise ProtocolError(f"gradient with {got} observation moments, this learner takes {moments}", "wrong_size")
    staleness = state.version - message.policy_version
    if staleness < 0:
        raise ProtocolError(f"gradient of version {message.policy_version}, ahead of the learner's {state.version}",
                            "ahead")
    if staleness > config.max_gradient_staleness:
        raise ProtocolError(f"gradient of version {message.policy_version}, the learner's is {state.version} "
                            f"(at most {config.max_gradient_staleness} behind)", "stale")


def apply(state: ppo.TrainState, message: Gradient, config: A3CConfig) -> dict[str, torch.Tensor]:
    """One A3C update on one actor's gradient (module docstring); ProtocolError where `check`
    refuses it, leaving the state as it was. Returns metrics."""
    # 1. Refuse what does not fit or is too stale.
    check(state, message, config)
    device = state.actor.head.weight.device
    # 2. The rollout's observations into the running statistics, as A2C's update merges its batch's.
    if message.obs_moments is not None:
        state.actor.observation_filter.merge(torch.as_tensor(np.array(message.obs_moments), device=device))
    # 3. One step of A2C's optimizer on the gradient.
    flat = torch.as_tensor(np.array(message.gradient), device=device)
    params = state.parameters()
    for param, grad in zip(params, flat.split([p.numel() for p in params])):
        param.grad = grad.view_as(param)
    norm = ppo.gradient_step(state, config)
    return {"gradient_norm": norm, "staleness": torch.tensor(float(state.version - message.policy_version))}
