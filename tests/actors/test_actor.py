"""A real `l2r-actor` process, with this test playing the learner and the replay server over
loopback Zenoh. The environment is a stand-in with the runner's shapes (tests/actors/standin.py),
so these tests are about the actor; the real runner is exercised in tests/system."""

import dataclasses
import signal
import subprocess
import sys
import time
import uuid

import numpy as np
import pytest
import zenoh

from l2r.actors.actor import ActorConfig, levers_on
from l2r.actors.curriculum import DISTANCE_WINDOW, DifficultySchedule
from l2r.config import EXIT_CANNOT_START
from l2r.policy import build_policy, policy_state, uniform_log_prob
from l2r.sim.randomize import Randomization
from l2r.protocol import (
    EpisodeSummary, EvaluationRound, ExperienceChunk, Keys, Stats, Weights, decode, encode, session_config,
)
from tests.conftest import PROCESS_START_S, ROOT, free_port, wait_for

STANDIN = "tests.actors.standin:StandIn-v0"
SPEC = {"obs_dim": 41, "act_dim": 18, "hidden": [32], "activation": "elu", "layer_norm": False}


class Peer:
    """This test's side: replay token (optional), weights queryable, and recorders of what the actor sends."""

    def __init__(self, run: str):
        self.port = free_port()
        self.keys = Keys(run)
        self.session = zenoh.open(session_config(listen=[f"tcp/127.0.0.1:{self.port}"]))
        self.chunks: list[ExperienceChunk] = []
        self.episodes: list[EpisodeSummary] = []
        self.rounds: list[EvaluationRound] = []
        self.stats: list[Stats] = []
        self.latest = Weights(3, policy_state(build_policy(SPEC)), SPEC)
        self.token = None
        s = self.session
        self._subs = [
            s.declare_subscriber(self.keys.experience_of_shard(0), lambda x: self.chunks.append(decode(x.payload))),
            s.declare_subscriber(self.keys.all_episodes, lambda x: self.episodes.append(decode(x.payload))),
            s.declare_subscriber(self.keys.all_rounds, lambda x: self.rounds.append(decode(x.payload))),
            s.declare_subscriber(self.keys.all_stats, lambda x: self.stats.append(decode(x.payload))),
            s.declare_queryable(self.keys.weights_query, lambda q: q.reply(self.keys.weights_query, encode(self.latest))),
        ]

    def replay_up(self, up: bool) -> None:
        if up and self.token is None:
            self.token = self.session.liveliness().declare_token(self.keys.alive("replay", 0))
        elif not up and self.token is not None:
            self.token.undeclare()
            self.token = None

    def publish(self, payload: bytes) -> None:
        self.session.put(self.keys.weights, payload)

    def last_stats(self) -> dict:
        return self.stats[-1].values if self.stats else {}

    def actor(self, *args: str) -> subprocess.Popen:
        return subprocess.Popen(
            [sys.executable, "-m", "l2r.actors", "--run", self.keys.run, "--connect", f"tcp/127.0.0.1:{self.port}",
             "--env-id", STANDIN, "--num-envs", "3", "--chunk-size", "16", "--stats-interval", "0.2", *args],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

    def close(self) -> None:
        self.session.close()


@pytest.fixture
def peer():
    p = Peer(f"test-actor-{uuid.uuid4().hex[:8]}")
    yield p
    p.close()


def stop(proc: subprocess.Popen) -> str:
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 0, out
    return out


def test_the_untrained_policy_of_a_new_run_leaves_the_warm_up_to_run_its_course(peer):
    # A learner publishes version 1 before its first update; the warm-up must not end on it.
    peer.latest = Weights(1, peer.latest.params, SPEC)
    peer.replay_up(True)
    proc = peer.actor("--random-steps", "1000000", "--seed", "4")
    try:
        assert wait_for(lambda: len(peer.chunks) >= 3, PROCESS_START_S), "chunks"
        uniform = uniform_log_prob(SPEC["act_dim"])
        assert all(np.allclose(c.log_probs, uniform) for c in peer.chunks), "uniform random actions"
    finally:
        assert "warm-up over" not in stop(proc)


def test_actor_follows_weights_survives_bad_ones_and_waits_for_replay(peer):
    peer.replay_up(True)
    # Joining a run whose policy is past version 0 skips the warm-up, however long it is.
    proc = peer.actor("--random-steps", "1000000", "--seed", "4")
    try:
        # The weights it asked for on join drive its first chunks.
        assert wait_for(lambda: any(c.policy_version == 3 for c in peer.chunks), PROCESS_START_S), \
            "chunks acted by version 3"
        assert wait_for(lambda: any(e.policy_version == 3 for e in peer.episodes)), "episodes acted by version 3"
        alive = peer.session.liveliness().get(peer.keys.alive_role("actor"))
        assert [str(r.ok.key_expr) for r in alive if r.ok] == [peer.keys.alive("actor", 0)]

        # Garbage, weights that do not fit the network, a policy for 40 observations where the env
        # gives 41, stacks the replay cannot build: counted, not fatal, the policy kept.
        peer.publish(b"\x00not msgpack")
        peer.publish(encode(Weights(4, {"trunk.0.weight": np.zeros((2, 2), np.float32)}, SPEC)))
        narrow = {**SPEC, "obs_dim": 40}
        peer.publish(encode(Weights(4, policy_state(build_policy(narrow)), narrow)))
        peer.publish(encode(Weights(4, peer.latest.params, {**SPEC, "frame_stack": 17})))
        assert wait_for(lambda: peer.last_stats().get("rejected_weights", 0) >= 4), "four rejections counted"
        assert peer.last_stats()["policy_version"] == 3
        assert proc.poll() is None

        # A published update is swapped in; its chunks carry the new version.
        peer.publish(encode(Weights(5, policy_state(build_policy(SPEC)), SPEC)))
        assert wait_for(lambda: any(c.policy_version == 5 for c in peer.chunks)), "chunks acted by version 5"
        assert wait_for(lambda: peer.last_stats().get("policy_version") == 5 and peer.last_stats().get("staleness") == 0), "stats at version 5"
        assert "frames_per_s" not in peer.last_stats()  # a vector task renders no frames

        # Without a replay server the actor waits instead of sending into the void.
        peer.replay_up(False)
        assert wait_for(lambda: peer.last_stats().get("waiting_for_replay") == 1), "actor waiting"
        time.sleep(0.3)
        n = len(peer.chunks)
        time.sleep(0.5)
        assert len(peer.chunks) == n
        peer.replay_up(True)
        assert wait_for(lambda: len(peer.chunks) > n), "chunks after replay came back"
    finally:
        out = stop(proc)
    assert "rejected message" in out

    # This peer never acknowledges, so the actor sends chunks again after a while: first copies only.
    firsts: dict[int, ExperienceChunk] = {}
    for c in peer.chunks:
        firsts.setdefault(c.seq, c)
    first = list(firsts.values())
    versions = [c.policy_version for c in first]
    assert versions == sorted(versions)  # a chunk never mixes or reverts versions
    seqs = [c.seq for c in first]
    assert seqs == list(range(len(seqs)))  # one sequence across the actor's environments, none lost
    assert {c.env_id for c in peer.chunks} == {0, 1, 2}
    assert len({c.epoch for c in peer.chunks}) == 1
    train = [e for e in peer.episodes if not e.evaluation]
    assert train and all(e.length == 40 and e.actor_id == 0 for e in train)  # stand-in: 40 steps of 0.01 s


def test_an_environment_that_breaks_its_own_observation_space_stops_the_actor_with_one_line(peer):
    peer.replay_up(True)
    proc = peer.actor("--env-id", "tests.actors.standin:BrokenStandIn-v0", "--num-envs", "1")
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 1, out
    assert "tests.actors.standin:BrokenStandIn-v0 returned an observation outside its own observation space: " \
           "observation.state: shape [40], expected [41]; stopping" in out, out
    assert "Traceback" not in out


def test_an_environment_whose_observations_l2r_cannot_take_stops_the_actor_at_start_with_one_line(peer):
    proc = peer.actor("--env-id", "tests.actors.standin:CountingStandIn-v0", "--num-envs", "1")
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == EXIT_CANNOT_START, out
    assert out.strip().splitlines()[-1] == ("l2r-actor: tests.actors.standin:CountingStandIn-v0: observation 'state' "
                                            "is a Discrete space; l2r takes a Box or a Dict of Box spaces"), out


def test_evaluation_role_announces_and_repeats_its_rounds_exactly_under_the_same_weights_and_sends_no_experience(peer):
    peer.replay_up(True)
    proc = peer.actor("--evaluate", "--actor-id", "9", "--eval-episodes", "4", "--seed", "100", "--eval-interval", "0")

    def round_of(version: int) -> dict[int, tuple[float, float, int]]:
        return {e.seed: (e.episode_return, e.distance, e.length) for e in peer.episodes if e.policy_version == version}

    try:
        assert wait_for(lambda: len(round_of(3)) == 4, PROCESS_START_S), "no evaluation round of version 3"
        # The same weights again, under a new version: a second round that must repeat the first.
        peer.publish(encode(Weights(8, peer.latest.params, SPEC)))
        assert wait_for(lambda: len(round_of(8)) == 4), "no evaluation round of version 8"
        # Other weights: a round that must differ, or the equality above would prove nothing.
        peer.publish(encode(Weights(9, policy_state(build_policy(SPEC)), SPEC)))
        assert wait_for(lambda: len(round_of(9)) == 4), "no evaluation round of version 9"
    finally:
        stop(proc)
    assert not peer.chunks
    assert all(e.evaluation and e.actor_id == 9 for e in peer.episodes)
    assert [(r.actor_id, r.policy_version) for r in peer.rounds] == [(9, 3), (9, 8), (9, 9)]
    assert sorted(round_of(3)) == [100, 101, 102, 103]
    assert round_of(8) == round_of(3)
    assert all(round_of(9)[seed] != round_of(3)[seed] for seed in round_of(3))


def actions_of_a_constant_policy(peer, flags: list[str], chunks: int, log_std_bias: float = 0.0) -> list[np.ndarray]:
    """The actions a real actor with `flags` sends in `chunks` chunks, acting with a policy whose
    mean and std are the same at every observation (its head zero, the log-std rows' bias given)."""
    params = policy_state(build_policy(SPEC))
    params |= {name: np.zeros_like(params[name]) for name in ("head.weight", "head.bias")}
    params["head.bias"][len(params["head.bias"]) // 2:] = log_std_bias
    peer.latest = Weights(3, params, SPEC)
    peer.replay_up(True)
    proc = peer.actor(*flags, "--seed", "4")
    try:
        assert wait_for(lambda: sum(c.policy_version == 3 for c in peer.chunks) >= chunks, PROCESS_START_S), "chunks"
    finally:
        stop(proc)
    return [c.actions for c in peer.chunks if c.policy_version == 3]


def test_red_exploration_noise_correlates_each_env_s_successive_actions(peer):
    # What varies is the noise alone.
    acted = actions_of_a_constant_policy(peer, ["--exploration-noise", "red"], chunks=12)
    steps = np.concatenate(acted)
    assert 0.3 < steps.mean() < 0.7 and steps.std() > 0.03  # N(0, 1) draws through std 0.22 and the tanh
    # (a chunk sent early, at a change of weights, may hold a step or two: too few to correlate)
    within = [np.corrcoef(a[:-1].ravel(), a[1:].ravel())[0, 1] for a in acted if len(a) >= 8]
    assert len(within) >= 8 and np.median(within) > 0.6, within  # white draws: about 0


def test_parameter_noise_moves_the_actions_of_a_policy_that_does_not_explore_itself(peer):
    # Every action 0.5 with a std of e^-20 (the log-std's lower bound): what moves them is the perturbation alone.
    steps = np.concatenate(actions_of_a_constant_policy(peer, ["--parameter-noise", "0.2"], chunks=4,
                                                        log_std_bias=-10.0))
    assert np.abs(steps - 0.5).mean() > 0.01, np.abs(steps - 0.5).mean()  # without the noise: below 1e-6


def test_a_distance_stage_moves_the_actor_to_the_obstacles_once_its_episodes_ran_that_far(peer):
    # Random excitations fall within a metre of the start: a -5 m stage is reached at the 20th episode.
    peer.replay_up(True)
    proc = peer.actor("--env-id", "l2r/Run-v0", "--difficulty-schedule", "0:0,-5m:2", "--random-steps", "1000000")
    try:
        assert wait_for(lambda: any(e.difficulty == 2 for e in peer.episodes), 120), [e.difficulty for e in
                                                                                       peer.episodes]
    finally:
        stop(proc)
    training = sorted(peer.episodes, key=lambda e: e.time)
    first_move = next(i for i, e in enumerate(training) if e.difficulty == 2)
    assert first_move >= DISTANCE_WINDOW and all(e.difficulty == 0 for e in training[:DISTANCE_WINDOW])
    # Every episode begun after the move is on the course; the other two worlds finish the ones they were on.
    assert all(e.difficulty == 2 for e in training[first_move + 2:])


def test_a_training_actor_names_the_levers_it_has_on_and_an_evaluator_none():
    config = ActorConfig(run="x", randomize=Randomization.parse("mass=0.1,delay=0.5"), parameter_noise=0.2,
                         exploration_noise="pink", difficulty_schedule=DifficultySchedule.parse("0:0,1000:2"))
    assert levers_on(config) == ["difficulty schedule 0:0,1000:2", "randomised mass=0.1,delay=0.5",
                                 "pink exploration noise", "parameter noise 0.2"]
    assert levers_on(dataclasses.replace(config, env_steps_before=1_500_000))[0] == \
        "difficulty schedule 0:0,1000:2 from env step 1,500,000"
    assert levers_on(ActorConfig(run="x")) == []
    assert levers_on(dataclasses.replace(config, evaluate=True)) == []
