"""The curvature products of TRPO and ACKTR against dense matrices built by autograd on tiny networks."""

import math

import pytest
import torch
from torch import nn
from torch.func import functional_call
from torch.nn.utils import parameters_to_vector

from l2r.learner.common import policy_spec
from l2r.learner.curvature import (
    KFAC, conjugate_gradients, fisher_vector_product, gaussian_kl, line_search, trust_region_scale,
)
from l2r.learner.ppo import PPOConfig
from l2r.policy import Policy


def test_gaussian_kl_is_the_closed_form_and_zero_between_equal_policies():
    mean_p, log_std_p = torch.tensor([[0.0, 1.0]]), torch.tensor([[0.0, math.log(2.0)]])
    mean_q, log_std_q = torch.tensor([[1.0, 1.0]]), torch.tensor([[0.0, 0.0]])
    # dim 1: (1 + 1 - 1) / 2 = .5; dim 2: log(1/2) + (4 + 0) / 2 - 1/2
    assert float(gaussian_kl(mean_p, log_std_p, mean_q, log_std_q)) == pytest.approx(0.5 + math.log(0.5) + 1.5)
    assert float(gaussian_kl(mean_p, log_std_p, mean_p, log_std_p)) == 0.0


def test_the_fisher_vector_product_is_the_kl_hessian_times_the_vector_plus_damping():
    torch.manual_seed(0)
    actor = Policy(policy_spec(PPOConfig(hidden=(4,)), 3, 2))  # float32: its head casts to float32
    obs = torch.randn(16, 3)
    names, params = zip(*actor.named_parameters())
    with torch.no_grad():
        mean_old, log_std_old = actor(obs)

    def kl_at(flat: torch.Tensor) -> torch.Tensor:
        tensors, start = {}, 0
        for name, p in zip(names, params):
            tensors[name] = flat[start:start + p.numel()].view_as(p)
            start += p.numel()
        mean, log_std = functional_call(actor, tensors, (obs,))
        return gaussian_kl(mean_old, log_std_old, mean, log_std).mean()

    hessian = torch.autograd.functional.hessian(kl_at, parameters_to_vector(params).detach())
    mean, log_std = actor(obs)
    product = fisher_vector_product(gaussian_kl(mean_old, log_std_old, mean, log_std).mean(), params, damping=0.1)
    for _ in range(3):
        vector = torch.randn(len(hessian))
        torch.testing.assert_close(product(vector), hessian @ vector + 0.1 * vector, rtol=1e-4, atol=1e-5)
    assert torch.linalg.eigvalsh(hessian.double()).min() > -1e-5  # a Fisher: positive semi-definite


def test_conjugate_gradients_solve_a_small_positive_definite_system():
    torch.manual_seed(0)
    b_matrix = torch.randn(5, 5, dtype=torch.float64)
    matrix = b_matrix @ b_matrix.T + torch.eye(5, dtype=torch.float64)
    b = torch.randn(5, dtype=torch.float64)
    torch.testing.assert_close(conjugate_gradients(lambda v: matrix @ v, b, max_steps=5),
                               torch.linalg.solve(matrix, b))
    assert torch.linalg.norm(matrix @ conjugate_gradients(lambda v: matrix @ v, b, max_steps=2) - b) > 1e-3


def quadratic_problem():
    """Parameters p from (0, 0), KL |p|^2, surrogate p1 + p2; the evaluations are kept."""
    params = [torch.zeros(2)]
    tried = []

    def evaluate():
        kl, surrogate = params[0].pow(2).sum(), params[0].sum()
        tried.append((float(surrogate), float(kl)))
        return surrogate, kl

    return params, evaluate, tried


def test_the_line_search_shrinks_the_step_until_the_kl_is_within_the_bound():
    params, evaluate, tried = quadratic_problem()
    # the whole step has KL 2; halves give .5, then .125: the first within .5 is taken
    result = line_search(params, torch.ones(2), evaluate, 0.0, max_kl=0.5, shrink=0.5, max_steps=10)
    assert result.fraction == 0.5 and result.kl == 0.5 and result.surrogate == 1.0
    assert tried == [(2.0, 2.0), (1.0, 0.5)]
    torch.testing.assert_close(params[0], torch.full((2,), 0.5))


def test_the_line_search_takes_no_step_that_exceeds_the_kl_bound_and_gives_up_leaving_the_parameters():
    params, evaluate, tried = quadratic_problem()
    result = line_search(params, torch.ones(2), evaluate, 0.0, max_kl=1e-6, shrink=0.5, max_steps=4)
    assert result.fraction == 0.0 and len(tried) == 4 and all(kl > 1e-6 for _, kl in tried)
    assert torch.equal(params[0], torch.zeros(2))


def test_the_line_search_refuses_a_step_that_does_not_improve_the_surrogate_or_gives_nan():
    params, evaluate, tried = quadratic_problem()
    assert line_search(params, -torch.ones(2), evaluate, 0.0, max_kl=10.0, shrink=0.5, max_steps=3).fraction == 0.0
    assert torch.equal(params[0], torch.zeros(2))
    nan = line_search(params, torch.ones(2), lambda: (torch.tensor(1.0), torch.tensor(math.nan)), 0.0,
                      max_kl=10.0, shrink=0.5, max_steps=3)
    assert nan.fraction == 0.0 and torch.equal(params[0], torch.zeros(2))


def test_the_trust_region_scale_puts_the_quadratic_kl_on_the_bound():
    direction, fisher = torch.tensor([1.0, 2.0]), torch.diag(torch.tensor([2.0, 0.5]))
    scale = trust_region_scale(direction @ fisher @ direction, max_kl=0.01)
    assert float(0.5 * (scale * direction) @ fisher @ (scale * direction)) == pytest.approx(0.01)


def tiny_network_and_kfac(decay=0.9, damping=0.05):
    torch.manual_seed(0)
    network = nn.Sequential(nn.Linear(3, 4), nn.Tanh(), nn.Linear(4, 2)).double()
    return network, KFAC([network], decay, damping)


def per_sample_factors(network, x, targets):
    """A and G of each layer from each row's own gradient of its log-likelihood, one row at a time."""
    hidden = network[0](x)
    out = network[2](torch.tanh(hidden))
    log_likelihood = -0.5 * (out - targets).pow(2).sum(-1)
    factors = []
    for layer_input, output in ((x, hidden), (torch.tanh(hidden), out)):
        a = torch.cat([layer_input, torch.ones(len(x), 1, dtype=x.dtype)], 1).detach()
        g = torch.stack([torch.autograd.grad(log_likelihood[i], output, retain_graph=True)[0][i]
                         for i in range(len(x))])
        factors.append((a.T @ a / len(x), g.T @ g / len(x)))
    return factors


def record_batch(network, kfac, x, targets):
    with kfac.recording():
        out = network(x)
    kfac.update_factors(-0.5 * (out - targets).pow(2).sum(-1).mean())
    return out


def test_kfac_factors_are_the_covariances_of_inputs_and_per_sample_output_gradients_averaged_over_batches():
    network, kfac = tiny_network_and_kfac(decay=0.9)
    batches = [(torch.randn(8, 3, dtype=torch.float64), torch.randn(8, 2, dtype=torch.float64)) for _ in range(2)]
    record_batch(network, kfac, *batches[0])
    record_batch(network, kfac, *batches[1])
    first, second = (per_sample_factors(network, *batch) for batch in batches)
    for (a, g), (a1, g1), (a2, g2) in zip(kfac.factors, first, second):
        torch.testing.assert_close(a, 0.9 * a1 + 0.1 * a2)
        torch.testing.assert_close(g, 0.9 * g1 + 0.1 * g2)


def test_the_kfac_natural_gradient_is_the_damped_kronecker_inverse_computed_densely():
    network, kfac = tiny_network_and_kfac(damping=0.05)
    x, targets = torch.randn(8, 3, dtype=torch.float64), torch.randn(8, 2, dtype=torch.float64)
    out = record_batch(network, kfac, x, targets)
    network.zero_grad()
    out.pow(3).mean().backward()  # any loss: the gradient is what gets preconditioned
    natural = kfac.natural_gradient()
    for i, (layer, (a, g)) in enumerate(zip(kfac.layers, kfac.factors)):
        gradient = torch.cat([layer.weight.grad, layer.bias.grad[:, None]], 1)
        # vec stacks columns: vec(G V A) = (A (x) G) vec(V) for symmetric A
        dense = torch.kron(a, g) + 0.05 * torch.eye(len(a) * len(g), dtype=torch.float64)
        solved = torch.linalg.solve(dense, gradient.T.reshape(-1)).reshape(gradient.shape[1], -1).T
        torch.testing.assert_close(natural[2 * i], solved[:, :-1])
        torch.testing.assert_close(natural[2 * i + 1], solved[:, -1])
    assert [p.shape for p in kfac.parameters()] == [p.shape for p in natural]


def test_kfac_refuses_statistics_of_a_pass_that_missed_a_layer():
    network, kfac = tiny_network_and_kfac()
    with kfac.recording():
        out = network[0](torch.randn(4, 3, dtype=torch.float64))
    with pytest.raises(RuntimeError, match="1 of 2 layers ran while recording"):
        kfac.update_factors(out.sum())
