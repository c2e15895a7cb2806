"""Curvature of a policy for natural-gradient steps: what TRPO and ACKTR share, apart from either.

TRPO's parts: `fisher_vector_product` (the KL's Hessian at the current parameters, which is the
policy's Fisher information there, times a vector, by differentiating the KL's gradient once
more), `conjugate_gradients` (solves F x = g with those products alone), `trust_region_scale`
(the largest multiple of a direction whose quadratic KL stays within a bound) and `line_search`
(backtracks along the step until the surrogate improves and the mean KL keeps within the bound).

ACKTR's part: `KFAC`, the Fisher of each Linear layer approximated as the Kronecker product of
the covariance of its inputs (A) and of the gradients of its outputs (G), kept as running
averages, inverted with damping through each factor's eigendecomposition.

`gaussian_kl` is the KL between the policies both measure: the tanh is one-to-one, so the KL of
two tanh-Gaussians is that of their Gaussians before the tanh, in closed form.
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Callable, Iterator, NamedTuple, Sequence

import torch
from torch import nn
from torch.nn.utils import parameters_to_vector, vector_to_parameters


def gaussian_kl(mean_p: torch.Tensor, log_std_p: torch.Tensor, mean_q: torch.Tensor,
                log_std_q: torch.Tensor) -> torch.Tensor:
    """KL(p || q) of diagonal Gaussians, summed over the last dimension."""
    variance_ratio = (2.0 * (log_std_p - log_std_q)).exp()
    mean_term = ((mean_p - mean_q) / log_std_q.exp()).pow(2)
    return 0.5 * (variance_ratio + mean_term - 1.0).sum(-1) - (log_std_p - log_std_q).sum(-1)


def flat_grad(output: torch.Tensor, params: Sequence[torch.Tensor], **kwargs) -> torch.Tensor:
    """The gradient of a scalar with respect to `params`, as one vector."""
    return torch.cat([g.reshape(-1) for g in torch.autograd.grad(output, params, **kwargs)])


def fisher_vector_product(kl: torch.Tensor, params: Sequence[torch.Tensor],
                          damping: float) -> Callable[[torch.Tensor], torch.Tensor]:
    """v -> (H + damping I) v, H the Hessian of `kl` (the mean KL of the policy at `params` from
    a fixed copy of itself, a graph built at those parameters): there H is the Fisher information.
    The damping keeps conjugate gradients well posed where the batch leaves H singular."""
    grad = flat_grad(kl, params, create_graph=True)

    def product(vector: torch.Tensor) -> torch.Tensor:
        return flat_grad(grad @ vector, params, retain_graph=True) + damping * vector

    return product


def conjugate_gradients(matvec: Callable[[torch.Tensor], torch.Tensor], b: torch.Tensor, max_steps: int,
                        tolerance: float = 1e-10) -> torch.Tensor:
    """x with M x = b for a symmetric positive-definite M given by its products, after at most
    `max_steps` steps (exact after as many as b has entries) or once |residual|^2 < tolerance."""
    x = torch.zeros_like(b)
    residual, direction = b.clone(), b.clone()
    squared = residual @ residual
    for _ in range(max_steps):
        if squared < tolerance:
            break
        product = matvec(direction)
        alpha = squared / (direction @ product)
        x += alpha * direction
        residual -= alpha * product
        squared, before = residual @ residual, squared
        direction = residual + (squared / before) * direction
    return x


def trust_region_scale(quadratic: torch.Tensor, max_kl: float) -> torch.Tensor:
    """sqrt(2 max_kl / quadratic): the multiple of a direction d, with quadratic = d' F d, whose
    second-order KL (1/2 (s d)' F (s d)) is max_kl."""
    return (2.0 * max_kl / quadratic).sqrt()


class LineSearch(NamedTuple):
    fraction: float
    """The fraction of the step taken: 1, shrink, shrink^2, ...; 0 when none was accepted."""
    surrogate: float
    kl: float
    """The mean KL from the policy before the step (0 when none was taken)."""


@torch.no_grad()
def line_search(params: Sequence[torch.Tensor], step: torch.Tensor,
                evaluate: Callable[[], tuple[torch.Tensor, torch.Tensor]], surrogate_before: float,
                max_kl: float, shrink: float, max_steps: int) -> LineSearch:
    """Backtracking along `step` from the current `params`: tries step, shrink * step, ... (at
    most `max_steps` tries) and keeps the first whose surrogate (`evaluate()` -> surrogate, mean
    KL, at the parameters as they are) is above `surrogate_before` with a KL of at most `max_kl`.
    If none is, the parameters are left as they were."""
    start = parameters_to_vector(params)
    fraction = 1.0
    for _ in range(max_steps):
        vector_to_parameters(start + fraction * step, params)
        surrogate, kl = (float(value) for value in evaluate())
        if kl <= max_kl and surrogate > surrogate_before:  # a NaN fails both
            return LineSearch(fraction, surrogate, kl)
        fraction *= shrink
    vector_to_parameters(start, params)
    return LineSearch(0.0, surrogate_before, 0.0)


class KFAC:
    """Kronecker-factored approximate curvature of the Linear layers of `modules`.

    The Fisher block of a layer s = W a + b is taken as A (x) G, A = E[a a'] over its inputs with
    a 1 appended (for the bias), G = E[g g'] over the gradients g of a sampled log-likelihood with
    respect to its outputs s. `recording()` keeps what a forward pass feeds each layer and gets
    from it; `update_factors(fisher_loss)` takes the statistics of those tensors into running
    averages (the first batch starts them); `natural_gradient()` maps each layer's gradient V
    (out x in+1) to (A (x) G + damping I)^-1 vec(V), through the eigendecompositions of A and G.
    """

    def __init__(self, modules: Sequence[nn.Module], decay: float, damping: float):
        self.layers = [layer for module in modules for layer in module.modules() if isinstance(layer, nn.Linear)]
        self.decay, self.damping = decay, damping
        self.factors: list[tuple[torch.Tensor, torch.Tensor]] = []
        """(A, G) per layer, once a batch has been taken in."""
        self._recorded: dict[nn.Module, tuple[torch.Tensor, torch.Tensor]] = {}

    @contextmanager
    def recording(self) -> Iterator[None]:
        """Within it, each forward pass through a layer is kept (its input and output) for `update_factors`."""
        self._recorded = {}

        def keep(layer: nn.Module, inputs: tuple[torch.Tensor], output: torch.Tensor) -> None:
            self._recorded[layer] = inputs[0], output

        hooks = [layer.register_forward_hook(keep) for layer in self.layers]
        try:
            yield
        finally:
            for hook in hooks:
                hook.remove()

    def update_factors(self, fisher_loss: torch.Tensor) -> None:
        """Take the covariances of the recorded layers' inputs and of `fisher_loss`'s gradients
        at their outputs into the running averages. `fisher_loss` is a mean over the batch of
        log-likelihoods of targets sampled from the model, so n times its gradient at a row is
        that row's own. Each layer must have run while recording (the last pass counts)."""
        if len(self._recorded) != len(self.layers):
            raise RuntimeError(f"{len(self._recorded)} of {len(self.layers)} layers ran while recording: K-FAC "
                               "needs the statistics of every one")
        recorded = [self._recorded[layer] for layer in self.layers]
        grads = torch.autograd.grad(fisher_loss, [output for _, output in recorded], retain_graph=True)
        batch = []
        for (inputs, _), grad in zip(recorded, grads):
            a = torch.cat([inputs.detach(), inputs.new_ones(len(inputs), 1)], dim=1)
            g = grad * len(grad)
            batch.append((a.T @ a / len(a), g.T @ g / len(g)))
        self._recorded = {}
        if not self.factors:
            self.factors = batch
            return
        for (a_running, g_running), (a_new, g_new) in zip(self.factors, batch):
            a_running.lerp_(a_new, 1.0 - self.decay)
            g_running.lerp_(g_new, 1.0 - self.decay)

    def natural_gradient(self) -> list[torch.Tensor]:
        """Each layer's weight and bias gradients preconditioned: [weight, bias, weight, bias, ...]."""
        natural = []
        for layer, (a, g) in zip(self.layers, self.factors):
            values_a, vectors_a = torch.linalg.eigh(a)
            values_g, vectors_g = torch.linalg.eigh(g)
            gradient = torch.cat([layer.weight.grad, layer.bias.grad[:, None]], dim=1)
            rotated = vectors_g.T @ gradient @ vectors_a
            # Eigenvalues of A (x) G are the products of theirs; a tiny negative one is rounding.
            rotated /= (values_g[:, None] * values_a[None, :]).clamp(min=0.0) + self.damping
            preconditioned = vectors_g @ rotated @ vectors_a.T
            natural += [preconditioned[:, :-1], preconditioned[:, -1]]
        return natural

    def parameters(self) -> list[torch.Tensor]:
        """The parameters `natural_gradient` gives directions for, in its order."""
        return [p for layer in self.layers for p in (layer.weight, layer.bias)]

    def state_dict(self) -> dict:
        return {"factors": [t for pair in self.factors for t in pair]}

    def load_state_dict(self, saved: dict) -> None:
        flat = list(saved["factors"])
        self.factors = [(a.clone(), g.clone()) for a, g in zip(flat[0::2], flat[1::2])]
