"""`l2r eval` steps the env with the action repeat training used, read from the checkpoint, prints
each episode's score in its task family's terms (the runner's distance, another task's return),
and says clearly when there is no checkpoint or it is another task's."""

import json
import re
import subprocess
import sys

import torch

from l2r.actors.actor import ActorConfig, make_env, run_deterministic
from l2r.evaluate import evaluate
from l2r.learner.checkpoint import checkpoint_path, load_checkpoint, save_checkpoint
from l2r.learner.sac import SACConfig, init_state
from tests.conftest import ROOT


def l2r_eval(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "l2r.cli", "eval", *argv], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)


def test_eval_uses_the_action_repeat_stored_in_the_checkpoint(tmp_path):
    config = SACConfig(hidden=(16,), precision="float32")
    save_checkpoint(checkpoint_path(tmp_path), init_state(config, 41, 18, seed=0), config, 41, 18, action_repeat=5)
    run = l2r_eval(str(tmp_path), "--episodes", "1", "--json")
    assert run.returncode == 0, run.stderr
    result = json.loads(run.stdout)
    assert result["action_repeat"] == 5

    torch.set_num_threads(1)
    policy = load_checkpoint(tmp_path).policy()
    stepped_by_5 = evaluate(policy, 1, 0, 0, action_repeat=5)[0]
    assert (result["returns"][0], result["distances"][0], result["lengths"][0]) == stepped_by_5[:3]
    assert evaluate(policy, 1, 0, 0, action_repeat=3)[0] != stepped_by_5  # the repeat shows in the result


def test_eval_reports_a_missing_checkpoint_clearly(tmp_path):
    run = l2r_eval(str(tmp_path))
    assert run.returncode == 1 and "no learner checkpoint" in run.stderr


def hopper_checkpoint(directory):
    config = SACConfig(hidden=(16,), precision="float32")
    save_checkpoint(checkpoint_path(directory), init_state(config, 11, 3, seed=0), config, 11, 3, action_repeat=1)


def test_eval_of_a_standard_task_prints_returns_measured_as_its_evaluators_measure_them(tmp_path):
    hopper_checkpoint(tmp_path)
    run = l2r_eval(str(tmp_path), "--env-id", "Hopper-v5", "--episodes", "2", "--json")
    assert run.returncode == 0, run.stderr
    result = json.loads(run.stdout)
    assert result["score"] == "return" and result["mean_return"] == sum(result["returns"]) / 2
    # An evaluator of `l2r up --env-id Hopper-v5`: the task rescaled to the policy's actions, no blow-up check.
    torch.set_num_threads(1)
    envs = [make_env(ActorConfig(env_id="Hopper-v5", action_repeat=1), seed=0) for _ in range(2)]
    evaluator = run_deterministic(load_checkpoint(tmp_path).policy(), envs, [0, 1], max_speed=0)
    assert list(zip(result["returns"], result["distances"], result["lengths"])) == [
        (e.episode_return, e.distance, e.length) for e in evaluator]

    run = l2r_eval(str(tmp_path), "--env-id", "Hopper-v5", "--episodes", "2")
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert lines[1] == f"episode 0 (seed 0): return {result['returns'][0]:7.3f}  steps {result['lengths'][0]}"
    assert lines[-1] == f"mean return {result['mean_return']:.3f} over 2 episodes"
    assert "distance" not in run.stdout and "difficulty" not in run.stdout


def test_eval_of_the_runner_prints_distances(tmp_path):
    config = SACConfig(hidden=(16,), precision="float32")
    save_checkpoint(checkpoint_path(tmp_path), init_state(config, 41, 18, seed=0), config, 41, 18, action_repeat=3)
    run = l2r_eval(str(tmp_path), "--episodes", "1")
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert re.fullmatch(r"episode 0 \(seed 0\): distance +-?\d+\.\d{3} m  return +-?\d+\.\d{3}  steps \d+", lines[1])
    assert re.fullmatch(r"mean distance -?\d+\.\d{3} m over 1 episodes", lines[-1])


def test_eval_says_when_the_checkpoint_is_another_task_s(tmp_path):
    hopper_checkpoint(tmp_path)
    run = l2r_eval(str(tmp_path), "--episodes", "1")  # the runner, by default
    assert run.returncode == 1
    assert ("the policy takes observations {state: float32[11]} and gives 3 actions, l2r/Run-v0 gives "
            "{state: float32[41]} and takes 18") in run.stderr
    assert "Traceback" not in run.stderr
