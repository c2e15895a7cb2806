"""`l2r up` on a camera task, end to end: real replay, learner, actor and evaluator processes over
loopback Zenoh, the actors rendering a small cartpole (tests.actors.camera), the learner training
TD3 (DrQ-v2) or SAC (DrQ) on stacks of its frames with the pixels recipes, and `l2r eval` acting on what it leaves."""

import json
import re
import subprocess
import sys
import uuid

import pytest

from tests.actors.camera import CAMERA, RENDERER
from tests.conftest import ROOT
from tests.system.test_up import finish, l2r_up, rows

pytestmark = [pytest.mark.slow, pytest.mark.skipif(not RENDERER, reason="no EGL or OSMesa to render with")]


@pytest.mark.parametrize("algo", ["td3", "sac"])
def test_a_camera_task_trains_on_stacked_frames_and_its_checkpoint_evaluates(tmp_path, algo):
    name = f"test-{uuid.uuid4().hex[:6]}"
    proc = l2r_up(tmp_path / "up.out", "--env-id", CAMERA, "--algo", algo, "--recipe", "pixels", "--env-steps", "300",
                  "--seconds", "300", "--name", name, "--runs-dir", str(tmp_path), "--hidden", "32,32",
                  "--batch-size", "16", "--samples-per-insert", "4", "--random-steps", "100", "--min-replay", "100",
                  "--publish-every", "5", "--eval-episodes", "2", "--eval-interval", "0", "--status-interval", "2",
                  "--learner-arg=--checkpoint-interval=3")
    out = finish(proc, tmp_path / "up.out", 300)
    assert proc.returncode == 0, out
    run_dir = next(tmp_path.glob(f"{name}-*"))
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["env_steps"] >= 300 and summary["updates"] > 0, summary
    assert "frames/s" in out  # the status line counts the camera's frames

    logs = run_dir / "logs"
    assert "observation {pixels: uint8[3, 16, 16]}" in (logs / "replay.log").read_text()
    # The actor's warm-up ran its course, then it acted on stacks with the learner's image policy.
    assert "warm-up over after 100 random steps" in (logs / "actor-0.log").read_text()
    assert "bad_spec" not in (logs / "actor-0.log").read_text() + (logs / "evaluator-0.log").read_text()
    # Every round reached l2r up, the first too (sent as the evaluator joins: v1, or a later version
    # where the evaluator started after the learner had sent more), and a trained image policy was
    # among them (each new version is evaluated: --eval-interval 0).
    evaluated = [int(r["version"]) for r in rows(run_dir / "metrics" / "evaluation.csv")]
    first_round = int(re.search(r"evaluation of policy v(\d+)", (logs / "evaluator-0.log").read_text())[1])
    assert evaluated[:2] == [first_round, first_round] and max(evaluated) > 1, (first_round, evaluated)

    ev = subprocess.run([sys.executable, "-m", "l2r.cli", "eval", str(run_dir), "--env-id", CAMERA, "--episodes", "1",
                         "--json"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert ev.returncode == 0, ev.stderr
    assert len(json.loads(ev.stdout)["returns"]) == 1
