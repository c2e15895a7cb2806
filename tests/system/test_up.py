"""`l2r up` end to end: real replay, learner and actor processes on the real runner over
loopback Zenoh; a killed actor is restarted, a killed learner resumes from its checkpoint,
and `l2r eval` loads what the run left."""

import json
import os
import re
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
# Small networks and batches so a few hundred updates fit in seconds on two shared cores.
SMALL = ["--learner-arg=--hidden=64,64", "--learner-arg=--publish-every=20", "--learner-arg=--update-repeat=1",
         "--learner-arg=--checkpoint-interval=3", "--batch-size", "64"]


def wait_for(predicate, proc, timeout, what):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        assert proc.poll() is None, f"l2r up exited early while waiting for {what}"
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for {what}")


def pid_of(run_dir: Path, name: str) -> int | None:
    log = run_dir / "logs" / "up.log"
    pids = re.findall(rf"started {name} \(pid (\d+)\)", log.read_text()) if log.exists() else []
    return int(pids[-1]) if pids else None


def last_status(run_dir: Path) -> dict:
    path = run_dir / "metrics.jsonl"
    rows = [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []
    statuses = [r for r in rows if r["type"] == "status"]
    return statuses[-1] if statuses else {}


@pytest.mark.slow
def test_up_trains_restarts_resumes_and_leaves_a_checkpoint_eval_loads(tmp_path):
    name = f"test-{uuid.uuid4().hex[:6]}"
    proc = subprocess.Popen(
        [sys.executable, "-m", "l2r.cli", "up", "--seconds", "45", "--name", name, "--runs-dir", str(tmp_path),
         "--actors", "1", "--envs-per-actor", "2", "--evaluators", "1", "--eval-episodes", "1",
         "--eval-interval", "3", "--random-steps", "300", "--min-replay", "300", "--status-interval", "1", *SMALL],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        run_dir = wait_for(lambda: next(tmp_path.glob(f"{name}-*"), None), proc, 30, "the run directory")
        wait_for(lambda: last_status(run_dir).get("updates", 0) > 0, proc, 40, "learner updates")

        os.kill(pid_of(run_dir, "actor-0"), signal.SIGKILL)
        wait_for(lambda: "actor-0 exited" in (run_dir / "logs" / "up.log").read_text(), proc, 10, "actor restart")

        checkpoint = run_dir / "learner" / "checkpoint.pt"
        wait_for(checkpoint.exists, proc, 20, "a learner checkpoint")
        os.kill(pid_of(run_dir, "learner"), signal.SIGKILL)
        wait_for(lambda: "learner exited" in (run_dir / "logs" / "up.log").read_text(), proc, 10, "learner restart")
        out, _ = proc.communicate(timeout=90)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, out

    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["restarts_by_process"] == {"actor-0": 1, "learner": 1}
    assert summary["updates"] >= 200, summary
    assert summary["env_steps"] > 1000
    learner_log = (run_dir / "logs" / "learner.log").read_text()
    resumed = re.findall(r"version (\d+), (\d+) updates so far", learner_log)
    assert len(resumed) == 2 and int(resumed[1][1]) > 0, resumed  # the restarted learner continued

    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    trained = [r["version"] for r in rows if r["type"] == "episode" and not r["evaluation"] and r["version"] >= 0]
    assert trained and max(trained) >= 2  # new weights reached the actors
    assert any(r["type"] == "episode" and r["evaluation"] for r in rows)
    for name in ("up", "replay", "learner", "actor-0", "evaluator-0"):
        assert (run_dir / "logs" / f"{name}.log").stat().st_size > 0
    assert summary["best_eval_recording"] == str(run_dir / "best_eval.rrd")
    assert (run_dir / "best_eval.rrd").stat().st_size > 0

    ev = subprocess.run([sys.executable, "-m", "l2r.cli", "eval", str(run_dir), "--episodes", "2", "--json"],
                        cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert ev.returncode == 0, ev.stderr
    result = json.loads(ev.stdout.strip().splitlines()[-1])
    assert len(result["distances"]) == 2 and result["version"] >= 1

