"""Soft Actor-Critic: settings, training state and the update, apart from any process.

`update(state, batch, config)` is the whole algorithm, in CleanRL's order: soft Bellman target,
twin-critic loss and step, actor loss and step, temperature (alpha) loss and step, Polyak copy
of the target critics. The learner daemon and the tests call this same function, the daemon
through `steps.GradientSteps`, which counts the updates and may compile the update or capture it
as a CUDA graph: so it never reads a value back to the host and branches only on the config.

Image observations make it DrQ (Kostrikov, Yarats and Fergus, ICLR 2021) in DrQ-v2's arrangement, as
TD3 makes DrQ-v2 (docs/learner.md): one convolutional encoder, the policy's, learnt by the critic
loss alone, embeds each batch once for every network (`views`), of images shifted afresh in each
update (`augment_pad`); the target critics take the online encoder's embedding.

Where the speed comes from: the critics run as one batched network; the actor loss
differentiates the critics with respect to the action only (their weights are detached, so no
weight gradients are computed there); hidden-layer matmuls run in bfloat16 where the hardware
does it natively (`precision`); the optimizers use the fused Adam kernels; and nothing here
reads a value back to Python (metrics stay tensors), so a GPU never waits for the host.
"""

from __future__ import annotations

import copy
import functools
import math
import re
from dataclasses import asdict, dataclass, field, replace
from typing import Mapping

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from l2r import encoders
from l2r.learner.common import (
    Transitions, adam, bfloat16_pays, check_off_policy, device_tensor, float_tensor, load_adam_state, policy_spec,
)
from l2r.learner.distributed import average_gradients, broadcast, sum_over_ranks
from l2r.policy import ACTIVATIONS, Policy, PolicyNetwork, to_tanh_space
from l2r.protocol.observations import ObservationSpec
from l2r.sim import layout

# `hidden` as command lines write it: widths separated by commas, e.g. 256,256.
HIDDEN_WIDTHS = re.compile(r"[1-9]\d*(,[1-9]\d*)*")


@dataclass
class SACConfig:
    """Algorithm settings (run and infrastructure settings live with the daemon)."""

    gamma: float = 0.99
    """Discount per environment step of the policy (one action-repeated step)."""
    tau: float = 0.005
    """Polyak rate: target <- (1 - tau) * target + tau * online, after every update."""
    actor_lr: float = 3e-4
    """Adam learning rate of the policy."""
    critic_lr: float = 3e-4
    """Adam learning rate of the critics."""
    alpha_lr: float = 3e-4
    """Adam learning rate of log(alpha), the entropy temperature."""
    batch_size: int = 640
    """Transitions per sampled batch (the reference solution's 640)."""
    hidden: tuple[int, ...] = (512, 512, 512)
    """Widths of the hidden layers, the same for policy and critics."""
    activation: str = "elu"
    """Hidden activation: 'elu' (reference), 'relu' or 'tanh'."""
    layer_norm: bool = True
    """LayerNorm after each hidden Linear, before the activation (reference: on)."""
    reward_scale: float = 10.0
    """Multiplier on rewards before the Bellman target (per-step rewards here are ~0.01-0.03 m)."""
    update_repeat: int = 3
    """Gradient steps taken on each sampled batch (the reference solution's 3)."""
    n_step: int = 1
    """Rewards of n steps summed by the replay server before the bootstrap (`Batch.discounts`), so
    that a step's reward reaches the value of the state n steps back in one update. The entropy
    bonus is the bootstrap's alone, as in n-step SAC's usual form."""
    critics: int = 2
    """Q networks trained side by side on each batch, each towards the same target: SAC's twin
    critics, or an ensemble (the 2017 finalists' PKU team trained ensembles; REDQ's 10)."""
    critics_in_min: int = 2
    """How many of the critics, drawn anew at each use, the Bellman target and the actor's loss
    take the least of: all of them is SAC's clipped double Q; REDQ's target takes 2 of 10."""
    target_entropy: float | None = None
    """Entropy the temperature steers towards; None means -act_dim."""
    initial_alpha: float = 0.1
    """Entropy temperature at the start of training."""
    autotune_alpha: bool = True
    """Learn alpha towards the target entropy; off keeps it at initial_alpha."""
    min_alpha: float = 0.0
    """A floor under the learnt temperature: however far the entropy rises above its target, alpha
    stays at least this; 0: none."""
    relative_x: bool = False
    """The networks see world x coordinates as distances from the pelvis (see ObservationFilter)."""
    normalize_obs: bool = False
    """The networks see observations standardised by running statistics of the sampled batches."""
    mirror: bool = False
    """Each sampled transition has its legs swapped with probability 1/2: training on the
    mirrored data set as well, at no extra cost per update (the body is left-right symmetric)."""
    frame_stack: int = 1
    """The networks take the last k observations, oldest first (an observation history, as the
    2017 winners stacked theirs, or an image observation's frames: DrQ's 3); the actors keep them
    and the replay stacks them when it samples."""
    augment_pad: int = 0
    """Image observations: DrQ's random shift, each image of each update padded by this many pixels
    that repeat its edge and cropped back at a random offset (DrQ: 4); 0: none."""
    encoder: str = encoders.DRQ
    """Image observations: the encoder, 'drq' (four convolutions, flattened) or 'dual' (RLPixTuner's
    global and local paths; l2r.encoders.DualPath)."""
    encoder_channels: int = encoders.CHANNELS
    """Image observations: channels of each of the encoder's convolutions."""
    encoder_features: int = encoders.FEATURES
    """Image observations: features out of the actor's and the critics' projections of the encoder's output."""
    precision: str = "auto"
    """'bfloat16': hidden-layer matmuls in bfloat16 with float32 accumulation (weights, output
    heads, losses and Adam stay float32); 'float32'; 'auto': bfloat16 on CPUs that compute it
    natively (AVX512-BF16 or AMX), float32 elsewhere, CUDA included (`common.bfloat16_pays`)."""

    def __post_init__(self) -> None:
        self.hidden = tuple(int(h) for h in self.hidden)
        check_off_policy(self)
        if min(self.batch_size, self.update_repeat, self.n_step) < 1 or self.initial_alpha <= 0:
            raise ValueError("batch_size, update_repeat and n_step must be >= 1 and initial_alpha > 0")
        if not 0 <= self.min_alpha <= self.initial_alpha:
            raise ValueError(f"need 0 <= min_alpha <= initial_alpha, got {self.min_alpha} and {self.initial_alpha}")
        if not 1 <= self.critics_in_min <= self.critics:
            raise ValueError(f"need 1 <= critics_in_min <= critics, got {self.critics_in_min} of {self.critics}")

    def to_dict(self) -> dict:
        return {**asdict(self), "hidden": list(self.hidden)}


class TwinCritic(nn.Module):
    """`n` Q networks evaluated as one: every layer stacks the critics' weights as (n, in, out).

    One batched matmul per layer instead of one per critic; `forward` returns (n, batch).
    """

    def __init__(self, obs_dim: int, act_dim: int, hidden: tuple[int, ...], activation: str,
                 layer_norm: bool, n: int = 2, projection: nn.Module | None = None):
        super().__init__()
        dims = [obs_dim + act_dim, *hidden, 1]
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for d_in, d_out in zip(dims[:-1], dims[1:]):
            bound = 1.0 / math.sqrt(d_in)  # nn.Linear's default initialisation
            self.weights.append(nn.Parameter(torch.empty(n, d_in, d_out).uniform_(-bound, bound)))
            self.biases.append(nn.Parameter(torch.empty(n, 1, d_out).uniform_(-bound, bound)))
        self.norm_scales = nn.ParameterList(
            [nn.Parameter(torch.ones(n, 1, h)) for h in hidden] if layer_norm else [])
        self.norm_shifts = nn.ParameterList(
            [nn.Parameter(torch.zeros(n, 1, h)) for h in hidden] if layer_norm else [])
        self.activation = ACTIVATIONS[activation]()
        self.projection = projection
        """Image observations: the critics' own view of the embedding they are given (l2r.encoders.Projection,
        one for both critics, as DrQ-v2's); None: they take it as it is."""

    def forward(self, obs: torch.Tensor, action: torch.Tensor, detach_weights: bool = False,
                critics: int | None = None) -> torch.Tensor:
        """Q values (critics, batch): of the first `critics` only if given (TD3's actor reads Q1)."""
        def used(params: nn.ParameterList) -> list[torch.Tensor]:
            return [(p.detach() if detach_weights else p)[:critics] for p in params]

        weights, biases, scales, shifts = map(used, (self.weights, self.biases, self.norm_scales, self.norm_shifts))
        if self.projection is not None:
            parameters = {name: p.detach() if detach_weights else p for name, p in self.projection.named_parameters()}
            obs = torch.func.functional_call(self.projection, parameters, (obs,))
        x = torch.cat([obs, action], dim=-1).expand(len(weights[0]), -1, -1)
        for i, (w, b) in enumerate(zip(weights[:-1], biases[:-1])):
            x = torch.baddbmm(b, x, w)
            if scales:  # affine cast to x's dtype, so bfloat16 activations stay bfloat16 (half the bytes)
                x = torch.addcmul(shifts[i].to(x.dtype), F.layer_norm(x, x.shape[-1:]), scales[i].to(x.dtype))
            x = self.activation(x)
        # The Q head stays in float32 under mixed precision: TD errors are small differences.
        with torch.autocast(obs.device.type, enabled=False):
            return torch.baddbmm(biases[-1], x.float(), weights[-1]).squeeze(-1)


@dataclass
class TrainState:
    """Everything training changes: networks, optimizers, temperature and counters."""

    actor: Policy
    critic: TwinCritic
    target_critic: TwinCritic
    log_alpha: torch.Tensor
    actor_opt: torch.optim.Optimizer
    critic_opt: torch.optim.Optimizer
    alpha_opt: torch.optim.Optimizer
    target_entropy: float
    updates: int = 0
    """Gradient steps taken so far (over the whole run, across resumes)."""
    version: int = 0
    """Version of the last weights published; increases with every publication."""
    extra: dict = field(default_factory=dict)
    """Counters the hosting process wants checkpointed with the networks (plain values)."""
    bfloat16: bool = False
    """Whether hidden-layer matmuls run in bfloat16 (resolved from config.precision, not saved)."""

    def parameters(self) -> list[torch.Tensor]:
        """What training changes, to check for divergence."""
        return [*self.actor.parameters(), *self.critic.parameters(), self.log_alpha]

    def critic_parameters(self) -> list[torch.Tensor]:
        return critic_parameters(self.actor, self.critic)

    def set_learning_rates(self, config: SACConfig) -> None:
        """Apply the config's learning rates (a resumed run takes the command line's, not the saved ones)."""
        for opt, lr in ((self.actor_opt, config.actor_lr), (self.critic_opt, config.critic_lr),
                        (self.alpha_opt, config.alpha_lr)):
            for group in opt.param_groups:
                group["lr"] = lr

    def autocast(self) -> torch.autocast:
        return torch.autocast(self.log_alpha.device.type, dtype=torch.bfloat16, enabled=self.bfloat16)

    def state_dict(self) -> dict:
        return {name: getattr(self, name).state_dict() for name in (*_MODULES, *_OPTIMIZERS)} | {
            "log_alpha": self.log_alpha.detach().cpu().clone(),
            "updates": self.updates, "version": self.version, "extra": dict(self.extra)}

    def load_state_dict(self, saved: Mapping) -> None:
        for name in _MODULES:
            getattr(self, name).load_state_dict(saved[name])
        for name in _OPTIMIZERS:
            load_adam_state(getattr(self, name), saved[name])
        with torch.no_grad():
            self.log_alpha.copy_(saved["log_alpha"])
        self.updates, self.version = int(saved["updates"]), int(saved["version"])
        self.extra = dict(saved.get("extra", {}))


_MODULES, _OPTIMIZERS = ("actor", "critic", "target_critic"), ("actor_opt", "critic_opt", "alpha_opt")


def init_state(config: SACConfig, observation: ObservationSpec | int, act_dim: int,
               device: str | torch.device = "cpu", seed: int | None = None) -> TrainState:
    """Freshly initialised networks and optimizers on `device`, for `observation` (its spec, or the
    width of the float32 vector)."""
    device = torch.device(device)
    if isinstance(observation, int):
        observation = ObservationSpec.vector(observation)
    check_mirror(config, observation.vector_width, act_dim)
    if seed is not None:
        torch.manual_seed(seed)
    actor = Policy(policy_spec(config, observation, act_dim, frame_stack=config.frame_stack,
                               encoder=image_encoder(config))).to(device)
    check_augmentation(config, actor)
    critic = critics_of(actor, act_dim, config, n=config.critics).to(device)
    target_critic = copy.deepcopy(critic).requires_grad_(False)
    log_alpha = torch.tensor(math.log(config.initial_alpha), device=device, requires_grad=True)
    target_entropy = -float(act_dim) if config.target_entropy is None else float(config.target_entropy)
    bfloat16 = config.precision == "bfloat16" or (config.precision == "auto" and bfloat16_pays(device))
    return TrainState(actor, critic, target_critic, log_alpha,
                      adam(policy_parameters(actor), config.actor_lr, device),
                      adam(critic_parameters(actor, critic), config.critic_lr, device),
                      adam([log_alpha], config.alpha_lr, device), target_entropy,
                      bfloat16=bfloat16)


def image_encoder(config: SACConfig) -> dict:
    """The policy spec's "encoder" of a config (SAC's or TD3's): its sizes, used where the observation has images."""
    return {"kind": config.encoder, "channels": config.encoder_channels, "features": config.encoder_features}


def check_augmentation(config: SACConfig, actor: PolicyNetwork) -> None:
    """ValueError where the config shifts images (augment_pad) and the actor's observation has none."""
    if config.augment_pad and actor.encoder is None:
        raise ValueError(f"augment_pad shifts images, and observation {actor.observation} has none")


def critics_of(actor: PolicyNetwork, act_dim: int, config: SACConfig, n: int = 2) -> TwinCritic:
    """The critics of an actor's observation: on its filtered vector (stacked), or, for images, on the
    actor's encoder's embedding through a projection of their own (DrQ-v2's: one for all n)."""
    if actor.encoder is None:
        return TwinCritic(actor.spec["obs_dim"] * actor.frame_stack, act_dim, config.hidden, config.activation,
                          config.layer_norm, n=n)
    projection = encoders.Projection(actor.encoder.conv_dim, actor.encoder.vector_dim, config.encoder_features)
    return TwinCritic(projection.out_dim, act_dim, config.hidden, config.activation, config.layer_norm, n=n,
                      projection=projection)


def policy_parameters(actor: PolicyNetwork) -> list[torch.Tensor]:
    """What the actor's loss trains: the policy's own layers, not the image encoder it shares with the critics."""
    return [p for name, p in actor.named_parameters() if not name.startswith("encoder.")]


def critic_parameters(actor: PolicyNetwork, critic: TwinCritic) -> list[torch.Tensor]:
    """What the critic loss trains: the critics, and the image encoder the actor shares with them."""
    encoder = [] if actor.encoder is None else list(actor.encoder.parameters())
    return [*critic.parameters(), *encoder]


def check_mirror(config: SACConfig, obs_dim: int | None, act_dim: int) -> None:
    """ValueError if config.mirror is on for widths other than the Learning to Run layout's (None: images)."""
    if config.mirror and (obs_dim, act_dim) != (layout.OBS_SIZE, len(layout.ACTION_LABELS)):
        raise ValueError(f"mirror needs the Learning to Run layout ({layout.OBS_SIZE} observations, "
                         f"{len(layout.ACTION_LABELS)} actions), got {obs_dim} and {act_dim}")


@dataclass
class Batch(Transitions):
    """A batch of sampled transitions."""

    weights: torch.Tensor | None = None
    """Importance weights from prioritized replay, or None for uniform sampling."""
    discounts: torch.Tensor | None = None
    """n-step returns (n_step > 1): the discount of each sample's bootstrap,
    0 where the episode terminated within its window, else gamma^m for a window of m steps; its
    reward is then the window's discounted sum and next_obs the observation after it. None: one step."""

    def bootstrap_discounts(self, gamma: float) -> torch.Tensor:
        """What multiplies each sample's bootstrapped value: its n-step discount, or for one step
        gamma where the episode went on (a time limit included) and 0 where it terminated."""
        return gamma * (1.0 - self.terminated) if self.discounts is None else self.discounts


def batch_from_numpy(obs: np.ndarray, action: np.ndarray, reward: np.ndarray, next_obs: np.ndarray,
                     terminated: np.ndarray, weights: np.ndarray | None = None,
                     device: str | torch.device = "cpu", discounts: np.ndarray | None = None) -> Batch:
    """A Batch from replay arrays; actions arrive as [0, 1] excitations."""
    return _batch(float_tensor(obs, device), float_tensor(next_obs, device), action, reward, terminated, weights,
                  device, discounts)


def batch_from_frames(frames: Mapping[str, np.ndarray], obs_frames: np.ndarray, next_obs_frames: np.ndarray,
                      action: np.ndarray, reward: np.ndarray, terminated: np.ndarray,
                      weights: np.ndarray | None = None, device: str | torch.device = "cpu",
                      discounts: np.ndarray | None = None) -> Batch:
    """A Batch from a sample batch's frames form: each field's distinct frames go to the device once,
    in their own dtype (uint8 images stay uint8, a quarter of float32's bytes), and are gathered
    into stacks there (`encoders.stack_frames`): obs and next_obs are maps of stacked fields."""
    on_device = {name: device_tensor(rows, device) for name, rows in frames.items()}
    obs, next_obs = (encoders.stack_frames(on_device, device_tensor(rows, device))
                     for rows in (obs_frames, next_obs_frames))
    return _batch(obs, next_obs, action, reward, terminated, weights, device, discounts)


def _batch(obs, next_obs, action: np.ndarray, reward: np.ndarray, terminated: np.ndarray,
           weights: np.ndarray | None, device: str | torch.device, discounts: np.ndarray | None) -> Batch:
    return Batch(obs, to_tanh_space(float_tensor(action, device)), float_tensor(reward, device).reshape(-1), next_obs,
                 float_tensor(terminated, device).reshape(-1),
                 None if weights is None else float_tensor(weights, device).reshape(-1),
                 None if discounts is None else float_tensor(discounts, device).reshape(-1))


@functools.cache
def _mirror_permutations(device: torch.device, frames: int) -> tuple[torch.Tensor, torch.Tensor]:
    """layout's leg-swapping permutations on `device` (of each of `frames` observations stacked),
    made once: a copy from host memory to a GPU would wait for the device's queued work on every batch."""
    obs = np.concatenate([np.asarray(layout.MIRROR_OBS) + k * layout.OBS_SIZE for k in range(frames)])
    return torch.as_tensor(obs, device=device), torch.as_tensor(layout.MIRROR_ACTION, device=device)


def prepare(state: TrainState, batch: Batch, config: SACConfig) -> Batch:
    """Once per sampled batch, before its gradient steps: mirror a random half of it (config.mirror)
    and add its observations to the running statistics the networks' inputs are standardised by.
    An image batch goes as it came (its augmentation is drawn afresh in every update)."""
    if state.actor.encoder is not None:
        return batch
    if config.mirror:
        swap = torch.rand(len(batch.obs), 1, device=batch.obs.device) < 0.5
        obs_mirror, action_mirror = _mirror_permutations(batch.obs.device, state.actor.frame_stack)
        batch = replace(batch, obs=torch.where(swap, batch.obs[:, obs_mirror], batch.obs),
                        action=torch.where(swap, batch.action[:, action_mirror], batch.action),
                        next_obs=torch.where(swap, batch.next_obs[:, obs_mirror], batch.next_obs))
    state.actor.observation_filter.update(batch.obs, sum_over_ranks)
    return batch


def views(actor: PolicyNetwork, batch: Batch, augment_pad: int) -> tuple[torch.Tensor, torch.Tensor]:
    """A batch's observation and next observation as every network sees them, each embedded once:
    the filtered vector, or, for images shifted at random first where `augment_pad` says, the
    shared encoder's output, which learns from the critic loss alone (the actor's takes it
    detached); the next one is made without gradients. The shift leaves other fields as they are."""
    obs, next_obs = batch.obs, batch.next_obs
    if augment_pad:
        obs = encoders.random_shift(obs, actor.image_fields, augment_pad)
        next_obs = encoders.random_shift(next_obs, actor.image_fields, augment_pad)
    embedding = actor.embed(obs)
    with torch.no_grad():
        next_embedding = actor.embed(next_obs)
    return embedding, next_embedding


def update(state: TrainState, batch: Batch, config: SACConfig) -> dict[str, torch.Tensor]:
    """One SAC gradient step. Returns detached metrics tensors and `priorities` (|TD error|, per sample).
    `state.updates` is the caller's to count (`steps.GradientSteps` does)."""
    alpha = state.log_alpha.detach().exp()
    embedding, next_embedding = views(state.actor, batch, config.augment_pad)

    # 1. Soft Bellman target. Only a real termination cuts the bootstrap; a time limit does not.
    #    n-step batches carry the discount of theirs.
    with torch.no_grad(), state.autocast():
        next_action, next_log_prob = state.actor.sample_of(next_embedding)
        next_q = least_of_drawn(state.target_critic(next_embedding, next_action), config)
        next_value = next_q - alpha * next_log_prob
        target = config.reward_scale * batch.reward + batch.bootstrap_discounts(config.gamma) * next_value

    # 2. Critic loss, each critic towards the same target (importance-weighted under prioritized replay), and step.
    with state.autocast():
        q = state.critic(embedding, batch.action)
    td_error = q - target
    squared = td_error.pow(2) if batch.weights is None else td_error.pow(2) * batch.weights
    critic_loss = squared.mean(-1).sum()
    state.critic_opt.zero_grad(set_to_none=True)
    critic_loss.backward()
    average_gradients(state.critic_parameters())
    state.critic_opt.step()

    # 3. Actor loss against the updated critics; their weights are detached (only dQ/da is needed).
    with state.autocast():
        embedding = embedding.detach()
        action, log_prob = state.actor.sample_of(embedding)
        q_pi = least_of_drawn(state.critic(embedding, action, detach_weights=True), config)
    actor_loss = (alpha * log_prob - q_pi).mean()
    state.actor_opt.zero_grad(set_to_none=True)
    actor_loss.backward()
    average_gradients(state.actor.parameters())
    state.actor_opt.step()

    # 4. Temperature: raise alpha when entropy is below target, lower it (no further than min_alpha) when above.
    log_prob = log_prob.detach()
    alpha_loss = -(state.log_alpha.exp() * (log_prob + state.target_entropy)).mean()
    if config.autotune_alpha:
        state.alpha_opt.zero_grad(set_to_none=True)
        alpha_loss.backward()
        average_gradients([state.log_alpha])
        state.alpha_opt.step()
        if config.min_alpha > 0:
            with torch.no_grad():
                state.log_alpha.clamp_(min=math.log(config.min_alpha))

    # 5. Polyak copy of the target critics.
    with torch.no_grad():
        torch._foreach_lerp_(list(state.target_critic.parameters()), list(state.critic.parameters()),
                             config.tau)

    return {
        "critic_loss": critic_loss.detach(), "actor_loss": actor_loss.detach(),
        "alpha_loss": alpha_loss.detach(), "alpha": alpha, "q_mean": q.detach().mean(),
        "target_mean": target.mean(), "entropy": -log_prob.mean(),
        "priorities": td_error.detach().abs().mean(0),
    }


def least_of_drawn(q: torch.Tensor, config: SACConfig) -> torch.Tensor:
    """The least, per sample, of `config.critics_in_min` of the critics' values q (critics, batch),
    drawn at random (all of them when it is all of them): a draw on the device, so no host sync."""
    if config.critics_in_min < config.critics:
        q = q[torch.rand(config.critics, device=q.device).argsort()[:config.critics_in_min]]
    return q.min(0).values


def broadcast_state(state: TrainState) -> None:
    """Give every data-parallel rank the weights of rank 0, so all start identical."""
    broadcast([state.actor, state.critic, state.target_critic], [state.log_alpha])
