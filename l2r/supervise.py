"""The daemons of `l2r up` as supervised processes: started with a log file each, restarted with
back-off when they exit, given up on when restarts bring no progress, stopped in tiers.

The give-up rule counts restarts, not time, so it does not depend on how fast or loaded the
machine is. Each process has a progress counter (the learner's updates, an actor's or
evaluator's env steps, the replay server's inserts). A process that exits after its counter
rose is restarted after `RESTART_DELAY` and its count starts over; one that exits without its
counter rising is restarted after a delay that doubles each time (at most `MAX_RESTART_DELAY`),
and after `max_restarts` such restarts in a row the job gives up on it. Exit codes 2 (a usage
error) and 3 (valid settings this machine cannot serve: too little memory for the capacity, an
unreadable checkpoint) are mistakes a restart would repeat, not faults it could clear, so the job
gives up at once, with the process's own last line as the reason. Exit code 0 is a process that
finished (the learner's --max-updates, an actor's --max-steps): it stays finished.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from l2r.config import EXIT_CANNOT_START, EXIT_USAGE

log = logging.getLogger("l2r.up")

RESTART_DELAY = 1.0  # seconds before the first restart
MAX_RESTART_DELAY = 30.0
# Exits that the same command would repeat, as the job says them.
MISTAKES = {EXIT_USAGE: "rejected its command line", EXIT_CANNOT_START: "cannot start on this machine"}

# What a process is doing, as the status shows it.
RUNNING, WAITING, FINISHED, FAILED, STOPPED = "running", "waiting to restart", "finished", "gave up", "stopped"


def restart_delay(exits_without_progress: int) -> float:
    """Seconds before a restart: RESTART_DELAY after an exit that followed progress, doubling with
    each exit in a row without progress, at most MAX_RESTART_DELAY."""
    return min(RESTART_DELAY * 2 ** max(exits_without_progress - 1, 0), MAX_RESTART_DELAY)


def exit_reason(code: int) -> str:
    """`exit code 1`, or `killed by SIGKILL` for a process a signal ended."""
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"


def last_lines(path: Path, count: int = 20, max_bytes: int = 64 * 1024) -> list[str]:
    """The last `count` lines of a log file (read from its end), or none if it does not exist."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            f.seek(max(0, f.tell() - max_bytes))
            return f.read().decode(errors="replace").splitlines()[-count:]
    except FileNotFoundError:
        return []


@dataclass
class Child:
    """One daemon of the job. Higher tiers stop first (actors, then learner, then replay).
    `progress` names the counter of its stats that shows it works: (role, instance, value)."""

    name: str
    argv: list[str]
    tier: int
    progress: tuple[str, str, str]
    resume_args: list[str] = field(default_factory=list)
    nice: int = 0
    process: subprocess.Popen | None = None
    state: str = WAITING
    restarts: int = 0
    last_code: int | None = None
    exits_without_progress: int = 0
    progress_at_start: int = 0
    restart_at: float = 0.0

    @property
    def last_exit(self) -> str:
        """Why it last exited ("exit code 1", "killed by SIGKILL"), or "" if it has not."""
        return "" if self.last_code is None else exit_reason(self.last_code)


PR_SET_PDEATHSIG = 1  # from <linux/prctl.h>
# Looked up here, in the parent: loading a library between fork and exec can deadlock.
_prctl = ctypes.CDLL(None, use_errno=True).prctl if sys.platform == "linux" else None


def _before_exec(parent: int, nice: int) -> None:
    """In a child between fork and exec: its niceness, and on Linux a SIGTERM when `l2r up` dies,
    even by SIGKILL, so that no daemon outlives the job (the child runs in a session of its own)."""
    if nice:
        os.nice(nice)
        _nice_autogroup(nice)
    if _prctl is not None:
        _prctl(PR_SET_PDEATHSIG, signal.SIGTERM)
        if os.getppid() != parent:  # the parent died before the request took effect
            os.kill(os.getpid(), signal.SIGTERM)


def _nice_autogroup(nice: int) -> None:
    """Where Linux schedules by autogroup (sched_autogroup_enabled, as most distributions' kernels
    do), each session is a group that shares the CPU evenly with the others whatever its processes'
    nice values: a niced child in a session of its own would take as much CPU as the learner. The
    group's own nice value is what weighs across groups (sched(7)); a kernel without it has no file."""
    try:
        fd = os.open("/proc/self/autogroup", os.O_WRONLY)
    except OSError:
        return
    try:
        os.write(fd, str(nice).encode())
    except OSError:
        pass  # a raise of priority needs CAP_SYS_NICE; lowering it, as here, does not
    finally:
        os.close(fd)


class ProcessGroup:
    """Starts the children with one log file each, restarts the ones that exit, stops them in tiers.

    `progress(role, instance, value)` counts how often that value of a process's stats has risen
    so far; `on_exit(child, code)` hears of every exit while the job runs."""

    def __init__(self, children: list[Child], log_dir: Path, progress: Callable[[str, str, str], int],
                 on_exit: Callable[[Child, int], None], max_restarts: int = 3, resume: bool = False):
        self.children = children
        self.log_dir = log_dir
        self.progress, self.on_exit = progress, on_exit
        self.max_restarts = max_restarts
        self.resume = resume

    def log_path(self, child: Child) -> Path:
        return self.log_dir / f"{child.name}.log"

    def _spawn(self, child: Child, resume: bool) -> None:
        argv = child.argv + (child.resume_args if resume else [])
        with open(self.log_path(child), "ab") as out:
            # A session of its own: a Ctrl-C at the terminal reaches `l2r up` only, which then
            # stops the children in order.
            child.process = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                             start_new_session=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
                                             preexec_fn=functools.partial(_before_exec, os.getpid(), child.nice))
        child.state = RUNNING
        child.progress_at_start = self.progress(*child.progress)
        log.info("started %s (pid %d)%s", child.name, child.process.pid, " with --resume" if resume and child.resume_args else "")

    def start(self) -> None:
        for child in self.children:
            self._spawn(child, self.resume)

    def poll(self) -> Child | None:
        """Note exits, start restarts that are due; the child given up on, if any."""
        now = time.monotonic()
        for child in self.children:
            if child.state == WAITING and now >= child.restart_at:
                child.restarts += 1
                self._spawn(child, resume=True)
            elif child.state == RUNNING and (code := child.process.poll()) is not None:
                self._exited(child, code, now)
                if child.state == FAILED:
                    return child
        return None

    def _exited(self, child: Child, code: int, now: float) -> None:
        child.last_code = code
        self.on_exit(child, code)
        if code == 0:
            child.state = FINISHED
            log.info("%s finished (exit code 0)", child.name)
            return
        progressed = self.progress(*child.progress) > child.progress_at_start
        child.exits_without_progress = 0 if progressed else child.exits_without_progress + 1
        if code in MISTAKES or child.exits_without_progress > self.max_restarts:
            child.state = FAILED
            log.error("%s %s; giving up: %s", child.name, child.last_exit, self.failure(child))
            return
        delay = restart_delay(child.exits_without_progress)
        child.state, child.restart_at = WAITING, now + delay
        log.warning("%s %s after %s; restarting it in %.0f s (see logs/%s.log)", child.name, child.last_exit,
                    "progress" if progressed else "no progress", delay, child.name)

    def failure(self, child: Child) -> str:
        """What is wrong with a child that exits without progress, in words: for a mistake, the
        last line of its log, where a daemon says why it refused to start."""
        if child.last_code in MISTAKES:
            said = [line.strip() for line in last_lines(self.log_path(child)) if line.strip()]
            return (f"{child.name} {MISTAKES[child.last_code]} ({child.last_exit}), which a restart would repeat"
                    + (f": {said[-1]}" if said else ""))
        return (f"{child.name} exited {child.exits_without_progress} times in a row without progress "
                f"(last: {child.last_exit})")

    def failing(self) -> list[Child]:
        """The children whose last exits brought no progress: given up on, or not yet."""
        return [c for c in self.children if c.exits_without_progress]

    def finished(self, name_prefix: str) -> bool:
        """Whether every child whose name starts with `name_prefix` has finished (exit code 0)."""
        return all(c.state == FINISHED for c in self.children if c.name.startswith(name_prefix))

    def stop(self, timeout: float = 30.0) -> None:
        """SIGTERM tier by tier (highest first), wait, then SIGKILL what is left."""
        for child in self.children:
            if child.state == WAITING:
                child.state = STOPPED
        for tier in sorted({c.tier for c in self.children}, reverse=True):
            group = [c for c in self.children if c.tier == tier and c.state == RUNNING and c.process.poll() is None]
            for child in group:
                child.process.terminate()
            deadline = time.monotonic() + timeout
            for child in group:
                try:
                    child.process.wait(max(deadline - time.monotonic(), 0.1))
                    log.info("%s stopped (%s)", child.name, exit_reason(child.process.returncode))
                except subprocess.TimeoutExpired:
                    log.warning("%s did not stop within %.0f s; killing it", child.name, timeout)
                    child.process.kill()
                    child.process.wait()
                child.state = STOPPED
