"""`l2r eval` steps the env with the action repeat training used, read from the checkpoint, and
says clearly when there is no checkpoint."""

import json
import subprocess
import sys

import torch

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
    assert (result["returns"][0], result["distances"][0], result["lengths"][0]) == stepped_by_5
    assert evaluate(policy, 1, 0, 0, action_repeat=3)[0] != stepped_by_5  # the repeat shows in the result


def test_eval_reports_a_missing_checkpoint_clearly(tmp_path):
    run = l2r_eval(str(tmp_path))
    assert run.returncode == 1 and "no learner checkpoint" in run.stderr
