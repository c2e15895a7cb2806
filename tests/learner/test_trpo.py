"""TRPO's update against the natural-gradient step computed densely by hand on a tiny network; TRPO's
and ACKTR's checkpoints."""

import copy

import numpy as np
import pytest
import torch
from torch.func import functional_call
from torch.nn.utils import parameters_to_vector

from l2r.learner import acktr, trpo
from l2r.learner.__main__ import parse_settings
from l2r.learner.checkpoint import checkpoint_path, load_checkpoint, save_checkpoint
from l2r.learner.curvature import gaussian_kl
from l2r.learner.ppo import LOG_RATIO_BOUND, batch_from_sample, estimate
from l2r.learner.trpo import TRPOConfig, init_state, update
from l2r.policy import tanh_gaussian_log_prob
from tests.learner.test_ppo import sample_batch

OBS, ACT = 3, 2


def tiny(**settings) -> TRPOConfig:
    return TRPOConfig(**{"batch_size": 32, "hidden": (4,), "cg_steps": 100, "value_epochs": 2,
                         "value_minibatch_size": 8, "lag_correction": "none", **settings})


def dense_step(state, batch, config) -> torch.Tensor:
    """sqrt(2 max_kl / d' F d) d with d = F^-1 g: F the KL's Hessian plus the damping, g the
    surrogate's gradient, both built whole by autograd."""
    state = copy.deepcopy(state)
    estimates = estimate(state, batch, config)
    advantages = (estimates.advantages - estimates.advantages.mean()) / (estimates.advantages.std() + 1e-8)
    names, params = zip(*state.actor.named_parameters())
    with torch.no_grad():
        old_mean, old_log_std = state.actor(batch.obs)

    def at(flat):
        tensors, start = {}, 0
        for name, p in zip(names, params):
            tensors[name] = flat[start:start + p.numel()].view_as(p)
            start += p.numel()
        return functional_call(state.actor, tensors, (batch.obs,))

    def surrogate(flat):
        mean, log_std = at(flat)
        log_ratio = tanh_gaussian_log_prob(mean, log_std, batch.action) - estimates.old_log_prob
        return (log_ratio.clamp(-LOG_RATIO_BOUND, LOG_RATIO_BOUND).exp() * advantages).mean()

    def kl(flat):
        return gaussian_kl(old_mean, old_log_std, *at(flat)).mean()

    theta = parameters_to_vector(params).detach().double()
    fisher = torch.autograd.functional.hessian(lambda f: kl(f.float()).double(), theta)
    fisher += config.cg_damping * torch.eye(len(theta), dtype=torch.float64)
    gradient = torch.autograd.functional.jacobian(lambda f: surrogate(f.float()).double(), theta)
    direction = torch.linalg.solve(fisher, gradient)
    return (torch.sqrt(2 * config.max_kl / (direction @ fisher @ direction)) * direction).float()


def test_the_policy_moves_by_the_natural_gradient_step_backtracked_within_the_kl_bound():
    # a trust region so wide that the KL's quadratic model falls short of it: the full step's KL
    # is above the bound, and the search must backtrack
    config = tiny(max_kl=3.0)
    state = init_state(config, OBS, ACT, seed=0)
    batch = batch_from_sample(sample_batch(32, obs_dim=OBS, act_dim=ACT))
    before = parameters_to_vector(state.actor.parameters()).detach().clone()
    with torch.no_grad():
        old_mean, old_log_std = state.actor(batch.obs)
    step = dense_step(state, batch, config)
    metrics = update(state, batch, config)

    fraction = float(metrics["step_fraction"])
    assert any(fraction == pytest.approx(0.8 ** k) for k in range(1, 10))
    moved = parameters_to_vector(state.actor.parameters()).detach() - before
    torch.testing.assert_close(moved, fraction * step, rtol=1e-3, atol=1e-4 * float(step.abs().max()))
    with torch.no_grad():
        kl = gaussian_kl(old_mean, old_log_std, *state.actor(batch.obs)).mean()
    assert float(kl) == pytest.approx(float(metrics["kl"]), rel=1e-4) and float(kl) <= config.max_kl
    assert state.updates == 1


def test_the_value_network_takes_its_own_adam_steps_and_the_policy_only_the_line_search_step():
    config = tiny()
    state = init_state(config, OBS, ACT, seed=1)
    batch = batch_from_sample(sample_batch(32, obs_dim=OBS, act_dim=ACT))
    values_before = [p.detach().clone() for p in state.value.parameters()]
    update(state, batch, config)
    # 2 epochs of 32 / 8 minibatches; the optimizer holds the value network alone
    assert [int(s["step"]) for s in state.optimizer.state.values()] == [8] * len(values_before)
    assert len(state.optimizer.param_groups[0]["params"]) == len(values_before)
    assert all(not torch.equal(a, b) for a, b in zip(values_before, state.value.parameters()))


def test_a_batch_with_nothing_to_improve_leaves_the_policy_as_it_was():
    # Equal advantages standardise to zero: no gradient, no direction, no step (and no NaN).
    sample = sample_batch(32, obs_dim=OBS, act_dim=ACT, rewards=np.ones(32))
    sample.terminated[:] = True
    config = tiny(normalize_advantages=True)
    state = init_state(config, OBS, ACT, seed=2)
    with torch.no_grad():
        state.value.head.weight.zero_()
        state.value.head.bias.fill_(1.0)  # every advantage exactly 0
    before = [p.detach().clone() for p in state.actor.parameters()]
    metrics = update(state, batch_from_sample(sample), config)
    assert float(metrics["step_fraction"]) == 0.0
    assert all(torch.equal(a, b) for a, b in zip(before, state.actor.parameters()))


@pytest.mark.parametrize("algo", ["trpo", "acktr"])
def test_a_checkpoint_restores_the_state_and_the_next_update_is_identical(algo, tmp_path):
    module = {"trpo": trpo, "acktr": acktr}[algo]
    config = tiny() if algo == "trpo" else acktr.ACKTRConfig(batch_size=32, hidden=(4,))
    state = module.init_state(config, OBS, ACT, seed=3)
    batch = batch_from_sample(sample_batch(32, obs_dim=OBS, act_dim=ACT))
    module.update(state, batch, config)
    save_checkpoint(checkpoint_path(tmp_path), state, config, OBS, ACT)
    saved = load_checkpoint(tmp_path)
    restored = saved.restore()
    assert (saved.algo, saved.config, restored.updates) == (algo, config, 1)
    for each in (state, restored):
        torch.manual_seed(4)
        module.update(each, batch, config)
    assert all(torch.equal(a, b) for a, b in zip(state.parameters(), restored.parameters()))
    if algo == "acktr":  # the K-FAC factors came back too: the second step used the same running averages
        assert all(torch.equal(a, b) for pair_a, pair_b in zip(state.curvature.factors, restored.curvature.factors)
                   for a, b in zip(pair_a, pair_b))


def test_the_learner_command_line_takes_each_algorithm_s_published_defaults_and_its_flags():
    assert parse_settings(["--algo", "trpo"]).algorithm() == TRPOConfig()
    assert parse_settings(["--algo", "acktr"]).algorithm() == acktr.ACKTRConfig()
    assert parse_settings(["--algo", "acktr", "--max-kl", "0.002", "--lr", "0.1"]).algorithm() == acktr.ACKTRConfig(
        max_kl=0.002, lr=0.1)
    assert parse_settings(["--algo", "trpo", "--cg-steps", "10", "--gae-lambda", "0.9"]).algorithm() == TRPOConfig(
        cg_steps=10, gae_lambda=0.9)
