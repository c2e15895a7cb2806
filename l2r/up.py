"""`l2r up`: a whole training job on this host.

Starts one replay server, one learner and N actors (plus an evaluator) as separate processes
that talk over loopback Zenoh: the replay server and the learner listen on free 127.0.0.1
ports, everyone else connects to both, multicast scouting is off, and no router is needed.
It watches them (a crashed process is restarted; the learner resumes from its checkpoint),
prints a live status line from the stats and episode summaries the daemons publish, and stops
everything when the budget is spent or on Ctrl-C / SIGTERM: actors first, then the learner
(which checkpoints), then the replay server (which snapshots).

The run directory `runs/<name>-<timestamp>/` keeps:
    logs/<process>.log    one log per process (a restarted one appends)
    learner/              the learner's checkpoints (`l2r eval` takes this run directory)
    replay/               replay snapshots
    episodes/             MCAP logs of every Nth training episode and of evaluation episodes
    metrics.jsonl         status snapshots ("status") and episode summaries ("episode")
    summary.json          the final status, restarts and the best evaluation episode
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import signal
import sys
import threading
import time
from datetime import datetime, timezone
from pathlib import Path

import os
import socket
import subprocess
from collections import deque
from dataclasses import dataclass, field

import zenoh

from l2r.protocol import (
    EpisodeSummary, Keys, LearnerVersion, ProtocolError, Stats, decode, session_config,
)
from l2r.view import best_episode, write_recording

log = logging.getLogger("l2r.up")


# -- processes ---------------------------------------------------------------------------------

def loopback(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def free_port() -> int:
    """A TCP port free on 127.0.0.1 right now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@dataclass
class Child:
    """One daemon of the job. Higher tiers stop first (actors, then learner, then replay)."""

    name: str
    argv: list[str]
    tier: int
    resume_args: list[str] = field(default_factory=list)
    nice: int = 0
    process: subprocess.Popen | None = None
    restarts: int = 0
    crash_times: deque = field(default_factory=deque)


class ProcessGroup:
    """Starts the children with one log file each, restarts the ones that exit, stops them in tiers."""

    def __init__(self, children: list[Child], log_dir: Path, resume: bool = False,
                 max_crashes: int = 5, crash_window: float = 60.0):
        self.children = children
        self.log_dir = log_dir
        self.resume = resume
        self.max_crashes, self.crash_window = max_crashes, crash_window

    def _spawn(self, child: Child, resume: bool) -> None:
        argv = child.argv + (child.resume_args if resume else [])
        with open(self.log_dir / f"{child.name}.log", "ab") as out:
            # A session of its own: a Ctrl-C at the terminal reaches `l2r up` only, which then
            # stops the children in order.
            child.process = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                             start_new_session=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
                                             preexec_fn=(lambda: os.nice(child.nice)) if child.nice else None)
        log.info("started %s (pid %d)%s", child.name, child.process.pid, " with --resume" if resume and child.resume_args else "")

    def start(self) -> None:
        for child in self.children:
            self._spawn(child, self.resume)

    def supervise(self, on_restart) -> bool:
        """Restart every child that exited; False when one crashed too often to go on."""
        now = time.monotonic()
        for child in self.children:
            code = child.process.poll()
            if code is None:
                continue
            child.crash_times.append(now)
            while child.crash_times and now - child.crash_times[0] > self.crash_window:
                child.crash_times.popleft()
            if len(child.crash_times) > self.max_crashes:
                log.error("%s exited %d times within %.0f s (last code %s); giving up, see logs/%s.log",
                          child.name, len(child.crash_times), self.crash_window, code, child.name)
                return False
            log.warning("%s exited with code %s; restarting it (see logs/%s.log)", child.name, code, child.name)
            child.restarts += 1
            on_restart(child.name, code)
            self._spawn(child, resume=True)
        return True

    def stop(self, timeout: float = 30.0) -> None:
        """SIGTERM tier by tier (highest first), wait, then SIGKILL what is left."""
        for tier in sorted({c.tier for c in self.children}, reverse=True):
            group = [c for c in self.children if c.tier == tier and c.process and c.process.poll() is None]
            for child in group:
                child.process.terminate()
            deadline = time.monotonic() + timeout
            for child in group:
                try:
                    child.process.wait(max(deadline - time.monotonic(), 0.1))
                    log.info("%s stopped (code %s)", child.name, child.process.returncode)
                except subprocess.TimeoutExpired:
                    log.warning("%s did not stop within %.0f s; killing it", child.name, timeout)
                    child.process.kill()
                    child.process.wait()


# -- status --------------------------------------------------------------------------------------

class StatusBoard:
    """Collects what the daemons publish, writes metrics.jsonl, and renders the status line."""

    def __init__(self, session: zenoh.Session, keys: Keys, metrics_path: Path, recent: int = 20):
        self._lock = threading.Lock()
        self._out = open(metrics_path, "a")
        self._t0 = time.time()
        self.stats: dict[tuple[str, str], dict] = {}
        self._steps_base: dict[str, int] = {}  # steps of earlier incarnations of each actor
        self._steps_last: dict[str, int] = {}
        self.train: deque[EpisodeSummary] = deque(maxlen=recent)
        self.evals: deque[EpisodeSummary] = deque(maxlen=recent)
        self.best_eval: EpisodeSummary | None = None
        self.episodes = 0
        self.version = -1
        self.restarts: dict[str, int] = {}
        self._subs = [session.declare_subscriber(k, self._on_stats) for k in (keys.all_stats, keys.all_metrics)]
        self._subs.append(session.declare_subscriber(keys.all_episodes, self._on_episode))
        self._subs.append(session.declare_subscriber(keys.learner_version, self._on_version))

    def _write(self, record: dict) -> None:
        self._out.write(json.dumps(record) + "\n")

    def _on_stats(self, sample: zenoh.Sample) -> None:
        try:
            stats = decode(sample.payload, Stats)
        except ProtocolError as e:
            log.debug("ignored stats on %s: %s", sample.key_expr, e)
            return
        with self._lock:
            self.stats[(stats.role, stats.instance)] = stats.values
            if stats.role == "actor" and "env_steps" in stats.values:
                steps = int(stats.values["env_steps"])
                if steps < self._steps_last.get(stats.instance, 0):  # a restarted actor counts from 0
                    self._steps_base[stats.instance] = self._steps_base.get(stats.instance, 0) + self._steps_last[stats.instance]
                self._steps_last[stats.instance] = steps

    def _on_episode(self, sample: zenoh.Sample) -> None:
        try:
            ep = decode(sample.payload, EpisodeSummary)
        except ProtocolError as e:
            log.debug("ignored episode summary on %s: %s", sample.key_expr, e)
            return
        with self._lock:
            self.episodes += 1
            (self.evals if ep.evaluation else self.train).append(ep)
            if ep.evaluation and (self.best_eval is None or ep.distance > self.best_eval.distance):
                self.best_eval = ep
            self._write({"type": "episode", "t": time.time() - self._t0, "actor": ep.actor_id, "env": ep.env_id,
                         "evaluation": ep.evaluation, "return": ep.episode_return, "distance": ep.distance,
                         "length": ep.length, "version": ep.policy_version, "seed": ep.seed,
                         "difficulty": ep.difficulty})

    def _on_version(self, sample: zenoh.Sample) -> None:
        try:
            self.version = max(self.version, decode(sample.payload, LearnerVersion).version)
        except ProtocolError:
            pass

    def note_restart(self, name: str, code: int | None) -> None:
        with self._lock:
            self.restarts[name] = self.restarts.get(name, 0) + 1
            self._write({"type": "restart", "t": time.time() - self._t0, "process": name, "exit_code": code})

    @property
    def env_steps(self) -> int:
        with self._lock:
            return sum(self._steps_base.values()) + sum(self._steps_last.values())

    def snapshot(self) -> dict:
        """The figures of the status line, as numbers."""
        env_steps = self.env_steps
        with self._lock:
            by_role: dict[str, list[dict]] = {}
            for (role, _), values in self.stats.items():
                by_role.setdefault(role, []).append(values)
            actors, learners, replays = by_role.get("actor", []), by_role.get("learner", []), by_role.get("replay", [])

            def total(rows, key):
                return sum(float(v.get(key, 0.0)) for v in rows)

            def mean(eps, attr):
                return sum(getattr(e, attr) for e in eps) / len(eps) if eps else None

            return {
                "env_steps": env_steps,
                "env_steps_per_s": total(actors, "env_steps_per_s"),
                "updates": int(total(learners, "updates")),
                "updates_per_s": total(learners, "updates_per_s"),
                "version": max([self.version] + [int(v.get("version", -1)) for v in learners]),
                "policy_lag": max([lag for v in replays + learners if math.isfinite(lag := float(v.get("policy_lag", 0.0)))] or [0.0]),
                "actor_staleness": max([float(v.get("staleness", 0.0)) for v in actors] or [0.0]),
                "replay_size": int(total(replays, "size")),
                "episodes": self.episodes,
                "recent_return": mean(self.train, "episode_return"),
                "recent_distance": mean(self.train, "distance"),
                "eval_distance": mean(self.evals, "distance"),
                "best_eval_distance": self.best_eval.distance if self.best_eval else None,
                "restarts": sum(self.restarts.values()),
            }

    def show(self, elapsed: float, final: bool = False) -> None:
        s = self.snapshot()
        with self._lock:
            self._write({"type": "status", "t": time.time() - self._t0, "elapsed": elapsed, **s})
            self._out.flush()

        def num(x, fmt):
            return "-" if x is None else format(x, fmt)

        line = (f"[{elapsed:6.0f}s] env {s['env_steps_per_s']:7.0f} steps/s ({s['env_steps']:,})"
                f" | learner {s['updates_per_s']:5.1f} upd/s ({s['updates']:,}, v{s['version']})"
                f" | return {num(s['recent_return'], '.2f')} distance {num(s['recent_distance'], '.2f')} m"
                f" | eval {num(s['eval_distance'], '.2f')} m | lag {s['policy_lag']:.0f}"
                f" | replay {s['replay_size']:,}" + (f" | restarts {s['restarts']}" if s["restarts"] else ""))
        if sys.stdout.isatty() and not final:
            print("\r" + line + "\x1b[K", end="", flush=True)
        else:
            print(line, flush=True)

    def summary(self) -> dict:
        s = self.snapshot()
        best = self.best_eval
        s["best_eval_episode"] = None if best is None else {
            "actor": best.actor_id, "seed": best.seed, "version": best.policy_version,
            "distance": best.distance, "return": best.episode_return, "length": best.length}
        s["restarts_by_process"] = dict(self.restarts)
        return s

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        with self._lock:
            self._out.close()


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="l2r up",
        description="Train on this host: start a replay server, a learner and actors as separate "
                    "processes over loopback Zenoh, show their progress, restart what crashes, and "
                    "stop everything when the budget is spent or on Ctrl-C. The defaults are a short "
                    "CPU demo (what `make run` starts); raise --seconds for real training.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    b = p.add_argument_group("budget (whichever is spent first)")
    b.add_argument("--seconds", type=float, default=100.0, help="wall-clock budget of the training (0: none)")
    b.add_argument("--env-steps", type=int, default=0, help="budget in actor steps, summed over actors (0: none)")
    r = p.add_argument_group("run")
    r.add_argument("--name", default="l2r", help="run name; the directory is <runs-dir>/<name>-<UTC timestamp>")
    r.add_argument("--runs-dir", type=Path, default=Path("runs"), help="where run directories go")
    r.add_argument("--resume", type=Path, metavar="RUN_DIR",
                   help="continue a run directory: the learner resumes its checkpoint, replay restores its snapshot")
    r.add_argument("--seed", type=int, default=0, help="base seed of the actors' episodes")
    a = p.add_argument_group("actors")
    a.add_argument("--actors", type=int, default=2, help="actor processes")
    a.add_argument("--envs-per-actor", type=int, default=2, help="environments per actor, batched in one policy call")
    a.add_argument("--difficulty", type=int, choices=(0, 1, 2), default=0, help="0 flat, 1 obstacles, 2 obstacles + weak psoas")
    a.add_argument("--action-repeat", type=int, default=3, help="0.01 s environment steps per action")
    a.add_argument("--random-steps", type=int, default=1000,
                   help="uniform random steps of each actor before it uses the policy (warm-up)")
    a.add_argument("--evaluators", type=int, default=1,
                   help="evaluator processes: deterministic episodes on fixed seeds for each new policy")
    a.add_argument("--eval-episodes", type=int, default=2, help="episodes per evaluation round")
    a.add_argument("--eval-interval", type=float, default=20.0, help="least seconds between evaluation rounds")
    a.add_argument("--eval-env-id", metavar="ENV_ID",
                   help="gymnasium id of the evaluators' environment, e.g. l2r/RunOpenSim-v0 to measure the policy "
                        "on OpenSim 4.6 as in 2017 while the actors train on MuJoCo; unset, the evaluators run the "
                        "actors' environment (l2r/Run-v0 unless --actor-arg=--env-id=... names another)")
    a.add_argument("--log-every", type=int, default=10,
                   help="actors log every Nth training episode as MCAP under episodes/ (0: none); "
                        "evaluation episodes are always logged")
    a.add_argument("--actor-nice", type=int, default=10,
                   help="niceness of actors and evaluators: on a machine with few cores the learner, at normal "
                        "priority, gets the CPU it needs and the actors use what is left (0: equal priority)")
    a.add_argument("--no-episode-logs", action="store_true", help="write no MCAP episode logs at all")
    le = p.add_argument_group("learner and replay")
    le.add_argument("--device", default="cpu", choices=("auto", "cpu", "cuda"), help="learner device")
    le.add_argument("--learner-threads", type=int, default=0,
                    help="torch CPU threads of the learner; 0: the cores left after one per actor or evaluator and one for "
                         "replay, at least 1 (oversubscribed threads wait on each other and slow every update)")
    le.add_argument("--batch-size", type=int, default=256, help="learner batch size")
    le.add_argument("--min-replay", type=int, default=1000, help="transitions stored before the learner starts")
    le.add_argument("--samples-per-insert", type=float, default=0.0,
                    help="replay rate limit: sampled transitions per inserted one (0: no limit)")
    le.add_argument("--capacity", type=int, default=1_000_000, help="replay capacity in transitions")
    le.add_argument("--learner-arg", action="append", default=[], metavar="ARG",
                    help="extra argument for l2r-learner, e.g. --learner-arg=--lr=3e-4 (repeatable)")
    le.add_argument("--replay-arg", action="append", default=[], metavar="ARG",
                    help="extra argument for l2r-replay (repeatable)")
    le.add_argument("--actor-arg", action="append", default=[], metavar="ARG",
                    help="extra argument for every l2r-actor, evaluators included, e.g. "
                         "--actor-arg=--env-id=l2r/RunOpenSim-v0 (repeatable)")
    o = p.add_argument_group("output")
    o.add_argument("--status-interval", type=float, default=2.0, help="seconds between status updates")
    o.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                   help="log level of every process")
    return p


def make_run_dir(args: argparse.Namespace) -> Path:
    if args.resume:
        if not args.resume.is_dir():
            raise SystemExit(f"l2r up: --resume {args.resume}: no such run directory")
        return args.resume
    stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S")
    run_dir = args.runs_dir / f"{args.name}-{stamp}"
    run_dir.mkdir(parents=True, exist_ok=False)
    return run_dir


def learner_threads(args: argparse.Namespace) -> int:
    return args.learner_threads or max(1, (os.cpu_count() or 1) - args.actors - args.evaluators - 1)


def plan_children(args: argparse.Namespace, run: str, run_dir: Path, replay_port: int, learner_port: int) -> list[Child]:
    """The processes of the job, in start order (stopped in reverse)."""
    replay_ep, learner_ep = loopback(replay_port), loopback(learner_port)
    # Everyone also listens on an ephemeral loopback port, so Zenoh's gossip meshes the peers.
    common = ["--run", run, "--log-level", args.log_level]
    py = [sys.executable, "-m"]
    children = [Child("replay", tier=0,
                      argv=py + ["l2r.replay", *common, "--listen", replay_ep,
                                 "--capacity", str(args.capacity), "--min-size", str(args.min_replay),
                                 "--samples-per-insert", str(args.samples_per_insert),
                                 "--snapshot-dir", str(run_dir / "replay"), *args.replay_arg])]
    children.append(Child("learner", tier=1, resume_args=["--resume"],
                          argv=py + ["l2r.learner", *common, "--listen", learner_ep, "--connect", replay_ep,
                                     "--device", args.device, "--batch-size", str(args.batch_size),
                                     "--threads", str(learner_threads(args)),
                                     "--run-dir", str(run_dir), *args.learner_arg]))
    peers = ["--connect", replay_ep, "--connect", learner_ep, "--listen", "tcp/127.0.0.1:0"]
    acting = ["--num-envs", str(args.envs_per_actor), "--difficulty", str(args.difficulty),
              "--action-repeat", str(args.action_repeat), "--seed", str(args.seed)]
    logs = [] if args.no_episode_logs else ["--episode-log-dir", str(run_dir / "episodes"), "--log-every", str(args.log_every)]
    for i in range(args.actors):
        children.append(Child(f"actor-{i}", tier=2, nice=args.actor_nice,
                              argv=py + ["l2r.actors", *common, *peers, *acting, "--actor-id", str(i),
                                         "--random-steps", str(args.random_steps), *logs, *args.actor_arg]))
    # Last on the evaluators' command line, so it overrides an --env-id among the actor arguments.
    eval_env = [] if args.eval_env_id is None else ["--env-id", args.eval_env_id]
    for i in range(args.evaluators):
        # Evaluators take ids after the actors' so their keys never collide.
        children.append(Child(f"evaluator-{i}", tier=2, nice=args.actor_nice,
                              argv=py + ["l2r.actors", *common, *peers, *acting, "--evaluate",
                                         "--actor-id", str(args.actors + i),
                                         "--num-envs", str(min(args.eval_episodes, args.envs_per_actor)),
                                         "--eval-episodes", str(args.eval_episodes),
                                         "--eval-interval", str(args.eval_interval), *logs, *args.actor_arg,
                                         *eval_env]))
    return children


def after_run(run_dir: Path, board: StatusBoard) -> dict:
    """What the run leaves besides logs and checkpoints: summary.json, and best_eval.rrd, a Rerun
    recording of the logged evaluation episode with the highest return."""
    summary = board.summary()
    best = best_episode(run_dir / "episodes")
    if best is not None:
        try:
            summary["best_eval_recording"] = str(write_recording([best], run_dir / "best_eval.rrd"))
        except Exception as e:  # a convenience: the run's results are saved whatever happens here
            log.warning("no recording of the best evaluation episode (%s): %s", best.name, e)
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def cli(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.actors < 1 or args.envs_per_actor < 1:
        raise SystemExit("l2r up: --actors and --envs-per-actor must be at least 1")
    run_dir = make_run_dir(args)
    (run_dir / "logs").mkdir(exist_ok=True)
    logging.basicConfig(level=getattr(logging, args.log_level), format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        handlers=[logging.FileHandler(run_dir / "logs" / "up.log"), logging.StreamHandler(sys.stderr)])
    run = run_dir.name
    replay_port, learner_port = free_port(), free_port()
    (run_dir / "launch.json").write_text(json.dumps(
        {"argv": sys.argv[1:] if argv is None else argv, "zenoh_run": run, "replay_port": replay_port,
         "learner_port": learner_port, **{k: str(v) for k, v in vars(args).items()}}, indent=2) + "\n")

    stop = threading.Event()
    reason = ["interrupted"]

    def on_signal(signum, _frame):
        reason[0] = signal.Signals(signum).name
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)

    children = plan_children(args, run, run_dir, replay_port, learner_port)
    group = ProcessGroup(children, run_dir / "logs", resume=args.resume is not None)
    conf = session_config(connect=[loopback(replay_port), loopback(learner_port)], listen=["tcp/127.0.0.1:0"])
    print(f"l2r up: run directory {run_dir}  (Zenoh run {run!r}; Ctrl-C stops cleanly)", file=sys.stderr)
    log.info("starting %s", ", ".join(c.name for c in children))
    code = 0
    with zenoh.open(conf) as session:
        token = session.liveliness().declare_token(Keys(run).alive("launcher", 0))
        board = StatusBoard(session, Keys(run), run_dir / "metrics.jsonl")
        group.start()
        started = time.monotonic()
        next_status = started + args.status_interval
        try:
            while not stop.wait(0.25):
                if not group.supervise(board.note_restart):
                    reason[0], code = "a process keeps crashing (see logs/)", 1
                    break
                elapsed = time.monotonic() - started
                if args.seconds and elapsed >= args.seconds:
                    reason[0] = f"time budget of {args.seconds:g} s spent"
                    break
                if args.env_steps and board.env_steps >= args.env_steps:
                    reason[0] = f"budget of {args.env_steps} env steps spent"
                    break
                if time.monotonic() >= next_status:
                    board.show(elapsed)
                    next_status += args.status_interval
        finally:
            board.show(time.monotonic() - started, final=True)
            print(f"\nl2r up: stopping ({reason[0]})", file=sys.stderr)
            log.info("stopping: %s", reason[0])
            group.stop()
            board.close()
            token.undeclare()
    summary = after_run(run_dir, board)
    best = summary["best_eval_distance"]
    checkpoint = run_dir / "learner" / "checkpoint.pt"
    print(f"l2r up: done. {summary['env_steps']:,} env steps, {summary['updates']:,} updates, best evaluation "
          f"distance {'-' if best is None else f'{best:.2f} m'}\n        run directory: {run_dir}\n        "
          + (f"evaluate with: l2r eval {run_dir}" if checkpoint.exists() else "no learner checkpoint was written")
          + (f"\n        watch the best evaluation episode: rerun {summary['best_eval_recording']}"
             if "best_eval_recording" in summary else ""),
          file=sys.stderr)
    return code
