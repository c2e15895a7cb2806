"""Twin Delayed DDPG (TD3): settings, training state and the update, apart from any process.

`update(state, batch, config, actor_step)` is the whole algorithm, in CleanRL's order: the clipped
double-Q target of a smoothed target action, the twin-critic loss and step, and, on the updates
whose `actor_step` is True (every `policy_delay`-th), the deterministic actor's step and the Polyak
copy of target actor and target critics. The learner daemon and the tests call this same function
through `steps.GradientSteps`, which counts the updates, decides `actor_step` from the count, and
may compile the update or capture it as CUDA graphs.

Additions to Fujimoto et al.'s algorithm, all off by default:
- n-step returns (`n_step`): the replay server sums the rewards of n steps and gives each sample
  its bootstrap's discount (`Batch.discounts`), so the target needs no knowledge of the window.
- a linear schedule of the exploration noise (`exploration_std_*`), as DrQ-v2 decays it. The
  std is a buffer of the policy (`DeterministicPolicy.exploration_std`): set after every batch's
  updates (`follow_exploration_schedule`), it goes out with every weights message and checkpoint,
  and the actors explore with it.
- DrQ-v2's two departures (`online_target_actor`, `actor_loss`): the target action from the
  online actor, and the actor ascending the lower critic at its action plus clipped exploration
  noise.

Image observations make it DrQ-v2 (docs/learner.md): one convolutional encoder (the actor's),
learnt by the critic loss alone, embeds each batch once for all networks, each of which projects
the embedding its own way; every update shifts the images at random first (`augment_pad`).

The critics, the batches, the precision options and the speed measures are SAC's
(`l2r.learner.sac`). For graph capture: the update never reads a value back to Python; it
branches on the `actor_step` bool and the config, never on a tensor or a counter; the exploration
std is written from Python outside it (the target noise reads the std's buffer, not a Python float).
"""

from __future__ import annotations

import copy
from dataclasses import asdict, dataclass, field
from typing import Mapping

import torch

from l2r import encoders
from l2r.learner import sac
from l2r.learner.common import adam, bfloat16_pays, check_off_policy, load_adam_state, policy_spec
from l2r.learner.distributed import average_gradients, broadcast
from l2r.learner.sac import Batch, TwinCritic
from l2r.policy import DETERMINISTIC, RESIDUAL, DeterministicPolicy, build_policy
from l2r.protocol.observations import ObservationSpec


Q1, MIN_NOISY = "q1", "min-noisy"
ACTOR_LOSSES = (Q1, MIN_NOISY)


@dataclass
class TD3Config:
    """Algorithm settings (run and infrastructure settings live with the daemon). Network, batch,
    reward and learning-rate defaults are SAC's, so the two compare on the same networks."""

    gamma: float = 0.99
    """Discount per environment step of the policy (one action-repeated step)."""
    tau: float = 0.005
    """Polyak rate: target <- (1 - tau) * target + tau * online, on every actor update."""
    actor_lr: float = 3e-4
    """Adam learning rate of the policy."""
    critic_lr: float = 3e-4
    """Adam learning rate of the twin critics."""
    batch_size: int = 640
    """Transitions per sampled batch."""
    hidden: tuple[int, ...] = (512, 512, 512)
    """Widths of the hidden layers, the same for policy and critics."""
    activation: str = "elu"
    """Hidden activation: 'elu', 'relu' or 'tanh'."""
    layer_norm: bool = True
    """LayerNorm after each hidden Linear, before the activation."""
    reward_scale: float = 10.0
    """Multiplier on rewards before the Bellman target."""
    update_repeat: int = 3
    """Gradient steps taken on each sampled batch."""
    n_step: int = 1
    """Steps summed into each sampled reward before the bootstrap (n-step returns, built by the
    replay server); 1 is TD3's one-step target."""
    policy_delay: int = 2
    """The actor steps, and the targets follow, on every policy_delay-th update; the critics on every one."""
    critic_warmup: int = 0
    """The run's first updates in which the actor holds still while the critics and their targets learn
    its values: a warm start's (`--init-from` a policy), which critics that know nothing yet would
    lead away. 0: none."""
    target_noise: float | None = 0.2
    """Std of the Gaussian noise on the target action (target policy smoothing); None: the current
    exploration std, as DrQ-v2 does."""
    noise_clip: float = 0.5
    """The target action's noise is clipped to +-noise_clip (TD3's paper and SB3: 0.5; DrQ-v2: 0.3)."""
    online_target_actor: bool = False
    """The target action is the online actor's (DrQ-v2), not its Polyak copy's (TD3)."""
    actor_loss: str = Q1
    """What the actor ascends: 'q1', the first critic at the actor's own action (TD3); 'min-noisy', the
    lower of the two critics at that action plus the exploration noise clipped at noise_clip, kept
    in [-1, 1] without cutting the gradient (DrQ-v2)."""
    exploration_std_start: float = 0.1
    """Std of the actors' Gaussian exploration noise at update 0 (SB3 / rl-zoo: 0.1; DrQ-v2: 1.0)."""
    exploration_std_end: float = 0.1
    """... and from exploration_std_updates on (SB3 / rl-zoo: 0.1, a constant; DrQ-v2: 0.1)."""
    exploration_std_updates: int = 250_000
    """Learner updates over which the std goes linearly from start to end. The schedule counts
    gradient steps: at one gradient step per environment step, environment steps."""
    relative_x: bool = False
    """The networks see world x coordinates as distances from the pelvis (see ObservationFilter)."""
    normalize_obs: bool = False
    """The networks see observations standardised by running statistics of the sampled batches."""
    mirror: bool = False
    """Each sampled transition has its legs swapped with probability 1/2, as for SAC."""
    precision: str = "auto"
    """Hidden-layer matmul precision, as SAC's: 'bfloat16', 'float32' or 'auto'."""
    frame_stack: int = 1
    """Observations stacked into each input, oldest first: an image observation's frames (DrQ-v2: 3),
    or the float32 vector's history (SAC's frame_stack)."""
    augment_pad: int = 0
    """Image observations: DrQ's random shift, each image of each update padded by this many pixels
    that repeat its edge and cropped back at a random offset (DrQ-v2: 4); 0: none."""
    encoder: str = encoders.DRQ
    """Image observations: the encoder, 'drq' (DrQ-v2's four convolutions, flattened) or 'dual'
    (RLPixTuner's global and local paths; l2r.encoders.DualPath)."""
    encoder_channels: int = encoders.CHANNELS
    """Image observations: channels of each of the encoder's convolutions."""
    encoder_features: int = encoders.FEATURES
    """Image observations: features out of the actor's and the critics' projections of the encoder's output."""
    residual: int | None = None
    """The policy's action is a change to the last one, which the observation's float32 state holds
    from this index on (l2r.policy, "residual"; the photo tuner's `PhotoTuneEnv.parameters_at`);
    None: a whole action."""

    def __post_init__(self) -> None:
        self.hidden = tuple(int(h) for h in self.hidden)
        check_off_policy(self)
        if min(self.batch_size, self.update_repeat, self.n_step, self.policy_delay) < 1:
            raise ValueError("batch_size, update_repeat, n_step and policy_delay must be >= 1")
        if self.critic_warmup < 0:
            raise ValueError(f"critic_warmup must be >= 0, got {self.critic_warmup}")
        if self.actor_loss not in ACTOR_LOSSES:
            raise ValueError(f"actor_loss must be one of {ACTOR_LOSSES}, got {self.actor_loss!r}")
        stds = (self.exploration_std_start, self.exploration_std_end, self.noise_clip,
                0.0 if self.target_noise is None else self.target_noise)
        if min(stds) < 0 or self.exploration_std_updates < 0:
            raise ValueError("exploration stds, target_noise, noise_clip and exploration_std_updates must be >= 0")

    def to_dict(self) -> dict:
        return {**asdict(self), "hidden": list(self.hidden)}


def exploration_std(config: TD3Config, updates: int) -> float:
    """The exploration std after `updates` updates: linear from start to end over
    exploration_std_updates updates, then end."""
    if updates >= config.exploration_std_updates:
        return config.exploration_std_end
    progress = updates / config.exploration_std_updates
    return config.exploration_std_start + progress * (config.exploration_std_end - config.exploration_std_start)


@dataclass
class TrainState:
    """Everything training changes: networks, target networks, optimizers and counters."""

    actor: DeterministicPolicy
    target_actor: DeterministicPolicy
    critic: TwinCritic
    target_critic: TwinCritic
    actor_opt: torch.optim.Optimizer
    critic_opt: torch.optim.Optimizer
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
        return [*self.actor.parameters(), *self.critic.parameters()]

    def critic_parameters(self) -> list[torch.Tensor]:
        return sac.critic_parameters(self.actor, self.critic)

    def set_learning_rates(self, config: TD3Config) -> None:
        """Apply the config's learning rates (a resumed run takes the command line's, not the saved ones)."""
        for opt, lr in ((self.actor_opt, config.actor_lr), (self.critic_opt, config.critic_lr)):
            for group in opt.param_groups:
                group["lr"] = lr

    def autocast(self) -> torch.autocast:
        return torch.autocast(self.actor.head.weight.device.type, dtype=torch.bfloat16, enabled=self.bfloat16)

    def state_dict(self) -> dict:
        return {name: getattr(self, name).state_dict() for name in (*_MODULES, *_OPTIMIZERS)} | {
            "updates": self.updates, "version": self.version, "extra": dict(self.extra)}

    def load_state_dict(self, saved: Mapping) -> None:
        for name in _MODULES:
            getattr(self, name).load_state_dict(saved[name])
        for name in _OPTIMIZERS:
            load_adam_state(getattr(self, name), saved[name])
        self.updates, self.version = int(saved["updates"]), int(saved["version"])
        self.extra = dict(saved.get("extra", {}))


_MODULES, _OPTIMIZERS = ("actor", "target_actor", "critic", "target_critic"), ("actor_opt", "critic_opt")


def init_state(config: TD3Config, observation: ObservationSpec | int, act_dim: int,
               device: str | torch.device = "cpu", seed: int | None = None) -> TrainState:
    """Freshly initialised networks and optimizers on `device`, for `observation` (its spec, or the
    width of the float32 vector)."""
    device = torch.device(device)
    if isinstance(observation, int):
        observation = ObservationSpec.vector(observation)
    sac.check_mirror(config, observation.vector_width, act_dim)
    if seed is not None:
        torch.manual_seed(seed)
    kind = DETERMINISTIC if config.residual is None else RESIDUAL
    actor = build_policy(policy_spec(config, observation, act_dim, kind, config.frame_stack,
                                     sac.image_encoder(config), residual=config.residual)).to(device)
    sac.check_augmentation(config, actor)
    actor.exploration_std.fill_(exploration_std(config, 0))
    target_actor = copy.deepcopy(actor).requires_grad_(False)
    if actor.encoder is None:
        # The target policy sees observations through the online filter: its statistics are not
        # learned weights, so a slow copy of them would only be a stale one.
        target_actor.observation_filter = actor.observation_filter
    else:
        # One encoder for all (DrQ-v2's): the target networks take the online encoder's embedding.
        target_actor.encoder = actor.encoder
    critic = sac.critics_of(actor, act_dim, config).to(device)
    target_critic = copy.deepcopy(critic).requires_grad_(False)
    bfloat16 = config.precision == "bfloat16" or (config.precision == "auto" and bfloat16_pays(device))
    return TrainState(actor, target_actor, critic, target_critic,
                      adam(sac.policy_parameters(actor), config.actor_lr, device),
                      adam(sac.critic_parameters(actor, critic), config.critic_lr, device), bfloat16=bfloat16)


# Once per sampled batch, SAC's: mirroring and the observation statistics for the vector; an image
# batch goes as it came.
prepare = sac.prepare


def follow_exploration_schedule(state: TrainState, config: TD3Config) -> None:
    """Set the exploration std the schedule gives after `state.updates` updates: what the next
    publication carries. Called after each batch's updates, outside them, so that no compiled or
    captured update holds the Python float."""
    state.actor.exploration_std.fill_(exploration_std(config, state.updates))


def update(state: TrainState, batch: Batch, config: TD3Config, actor_step: bool,
           actor_learns: bool = True) -> dict[str, torch.Tensor]:
    """One TD3 gradient step: the critics', and the actor's and the targets' if `actor_step` (the
    targets' alone where the actor does not learn yet, `config.critic_warmup`).
    Returns detached metrics tensors (`actor_loss` on actor steps only) and `priorities`
    (|TD error|, per sample). `state.updates` is the caller's to count (`steps.GradientSteps` does)."""
    # Observations as the networks see them, embedded once for all of them (SAC's `views`); the
    # residual kind reads its last action from the batch's state, which no shift moves.
    embedding, next_embedding = sac.views(state.actor, batch, config.augment_pad)

    # 1. Target: clipped double Q of the target policy's action, smoothed by clipped noise.
    #    Only a real termination cuts the bootstrap; n-step batches carry the discount of theirs.
    with torch.no_grad(), state.autocast():
        target_policy = state.actor if config.online_target_actor else state.target_actor
        next_action = target_policy.action_of(next_embedding, batch.next_obs)
        noise_std = state.actor.exploration_std if config.target_noise is None else config.target_noise
        smoothing = (torch.randn_like(next_action) * noise_std).clamp(-config.noise_clip, config.noise_clip)
        next_action = (next_action + smoothing).clamp(-1.0, 1.0)
        next_q = state.target_critic(next_embedding, next_action).min(0).values
        target = config.reward_scale * batch.reward + batch.bootstrap_discounts(config.gamma) * next_q

    # 2. Twin critic loss (importance-weighted under prioritized replay) and step, every update.
    with state.autocast():
        q = state.critic(embedding, batch.action)
    td_error = q - target
    squared = td_error.pow(2) if batch.weights is None else td_error.pow(2) * batch.weights
    critic_loss = squared.mean(-1).sum()
    state.critic_opt.zero_grad(set_to_none=True)
    critic_loss.backward()
    average_gradients(state.critic_parameters())
    state.critic_opt.step()
    metrics = {"critic_loss": critic_loss.detach(), "q_mean": q.detach().mean(), "target_mean": target.mean(),
               "priorities": td_error.detach().abs().mean(0)}

    # 3. Delayed: the actor ascends Q1 of its own action, or the lower critic at it with noise (DrQ-v2),
    #    against the updated critics (their weights detached: only dQ/da is needed), then the
    #    targets follow by Polyak averaging.
    if actor_step and actor_learns:
        with state.autocast():
            embedding = embedding.detach()
            action = state.actor.action_of(embedding, batch.obs)
            if config.actor_loss == Q1:
                q_pi = state.critic(embedding, action, detach_weights=True, critics=1)[0]
            else:
                noise = (torch.randn_like(action) * state.actor.exploration_std).clamp(-config.noise_clip,
                                                                                       config.noise_clip)
                noisy = action + noise
                # Held in range, its gradient passed as if it were not (DrQ-v2's): a bound stops no learning.
                noisy = noisy + (noisy.clamp(-1.0, 1.0) - noisy).detach()
                q_pi = state.critic(embedding, noisy, detach_weights=True).min(0).values
        actor_loss = -q_pi.mean()
        state.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
        average_gradients(state.actor.parameters())
        state.actor_opt.step()
        metrics["actor_loss"] = actor_loss.detach()
    if actor_step:
        with torch.no_grad():
            torch._foreach_lerp_([*state.target_actor.parameters(), *state.target_critic.parameters()],
                                 [*state.actor.parameters(), *state.critic.parameters()], config.tau)

    return metrics | {"exploration_std": state.actor.exploration_std.clone()}


def broadcast_state(state: TrainState) -> None:
    """Give every data-parallel rank the weights of rank 0, so all start identical."""
    broadcast([state.actor, state.target_actor, state.critic, state.target_critic])
