"""`l2r up --algo a3c` end to end on Hopper-v5: real replay, learner and actor processes over
loopback Zenoh; the actor's gradients reach the learner, whose version advances by one for each
one applied, and the run leaves an A3C checkpoint."""

import json
import uuid

import pytest

from l2r.learner.checkpoint import load_checkpoint
from tests.system.test_up import finish, l2r_up, rows


@pytest.mark.slow
def test_an_a3c_job_trains_on_the_actors_gradients(tmp_path):
    name = f"test-{uuid.uuid4().hex[:6]}"
    proc = l2r_up(tmp_path / "up.out", "--env-id", "Hopper-v5", "--algo", "a3c", "--env-steps", "200", "--seconds", "240",
                  "--name", name,
                  "--runs-dir", str(tmp_path), "--actors", "1", "--evaluators", "0", "--status-interval", "1",
                  "--hidden", "16,16", "--learner-arg=--checkpoint-interval=3")
    out = finish(proc, tmp_path / "up.out", 300)
    assert proc.returncode == 0, out
    run_dir = next(tmp_path.glob(f"{name}-*"))
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["updates"] > 0, out
    saved = load_checkpoint(run_dir / "learner" / "checkpoint.pt")
    # One publication before the first gradient, then one after each gradient applied.
    assert saved.algo == "a3c" and saved.train_state["version"] == saved.train_state["updates"] + 1 > 1
    actor = [r for r in rows(run_dir / "metrics" / "actors.csv") if r["role"] == "actor"][-1]
    assert int(actor["gradients_sent"]) >= saved.train_state["updates"] and int(actor["chunks_sent"]) == 0
    assert int(actor["rollouts_without_gradient"]) == 0  # no random steps before the first weights
