"""The learner process: batches in from replay, updates, weights, metrics and checkpoints out.

The algorithms live in `l2r.learner.sac`, `l2r.learner.td3`, `l2r.learner.ppo` (A2C and
REINFORCE are PPO's update at their settings: `l2r.learner.a2c`, `l2r.learner.reinforce`),
`l2r.learner.trpo` and `l2r.learner.acktr`; this module only hosts them. Steady state:

    replay client (sample queries in flight) -> batch, staged on the device -> the algorithm's step:
        SAC, TD3: update x update_repeat on a batch from the replay table (eager, compiled or one
                  CUDA graph: --compile), priorities back (prioritized only)
        on-policy (PPO, A2C, REINFORCE, TRPO, ACKTR; l2r.learner.algorithms.ON_POLICY): one
                  update (PPO's epochs x minibatches, a natural-gradient step) on a batch from the
                  queue table
    or, colocated (l2r.learner.colocated): worlds this process steps itself -> SAC, TD3: one step of
                  every world, a batch sampled on the device from their transitions; on-policy: a
                  rollout of every world -> the algorithm's step, as above
    or, for A3C (l2r.learner.a3c), no replay: the actors' gradients in arrival order -> one
                  optimizer step on each (too stale or ill-fitting ones refused, counted)
        -> weights (new version) published and kept for queries: SAC and TD3 every K updates,
           the on-policy algorithms after every batch (their data must come from the newest policy),
           A3C after every gradient, with its value network and settings for the actors
        -> every T seconds: checkpoint (rank 0); every few seconds: metrics

SIGTERM and SIGINT stop the loop; the checkpoint is written last.
"""

from __future__ import annotations

import logging
import math
import queue
import signal
import threading
import time
from collections import deque
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

import numpy as np
import torch
import zenoh

from l2r.durable import DISK_ERRORS, FailureLog
from l2r.learner import a3c, ppo, sac, td3
from l2r.learner.algorithms import ON_POLICY
from l2r.learner.checkpoint import (
    ALGORITHMS, AlgorithmConfig, Checkpoint, CheckpointError, TrainState, algorithm_of, checkpoint_path,
    load_checkpoint, save_checkpoint,
)
from l2r.learner.colocated import WorldsConfig, colocated_experience
from l2r.learner.distributed import any_rank, close_distributed, init_distributed, select_device
from l2r.learner.ppo import PPOConfig
from l2r.learner.sac import SACConfig
from l2r.learner.steps import GradientSteps, resolve_mode
from l2r.learner.td3 import TD3Config
from l2r.policy import check_spec, policy_state
from l2r.protocol import (
    STATS_QOS, VERSION_QOS, WEIGHTS_QOS, Gradient, Keys, LearnerVersion, ObservationSpec, ProtocolError, Rejections,
    ReplayClient, SampleBatch, Stats, Weights, decode, encode, reuse_large_buffers,
)
from l2r.protocol.observations import VECTOR_FIELD

log = logging.getLogger("l2r.learner")
# A checkpoint the disk refuses is one line per cause, and training goes on: the last one written stays whole.
CHECKPOINT_FAILURES = FailureLog(log, "checkpoint")


@dataclass
class LearnerConfig:
    """Run and infrastructure settings of one learner process (the algorithm's are in SACConfig, TD3Config or
    PPOConfig)."""

    run: str = "default"
    run_dir: Path | None = None
    """Where the checkpoint goes (<run_dir>/learner/checkpoint.pt); default runs/<run>."""
    resume: bool = False
    init_from: Path | None = None
    """A checkpoint (or run directory) to start from when there is none to resume: a training
    checkpoint's networks, optimizers and counters, or a policy checkpoint's policy alone."""
    device: str = "auto"
    threads: int = 0
    """torch CPU threads; 0 keeps torch's default."""
    compile: str = "auto"
    """How SAC's and TD3's update runs: off, graphs, inductor, inductor-graphs or auto (l2r.learner.steps)."""
    obs_dim: int = 41
    """Width of the float32 vector observation, unless `observation` says otherwise."""
    observation: ObservationSpec | None = None
    """Observations with image fields (TD3): their spec, sampled from replay in the frames form
    and stacked TD3Config.frame_stack deep; None: the float32 vector of obs_dim."""
    act_dim: int = 18
    prioritized: bool = False
    priority_beta: float = 0.4
    in_flight: int = 4
    publish_every: int = 50
    checkpoint_interval: float = 60.0
    keep_checkpoints: int = 3
    """Checkpoints kept: the newest and the ones before it (see l2r.learner.checkpoint)."""
    action_repeat: int | None = None
    """The actors' action repeat, stored in checkpoints for `l2r eval`; None: not known."""
    metrics_interval: float = 5.0
    max_updates: int = 0
    """Stop (and checkpoint) after this many updates in total; 0 = run until stopped."""
    seed: int | None = None
    colocated: WorldsConfig | None = None
    """Worlds this process steps itself, their transitions kept on its device (l2r.learner.colocated),
    instead of batches from replay."""
    world_size: int = 1
    rank: int = 0
    dist_url: str | None = None

    @property
    def checkpoint(self) -> Path:
        return checkpoint_path(self.run_dir or Path("runs") / self.run)


class Diverged(RuntimeError):
    """Training produced NaN or infinite weights."""


def _finite(state: TrainState) -> bool:
    # One read back for all tensors: on a GPU each read waits for the device.
    return bool(torch.stack([torch.isfinite(t).all() for t in state.parameters()]).all())


class WeightsOutlet:
    """Publishes versioned policy weights and answers queries for the latest ones; with `training`
    (A3C's settings, for its actors' gradients) the value network's weights and those settings too."""

    def __init__(self, session: zenoh.Session, keys: Keys, training: dict | None = None):
        self._training = training
        self._latest: bytes | None = None
        self._lock = threading.Lock()
        self._query_key = keys.weights_query
        self._weights = session.declare_publisher(keys.weights, **WEIGHTS_QOS.publisher())
        self._version = session.declare_publisher(keys.learner_version, **VERSION_QOS.publisher())
        self._queryable = session.declare_queryable(keys.weights_query, self._answer)

    def publish(self, state: TrainState) -> None:
        state.version += 1
        value = None if self._training is None else policy_state(state.value)
        payload = encode(Weights(state.version, policy_state(state.actor), dict(state.actor.spec), value,
                                 self._training))
        with self._lock:
            self._latest = payload
        self._weights.put(payload)
        self._version.put(encode(LearnerVersion(state.version, state.updates, time.time())))

    def _answer(self, query: zenoh.Query) -> None:
        with self._lock:
            payload = self._latest
        if payload is not None:
            query.reply(self._query_key, payload)  # a concrete key, whatever pattern was asked


class Meter:
    """Averages metrics over a reporting interval without reading tensors back every update. Each
    metric is averaged over the batches that gave it (TD3's actor loss comes with actor updates only)."""

    def __init__(self) -> None:
        self.reset(time.monotonic())

    def reset(self, now: float) -> None:
        self.sums: dict[str, torch.Tensor] = {}
        self.counts: dict[str, int] = {}
        self.updates = self.samples = 0
        self.lag_sum = self.waited = 0.0
        self.batches = 0
        self.since = now

    def add(self, metrics: dict[str, torch.Tensor], updates: int, samples: int, lag: float) -> None:
        for name, value in metrics.items():
            if value.dim() == 0:
                self.sums[name] = self.sums[name] + value if name in self.sums else value.clone()
                self.counts[name] = self.counts.get(name, 0) + 1
        self.updates += updates
        self.samples += samples
        self.lag_sum += lag
        self.batches += 1

    def report(self, now: float) -> dict[str, float]:
        elapsed = max(now - self.since, 1e-9)
        values = {name: float(total) / self.counts[name] for name, total in self.sums.items()}
        values |= {"updates_per_s": self.updates / elapsed, "samples_per_s": self.samples / elapsed,
                   "policy_lag": self.lag_sum / max(self.batches, 1), "wait_fraction": self.waited / elapsed}
        self.reset(now)
        return values


def main(config: LearnerConfig, algo: AlgorithmConfig, conf: zenoh.Config) -> int:
    """Run a learner until SIGTERM/SIGINT or `max_updates`; returns the exit status. A checkpoint
    it cannot resume from is a CheckpointError."""
    if config.threads > 0:
        torch.set_num_threads(config.threads)
    device = select_device(config.device, config.rank)
    # Data-parallel ranks run the update eagerly (their gradient all-reduce is not captured), and
    # the on-policy algorithms loop over their own steps.
    eager = config.world_size > 1 or algorithm_of(algo) in ON_POLICY
    config = replace(config, compile=resolve_mode("off" if eager else config.compile, device,
                                                  images=config.observation is not None))
    if config.observation is not None:
        reuse_large_buffers()  # before Zenoh's threads start: batches of frames are 20-30 MB each
    stop = threading.Event()

    def on_signal(signum: int, _frame) -> None:
        log.info("%s: finishing the current update, then checkpointing", signal.Signals(signum).name)
        stop.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
    init_distributed(config.world_size, config.rank, config.dist_url, device)
    try:
        state = _initial_state(config, algo, device)
        ALGORITHMS[algorithm_of(algo)][1].broadcast_state(state)
        bfloat16 = getattr(state, "bfloat16", False)  # PPO's state has no such option: it runs float32
        critics = getattr(algo, "critics", 2)  # SAC's ensemble, named where it is not the twin pair
        ensemble = "" if critics == 2 else f" with {critics} critics (the least of {algo.critics_in_min})"
        n_step = getattr(algo, "n_step", 1)  # SAC's and TD3's; the on-policy family's returns are their own
        returns = "" if n_step == 1 else f" on {n_step}-step returns"
        log.info("%s%s%s rank %d on %s (%s matmuls, %d threads, compile %s), version %d, %d updates so far",
                 algorithm_of(algo).upper(), ensemble, returns, config.rank, device,
                 "bfloat16" if bfloat16 else "float32", torch.get_num_threads(), config.compile, state.version,
                 state.updates)
        _serve(config, algo, state, conf, device, stop)
        return 0
    except Diverged as e:
        log.error("%s: stopping without a checkpoint; --resume continues from the last good one", e)
        return 1
    finally:
        close_distributed()
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _serve(config: LearnerConfig, algo: AlgorithmConfig, state: TrainState, conf: zenoh.Config,
           device: torch.device, stop: threading.Event) -> None:
    """The Zenoh side: liveliness, publishers, replay client and training; the checkpoint comes last."""
    keys = Keys(config.run)
    leader = config.rank == 0
    try:
        with zenoh.open(conf) as session:
            token = session.liveliness().declare_token(keys.alive("learner", config.rank))
            metrics_out = session.declare_publisher(keys.metrics(config.rank), **STATS_QOS.publisher())
            gradients = algorithm_of(algo) == "a3c"
            outlet = WeightsOutlet(session, keys, algo.to_dict() if gradients else None) if leader else None
            if gradients:  # no replay: the actors send gradients, taken from before the first weights go out
                with GradientInbox(session, keys) as inbox:
                    outlet.publish(state)
                    _learn_from_gradients(config, algo, state, inbox, outlet, metrics_out, stop)
            elif config.colocated is not None:
                _learn_colocated(config, algo, state, session, outlet, metrics_out, device, stop)
            else:
                _learn_from_replay(config, algo, state, session, outlet, metrics_out, device, stop)
            token.undeclare()
    finally:
        if leader:
            _checkpoint(config, algo, state)


def _learn_from_replay(config: LearnerConfig, algo: AlgorithmConfig, state: TrainState, session: zenoh.Session,
                       outlet: WeightsOutlet | None, metrics_out: zenoh.Publisher, device: torch.device,
                       stop: threading.Event) -> None:
    """The replay client, then training on its batches."""
    # The replay table's requests stay as before the queue.
    table = "queue" if algorithm_of(algo) in ON_POLICY else None
    # The vector's requests stay version 1, as before the frames form, unless it takes a history.
    frame_stack = getattr(algo, "frame_stack", 1)
    frame_stack = None if config.observation is None and frame_stack == 1 else frame_stack
    with ReplayClient(session, config.run, algo.batch_size, config.prioritized, config.in_flight,
                      table=table, n_step=getattr(algo, "n_step", 1), gamma=algo.gamma,
                      frame_stack=frame_stack) as replay:
        newest = replay.newest_version(stop)
        if newest > state.version:  # resumed without a checkpoint, or from an older one
            log.info("the run's replay has seen policy version %d: going on above it, not from %d",
                     newest, state.version)
            state.version = newest
        if outlet:
            outlet.publish(state)
        experience = ReplayExperience(replay, config, stop, STEPS[algorithm_of(algo)][0])
        experience.learner_version = state.version
        _train(config, algo, state, experience, outlet, metrics_out, device, stop)


def _learn_colocated(config: LearnerConfig, algo: AlgorithmConfig, state: TrainState, session: zenoh.Session,
                     outlet: WeightsOutlet, metrics_out: zenoh.Publisher, device: torch.device,
                     stop: threading.Event) -> None:
    """Training on transitions of worlds this process steps itself (l2r.learner.colocated)."""
    experience = colocated_experience(session, Keys(config.run), config.colocated, state.actor, algo.batch_size,
                                      device, on_policy=algorithm_of(algo) in ON_POLICY)
    try:
        outlet.publish(state)
        experience.learner_version = state.version
        _train(config, algo, state, experience, outlet, metrics_out, device, stop)
    finally:
        experience.close()


def _initial_state(config: LearnerConfig, algo: AlgorithmConfig, device: torch.device) -> TrainState:
    if config.seed is not None:
        torch.manual_seed(config.seed + config.rank)
    name = algorithm_of(algo)
    state = ALGORITHMS[name][1].init_state(algo, config.observation or config.obs_dim, config.act_dim, device)
    if config.resume and config.checkpoint.is_file():
        saved = load_checkpoint(config.checkpoint, map_location=device)
        _check_same_networks(saved, state, algo, name, "a new run directory")
        state.load_state_dict(saved.train_state)
        state.set_learning_rates(algo)  # the command line's, not the saved ones
        log.info("resumed from %s: version %d, %d updates", saved.path, state.version, state.updates)
        return state
    if config.resume:
        log.info("--resume: no checkpoint at %s yet, starting %s", config.checkpoint,
                 "fresh" if config.init_from is None else f"from {config.init_from}")
    if config.init_from is None:
        return state
    saved = load_checkpoint(config.init_from, map_location=device)
    if saved.config is None:  # a policy alone (best.pt): the critics, value and optimizers start fresh
        _check_same_networks(saved, state, algo, name, "another --init-from", policy_alone=True)
        for actor in (state.actor, getattr(state, "target_actor", None)):
            if actor is not None:
                actor.load_state_dict(saved.train_state["actor"])
        log.info("started from %s: its policy (version %d), the rest fresh", saved.path, saved.version)
        return state
    _check_same_networks(saved, state, algo, name, "another --init-from")
    state.load_state_dict(saved.train_state)
    state.set_learning_rates(algo)
    log.info("started from %s: its networks, optimizers and counters (version %d, %d updates)", saved.path,
             state.version, state.updates)
    return state


def _check_same_networks(saved: Checkpoint, state: TrainState, algo: AlgorithmConfig, name: str, instead: str,
                         policy_alone: bool = False) -> None:
    """CheckpointError, in one line ending with what to use `instead`, unless the saved networks are
    the ones these settings build (the policy's alone with `policy_alone`)."""
    if not policy_alone and (saved.algo != name or saved.config is None):
        raise CheckpointError(f"{saved.path} holds {'a policy alone' if saved.config is None else saved.algo.upper()}"
                              f", not a {name.upper()} training state: use --algo {saved.algo}, or {instead}")
    saved_observation = ObservationSpec.from_policy_spec(saved.policy_spec)
    saved_stack = saved.policy_spec.get("frame_stack", 1)
    if (saved_observation, saved_stack) != (state.actor.observation, state.actor.frame_stack):
        raise CheckpointError(f"{saved.path} was trained on observations {saved_observation} stacked {saved_stack}, "
                              f"this learner's are {state.actor.observation} stacked {state.actor.frame_stack}: use "
                              f"the same environment and --frame-stack, or {instead}")
    if check_spec(saved.policy_spec) != state.actor.spec or not policy_alone and (
            saved.config.hidden != algo.hidden or saved.config.layer_norm != algo.layer_norm
            or saved.config.activation != algo.activation):
        raise CheckpointError(f"{saved.path} holds a network of {saved.policy_spec}, the settings ask for "
                              f"{state.actor.spec}: use the same architecture flags, or {instead}")
    if policy_alone:
        return
    if getattr(saved.config, "critics", None) != getattr(algo, "critics", None):
        raise CheckpointError(f"{saved.path} holds {saved.config.critics} critics, the settings ask for {algo.critics}: "
                              f"use the same --critics, or {instead}")
    if getattr(saved.config, "optimizer", None) != getattr(algo, "optimizer", None):
        raise CheckpointError(f"{saved.path} holds the state of {saved.config.optimizer}, the settings ask for "
                              f"{algo.optimizer}: use the same --optimizer, or {instead}")


def _replay_batch(batch: SampleBatch, config: LearnerConfig, device: torch.device) -> sac.Batch:
    weights = batch.importance_weights(config.priority_beta) if batch.prioritized else None
    if batch.frames is not None:
        stacked = sac.batch_from_frames(batch.frames, batch.obs_frames, batch.next_obs_frames, batch.actions,
                                        batch.rewards, batch.terminated, weights, device, batch.discounts)
        if config.observation is None:  # the vector's history: its networks take the stacked vector itself
            stacked = replace(stacked, obs=stacked.obs[VECTOR_FIELD], next_obs=stacked.next_obs[VECTOR_FIELD])
        return stacked
    return sac.batch_from_numpy(batch.obs, batch.actions, batch.rewards, batch.next_obs, batch.terminated, weights,
                                device, batch.discounts)


def _replay_step(state: sac.TrainState | td3.TrainState, tensors: sac.Batch, batch: SampleBatch,
                 algo: SACConfig | TD3Config, experience: Experience, steps: GradientSteps) -> dict[str, torch.Tensor]:
    """SAC's and TD3's step: update_repeat updates on one batch from the replay table."""
    algorithm = ALGORITHMS[algorithm_of(algo)][1]
    metrics = steps(state, algorithm.prepare(state, tensors, algo))
    if batch.prioritized:
        experience.update_priorities(batch, metrics["priorities"].float().cpu().numpy())
    return metrics


def _td3_step(state: td3.TrainState, tensors: sac.Batch, batch: SampleBatch, algo: TD3Config,
              experience: Experience, steps: GradientSteps) -> dict[str, torch.Tensor]:
    """The replay step, then the exploration std the schedule gives at the new update count: set
    here, outside the update, so that no compiled or captured update holds it."""
    metrics = _replay_step(state, tensors, batch, algo, experience, steps)
    td3.follow_exploration_schedule(state, algo)
    return metrics


def _queue_batch(batch: SampleBatch, config: LearnerConfig, device: torch.device) -> ppo.Batch:
    return ppo.batch_from_sample(batch, device)


def _on_policy_step(state: ppo.TrainState, tensors: ppo.Batch, batch: SampleBatch, algo: PPOConfig,
                    experience: Experience, steps: None) -> dict[str, torch.Tensor]:
    """An on-policy algorithm's update (its module's `update`) on one batch from the queue table."""
    return ALGORITHMS[algorithm_of(algo)][1].update(state, tensors, algo)


# Per algorithm: its batch as tensors on the device (staged while the update before it runs), its
# training on one batch, the update its GradientSteps run (None: it loops over its own steps), and
# whether weights go out after every batch (else every --publish-every updates).
STEPS = {"sac": (_replay_batch, _replay_step, sac.update, False),
         "td3": (_replay_batch, _td3_step, td3.update, False),
         **{name: (_queue_batch, _on_policy_step, None, True) for name in ON_POLICY}}


class Experience(Protocol):
    """Where the learner's batches come from: the replay shards (`ReplayExperience`), or worlds the
    learner steps itself (`l2r.learner.colocated`)."""

    learner_version: int
    """The newest version published, which the batches' policy lag is measured against."""

    def next_batch(self, timeout: float):
        """The next batch, or None after `timeout` seconds (short, so stop requests are seen)."""

    def to_device(self, batch, device: torch.device):
        """The batch as the algorithm's tensors on `device`."""

    def update_priorities(self, batch, priorities: np.ndarray) -> None: ...

    def waiting(self) -> str:
        """What the learner is waiting for, while no batch comes."""


class ReplayExperience:
    """Batches from the replay shards, checked (`_next_batch`), converted by `to_device` (the algorithm's)."""

    def __init__(self, replay: ReplayClient, config: LearnerConfig, stop: threading.Event, to_device):
        self.replay, self._config, self._stop, self._to_device = replay, config, stop, to_device

    @property
    def learner_version(self) -> int:
        return self.replay.learner_version

    @learner_version.setter
    def learner_version(self, version: int) -> None:
        self.replay.learner_version = version

    def next_batch(self, timeout: float) -> SampleBatch | None:
        return _next_batch(self.replay, self._config, self._stop, timeout)

    def to_device(self, batch: SampleBatch, device: torch.device):
        return self._to_device(batch, self._config, device)

    def update_priorities(self, batch: SampleBatch, priorities: np.ndarray) -> None:
        self.replay.update_priorities(batch, priorities)

    def waiting(self) -> str:
        return f"waiting for replay (shards alive: {self.replay.shards}, not-ready replies: {self.replay.waits})"


class Staging:
    """Batches from the experience, each converted and copied to the training device while the
    update before it runs. On CUDA an update runs on the device after the host has queued it, so
    the host takes the next batch meanwhile (pinned memory, a copy that does not wait for the
    device; colocated worlds take their step); on CPU the update has run by then, and the
    conversion is all that comes ahead.

    Waiting is counted only while the device has nothing to do: with no batch ready, the update
    in flight is finished first, then the wait for a batch is timed. At most two updates are
    queued on the device, so the host never runs far ahead of it.
    """

    def __init__(self, experience: Experience, device: torch.device, meter: Meter):
        self._experience, self._device, self._meter = experience, device, meter
        self._staged: tuple[SampleBatch, object] | None = None
        self._in_flight: deque[torch.cuda.Event] = deque()

    def take(self) -> tuple[SampleBatch, object] | None:
        """The next batch and its tensors: the staged one, else one waited for (None after 0.5 s)."""
        if self._staged is None:
            self._finish(0)
            asked = time.monotonic()
            batch = self._experience.next_batch(timeout=0.5)
            self._meter.waited += time.monotonic() - asked
            self._stage(batch)
        self._finish(1)
        staged, self._staged = self._staged, None
        return staged

    def ahead(self) -> None:
        """After an update is queued: stage the next batch if one is ready."""
        if self._device.type == "cuda":
            self._in_flight.append(torch.cuda.Event())
            self._in_flight[-1].record()
        self._stage(self._experience.next_batch(timeout=0.0))

    def _stage(self, batch: SampleBatch | None) -> None:
        if batch is not None:
            self._staged = batch, self._experience.to_device(batch, self._device)

    def _finish(self, keep: int) -> None:
        """Wait until at most `keep` updates are still running on the device."""
        while len(self._in_flight) > keep:
            self._in_flight.popleft().synchronize()


def _train(config: LearnerConfig, algo: AlgorithmConfig, state: TrainState, experience: Experience,
           outlet: WeightsOutlet | None, metrics_out: zenoh.Publisher, device: torch.device,
           stop: threading.Event) -> None:
    _, step, update, publish_each_batch = STEPS[algorithm_of(algo)]
    steps = update and GradientSteps(update, algo, config.compile, device, algo.update_repeat,
                                     policy_delay=getattr(algo, "policy_delay", None),
                                     actor_after=getattr(algo, "critic_warmup", 0))
    meter = Meter()
    staging = Staging(experience, device, meter)
    last_publish, last_checkpoint, waiting_since = state.updates, time.monotonic(), None
    while True:
        staged = staging.take()
        if staged is None and not stop.is_set():
            now = time.monotonic()
            waiting_since = waiting_since or now
            if now - waiting_since > 10.0:
                log.info("%s", experience.waiting())
                waiting_since = now
            if now - meter.since >= config.metrics_interval:  # rates of zero are news too
                _report(config, algo, state, meter.report(now), metrics_out)
            continue
        waiting_since = None
        done = config.max_updates and state.updates >= config.max_updates
        if any_rank(stop.is_set() or bool(done), device):
            return
        batch, tensors = staged
        updates_before = state.updates
        metrics = step(state, tensors, batch, algo, experience, steps)
        lag = float(state.version - np.mean(batch.policy_versions))
        meter.add(metrics, state.updates - updates_before, len(batch.actions), lag)

        state.extra["samples"] = state.extra.get("samples", 0) + len(batch.actions)

        now = time.monotonic()
        if publish_each_batch or state.updates - last_publish >= config.publish_every:
            # Every rank checks (their weights are identical), so all stop together.
            if not _finite(state):
                raise Diverged(f"weights hold NaN or infinity after {state.updates} updates")
            if outlet:
                outlet.publish(state)
                experience.learner_version = state.version
            last_publish = state.updates
        # After a publication, so that PPO's next batch is asked for once the actors have its weights.
        staging.ahead()
        if now - meter.since >= config.metrics_interval:
            _report(config, algo, state, meter.report(now), metrics_out)
        if outlet and now - last_checkpoint >= config.checkpoint_interval:
            _checkpoint(config, algo, state)
            last_checkpoint = now


class GradientInbox:
    """A3C's gradients as they arrive from the actors, decoded on Zenoh's thread; malformed ones
    (wrong types, NaN, another protocol version) are counted in `rejections` and dropped there. A
    queue without bound: a step is far shorter than an actor's rollout, and stale gradients are
    refused when taken."""

    def __init__(self, session: zenoh.Session, keys: Keys):
        self.rejections = Rejections(log)
        self._queue: queue.SimpleQueue[Gradient] = queue.SimpleQueue()
        self._subscriber = session.declare_subscriber(keys.all_gradients, self._on_gradient)

    def _on_gradient(self, sample: zenoh.Sample) -> None:
        try:
            self._queue.put(decode(sample.payload, Gradient))
        except ProtocolError as e:
            self.rejections.add(e, str(sample.key_expr))

    def take(self, timeout: float) -> Gradient | None:
        try:
            return self._queue.get(timeout=timeout)
        except queue.Empty:
            return None

    def __enter__(self) -> GradientInbox:
        return self

    def __exit__(self, *exc) -> None:
        self._subscriber.undeclare()


def _learn_from_gradients(config: LearnerConfig, algo: a3c.A3CConfig, state: ppo.TrainState, inbox: GradientInbox,
                          outlet: WeightsOutlet, metrics_out: zenoh.Publisher, stop: threading.Event) -> None:
    """A3C: each gradient applied as it comes (`a3c.apply`), weights published after each."""
    meter = Meter()
    last_checkpoint = time.monotonic()
    while not stop.is_set() and not (config.max_updates and state.updates >= config.max_updates):
        asked = time.monotonic()
        message = inbox.take(timeout=0.5)
        meter.waited += time.monotonic() - asked
        now = time.monotonic()
        if now - meter.since >= config.metrics_interval:
            _report(config, algo, state, meter.report(now) | inbox.rejections.counters(), metrics_out)
        if message is None:
            continue
        try:
            metrics = a3c.apply(state, message, algo)
        except ProtocolError as e:
            inbox.rejections.add(e, f"actor {message.actor_id}")
            if e.reason == "ahead":  # resumed from before the actors' weights, which take only newer versions
                log.info("actors hold version %d: going on above it, not from %d", message.policy_version,
                         state.version)
                state.version = message.policy_version
                outlet.publish(state)
            continue
        meter.add(metrics, 1, message.env_steps, float(metrics["staleness"]))
        state.extra["samples"] = state.extra.get("samples", 0) + message.env_steps
        if not _finite(state):
            raise Diverged(f"weights hold NaN or infinity after {state.updates} updates")
        outlet.publish(state)
        if now - last_checkpoint >= config.checkpoint_interval:
            _checkpoint(config, algo, state)
            last_checkpoint = now


def _next_batch(replay: ReplayClient, config: LearnerConfig, stop: threading.Event,
                timeout: float) -> SampleBatch | None:
    """The next well-shaped batch, or None after `timeout` seconds (short, so stop requests are seen)."""
    if stop.is_set():
        return None
    try:
        batch = replay.sample(timeout=timeout)
    except queue.Empty:
        return None
    try:
        _check_observations(batch, config, replay.frame_stack)
    except ProtocolError as e:
        replay.rejections.add(e, f"shard {batch.shard}")
        return None
    if batch.actions.shape[1] != config.act_dim:
        replay.rejections.add(ProtocolError(f"batch of actions {batch.actions.shape}, this learner trains on "
                                            f"{config.act_dim}", "wrong_width"), f"shard {batch.shard}")
        return None
    if replay.table == "queue" and batch.log_probs is None:
        replay.rejections.add(ProtocolError("a replay-table batch in answer to a queue request: is the shard an "
                                            "l2r-replay from before the queue table?", "not_from_queue"),
                              f"shard {batch.shard}")
        return None
    return batch


def _check_observations(batch: SampleBatch, config: LearnerConfig, frame_stack: int | None) -> None:
    """ProtocolError unless the batch's observations are what this learner trains on: the vector of
    its width, or frames of its observation spec (the vector's, for a history) stacked `frame_stack` deep."""
    if config.observation is None and frame_stack is None:
        if batch.obs is None or batch.obs.shape[1] != config.obs_dim:
            raise ProtocolError(f"batch of obs {None if batch.obs is None else batch.obs.shape}, this learner trains "
                                f"on {config.obs_dim}", "wrong_width")
        return
    observation = config.observation or ObservationSpec.vector(config.obs_dim)
    observation.check(batch.frames, "sample_batch.frames")  # the replay client asked for frames
    if batch.obs_frames.shape[1] != frame_stack:
        raise ProtocolError(f"sample_batch: stacks of {batch.obs_frames.shape[1]} frames, this learner asked for "
                            f"{frame_stack}", "wrong_stack")


# What the log line shows of each algorithm's metrics: (label, metric).
PPO_LOGGED = (("policy", "policy_loss"), ("value", "value_loss"), ("entropy", "entropy"), ("kl", "approx_kl"),
              ("clipped", "clip_fraction"))
LOGGED = {
    "sac": (("critic", "critic_loss"), ("actor", "actor_loss"), ("alpha", "alpha"), ("q", "q_mean"),
            ("entropy", "entropy")),
    "td3": (("critic", "critic_loss"), ("actor", "actor_loss"), ("q", "q_mean"), ("std", "exploration_std")),
    "ppo": PPO_LOGGED, "a2c": PPO_LOGGED, "reinforce": PPO_LOGGED,
    "a3c": (("gradient norm", "gradient_norm"), ("staleness", "staleness"), ("rejected", "rejected")),
    "trpo": (("surrogate", "surrogate"), ("value", "value_loss"), ("entropy", "entropy"), ("kl", "kl"),
             ("step", "step_fraction")),
    "acktr": (("policy", "policy_loss"), ("value", "value_loss"), ("entropy", "entropy"),
              ("step size", "step_size"), ("kl", "kl"), ("lr", "lr")),
}


def _report(config: LearnerConfig, algo: AlgorithmConfig, state: TrainState, values: dict[str, float],
            out: zenoh.Publisher) -> None:
    values |= {"updates": state.updates, "version": state.version, "samples": state.extra.get("samples", 0)}
    losses = ", ".join(f"{label} {values.get(name, math.nan):.4g}" for label, name in LOGGED[algorithm_of(algo)])
    log.info("updates %d (%.1f/s), samples %.0f/s, waiting %.0f%%, version %d, lag %.1f, %s", state.updates,
             values["updates_per_s"], values["samples_per_s"], 100 * values["wait_fraction"], state.version,
             values["policy_lag"], losses)
    out.put(encode(Stats("learner", str(config.rank), time.time(), values)))


def _checkpoint(config: LearnerConfig, algo: AlgorithmConfig, state: TrainState) -> None:
    """Save, unless training has diverged: a NaN state never replaces a good checkpoint."""
    if not _finite(state):
        log.error("training state holds NaN or infinity: checkpoint NOT written, %s keeps the last good one",
                  config.checkpoint)
        return
    started = time.monotonic()
    try:
        path = save_checkpoint(config.checkpoint, state, algo, 0 if config.observation else config.obs_dim,
                               config.act_dim, config.action_repeat, config.keep_checkpoints)
    except OSError as e:
        if e.errno not in DISK_ERRORS:
            raise
        CHECKPOINT_FAILURES.failed(e, config.checkpoint, f"checkpoint of {state.updates} updates NOT written; "
                                   f"{config.checkpoint} stays the last one written")
        return
    CHECKPOINT_FAILURES.succeeded()
    log.info("checkpoint %s (version %d, %d updates) in %.2f s", path, state.version, state.updates,
             time.monotonic() - started)
