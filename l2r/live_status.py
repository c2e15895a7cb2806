"""The live status of `l2r up`: the job's figures and each process's state, restarts and the
reason of its last exit. On a terminal it redraws in place (rich) with log messages above it;
otherwise (a log file, CI) it prints one plain line per update and log messages as lines.
"""

from __future__ import annotations

import logging
import sys
from typing import TextIO

from rich.console import Console, Group
from rich.live import Live
from rich.table import Table
from rich.text import Text

from l2r.families import Score
from l2r.supervise import FAILED, RUNNING, WAITING, Child

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
STATE_STYLES = {RUNNING: "green", WAITING: "yellow", FAILED: "bold red"}


def _num(x, fmt: str) -> str:
    return "-" if x is None else format(x, fmt)


def status_line(s: dict, score: Score) -> str:
    """The figures of RunMetrics.snapshot in one line, evaluations in the terms of the task's `score`."""
    opensim = s.get(f"opensim_eval_{score.name}")
    frames = s.get("frames_per_s")  # camera tasks only
    return (f"[{s['time']:6.0f}s] env {s['env_steps_per_s']:7.0f} steps/s ({s['env_steps']:,})"
            + ("" if frames is None else f", {frames:.0f} frames/s")
            + f" | learner {s['updates_per_s']:5.1f} upd/s ({s['updates']:,}, v{s['version']})"
            f" | return {_num(s['recent_return'], '.2f')}"
            + ("" if score.name == "return" else f" {score.text(s[f'recent_{score.name}'])}")
            + f" | eval {score.text(s[f'eval_{score.name}'])}"
            + ("" if opensim is None else f" (OpenSim {score.shown(opensim)})")
            + f" | lag {s['policy_lag']:.0f}"
            f" | replay {s['replay_size']:,}"
            + ("" if s.get("disk_free_mb") is None else f" | disk {s['disk_free_mb']:,.1f} MB free"))


def restarts_note(children: list[Child]) -> str:
    """`restarts: actor-0 2 (last: killed by SIGKILL)` for the processes that exited, or ""."""
    exited = [c for c in children if c.last_exit]
    return "" if not exited else "restarts: " + ", ".join(
        f"{c.name} {c.restarts} (last: {c.last_exit}{', waiting' if c.state == WAITING else ''})" for c in exited)


class StatusDisplay:
    """Shows the status; a context manager around the job's main loop."""

    def __init__(self, score: Score, out: TextIO | None = None):
        self.score = score  # what evaluations are judged by
        self.out = out or sys.stdout
        self.interactive = self.out.isatty()
        self.console = Console(file=self.out) if self.interactive else None
        self._live: Live | None = None

    def log_handler(self) -> logging.Handler:
        """Where log messages go to be seen: above the live status on a terminal, stderr otherwise."""
        if not self.interactive:
            handler = logging.StreamHandler(sys.stderr)
        else:
            handler = _ConsoleHandler(self.console)
        handler.setFormatter(logging.Formatter(LOG_FORMAT))
        return handler

    def __enter__(self) -> StatusDisplay:
        if self.interactive:
            self._live = Live(Text("starting..."), console=self.console, refresh_per_second=4,
                              redirect_stdout=False, redirect_stderr=False)
            self._live.start()
        return self

    def update(self, figures: dict, children: list[Child]) -> None:
        line = status_line(figures, self.score)
        if self._live is None:
            note = restarts_note(children)
            print(line + (f" | {note}" if note else ""), file=self.out, flush=True)
            return
        table = Table(box=None, header_style="bold", pad_edge=False)
        for column in ("process", "state", "pid", "restarts", "last exit"):
            table.add_column(column)
        for c in children:
            state = Text(c.state, style=STATE_STYLES.get(c.state, ""))
            table.add_row(c.name, state, str(c.process.pid) if c.process else "-", str(c.restarts), c.last_exit or "-")
        self._live.update(Group(Text(line), table))

    def __exit__(self, *exc) -> None:
        if self._live is not None:
            self._live.stop()  # the last table stays on screen


class _ConsoleHandler(logging.Handler):
    """Log lines printed through the rich console, so they appear above the live status."""

    def __init__(self, console: Console):
        super().__init__()
        self.console = console

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.console.print(self.format(record), markup=False, highlight=False, soft_wrap=True)
        except Exception:
            self.handleError(record)
