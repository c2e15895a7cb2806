"""Supervision of `l2r up`'s processes: restarts back off, a process that keeps exiting without
progress is given up on after a set number of restarts however fast it fails, one that makes
progress is not, a mistake (a usage error, a process that cannot start) is given up on at once with
its own reason, and a clean exit is final."""

import subprocess
import sys
from pathlib import Path

import pytest

from l2r import supervise
from l2r.supervise import (
    FAILED, FINISHED, RUNNING, WAITING, Child, ProcessGroup, exit_reason, last_lines, restart_delay,
)
from tests.conftest import ROOT, wait_for


@pytest.fixture
def short_delays(monkeypatch):
    monkeypatch.setattr(supervise, "RESTART_DELAY", 0.05)
    monkeypatch.setattr(supervise, "MAX_RESTART_DELAY", 0.2)


def exiting(code: int) -> Child:
    return Child("proc", [sys.executable, "-c", f"print('attempt'); raise SystemExit({code})"], tier=0,
                 progress=("actor", "0", "env_steps"))


def supervise_until_settled(group: ProcessGroup, timeout: float = 20.0) -> Child | None:
    """Poll like `l2r up` does until a child is given up on or every child settled."""
    failed = []
    wait_for(lambda: failed.append(group.poll()) or failed[-1] or all(
        c.state not in (RUNNING, WAITING) for c in group.children), timeout=timeout, interval=0.01)
    return failed[-1]


def test_restarts_back_off_while_there_is_no_progress():
    assert [restart_delay(n) for n in range(7)] == [1, 1, 2, 4, 8, 16, 30]


def test_a_process_failing_without_progress_is_given_up_on_after_max_restarts(tmp_path, short_delays):
    exits = []
    group = ProcessGroup([exiting(1)], tmp_path, progress=lambda *key: 0, max_restarts=3,
                         on_exit=lambda child, code: exits.append(code))
    group.start()
    child = group.children[0]
    assert supervise_until_settled(group) is child
    assert child.state == FAILED and child.restarts == 3 and exits == [1, 1, 1, 1]
    assert group.failure(child) == "proc exited 4 times in a row without progress (last: exit code 1)"
    assert last_lines(tmp_path / "proc.log") == ["attempt"] * 4


def test_a_process_that_makes_progress_between_exits_is_restarted_on(tmp_path, short_delays):
    progress = iter(range(1000))
    group = ProcessGroup([exiting(1)], tmp_path, progress=lambda *key: next(progress), max_restarts=1,
                         on_exit=lambda child, code: None)
    group.start()
    child = group.children[0]
    assert not wait_for(lambda: group.poll() or child.restarts >= 5, timeout=20, interval=0.01) is child
    assert child.restarts >= 5 and child.state != FAILED and child.exits_without_progress == 0
    group.stop()


@pytest.mark.parametrize("code, mistake", [(2, "rejected its command line"), (3, "cannot start on this machine")])
def test_a_mistake_is_given_up_on_at_once_with_the_process_s_own_reason(tmp_path, short_delays, code, mistake):
    refusing = Child("proc", [sys.executable, "-c", f"import sys; print('proc: --capacity 9 needs 9 GiB', file=sys.stderr); "
                                                    f"raise SystemExit({code})"], tier=0, progress=("actor", "0", "env_steps"))
    group = ProcessGroup([refusing], tmp_path, progress=lambda *key: 0, max_restarts=5, on_exit=lambda c, code: None)
    group.start()
    failed = supervise_until_settled(group)
    assert failed is refusing and failed.restarts == 0
    assert group.failure(failed) == (f"proc {mistake} (exit code {code}), which a restart would repeat: "
                                     "proc: --capacity 9 needs 9 GiB")


def test_a_clean_exit_is_final(tmp_path, short_delays):
    group = ProcessGroup([exiting(0)], tmp_path, progress=lambda *key: 0, max_restarts=5, on_exit=lambda c, code: None)
    group.start()
    assert supervise_until_settled(group) is None
    assert group.children[0].state == FINISHED and group.finished("proc")


def test_exit_reasons_name_the_signal():
    assert exit_reason(1) == "exit code 1"
    assert exit_reason(-9) == "killed by SIGKILL"


def test_the_processes_stop_when_their_supervisor_is_killed(tmp_path):
    # A supervisor in a process of its own, killed by SIGKILL: it can stop nobody, the kernel must.
    supervisor = subprocess.Popen([sys.executable, "-c", f"""
import sys, time
from pathlib import Path
from l2r.supervise import Child, ProcessGroup
group = ProcessGroup([Child("sleeper", [sys.executable, "-c", "import time; time.sleep(120)"], tier=0,
                            progress=("actor", "0", "env_steps"), nice=5)],
                     Path({str(tmp_path)!r}), progress=lambda *key: 0, max_restarts=0, on_exit=lambda c, code: None)
group.start()
print(group.children[0].process.pid, flush=True)
time.sleep(120)
"""], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        child = int(supervisor.stdout.readline())
        assert alive(child)
        supervisor.kill()
        supervisor.wait()
        assert wait_for(lambda: not alive(child), timeout=10), "the supervised process outlived its supervisor"
    finally:
        supervisor.kill()


def alive(pid: int) -> bool:
    """Running, not merely a zombie waiting for a parent to read its exit."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, ProcessLookupError):
        return False


@pytest.mark.skipif(not Path("/proc/self/autogroup").exists(), reason="this kernel schedules without autogroups")
def test_a_niced_process_in_a_session_of_its_own_is_niced_against_the_other_sessions_too(tmp_path):
    # Under autogroup scheduling a session's share of the CPU is set by its group's nice value alone.
    sleeper = [sys.executable, "-c", "import time; time.sleep(60)"]
    group = ProcessGroup([Child("actor", sleeper, tier=1, progress=("actor", "0", "env_steps"), nice=7),
                          Child("learner", sleeper, tier=0, progress=("learner", "0", "updates"))],
                         tmp_path, progress=lambda *key: 0, max_restarts=0, on_exit=lambda c, code: None)
    group.start()
    try:
        actor, learner = (Path(f"/proc/{c.process.pid}/autogroup").read_text().split() for c in group.children)
        assert actor[-2:] == ["nice", "7"] and learner[-2:] == ["nice", "0"]
        assert actor[0] != learner[0]  # each a group of its own
    finally:
        group.stop()
