"""A learner started from another run's checkpoint (--init-from): staged training and warm starts."""

import numpy as np
import pytest
import torch

from l2r.config import EXIT_CANNOT_START
from l2r.learner import sac, td3
from l2r.learner.__main__ import cli
from l2r.learner.checkpoint import CheckpointError, checkpoint_path, save_checkpoint, save_policy_checkpoint
from l2r.learner.daemon import LearnerConfig, _initial_state
from l2r.policy import policy_state

OBS, ACT = 5, 3
SAC = sac.SACConfig(hidden=(32, 32), batch_size=16, precision="float32")
TD3 = td3.TD3Config(hidden=(32, 32), batch_size=16, precision="float32")


def trained(module, config, seed: int):
    """A state a few updates from its initialisation, so that nothing in it is as a fresh one's."""
    state = module.init_state(config, OBS, ACT, seed=seed)
    rng = np.random.default_rng(seed)
    for _ in range(3):
        batch = sac.batch_from_numpy(rng.normal(size=(16, OBS)), rng.random((16, ACT)), rng.normal(size=16),
                                     rng.normal(size=(16, OBS)), np.zeros(16))
        if module is td3:
            td3.update(state, batch, config, actor_step=True)
        else:
            sac.update(state, batch, config)
    state.updates, state.version = 3, 2  # the daemon's counts
    return state


def started(tmp_path, config, **learner) -> object:
    settings = LearnerConfig(run_dir=tmp_path / "new", obs_dim=OBS, act_dim=ACT, seed=0, **learner)
    return _initial_state(settings, config, torch.device("cpu"))


def same(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    return all(torch.equal(x, y) for x, y in zip(a.state_dict().values(), b.state_dict().values()))


def test_a_training_checkpoint_gives_its_networks_optimizers_and_counters(tmp_path):
    before = trained(sac, SAC, seed=1)
    save_checkpoint(checkpoint_path(tmp_path / "old"), before, SAC, OBS, ACT)
    state = started(tmp_path, SAC, init_from=tmp_path / "old")  # a run directory names its checkpoint
    assert same(state.actor, before.actor) and same(state.critic, before.critic)
    assert same(state.target_critic, before.target_critic)
    assert torch.equal(state.log_alpha, before.log_alpha)
    assert (state.updates, state.version) == (3, 2)
    assert state.critic_opt.state_dict()["state"], "the critics' Adam moments came with them"


def test_a_policy_checkpoint_gives_the_policy_alone_to_the_actor_and_its_target(tmp_path):
    before = trained(td3, TD3, seed=1)
    best = save_policy_checkpoint(tmp_path / "best.pt", policy_state(before.actor), before.actor.spec, version=9,
                                  updates=3, action_repeat=1, evaluation={"score": "return"})
    fresh = started(tmp_path, TD3)
    state = started(tmp_path, TD3, init_from=best)
    assert same(state.actor, before.actor) and same(state.target_actor, before.actor)
    assert same(state.critic, fresh.critic) and not same(state.critic, before.critic)
    assert state.updates == 0


def test_a_runs_own_checkpoint_comes_before_init_from_on_resume(tmp_path):
    other, own = trained(sac, SAC, seed=1), trained(sac, SAC, seed=2)
    save_checkpoint(checkpoint_path(tmp_path / "old"), other, SAC, OBS, ACT)
    assert same(started(tmp_path, SAC, resume=True, init_from=tmp_path / "old").actor, other.actor)
    save_checkpoint(checkpoint_path(tmp_path / "new"), own, SAC, OBS, ACT)
    assert same(started(tmp_path, SAC, resume=True, init_from=tmp_path / "old").actor, own.actor)


@pytest.mark.parametrize("saved, config, refusal", [
    ("sac", sac.SACConfig(hidden=(64, 64), precision="float32"), "holds a network of"),
    ("sac", sac.SACConfig(hidden=(32, 32), critics=4, precision="float32"), "holds 2 critics, the settings ask for 4"),
    ("sac", TD3, "not a TD3 training state: use --algo sac"),
    ("td3 policy", SAC, "holds a network of"),  # a deterministic policy is no tanh-Gaussian one
])
def test_a_checkpoint_of_other_networks_is_refused_in_one_line(tmp_path, saved, config, refusal):
    if saved == "sac":
        path = save_checkpoint(checkpoint_path(tmp_path / "old"), trained(sac, SAC, seed=1), SAC, OBS, ACT)
    else:
        actor = trained(td3, TD3, seed=1).actor
        path = save_policy_checkpoint(tmp_path / "best.pt", policy_state(actor), actor.spec, 1, 3, 1, {})
    with pytest.raises(CheckpointError, match=refusal) as refused:
        started(tmp_path, config, init_from=path)
    assert str(refused.value).endswith("or another --init-from")


def test_the_learner_command_refuses_a_missing_or_foreign_checkpoint_before_it_starts(tmp_path, capsys):
    path = save_checkpoint(checkpoint_path(tmp_path / "old"), trained(sac, SAC, seed=1), SAC, OBS, ACT)
    argv = ["--run", "x", "--run-dir", str(tmp_path / "new"), "--device", "cpu", "--obs-dim", str(OBS),
            "--act-dim", str(ACT), "--connect", "tcp/127.0.0.1:9"]
    assert cli([*argv, "--hidden", "64,64", "--init-from", str(path)]) == EXIT_CANNOT_START
    assert "use the same architecture flags, or another --init-from" in capsys.readouterr().err
    assert cli([*argv, "--init-from", str(tmp_path / "nothing.pt")]) == EXIT_CANNOT_START
    assert "no such checkpoint" in capsys.readouterr().err
