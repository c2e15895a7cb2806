"""The `l2r-actor` daemon: several environments in one process (single envs, or the worlds of one
vector env: `worlds.py`), one batched policy call per step.

Each loop iteration swaps in the newest weights if some arrived, picks actions for all
environments at once (uniform random excitations during warm-up, the stochastic policy while
training, its mean when evaluating), steps every environment, and hands finished chunks and
episodes to Zenoh. Nothing here blocks on the learner: without new weights the actor goes on
with the policy it has. While its own replay shard is not alive it waits, since its experience
would be lost. Sent chunks stay in a resend buffer until that shard acknowledges them; a
background thread sends the unacknowledged ones again, so chunks lost in flight (a cut link) are
not lost, and on shutdown the actor waits a little for the acks of its last chunks.
"""

from __future__ import annotations

import dataclasses
import functools
import importlib
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import NamedTuple

import gymnasium
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.wrappers import RescaleAction
import torch
import zenoh

import l2r.control  # noqa: F401  (registers the camera tasks, l2r/dmc-<domain>-<task>-v0)
import l2r.photo  # noqa: F401  (registers the photo tasks, l2r/PhotoTune-v0)
from l2r.actors.actor_id import ask_actor_id
from l2r.actors.curriculum import Course, DifficultySchedule
from l2r.actors.experience import ChunkBuilder, ResendBuffer
from l2r.actors.frame_stack import FrameStack
from l2r.actors.gradients import GradientSender
from l2r.actors.noise import ColouredNoise
from l2r.actors.parameter_noise import ParameterNoise
from l2r.actors.weights import WeightFollower
from l2r.actors.worlds import EnvList, VectorWorlds, Worlds
from l2r.config import StartupFailure
from l2r.episodes.live import LiveFrames
from l2r.families import PHOTO, RUNNER, family_of, score_of
from l2r.policy import act, act_with_log_prob, uniform_log_prob
from l2r.protocol import (
    EPISODE_QOS, EXPERIENCE_QOS, LISTENER_GRACE, ROUND_QOS, STATS_QOS, EpisodeSummary, EvaluationRound, FrameCompressor,
    Keys, ObservationSpec, ProtocolError, Rejections, ReplayAck, Stats, await_listener, decode, encode, shard_of,
)
from l2r.sim import WARP_ID, randomize_refusal  # (importing l2r.sim registers the runner's envs)
from l2r.sim.randomize import Randomization
from l2r.sim.wrappers import ActionNoise, ActionRepeat, ObservationNoise
from l2r.spaces import image_size_option, photo_goals_option

log = logging.getLogger("l2r.actor")

STEP_SECONDS = 0.01  # one inner step of the runner
MAX_RESEND_DELAY = 30.0  # a chunk's resend wait doubles up to this while no shard acknowledges it
HOLD_FOR = 2.0  # seconds an ack's hold lasts unless renewed (a shard repeats it every ack interval)


def blew_up(reward: float, info: dict, max_speed: float) -> bool:
    """Whether a step moved the pelvis faster than any runner can: a simulation blow-up, whose
    reward would teach the policy to break the physics rather than to run."""
    return max_speed > 0 and abs(reward) > max_speed * STEP_SECONDS * int(info.get("inner_steps", 1))


# The version of the policy a learner publishes before its first update.
UNTRAINED = 1
# Env steps each world's exploration noise series spans (the runner's, Hopper's, a camera task's
# episode at most): a series covers an episode's actions.
NOISE_SERIES_STEPS = 1000


@dataclass
class ActorConfig:
    """What one actor process does. Run and network settings travel in the Zenoh config."""

    run: str = "default"
    actor_id: int | None = 0
    """None: ask replay shard 0 for an id no other actor process of the run has (--actor-id auto)."""
    num_envs: int = 4
    """Environments stepped in lock-step, their observations batched into one policy call."""
    vector_env: bool | None = None
    """Step the envs as one gymnasium VectorEnv, one call for all (`make_worlds`); None: when the
    env id registers a vector entry point (l2r/RunWarp-v0). Training actors only."""
    device: str = "cpu"
    """Where the policy acts, and l2r/RunWarp-v0's worlds step: cpu, cuda, or auto (cuda if there is one)."""
    env_id: str = "l2r/Run-v0"
    """Gymnasium id of the environment: any env with Box actions and a Box, or Dict of Box,
    observation space (`ObservationSpec.from_space`)."""
    image_size: int | None = None
    """A camera task's frames, pixels a side (None: the task's own, 84)."""
    photo_goals: str | None = None
    """The photo tuner's goals (l2r.photo.env.GOALS; None: the task's own, random)."""
    difficulty: int = 0
    difficulty_schedule: DifficultySchedule | None = None
    """Training episodes start at the schedule's difficulty, its stages entered at a count of the
    actor's env steps or a distance its episodes reach (the runner; l2r.actors.curriculum.Course;
    None: `difficulty` throughout)."""
    env_steps_before: int = 0
    """Env steps this actor's place in the run took before this process: where the schedule goes on from."""
    randomize: Randomization = field(default_factory=Randomization)
    """Per-episode randomisation of the MuJoCo runner's body (off by default)."""
    observation_noise: float = 0.0
    """Std of the Gaussian noise added to every observed value (0: none)."""
    action_noise: float = 0.0
    """Std of the Gaussian noise added to every action value before the env takes it (0: none)."""
    exploration_noise: str = "white"
    """The colour of the policy's own exploring draws over an episode (`l2r.actors.noise.COLOURS`):
    white draws each step's anew; pink and red are correlated in time."""
    parameter_noise: float = 0.0
    """Exploration in parameter space (`l2r.actors.parameter_noise`): each world's policy weights
    perturbed for each episode, the std adapted to this RMS distance of the actions (0: off)."""
    action_repeat: int = 3
    random_steps: int = 5_000
    """Uniform random excitations for this many of the actor's first steps (skipped when it
    joins a run whose policy is already past version 0)."""
    chunk_size: int = 64
    """Transitions per experience chunk."""
    chunk_delay: float = 1.0
    """A chunk older than this (seconds) is sent even when not full."""
    resend_buffer_mb: float = 64.0
    """Sent chunks kept until the replay shard acknowledges them (MiB; oldest dropped beyond; 0: off)."""
    resend_delay: float = 3.0
    """Seconds after its last send before an unacknowledged chunk is sent again (then doubling)."""
    compress_frames: bool = True
    """Send the chunks' frames (uint8 fields) zstd-compressed, protocol version 3: 3.5 - 32 times
    fewer bytes for well under 1 % of a camera actor's CPU (docs/performance.md)."""
    final_ack_wait: float = 5.0
    """At shutdown, seconds to wait for the shard to acknowledge the last chunks (when it acknowledges at all)."""
    seed: int = 0
    num_shards: int = 1
    evaluate: bool = False
    """Evaluation role: deterministic episodes on fixed seeds, no experience sent."""
    eval_episodes: int = 4
    """Evaluation: episodes per round, on seeds seed, seed+1, ..."""
    eval_interval: float = 30.0
    """Evaluation: seconds between the starts of two rounds (a round waits for a new policy)."""
    torch_threads: int = 1
    max_speed: float = 20.0
    """Pelvis speed (m/s) above which a step counts as a simulation blow-up: the episode ends
    before it (stored as a terminal step without reward) and the blow-up is counted (0: off)."""
    stats_interval: float = 2.0
    max_steps: int = 0
    """Stop after this many steps of this actor (0: run until stopped)."""
    episode_log: dict = field(default_factory=dict)
    """Keyword arguments for the MCAP episode logger; empty: no logging."""
    send_gradients: bool = False
    """A3C: each chunk's gradient (at the weights that acted it) goes to the learner instead of the
    chunk, and weights are swapped in only between chunks (`l2r.actors.gradients`)."""

    @property
    def role(self) -> str:
        return "evaluator" if self.evaluate else "actor"


def make_task(env_id: str, difficulty: int = 0, seed: int | None = None,
              randomize: Randomization | None = None, image_size: int | None = None,
              photo_goals: str | None = None) -> gymnasium.Env:
    """The runner (l2r/...) with its difficulty, seed and randomisation (the MuJoCo bodies' alone),
    or any other gymnasium env with Box actions (a camera task's frames `image_size` pixels a side,
    the photo tuner's goals `photo_goals`, None: its own), rescaled so that it takes the policy's
    [0, 1] excitations (Hopper-v5's [-1, 1], say)."""
    if randomize and randomize_refusal(env_id):
        raise ValueError(randomize_refusal(env_id))
    if family_of(env_id) == RUNNER:
        options = {"randomize": randomize} if randomize else {}  # the OpenSim env takes no randomize
        return gymnasium.make(env_id, difficulty=difficulty, seed=seed, **options)
    return unit_actions(gymnasium.make(env_id, **image_size_option(env_id, image_size),
                                       **photo_goals_option(env_id, photo_goals)))


def unit_actions(env: gymnasium.Env) -> gymnasium.Env:
    """The env, rescaled where its Box actions are not [0, 1] already so that it takes the policy's
    [0, 1] excitations."""
    if not (np.all(env.action_space.low == 0.0) and np.all(env.action_space.high == 1.0)):
        bound = env.action_space.dtype.type  # (Python floats would make gymnasium warn of a float64 bound)
        env = RescaleAction(env, bound(0.0), bound(1.0))
    return env


def make_env(config: ActorConfig, seed: int) -> gymnasium.Env:
    """The actor's task (`make_task`) with the noise configured, each action repeated as configured
    (the action noise drawn anew for each repeat)."""
    env = make_task(config.env_id, config.difficulty, seed, config.randomize, config.image_size, config.photo_goals)
    if config.action_noise:
        env = ActionNoise(env, config.action_noise)
    if config.observation_noise:
        env = ObservationNoise(env, config.observation_noise)
    return ActionRepeat(env, config.action_repeat) if config.action_repeat > 1 else env


def registers_vector_env(env_id: str) -> bool:
    """Whether ``env_id`` registers a vector entry point: a VectorEnv of its own (l2r/RunWarp-v0;
    "module:Name-v0" imports the module that registers it, as gymnasium.make does)."""
    module, _, name = env_id.rpartition(":")
    try:
        if module:
            importlib.import_module(module)
        return gymnasium.spec(name).vector_entry_point is not None
    except (gymnasium.error.Error, ImportError):  # an unknown id or module: make_env says so
        return False


def uses_vector_env(config: ActorConfig) -> bool:
    """Whether the actor steps its envs as one VectorEnv (an evaluator runs single envs, as `l2r eval` does)."""
    if config.evaluate:
        return False
    return registers_vector_env(config.env_id) if config.vector_env is None else config.vector_env


def make_worlds(config: ActorConfig, seeds: list[int]) -> Worlds:
    """The actor's ``config.num_envs`` envs, world i's first episode to start from seeds[i]:
    single envs (`make_env`) stepped one by one, or where `uses_vector_env` one VectorEnv, the env
    id's own (its action repeated across it; no noise wrappers) or else a SyncVectorEnv of the
    single envs, which the actor resets itself (the same experience as the single envs)."""
    if not uses_vector_env(config):
        return EnvList([make_env(config, seed) for seed in seeds])
    if not registers_vector_env(config.env_id):
        envs = [functools.partial(make_env, config, seed) for seed in seeds]
        return VectorWorlds(gymnasium.vector.SyncVectorEnv(envs, autoreset_mode=AutoresetMode.DISABLED))
    # l2r/RunWarp-v0's worlds on the actor's device, each reset with the actor's seed and options
    env = make_vector_task(config.env_id, config.num_envs, config.difficulty, config.randomize, config.device,
                           AutoresetMode.DISABLED)
    return VectorWorlds(env, config.action_repeat)


def make_vector_task(env_id: str, num_envs: int, difficulty: int = 0, randomize: Randomization | None = None,
                     device: str | None = None,
                     autoreset_mode: AutoresetMode = AutoresetMode.SAME_STEP) -> gymnasium.vector.VectorEnv:
    """The vector env an id registers of its own (`registers_vector_env`), as `make_task` makes a
    single one: the runner's with its difficulty, and `l2r/RunWarp-v0`'s worlds on the Warp
    `device` with the randomisation and the autoreset mode given."""
    options = {"difficulty": difficulty} if family_of(env_id) == RUNNER else {}
    if env_id == WARP_ID:
        options |= {"device": device, "autoreset_mode": autoreset_mode}
        options |= {"randomize": randomize} if randomize else {}
    return gymnasium.make_vec(env_id, num_envs=num_envs, vectorization_mode="vector_entry_point", **options)


class ObservationError(RuntimeError):
    """The environment's observations are not ones l2r takes: its declared space, or a reset or
    step that breaks it. The actor stops: every chunk would be refused."""


def observation_spec(env: gymnasium.Env, env_id: str) -> ObservationSpec:
    """The spec ``env`` declares (ObservationError when l2r cannot take its space)."""
    try:
        return ObservationSpec.from_space(env.observation_space)
    except (ValueError, ProtocolError) as e:
        raise ObservationError(f"{env_id}: {e}") from None


def fields_of(spec: ObservationSpec, observation, env_id: str) -> dict[str, np.ndarray]:
    """An observation ``env_id`` returned, as the fields of its spec (ObservationError when it
    breaks the env's own declared space)."""
    try:
        return spec.fields_of(observation)
    except ProtocolError as e:
        raise ObservationError(f"{env_id} returned an observation outside its own observation space: {e}") from None


def levers_on(config: ActorConfig) -> list[str]:
    """The robustness levers a training actor has on, as its start line names them."""
    if config.evaluate:
        return []
    going_on = f" from env step {config.env_steps_before:,}" if config.env_steps_before else ""
    on = {f"difficulty schedule {config.difficulty_schedule}{going_on}": config.difficulty_schedule is not None,
          f"randomised {config.randomize}": bool(config.randomize),
          f"observation noise {config.observation_noise:g}": config.observation_noise,
          f"action noise {config.action_noise:g}": config.action_noise,
          f"{config.exploration_noise} exploration noise": config.exploration_noise != "white",
          f"parameter noise {config.parameter_noise:g}": config.parameter_noise}
    return [lever for lever, is_on in on.items() if is_on]


def episode_seed(config: ActorConfig, env_index: int, episode: int) -> int:
    """Training seeds differ across actors, envs and episodes; evaluation seeds are fixed."""
    if config.evaluate:
        return config.seed + episode % config.eval_episodes
    return int(np.random.SeedSequence([config.seed, config.actor_id, env_index, episode]).generate_state(1)[0])


def course_of(config: ActorConfig) -> Course | None:
    """A training actor's place on its difficulty schedule (None: `config.difficulty` throughout)."""
    if config.difficulty_schedule is None or config.evaluate:
        return None
    return Course(config.difficulty_schedule, config.env_steps_before)


def episode_difficulty(config: ActorConfig, course: Course | None, steps: int) -> tuple[int, dict | None]:
    """The difficulty of a training episode starting after `steps` env steps of this process on
    `course`, and the reset options that set it (None: the env's own, `config.difficulty`)."""
    if course is None:
        return config.difficulty, None
    difficulty = course.difficulty(steps)
    return difficulty, {"difficulty": difficulty}


class ReplayWatch:
    """Whether the replay shard an actor feeds holds its liveliness token: another shard alive
    does not store this actor's chunks."""

    def __init__(self, session: zenoh.Session, keys: Keys, shard: int):
        self.shard = shard
        self.alive = False
        self._sub = session.liveliness().declare_subscriber(keys.alive("replay", shard), self._on_token, history=True)

    def _on_token(self, sample: zenoh.Sample) -> None:
        self.alive = sample.kind == zenoh.SampleKind.PUT


@dataclass
class EnvSlot:
    """One world's episode in progress."""

    obs: dict[str, np.ndarray]  # the fields of the observation to act on
    seed: int
    difficulty: int
    episode: int = 0
    ret: float = 0.0
    length: int = 0
    start_x: float = 0.0
    x: float = 0.0  # distance after the last step
    recorder: object = None  # MCAP recorder of the episode (a no-op one when not logged)


class Actor:
    """The stepping loop; `main` wires it to a Zenoh session."""

    def __init__(self, config: ActorConfig, session: zenoh.Session):
        self.config = config
        self.keys = Keys(config.run)
        self.session = session
        self.replay = None if config.evaluate else ReplayWatch(
            session, self.keys, shard_of(config.actor_id, config.num_shards))
        self.rng = np.random.default_rng([config.seed, config.actor_id])
        self.epoch = time.time_ns()
        self.seq = 0
        self.steps = 0
        self.course = course_of(config)
        self.episodes = 0
        self.chunks_sent = 0
        self.blowups = 0
        self.held_s = 0.0  # seconds spent waiting because the shard's queue was full
        self.waiting_for_replay = False
        self.first_version: int | None = None  # version of the first weights received
        self.random_phase = not config.evaluate and config.random_steps > 0
        self.slots: list[EnvSlot] = []
        seeds = [episode_seed(config, i, 0) for i in range(config.num_envs)]
        self.worlds = make_worlds(config, seeds)
        self.noise = None if config.evaluate or config.exploration_noise == "white" else ColouredNoise(
            config.exploration_noise, config.num_envs, self.worlds.action_space.shape[0],
            math.ceil(NOISE_SERIES_STEPS / config.action_repeat), self.rng)
        self.parameter_noise = None if config.evaluate or not config.parameter_noise else ParameterNoise(
            config.parameter_noise, config.num_envs, seed=int(self.rng.integers(2**63)))
        self.observation = observation_spec(self.worlds, config.env_id)
        # Photos are images too, but no camera renders them: no frames to count.
        images = any(field.dtype == np.uint8 for field in self.observation.fields.values())
        self.camera = images and family_of(config.env_id) != PHOTO
        self.frames = 0  # of a camera task: the inner steps its env took, the "frames" papers count
        difficulty, options = episode_difficulty(self.config, self.course, self.steps)
        for seed, (obs, info) in zip(seeds, self.worlds.reset(seeds, options)):
            x = float(info.get("distance", 0.0))
            self.slots.append(EnvSlot(self.observe(obs), seed, difficulty, start_x=x, x=x))
        self.weights = WeightFollower(session, self.keys, self.observation, config.device)
        self.stacks = FrameStack(self.observation, self.weights.frame_stack, config.num_envs)
        self.builders = [ChunkBuilder(config.actor_id, i, self.epoch, config.chunk_size, self.observation)
                         for i in range(config.num_envs)]
        for i, (builder, slot) in enumerate(zip(self.builders, self.slots)):
            builder.begin(slot.obs)
            self.stacks.reset(i, slot.obs)
        self.experience = session.declare_publisher(
            self.keys.experience(config.actor_id, config.num_shards), **EXPERIENCE_QOS.publisher())
        self.compressor = FrameCompressor() if config.compress_frames else None
        self.resend = self.resender = None
        self.gradients = None if config.evaluate or not config.send_gradients else GradientSender(
            session, self.keys, config.actor_id)
        if not config.evaluate and config.resend_buffer_mb > 0 and self.gradients is None:
            self.resend = ResendBuffer(int(config.resend_buffer_mb * 2**20), config.resend_delay, MAX_RESEND_DELAY)
            self.resender = Resender(self, session)
        self.summaries = session.declare_publisher(self.keys.episodes(config.actor_id), **EPISODE_QOS.publisher())
        self.rounds = session.declare_publisher(self.keys.rounds(config.actor_id), **ROUND_QOS.publisher())
        self.stats = session.declare_publisher(self.keys.stats(config.role, config.actor_id), **STATS_QOS.publisher())
        self.episode_logger = make_episode_logger(config)
        self.live = LiveFrames(session, self.keys, config.actor_id)  # frames only while a viewer watches
        if not config.evaluate:  # evaluation rounds start their own recordings
            for i, slot in enumerate(self.slots):
                self.begin_record(i, slot)
        self._rate_steps, self._rate_frames, self._rate_time = 0, 0, time.monotonic()
        self._next_round = 0.0
        self._round_version = -1
        self._listen_deadline = time.monotonic() + LISTENER_GRACE  # the first summaries wait for l2r up

    def observe(self, observation) -> dict[str, np.ndarray]:
        return fields_of(self.observation, observation, self.config.env_id)

    # -- actions -------------------------------------------------------------------------

    @property
    def acting_randomly(self) -> bool:
        return self.random_phase or self.weights.policy is None

    def actions(self) -> tuple[np.ndarray, np.ndarray]:
        """Excitations for every env, and the log-probability of each under what chose it."""
        act_dim = self.worlds.action_space.shape[0]
        uniform = np.full(len(self.slots), uniform_log_prob(act_dim), np.float32)
        if self.acting_randomly:
            return self.rng.random((len(self.slots), act_dim), dtype=np.float32), uniform
        noise = None if self.noise is None else self.noise.next()
        explore = None if self.parameter_noise is None else functools.partial(self.parameter_noise.explore,
                                                                               self.weights.policy)
        actions, log_probs = act_with_log_prob(self.weights.policy, self.stacks.stacked(), noise, explore)
        bad = ~(np.isfinite(actions).all(axis=1) & np.isfinite(log_probs))
        if bad.any():  # a diverged policy must not crash the actor: step those envs randomly
            log.warning("policy v%d produced non-finite actions for %d env(s); using random ones",
                        self.weights.version, int(bad.sum()))
            actions[bad] = self.rng.random((int(bad.sum()), act_dim), dtype=np.float32)
            log_probs[bad] = uniform[bad]
        return actions, log_probs

    # -- one iteration ---------------------------------------------------------------------

    def step(self) -> None:
        acted_by = self.weights.version
        # A gradient is of one policy's rollout: an A3C actor swaps weights only between chunks.
        if (self.gradients is None or not any(self.builders)) and self.weights.poll():
            self.flush(force=True, version=acted_by)  # a chunk carries the one version that produced it
            if self.weights.frame_stack != self.stacks.depth:
                self.stacks = self.stacks.with_depth(self.weights.frame_stack)
            if self.first_version is None:
                self.first_version = self.weights.version
        if self.gradients is not None and self.weights.policy is None:
            time.sleep(0.05)  # an A3C actor learns nothing from random steps: it waits for the first weights
            return
        if self.random_phase and (self.steps >= self.config.random_steps or (self.first_version or 0) > UNTRAINED):
            # A first policy past the untrained one means the run was already training: no warm-up.
            self.random_phase = False
            log.info("warm-up over after %d random steps; acting with the policy", self.steps)
        actions, log_probs = self.actions()
        now = time.time()
        ended = []  # the worlds whose episodes ended in this step, each with its last step
        for i, (slot, action, (raw, reward, terminated, truncated, info)) in enumerate(
                zip(self.slots, actions, self.worlds.step(actions))):
            obs = self.observe(raw)
            if blew_up(reward, info, self.config.max_speed):
                self.blowups += 1
                if self.blowups == 1 or self.blowups % 100 == 0:
                    log.warning("simulation blow-up (%.1f m in one step); episode ended before it (%d so far)",
                                reward, self.blowups)
                obs, reward, terminated, truncated = slot.obs, 0.0, True, False
                info = {**info, "distance": slot.x}
            slot.x = float(info.get("distance", 0.0))
            slot.ret += float(reward)
            slot.length += int(info.get("inner_steps", 1))
            self.frames += int(info.get("inner_steps", 1))
            if slot.recorder is not None:
                slot.recorder.log_step(obs, action, reward, info)
            self.live.publish(i, slot.episode, slot.length, obs, reward, info)
            if terminated or truncated:
                self.end_episode(i, slot, info, terminated, truncated)
                ended.append((i, action, reward, terminated, truncated, obs, log_probs[i]))
            else:
                slot.obs = obs
                self.stacks.push(i, obs)
                if not self.config.evaluate:
                    self.builders[i].add(action, reward, terminated, truncated, obs, None, now, log_probs[i])
        # The next episodes, in one call: a vector env resets its finished worlds together.
        difficulty, options = episode_difficulty(self.config, self.course, self.steps)
        worlds = [last[0] for last in ended]
        starts = self.worlds.reset_worlds(worlds, [self.slots[i].seed for i in worlds], options)
        for (i, action, reward, terminated, truncated, obs, log_prob), (first, info) in zip(ended, starts):
            slot = self.slots[i]
            self.begin_episode(i, slot, difficulty, first, info)
            self.stacks.reset(i, slot.obs)
            if not self.config.evaluate:
                self.builders[i].add(action, reward, terminated, truncated, obs, slot.obs, now, log_prob)
        self.steps += len(self.slots)
        self.flush()

    def begin_record(self, i: int, slot: EnvSlot) -> None:
        if self.episode_logger is not None:
            slot.recorder = self.episode_logger.begin_episode({
                "env_id": self.config.env_id, "seed": slot.seed, "difficulty": slot.difficulty, "evaluation": False,
                "policy_version": -1 if self.acting_randomly else self.weights.version,
                "obstacles": self.worlds.obstacles(i)})

    def record_evaluation(self, env: gymnasium.Env, seed: int):
        return self.episode_logger.begin_episode({
            "env_id": self.config.env_id, "seed": seed, "difficulty": self.config.difficulty, "evaluation": True,
            "policy_version": self.weights.version, "obstacles": getattr(env.unwrapped, "obstacles", [])})

    def end_episode(self, i: int, slot: EnvSlot, info: dict, terminated: bool, truncated: bool) -> None:
        """Publish the summary of env i's episode, whose last step's info is `info`, and pick the
        next one's seed."""
        summary = EpisodeSummary(
            actor_id=self.config.actor_id, env_id=i, episode_return=slot.ret,
            distance=float(info.get("distance", 0.0)) - slot.start_x, length=slot.length,
            policy_version=-1 if self.acting_randomly else self.weights.version,
            difficulty=slot.difficulty, seed=slot.seed, evaluation=self.config.evaluate,
            time=time.time(), psnr_db=final_psnr(info))
        await_listener(self.summaries, self._listen_deadline)
        self.summaries.put(encode(summary))
        if self.course is not None:
            self.course.record(slot.difficulty, summary.distance)
        if slot.recorder is not None:
            slot.recorder.end({"return": summary.episode_return, "distance": summary.distance,
                               "length": summary.length, "terminated": terminated, "truncated": truncated,
                               **score_record(summary.psnr_db)})
        self.episodes += 1
        slot.episode += 1
        slot.seed = episode_seed(self.config, i, slot.episode)
        if self.noise is not None:
            self.noise.reset(i)
        if self.parameter_noise is not None:
            self.parameter_noise.reset(i)
        slot.ret, slot.length = 0.0, 0

    def begin_episode(self, i: int, slot: EnvSlot, difficulty: int, obs, info: dict) -> None:
        """Env i's next episode has begun at `obs` (its first observation) and `info`."""
        slot.difficulty = difficulty
        slot.obs = self.observe(obs)
        slot.start_x = slot.x = float(info.get("distance", 0.0))
        self.begin_record(i, slot)

    def flush(self, force: bool = False, version: int | None = None) -> None:
        """Send every chunk that is full, older than the delay, or any at all when forced.
        Chunks are stamped with ``version`` (default: the policy in use; 0 before any)."""
        deadline = time.time() - self.config.chunk_delay
        version = max(self.weights.version if version is None else version, 0)
        for builder in self.builders:
            if builder and (force or builder.full or builder.started_at < deadline):
                chunk = builder.take(self.seq, version)
                if self.gradients is not None:
                    self.gradients.send(chunk, None if self.acting_randomly else self.weights.in_use)
                    continue
                payload = encode(chunk, self.compressor)  # the resend buffer counts the bytes sent
                if self.resend is not None:
                    self.resend.add(self.seq, payload, time.monotonic())
                self.experience.put(payload)
                self.seq += 1
                self.chunks_sent += 1

    # -- evaluation rounds -------------------------------------------------------------------

    def ready_for_round(self) -> bool:
        """An evaluation round starts when the interval has passed and the policy is new."""
        version = self.weights.version
        if version < 0 or version == self._round_version or time.monotonic() < self._next_round:
            return False
        self._round_version = version
        self._next_round = time.monotonic() + self.config.eval_interval
        return True

    def run_round(self, stop: threading.Event) -> None:
        """`eval_episodes` deterministic episodes with one policy version, spread over the envs."""
        version, n, scores = self.weights.version, len(self.slots), []
        # Said before the first episode, so that l2r up keeps this version's weights to save if it scores best.
        await_listener(self.rounds, self._listen_deadline)
        self.rounds.put(encode(EvaluationRound(self.config.actor_id, version)))
        score = score_of(self.config.env_id)
        for start in range(0, self.config.eval_episodes, n):
            seeds = [self.config.seed + k for k in range(start, min(start + n, self.config.eval_episodes))]
            envs = self.worlds.envs[:len(seeds)]  # an evaluator's worlds are single envs (`uses_vector_env`)
            results = run_deterministic(self.weights.policy, envs, seeds, stop,
                                        self.record_evaluation if self.episode_logger is not None else None,
                                        self.config.max_speed, self.weights.frame_stack, self.config.env_id)
            for env_index, (seed, result) in enumerate(zip(seeds, results)):
                summary = EpisodeSummary(
                    actor_id=self.config.actor_id, env_id=env_index, episode_return=result.episode_return,
                    distance=result.distance, length=result.length, policy_version=version,
                    difficulty=self.config.difficulty, seed=seed, evaluation=True, time=time.time(),
                    psnr_db=result.psnr_db)
                await_listener(self.summaries, self._listen_deadline)
                self.summaries.put(encode(summary))
                self.episodes += 1
                scores.append(score.of(summary))
        if scores:
            log.info("evaluation of policy v%d: mean %s over %d episodes",
                     version, score.text(float(np.mean(scores))), len(scores))

    # -- stats -------------------------------------------------------------------------------

    def publish_stats(self) -> None:
        now = time.monotonic()
        elapsed = max(now - self._rate_time, 1e-9)
        rate, frame_rate = (self.steps - self._rate_steps) / elapsed, (self.frames - self._rate_frames) / elapsed
        self._rate_steps, self._rate_frames, self._rate_time = self.steps, self.frames, now
        values = {
            "env_steps": self.steps, "env_steps_per_s": rate, "episodes": self.episodes,
            "chunks_sent": self.chunks_sent, "policy_version": self.weights.version,
            "newest_version": self.weights.newest_seen, "staleness": self.weights.staleness,
            "weight_swaps": self.weights.swaps, "rejected_weights": self.weights.rejections.total,
            "random_phase": int(self.random_phase), "waiting_for_replay": int(self.waiting_for_replay),
            "num_envs": len(self.slots), "blowups": self.blowups, "held_s": self.held_s,
        }
        if self.gradients is not None:
            values |= self.gradients.counters()
        if self.camera:  # one frame rendered per env step; the papers count a frame per inner step
            values |= {"frames": self.frames, "frames_per_s": frame_rate}
        if self.resend is not None:
            values |= {"chunks_acked": self.resend.acked, "chunks_resent": self.resend.resent,
                       "unacked_chunks": len(self.resend), "unacked_bytes": self.resend.nbytes,
                       "resend_dropped": self.resend.dropped, "rejected_acks": self.resender.rejections.total}
        self.stats.put(encode(Stats(self.config.role, str(self.config.actor_id), time.time(), values)))

    def close(self) -> None:
        if not self.config.evaluate:
            self.flush(force=True)
        if self.resender is not None:
            self.await_last_acks()
            self.resender.close()
        if self.episode_logger is not None:
            self.episode_logger.close()
        self.weights.close()
        if self.gradients is not None:
            self.gradients.close()
        self.live.close()
        self.worlds.close()


    def held(self) -> bool:
        """Whether the shard's last acks ask this actor to wait: its queue table is full, the
        learner behind. An ack's hold lapses unless renewed, so a lost release costs little."""
        return self.resender is not None and time.monotonic() < self.resender.held_until

    def await_last_acks(self) -> None:
        """Wait (bounded) until the shard has acknowledged every chunk sent, so that closing the
        session loses nothing: an ack means the shard holds the chunk. Not when the shard has
        never acknowledged (an older one) or is gone: then nothing would come."""
        if not self.resender.heard_ack or not self.replay.alive or not len(self.resend):
            return
        start, unacked = time.monotonic(), len(self.resend)
        while len(self.resend) and time.monotonic() - start < self.config.final_ack_wait:
            time.sleep(0.05)
        if len(self.resend):
            log.warning("%d of the last %d chunks unacknowledged after %.0f s; stopping without them",
                        len(self.resend), unacked, self.config.final_ack_wait)
        else:
            log.info("the replay shard acknowledged the last %d chunks after %.1f s", unacked, time.monotonic() - start)


class Resender:
    """Applies the shard's acks to the actor's resend buffer and sends due chunks again, on a
    thread of its own: a put that blocks on a silent link never holds up the environments."""

    def __init__(self, actor: Actor, session: zenoh.Session):
        self.actor = actor
        self.rejections = Rejections(log)
        self.heard_ack = False  # whether the shard ever acknowledged a chunk of this actor
        self.held_until = 0.0  # monotonic time until which the shard's last ack asks to wait
        self._acks = session.declare_subscriber(actor.keys.replay_ack(actor.replay.shard), self._on_ack)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="resend", daemon=True)
        self._thread.start()

    def _on_ack(self, sample: zenoh.Sample) -> None:
        try:
            ack = decode(sample.payload, ReplayAck)
        except ProtocolError as e:
            self.rejections.add(e, str(sample.key_expr))
            return
        self.held_until = time.monotonic() + HOLD_FOR if ack.hold else 0.0
        mine = ack.of(self.actor.config.actor_id, self.actor.epoch)
        if mine is not None:
            self.heard_ack = True
            self.actor.resend.ack(*mine)

    def _run(self) -> None:
        while not self._stop.wait(0.25):
            if not self.actor.replay.alive:
                continue  # nobody to send to; the waits are not used up meanwhile
            for payload in self.actor.resend.due(time.monotonic()):
                if self._stop.is_set():
                    return
                self.actor.experience.put(payload)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
        self._acks.undeclare()


def final_psnr(info: dict) -> float | None:
    """A photo task's score from its last step's info: the PSNR to the goal (None on other tasks)."""
    return None if "psnr_db" not in info else float(info["psnr_db"])


def score_record(psnr: float | None) -> dict[str, float]:
    """What an episode log's result holds beside return and distance: a photo task's PSNR."""
    return {} if psnr is None else {"psnr_db": psnr}


class EpisodeResult(NamedTuple):
    """One deterministic episode, in the terms of EpisodeSummary (so a family's Score reads it)."""

    episode_return: float
    distance: float
    length: int
    psnr_db: float | None = None


def run_deterministic(policy, envs: list[gymnasium.Env], seeds: list[int], stop: threading.Event | None = None,
                      record=None, max_speed: float = ActorConfig.max_speed, frame_stack: int = 1,
                      env_id: str = "the environment") -> list[EpisodeResult]:
    """Run one deterministic episode per env (batched policy calls); its EpisodeResult each.

    The policy acts on stacks of the last ``frame_stack`` observations, as in training.
    ``record(env, seed)``, if given, is called after each reset and returns an episode
    recorder (see `episode_log`). Shared by the evaluation role and `l2r eval`."""
    spec = observation_spec(envs[0], env_id)
    frames = FrameStack(spec, frame_stack, len(envs))
    obs, start_x, recorders = [], [], []
    for i, (env, seed) in enumerate(zip(envs, seeds)):
        o, info = env.reset(seed=seed)
        obs.append(fields_of(spec, o, env_id))
        frames.reset(i, obs[i])
        start_x.append(float(info.get("distance", 0.0)))
        recorders.append(record(env, seed) if record else None)
    x = list(start_x)
    results: list = [None] * len(envs)
    returns = [0.0] * len(envs)
    lengths = [0] * len(envs)
    running = list(range(len(envs)))
    while running and not (stop is not None and stop.is_set()):
        actions = act(policy, frames.stacked(running), deterministic=True)
        still = []
        for i, action in zip(running, actions):
            raw, reward, terminated, truncated, info = envs[i].step(action)
            o = fields_of(spec, raw, env_id)
            if blew_up(reward, info, max_speed):  # ends the episode where it was, as in training
                o, reward, terminated, info = obs[i], 0.0, True, {**info, "distance": x[i]}
            x[i] = float(info.get("distance", 0.0))
            returns[i] += float(reward)
            lengths[i] += int(info.get("inner_steps", 1))
            obs[i] = o
            frames.push(i, o)
            if recorders[i] is not None:
                recorders[i].log_step(o, action, reward, info)
            if terminated or truncated:
                results[i] = EpisodeResult(returns[i], float(info.get("distance", 0.0)) - start_x[i], lengths[i],
                                           final_psnr(info))
                if recorders[i] is not None:
                    recorders[i].end({"return": returns[i], "distance": results[i].distance, "length": lengths[i],
                                      "terminated": terminated, "truncated": truncated,
                                      **score_record(results[i].psnr_db)})
            else:
                still.append(i)
        running = still
    return [r for r in results if r is not None]


def make_episode_logger(config: ActorConfig):
    """The MCAP episode logger the config asks for, or None."""
    if not config.episode_log:
        return None
    # Imported here: it loads the body model, which an actor without logs does not need.
    from l2r.actors.episode_log import EpisodeLogger, LogPolicy
    options = dict(config.episode_log)
    policy = LogPolicy(every=options.pop("every", 10), evaluation=True)
    return EpisodeLogger(run=config.run, actor_id=config.actor_id, policy=policy,
                         step_seconds=0.01 * config.action_repeat, with_body=family_of(config.env_id) == RUNNER,
                         with_psnr=family_of(config.env_id) == PHOTO,
                         **options)


def main(config: ActorConfig, zenoh_config: zenoh.Config, stop: threading.Event | None = None) -> int:
    """Run the actor until ``stop`` is set (or ``config.max_steps`` is reached)."""
    stop = stop or threading.Event()
    torch.set_num_threads(config.torch_threads)
    if config.device == "auto":
        config = dataclasses.replace(config, device="cuda" if torch.cuda.is_available() else "cpu")
    elif config.device == "cuda" and not torch.cuda.is_available():
        raise StartupFailure(f"--device cuda, but torch {torch.__version__} sees no CUDA device")
    with zenoh.open(zenoh_config) as session:
        keys = Keys(config.run)
        if config.actor_id is None:
            actor_id = ask_actor_id(session, keys, stop)
            if actor_id is None:  # stopped while waiting for replay shard 0
                return 0
            config = dataclasses.replace(config, actor_id=actor_id)
        token = session.liveliness().declare_token(keys.alive(config.role, config.actor_id))
        try:
            actor = Actor(config, session)
        except ObservationError as e:
            raise StartupFailure(str(e)) from None
        log.info("%s %d up: %d x %s%s (difficulty %d, action repeat %d%s), run %r", config.role,
                 config.actor_id, config.num_envs, config.env_id,
                 f" as one vector env on {config.device}" if isinstance(actor.worlds, VectorWorlds) else "",
                 config.difficulty, config.action_repeat, "".join(f"; {lever}" for lever in levers_on(config)),
                 config.run)
        next_stats = 0.0
        waited_since = None
        try:
            while not stop.is_set():
                if config.max_steps and actor.steps >= config.max_steps:
                    break
                if time.monotonic() >= next_stats:
                    actor.publish_stats()
                    next_stats = time.monotonic() + config.stats_interval
                if config.evaluate:
                    actor.weights.poll()
                    if actor.ready_for_round():
                        actor.run_round(stop)
                    else:
                        stop.wait(0.2)
                    continue
                if not actor.replay.alive:
                    # Without its replay shard the experience would be lost: wait for it.
                    if waited_since is None:
                        waited_since = time.monotonic()
                        actor.waiting_for_replay = True
                        log.info("no replay server alive for shard %d; waiting", actor.replay.shard)
                    actor.weights.poll()
                    stop.wait(0.2)
                    continue
                if waited_since is not None:
                    log.info("replay server alive again after %.1f s; going on", time.monotonic() - waited_since)
                    waited_since = None
                    actor.waiting_for_replay = False
                if actor.held():  # no weights swapped in here: step() does that, flushing first
                    started = time.monotonic()
                    stop.wait(0.02)
                    actor.held_s += time.monotonic() - started
                    continue
                actor.step()
        except ObservationError as e:  # every chunk from here on would be refused: stop, with the chunks so far
            log.error("%s; stopping", e)
            return 1
        finally:
            actor.close()
            actor.publish_stats()
            token.undeclare()
            log.info("%s %d stopped after %d steps, %d episodes, %d chunks", config.role,
                     config.actor_id, actor.steps, actor.episodes, actor.chunks_sent)
    return 0
