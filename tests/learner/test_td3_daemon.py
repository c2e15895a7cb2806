"""TD3 end to end through real daemons over loopback Zenoh: an l2r-actor exploring with the published
deterministic policy (on the stand-in env), an l2r-replay, l2r-learner --algo td3, then l2r eval
of its checkpoint."""

import json
import re
import signal
import subprocess
import sys

import numpy as np
import pytest

from l2r.learner.checkpoint import load_checkpoint
from l2r.learner.td3 import TD3Config, exploration_std
from l2r.policy import DeterministicPolicy
from tests.conftest import ROOT
from tests.learner.conftest import WeightsWatcher, learner_args

# The std falls from 1.0 to 0.1 over the first 100 updates; with 2 updates a batch and weights every
# 20 updates, version v (v >= 2) goes out at update 20 * (v - 1).
SCHEDULE = ["--exploration-std-start", "1.0", "--exploration-std-end", "0.1", "--exploration-std-updates", "100"]
# 3-step returns: the learner's requests ask the replay server for them (SAC's tests cover one step).
TD3_LEARNER = ["--algo", "td3", "--n-step", "3", "--checkpoint-interval", "1", *SCHEDULE]


@pytest.mark.slow
def test_td3_trains_on_an_actor_s_experience_publishes_its_schedule_and_checkpoints(network, tmp_path):
    run_dir = tmp_path / "run"
    watcher = WeightsWatcher(network.session, network.run)
    learner = network.start("l2r.learner", *learner_args(network, run_dir, *TD3_LEARNER), name="learner")
    actor = network.start("l2r.actors", "--run", network.run, "--connect", network.endpoint, "--env-id",
                          "tests.actors.standin:StandIn-v0", "--num-envs", "4", "--chunk-size", "16",
                          "--random-steps", "0", name="actor")
    # A metrics report of training too: a fast learner reaches version 7 before its first report.
    watcher.wait(lambda v: v and v[-1] >= 7 and any(m["updates_per_s"] > 0 for m in watcher.metrics), 90,
                 "version 7 and a report of training", learner)
    assert learner.stop(signal.SIGTERM) == 0, learner.log()
    assert actor.stop(signal.SIGTERM) == 0, actor.log()

    assert watcher.versions == sorted(set(watcher.versions)), "versions must rise"
    config = TD3Config(exploration_std_start=1.0, exploration_std_end=0.1, exploration_std_updates=100)
    with watcher._lock:
        last = watcher.last
    assert float(last.params["exploration_std"]) == pytest.approx(exploration_std(config, 20 * (last.version - 1)))
    assert last.spec["kind"] == "deterministic"
    # The actor acted with the published policies (no warm-up) and took every one it was sent.
    assert re.search(r"policy version \d+ in use", actor.log()) and "rejected" not in actor.log()
    trained = [m for m in watcher.metrics if m["updates_per_s"] > 0]
    assert trained and all(np.isfinite(m["critic_loss"]) for m in trained), trained
    assert any(np.isfinite(m.get("actor_loss", np.nan)) for m in trained)
    assert "critic " in learner.log() and " std " in learner.log()

    saved = load_checkpoint(run_dir)  # written on SIGTERM, after the last publication
    assert saved.algo == "td3" and isinstance(saved.config, TD3Config) and saved.version == last.version
    assert saved.config.n_step == 3 and "rejected" not in learner.log()
    assert saved.updates >= 120 and isinstance(saved.policy(), DeterministicPolicy)
    evaluation = subprocess.run([sys.executable, "-m", "l2r.cli", "eval", str(run_dir), "--episodes", "1",
                                 "--json", "--action-repeat", "1", "--env-id", "tests.actors.standin:StandIn-v0"],
                                cwd=ROOT,
                                capture_output=True, text=True, timeout=120)
    assert evaluation.returncode == 0, evaluation.stderr
    assert json.loads(evaluation.stdout)["lengths"] == [40]  # the stand-in's episodes last 40 steps
