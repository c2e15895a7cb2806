"""`l2r up` end to end: real replay, learner and actor processes on the real runner over
loopback Zenoh. A killed actor is restarted, a killed learner resumes from its checkpoint,
metrics reach TensorBoard and CSV files, `l2r eval` loads what the run left with the action
repeat it trained with; `--resume` reuses the run's flags and continues its counters; the
env-step budget ends a job; a learner or replay server that cannot start ends the job at once,
without a restart, with its reason on screen."""

import csv
import json
import os
import re
import signal
import stat
import subprocess
import sys
import uuid
from pathlib import Path

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from l2r.episodes.read import episode_metadata
from tests.conftest import ROOT, wait_for

# Small networks and batches so a few hundred updates fit in seconds on two shared cores.
SMALL = ["--learner-arg=--hidden=64,64", "--learner-arg=--publish-every=20", "--learner-arg=--update-repeat=1",
         "--learner-arg=--checkpoint-interval=3", "--batch-size", "64", "--random-steps", "300", "--min-replay", "300",
         "--status-interval", "1"]


def l2r_up(output: Path, *argv: str) -> subprocess.Popen:
    """`l2r up` writing what it shows to a file, which (unlike a pipe nobody reads) never fills up."""
    with open(output, "w") as out:
        return subprocess.Popen([sys.executable, "-m", "l2r.cli", "up", *argv], cwd=ROOT, stdout=out,
                                stderr=subprocess.STDOUT)


def finish(proc: subprocess.Popen, output: Path, timeout: float) -> str:
    """What `l2r up` showed, once it has exited (killed after `timeout` seconds)."""
    try:
        proc.wait(timeout)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return output.read_text()


def pid_of(run_dir: Path, name: str) -> int | None:
    log = run_dir / "logs" / "up.log"
    pids = re.findall(rf"started {name} \(pid (\d+)\)", log.read_text()) if log.exists() else []
    return int(pids[-1]) if pids else None


def rows(path: Path) -> list[dict]:
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def up_log(run_dir: Path) -> str:
    return (run_dir / "logs" / "up.log").read_text()


@pytest.mark.slow
def test_up_trains_restarts_writes_metrics_and_leaves_a_checkpoint_eval_loads(tmp_path):
    name = f"test-{uuid.uuid4().hex[:6]}"
    # Stopped with SIGTERM once everything was seen, so a loaded machine only makes it slower.
    proc = l2r_up(tmp_path / "up.out", "--seconds", "600", "--name", name, "--runs-dir", str(tmp_path),
                  "--actors", "1", "--envs-per-actor", "2", "--evaluators", "1", "--eval-episodes", "1",
                  "--eval-interval", "3", "--action-repeat", "2", "--keep-checkpoints", "2", *SMALL)

    def updates() -> int:
        return int(([{}] + rows(run_dir / "metrics" / "status.csv"))[-1].get("updates", 0))

    try:
        run_dir = wait_for(lambda: next(tmp_path.glob(f"{name}-*"), None), timeout=60)
        assert run_dir, "no run directory"
        assert wait_for(lambda: updates() > 0, timeout=180), "no learner updates"
        os.kill(pid_of(run_dir, "actor-0"), signal.SIGKILL)
        assert wait_for(lambda: "actor-0 killed by SIGKILL" in up_log(run_dir), timeout=10)
        assert wait_for((run_dir / "learner" / "checkpoint.pt").exists, timeout=60)
        os.kill(pid_of(run_dir, "learner"), signal.SIGKILL)
        assert wait_for(lambda: "learner killed by SIGKILL" in up_log(run_dir), timeout=10)
        resumed_at = updates()
        # Every process's stats too: the learner's come every few seconds, and a fast machine reaches
        # the updates before the restarted learner's first.
        assert wait_for(lambda: updates() >= max(200, resumed_at + 50) and (run_dir / "learner" / "best.pt").exists()
                        and all(rows(run_dir / "metrics" / f"{table}.csv") for table in ("evaluation", "learner", "replay")),
                        timeout=180), "no training after the restart"
        proc.send_signal(signal.SIGTERM)
    finally:
        out = finish(proc, tmp_path / "up.out", 120)
    assert proc.returncode == 0, out
    assert "done: stopped by SIGTERM" in out
    assert re.search(r"restarts: .*actor-0 1 \(last: killed by SIGKILL\)", out)  # the status says who restarted and why

    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["restarts_by_process"] == {"actor-0": 1, "learner": 1}
    assert summary["last_exit_by_process"] == {"actor-0": "killed by SIGKILL", "learner": "killed by SIGKILL"}
    assert summary["updates"] >= 200 and summary["env_steps"] > 1000, summary
    resumed = re.findall(r"version (\d+), (\d+) updates so far", (run_dir / "logs" / "learner.log").read_text())
    assert len(resumed) == 2 and int(resumed[1][1]) > 0, resumed  # the restarted learner continued

    # The newest checkpoints, readable by everyone; eval steps with the action repeat of training.
    learner_files = sorted((run_dir / "learner").iterdir())
    assert len([p for p in learner_files if p.name.startswith("checkpoint-")]) == 2
    assert all(stat.S_IMODE(p.stat().st_mode) == 0o644 for p in learner_files)
    ev = subprocess.run([sys.executable, "-m", "l2r.cli", "eval", str(run_dir), "--episodes", "1", "--json"],
                        cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert ev.returncode == 0, ev.stderr
    result = json.loads(ev.stdout.strip().splitlines()[-1])
    assert result["version"] >= 1 and result["action_repeat"] == 2

    # Metrics where people read them: TensorBoard and CSV.
    events = EventAccumulator(str(run_dir / "metrics"))
    events.Reload()
    scalars = set(events.Tags()["scalars"])
    for tag in ("learner/critic_loss", "learner/actor_loss", "learner/alpha", "learner/q_mean", "learner/entropy",
                "actor/0/env_steps_per_s", "replay/0/size", "train/distance", "eval/distance"):
        assert tag in scalars, (tag, sorted(scalars))
    assert max(e.step for e in events.Scalars("learner/critic_loss")) >= 200  # by updates
    learner_rows = rows(run_dir / "metrics" / "learner.csv")
    assert any(r["critic_loss"] and r["entropy"] for r in learner_rows)
    for table in ("actors", "replay", "episodes", "evaluation", "status"):
        assert rows(run_dir / "metrics" / f"{table}.csv"), table
    assert [r["process"] for r in rows(run_dir / "metrics" / "exits.csv")] == ["actor-0", "learner"]

    # summary.json's best evaluation episode is the one best_eval.rrd records.
    best = summary["best_eval_episode"]
    evaluations = rows(run_dir / "metrics" / "evaluation.csv")
    assert best["distance"] == max(float(r["distance"]) for r in evaluations)
    assert summary["best_eval_recording"] == str(run_dir / "best_eval.rrd")
    assert (run_dir / "best_eval.rrd").stat().st_size > 0
    recorded = episode_metadata(best["log"])
    assert (recorded["episode"]["kind"], int(recorded["episode"]["actor"]), int(recorded["episode"]["seed"]),
            int(recorded["episode"]["policy_version"])) == ("eval", best["actor"], best["seed"], best["version"])
    assert float(recorded["result"]["distance"]) == best["distance"]
    assert summary["best_policy"]["path"] == str(run_dir / "learner" / "best.pt")


@pytest.mark.slow
def test_the_env_step_budget_ends_a_job_and_resume_reuses_its_flags_and_counters(tmp_path):
    name = f"test-{uuid.uuid4().hex[:6]}"
    first = l2r_up(tmp_path / "first.out", "--env-steps", "1500", "--seconds", "400", "--name", name,
                   "--runs-dir", str(tmp_path), "--actors", "1", "--evaluators", "0", "--keep-checkpoints", "2", *SMALL)
    out = finish(first, tmp_path / "first.out", 400)
    assert first.returncode == 0, out
    assert "done: budget of 1,500 env steps spent" in out
    assert "a longer run: l2r up --seconds 3600" in out  # a short run says what a long one reaches
    run_dir = next(tmp_path.glob(f"{name}-*"))
    before = json.loads((run_dir / "summary.json").read_text())
    assert 1500 <= before["env_steps"] < 1500 + 3000 and before["time"] < 400 and before["updates"] > 0, before

    # No flag but the budget: the small networks, one actor and no evaluator come from launch.json
    # (a learner started with the default networks would refuse the checkpoint and the job give up).
    # The budget goes beyond what the first session spent, however far it overshot its own.
    budget = str(before["env_steps"] + 1500)
    second = l2r_up(tmp_path / "second.out", "--resume", str(run_dir), "--env-steps", budget)
    out = finish(second, tmp_path / "second.out", 400)
    assert second.returncode == 0, out
    assert f"--env-steps {budget} replaces 1500 from {run_dir / 'launch.json'}" in out
    launch = json.loads((run_dir / "launch.json").read_text())
    assert launch["args"]["actors"] == 1 and "--learner-arg=--hidden=64,64" in launch["argv"]
    assert [s["argv"] for s in launch["sessions"]] == [launch["argv"], ["--resume", str(run_dir), "--env-steps", budget]]
    assert "started evaluator" not in up_log(run_dir) and "started actor-1" not in up_log(run_dir)

    resumed = re.findall(r"resumed from .*checkpoint.pt: version (\d+), (\d+) updates",
                         (run_dir / "logs" / "learner.log").read_text())
    assert len(resumed) == 1 and int(resumed[0][1]) > 0  # the checkpoint was kept and continued
    after = json.loads((run_dir / "summary.json").read_text())
    assert after["env_steps"] >= int(budget) and after["updates"] > int(resumed[0][1]) and after["time"] > before["time"]
    status = rows(run_dir / "metrics" / "status.csv")
    times, steps = [float(r["time"]) for r in status], [int(r["env_steps"]) for r in status]
    assert times == sorted(times) and steps == sorted(steps)  # the counters went on, not back to 0


def exits(run_dir: Path, process: str) -> list[str]:
    return [row["exit_code"] for row in rows(run_dir / "metrics" / "exits.csv") if row["process"] == process]


@pytest.mark.slow
def test_a_learner_that_cannot_start_ends_the_job_at_once_with_its_error_on_screen(tmp_path):
    run_dir = tmp_path / "broken"
    (run_dir / "learner").mkdir(parents=True)
    (run_dir / "learner" / "checkpoint.pt").write_bytes(b"PK\x03\x04 truncated")
    (run_dir / "launch.json").write_text(json.dumps({"args": {"actors": 1, "evaluators": 0, "seconds": 900}}))
    proc = l2r_up(tmp_path / "up.out", "--resume", str(run_dir))
    out = finish(proc, tmp_path / "up.out", 300)  # well within the 900 s budget
    assert proc.returncode == 1, out
    assert ("failed: gave up: learner cannot start on this machine (exit code 3), which a restart would repeat: "
            f"l2r-learner: cannot read checkpoint {run_dir / 'learner' / 'checkpoint.pt'}") in out
    tail = out[out.index("the last lines of"):]
    assert "cannot read checkpoint" in tail  # the learner's own error, last on screen
    assert "l2r eval" not in out and "best_eval.rrd" not in out  # nothing to evaluate or watch
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["exit_code"] == 1 and summary["restarts_by_process"] == {}
    assert exits(run_dir, "learner") == ["3"] and "restarting learner" not in up_log(run_dir)


@pytest.mark.slow
def test_a_replay_capacity_beyond_memory_ends_the_job_at_once_without_a_restart(tmp_path):
    proc = l2r_up(tmp_path / "up.out", "--capacity", "2000000000", "--seconds", "900", "--actors", "1",
                  "--evaluators", "0", "--name", "huge", "--runs-dir", str(tmp_path))
    out = finish(proc, tmp_path / "up.out", 120)  # a job that restarted the replay would run for 900 s
    assert proc.returncode == 1, out
    assert ("l2r up: failed: gave up: replay cannot start on this machine (exit code 3), which a restart would "
            "repeat: l2r-replay: --capacity 2000000000 needs 584.3 GiB of memory; ") in out, out
    run_dir = next(tmp_path.glob("huge-*"))
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["restarts_by_process"] == {} and summary["last_exit_by_process"]["replay"] == "exit code 3"
    assert exits(run_dir, "replay") == ["3"] and "restarting replay" not in up_log(run_dir)
