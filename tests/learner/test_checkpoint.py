"""Checkpoints restore training exactly; the newest few are kept, readable by everyone and
durable; a policy alone can be saved; broken files give clear errors; device choice."""

import copy
import errno
import os
import stat
from unittest import mock

import numpy as np
import pytest
import torch

from l2r.learner.checkpoint import (
    CheckpointError, checkpoint_path, load_checkpoint, save_checkpoint, save_policy_checkpoint,
)
from l2r.learner.distributed import DeviceUnavailable, select_device
from l2r.learner.sac import SACConfig, batch_from_numpy, init_state, update
from l2r.learner.steps import GradientSteps
from l2r.policy import act, policy_state

OBS, ACT = 5, 3


def batch(seed: int):
    rng = np.random.default_rng(seed)
    return batch_from_numpy(rng.normal(size=(32, OBS)), rng.random((32, ACT)), rng.normal(size=32),
                            rng.normal(size=(32, OBS)), rng.random(32) < 0.1)


def test_round_trip_is_exact_and_training_continues_identically(tmp_path):
    config = SACConfig(hidden=(16, 16), precision="float32")
    state = init_state(config, OBS, ACT, seed=0)
    steps = GradientSteps(update, config)
    for step in range(3):
        steps(state, batch(step))
    state.version, state.extra = 7, {"samples": 96}
    save_checkpoint(checkpoint_path(tmp_path), state, config, OBS, ACT)

    saved = load_checkpoint(tmp_path)  # the run directory is enough
    assert (saved.version, saved.updates, saved.config) == (7, 3, config)
    restored = saved.restore()
    assert restored.extra == {"samples": 96}
    original = copy.deepcopy(state)
    torch.manual_seed(1)
    metrics_a = update(original, batch(9), config)
    torch.manual_seed(1)
    metrics_b = update(restored, batch(9), config)
    for name in metrics_a:  # same networks, optimizer moments, alpha: the same next step
        torch.testing.assert_close(metrics_a[name], metrics_b[name], rtol=0, atol=0)
    for key, value in original.actor.state_dict().items():
        assert torch.equal(value, restored.actor.state_dict()[key])
    obs = np.random.default_rng(2).normal(size=(4, OBS))
    np.testing.assert_array_equal(act(saved.policy(), obs, True), act(state.actor.eval(), obs, True))


def test_loading_keeps_the_optimizers_own_capturable_flag(tmp_path):
    # On CUDA the optimizers are capturable (common.adam), which a CUDA graph of the update needs;
    # a checkpoint saved on a CPU says capturable=False and must not turn it off when resumed there.
    config = SACConfig(hidden=(8,), precision="float32")
    saved = init_state(config, OBS, ACT, seed=0).state_dict()
    state = init_state(config, OBS, ACT)
    optimizers = (state.actor_opt, state.critic_opt, state.alpha_opt)
    for group in (group for opt in optimizers for group in opt.param_groups):
        group["capturable"] = True  # as on a GPU
    state.load_state_dict(saved)
    assert all(group["capturable"] for opt in optimizers for group in opt.param_groups)


def test_save_replaces_atomically_and_leaves_no_temporary_files(tmp_path):
    config = SACConfig(hidden=(8,), precision="float32")
    state = init_state(config, OBS, ACT)
    path = checkpoint_path(tmp_path)
    save_checkpoint(path, state, config, OBS, ACT)
    state.version = 2
    save_checkpoint(path, state, config, OBS, ACT)
    assert load_checkpoint(path).version == 2
    assert sorted(p.name for p in path.parent.iterdir()) == ["checkpoint.pt"]


def test_the_newest_checkpoints_are_kept_readable_by_everyone_with_the_action_repeat(tmp_path):
    config = SACConfig(hidden=(8,), precision="float32")
    state = init_state(config, OBS, ACT)
    path = checkpoint_path(tmp_path)
    for updates in (10, 20, 30, 40):
        state.updates = updates
        save_checkpoint(path, state, config, OBS, ACT, action_repeat=2, keep=3)
    files = sorted(path.parent.iterdir())
    assert [p.name for p in files] == ["checkpoint-0000000020.pt", "checkpoint-0000000030.pt",
                                       "checkpoint-0000000040.pt", "checkpoint.pt"]
    assert (load_checkpoint(path).updates, load_checkpoint(path).action_repeat) == (40, 2)
    assert load_checkpoint(path.parent / "checkpoint-0000000020.pt").updates == 20
    assert all(stat.S_IMODE(p.stat().st_mode) == 0o644 for p in files)


def test_a_save_fsyncs_the_directory_after_the_rename(tmp_path, monkeypatch):
    events = []
    real_replace, real_fsync = os.replace, os.fsync
    monkeypatch.setattr(os, "replace", lambda *a: (real_replace(*a), events.append("rename"))[0])
    monkeypatch.setattr(os, "fsync", lambda fd: (real_fsync(fd), events.append(
        "fsync directory" if stat.S_ISDIR(os.fstat(fd).st_mode) else "fsync file"))[0])
    config = SACConfig(hidden=(8,), precision="float32")
    save_checkpoint(checkpoint_path(tmp_path), init_state(config, OBS, ACT), config, OBS, ACT)
    assert events == ["fsync file", "rename", "fsync directory"]


def test_a_policy_alone_is_a_checkpoint_eval_reads_but_no_learner_resumes(tmp_path):
    config = SACConfig(hidden=(16,), precision="float32")
    state = init_state(config, OBS, ACT, seed=3)
    path = save_policy_checkpoint(tmp_path / "best.pt", policy_state(state.actor), dict(state.actor.spec),
                                  version=12, updates=600, action_repeat=4,
                                  evaluation={"mean_distance": 1.5, "episodes": 2})
    saved = load_checkpoint(path)
    assert (saved.version, saved.updates, saved.action_repeat, saved.config) == (12, 600, 4, None)
    assert saved.evaluation == {"mean_distance": 1.5, "episodes": 2}
    assert stat.S_IMODE(path.stat().st_mode) == 0o644
    obs = np.random.default_rng(0).normal(size=(3, OBS))
    np.testing.assert_array_equal(act(saved.policy(), obs, True), act(state.actor.eval(), obs, True))
    with pytest.raises(CheckpointError, match="holds a policy alone"):
        saved.restore()


def test_a_full_disk_is_an_oserror_that_says_so_and_the_previous_checkpoint_stays(small_disk):
    # Writers catch OSError by errno (l2r.durable.DISK_ERRORS); torch's zip writer, saving to the
    # file itself, turned ENOSPC into a RuntimeError from its cleanup.
    disk = small_disk(1)
    config = SACConfig(hidden=(16,), precision="float32")
    state = init_state(config, OBS, ACT, seed=3)
    path = save_policy_checkpoint(disk.path / "best.pt", policy_state(state.actor), dict(state.actor.spec),
                                  version=1, updates=10, action_repeat=1, evaluation={})
    disk.fill(leave=64 << 10)  # a write that fails part of the way, then room for torch's cleanup
    config = SACConfig(hidden=(128, 128), precision="float32")
    state = init_state(config, OBS, ACT, seed=3)
    for save in (lambda: save_policy_checkpoint(path, policy_state(state.actor), dict(state.actor.spec),
                                                version=2, updates=20, action_repeat=1, evaluation={}),
                 lambda: save_checkpoint(disk.path / "checkpoint.pt", state, config, OBS, ACT)):
        with pytest.raises(OSError) as refused:
            save()
        assert refused.value.errno == errno.ENOSPC
    assert load_checkpoint(path).version == 1
    assert sorted(p.name for p in disk.path.iterdir()) == ["ballast", "best.pt"]  # no temporary file left


def test_unusable_checkpoints_raise_clear_errors(tmp_path):
    with pytest.raises(CheckpointError, match="no learner checkpoint"):
        load_checkpoint(tmp_path)
    truncated = tmp_path / "cut.pt"
    config = SACConfig(hidden=(8,), precision="float32")
    save_checkpoint(truncated, init_state(config, OBS, ACT), config, OBS, ACT)
    truncated.write_bytes(truncated.read_bytes()[:1000])
    with pytest.raises(CheckpointError, match="cannot read"):
        load_checkpoint(truncated)
    foreign = tmp_path / "foreign.pt"
    torch.save({"hello": 1}, foreign)
    with pytest.raises(CheckpointError, match="not an l2r learner checkpoint"):
        load_checkpoint(foreign)


def test_device_selection():
    assert select_device("cpu") == torch.device("cpu")
    with mock.patch("torch.cuda.is_available", return_value=False):
        assert select_device("auto") == torch.device("cpu")
        with pytest.raises(DeviceUnavailable, match="no CUDA"):
            select_device("cuda")
    with mock.patch("torch.cuda.is_available", return_value=True), \
            mock.patch("torch.cuda.device_count", return_value=2):
        assert select_device("auto") == torch.device("cuda", 0)
        assert select_device("cuda", local_rank=3) == torch.device("cuda", 1)
    with pytest.raises(ValueError):
        select_device("tpu")
