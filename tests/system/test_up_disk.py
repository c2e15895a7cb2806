"""`l2r up` on a disk of its own (a tmpfs the test mounts): a run that may not fit is refused
before anything starts, and a disk that fills while the job runs stops it with one line that
names the run directory and its free space, no traceback, the newest checkpoint whole for
`l2r eval` and the command that resumes it. Its metrics files and up.log, on a full disk, say so
once and write again when there is room."""

import csv
import json
import logging
import re
import subprocess
import sys

import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from l2r.disk_budget import Shedding
from l2r.durable import FailureLog, FileLogHandler
from l2r.run_metrics import CsvLog, ScalarEvents
from tests.conftest import ROOT, wait_for
from tests.system.test_up import SMALL, finish, l2r_up


@pytest.mark.parametrize("staged", [[], ["--opensim-stage", "2"]])
def test_a_run_that_may_not_fit_on_its_disk_is_refused_in_one_line(small_disk, staged):
    disk = small_disk(8)
    # The default replay table (a million transitions) alone is estimated at about 900 MB.
    done = subprocess.run([sys.executable, "-m", "l2r.cli", "up", "--runs-dir", str(disk.path), "--seconds", "5",
                           *staged], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "MB free at" in lines[0] and "replay" in lines[0] and "--force" in lines[0], lines
    assert not any(disk.path.iterdir()), "a refused run left a run directory"


@pytest.mark.slow
def test_a_disk_that_fills_stops_the_job_in_one_line_and_keeps_the_newest_checkpoint(small_disk, tmp_path):
    disk = small_disk(48)
    # Small enough to fit the start-up estimate: 5,000 transitions, 2 MB of episodes per actor.
    proc = l2r_up(tmp_path / "up.out", "--seconds", "600", "--runs-dir", str(disk.path), "--capacity", "5000",
                  "--actor-arg=--log-budget-mb=2", "--envs-per-actor", "2", "--eval-interval", "3", *SMALL)
    try:
        run_dir = wait_for(lambda: next(disk.path.glob("l2r-*"), None), timeout=60)
        assert run_dir, "no run directory"
        checkpoint = run_dir / "learner" / "checkpoint.pt"
        assert wait_for(checkpoint.exists, timeout=240), "no checkpoint"
        disk.fill()
        proc.wait(120)
    finally:
        out = finish(proc, tmp_path / "up.out", 10)
    assert proc.returncode == 1, out
    assert "Traceback" not in out and "Logging error" not in out, out
    stop = [line for line in out.splitlines() if line.startswith("l2r up: failed:")]
    assert len(stop) == 1 and f"disk full at {run_dir}: " in stop[0] and " MB free" in stop[0], out
    # A line per cause and spell (metrics, summary.json, the stop; space the run frees itself, as old
    # checkpoints go, starts a new spell), not one per failed write.
    assert len([line for line in out.splitlines() if "disk full at" in line]) <= 10, out
    assert f"l2r up --resume {run_dir}" in out
    assert re.search(r"\| disk \d+\.\d MB free", out), out  # the status line shows a disk running low
    # Its last checkpoint refused is a line of its own log, not a crash (a learner slow to stop on
    # a loaded machine may be killed after the stop timeout instead: that is not this test's matter).
    assert "learner stopped (exit code 1)" not in out, out

    ev = subprocess.run([sys.executable, "-m", "l2r.cli", "eval", str(run_dir), "--episodes", "1", "--json"],
                        cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert ev.returncode == 0, ev.stderr
    assert json.loads(ev.stdout.strip().splitlines()[-1])["version"] >= 1


class Console(logging.Handler):
    def __init__(self):
        super().__init__()
        self.lines: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.lines.append(record.getMessage())


def test_metrics_on_a_full_disk_say_so_once_and_write_whole_rows_again_once_it_has_room(small_disk, caplog):
    caplog.set_level(logging.INFO)
    disk = small_disk(1)
    failures = FailureLog(logging.getLogger("l2r.up"), "metrics")
    table, events = CsvLog(disk.path / "status.csv", ["time", "note"], failures), ScalarEvents(disk.path, failures)
    table.write({"time": 0, "note": ""})
    table.flush()
    disk.fill()
    for i in range(1, 2000):  # far more than the page the file ends in can take
        table.write({"time": i, "note": "x" * 100})
        events.add("status/time", float(i), i, 0.0)
        table.flush()
        events.flush()
    refused = [r.getMessage() for r in caplog.records if "disk full at" in r.getMessage()]
    assert len(refused) == 1 and f"disk full at {disk.path}" in refused[0], refused

    disk.free()
    table.flush()  # the next status update opens the files again
    events.flush()
    table.write({"time": 2000, "note": "back"})
    table.flush()
    events.add("status/time", 2000.0, 2000, 0.0)
    events.flush()
    assert any("writing again" in r.getMessage() for r in caplog.records)
    table.close()
    events.close()
    with open(disk.path / "status.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows[0]["time"] == "0" and rows[-1] == {"time": "2000", "note": "back"}  # whole rows, the header kept
    accumulator = EventAccumulator(str(disk.path))
    accumulator.Reload()
    assert accumulator.Scalars("status/time")[-1].step == 2000


def test_a_filling_disk_sheds_episode_logs_then_events_each_change_said_once(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="l2r.disk_budget")
    shedding, reserve = Shedding(tmp_path), 1_000_000
    steps = [(20, set()), (9, {"episode logs"}), (8, {"episode logs"}),
             (4, {"episode logs", "TensorBoard events"}), (3, {"episode logs", "TensorBoard events"}), (12, set())]
    for reserves, shed in steps:
        assert shedding.update(reserves * reserve, reserve) == shed, reserves
    lines = [(r.levelname, r.getMessage()) for r in caplog.records]
    assert [level for level, _ in lines] == ["WARNING", "WARNING", "INFO", "INFO"], lines
    assert "episode logs are not written" in lines[0][1] and "TensorBoard events are not written" in lines[1][1]

    events = ScalarEvents(tmp_path, FailureLog(logging.getLogger("l2r.up"), "metrics"))
    for step, paused in ((1, False), (2, True), (3, False)):
        events.paused = paused
        events.add("status/time", float(step), step, 0.0)
    events.close()
    accumulator = EventAccumulator(str(tmp_path))
    accumulator.Reload()
    assert [e.step for e in accumulator.Scalars("status/time")] == [1, 3]


def test_up_log_on_a_full_disk_is_one_line_on_the_console_not_a_traceback_per_record(small_disk, capsys):
    disk = small_disk(1)
    console = Console()
    handler = FileLogHandler(disk.path / "up.log", console)
    logger = logging.getLogger("test.up_log")
    logger.propagate = False
    logger.addHandler(handler)
    try:
        disk.fill()
        for _ in range(50):
            logger.warning("x" * 10_000)
        assert len(console.lines) == 1 and "disk full at" in console.lines[0] and "up.log" in console.lines[0]
        assert "Logging error" not in capsys.readouterr().err
        disk.free()
        logger.warning("back")
        assert console.lines[-1].endswith("writing again")
    finally:
        logger.removeHandler(handler)
        handler.close()
