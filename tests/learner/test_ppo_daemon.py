"""PPO end to end through real daemons over loopback Zenoh: an l2r-actor (on the stand-in env), an
l2r-replay with the queue table alone, and l2r-learner --algo ppo."""

import signal

import numpy as np
import pytest

from l2r.learner.checkpoint import load_checkpoint
from l2r.learner.ppo import PPOConfig
from l2r.protocol import Keys, Stats, decode
from tests.learner.conftest import WeightsWatcher, learner_args

# max lag 0: a transition acted by any policy but the newest published is dropped, so the run
# drops stale data all along (the actors swap in new weights a little after each update).
QUEUE_REPLAY = ["--capacity", "0", "--queue-capacity", "256", "--queue-max-lag", "0"]
PPO_LEARNER = ["--algo", "ppo", "--in-flight", "1", "--epochs", "2", "--minibatches", "4"]  # 8 updates a batch


def replay_stats(network) -> dict:
    replies = [r.ok for r in network.session.get(Keys(network.run).stats("replay", 0), timeout=5) if r.ok]
    return decode(replies[0].payload, Stats).values


@pytest.mark.slow
@pytest.mark.parametrize("network", [QUEUE_REPLAY], indirect=True)
def test_ppo_trains_through_real_daemons_with_rising_versions_and_a_queue_that_drops_stale_data(network, tmp_path):
    run_dir = tmp_path / "run"
    watcher = WeightsWatcher(network.session, network.run)
    learner = network.start("l2r.learner", *learner_args(network, run_dir, *PPO_LEARNER), name="learner")
    network.start("l2r.actors", "--run", network.run, "--connect", network.endpoint, "--env-id",
                  "tests.actors.standin:StandIn-v0", "--num-envs", "4", "--chunk-size", "16", "--random-steps", "0",
                  name="actor")
    # Version 1 at the start, then one after every batch of 8 updates: version 41 is 320 updates.
    watcher.wait(lambda v: v and v[-1] >= 41, 90, "version 41", learner)
    assert learner.stop(signal.SIGTERM) == 0, learner.log()

    assert watcher.versions == sorted(set(watcher.versions)), "versions must rise"
    saved = load_checkpoint(run_dir)
    assert saved.algo == "ppo" and isinstance(saved.config, PPOConfig) and saved.updates >= 320
    assert saved.version == watcher.versions[-1] and saved.updates == 8 * (saved.version - 1)
    trained = [m for m in watcher.metrics if m["updates_per_s"] > 0]
    # Lag at most 1: the queue gives nothing older than the version a request names, and the client
    # sends its next request as it takes a batch, before that batch's update publishes a new version.
    assert trained and all(np.isfinite(m["value_loss"]) and m["policy_lag"] <= 1 for m in trained), trained

    values = replay_stats(network)
    # Each transition leaves the queue once: given to the learner, dropped, or still waiting.
    assert values["queue.inserted"] == (values["queue.given"] + values["queue.dropped_stale"]
                                        + values["queue.dropped_full"] + values["queue.size"]), values
    assert values["queue.given"] >= saved.train_state["extra"]["samples"] >= 64 * 40
    assert values["queue.dropped_stale"] > 0, values
    assert "rejected message" not in learner.log()
