"""The best evaluated policy of a run, kept by `l2r up` as `learner/best.pt`.

An evaluator runs rounds of `--eval-episodes` deterministic episodes, each round with one
policy version, on the same seeds. With evaluators in several simulators, those of the first
`--eval-env-id` judge. When a round ends with a higher mean score (l2r.families: the distance on
the runner, the return on a standard task) than any before in the run, the policy of that
version is saved as a policy checkpoint (see l2r.learner.checkpoint) that `l2r eval` reads. Its
`evaluation` names the score and holds its mean as `mean_<score>` (`mean_distance` on the
runner, as files from before scores were named). The weights come from the learner's weights
messages, the very ones the evaluator loaded. The newest `CACHED_VERSIONS` are kept in memory,
and besides them the version each evaluator said it evaluates as its round began (the
`evaluation_round` message), until that round ends or the evaluator's next one begins: a learner
may publish hundreds of versions a second, far more than a cache holds over a round of episodes.
The round's announcement comes milliseconds after the evaluator took the newest weights, while
they are still cached. An evaluator that does not announce its rounds (from before the message)
has its policy saved only while the version is still among the newest cached.
"""

from __future__ import annotations

import logging
import math
import threading
from collections import OrderedDict
from pathlib import Path

import zenoh

from l2r.durable import DISK_ERRORS, FailureLog
from l2r.families import Score
from l2r.learner.checkpoint import CheckpointError, best_policy_path, load_checkpoint, save_policy_checkpoint
from l2r.protocol import EpisodeSummary, EvaluationRound, Keys, LearnerVersion, Weights, watched

log = logging.getLogger("l2r.up")

CACHED_VERSIONS = 64  # how far the learner may run ahead of an evaluator that does not announce its rounds


class BestPolicy:
    """Saves the policy of each evaluation round that beats the best mean score so far."""

    def __init__(self, session: zenoh.Session, keys: Keys, run_dir: Path, episodes_per_round: int,
                 action_repeat: int, score: Score, judges: set[int] | None = None):
        self.path = best_policy_path(run_dir)
        self.write_failures = FailureLog(log, "best evaluated policy")
        self.score = score
        self.judges = judges  # the evaluators (actor ids) whose rounds count; None: all of them
        self.episodes_per_round, self.action_repeat = episodes_per_round, action_repeat
        self.best: dict | None = None  # the evaluation of the policy in best.pt
        if self.path.exists():  # a resumed run: beat the best of the sessions before
            self.best = self._earlier_best()
        self._lock = threading.Lock()
        self._weights: OrderedDict[int, Weights] = OrderedDict()
        self._updates: dict[int, int] = {}  # updates at each version, from the learner's beacon
        self._evicted_through = 0  # the newest version whose weights left the cache
        self._rounds: dict[tuple[int, int], dict[int, float]] = {}  # (evaluator, version) -> seed -> score
        self._evaluating: dict[int, int] = {}  # evaluator -> the version of its round under way, kept cached
        self._subs = [session.declare_subscriber(keys.weights, self._on_weights),
                      session.declare_subscriber(keys.learner_version, self._on_version),
                      session.declare_subscriber(keys.all_rounds, self._on_round),
                      session.declare_subscriber(keys.all_episodes, self._on_episode)]

    def _is_judge(self, actor_id: int) -> bool:
        """Whether the rounds of this evaluator choose best.pt."""
        return self.judges is None or actor_id in self.judges

    def _earlier_best(self) -> dict | None:
        """The evaluation of the best.pt a resumed run left, if it was judged by this score."""
        try:
            evaluation = load_checkpoint(self.path).evaluation or {}
        except CheckpointError as e:
            log.warning("%s; it will be replaced by the next evaluated policy", e)
            return None
        # Files from before scores were named hold mean_distance alone, whatever the task.
        if f"mean_{self.score.name}" not in evaluation:
            log.warning("%s was not chosen by %s, this run's score: it will be replaced by the next evaluated policy",
                        self.path, self.score.name)
            return None
        return evaluation

    @property
    def best_mean(self) -> float:
        """The mean score of the policy in best.pt (-inf without one)."""
        return -math.inf if self.best is None else float(self.best[f"mean_{self.score.name}"])

    def _on_weights(self, sample: zenoh.Sample) -> None:
        weights = watched(sample, Weights)
        if weights is None:
            return
        with self._lock:
            self._weights[weights.version] = weights
            evaluating = set(self._evaluating.values())
            unpinned = [version for version in self._weights if version not in evaluating]  # oldest first
            evicted = unpinned[:max(0, len(unpinned) - CACHED_VERSIONS)]
            for version in evicted:
                del self._weights[version]
            if evicted:  # also the beacons of older versions, whose weights may have been dropped on the way
                self._evicted_through = evicted[-1]
                self._updates = {version: updates for version, updates in self._updates.items()
                                 if version > self._evicted_through or version in evaluating}

    def _on_version(self, sample: zenoh.Sample) -> None:
        beacon = watched(sample, LearnerVersion)
        if beacon is None:
            return
        with self._lock:
            # Beacons and weights come on separate keys, in no set order: a beacon heard after its
            # version's weights left the cache would otherwise be kept for ever.
            if beacon.version > self._evicted_through or beacon.version in self._evaluating.values():
                self._updates[beacon.version] = beacon.updates

    def _on_round(self, sample: zenoh.Sample) -> None:
        round_ = watched(sample, EvaluationRound)
        if round_ is None or not self._is_judge(round_.actor_id):
            return
        with self._lock:  # its previous round is over: that version's weights go as the cache moves on
            self._evaluating[round_.actor_id] = round_.policy_version

    def _on_episode(self, sample: zenoh.Sample) -> None:
        ep = watched(sample, EpisodeSummary)
        if ep is None:
            return
        if not ep.evaluation or not self._is_judge(ep.actor_id):
            return
        with self._lock:
            round_ = self._rounds.setdefault((ep.actor_id, ep.policy_version), {})
            round_[ep.seed] = self.score.of(ep)  # a restarted evaluator repeats a seed with the same result
            if len(round_) < self.episodes_per_round:
                return
            del self._rounds[(ep.actor_id, ep.policy_version)]
            if self._evaluating.get(ep.actor_id) == ep.policy_version:
                del self._evaluating[ep.actor_id]  # its weights are read below or not needed
            mean = sum(round_.values()) / len(round_)
            if mean <= self.best_mean:
                return
            weights = self._weights.get(ep.policy_version)
            if weights is None:
                log.warning("evaluation of v%d: best mean %s so far, but its weights are no longer at hand; %s "
                            "keeps %s", ep.policy_version, self.score.text(mean), self.path,
                            f"v{self.best['version']}" if self.best else "no policy yet")
                return
            evaluation = {"version": ep.policy_version, "score": self.score.name, f"mean_{self.score.name}": mean,
                          "episodes": len(round_), "seeds": sorted(round_), "evaluator": ep.actor_id}
            try:
                save_policy_checkpoint(self.path, weights.params, weights.spec, ep.policy_version,
                                       self._updates.get(ep.policy_version, -1), self.action_repeat, evaluation)
            except OSError as e:
                if e.errno not in DISK_ERRORS:
                    raise
                self.write_failures.failed(e, self.path, f"the policy v{ep.policy_version} is not kept")
                return
            self.write_failures.succeeded()
            self.best = evaluation
            log.info("best evaluated policy so far: v%d, mean %s, saved as %s", ep.policy_version,
                     self.score.text(mean), self.path)

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
