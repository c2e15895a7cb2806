"""A TD3 (DrQ-v2) and a SAC (DrQ) learner on image observations through real daemons over loopback Zenoh: an l2r-replay
storing 24 x 24 frames, a feeder sending it random image chunks, and l2r-learner --observation
sampling stacks of frames from it, training, publishing and checkpointing."""

import signal

import pytest

from l2r.learner.checkpoint import load_checkpoint
from l2r.protocol import ObservationSpec
from tests.learner.conftest import Feeder, WeightsWatcher, learner_args

PIXELS = ObservationSpec.parse("pixels: uint8[3, 24, 24]")
ACT = 2


@pytest.mark.slow
@pytest.mark.parametrize("network", [["--observation", str(PIXELS), "--act-dim", str(ACT)]], indirect=True)
@pytest.mark.parametrize("algorithm", [["td3", "--n-step", "3"], ["sac"]], ids=["td3", "sac"])
def test_trains_on_stacks_of_frames_sampled_from_an_image_shard(network, tmp_path, algorithm):
    run_dir = tmp_path / "run"
    feeder = Feeder(network.session, network.run, chunk=20, observation=PIXELS, act_dim=ACT)
    watcher = WeightsWatcher(network.session, network.run)
    learner = network.start("l2r.learner", *learner_args(
        network, run_dir, "--algo", *algorithm, "--observation", str(PIXELS), "--act-dim", str(ACT),
        "--batch-size", "16", "--checkpoint-interval", "1"), name="learner")
    try:
        watcher.wait(lambda v: v and v[-1] >= 3, 90, "version 3", learner)
        assert learner.stop(signal.SIGTERM) == 0, learner.log()
    finally:
        feeder.stop()

    with watcher._lock:
        last = watcher.last
    assert ObservationSpec.from_policy_spec(last.spec) == PIXELS and last.spec["frame_stack"] == 3
    assert "obs_dim" not in last.spec and any(name.startswith("encoder.") for name in last.params)
    assert "rejected" not in learner.log(), learner.log()
    saved = load_checkpoint(run_dir)
    assert saved.policy_spec == last.spec and saved.config.augment_pad == 4 and saved.updates >= 40
