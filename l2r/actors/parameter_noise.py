"""Exploration in parameter space: each world acts with its own perturbed copy of the policy.

Plappert et al. (ICLR 2018, "Parameter Space Noise for Exploration") add Gaussian noise to a
policy's weights once an episode instead of to each action, so a world explores with one
consistent behaviour for a whole episode; reason8, a 2017 finalist, trained the runner so, with
LayerNorm, which keeps a perturbation's effect alike from layer to layer. The noise's std adapts
so the perturbed policies' deterministic actions lie at a chosen RMS distance from the plain
policy's, in its (-1, 1) action space: 1 % larger while they lie closer, 1 % smaller while
further, judged every `ADAPT_EVERY` calls on the worlds' current observations.

Perturbed: the weights and biases of the hidden Linear layers and the head's action rows (a
Gaussian policy's mean; its log-std rows stay, so its own exploring draws keep their width);
LayerNorm's scales and shifts stay, as Plappert's code left them. A world's noise is drawn at
its episode's start and added to whichever weights are newest, so a new policy version keeps
each world's perturbation. The policy's own exploring draws come on top, and the action sent
is the one taken; its log-probability is the perturbed policy's, which is why on-policy
learners, whose ratios need the plain policy's, do not take this noise.
"""

from __future__ import annotations

import logging
from typing import Mapping

import torch
from torch import nn

from l2r.policy import PolicyNetwork

log = logging.getLogger(__name__)

INITIAL_STD = 0.05
"""The perturbation's std before the first adaptation."""
ADAPT_EVERY = 50
"""Calls (actor steps) between adaptations of the std, as Plappert's code adapted every 50 steps."""
ADAPT_FACTOR = 1.01
LOG_EVERY = 100
"""Adaptations between log lines of the std and the distance."""


class _Explore(nn.Module):
    """The policy's `explore` as a module's forward, so `torch.func.functional_call` can run it with other weights."""

    def __init__(self, policy: PolicyNetwork):
        super().__init__()
        self.policy = policy

    def forward(self, obs, draws: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return self.policy.explore(obs, draws)


class _MeanAction(_Explore):
    def forward(self, obs, draws: torch.Tensor) -> torch.Tensor:
        return self.policy.mean_action(obs)


def perturbed_parameters(policy: PolicyNetwork) -> dict[str, torch.Tensor]:
    """The parameters that are perturbed, by name: each Linear's of the trunk and the head."""
    return {name: p for name, p in policy.named_parameters()
            if name.startswith(("trunk.", "head.")) and isinstance(policy.get_submodule(name.rsplit(".", 1)[0]), nn.Linear)}


class ParameterNoise:
    """Per-world Gaussian perturbations of a policy's weights, with an adaptive std (see the module)."""

    def __init__(self, distance: float, num_envs: int, seed: int):
        if distance <= 0:
            raise ValueError(f"the parameter noise's target distance must be > 0, got {distance}")
        self.distance, self.num_envs = distance, num_envs
        self.std = INITIAL_STD
        self.generator = torch.Generator().manual_seed(seed)
        self.noise: dict[str, torch.Tensor] = {}  # name -> (num_envs, *shape), drawn at each world's episode start
        self._fresh = set(range(num_envs))  # worlds whose next call draws their perturbation
        self._calls = 0
        self.last_distance = float("nan")
        """The RMS distance measured at the last adaptation (a stat for the status line and metrics)."""

    def reset(self, env: int) -> None:
        """World `env`'s episode has begun: a new perturbation at its next action."""
        self._fresh.add(env)

    @torch.no_grad()
    def explore(self, policy: PolicyNetwork, obs: torch.Tensor | Mapping[str, torch.Tensor],
                draws: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Each world's exploring excitation and its log-probability under its perturbed policy, as
        `policy.explore` gives them for one policy; `draws`: the policy's own standard normal draws,
        [num_envs, act_dim], or None to draw them here."""
        params = perturbed_parameters(policy)
        self._draw_fresh(params, policy.spec["act_dim"])
        if draws is None:
            draws = torch.randn(self.num_envs, policy.spec["act_dim"], generator=self.generator).to(obs_device(obs))
        worlds = {f"policy.{name}": p.detach() + self.noise[name] for name, p in params.items()}
        excitation, log_prob = self._per_world(_Explore(policy), worlds, obs, draws)
        self._calls += 1
        if self._calls % ADAPT_EVERY == 0:
            self._adapt(policy, worlds, obs, draws)
        return excitation, log_prob

    def _draw_fresh(self, params: Mapping[str, torch.Tensor], act_dim: int) -> None:
        if not self.noise or any(self.noise[name].shape[1:] != p.shape for name, p in params.items()):
            self.noise = {name: torch.zeros(self.num_envs, *p.shape, device=p.device) for name, p in params.items()}
            self._fresh = set(range(self.num_envs))
        for env in sorted(self._fresh):
            for name, p in params.items():
                noise = torch.randn(p.shape, generator=self.generator) * self.std
                if name.startswith("head."):
                    noise[act_dim:] = 0.0  # the action rows only: a Gaussian head's log-std rows stay
                self.noise[name][env] = noise.to(p.device)
        self._fresh.clear()

    def _adapt(self, policy: PolicyNetwork, worlds: dict[str, torch.Tensor], obs, draws: torch.Tensor) -> None:
        perturbed = self._per_world(_MeanAction(policy), worlds, obs, draws)
        self.last_distance = float((perturbed - policy.mean_action(obs)).pow(2).mean().sqrt())
        self.std = self.std * ADAPT_FACTOR if self.last_distance < self.distance else self.std / ADAPT_FACTOR
        if self._calls % (ADAPT_EVERY * LOG_EVERY) == 0:
            log.info("parameter noise: std %.4f, the perturbed actions %.3f from the policy's (target %.3f)",
                     self.std, self.last_distance, self.distance)

    @staticmethod
    def _per_world(module: nn.Module, worlds: dict[str, torch.Tensor], obs, draws: torch.Tensor):
        """`module` run on each world's observation with that world's weights (one batched call)."""
        def one(weights, world_obs, world_draws):
            out = torch.func.functional_call(module, weights, (_one_row(world_obs), world_draws.unsqueeze(0)))
            return tuple(x.squeeze(0) for x in out) if isinstance(out, tuple) else out.squeeze(0)
        return torch.func.vmap(one)(worlds, obs, draws)


def _one_row(obs: torch.Tensor | Mapping[str, torch.Tensor]):
    """One world's observation as a batch of one (a vector, or a map of fields)."""
    return obs.unsqueeze(0) if isinstance(obs, torch.Tensor) else {name: x.unsqueeze(0) for name, x in obs.items()}


def obs_device(obs: torch.Tensor | Mapping[str, torch.Tensor]) -> torch.device:
    return (obs if isinstance(obs, torch.Tensor) else next(iter(obs.values()))).device
