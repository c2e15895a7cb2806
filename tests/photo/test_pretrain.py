"""The tuner's warm start from its random goals' hidden parameters (`l2r photo pretrain`): real
episodes of the task, the real command in a subprocess, and the learner that goes on from it."""

import json

import numpy as np
import pytest
import torch

from l2r.job_plan import plan_children
from l2r.learner.__main__ import parse_settings as learner_settings
from l2r.learner.checkpoint import load_checkpoint
from l2r.learner.daemon import _initial_state
from l2r.photo.pretrain import EVAL_SEED, Episodes, PretrainConfig, learning_rate, pretrain
from l2r.up import parse_args
from tests.photo.test_tune import l2r_photo

STATS_ID = "l2r/PhotoTuneStats-v0"
COMPARE_ID = "l2r/PhotoTuneCompare-v0"


@pytest.fixture
def one_thread():
    """Small networks: one torch thread, as the command runs them (two contend with the suite's other worker)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_the_policy_learns_the_answers_of_its_episodes_and_tunes_far_past_the_input(one_thread):
    torch.manual_seed(0)
    policy, evaluation = pretrain(PretrainConfig(env_id=STATS_ID, rounds=2, episodes=6, updates=150, eval_episodes=4),
                                  progress=lambda _line: None)
    episodes = Episodes(STATS_ID)
    untouched = [episodes.play(EVAL_SEED + i, lambda _obs, answer: np.zeros_like(answer), keep=False)
                 for i in range(4)]
    answered = [episodes.play(EVAL_SEED + i, lambda _obs, answer: answer, keep=False) for i in range(4)]
    # The neutral parameters leave the input (12 dB); the answer itself reaches the goal (100 dB, capped).
    assert np.mean(untouched) + 3.0 < evaluation["mean_psnr"] < np.mean(answered), (untouched, evaluation)
    assert policy.spec["kind"] == "deterministic"


def test_the_cosine_schedule_falls_from_the_learning_rate_to_nothing_over_a_round():
    cosine = PretrainConfig(lr=1e-3, updates=1000, lr_schedule="cosine")
    rates = [learning_rate(cosine, step) for step in range(1000)]
    assert rates[0] == pytest.approx(1e-3) and rates[500] == pytest.approx(5e-4) and rates[-1] < 1e-7
    assert all(later < earlier for earlier, later in zip(rates, rates[1:]))
    assert {learning_rate(PretrainConfig(lr=1e-3, updates=1000), step) for step in (0, 500, 999)} == {1e-3}
    with pytest.raises(ValueError, match="lr_schedule must be constant or cosine, got 'linear'"):
        PretrainConfig(lr_schedule="linear")


def test_the_steps_follow_the_schedule(one_thread):
    def weights(schedule: str) -> torch.Tensor:
        torch.manual_seed(0)
        policy, _ = pretrain(PretrainConfig(env_id=STATS_ID, episodes=2, updates=20, eval_episodes=1,
                                            lr_schedule=schedule), progress=lambda _line: None)
        return torch.cat([p.detach().flatten() for p in policy.parameters()])

    # The same episodes and batches (the seed's), so only the rates of the steps tell them apart.
    assert torch.equal(weights("cosine"), weights("cosine"))
    assert not torch.allclose(weights("constant"), weights("cosine"))


def test_the_workers_play_the_episodes_one_process_would(one_thread):
    """Two rounds, so that the workers also play the policy's own queries (DAgger), with its weights of the time."""
    def learnt(workers: int) -> tuple[torch.Tensor, dict]:
        torch.manual_seed(0)
        policy, evaluation = pretrain(PretrainConfig(env_id=STATS_ID, rounds=2, episodes=6, updates=20, eval_episodes=2,
                                                     workers=workers), progress=lambda _line: None)
        return torch.cat([p.detach().flatten() for p in policy.parameters()]), evaluation

    (alone, here), (shared, there) = learnt(1), learnt(2)
    assert torch.equal(alone, shared)
    assert (here["mean_psnr"], here["losses"], here["observations"]) == \
        (there["mean_psnr"], there["losses"], there["observations"])


@pytest.mark.parametrize("residual", [False, True])
def test_the_command_writes_a_checkpoint_compare_runs_and_the_recipe_s_learner_starts_from(tmp_path, residual):
    out = tmp_path / "tuner.pt"
    run = l2r_photo("pretrain", "--out", str(out), "--env-id", COMPARE_ID, "--rounds", "1", "--episodes", "2",
                    "--updates", "5", "--eval-episodes", "1", "--source-variety", "0.3", "--json",
                    *(["--residual"] if residual else []))
    assert run.returncode == 0, run.stderr
    result = json.loads(run.stdout)
    assert result["checkpoint"] == str(out) and result["env_id"] == COMPARE_ID and result["source_variety"] == 0.3
    # The compare view's state: 2 x 25 image features, 40 compared, then the 9 parameters at 90.
    assert result["residual_from"] == (90 if residual else None)
    assert "round 1/1: 20 observations" in run.stderr
    # Long work says how far it is: each tenth of the episodes and of the steps, the last aside.
    assert "round 1/1: 1 of 2 episodes played" in run.stderr and "round 1/1: 4 of 5 steps, loss" in run.stderr
    assert "2 of 2 episodes" not in run.stderr and "5 of 5 steps" not in run.stderr
    saved = load_checkpoint(out)
    assert saved.evaluation["score"] == "psnr" and saved.evaluation["mean_psnr"] == result["psnr_db"]
    compared = l2r_photo("compare", "--checkpoint", str(out), "--photos", "1", "--budgets", "10", "--json")
    assert compared.returncode == 0, compared.stderr
    assert json.loads(compared.stdout)["policy_psnr_db"] is not None
    # l2r up's photo/td3 learner takes it as its policy: the same networks, the critics fresh.
    args, _ = parse_args(["--env-id", COMPARE_ID, "--algo", "td3", "--init-from", str(out),
                          *(["--learner-arg=--residual-from=90"] if residual else [])])
    learner = next(c for c in plan_children(args, "run", tmp_path / "run", [7447], 7448) if c.name == "learner")
    settings = learner_settings(learner.argv[3:])
    state = _initial_state(settings.learner(), settings.algorithm(), torch.device("cpu"))
    assert all(torch.equal(a, b) for a, b in zip(state.actor.state_dict().values(),
                                                 saved.policy().state_dict().values()))
    assert state.actor.spec.get("residual") == result["residual_from"] == saved.policy_spec.get("residual")


@pytest.mark.parametrize("argv, message", [
    (["--out", "/nonexistent/tuner.pt"], "/nonexistent: no such directory for --out"),
    (["--out", "x.pt", "--rounds", "0"],
     "rounds, episodes, updates, batch_size, eval_episodes and workers must be at least 1"),
    (["--out", "x.pt", "--workers", "0"],
     "rounds, episodes, updates, batch_size, eval_episodes and workers must be at least 1"),
    (["--out", "x.pt", "--source-variety", "1.5"], "source_variety must be in [0, 1], got 1.5"),
])
def test_the_command_says_in_one_line_what_is_wrong(argv, message):
    run = l2r_photo("pretrain", *argv)
    assert run.returncode == 1 and run.stderr.strip() == f"l2r photo pretrain: {message}"
