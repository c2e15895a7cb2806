"""Colocated worlds (l2r.learner.colocated): the ring of transitions on the device, the worlds'
steps as the learner stores them (an ended episode's last observation, not the next one's
first), their episode summaries and stats over a real Zenoh session, the worlds of
l2r/RunWarp-v0 on Warp's CPU device, and a real l2r-learner training on its own worlds."""

import signal
import threading
import uuid

import numpy as np
import pytest
import torch
import zenoh

from l2r.learner.checkpoint import load_checkpoint
from l2r.learner.colocated import DeviceReplay, WorldsConfig, colocated_experience
from l2r.policy import Policy, default_spec
from l2r.protocol import EpisodeSummary, Keys, Stats, decode, session_config
from tests.conftest import free_port, wait_for
from tests.learner.conftest import Daemon, WeightsWatcher

CPU = torch.device("cpu")


@pytest.fixture
def session():
    with zenoh.open(session_config(listen=[f"tcp/127.0.0.1:{free_port()}"])) as s:
        yield s


class Heard:
    """Every episode summary and stats message of a run's actor 0, as decoded."""

    def __init__(self, session: zenoh.Session, run: str):
        self.episodes: list[EpisodeSummary] = []
        self.stats: list[dict] = []
        self._lock = threading.Lock()
        keys = Keys(run)
        self._subs = [session.declare_subscriber(keys.episodes(0), self._on_episode),
                      session.declare_subscriber(keys.stats("actor", 0), self._on_stats)]

    def _on_episode(self, sample) -> None:
        with self._lock:
            self.episodes.append(decode(sample.payload, EpisodeSummary))

    def _on_stats(self, sample) -> None:
        with self._lock:
            self.stats.append(decode(sample.payload, Stats).values)


def small_policy(obs_dim: int, act_dim: int) -> Policy:
    return Policy(default_spec(obs_dim, act_dim) | {"hidden": [16]})


def test_the_ring_keeps_the_newest_rows_with_their_versions_and_samples_only_those():
    replay = DeviceReplay(5, obs_dim=2, act_dim=1, device=CPU)

    def rows(first: int, n: int):
        values = torch.arange(first, first + n, dtype=torch.float32)
        obs = values[:, None].repeat(1, 2)
        return obs, values[:, None], values, obs + 100, torch.zeros(n)

    replay.add(*rows(0, 3), version=1)
    replay.add(*rows(3, 4), version=2)  # wraps: rows 3-6 over the oldest two and into the free ones
    assert len(replay) == 5
    assert replay.obs[:, 0].tolist() == [5, 6, 2, 3, 4]
    assert replay.next_obs[:, 1].tolist() == [105, 106, 102, 103, 104]
    assert replay.versions.tolist() == [2, 2, 1, 2, 2]
    batch, versions = replay.sample(200, np.random.default_rng(0))
    held = {2, 3, 4, 5, 6}
    assert set(batch.obs[:, 0].tolist()) == held and set(batch.reward.tolist()) == held
    assert torch.equal(batch.next_obs[:, 0], batch.obs[:, 0] + 100) and torch.equal(batch.action[:, 0], batch.reward)
    assert all(v == (1 if o == 2 else 2) for o, v in zip(batch.obs[:, 0].tolist(), versions))
    replay.add(*rows(10, 7), version=3)  # more rows than it holds: the newest five
    assert sorted(replay.obs[:, 0].tolist()) == [12, 13, 14, 15, 16] and set(replay.versions.tolist()) == {3}


def test_colocated_worlds_store_each_step_with_an_ended_episode_s_last_observation_and_report_it(session):
    """Pendulum-v1 ends by its 200-step time limit: with each action repeated twice, after 100
    actions. Three worlds, 110 steps: each world's rows chain (next_obs is the next row's obs) but
    at its episode's end, where the next row starts the next episode."""
    run, worlds = f"test-colocated-{uuid.uuid4().hex[:8]}", 3
    heard = Heard(session, run)
    config = WorldsConfig("Pendulum-v1", worlds=worlds, capacity=1000, random_steps=30, min_replay=0,
                          action_repeat=2, seed=5)
    experience = colocated_experience(session, Keys(run), config, small_policy(3, 1), batch_size=8, device=CPU,
                                      on_policy=False)
    batches = [experience.next_batch(timeout=0.0) for _ in range(110)]
    experience.close()

    assert all(b is None for b in batches[:9]) and all(b is not None for b in batches[9:])  # 30 rows before the first
    assert batches[-1].tensors.obs.shape == (8, 3) and batches[-1].actions.shape == (8, 1)
    replay = experience.replay
    assert len(replay) == 330 and not replay.terminated[:330].any()  # a time limit cuts no bootstrap
    obs, next_obs = replay.obs[:330].reshape(110, worlds, 3), replay.next_obs[:330].reshape(110, worlds, 3)
    chained = (next_obs[:-1] == obs[1:]).all(dim=-1)  # (step, world)
    assert chained[:99].all() and chained[100:].all() and not chained[99].any()
    assert (replay.action[:330].abs() <= 1).all()

    assert wait_for(lambda: len(heard.episodes) == worlds and heard.stats and heard.stats[-1]["env_steps"] == 330)
    rewards = replay.reward[:330].reshape(110, worlds)
    for summary in sorted(heard.episodes, key=lambda s: s.env_id):
        assert summary.length == 100 and summary.actor_id == 0 and not summary.evaluation
        assert summary.episode_return == pytest.approx(float(rewards[:100, summary.env_id].sum()), rel=1e-5)
    assert heard.stats[-1]["episodes"] == worlds and heard.stats[-1]["num_envs"] == worlds


def test_a_step_that_blows_up_is_stored_as_a_terminal_step_without_reward_from_where_the_world_was(session):
    """Stand-ins whose 7th step returns NaN observations: the ring holds no NaN, each blow-up is
    a terminal row whose next observation is its own, and the stats count them."""
    run = f"test-colocated-nan-{uuid.uuid4().hex[:8]}"
    heard = Heard(session, run)
    config = WorldsConfig("tests.actors.standin:Diverging-v0", worlds=2, capacity=100, random_steps=100, min_replay=0)
    experience = colocated_experience(session, Keys(run), config, small_policy(41, 18), batch_size=4, device=CPU,
                                      on_policy=False)
    for _ in range(10):
        experience.next_batch(timeout=0.0)
    experience.close()

    replay = experience.replay
    assert torch.isfinite(replay.obs[:20]).all() and torch.isfinite(replay.next_obs[:20]).all()
    blown = replay.terminated[:20].reshape(10, 2)
    assert blown[6].tolist() == [1.0, 1.0] and blown.sum() == 2
    assert torch.equal(replay.next_obs[12:14], replay.obs[12:14]) and replay.reward[12:14].tolist() == [0.0, 0.0]
    assert wait_for(lambda: heard.stats and heard.stats[-1]["blowups"] == 2 and len(heard.episodes) == 2)
    assert all(e.length == 7 for e in heard.episodes)


def test_colocated_runner_worlds_on_warp_s_cpu_device_end_in_falls_that_cut_the_bootstrap(session):
    """l2r/RunWarp-v0 (kernels cached by make setup): random excitations fell each runner within
    its 1000 steps; each fall is one terminated row and one episode summary, its distance the
    pelvis' travel, as an actor reports it."""
    run = f"test-colocated-warp-{uuid.uuid4().hex[:8]}"
    heard = Heard(session, run)
    config = WorldsConfig("l2r/RunWarp-v0", worlds=2, capacity=4000, random_steps=10_000, min_replay=0,
                          action_repeat=3, seed=1)
    experience = colocated_experience(session, Keys(run), config, small_policy(41, 18), batch_size=8, device=CPU,
                                      on_policy=False)
    assert experience.worlds.env.unwrapped.device.is_cpu
    for _ in range(200):
        experience.next_batch(timeout=0.0)
    experience.close()

    ended = int(experience.replay.terminated[:400].sum())
    assert ended >= 2 and torch.isfinite(experience.replay.obs[:400]).all()
    assert wait_for(lambda: len(heard.episodes) == ended)
    assert all(s.length < 200 and -2 < s.distance < 2 for s in heard.episodes), heard.episodes


def test_on_policy_rollouts_lay_each_world_s_steps_end_to_end_with_the_log_probs_of_the_policy_that_acted(session):
    """Rollouts of 10 steps of 3 Pendulum-v1 worlds (batch 30), one action a step: world after
    world, each piece ending at its last row; the next rollout goes on where this one stopped."""
    run, worlds, length = f"test-colocated-rollouts-{uuid.uuid4().hex[:8]}", 3, 10
    policy = small_policy(3, 1)
    config = WorldsConfig("Pendulum-v1", worlds=worlds, seed=2)
    experience = colocated_experience(session, Keys(run), config, policy, batch_size=30, device=CPU, on_policy=True)
    experience.learner_version = 4
    first, second = experience.next_batch(timeout=0.0), experience.next_batch(timeout=0.0)
    experience.close()

    batch = first.tensors
    assert batch.obs.shape == (30, 3) and first.policy_versions.tolist() == [4] * 30
    obs, next_obs = batch.obs.reshape(worlds, length, 3), batch.next_obs.reshape(worlds, length, 3)
    assert torch.equal(next_obs[:, :-1], obs[:, 1:])  # no episode ends within 10 of its 200 steps
    assert batch.ends.reshape(worlds, length)[:, -1].tolist() == [1.0] * worlds and batch.ends.sum() == worlds
    assert not batch.terminated.any()
    assert torch.equal(second.tensors.obs.reshape(worlds, length, 3)[:, 0], next_obs[:, -1])
    with torch.no_grad():
        log_prob, _ = policy.evaluate(batch.obs, batch.action)
    assert torch.allclose(log_prob, batch.behaviour_log_prob, atol=1e-4)


@pytest.mark.slow
@pytest.mark.parametrize("algo", ["td3", "ppo"])
def test_a_learner_trains_on_its_own_worlds_publishes_weights_and_their_episodes_and_checkpoints(algo, tmp_path):
    run, endpoint = f"test-colocated-{uuid.uuid4().hex[:8]}", f"tcp/127.0.0.1:{free_port()}"
    session = zenoh.open(session_config(connect=[endpoint]))
    heard, watcher = Heard(session, run), WeightsWatcher(session, run)
    learner = Daemon("l2r.learner", ["--run", run, "--listen", endpoint, "--run-dir", str(tmp_path / "run"),
                                     "--device", "cpu", "--threads", "1", "--hidden", "32,32", "--batch-size", "64",
                                     "--publish-every", "20", "--metrics-interval", "1", "--algo", algo,
                                     "--colocated-env", "Pendulum-v1", "--colocated-worlds", "4",
                                     "--colocated-min-replay", "200", "--colocated-random-steps", "100",
                                     "--action-repeat", "2"],
                     tmp_path / "learner.log")
    try:
        # A metrics report of training too: a fast learner reaches version 5 before its first report.
        watcher.wait(lambda v: v and v[-1] >= 5 and any(m["updates_per_s"] > 0 for m in watcher.metrics), 90,
                     "version 5 and a report of training", learner)
        assert wait_for(lambda: heard.episodes, timeout=60), learner.log()
        assert wait_for(lambda: heard.stats and heard.stats[-1]["env_steps"] >= 400, timeout=30), heard.stats[-1:]
        assert learner.stop(signal.SIGTERM) == 0, learner.log()
        # Every episode the worlds counted reached this listener, the first too (sent as the learner joined).
        counted = max(s["episodes"] for s in heard.stats)
        assert wait_for(lambda: len(heard.episodes) >= counted, timeout=5), (len(heard.episodes), counted)
    finally:
        session.close()
    log = learner.log()
    assert "stepping 4 worlds of Pendulum-v1" in log and "rejected" not in log
    saved = load_checkpoint(tmp_path / "run")
    assert saved.algo == algo and saved.version >= 5 and saved.action_repeat == 2
    assert all(e.length == 100 and e.actor_id == 0 for e in heard.episodes)
    # The batches' policy lag: a rollout is the newest policy's; a ring holds older ones too.
    lags = [m["policy_lag"] for m in watcher.metrics if m["updates_per_s"] > 0]
    assert lags and (max(lags) == 0 if algo == "ppo" else max(lags) > 0), lags
