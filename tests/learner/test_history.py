"""An observation history for the float32 vector (SAC and TD3 with --frame-stack k): the policy
spec, the filter and the mirror per observation, the learner's flags, and the whole loop through
real daemons: an actor acting on its last k observations, the replay stacking them when it
samples, the learner training on the stacks, `l2r eval` of its checkpoint."""

import json
import re
import signal
import subprocess
import sys

import numpy as np
import pytest
import torch

from l2r.learner.__main__ import UsageError, parse_settings
from l2r.learner.checkpoint import load_checkpoint
from l2r.learner.sac import Batch, SACConfig, init_state, prepare
from l2r.policy import ObservationFilter, check_spec, default_spec
from l2r.sim import layout
from tests.conftest import ROOT
from tests.learner.conftest import WeightsWatcher, learner_args

K = 3
RUNNER_OPTIONS = ["--relative-x", "--normalize-obs", "--mirror"]


def test_a_vector_spec_says_its_history_and_without_one_keeps_the_form_it_always_had():
    spec = {**default_spec(41, 18), "frame_stack": K}
    assert check_spec(spec) == spec and "observation" not in check_spec(spec)
    assert check_spec({**default_spec(41, 18), "frame_stack": 1}) == default_spec(41, 18)
    assert init_state(SACConfig(hidden=(8,), frame_stack=K), 41, 18).actor.spec["frame_stack"] == K
    with pytest.raises(ValueError, match="frame_stack"):
        SACConfig(frame_stack=0)


def test_each_observation_of_a_stack_is_filtered_as_it_would_be_alone():
    stacked, alone = ObservationFilter(41, True, True, frames=K), ObservationFilter(41, True, True)
    rng = np.random.default_rng(0)
    frames = torch.as_tensor(rng.normal(3.0, 2.0, (16, K, 41)), dtype=torch.float32)
    stacked.update(frames.flatten(1))
    alone.update(frames.flatten(0, 1))  # the same observations, one a row
    assert int(stacked.count) == 16 * K
    torch.testing.assert_close(stacked.mean, alone.mean) and torch.testing.assert_close(stacked.var, alone.var)
    torch.testing.assert_close(stacked(frames.flatten(1)), alone(frames.flatten(0, 1)).reshape(16, K * 41))
    # relative_x measures each observation's x coordinates from its own pelvis
    first = stacked(frames.flatten(1)).unflatten(1, (K, 41))
    torch.testing.assert_close(first[:, 1], alone(frames[:, 1]))


def test_the_mirror_swaps_the_legs_of_every_observation_of_a_stack():
    state = init_state(SACConfig(hidden=(8,), mirror=True, frame_stack=K), 41, 18, seed=0)
    rng = np.random.default_rng(1)
    obs, next_obs = (torch.as_tensor(rng.normal(size=(256, K * 41)), dtype=torch.float32) for _ in range(2))
    action = torch.as_tensor(rng.uniform(-1, 1, (256, 18)), dtype=torch.float32)
    batch = prepare(state, Batch(obs, action, torch.zeros(256), next_obs, torch.zeros(256)), SACConfig(mirror=True))
    swapped = ~torch.all(batch.action == action, dim=1)
    assert 64 < int(swapped.sum()) < 192  # about half
    by_frame = obs.unflatten(1, (K, 41))[:, :, layout.MIRROR_OBS].flatten(1)
    torch.testing.assert_close(batch.obs[swapped], by_frame[swapped])
    torch.testing.assert_close(batch.obs[~swapped], obs[~swapped])
    torch.testing.assert_close(batch.next_obs[swapped],
                               next_obs.unflatten(1, (K, 41))[:, :, layout.MIRROR_OBS].flatten(1)[swapped])


def test_the_learner_takes_a_history_for_the_off_policy_algorithms_alone():
    assert parse_settings(["--frame-stack", "8"]).sac().frame_stack == 8
    assert parse_settings(["--algo", "td3", "--frame-stack", "8"]).td3().frame_stack == 8
    assert parse_settings([]).sac().frame_stack == 1
    with pytest.raises(UsageError, match="--frame-stack 4: stacks are sampled from the replay table, by SAC and "
                                         "TD3; --algo ppo takes one observation at a time"):
        parse_settings(["--algo", "ppo", "--frame-stack", "4"])


@pytest.mark.slow
def test_sac_trains_on_histories_an_actor_keeps_and_the_replay_stacks(network, tmp_path):
    run_dir = tmp_path / "run"
    watcher = WeightsWatcher(network.session, network.run)
    learner = network.start("l2r.learner", *learner_args(network, run_dir, "--frame-stack", str(K), *RUNNER_OPTIONS,
                                                         "--checkpoint-interval", "1"), name="learner")
    actor = network.start("l2r.actors", "--run", network.run, "--connect", network.endpoint, "--env-id",
                          "tests.actors.standin:StandIn-v0", "--num-envs", "4", "--chunk-size", "16",
                          "--random-steps", "0", name="actor")
    watcher.wait(lambda v: v and v[-1] >= 5, 90, "version 5", learner)
    assert learner.stop(signal.SIGTERM) == 0, learner.log()
    assert actor.stop(signal.SIGTERM) == 0, actor.log()

    with watcher._lock:
        last = watcher.last
    assert last.spec["obs_dim"] == 41 and last.spec["frame_stack"] == K
    assert last.params["trunk.0.weight"].shape == (32, 41 * K)
    # The actor acted with the published policies, on its stacks, and took every one it was sent.
    assert re.search(r"policy version \d+ in use", actor.log()) and "rejected" not in actor.log()
    assert "rejected" not in learner.log(), learner.log()
    saved = load_checkpoint(run_dir)
    assert saved.policy_spec == last.spec and saved.config.frame_stack == K and saved.updates >= 80
    evaluation = subprocess.run([sys.executable, "-m", "l2r.cli", "eval", str(run_dir), "--episodes", "1",
                                 "--json", "--action-repeat", "1", "--env-id", "tests.actors.standin:StandIn-v0"],
                                cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert evaluation.returncode == 0, evaluation.stderr
    assert json.loads(evaluation.stdout)["lengths"] == [40]
