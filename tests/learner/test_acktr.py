"""ACKTR's update against its step computed densely by hand: the actor-critic gradient, the damped
Kronecker-factored inverse, the trust region's step size."""

import copy
import math

import pytest
import torch
from torch.distributions import Normal

from l2r.learner.acktr import ACKTRConfig, adapted_step_size, init_state, update
from l2r.learner.curvature import gaussian_kl
from l2r.learner.ppo import batch_from_sample, estimate
from l2r.policy import tanh_gaussian_log_prob
from tests.learner.test_ppo import sample_batch

OBS, ACT = 3, 2


def gradients_and_factors_at_start(state, batch, config, seed):
    """The actor-critic loss's gradient and the K-FAC factors of the first batch, computed on a
    copy of the state as it was, with the update's draws (seeded alike): A of each Linear layer's
    inputs, G of the gradients of each row's log-likelihood of a sampled action (of the pre-tanh
    Gaussian) and of its value plus unit noise."""
    state = copy.deepcopy(state)
    estimates = estimate(state, batch, config)
    advantages = (estimates.advantages - estimates.advantages.mean()) / (estimates.advantages.std() + 1e-8)
    passes = {}
    hooks = [layer.register_forward_hook(lambda layer, inputs, out: passes.__setitem__(layer, (inputs[0], out)))
             for layer in state.curvature.layers]
    mean, log_std = state.actor(batch.obs)
    values = state.value(state.actor.observation_filter(batch.obs))
    for hook in hooks:
        hook.remove()
    ratio = (tanh_gaussian_log_prob(mean, log_std, batch.action) - estimates.old_log_prob).exp()
    entropy = (log_std + 0.5 * math.log(2 * math.pi * math.e)).sum(-1).mean()
    loss = (-(ratio * advantages).mean() - config.entropy_coef * entropy
            + config.value_coef * 0.5 * (values - estimates.targets).pow(2).mean())
    gradients = torch.autograd.grad(loss, state.curvature.parameters(), retain_graph=True)

    torch.manual_seed(seed)
    actions = (mean + log_std.exp() * torch.randn_like(mean)).detach()
    noisy_values = (values + torch.randn_like(values)).detach()
    # rows are independent: row i of the gradient of the sum is row i's own gradient
    log_likelihoods = (Normal(mean, log_std.exp()).log_prob(actions).sum()
                       + Normal(values, 1.0).log_prob(noisy_values).sum())
    outputs = [passes[layer][1] for layer in state.curvature.layers]
    factors = []
    for layer, g in zip(state.curvature.layers, torch.autograd.grad(log_likelihoods, outputs)):
        a = torch.cat([passes[layer][0], torch.ones(len(g), 1)], 1).detach()
        factors.append((a.T @ a / len(a), g.T @ g / len(g)))
    return gradients, factors


def dense_natural_gradient(gradients, factors, damping) -> list[torch.Tensor]:
    """(A (x) G + damping I)^-1 vec(V) per layer, V its weight and bias gradients side by side."""
    natural = []
    for (weight, bias), (a, g) in zip(zip(gradients[0::2], gradients[1::2]), factors):
        v = torch.cat([weight, bias[:, None]], 1).double()
        dense = torch.kron(a, g).double() + damping * torch.eye(len(a) * len(g), dtype=torch.float64)
        solved = torch.linalg.solve(dense, v.T.reshape(-1)).reshape(v.shape[1], -1).T.float()
        natural += [solved[:, :-1], solved[:, -1]]
    return natural


@pytest.mark.parametrize("lr, trust_region_binds", [(1e-4, False), (100.0, True)])
def test_the_first_step_is_the_damped_kfac_natural_gradient_at_the_trust_region_step_size(lr, trust_region_binds):
    config = ACKTRConfig(batch_size=32, hidden=(4,), lr=lr, entropy_coef=0.01, lag_correction="none")
    state = init_state(config, OBS, ACT, seed=0)
    batch = batch_from_sample(sample_batch(32, obs_dim=OBS, act_dim=ACT))
    before = [p.detach().clone() for p in state.curvature.parameters()]
    gradients, factors = gradients_and_factors_at_start(state, batch, config, seed=5)
    torch.manual_seed(5)
    metrics = update(state, batch, config)

    natural = dense_natural_gradient(gradients, factors, config.kfac_damping)
    # each network in its own trust region: the policy's parameters come first
    actor_params = len(list(state.actor.parameters()))
    steps, step_sizes = [], []
    for network in (slice(0, actor_params), slice(actor_params, None)):
        quadratic = sum(float((d * g).sum()) for d, g in zip(natural[network], gradients[network]))
        step_size = min(lr, math.sqrt(2 * config.max_kl / quadratic))
        assert (step_size < lr) == trust_region_binds
        if trust_region_binds:  # the step's quadratic KL is on the trust region's edge
            assert 0.5 * step_size ** 2 * quadratic == pytest.approx(config.max_kl)
        steps += [step_size * d for d in natural[network]]
        step_sizes.append(step_size)
    assert [float(metrics["step_size"]), float(metrics["value_step_size"])] == pytest.approx(step_sizes, rel=1e-4)
    for old, new, step in zip(before, state.curvature.parameters(), steps):
        torch.testing.assert_close(new.detach() - old, -step, rtol=1e-3, atol=1e-7)
    assert state.updates == 1


def test_momentum_carries_the_last_step_into_the_next():
    config = ACKTRConfig(batch_size=32, hidden=(4,), lr=1e-3)
    state = init_state(config, OBS, ACT, seed=1)
    batch = batch_from_sample(sample_batch(32, obs_dim=OBS, act_dim=ACT))
    update(state, batch, config)
    first = [state.optimizer.state[p]["momentum_buffer"].clone() for p in state.curvature.parameters()]
    update(state, batch, config)
    second = [p.grad for p in state.curvature.parameters()]  # this step's scaled natural gradient
    for buffer, last, grad in zip((state.optimizer.state[p]["momentum_buffer"] for p in state.curvature.parameters()),
                                  first, second):
        torch.testing.assert_close(buffer, 0.9 * last + grad)


def test_acktr_refuses_layer_norm():
    with pytest.raises(ValueError, match="Linear layers alone"):
        ACKTRConfig(layer_norm=True)


def test_the_step_size_follows_the_paper_s_mujoco_rule():
    # target 0.002: above 0.004 the step shrinks by 1.5, below 0.001 it grows by 1.5, between it stays.
    assert adapted_step_size(0.03, 0.005, 0.002) == pytest.approx(0.02)
    assert adapted_step_size(0.03, 0.0009, 0.002) == pytest.approx(0.045)
    assert adapted_step_size(0.03, 0.004, 0.002) == 0.03 == adapted_step_size(0.03, 0.001, 0.002)
    assert adapted_step_size(0.9, 0.0, 0.002) == 1.0 and adapted_step_size(1.2e-8, 1.0, 0.002) == 1e-8


@pytest.mark.parametrize("target_kl, grows", [(10.0, True), (1e-12, False)])
def test_an_update_measures_its_kl_and_adapts_the_next_step_size_which_a_checkpoint_keeps(target_kl, grows):
    config = ACKTRConfig(batch_size=32, hidden=(4,), lr=0.03, target_kl=target_kl)
    state = init_state(config, OBS, ACT, seed=1)
    batch = batch_from_sample(sample_batch(32, obs_dim=OBS, act_dim=ACT))
    before = copy.deepcopy(state.actor)
    metrics = update(state, batch, config)
    with torch.no_grad():
        kl = gaussian_kl(*before(batch.obs), *state.actor(batch.obs)).mean()
    torch.testing.assert_close(metrics["kl"], kl)
    assert 0 < float(kl) < 2 * target_kl if grows else float(kl) > 2 * target_kl
    assert state.step_size == pytest.approx(0.045 if grows else 0.02)
    assert state.optimizer.param_groups[0]["lr"] == 0.03  # the step taken was at the step size before
    resumed = init_state(config, OBS, ACT)
    resumed.load_state_dict(state.state_dict())
    resumed.set_learning_rates(config)
    assert resumed.step_size == state.step_size


def test_without_a_target_the_step_size_is_the_command_line_s_lr():
    config = ACKTRConfig(batch_size=32, hidden=(4,), lr=0.03, target_kl=0.0)
    state = init_state(config, OBS, ACT, seed=1)
    update(state, batch_from_sample(sample_batch(32, obs_dim=OBS, act_dim=ACT)), config)
    assert state.step_size == 0.03
    state.set_learning_rates(ACKTRConfig(batch_size=32, hidden=(4,), lr=0.1, target_kl=0.0))
    assert state.step_size == 0.1
