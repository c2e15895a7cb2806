"""`l2r up` keeps the policy of the best evaluation round however fast the learner publishes. A real
BestPolicy hears, over loopback Zenoh, a learner-like peer that publishes many more versions during
a round than its cache holds, and an evaluator that announces its round, or one that does not."""

import logging

import numpy as np
import pytest
import zenoh

from l2r.best_policy import CACHED_VERSIONS, BestPolicy
from l2r.families import score_of
from l2r.learner.checkpoint import load_checkpoint
from l2r.policy import build_policy, policy_state
from l2r.protocol import EpisodeSummary, EvaluationRound, Keys, LearnerVersion, Weights, encode, session_config
from tests.conftest import free_port, wait_for

SPEC = {"obs_dim": 11, "act_dim": 3, "hidden": [8], "activation": "relu", "layer_norm": False}
EVALUATOR = 0
EPISODES = 2  # per round
PUBLISHED_PER_EPISODE = CACHED_VERSIONS  # so a round's version leaves the cache before the round ends


class Job:
    """A BestPolicy as `l2r up` runs it, and the learner's and an evaluator's side of its messages."""

    def __init__(self, run_dir, judges: set[int] | None = None):
        endpoint = f"tcp/127.0.0.1:{free_port()}"
        keys = Keys("best-policy-test")
        self.listener = zenoh.open(session_config(listen=[endpoint]))
        self.sender = zenoh.open(session_config(connect=[endpoint]))
        self.best = BestPolicy(self.listener, keys, run_dir, episodes_per_round=EPISODES, action_repeat=1,
                               score=score_of("Hopper-v5"), judges=judges)
        # Weights and beacons blocked rather than dropped, so the cache sees every version this test counts on.
        block = {"congestion_control": zenoh.CongestionControl.BLOCK}
        self._weights = self.sender.declare_publisher(keys.weights, **block)
        self._beacon = self.sender.declare_publisher(keys.learner_version, **block)
        self._rounds = {actor: self.sender.declare_publisher(keys.rounds(actor)) for actor in (0, 1)}
        self._episodes = {actor: self.sender.declare_publisher(keys.episodes(actor)) for actor in (0, 1)}
        publishers = [self._weights, self._beacon, *self._rounds.values(), *self._episodes.values()]
        # A put before the sender has learnt of the listener's subscribers is dropped.
        assert wait_for(lambda: all(p.matching_status.matching for p in publishers), 10)
        self.version = 0
        self.params = {}  # version -> its weights

    def publish(self, count: int, dropping: int = 0) -> None:
        """``count`` new versions, each with weights of its own and a beacon, as a learner publishing
        after every update; the weights of the first ``dropping`` lost on the way."""
        template = policy_state(build_policy(SPEC))
        for i in range(count):
            self.version += 1
            self.params[self.version] = {name: np.full_like(value, self.version) for name, value in template.items()}
            if i >= dropping:
                self._weights.put(encode(Weights(self.version, self.params[self.version], SPEC)))
            self._beacon.put(encode(LearnerVersion(self.version, updates=10 * self.version)))
        newest = self.version
        assert wait_for(lambda: newest in self.best._weights, 10), f"v{newest} never reached the cache"

    def announce(self, version: int, evaluator: int = EVALUATOR) -> None:
        self._rounds[evaluator].put(encode(EvaluationRound(evaluator, version)))
        assert wait_for(lambda: self.best._evaluating.get(evaluator) == version, 10), "the announcement never came"

    def episode(self, version: int, seed: int, ret: float, evaluator: int = EVALUATOR) -> None:
        self._episodes[evaluator].put(encode(EpisodeSummary(
            actor_id=evaluator, env_id=seed, episode_return=ret, distance=0.0, length=100, policy_version=version,
            difficulty=0, seed=seed, evaluation=True)))

    def round_while_publishing(self, version: int, ret: float, evaluator: int = EVALUATOR) -> None:
        """The episodes of a round of ``version``, the learner publishing a cache's worth of versions after each."""
        for seed in range(EPISODES):
            self.publish(PUBLISHED_PER_EPISODE)
            self.episode(version, seed, ret, evaluator)

    def close(self) -> None:
        self.best.close()
        self.sender.close()
        self.listener.close()


@pytest.fixture
def job(tmp_path):
    j = Job(tmp_path)
    yield j
    j.close()


def saved_version(best: BestPolicy) -> int | None:
    return best.best["version"] if best.best else None


def test_an_announced_round_keeps_its_weights_for_best_pt_while_the_learner_publishes_past_the_cache(job):
    job.publish(3)
    job.announce(3)  # as an evaluator does milliseconds after taking the newest weights
    job.round_while_publishing(3, ret=50.0)
    assert wait_for(lambda: saved_version(job.best) == 3, 10), "the round's policy was never saved"
    saved = load_checkpoint(job.best.path)
    assert (saved.version, saved.updates) == (3, 30)
    assert all(bool((value == 3).all()) for value in saved.train_state["actor"].values())
    assert job.best.best["mean_return"] == 50.0
    # Memory stays bounded: once its round has ended, the version is let go as the cache moves on.
    assert len(job.best._weights) <= CACHED_VERSIONS + 1
    job.publish(1)
    assert 3 not in job.best._weights and len(job.best._weights) == CACHED_VERSIONS
    assert not job.best._evaluating


def test_an_evaluators_next_round_lets_the_version_of_a_round_it_never_finished_go(job):
    job.publish(2)
    job.announce(2)
    job.publish(PUBLISHED_PER_EPISODE)
    assert 2 in job.best._weights  # kept while its round is under way...
    job.announce(job.version)  # ...until the evaluator, restarted, begins another
    job.publish(1)
    assert 2 not in job.best._weights and len(job.best._weights) == CACHED_VERSIONS + 1


def test_an_evaluator_that_does_not_announce_its_rounds_is_judged_as_before(job, caplog):
    job.publish(3)
    with caplog.at_level(logging.WARNING, logger="l2r.up"):
        job.round_while_publishing(3, ret=50.0)  # v3 leaves the cache before its round ends
        assert wait_for(lambda: "weights are no longer at hand" in caplog.text, 10), caplog.text
    assert saved_version(job.best) is None and not job.best.path.exists()
    recent = job.version
    for seed in range(EPISODES):  # a round that ends while its version is still cached
        job.episode(recent, seed, ret=60.0)
    assert wait_for(lambda: saved_version(job.best) == recent, 10)


def test_the_announcement_of_an_evaluator_that_does_not_judge_keeps_nothing(tmp_path):
    job = Job(tmp_path, judges={EVALUATOR})
    try:
        job.publish(3)
        job._rounds[1].put(encode(EvaluationRound(1, 3)))
        job.announce(2)  # put after evaluator 1's, so heard after it
        job.publish(PUBLISHED_PER_EPISODE)
        assert 2 in job.best._weights and 3 not in job.best._weights
        assert job.best._evaluating == {EVALUATOR: 2}
    finally:
        job.close()


def test_beacons_of_versions_whose_weights_were_dropped_on_the_way_are_not_kept_for_ever(job):
    job.publish(3 * CACHED_VERSIONS, dropping=CACHED_VERSIONS)
    assert wait_for(lambda: len(job.best._updates) <= CACHED_VERSIONS + 1, 10), len(job.best._updates)


def test_beacons_heard_after_their_versions_weights_left_the_cache_are_not_kept(job):
    job.publish(2 * CACHED_VERSIONS)  # the weights of the first CACHED_VERSIONS come and go
    for version in range(1, CACHED_VERSIONS + 1):  # their beacons, late: another key, no set order
        job._beacon.put(encode(LearnerVersion(version, updates=10 * version)))
    marker = job.version + 1  # heard after the late ones, which share its key
    job._beacon.put(encode(LearnerVersion(marker, updates=10 * marker)))
    assert wait_for(lambda: marker in job.best._updates, 10)
    assert len(job.best._updates) <= CACHED_VERSIONS + 1, len(job.best._updates)
