"""`l2r up --opensim-stage`: the port's actors for a while, then the learner goes on from its
checkpoint in a run of its own whose one actor steps OpenSim, learning from that experience alone."""

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from l2r import opensim_stage
from l2r.actors.__main__ import parse_settings as actor_settings
from l2r.job_plan import plan_children
from l2r.learner.__main__ import parse_settings as learner_settings
from l2r.learner.checkpoint import load_checkpoint
from l2r.replay.__main__ import parse_settings as replay_settings
from l2r.run_metrics import RunCounters
from l2r.up import budget_spent, parse_args


def port_run_with_checkpoint(tmp_path: Path) -> Path:
    port_run = tmp_path / "runner-20261127-120000"
    (port_run / "learner").mkdir(parents=True)
    (port_run / "learner" / "checkpoint.pt").write_bytes(b"")  # found here; the learner reads it
    (port_run / "metrics").mkdir()
    (port_run / "metrics" / "status.csv").write_text("time,env_steps,updates,episodes\n3600,2600000,100000,9000\n")
    return port_run


def test_the_opensim_stage_trains_one_opensim_actor_from_the_port_s_checkpoint_on_the_rest_of_the_time(tmp_path):
    port_run = port_run_with_checkpoint(tmp_path)
    args, _ = parse_args(["--seconds", "7200", "--opensim-stage", "3600", "--actors", "2", "--evaluators", "2",
                          "--eval-env-id", "l2r/RunOpenSim-v0", "--eval-env-id", "l2r/Run-v0"])
    stage = opensim_stage.stage_args(args, port_run)
    assert (stage.seconds, stage.opensim_stage, stage.resume) == (3600, 0, None)
    children = {c.name: c.argv[3:] for c in plan_children(stage, "run", Path("runs/x"), [7447], 7448)}
    assert sorted(children) == ["actor-0", "evaluator-0", "evaluator-1", "learner", "replay"]
    actor = actor_settings(children["actor-0"])
    assert actor.env_id == "l2r/RunOpenSim-v0" and not actor.randomize
    # On along the recipe's course from a port actor's share of the port's 2.6 M env steps.
    assert (str(actor.difficulty_schedule), actor.env_steps_before) == ("0:0,1000000:2", 1_300_000)
    replay = replay_settings(children["replay"])
    assert (replay.min_size, replay.samples_per_insert, replay.hold_actors) == (2000, 128.0, True)
    assert learner_settings(children["learner"]).init_from == (port_run / "learner" / "checkpoint.pt").resolve()
    assert [actor_settings(children[f"evaluator-{i}"]).env_id for i in (0, 1)] == ["l2r/RunOpenSim-v0", "l2r/Run-v0"]

    stage_run = opensim_stage.run_dir_of(port_run)
    (stage_run / "metrics").mkdir(parents=True)
    (stage_run / "launch.json").write_text("{}")
    (stage_run / "metrics" / "status.csv").write_text("time,env_steps,updates,episodes\n600,30000,20000,40\n")
    resumed = opensim_stage.stage_args(args, port_run)
    assert resumed.resume == tmp_path / "runner-20261127-120000-opensim"
    actor = next(actor_settings(c.argv[3:]) for c in plan_children(resumed, "run", stage_run, [7447], 7448)
                 if c.name == "actor-0")
    assert actor.env_steps_before == 1_300_000 + 30_000


def test_the_port_s_stage_ends_at_its_seconds_and_the_job_at_its_own():
    args, _ = parse_args(["--seconds", "7200", "--opensim-stage", "3600"])
    assert budget_spent(args, RunCounters(time=3599.0)) is None
    assert budget_spent(args, RunCounters(time=3600.0)) == "port's stage of 3600 s spent"
    args, _ = parse_args(["--seconds", "7200"])
    assert budget_spent(args, RunCounters(time=3600.0)) is None


@pytest.mark.parametrize("flags, refusal", [
    (["--env-id", "Hopper-v5"], "goes on from the port (l2r/Run-v0) to OpenSim, not from Hopper-v5"),
    (["--env-id", "l2r/RunOpenSim-v0"], "not from l2r/RunOpenSim-v0"),
    (["--algo", "ppo"], "--algo sac or td3, not --colocated"),
    (["--colocated"], "--algo sac or td3, not --colocated"),
    (["--env-steps", "100000"], "give the job's budget as --seconds, not --env-steps"),
    (["--seconds", "50"], "--opensim-stage 60 leaves no time of --seconds 50 for OpenSim's stage"),
])
def test_a_job_the_stage_cannot_go_on_from_is_refused_in_one_line(flags, refusal, capsys):
    with pytest.raises(SystemExit) as stopped:
        parse_args(["--opensim-stage", "60", *flags])
    assert stopped.value.code == 2 and refusal in capsys.readouterr().err


def run_up(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "l2r.cli", "up", *argv], capture_output=True, text=True, timeout=240)


@pytest.mark.slow
def test_a_staged_job_runs_the_port_then_opensim_from_the_port_s_learner_and_resumes_where_it_is(tmp_path):
    done = run_up("--seconds", "33", "--opensim-stage", "15", "--runs-dir", str(tmp_path), "--name", "staged",
                  "--replay-arg=--min-size=32", "--evaluators", "0", "--status-interval", "5")
    assert done.returncode == 0, done.stderr[-3000:]
    port_run, stage_run = sorted(tmp_path.iterdir())
    assert stage_run == opensim_stage.run_dir_of(port_run)
    port, stage = (json.loads((run / "summary.json").read_text()) for run in (port_run, stage_run))
    assert port["outcome"] == "port's stage of 15 s spent" and port["updates"] > 0
    # The learner went on from the port's counters, and its actor stepped OpenSim alone.
    assert stage["outcome"] == "time budget of 18 s spent" and stage["updates"] > port["updates"]
    launch = json.loads((stage_run / "launch.json").read_text())["args"]
    assert launch["init_from"] == str((port_run / "learner" / "checkpoint.pt").resolve())
    assert "actor 0 up: 4 x l2r/RunOpenSim-v0" in (stage_run / "logs" / "actor-0.log").read_text()
    # Its own updates are those past the checkpoint it started from.
    in_session = [int(n.replace(",", "")) for n in re.findall(r"updates \(([\d,]+) in this session\)", done.stderr)]
    carried = load_checkpoint(port_run).updates
    assert in_session[-1] == stage["updates"] - carried < stage["updates"], in_session
    assert stage["env_steps"] > 0

    # Once OpenSim's stage has begun, a resume goes on with it, even where the port's would have time left;
    # its budget is what the job's leaves after the port's stage as it ran (15 s and the poll's overshoot,
    # which on a loaded machine can pass the 17 s now asked for: the stage counts at most that).
    resumed = run_up("--resume", str(port_run), "--opensim-stage", "17", "--seconds", "33")
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    assert "port's stage of 17 s spent" not in resumed.stderr
    assert f"OpenSim's stage goes on in {stage_run}" in resumed.stderr
    left = re.search(r"nothing to do: the run's time budget of ([\d.]+) s spent", resumed.stderr)
    port_stage = min(17, RunCounters.read(port_run / "metrics").time)
    assert left and float(left[1]) == pytest.approx(33 - port_stage), resumed.stderr


def test_a_resume_whose_opensim_stage_launch_json_is_corrupt_is_refused_in_one_line(tmp_path):
    port_run = port_run_with_checkpoint(tmp_path)
    (port_run / "launch.json").write_text(json.dumps({"argv": [], "zenoh_run": port_run.name, "args": {
        "seconds": 60.0, "opensim_stage": 30.0}}))
    (opensim_stage.run_dir_of(port_run)).mkdir()
    (opensim_stage.run_dir_of(port_run) / "launch.json").write_text("{not json")
    done = run_up("--resume", str(port_run))
    assert done.returncode == 2 and "launch.json cannot be read" in done.stderr.strip().splitlines()[-1], done.stderr
    assert "Traceback" not in done.stderr
