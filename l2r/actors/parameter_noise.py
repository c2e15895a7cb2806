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

import contextlib
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


def perturbed_layers(policy: PolicyNetwork) -> dict[str, nn.Linear]:
    """The layers that are perturbed, by name: each Linear of the trunk, and the head."""
    return {name: m for name, m in policy.named_modules()
            if (name == "head" or name.startswith("trunk.")) and isinstance(m, nn.Linear)}


class ParameterNoise:
    """Per-world Gaussian perturbations of a policy's weights, with an adaptive std (see the module)."""

    def __init__(self, distance: float, num_envs: int, seed: int):
        if distance <= 0:
            raise ValueError(f"the parameter noise's target distance must be > 0, got {distance}")
        self.distance, self.num_envs = distance, num_envs
        self.std = INITIAL_STD
        self.generator = torch.Generator().manual_seed(seed)
        self.noise: dict[str, tuple[torch.Tensor, torch.Tensor]] = {}
        """Each perturbed layer's weight and bias noise, (num_envs, *shape), drawn at each world's episode start."""
        self._fresh = set(range(num_envs))  # worlds whose next call draws their perturbation
        self._calls = 0
        self.last_distance = float("nan")
        """The RMS distance measured at the last adaptation (logged every `LOG_EVERY` of them)."""

    def reset(self, env: int) -> None:
        """World `env`'s episode has begun: a new perturbation at its next action."""
        self._fresh.add(env)

    @torch.no_grad()
    def explore(self, policy: PolicyNetwork, obs: torch.Tensor | Mapping[str, torch.Tensor],
                draws: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """Each world's exploring excitation and its log-probability under its perturbed policy, as
        `policy.explore` gives them for one policy; row i of `obs` is world i's; `draws`: the
        policy's own standard normal draws, [num_envs, act_dim], or None to draw them here."""
        layers = perturbed_layers(policy)
        self._draw_fresh(layers, policy.spec["act_dim"])
        with self._perturbed(layers):
            excitation, log_prob = policy.explore(obs, draws)
            perturbed = policy.mean_action(obs) if (self._calls + 1) % ADAPT_EVERY == 0 else None
        self._calls += 1
        if perturbed is not None:
            self._adapt(perturbed, policy.mean_action(obs))
        return excitation, log_prob

    def _draw_fresh(self, layers: Mapping[str, nn.Linear], act_dim: int) -> None:
        shapes = {name: (layer.weight.shape, layer.bias.shape) for name, layer in layers.items()}
        if {name: (w.shape[1:], b.shape[1:]) for name, (w, b) in self.noise.items()} != shapes:
            self.noise = {name: (torch.zeros(self.num_envs, *w, device=layers[name].weight.device),
                                 torch.zeros(self.num_envs, *b, device=layers[name].weight.device))
                          for name, (w, b) in shapes.items()}
            self._fresh = set(range(self.num_envs))
        for env in sorted(self._fresh):
            for name, (weight, bias) in self.noise.items():
                for stacked in (weight, bias):
                    noise = torch.randn(stacked.shape[1:], generator=self.generator) * self.std
                    if name == "head":
                        noise[act_dim:] = 0.0  # the action rows only: a Gaussian head's log-std rows stay
                    stacked[env] = noise.to(stacked.device)
        self._fresh.clear()

    @contextlib.contextmanager
    def _perturbed(self, layers: Mapping[str, nn.Linear]):
        """Within: row i of each layer's batch goes through that layer with world i's noise added
        (x (W + E_i)^T + b + e_i, the added part one batched matmul), by forward hooks."""
        def hook(name):
            weight, bias = self.noise[name]
            return lambda layer, inputs, output: output + torch.baddbmm(
                bias.unsqueeze(1), inputs[0].unsqueeze(1), weight.transpose(1, 2)).squeeze(1)
        handles = [layer.register_forward_hook(hook(name)) for name, layer in layers.items()]
        try:
            yield
        finally:
            for handle in handles:
                handle.remove()

    def _adapt(self, perturbed: torch.Tensor, plain: torch.Tensor) -> None:
        self.last_distance = float((perturbed - plain).pow(2).mean().sqrt())
        self.std = self.std * ADAPT_FACTOR if self.last_distance < self.distance else self.std / ADAPT_FACTOR
        if self._calls % (ADAPT_EVERY * LOG_EVERY) == 0:
            log.info("parameter noise: std %.4f, the perturbed actions %.3f from the policy's (target %.3f)",
                     self.std, self.last_distance, self.distance)
