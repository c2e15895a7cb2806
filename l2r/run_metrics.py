"""What `l2r up` hears from its daemons: the figures of its status, and metrics files people read.

It subscribes to what the daemons already publish: the learner's metrics (losses, alpha, Q,
entropy, rates), every daemon's stats, episode summaries and the learner's version beacon. It
writes them to `<run_dir>/metrics/`:

    events.out.tfevents.*   TensorBoard (`tensorboard --logdir runs/`): learner/* by updates;
                            actor/<id>/*, evaluator/<id>/*, replay/<shard>/*, train/* (episodes)
                            and eval/* (evaluation episodes: return, length and the task's
                            score) by env steps; episodes of another simulator than the actors'
                            task under train/<env>/ and eval/<env>/, e.g. eval/RunOpenSim-v0/distance
    learner.csv, actors.csv, replay.csv     one row per stats message
    episodes.csv, evaluation.csv            one row per training / evaluation episode
    status.csv                              the status line's figures, every status interval
    exits.csv                               one row per process exit while the job ran

Every CSV row starts with `time` (seconds of training in the run), `wall_time` (s since the
epoch), `env_steps` and `updates` (of the run), then the message's own values (a process's own
counter of the same name as `process_env_steps`). The run's
counters continue across `l2r up --resume`: time and env steps start from the last row of
status.csv, and the learner counts its updates on from its checkpoint.

Evaluations are judged by the task family's score (l2r.families), and the status figures that
speak of it take its name: `eval_distance` and `best_eval_distance` on the runner,
`eval_psnr` and `best_eval_psnr` on a photo task, `eval_return` and `best_eval_return` on a
standard task; a photo task's episodes.csv and evaluation.csv have a `psnr` column.
"""

from __future__ import annotations

import contextlib
import csv
import logging
import math
import os
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import IO, BinaryIO, TextIO

import zenoh
from tensorboard.compat.proto.event_pb2 import Event
from tensorboard.compat.proto.summary_pb2 import Summary
from tensorboard.summary.writer.record_writer import RecordWriter

from l2r.durable import DISK_ERRORS, FailureLog, close_quietly
from l2r.families import RUNNER, family_of, score_of
from l2r.protocol import EpisodeSummary, Keys, LearnerVersion, Stats, watched
from l2r.sim import OPENSIM_ID, PORT_ID

log = logging.getLogger("l2r.up")

LEADING = ["time", "wall_time", "env_steps", "updates"]
EPISODE_COLUMNS = ["actor", "env", "simulator", "return", "distance", "length", "version", "seed", "difficulty"]


ROWS_DROPPED = "rows are dropped until a write succeeds"
EVENTS_DROPPED = "TensorBoard events are dropped until a write succeeds"


class DroppingFile:
    """A metrics file that, after a write the disk refuses (l2r.durable.DISK_ERRORS), reports it to
    `failures` once per cause and closes: its writes are dropped until a flush opens it again."""

    failures: FailureLog
    where: Path  # the path its failures name
    _file: IO | None

    @contextlib.contextmanager
    def _on_failure(self, consequence: str):
        try:
            yield
        except OSError as e:
            if e.errno not in DISK_ERRORS:
                raise
            self.failures.failed(e, self.where, consequence)
            close_quietly(self._file)
            self._file = None


class CsvLog(DroppingFile):
    """A CSV file that gains columns as new values appear. A new column rewrites the file
    (values first appear in the first minutes of a run, so this is rare and the file small).

    A write the disk refuses (l2r.durable.DISK_ERRORS) is reported to `failures` once per cause;
    rows are then dropped until a `flush` opens the file again, cut back to its last whole row."""

    def __init__(self, path: Path, columns: list[str], failures: FailureLog):
        self.path = self.where = path
        self.columns = list(columns)
        self.failures = failures
        self._file: TextIO | None = None
        self._reopened_at: int | None = None  # where the file ended when a flush opened it again
        if path.exists() and path.stat().st_size:
            with open(path, newline="") as f:
                header = next(csv.reader(f), [])
            self.columns = header + [c for c in self.columns if c not in header]
        else:
            path.write_text(",".join(self.columns) + "\n")
        self._open()

    def _open(self) -> None:
        self._file = open(self.path, "a", newline="")
        self._writer = csv.DictWriter(self._file, self.columns, restval="")

    def write(self, row: dict) -> None:
        if self._file is None:
            return  # dropped until a flush opens the file again
        with self._on_failure(ROWS_DROPPED):
            new = [k for k in row if k not in self.columns]
            if new:
                self._rewrite(self.columns + new)
            self._writer.writerow(row)

    def _rewrite(self, columns: list[str]) -> None:
        self._file.close()
        with open(self.path, newline="") as f:
            rows = list(csv.DictReader(f))
        tmp = self.path.with_name(f".{self.path.name}.tmp")
        try:
            with open(tmp, "w", newline="") as f:
                writer = csv.DictWriter(f, columns, restval="")
                writer.writeheader()
                writer.writerows(rows)
            os.replace(tmp, self.path)
        finally:
            tmp.unlink(missing_ok=True)
        self.columns = columns
        self._open()

    def flush(self) -> None:
        with self._on_failure(ROWS_DROPPED):
            if self._file is None:
                self._reopen()
            self._file.flush()
            if self._reopened_at is not None and self._file.tell() > self._reopened_at:  # rows reached the disk
                self._reopened_at = None
                self.failures.succeeded()

    def _reopen(self) -> None:
        """Open the file again after a failed write, without the row that write cut short."""
        with open(self.path, "rb+") as f:
            size = f.seek(0, os.SEEK_END)
            f.seek(max(0, size - 65536))
            tail = f.read()
            f.truncate(size - len(tail) + tail.rfind(b"\n") + 1)
        self._open()
        self._reopened_at = self._file.tell()

    def close(self) -> None:
        with self._on_failure("its last rows are lost"):
            if self._file is not None:
                self._file.close()


def read_rows(path: Path) -> list[dict[str, str]]:
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@dataclass(frozen=True)
class RunCounters:
    """Counters of a whole run: seconds of training, env steps, updates, episodes."""

    time: float = 0.0
    env_steps: int = 0
    updates: int = 0
    episodes: int = 0

    @classmethod
    def read(cls, directory: Path) -> RunCounters:
        """Where the sessions before ended (the last row of status.csv); zeros for a new run."""
        rows = read_rows(directory / "status.csv")
        if not rows:
            return cls()
        last = rows[-1]
        return cls(float(last["time"] or 0), int(float(last["env_steps"] or 0)), int(float(last["updates"] or 0)),
                   int(float(last.get("episodes") or 0)))


class ScalarEvents(DroppingFile):
    """TensorBoard event files of scalars, as plain `simple_value`s: what every reader of event
    files understands (TensorBoard, its EventAccumulator, pandas readers).

    Written here, on the callers' threads (TensorBoard's own writer has a thread whose failures are
    tracebacks). After a write the disk refuses, events are dropped until a `flush` starts a new
    file (TensorBoard reads every file of the directory; the old one ends at its last whole event)."""

    def __init__(self, directory: Path, failures: FailureLog):
        self.directory = directory
        self.where = directory / "events.out.tfevents"
        self.failures = failures
        self.paused = False  # set while the disk is low: events are what a run needs least after episodes
        self._files = 0
        self._file: BinaryIO | None = None
        self._start_file()

    def _start_file(self) -> None:
        path = self.directory / (f"events.out.tfevents.{int(time.time()):010d}.{socket.gethostname()}."
                                 f"{os.getpid()}.{self._files}")
        self._files += 1
        self._file = open(path, "wb")
        self._records = RecordWriter(self._file)
        try:
            self._write(Event(wall_time=time.time(), file_version="brain.Event:2"))
            self._file.flush()
        except OSError:
            close_quietly(self._file)
            path.unlink(missing_ok=True)  # no empty file per failed try
            raise

    def _write(self, event: Event) -> None:
        self._records.write(event.SerializeToString())

    def add(self, tag: str, value: float, step: int, wall_time: float) -> None:
        if self._file is None or self.paused:
            return  # dropped until a flush starts a new file, or while paused
        summary = Summary(value=[Summary.Value(tag=tag, simple_value=value)])
        with self._on_failure(EVENTS_DROPPED):
            self._write(Event(wall_time=wall_time, step=int(step), summary=summary))

    def flush(self) -> None:
        with self._on_failure(EVENTS_DROPPED):
            if self._file is None:
                self._start_file()
                self.failures.succeeded()
            self._file.flush()

    def close(self) -> None:
        with self._on_failure(EVENTS_DROPPED):
            if self._file is not None:
                self._file.close()


class Counter:
    """One number a process reports again and again (env steps, updates, inserts): how often it
    rose, and its total over restarts of the process, which count from 0 again."""

    def __init__(self) -> None:
        self.last = self.base = 0.0
        self.rises = 0

    def report(self, value: float) -> None:
        if value > self.last:
            self.rises += 1
        elif value < self.last:  # a restarted process counting from the start again
            self.base += self.last
        self.last = value

    @property
    def total(self) -> float:
        return self.base + self.last


class RunMetrics:
    """Collects what the daemons publish, writes the metrics files, and gives the status figures."""

    def __init__(self, session: zenoh.Session, keys: Keys, directory: Path, recent: int = 20,
                 env_id: str = PORT_ID, simulators: dict[int, str] | None = None, shown_eval_env_id: str | None = None):
        directory.mkdir(parents=True, exist_ok=True)
        self.env_id = env_id  # the actors' task
        # The simulator whose evaluations the status line shows (OpenSim's come beside them): the
        # actors' by default; the port's for actors on l2r/RunWarp-v0 judged by port evaluators.
        self.shown_eval_env_id = shown_eval_env_id or env_id
        self.score = score_of(env_id)
        self.simulators = simulators or {}  # actor id -> env id, for the episodes of other simulators
        self._lock = threading.Lock()
        self.before = RunCounters.read(directory)  # the sessions before a --resume
        self._start = time.monotonic()
        self._stopped: float | None = None
        # The evaluation episode with the best score, as its row of evaluation.csv.
        self.best_eval = max(read_rows(directory / "evaluation.csv"), key=self._score_of_row, default=None)

        # One line per cause of failed writes, whichever file meets it first.
        self.write_failures = FailureLog(log, "metrics")
        self._tensorboard = ScalarEvents(directory, self.write_failures)
        self._csv = {name: CsvLog(directory / f"{name}.csv", columns, self.write_failures) for name, columns in {
            "learner": LEADING, "actors": LEADING + ["role", "instance"], "replay": LEADING + ["shard"],
            "episodes": LEADING + EPISODE_COLUMNS, "evaluation": LEADING + EPISODE_COLUMNS,
            "status": LEADING, "exits": LEADING + ["process", "exit_code", "reason"]}.items()}

        self.stats: dict[tuple[str, str], dict] = {}
        self._counters: dict[tuple[str, str, str], Counter] = {}
        self.train: deque[EpisodeSummary] = deque(maxlen=recent)
        self.evals: deque[EpisodeSummary] = deque(maxlen=recent)
        self.episodes = 0
        self.version = -1
        self.updates = self.before.updates  # until the learner reports its own count
        self._last_status: tuple[float, int] | None = None  # (time, env steps) of the last status
        self._subs = [session.declare_subscriber(k, self._on_stats) for k in (keys.all_stats, keys.all_metrics)]
        self._subs.append(session.declare_subscriber(keys.all_episodes, self._on_episode))
        self._subs.append(session.declare_subscriber(keys.learner_version, self._on_version))

    def pause_events(self, paused: bool) -> None:
        """Write no TensorBoard events while `paused` (the disk is low); the CSV files go on."""
        self._tensorboard.paused = paused

    # -- counters -----------------------------------------------------------------------------

    @property
    def time(self) -> float:
        """Seconds of training in the run, this session and the ones before a --resume."""
        return self.before.time + (self._stopped or time.monotonic()) - self._start

    def _env_steps(self) -> int:
        return self.before.env_steps + int(sum(c.total for (role, _, name), c in self._counters.items()
                                            if role == "actor" and name == "env_steps"))

    @property
    def env_steps(self) -> int:
        """Training env steps of the run (evaluators' steps are not training)."""
        with self._lock:
            return self._env_steps()

    def stop_clock(self) -> None:
        """Training time ends here, when the job starts stopping its processes."""
        self._stopped = self._stopped or time.monotonic()

    def counters(self) -> RunCounters:
        """The run's counters now."""
        with self._lock:
            return RunCounters(self.time, self._env_steps(), self.updates, self.before.episodes + self.episodes)

    def rises(self, role: str, instance: str, name: str) -> int:
        """How often value `name` of that process's stats has risen: its progress."""
        with self._lock:
            counter = self._counters.get((role, instance, name))
            return counter.rises if counter else 0

    def _score_of_row(self, row: dict) -> float:
        return float(row[self.score.name])

    def _count(self, role: str, instance: str, name: str, value: float) -> None:
        self._counters.setdefault((role, instance, name), Counter()).report(value)

    def _leading(self) -> dict:
        return {"time": round(self.time, 3), "wall_time": round(time.time(), 3), "env_steps": self._env_steps(),
                "updates": self.updates}

    # -- what the daemons publish -------------------------------------------------------------

    def _on_stats(self, sample: zenoh.Sample) -> None:
        stats = watched(sample, Stats)
        if stats is None:
            return
        with self._lock:
            values = stats.values
            self.stats[(stats.role, stats.instance)] = values
            for name in ("env_steps", "updates", "inserted"):
                if name in values:
                    self._count(stats.role, stats.instance, name, float(values[name]))
            if stats.role == "learner":
                self.updates = max(self.updates, int(values.get("updates", 0)))
                self.version = max(self.version, int(values.get("version", -1)))
            row = self._leading()
            if stats.role == "learner":
                step, table, prefix = int(values.get("updates", 0)), "learner", "learner"
            elif stats.role == "replay":
                step, table, prefix = row["env_steps"], "replay", f"replay/{stats.instance}"
                row["shard"] = stats.instance
            else:
                step, table, prefix = row["env_steps"], "actors", f"{stats.role}/{stats.instance}"
                row |= {"role": stats.role, "instance": stats.instance}
            # A process's own counters keep their names apart from the run's (an actor's env_steps).
            self._csv[table].write(row | {f"process_{k}" if k in LEADING else k: v for k, v in values.items()})
            for name, value in values.items():
                self._tensorboard.add(f"{prefix}/{name}", float(value), step, stats.time)

    def _on_episode(self, sample: zenoh.Sample) -> None:
        ep = watched(sample, EpisodeSummary)
        if ep is None:
            return
        with self._lock:
            self.episodes += 1
            (self.evals if ep.evaluation else self.train).append(ep)
            simulator = self.simulators.get(ep.actor_id, self.env_id)
            row = self._leading() | {
                "actor": ep.actor_id, "env": ep.env_id, "simulator": simulator, "return": ep.episode_return,
                "distance": ep.distance,
                "length": ep.length, "version": ep.policy_version, "seed": ep.seed, "difficulty": ep.difficulty,
                self.score.name: self.score.of(ep)}  # a photo task's psnr beside the columns of every task
            if ep.evaluation and (self.best_eval is None
                                  or self._score_of_row(row) > self._score_of_row(self.best_eval)):
                self.best_eval = row
            self._csv["evaluation" if ep.evaluation else "episodes"].write(row)
            # The actors' task's episodes under eval/ and train/, another simulator's under eval/<its name>/.
            prefix = ("eval" if ep.evaluation else "train") + ("" if simulator == self.env_id else f"/{simulator.split('/')[-1]}")
            for name in dict.fromkeys(("return", self.score.name, "length")):
                self._tensorboard.add(f"{prefix}/{name}", float(row[name]), row["env_steps"], ep.time)

    def _on_version(self, sample: zenoh.Sample) -> None:
        beacon = watched(sample, LearnerVersion)
        if beacon is None:
            return
        with self._lock:
            self.version = max(self.version, beacon.version)
            self.updates = max(self.updates, beacon.updates)
            self._count("learner", "0", "updates", float(beacon.updates))

    def note_exit(self, process: str, code: int, reason: str) -> None:
        with self._lock:
            self._csv["exits"].write(self._leading() | {"process": process, "exit_code": code, "reason": reason})

    # -- figures ------------------------------------------------------------------------------

    def snapshot(self) -> dict:
        """The figures of the status line, as numbers."""
        with self._lock:
            by_role: dict[str, list[dict]] = {}
            for (role, _), values in self.stats.items():
                by_role.setdefault(role, []).append(values)
            actors, learners, replays = by_role.get("actor", []), by_role.get("learner", []), by_role.get("replay", [])

            def total(rows, key):
                return sum(float(v.get(key, 0.0)) for v in rows)

            def mean(eps, value=self.score.of):
                return sum(map(value, eps)) / len(eps) if eps else None

            def evals_in(simulator):
                return [e for e in self.evals if self.simulators.get(e.actor_id, self.env_id) == simulator]

            name = self.score.name
            cameras = [v for v in actors if "frames_per_s" in v]  # actors of camera tasks
            return {
                "time": self.time,
                "env_steps": self._env_steps(),
                "env_steps_per_s": total(actors, "env_steps_per_s"),
                **({"frames_per_s": total(cameras, "frames_per_s")} if cameras else {}),
                "updates": self.updates,
                "updates_per_s": total(learners, "updates_per_s"),
                "version": self.version,
                "policy_lag": max([lag for v in replays + learners if math.isfinite(lag := float(v.get("policy_lag", 0.0)))] or [0.0]),
                "actor_staleness": max([float(v.get("staleness", 0.0)) for v in actors] or [0.0]),
                "replay_size": int(total(replays, "size") + total(actors, "replay_size")),  # + a colocated ring
                "episodes": self.before.episodes + self.episodes,
                "recent_return": mean(self.train, lambda e: e.episode_return),
                f"recent_{name}": mean(self.train),
                f"eval_{name}": mean(evals_in(self.shown_eval_env_id)),
                # OpenSim, the runner's second simulator
                **({f"opensim_eval_{name}": mean(evals_in(OPENSIM_ID))} if family_of(self.env_id) == RUNNER else {}),
                f"best_eval_{name}": None if self.best_eval is None else self._score_of_row(self.best_eval),
            }

    def record_status(self) -> dict:
        """Write the status figures to status.csv, flush every file, and return the figures. Env
        steps (and frames) per second are over the interval since the last status: an actor's
        own two-second rate reads 0 whenever replay holds it, which in a learner-bound job (one
        gradient step per env step) is most of the time, however fast the job moves."""
        figures = self.snapshot()
        with self._lock:
            if self._last_status is not None and figures["time"] > self._last_status[0]:
                then, steps_then = self._last_status
                per_s = (figures["env_steps"] - steps_then) / (figures["time"] - then)
                if "frames_per_s" in figures:
                    cameras = [v for (role, _), v in self.stats.items() if role == "actor" and "frames" in v]
                    steps = sum(float(v["env_steps"]) for v in cameras)
                    figures["frames_per_s"] = per_s * (sum(float(v["frames"]) for v in cameras) / steps if steps else 1.0)
                figures["env_steps_per_s"] = per_s
            self._last_status = (figures["time"], figures["env_steps"])
            self._csv["status"].write(self._leading() | {k: ("" if v is None else v) for k, v in figures.items()
                                                         if k not in LEADING})
            for table in self._csv.values():
                table.flush()
            self._tensorboard.flush()
        return figures

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        with self._lock:
            for table in self._csv.values():
                table.close()
            self._tensorboard.close()
