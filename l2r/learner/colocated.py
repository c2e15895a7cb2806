"""Colocated experience: the learner steps its own worlds, and their transitions stay on its device.

The actors' path sends each transition over Zenoh to the replay shards and takes batches back:
right for envs stepped on CPUs anywhere, costly for thousands of worlds stepped on the learner's
own GPU (`l2r/RunWarp-v0`), where PPO and off-policy training in the manner of FastTD3 want many
worlds and big batches. Here the learner's process steps a vector env with its newest policy
(`ColocatedWorlds`) and keeps the transitions on the training device; weights, metrics and
episode summaries leave over Zenoh as before, so evaluators, `l2r up`'s metrics and its choice of
`best.pt` work unchanged. The worlds report as an actor (`actor_id`: its stats and episodes).

- SAC and TD3 (`ColocatedReplay`): every batch comes after one step of every world (the
  learner's `update_repeat` sets the updates per step), sampled from a ring of transitions on
  the device; the first `random_steps` env steps take uniform random excitations, as the actors
  warm up, and the first batch waits for `min_replay` transitions. The ring is not
  checkpointed: a resumed learner fills it again.
- The on-policy algorithms (`ColocatedRollouts`): every batch is a rollout of the newest policy,
  batch_size / worlds steps of every world, laid world after world as the queue table lays its
  pieces of trajectories.

Stepping and updating take turns: a step's policy call needs the weights the update before it
writes, so on a GPU it waits for that update. What crosses between host and device per step is
the observations the env computed on the host and the excitations.

    experience = colocated_experience(session, keys, WorldsConfig("l2r/RunWarp-v0", 4096), state.actor, ...)
    batch = experience.next_batch(timeout=0.5)   # steps the worlds, then a batch of their transitions
"""

from __future__ import annotations

import functools
import logging
import time
from dataclasses import dataclass

import gymnasium
import numpy as np
import torch
import zenoh
from gymnasium.vector import AutoresetMode

from l2r.actors.actor import make_task, make_vector_task, registers_vector_env
from l2r.families import RUNNER, family_of
from l2r.learner import ppo
from l2r.learner.sac import Batch
from l2r.policy import PolicyNetwork, to_tanh_space
from l2r.protocol import EPISODE_QOS, LISTENER_GRACE, STATS_QOS, EpisodeSummary, Keys, Stats, await_listener, encode
from l2r.sim.env import STEP_SECONDS
from l2r.sim.randomize import Randomization

log = logging.getLogger("l2r.learner.colocated")
STATS_INTERVAL = 2.0  # seconds between the worlds' stats, as an actor's


@dataclass(frozen=True)
class WorldsConfig:
    """The worlds a colocated learner steps (`l2r-learner --colocated-env ...`)."""

    env_id: str
    worlds: int = 1024
    capacity: int = 1_000_000
    """Transitions the ring on the device holds; the oldest go first."""
    random_steps: int = 10_000
    """Env steps (all worlds together) of uniform random excitations before the policy acts
    (SAC, TD3: an on-policy algorithm learns from its own policy's actions alone)."""
    min_replay: int = 10_000
    """Transitions in the ring before the first batch (and at least random_steps and a batch)."""
    action_repeat: int = 1
    difficulty: int = 0
    randomize: str = ""
    """The runner's per-episode body randomisation (`l2r.sim.randomize`, the actors' --randomize)."""
    seed: int = 0
    max_speed: float = 20.0
    """The runner's pelvis speed (m/s) above which a step is a simulation blow-up, as the actors'
    --max-speed (0: off; other tasks have none)."""
    actor_id: int = 0
    """The actor id its stats and episode summaries go out under (no actor of the run may share it)."""


def make_vector_env(config: WorldsConfig, device: torch.device) -> gymnasium.vector.VectorEnv:
    """The worlds, each resetting within the step that ends its episode: the env id's own vector
    env (`l2r/RunWarp-v0` on the training device: Warp's "cuda" or "cpu"), else gymnasium's
    SyncVectorEnv of the actors' single envs (`make_task`: actions rescaled to the policy's [0, 1]).
    ValueError for an observation other than one vector."""
    randomize = Randomization.parse(config.randomize) if config.randomize else None
    if registers_vector_env(config.env_id):
        env = make_vector_task(config.env_id, config.worlds, config.difficulty, randomize,
                               "cuda" if device.type == "cuda" else "cpu")
    else:
        env = gymnasium.vector.SyncVectorEnv(
            [functools.partial(make_task, config.env_id, config.difficulty, config.seed + w, randomize)
             for w in range(config.worlds)], autoreset_mode=AutoresetMode.SAME_STEP)
    space = env.single_observation_space
    if env.metadata.get("autoreset_mode") != AutoresetMode.SAME_STEP:
        env.close()
        raise ValueError(f"{config.env_id}: its vector env does not reset a world in the step that ends it")
    if not (isinstance(space, gymnasium.spaces.Box) and len(space.shape) == 1):
        env.close()
        raise ValueError(f"{config.env_id}: colocated worlds take a vector observation, this env's is {space}")
    return env


class DeviceReplay:
    """Transitions in a ring of tensors on one device, sampled uniformly; actions are kept in the
    policy's (-1, 1) space, as batches carry them. The policy version of each row stays on the
    host, for the policy lag the learner reports."""

    def __init__(self, capacity: int, obs_dim: int, act_dim: int, device: torch.device):
        self.capacity, self.device = capacity, device
        self.obs = torch.zeros((capacity, obs_dim), device=device)
        self.next_obs = torch.zeros((capacity, obs_dim), device=device)
        self.action = torch.zeros((capacity, act_dim), device=device)
        self.reward = torch.zeros(capacity, device=device)
        self.terminated = torch.zeros(capacity, device=device)
        self.versions = np.zeros(capacity, np.int64)
        self.size = self.cursor = 0

    def __len__(self) -> int:
        return self.size

    def add(self, obs: torch.Tensor, action: torch.Tensor, reward: torch.Tensor, next_obs: torch.Tensor,
            terminated: torch.Tensor, version: int) -> None:
        """Rows of one step of every world; with more rows than the ring holds, the newest."""
        n = min(len(obs), self.capacity)
        rows = torch.arange(self.cursor, self.cursor + n, device=self.device) % self.capacity
        for field, values in ((self.obs, obs), (self.next_obs, next_obs), (self.action, action),
                              (self.reward, reward), (self.terminated, terminated)):
            field[rows] = values[len(values) - n:]
        self.versions[(self.cursor + np.arange(n)) % self.capacity] = version
        self.cursor = (self.cursor + n) % self.capacity
        self.size = min(self.size + n, self.capacity)

    def sample(self, batch_size: int, rng: np.random.Generator) -> tuple[Batch, np.ndarray]:
        """A uniform batch (with replacement) and each row's policy version. The rows are drawn on
        the host and sent as one small copy: the device never waits for the host's draws."""
        rows = rng.integers(0, self.size, batch_size)
        index = torch.from_numpy(rows).to(self.device, non_blocking=True)
        batch = Batch(self.obs[index], self.action[index], self.reward[index], self.next_obs[index],
                      self.terminated[index])
        return batch, self.versions[rows]


@dataclass
class DeviceSample:
    """A batch on the device, with what the learner's loop reads of a replay batch."""

    tensors: Batch | ppo.Batch
    policy_versions: np.ndarray
    prioritized: bool = False

    @property
    def actions(self) -> torch.Tensor:
        return self.tensors.action


@dataclass
class WorldsStep:
    """One step of every world, as tensors on the device (rows: worlds)."""

    obs: torch.Tensor
    action: torch.Tensor
    """In the policy's (-1, 1) space."""
    log_prob: torch.Tensor
    """Of the action under the policy that took it (the warm-up's: meaningless)."""
    reward: torch.Tensor
    next_obs: torch.Tensor
    """The observation after the step; an ended episode's last."""
    terminated: torch.Tensor
    ended: torch.Tensor
    """1.0 where the world's episode ended, terminated or truncated."""


class ColocatedWorlds:
    """A vector env's worlds stepped with the learner's policy; their episode summaries and stats
    go out as an actor's."""

    def __init__(self, session: zenoh.Session, keys: Keys, config: WorldsConfig, policy: PolicyNetwork,
                 device: torch.device):
        self.config, self.policy, self.device = config, policy, device
        self.env = make_vector_env(config, device)
        self.obs_dim, self.act_dim = self.env.single_observation_space.shape[0], self.env.single_action_space.shape[0]
        if (self.obs_dim, self.act_dim) != (policy.spec["obs_dim"], policy.spec["act_dim"]):
            self.env.close()
            raise ValueError(f"{config.env_id} has {self.obs_dim} observations and {self.act_dim} actions, the "
                             f"learner's networks {policy.spec['obs_dim']} and {policy.spec['act_dim']}")
        n = config.worlds
        self.max_speed = config.max_speed if family_of(config.env_id) == RUNNER else 0.0
        obs, info = self.env.reset(seed=config.seed)
        self.host_obs, self.obs = obs, self._tensor(obs)
        self.returns, self.lengths = np.zeros(n), np.zeros(n, np.int64)
        self.start_x = self._distances(info)
        self.x = self.start_x.copy()
        self.steps = self.episodes = self.blowups = 0
        self.stats_extra: dict[str, float] = {}
        self._rate_steps, self._rate_time, self._next_stats = 0, time.monotonic(), 0.0
        self._summaries = session.declare_publisher(keys.episodes(config.actor_id), **EPISODE_QOS.publisher())
        self._listen_deadline = time.monotonic() + LISTENER_GRACE  # the first summaries wait for l2r up
        self._stats = session.declare_publisher(keys.stats("actor", config.actor_id), **STATS_QOS.publisher())
        self._token = session.liveliness().declare_token(keys.alive("actor", config.actor_id))

    def step(self, version: int, explore: bool = True) -> WorldsStep:
        """Every world one action (repeated `action_repeat` times): the policy's exploring one, or
        with `explore` False a uniform random one."""
        n = self.config.worlds
        with torch.no_grad():
            if explore:
                excitation, log_prob = self.policy.explore(self.obs)
            else:
                excitation = torch.rand((n, self.act_dim), device=self.device)
                log_prob = torch.zeros(n, device=self.device)
        actions = excitation.cpu().numpy()
        reward, terminated, ended = np.zeros(n), np.zeros(n, bool), np.zeros(n, bool)
        inner_steps, next_obs, x_before = np.zeros(n, np.int64), None, self.x.copy()
        for _ in range(self.config.action_repeat):  # a world that ends within the repeats takes no more reward
            obs, step_reward, step_terminated, step_truncated, info = self.env.step(actions)
            running = ~ended
            reward[running] += step_reward[running]
            inner_steps[running] += 1
            self.x[running] = self._distances(info)[running]
            done = running & (step_terminated | step_truncated)
            terminated |= done & step_terminated
            if done.any():
                last = info["final_obs"][done]  # a SyncVectorEnv's: an object array of each world's
                next_obs = obs.copy() if next_obs is None else next_obs
                next_obs[done] = np.stack(last) if last.dtype == object else last
                self.x[done] = self._distances(info["final_info"])[done]
            ended |= done
        next_obs = obs if next_obs is None else next_obs
        blown = self._blown_up(reward, next_obs, inner_steps)
        if blown.any():  # as an actor stores one: a terminal step without reward, from where it was
            next_obs, reward = next_obs.copy(), reward.copy()
            next_obs[blown], reward[blown], terminated[blown], ended[blown] = self.host_obs[blown], 0.0, True, True
            self.x[blown] = x_before[blown]
        self.lengths += 1
        self.returns += reward
        step = WorldsStep(self.obs, to_tanh_space(excitation), log_prob, self._tensor(reward), self._tensor(next_obs),
                          self._tensor(terminated), self._tensor(ended))
        self.host_obs, self.obs = obs, self._tensor(obs)
        self.steps += n
        if ended.any():
            self._episodes_ended(np.flatnonzero(ended), self._distances(info), version)
        if time.monotonic() >= self._next_stats:
            self.publish_stats(version)
        return step

    def publish_stats(self, version: int) -> None:
        now = time.monotonic()
        rate = (self.steps - self._rate_steps) / max(now - self._rate_time, 1e-9)
        self._rate_steps, self._rate_time, self._next_stats = self.steps, now, now + STATS_INTERVAL
        values = {"env_steps": self.steps, "env_steps_per_s": rate, "episodes": self.episodes,
                  "policy_version": version, "newest_version": version, "num_envs": self.config.worlds,
                  "blowups": self.blowups,
                  **self.stats_extra}
        self._stats.put(encode(Stats("actor", str(self.config.actor_id), time.time(), values)))

    def close(self, version: int) -> None:
        self.publish_stats(version)
        self._token.undeclare()
        self.env.close()

    def _blown_up(self, reward: np.ndarray, next_obs: np.ndarray, inner_steps: np.ndarray) -> np.ndarray:
        """The worlds whose step blew up: an observation not finite, or (the runner) the pelvis
        faster than `max_speed` (the actors' check); counted, and logged now and then."""
        blown = ~np.isfinite(next_obs).all(axis=1)
        if self.max_speed:
            blown |= np.abs(reward) > self.max_speed * STEP_SECONDS * inner_steps
        for _ in range(int(blown.sum())):
            self.blowups += 1
            if self.blowups == 1 or self.blowups % 100 == 0:
                log.warning("simulation blow-up; the episode ended before it (%d so far)", self.blowups)
        return blown

    def _episodes_ended(self, worlds: np.ndarray, new_start: np.ndarray, version: int) -> None:
        """Summaries of the episodes that ended, each world's distance the x it had reached; the
        next episodes start from `new_start` (a blown-up world's env goes on from where it is)."""
        now = time.time()
        await_listener(self._summaries, self._listen_deadline)
        for w in worlds.tolist():
            self._summaries.put(encode(EpisodeSummary(
                actor_id=self.config.actor_id, env_id=w, episode_return=float(self.returns[w]),
                distance=float(self.x[w] - self.start_x[w]), length=int(self.lengths[w]),
                policy_version=version, difficulty=self.config.difficulty, seed=self.config.seed + w, time=now)))
        self.episodes += len(worlds)
        self.returns[worlds], self.lengths[worlds] = 0.0, 0
        self.start_x[worlds] = self.x[worlds] = new_start[worlds]

    def _tensor(self, values: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(values, dtype=torch.float32, device=self.device)

    def _distances(self, info: dict) -> np.ndarray:
        """Each world's x (the runner's `info["distance"]`; 0 for a task without one)."""
        distance = info.get("distance")
        return np.zeros(self.config.worlds) if distance is None else np.asarray(distance, np.float64).copy()


class WorldsExperience:
    """What both kinds of experience from the worlds share: their batches are on the device
    already, sampled uniformly or in order (no priorities), and closing closes the worlds."""

    def __init__(self, worlds: ColocatedWorlds):
        self.worlds, self.learner_version = worlds, 0

    @staticmethod
    def to_device(batch: DeviceSample, device: torch.device) -> Batch | ppo.Batch:
        return batch.tensors

    def update_priorities(self, batch: DeviceSample, priorities: np.ndarray) -> None:
        raise ValueError("colocated worlds take no priorities")

    def close(self) -> None:
        self.worlds.close(self.learner_version)


class ColocatedReplay(WorldsExperience):
    """SAC's and TD3's experience from the worlds: one step of every world, then a batch sampled
    from the ring on the device (see the module docstring)."""

    def __init__(self, worlds: ColocatedWorlds, batch_size: int):
        super().__init__(worlds)
        config = worlds.config
        self.batch_size = batch_size
        self.replay = DeviceReplay(config.capacity, worlds.obs_dim, worlds.act_dim, worlds.device)
        self._first_batch = min(max(batch_size, config.min_replay, config.random_steps), config.capacity)
        self.rng = np.random.default_rng(config.seed)
        log.info("stepping %d worlds of %s on %s, %d transitions kept on %s", config.worlds, config.env_id,
                 getattr(worlds.env.unwrapped, "device", "the host"), config.capacity, worlds.device)

    def next_batch(self, timeout: float) -> DeviceSample | None:
        """Step every world once, then a batch from the ring (None while it holds too few)."""
        worlds, version = self.worlds, self.learner_version
        warming_up = worlds.steps < worlds.config.random_steps
        worlds.stats_extra = {"replay_size": len(self.replay), "random_phase": int(warming_up)}
        step = worlds.step(version, explore=not warming_up)
        self.replay.add(step.obs, step.action, step.reward, step.next_obs, step.terminated, version)
        if len(self.replay) < self._first_batch:
            return None
        return DeviceSample(*self.replay.sample(self.batch_size, self.rng))

    def waiting(self) -> str:
        return f"filling the ring on the device: {len(self.replay)} of {self._first_batch} transitions"


class ColocatedRollouts(WorldsExperience):
    """An on-policy algorithm's experience from the worlds: each batch a rollout of the newest
    policy, ceil(batch_size / worlds) steps of every world, laid world after world; a row's
    `ends` marks an episode's end and each world's last row (the piece ends there)."""

    def __init__(self, worlds: ColocatedWorlds, batch_size: int):
        super().__init__(worlds)
        self.length = -(-batch_size // worlds.config.worlds)
        log.info("stepping %d worlds of %s on %s, rollouts of %d steps of each", worlds.config.worlds,
                 worlds.config.env_id, getattr(worlds.env.unwrapped, "device", "the host"), self.length)

    def next_batch(self, timeout: float) -> DeviceSample:
        steps = [self.worlds.step(self.learner_version) for _ in range(self.length)]

        def laid(field: str) -> torch.Tensor:  # (step, world, ...) to world after world
            stacked = torch.stack([getattr(step, field) for step in steps], dim=1)
            return stacked.reshape(-1, *stacked.shape[2:])

        piece_end = torch.zeros(len(steps[0].ended), self.length, device=self.worlds.device)
        piece_end[:, -1] = 1.0
        batch = ppo.Batch(laid("obs"), laid("action"), laid("reward"), laid("next_obs"), laid("terminated"),
                          torch.maximum(laid("ended"), piece_end.reshape(-1)), laid("log_prob"))
        return DeviceSample(batch, np.full(len(batch.reward), self.learner_version))

    def waiting(self) -> str:
        return "stepping the worlds"


def colocated_experience(session: zenoh.Session, keys: Keys, config: WorldsConfig, policy: PolicyNetwork,
                         batch_size: int, device: torch.device, on_policy: bool) -> ColocatedReplay | ColocatedRollouts:
    """The learner's experience from worlds it steps itself: rollouts for an on-policy algorithm,
    a ring of transitions for SAC and TD3."""
    worlds = ColocatedWorlds(session, keys, config, policy, device)
    return ColocatedRollouts(worlds, batch_size) if on_policy else ColocatedReplay(worlds, batch_size)
