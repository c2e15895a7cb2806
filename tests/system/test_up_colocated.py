"""`l2r up --colocated`: the learner steps the training worlds itself, with no replay server and
no training actors; evaluators as ever. What it plans, what it refuses, and a real job."""

import json
import signal
import uuid
from pathlib import Path

import pytest

from l2r.actors.__main__ import parse_settings as actor_settings
from l2r.job_plan import plan_children
from l2r.learner.__main__ import parse_settings as learner_settings
from l2r.learner.colocated import WorldsConfig
from l2r.up import parse_args
from tests.conftest import wait_for
from tests.system.test_up import finish, l2r_up, rows


def test_the_learner_takes_the_actors_worlds_and_the_evaluators_the_ids_after_them():
    args, _ = parse_args(["--colocated", "--actors", "2", "--envs-per-actor", "8", "--random-steps", "500",
                          "--difficulty", "1", "--randomize", "strength=0.05,delay=0.5", "--seed", "3",
                          "--evaluators", "2", "--algo", "td3"])
    children = plan_children(args, "run", Path("runs/x"), [], 7448)
    assert [c.name for c in children] == ["learner", "evaluator-0", "evaluator-1"]
    learner = learner_settings(children[0].argv[3:])
    assert learner.connect == [] and learner.algo == "td3"
    assert learner.learner().colocated == WorldsConfig(
        "l2r/Run-v0", worlds=16, capacity=1_000_000, random_steps=1000, min_replay=10_000, action_repeat=3,
        difficulty=1, randomize="strength=0.05,delay=0.5", seed=3, actor_id=0)
    assert [actor_settings(c.argv[3:]).actor_id for c in children[1:]] == [1, 2]


def test_an_on_policy_learner_takes_the_worlds_without_a_warm_up_or_a_ring():
    args, _ = parse_args(["--colocated", "--algo", "ppo", "--envs-per-actor", "16"])  # its recipe has no min_replay
    argv = plan_children(args, "run", Path("runs/x"), [], 7448)[0].argv[3:]
    learner = learner_settings(argv)
    assert learner.algo == "ppo" and learner.learner().colocated.worlds == 16
    assert not {"--colocated-capacity", "--colocated-random-steps", "--colocated-min-replay"} & set(argv)


@pytest.mark.parametrize("argv, error", [
    (["--algo", "a3c"], "--colocated trains on the learner's own worlds; --algo a3c learns from the actors' gradients"),
    (["--opensim-actors", "1"], "--colocated: --opensim-actors are the actors' and replay's"),
    (["--exploration-noise", "pink", "--parameter-noise", "0.2"],
     "--colocated: --exploration-noise, --parameter-noise are"),
    (["--exploration-noise", "pink", "--frame-stack", "4"], "--colocated: --exploration-noise, --frame-stack are"),
    (["--env-id", "l2r/PhotoTuneStats-v0", "--algo", "td3"], "--colocated steps worlds of vector observations"),
])
def test_what_the_learner_s_own_worlds_cannot_take_is_refused_in_one_line(argv, error, capsys):
    with pytest.raises(SystemExit) as exit:
        parse_args(["--colocated", *argv])
    assert exit.value.code == 2 and error in capsys.readouterr().err


@pytest.mark.slow
def test_a_colocated_job_trains_evaluates_and_reports_its_worlds_as_actor_0(tmp_path):
    name = f"test-{uuid.uuid4().hex[:6]}"
    proc = l2r_up(tmp_path / "up.out", "--colocated", "--env-id", "Pendulum-v1", "--seconds", "600", "--name", name,
                  "--runs-dir", str(tmp_path), "--envs-per-actor", "4", "--eval-episodes", "1", "--eval-interval", "3",
                  "--learner-arg=--hidden=32,32", "--learner-arg=--publish-every=20", "--batch-size", "64",
                  "--random-steps", "100", "--min-replay", "200", "--status-interval", "1")
    try:
        run_dir = wait_for(lambda: next(tmp_path.glob(f"{name}-*"), None), timeout=60)
        assert run_dir, "no run directory"
        metrics = run_dir / "metrics"
        assert wait_for(lambda: rows(metrics / "episodes.csv") and rows(metrics / "evaluation.csv")
                        and (run_dir / "learner" / "best.pt").exists(), timeout=240), "no episodes or evaluations"
        proc.send_signal(signal.SIGTERM)
    finally:
        out = finish(proc, tmp_path / "up.out", 120)
    assert proc.returncode == 0, out
    assert "starting learner, evaluator-0" in out  # no replay server, no training actor
    assert not (run_dir / "logs" / "replay.log").exists()
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["updates"] > 0 and summary["env_steps"] >= 200, summary
    training = rows(run_dir / "metrics" / "episodes.csv")
    assert all(r["actor"] == "0" and int(r["length"]) == 200 for r in training), training[:3]
    assert {r["actor"] for r in rows(run_dir / "metrics" / "evaluation.csv")} == {"1"}
