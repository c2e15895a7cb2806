"""The real l2r-learner process against a real l2r-replay process over loopback Zenoh."""

import signal
import time

import numpy as np
import pytest
import torch

from l2r.learner.checkpoint import load_checkpoint
from l2r.policy import act, build_policy, load_policy_state
from l2r.protocol import Keys, Stats, Weights, decode
from l2r.protocol.session import wait_alive

from tests.conftest import free_port, wait_for
from tests.learner.conftest import Feeder, WeightsWatcher, learner_args


def checkpointed_updates(run_dir) -> int:
    return load_checkpoint(run_dir).updates if (run_dir / "learner/checkpoint.pt").exists() else 0


@pytest.mark.slow
def test_learner_trains_publishes_versions_and_resumes_after_a_kill(network, tmp_path):
    run_dir = tmp_path / "run"
    feeder = Feeder(network.session, network.run)
    watcher = WeightsWatcher(network.session, network.run)
    try:
        first = network.start("l2r.learner", *learner_args(network, run_dir, "--checkpoint-interval", "0.5"),
                              name="learner1")
        # Hundreds of updates (20 per version) and a periodic checkpoint holding 200 of them: a fast
        # learner runs 0.5 s of updates past its newest checkpoint, so the version alone says too little.
        watcher.wait(lambda v: v and v[-1] >= 15 and checkpointed_updates(run_dir) >= 200,
                     90, "version 15 and a checkpoint of 200 updates", first)
        first.stop(signal.SIGKILL)  # no chance to checkpoint on exit: the periodic one must do
        versions_before = list(watcher.versions)
        assert versions_before == sorted(set(versions_before)), "versions must increase"
        saved = load_checkpoint(run_dir)
        assert saved.updates >= 200 and 1 <= saved.version <= versions_before[-1]
        assert any(m["updates_per_s"] > 0 and np.isfinite(m["critic_loss"]) and 0 <= m["wait_fraction"] <= 1
                   for m in watcher.metrics)

        second = network.start("l2r.learner", *learner_args(network, run_dir, "--resume",
                                                             "--checkpoint-interval", "60"), name="learner2")
        watcher.wait(lambda v: len(v) >= len(versions_before) + 3, 60, "versions after resuming", second)
        resumed = watcher.versions[len(versions_before):]
        # A new publisher's first put can miss a subscriber it has not discovered yet, so the first
        # version seen may be saved.version + 2; the log says where it continued from.
        assert f"version {saved.version}, {saved.updates} updates" in second.log()
        assert resumed[0] > saved.version and resumed == sorted(set(resumed)), resumed

        # A joining actor asks for the latest weights and can act with them.
        replies = [r.ok for r in network.session.get(Keys(network.run).weights_query, timeout=5) if r.ok]
        latest = decode(replies[0].payload, Weights)
        assert latest.version >= resumed[0]
        policy = build_policy(latest.spec)
        load_policy_state(policy, latest.params)
        actions = act(policy, np.zeros((2, 41), np.float32))
        assert actions.shape == (2, 18) and ((0 <= actions) & (actions <= 1)).all()

        assert second.stop(signal.SIGTERM) == 0, second.log()
        final = load_checkpoint(run_dir)  # written on SIGTERM, after the last publication
        assert final.version == watcher.versions[-1] and final.updates > saved.updates
    finally:
        feeder.stop()


@pytest.mark.slow
def test_a_learner_without_a_checkpoint_publishes_above_the_versions_the_replay_holds(network, tmp_path):
    # The replay holds experience of version 40, as after a run whose learner lost its checkpoint.
    feeder = Feeder(network.session, network.run, policy_version=40)
    watcher = WeightsWatcher(network.session, network.run)
    try:
        assert wait_for(lambda: replay_stats(network).get("newest_version") == 40, timeout=30), replay_stats(network)
        learner = network.start("l2r.learner", *learner_args(network, tmp_path / "run"), name="learner")
        watcher.wait(lambda v: len(v) >= 3 and any(m["samples_per_s"] > 0 for m in watcher.metrics), 90,
                     "versions and a report of sampled batches", learner)
        assert min(watcher.versions) > 40, watcher.versions
        lags = [m["policy_lag"] for m in watcher.metrics if m["samples_per_s"] > 0]
        assert lags and min(lags) >= 0, lags
        assert "the run's replay has seen policy version 40: going on above it, not from 0" in learner.log()
        assert learner.stop() == 0
    finally:
        feeder.stop()


def replay_stats(network) -> dict:
    replies = [r.ok for r in network.session.get(Keys(network.run).stats("replay", 0), timeout=5) if r.ok]
    return decode(replies[0].payload, Stats).values if replies else {}


@pytest.mark.slow
def test_learner_waits_through_a_replay_restart(network, tmp_path):
    feeder = Feeder(network.session, network.run)
    watcher = WeightsWatcher(network.session, network.run)
    try:
        # Prioritized sampling here, so priority updates flow back to the server too.
        learner = network.start("l2r.learner", *learner_args(network, tmp_path / "run", "--prioritized"),
                                name="learner")
        assert wait_alive(network.session, Keys(network.run).alive("learner", 0), timeout=30), learner.log()
        watcher.wait(lambda v: len(v) >= 3, 60, "training before the restart", learner)
        assert network.replay.stop(signal.SIGTERM) == 0
        time.sleep(1.0)
        assert learner.proc.poll() is None, learner.log()
        replay = network.start_replay()
        seen = len(watcher.versions)
        watcher.wait(lambda v: len(v) >= seen + 3, 60, "training after the restart", learner)
        assert learner.stop() == 0
        assert all("rejected message" not in daemon.log() for daemon in (learner, network.replay, replay))
    finally:
        feeder.stop()


@pytest.mark.slow
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_a_gpu_learner_trains_with_its_updates_as_one_cuda_graph(network, tmp_path):
    # Batches staged ahead on the GPU, prioritized (priorities read back each batch), mirrored and
    # normalised (both change the batch and the statistics outside the graph), the graph replayed.
    run_dir = tmp_path / "run"
    feeder = Feeder(network.session, network.run)
    watcher = WeightsWatcher(network.session, network.run)
    try:
        learner = network.start("l2r.learner", *learner_args(network, run_dir, "--device", "cuda", "--compile",
                                                             "graphs", "--prioritized", "--mirror", "--normalize-obs"),
                                name="learner")
        watcher.wait(lambda v: len(v) >= 6 and any(m["updates_per_s"] > 0 for m in watcher.metrics), 90,
                     "versions and a metrics report from the graphed learner", learner)
        assert learner.stop() == 0, learner.log()
        assert "compile graphs" in learner.log()
        assert load_checkpoint(run_dir).updates >= 100
        reports = [m for m in watcher.metrics if m["updates_per_s"] > 0]
        assert reports and all(np.isfinite(m["critic_loss"]) and 0 <= m["wait_fraction"] <= 1 for m in reports)
    finally:
        feeder.stop()


@pytest.mark.slow
def test_two_data_parallel_learners_train_and_stop_together(network, tmp_path):
    run_dir = tmp_path / "run"
    url = f"tcp://127.0.0.1:{free_port()}"
    feeder = Feeder(network.session, network.run)
    watcher = WeightsWatcher(network.session, network.run)
    try:
        ranks = [network.start("l2r.learner", *learner_args(network, run_dir, "--world-size", "2", "--rank", str(r),
                                                            "--dist-url", url), name=f"rank{r}") for r in range(2)]
        watcher.wait(lambda v: len(v) >= 4, 90, "versions from rank 0", ranks[0])
        assert ranks[1].stop(signal.SIGTERM) == 0, ranks[1].log()  # stopping one rank stops both
        assert ranks[0].proc.wait(30) == 0, ranks[0].log()
        assert "rank 1 on cpu" in ranks[1].log()
        assert load_checkpoint(run_dir).version == watcher.versions[-1]  # rank 0 wrote it last
    finally:
        feeder.stop()


@pytest.mark.slow
def test_a_diverging_learner_stops_without_overwriting_its_checkpoint(network, tmp_path):
    run_dir = tmp_path / "run"
    feeder = Feeder(network.session, network.run)
    try:
        # Rewards scaled past float32's range make the critics' targets infinite at once, however many.
        learner = network.start("l2r.learner", *learner_args(network, run_dir, "--reward-scale", "1e39",
                                                             "--precision", "float32", "--critics", "3",
                                                             "--critics-in-min", "2", "--n-step", "2"),
                                name="learner")
        assert learner.proc.wait(60) == 1, learner.log()
        assert "NaN or infinity" in learner.log()
        assert "SAC with 3 critics (the least of 2) on 2-step returns rank 0" in learner.log()
        assert not (run_dir / "learner" / "checkpoint.pt").exists()
    finally:
        feeder.stop()
