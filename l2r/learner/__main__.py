"""``l2r-learner``: command line of the learner, SAC, TD3, PPO, A2C, A3C, REINFORCE, TRPO or ACKTR (see
``l2r.learner.daemon``)."""

from __future__ import annotations

import os

# Set before torch loads OpenMP: idle OpenMP workers then sleep instead of spinning. The learner
# shares cores with actors; spinning workers waste them, and when the cores are oversubscribed
# every parallel region waits for a descheduled spinner (measured: 3-4x fewer updates/s).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import sys  # noqa: E402
from functools import cached_property  # noqa: E402
from typing import Literal, Sequence  # noqa: E402

from pydantic import field_validator  # noqa: E402

from l2r.config import (  # noqa: E402
    CommandParser, FilePath, StartupFailure, UsageError, load, run_command, setting, settings_parser,
)
from l2r.encoders import DRQ, DUAL, GLOBAL_SIDE, IMAGE_VIEWS, LOCAL_GRID, MIN_IMAGE_SIDES  # noqa: E402
from l2r.learner.a2c import A2CConfig  # noqa: E402
from l2r.learner.a3c import A3CConfig  # noqa: E402
from l2r.learner.acktr import ACKTRConfig  # noqa: E402
from l2r.learner.algorithms import ON_POLICY  # noqa: E402
from l2r.learner.checkpoint import CheckpointError  # noqa: E402
from l2r.learner.colocated import WorldsConfig  # noqa: E402
from l2r.learner.daemon import LearnerConfig, main  # noqa: E402
from l2r.learner.distributed import DeviceUnavailable  # noqa: E402
from l2r.learner.ppo import LAG_CORRECTIONS, OPTIMIZERS, PPOConfig  # noqa: E402
from l2r.learner.reinforce import ReinforceConfig  # noqa: E402
from l2r.learner.sac import HIDDEN_WIDTHS, SACConfig  # noqa: E402
from l2r.learner.steps import COMPILE_MODES  # noqa: E402
from l2r.learner.td3 import ACTOR_LOSSES, TD3Config  # noqa: E402
from l2r.learner.trpo import TRPOConfig  # noqa: E402
from l2r.protocol import DaemonSettings, ObservationSpec, ProtocolError, configure_logging  # noqa: E402
from l2r.protocol.limits import MAX_FRAME_STACK  # noqa: E402
from l2r.sim.randomize import Randomization  # noqa: E402
from l2r.spaces import task_spaces  # noqa: E402

IMAGE_FRAME_STACK, IMAGE_AUGMENT_PAD = 3, 4
"""DrQ-v2's frame stack and random shift, the defaults for image observations."""

SAC_DEFAULTS, PPO_DEFAULTS, TD3_DEFAULTS = SACConfig(), PPOConfig(), TD3Config()
A3C_DEFAULTS = A3CConfig()
PPO_FAMILY = {"ppo": PPO_DEFAULTS, "a2c": A2CConfig(), "a3c": A3C_DEFAULTS, "reinforce": ReinforceConfig()}
"""The algorithms that are PPO's update at their own settings, each with its defaults."""
TRPO_DEFAULTS, ACKTR_DEFAULTS = TRPOConfig(), ACKTRConfig()
ON_POLICY_DEFAULTS = {**PPO_FAMILY, "trpo": TRPO_DEFAULTS, "acktr": ACKTR_DEFAULTS}
PROCESS, PARALLEL = "learner process", "data parallel (torch.distributed; NCCL with a GPU per rank, else gloo)"
BOTH, SAC = "algorithm (every --algo)", "SAC (with --algo sac)"
PPO = ("on-policy (with --algo ppo, a2c, a3c or reinforce; with --algo trpo or acktr where the algorithm has the "
       "setting)")
NATURAL = "TRPO and ACKTR (natural-gradient steps; with --algo trpo or acktr)"
OFF_POLICY, TD3 = "SAC and TD3 (with --algo sac or td3)", "TD3 (with --algo td3)"
COLOCATED = ("colocated worlds (the learner steps a vector env itself and keeps its transitions on its device, no "
             "replay; every --algo but a3c; l2r.learner.colocated)")
WORLDS_DEFAULTS = WorldsConfig("")


def _defaults(name: str, sac_value=None) -> str:
    """Help text for a setting whose default is the algorithm's: SAC's (TD3's are the same), then
    each on-policy algorithm's that has the setting, algorithms with the same default named together."""
    def shown(value) -> str:
        return ",".join(map(str, value)) if isinstance(value, tuple) else str(value)
    by_value: dict[str, list[str]] = {}
    for algo, config in ON_POLICY_DEFAULTS.items():
        if hasattr(config, name):
            by_value.setdefault(shown(getattr(config, name)), []).append(algo.upper())
    parts = [] if sac_value is None else [f"SAC and TD3 {shown(sac_value)}"]
    parts += [f"{' and '.join(algos)} {value}" for value, algos in by_value.items()]
    return f"(default: {', '.join(parts)})"


class LearnerSettings(DaemonSettings):
    run_dir: FilePath | None = setting(None, "run directory; the checkpoint is <run-dir>/learner/checkpoint.pt "
                                       "(default: runs/<run>)", group=PROCESS)
    resume: bool = setting(False, "continue from the run directory's checkpoint if there is one (networks, "
                           "optimizers, alpha, version, counters)", group=PROCESS)
    init_from: FilePath | None = setting(
        None, "start from this checkpoint (a file, or a run directory's learner/checkpoint.pt) when there is none to "
        "--resume: a training checkpoint gives its networks, optimizers, temperature and counters (staged training: "
        "one run's learner goes on with other settings or on a harder task); a policy checkpoint (best.pt) gives the "
        "policy alone, the critics or value starting fresh. Its networks must be the ones the settings build",
        group=PROCESS, metavar="CHECKPOINT")
    device: Literal["auto", "cpu", "cuda"] = setting("auto", "where to train; auto = CUDA if available", group=PROCESS)
    threads: int = setting(0, "torch CPU threads; 0 = torch's default", group=PROCESS, ge=0)
    compile: Literal[COMPILE_MODES] = setting(
        "auto", "how SAC's and TD3's update runs: off (eager, one kernel launch per operation); graphs (its "
        "update-repeat updates captured as one CUDA graph, replayed per batch; CUDA only, needs no compiler); inductor "
        "(torch.compile's fused kernels; a C++ compiler on CPU, Triton on CUDA; compiles for a minute or more at "
        "start); inductor-graphs (both, CUDA); auto = inductor-graphs on CUDA (graphs without Triton, and for "
        "image observations, which refuse inductor), off on CPU (docs/learner.md)",
        group=PROCESS)
    obs_dim: int = setting(41, "width of the float32 vector observation, when --observation and --env-id are not "
                           "given", group=PROCESS, ge=1)
    observation: str | None = setting(
        None, "the observation the networks take, as l2r-replay's --observation: fields 'name: dtype[shape]' "
        "separated by commas, e.g. 'pixels: uint8[3, 84, 84]'; image fields (uint8[C, H, W]) train with --algo td3 "
        "(DrQ-v2) or sac (DrQ) through --encoder (DrQ-v2's by default), sampled as stacks of --frame-stack "
        "frames. Default: 'state: float32[<obs-dim>]'",
        group=PROCESS, metavar="SPEC")
    env_id: str | None = setting(None, "take the observation (as --observation) and --act-dim from the spaces of this "
                                 "gymnasium environment, e.g. l2r/dmc-cartpole-swingup-v0 (it is made once, and "
                                 "closed)", group=PROCESS)
    act_dim: int = setting(18, "action width", group=PROCESS, ge=1)
    in_flight: int = setting(4, "sample requests kept in flight (on-policy algorithms: a batch fetched ahead comes "
                             "from an older policy; l2r up keeps 1 for them)", group=PROCESS, ge=1)
    prioritized: bool = setting(False, "prioritized sampling, |TD error| sent back as priority (SAC, TD3)",
                                group=PROCESS)
    priority_beta: float = setting(0.4, "importance-weight exponent under prioritized sampling", group=PROCESS, ge=0)
    publish_every: int = setting(50, "updates between weight publications (SAC, TD3; the on-policy algorithms "
                                 "publish after every batch)", group=PROCESS, ge=1)
    checkpoint_interval: float = setting(60.0, "seconds between checkpoints", group=PROCESS, gt=0)
    keep_checkpoints: int = setting(3, "checkpoints kept: checkpoint.pt is the newest, checkpoint-<updates>.pt "
                                    "the newest N", group=PROCESS, ge=1)
    action_repeat: int | None = setting(None, "the actors' action repeat; stored in checkpoints so `l2r eval` steps "
                                        "the env as training did (the learner itself uses it only for colocated "
                                        "worlds)",
                                        group=PROCESS, ge=1)
    metrics_interval: float = setting(5.0, "seconds between metrics reports", group=PROCESS, gt=0)
    max_updates: int = setting(0, "stop after this many updates in total; 0 = until stopped", group=PROCESS, ge=0)
    seed: int | None = setting(None, "torch seed (each rank adds its rank)", group=PROCESS)

    colocated_env: str | None = setting(
        None, "step this gymnasium env's worlds in the learner's own process and train on their transitions, kept "
        "on the training device (l2r/RunWarp-v0 on a GPU: thousands of worlds, big batches), instead of batches "
        "from replay: SAC and TD3 take one step of every world per batch sampled (--update-repeat updates each), "
        "the on-policy algorithms a rollout of every world of --batch-size transitions in all", group=COLOCATED,
        metavar="ENV_ID")
    colocated_worlds: int = setting(WORLDS_DEFAULTS.worlds, "worlds stepped at once", group=COLOCATED, ge=1)
    colocated_capacity: int = setting(WORLDS_DEFAULTS.capacity, "transitions kept on the device; the oldest go first",
                                      group=COLOCATED, ge=1)
    colocated_random_steps: int = setting(
        WORLDS_DEFAULTS.random_steps, "env steps of uniform random actions (all worlds together) before the policy "
        "acts (SAC, TD3)", group=COLOCATED, ge=0)
    colocated_min_replay: int = setting(WORLDS_DEFAULTS.min_replay, "transitions kept before the first batch (and at "
                                        "least --colocated-random-steps and a batch; SAC, TD3)", group=COLOCATED, ge=0)
    colocated_difficulty: int = setting(0, "the runner's difficulty (0, 1 or 2)", group=COLOCATED, ge=0, le=2)
    colocated_randomize: str = setting("", "the runner's per-episode body randomisation, as l2r-actor's --randomize "
                                       "(e.g. strength=0.05,delay=0.5)", group=COLOCATED, metavar="FIELD=FRACTION,...")

    # torchrun's variables, so that each rank it starts knows its place
    world_size: int = setting(1, "number of learners (default: $WORLD_SIZE or 1)", group=PARALLEL, ge=1,
                              variable="WORLD_SIZE")
    rank: int = setting(0, "this learner's rank; rank 0 publishes weights and checkpoints (default: $RANK or 0)",
                        group=PARALLEL, ge=0, variable="RANK")
    dist_url: str | None = setting(None, "rendezvous, e.g. tcp://127.0.0.1:29500 (default: env:// with $MASTER_ADDR "
                                   "and $MASTER_PORT)", group=PARALLEL)

    algo: Literal["sac", "td3", "ppo", "a2c", "a3c", "reinforce", "trpo", "acktr"] = setting(
        "sac", "sac: off-policy, from the replay table; td3: off-policy with a deterministic policy, from the replay "
        "table; on-policy, from the replay server's queue table (l2r-replay --queue-capacity): ppo; a2c, synchronous "
        "advantage actor-critic (PPO's update, one step per batch, RMSprop); a3c, A2C asynchronously: the actors send "
        "gradients of their own rollouts instead of experience, applied as they come (no replay); reinforce, "
        "Monte-Carlo returns and a "
        "value baseline (PPO's update, one step per batch, lambda 1); trpo, trust-region policy optimisation "
        "(conjugate gradients on the KL's Fisher, a line search under --max-kl); acktr, K-FAC natural gradients for "
        "policy and value network in a trust region", group=BOTH)
    batch_size: int | None = setting(None, "transitions per batch; for the on-policy algorithms, per update (their "
                                     "rollout) " + _defaults("batch_size", SAC_DEFAULTS.batch_size), group=BOTH, ge=1)
    gamma: float = setting(SAC_DEFAULTS.gamma, "discount", group=BOTH, ge=0, le=1)
    lr: float | None = setting(None, "learning rate of every network (and of SAC's alpha) "
                               + _defaults("lr", SAC_DEFAULTS.actor_lr), group=BOTH, gt=0)
    hidden: str | None = setting(None, "hidden layer widths of every network, comma-separated "
                                 + _defaults("hidden", SAC_DEFAULTS.hidden), group=BOTH)
    activation: Literal["elu", "relu", "tanh"] | None = setting(
        None, "hidden activation " + _defaults("activation", SAC_DEFAULTS.activation), group=BOTH)
    no_layer_norm: bool = setting(False, "no LayerNorm in hidden layers (SAC's and TD3's default has it)", group=BOTH)
    layer_norm: bool = setting(False, "LayerNorm in hidden layers (PPO's default has none)", group=BOTH)
    reward_scale: float | None = setting(None, "reward multiplier "
                                         + _defaults("reward_scale", SAC_DEFAULTS.reward_scale), group=BOTH)
    relative_x: bool = setting(False, "networks see world x coordinates as distances from the pelvis", group=BOTH)
    normalize_obs: bool = setting(False, "networks see observations standardised by running statistics (shipped "
                                  "with the weights)", group=BOTH)

    update_repeat: int = setting(SAC_DEFAULTS.update_repeat, "gradient steps per sampled batch", group=OFF_POLICY,
                                 ge=1)
    tau: float = setting(SAC_DEFAULTS.tau, "Polyak rate of the target networks", group=OFF_POLICY, gt=0, le=1)
    mirror: bool = setting(False, "swap the legs of a random half of each batch (left-right symmetry as "
                           "augmentation)", group=OFF_POLICY)
    precision: Literal["auto", "float32", "bfloat16"] = setting(
        SAC_DEFAULTS.precision, "hidden-layer matmul precision; auto = bfloat16 on a CPU with native bfloat16, "
        "else float32 (PPO runs float32: its ratios compare the learner's log-probabilities with the actors')",
        group=OFF_POLICY)

    target_entropy: float | None = setting(None, "entropy target of alpha tuning (default: "
                                           "--target-entropy-per-action x act-dim)", group=SAC)
    target_entropy_per_action: float = setting(-1.0, "the entropy target per action dimension, where "
                                               "--target-entropy is not given (-1: SAC's -act-dim)", group=SAC)
    initial_alpha: float = setting(SAC_DEFAULTS.initial_alpha, "starting temperature", group=SAC, gt=0)
    critics: int = setting(SAC_DEFAULTS.critics, "Q networks trained side by side on each batch (2: SAC's twin "
                           "critics; more: an ensemble)", group=SAC, ge=1)
    critics_in_min: int | None = setting(None, "how many of the critics, drawn at random each time, the Bellman "
                                         "target and the actor's loss take the least of (default: all; REDQ's "
                                         "target: 2 of 10)", group=SAC, ge=1)
    fixed_alpha: bool = setting(False, "keep alpha at --initial-alpha (no tuning)", group=SAC)
    min_alpha: float = setting(SAC_DEFAULTS.min_alpha, "a floor under the learnt temperature (0: none)", group=SAC, ge=0)

    n_step: int = setting(TD3_DEFAULTS.n_step, "steps summed into each sampled reward before the bootstrap "
                          "(n-step returns, built by the replay server)", group=OFF_POLICY, ge=1)
    policy_delay: int = setting(TD3_DEFAULTS.policy_delay, "the actor steps and the targets follow on every Nth "
                                "update; the critics on every one", group=TD3, ge=1)
    critic_warmup: int = setting(TD3_DEFAULTS.critic_warmup, "the run's first N updates train the critics and "
                                 "their targets alone, the actor held still: for a warm start (--init-from a "
                                 "policy), whose values fresh critics must learn before they lead it", group=TD3, ge=0,
                                 metavar="N")
    residual_from: int | None = setting(None, "the policy's action is a change to the last one, which the "
                                        "observation's float32 state holds from index N on (the photo tuner's "
                                        "current parameters: l2r photo pretrain --residual); unset: whole actions",
                                        group=TD3, ge=0, metavar="N")
    target_noise: float = setting(TD3_DEFAULTS.target_noise, "std of the noise on the target action (target policy "
                                  "smoothing)", group=TD3, ge=0)
    scheduled_target_noise: bool = setting(False, "the target action's noise takes the current exploration std "
                                           "instead of --target-noise (DrQ-v2's way)", group=TD3)
    noise_clip: float = setting(TD3_DEFAULTS.noise_clip, "the target action's noise is clipped to +-this (DrQ-v2: "
                                "0.3)", group=TD3, ge=0)
    online_target_actor: bool = setting(False, "the target action is the online actor's (DrQ-v2), not its Polyak "
                                        "copy's (TD3)", group=TD3)
    actor_loss: Literal[ACTOR_LOSSES] = setting(
        TD3_DEFAULTS.actor_loss, "what the actor ascends: q1, the first critic at its own action (TD3); min-noisy, "
        "the lower critic at its action plus the exploration noise clipped at --noise-clip (DrQ-v2)", group=TD3)
    exploration_std_start: float = setting(TD3_DEFAULTS.exploration_std_start, "std of the actors' Gaussian "
                                           "exploration noise at update 0 (DrQ-v2: 1.0)", group=TD3, ge=0)
    exploration_std_end: float = setting(TD3_DEFAULTS.exploration_std_end, "... and after "
                                         "--exploration-std-updates updates", group=TD3, ge=0)
    exploration_std_updates: int = setting(TD3_DEFAULTS.exploration_std_updates, "learner updates over which the "
                                           "exploration std goes linearly from start to end (at one gradient step "
                                           "per environment step: environment steps)", group=TD3, ge=0)
    frame_stack: int | None = setting(None, "observations stacked into each input, oldest first: an image "
                                      "observation's last frames, or the float32 vector's history (the actors keep "
                                      "them, the replay stacks them when it samples) (default: "
                                      f"{IMAGE_FRAME_STACK} for images, 1 for the vector)", group=OFF_POLICY, ge=1,
                                      le=MAX_FRAME_STACK)
    augment_pad: int | None = setting(None, "image observations: DrQ's random shift, each image of each update "
                                      "padded by this many pixels that repeat its edge, then cropped back to its "
                                      f"size at a random offset; 0: none (default: {IMAGE_AUGMENT_PAD} for images, "
                                      "0 for the vector, which takes no other)", group=OFF_POLICY, ge=0)
    encoder: Literal[tuple(IMAGE_VIEWS)] = setting(
        DRQ, "image observations: the convolutional encoder of each image field, shared by actor and critics: drq, "
        "DrQ-v2's four 3x3 convolutions of 32 channels (the first of stride 2), flattened; dual, RLPixTuner's "
        f"dual path, a global path (the image averaged down to {GLOBAL_SIDE} x {GLOBAL_SIDE}, strided "
        "convolutions, averaged to one value per channel: its tone and colour) beside a local path (convolutions "
        f"from full resolution, averaged into a grid of {LOCAL_GRID} x {LOCAL_GRID} cells: where its detail is); "
        f"images of at least {MIN_IMAGE_SIDES[DUAL]} x {MIN_IMAGE_SIDES[DUAL]}", group=OFF_POLICY)

    epochs: int | None = setting(None, "passes over each batch " + _defaults("epochs"), group=PPO, ge=1)
    minibatches: int | None = setting(None, "minibatches per pass, one gradient step each " + _defaults("minibatches"),
                                      group=PPO, ge=1)
    clip: float = setting(PPO_DEFAULTS.clip, "clip range of the probability ratio (1 +- clip)", group=PPO, gt=0)
    gae_lambda: float | None = setting(None, "lambda of GAE and of V-trace's traces " + _defaults("gae_lambda"),
                                       group=PPO, ge=0, le=1)
    value_coef: float | None = setting(None, "weight of the value loss, half the squared error "
                                       + _defaults("value_coef"), group=PPO, ge=0)
    entropy_coef: float = setting(PPO_DEFAULTS.entropy_coef, "weight of the entropy bonus", group=PPO, ge=0)
    max_grad_norm: float = setting(PPO_DEFAULTS.max_grad_norm, "gradient norm clip", group=PPO, gt=0)
    max_gradient_staleness: int = setting(
        A3C_DEFAULTS.max_gradient_staleness, "A3C: a gradient computed at weights more than this many versions behind "
        "the learner's is refused (logged and counted)", group=PPO, ge=0)
    optimizer: Literal[OPTIMIZERS] | None = setting(
        None, "adam, or rmsprop (alpha 0.99, as Stable-Baselines3's A2C) " + _defaults("optimizer"), group=PPO)
    normalize_advantages: bool = setting(False, "advantages standardised per minibatch (PPO's and REINFORCE's "
                                         "default; A2C's has none)", group=PPO)
    no_normalize_advantages: bool = setting(False, "advantages as computed, not standardised per minibatch",
                                            group=PPO)
    lag_correction: Literal[LAG_CORRECTIONS] = setting(
        PPO_DEFAULTS.lag_correction, "the actors' policy lag: none (data taken as on-policy), ratio (the acting "
        "policy's log-probabilities in PPO's clipped ratio) or vtrace (V-trace advantages and targets)", group=PPO)
    is_clip: float = setting(PPO_DEFAULTS.is_clip, "V-trace's truncation of importance ratios", group=PPO, gt=0)

    max_kl: float | None = setting(None, "the trust region: how far, in mean KL from the policy before it, one step "
                                   "may move the policy (ACKTR: its quadratic approximation) " + _defaults("max_kl"),
                                   group=NATURAL, gt=0)
    cg_steps: int = setting(TRPO_DEFAULTS.cg_steps, "TRPO: conjugate-gradient steps for the natural gradient",
                            group=NATURAL, ge=1)
    cg_damping: float = setting(TRPO_DEFAULTS.cg_damping, "TRPO: multiple of the identity added to the Fisher",
                                group=NATURAL, ge=0)
    line_search_shrink: float = setting(TRPO_DEFAULTS.line_search_shrink, "TRPO: each backtracking try takes this "
                                        "fraction of the step before", group=NATURAL, gt=0, lt=1)
    line_search_steps: int = setting(TRPO_DEFAULTS.line_search_steps, "TRPO: backtracking tries before the policy "
                                     "step is given up (the policy then stays as it was)", group=NATURAL, ge=1)
    value_epochs: int = setting(TRPO_DEFAULTS.value_epochs, "TRPO: passes of the value network's Adam over each "
                                "batch", group=NATURAL, ge=1)
    value_minibatch_size: int = setting(TRPO_DEFAULTS.value_minibatch_size, "TRPO: transitions per value-network "
                                        "step", group=NATURAL, ge=1)
    target_kl: float = setting(ACKTR_DEFAULTS.target_kl, "ACKTR: after each step, the KL it made adapts --lr (its "
                               "start): divided by 1.5 above twice this, times 1.5 below half of it, as the paper's "
                               "MuJoCo code does (0: --lr fixed)", group=NATURAL, ge=0)
    momentum: float = setting(ACKTR_DEFAULTS.momentum, "ACKTR: SGD momentum on the scaled natural gradient",
                              group=NATURAL, ge=0, lt=1)
    kfac_damping: float = setting(ACKTR_DEFAULTS.kfac_damping, "ACKTR: added to the Kronecker-factored Fisher "
                                  "before it is inverted", group=NATURAL, gt=0)
    kfac_decay: float = setting(ACKTR_DEFAULTS.kfac_decay, "ACKTR: running-average decay of the K-FAC factors",
                                group=NATURAL, ge=0, lt=1)
    value_fisher_coef: float = setting(ACKTR_DEFAULTS.value_fisher_coef, "ACKTR: weight of the value network's "
                                       "sampled log-likelihood in the Fisher statistics", group=NATURAL, ge=0)

    @field_validator("hidden")
    @classmethod
    def _widths(cls, hidden: str | None) -> str | None:
        if hidden is not None and not HIDDEN_WIDTHS.fullmatch(hidden):
            raise ValueError("should be layer widths separated by commas, e.g. 512,512,512")
        return hidden

    @cached_property
    def spaces(self) -> tuple[ObservationSpec, int]:
        """The observation the networks take and the action width: --env-id's (--colocated-env's), --observation's
        or the vector's."""
        env_id = self.env_id or self.colocated_env
        if env_id is not None:
            if self.observation is not None:
                raise UsageError(f"--observation and {env_id}'s spaces both give the observation: give one")
            try:
                return task_spaces(env_id)
            except ValueError as e:
                raise UsageError(f"{env_id}: {e}") from None
        if self.observation is None:
            return ObservationSpec.vector(self.obs_dim), self.act_dim
        try:
            return ObservationSpec.parse(self.observation), self.act_dim
        except ProtocolError as e:
            raise UsageError(f"--observation: {e}") from None

    @property
    def images(self) -> bool:
        return self.spaces[0].vector_width is None

    def check(self) -> None:
        observation = self.spaces[0]
        if self.images and self.algo not in ("sac", "td3"):
            raise UsageError(f"observation {observation}: image observations train with --algo td3 (DrQ-v2) or "
                             "sac (DrQ)")
        if self.images and self.compile.startswith("inductor"):
            raise UsageError(f"--compile {self.compile}: the image update compiled by inductor trained apart from "
                             "eager on a GPU (docs/learner.md); graphs (or auto) captures it as CUDA graphs")
        if not self.images and (self.augment_pad or self.encoder != DRQ):
            raise UsageError(f"--augment-pad and --encoder are for image observations, not {observation}")
        if (self.frame_stack or 1) > 1 and self.algo not in ("sac", "td3"):
            raise UsageError(f"--frame-stack {self.frame_stack}: stacks are sampled from the replay table, by SAC "
                             f"and TD3; --algo {self.algo} takes one observation at a time")
        if self.rank >= self.world_size:
            raise UsageError(f"--rank {self.rank} must be below --world-size {self.world_size}")
        if self.algo != "sac" and (self.critics != SAC_DEFAULTS.critics or self.critics_in_min is not None):
            raise UsageError(f"--critics and --critics-in-min are SAC's; --algo {self.algo} has its own critics")
        if self.layer_norm and self.no_layer_norm:
            raise UsageError("--layer-norm and --no-layer-norm contradict each other")
        if self.normalize_advantages and self.no_normalize_advantages:
            raise UsageError("--normalize-advantages and --no-normalize-advantages contradict each other")
        if self.compile not in ("auto", "off") and (self.algo in ON_POLICY or self.world_size > 1):
            raise UsageError(f"--compile {self.compile} is for one SAC or TD3 learner: {self.algo.upper()} loops "
                             "over its own steps, and data-parallel ranks all-reduce their gradients eagerly")
        if self.compile.endswith("graphs") and self.device == "cpu":
            raise UsageError(f"--compile {self.compile} captures CUDA graphs: it needs --device cuda or auto")
        if self.algo == "a3c" and (self.world_size > 1 or self.images):
            raise UsageError("--algo a3c runs on one learner and vector observations: its gradients come from the "
                             "actors, not from batches the ranks could share")
        if self.algo in ("trpo", "acktr") and self.world_size > 1:
            raise UsageError(f"--algo {self.algo} runs on one learner: its curvature is not averaged over ranks "
                             "(--world-size 1)")
        if self.colocated_env is not None:
            self._check_colocated()
        if self.algo in ON_POLICY and (self.mirror or self.prioritized):
            raise UsageError(f"--mirror and --prioritized are SAC's and TD3's: {self.algo.upper()} learns from the "
                             "actors' own actions, in order (their log-probabilities are of the actions as taken)")

    def _check_colocated(self) -> None:
        if self.env_id not in (None, self.colocated_env):
            raise UsageError(f"--env-id {self.env_id} and --colocated-env {self.colocated_env}: the networks take the "
                             "colocated worlds' spaces; give one env")
        if self.algo == "a3c":
            raise UsageError("--colocated-env trains on its worlds' transitions; --algo a3c takes the actors' "
                             "gradients")
        if self.images or (self.frame_stack or 1) > 1:
            raise UsageError(f"--colocated-env {self.colocated_env}: colocated worlds give one float32 vector at a "
                             f"time (observation {self.spaces[0]}, --frame-stack {self.frame_stack or 1})")
        if self.prioritized or self.world_size > 1:
            raise UsageError("--colocated-env samples uniformly, on one learner: no --prioritized or --world-size")
        if self.n_step > 1:
            raise UsageError(f"--n-step {self.n_step}: colocated worlds keep one-step transitions; n-step returns "
                             "are built by the replay server")
        if self.colocated_randomize:
            try:
                Randomization.parse(self.colocated_randomize)
            except ValueError as e:
                raise UsageError(f"--colocated-randomize: {e}") from None

    def worlds(self) -> WorldsConfig | None:
        """The colocated worlds (--colocated-env), or None: batches from replay."""
        if self.colocated_env is None:
            return None
        return WorldsConfig(self.colocated_env, self.colocated_worlds, self.colocated_capacity,
                            self.colocated_random_steps, self.colocated_min_replay, self.action_repeat or 1,
                            self.colocated_difficulty, self.colocated_randomize, self.seed or 0)

    def _network(self, defaults: SACConfig | PPOConfig | TD3Config) -> dict:
        """The settings both algorithms have, each unset one at the algorithm's default."""
        return {"batch_size": self.batch_size or defaults.batch_size, "gamma": self.gamma,
                "hidden": tuple(int(h) for h in self.hidden.split(",")) if self.hidden else defaults.hidden,
                "activation": self.activation or defaults.activation,
                "layer_norm": self.layer_norm or (defaults.layer_norm and not self.no_layer_norm),
                "reward_scale": self._given("reward_scale", defaults.reward_scale),
                "relative_x": self.relative_x, "normalize_obs": self.normalize_obs}

    def sac(self) -> SACConfig:
        try:
            return SACConfig(
                **self._network(SAC_DEFAULTS), tau=self.tau, actor_lr=self._given("lr", SAC_DEFAULTS.actor_lr),
                critic_lr=self._given("lr", SAC_DEFAULTS.critic_lr), alpha_lr=self._given("lr", SAC_DEFAULTS.alpha_lr),
                update_repeat=self.update_repeat, n_step=self.n_step,
                target_entropy=self._given("target_entropy", self.target_entropy_per_action * self.spaces[1]),
                initial_alpha=self.initial_alpha, autotune_alpha=not self.fixed_alpha,
                min_alpha=self.min_alpha, critics=self.critics,
                critics_in_min=self._given("critics_in_min", self.critics), mirror=self.mirror,
                precision=self.precision, **self._image_options())
        except ValueError as e:  # a combination SACConfig refuses
            raise UsageError(str(e)) from None

    def _image_options(self) -> dict:
        """The frame stack, random shift and encoder SAC and TD3 share, DrQ-v2's for images where unset."""
        return {"frame_stack": self.frame_stack or (IMAGE_FRAME_STACK if self.images else 1),
                "augment_pad": self._given("augment_pad", IMAGE_AUGMENT_PAD if self.images else 0),
                "encoder": self.encoder}

    def _given(self, name: str, default):
        """The flag `name` as given, or `default` where it was left unset (None)."""
        value = getattr(self, name)
        return default if value is None else value

    def _on_policy_common(self, defaults: PPOConfig | TRPOConfig | ACKTRConfig) -> dict:
        """The settings every on-policy algorithm has, each unset one at the algorithm's default."""
        return {**self._network(defaults), "lr": self._given("lr", defaults.lr),
                "gae_lambda": self._given("gae_lambda", defaults.gae_lambda),
                "normalize_advantages": self.normalize_advantages or (defaults.normalize_advantages
                                                                      and not self.no_normalize_advantages),
                "lag_correction": self.lag_correction, "is_clip": self.is_clip}

    def on_policy(self) -> PPOConfig:
        """PPO's, A2C's or REINFORCE's settings (--algo's), each unset one at that algorithm's default."""
        defaults = PPO_FAMILY[self.algo]
        try:
            return type(defaults)(
                **self._on_policy_common(defaults), clip=self.clip, entropy_coef=self.entropy_coef,
                max_grad_norm=self.max_grad_norm,
                **({"max_gradient_staleness": self.max_gradient_staleness} if self.algo == "a3c" else {}),
                **{name: self._given(name, getattr(defaults, name))
                   for name in ("epochs", "minibatches", "value_coef", "optimizer")})
        except ValueError as e:  # a combination the config refuses
            raise UsageError(str(e)) from None

    def trpo(self) -> TRPOConfig:
        try:
            return TRPOConfig(
                **self._on_policy_common(TRPO_DEFAULTS), max_kl=self._given("max_kl", TRPO_DEFAULTS.max_kl),
                cg_steps=self.cg_steps, cg_damping=self.cg_damping, line_search_shrink=self.line_search_shrink,
                line_search_steps=self.line_search_steps, value_epochs=self.value_epochs,
                value_minibatch_size=self.value_minibatch_size)
        except ValueError as e:  # a combination TRPOConfig refuses
            raise UsageError(str(e)) from None

    def acktr(self) -> ACKTRConfig:
        try:
            return ACKTRConfig(
                **self._on_policy_common(ACKTR_DEFAULTS), max_kl=self._given("max_kl", ACKTR_DEFAULTS.max_kl),
                momentum=self.momentum, target_kl=self.target_kl, kfac_damping=self.kfac_damping,
                kfac_decay=self.kfac_decay,
                value_fisher_coef=self.value_fisher_coef,
                value_coef=self._given("value_coef", ACKTR_DEFAULTS.value_coef), entropy_coef=self.entropy_coef)
        except ValueError as e:  # a combination ACKTRConfig refuses
            raise UsageError(str(e)) from None

    def td3(self) -> TD3Config:
        try:
            return TD3Config(
                **self._network(TD3_DEFAULTS), tau=self.tau, actor_lr=self._given("lr", TD3_DEFAULTS.actor_lr),
                critic_lr=self._given("lr", TD3_DEFAULTS.critic_lr),
                update_repeat=self.update_repeat, n_step=self.n_step, policy_delay=self.policy_delay,
                critic_warmup=self.critic_warmup, target_noise=None if self.scheduled_target_noise else self.target_noise, noise_clip=self.noise_clip,
                online_target_actor=self.online_target_actor, actor_loss=self.actor_loss,
                exploration_std_start=self.exploration_std_start, exploration_std_end=self.exploration_std_end,
                exploration_std_updates=self.exploration_std_updates, mirror=self.mirror, precision=self.precision,
                residual=self.residual_from, **self._image_options())
        except ValueError as e:  # a combination TD3Config refuses
            raise UsageError(str(e)) from None

    def algorithm(self) -> SACConfig | PPOConfig | TD3Config | TRPOConfig | ACKTRConfig:
        return {"sac": self.sac, "td3": self.td3, **dict.fromkeys(PPO_FAMILY, self.on_policy), "trpo": self.trpo,
                "acktr": self.acktr}[self.algo]()

    def learner(self) -> LearnerConfig:
        observation, act_dim = self.spaces
        return LearnerConfig(
            run=self.run, run_dir=self.run_dir, resume=self.resume, init_from=self.init_from, device=self.device,
            threads=self.threads, compile=self.compile, obs_dim=observation.vector_width or 0,
            observation=observation if self.images else None, act_dim=act_dim, prioritized=self.prioritized,
            priority_beta=self.priority_beta, in_flight=self.in_flight, publish_every=self.publish_every,
            checkpoint_interval=self.checkpoint_interval, keep_checkpoints=self.keep_checkpoints,
            action_repeat=self.action_repeat, metrics_interval=self.metrics_interval,
            max_updates=self.max_updates, seed=self.seed, colocated=self.worlds(), world_size=self.world_size,
            rank=self.rank, dist_url=self.dist_url)


def build_parser() -> CommandParser:
    return settings_parser(
        LearnerSettings, "l2r-learner",
        "Learner of an l2r run. SAC (the default) samples batches from the replay server(s) with several requests "
        "in flight and trains twin critics, a tanh-Gaussian policy and the entropy temperature; TD3 (--algo td3) "
        "samples the same way and trains twin critics and a deterministic policy, which the actors explore with "
        "scheduled Gaussian noise; PPO (--algo ppo), A2C (--algo a2c), REINFORCE (--algo reinforce), TRPO (--algo "
        "trpo) and ACKTR (--algo acktr) take batches from the replay servers' queue table, each transition once, and "
        "train the same policy with a value network. SAC and TD3 also learn from images (--observation or --env-id "
        "of a camera task): DrQ and DrQ-v2, one convolutional encoder trained by the critics. All publish versioned "
        "policy weights for actors and checkpoint atomically.",
        "Example: l2r-learner --run exp1 --connect tcp/127.0.0.1:7447 --run-dir runs/exp1 --resume\n"
        "TD3: l2r-learner --algo td3 --exploration-std-start 1.0 --exploration-std-updates 100000 ...\n"
        "PPO: l2r-learner --algo ppo --in-flight 1 ... against l2r-replay --capacity 0 --queue-capacity 8192 "
        "(A2C, REINFORCE, TRPO and ACKTR the same, with --algo a2c, reinforce, trpo or acktr)\n"
        "Two data-parallel learners: add --world-size 2 --rank 0|1 --dist-url tcp://127.0.0.1:29500\n"
        "Colocated worlds, no replay: l2r-learner --algo td3 --device cuda --colocated-env l2r/RunWarp-v0 "
        "--colocated-worlds 4096 --batch-size 32768 --action-repeat 3 ...")


def parse_settings(argv: Sequence[str] | None = None) -> LearnerSettings:
    return load(LearnerSettings, build_parser(), argv)


def cli(argv: Sequence[str] | None = None) -> int:
    return run_command("l2r-learner", lambda: train(parse_settings(argv)))


def train(s: LearnerSettings) -> int:
    algo = s.algorithm()
    configure_logging(s.log_level)
    try:
        return main(s.learner(), algo, s.zenoh_session_config())
    except (DeviceUnavailable, CheckpointError) as e:  # a restart would meet the same device or file
        raise StartupFailure(str(e)) from None


if __name__ == "__main__":
    sys.exit(cli())
