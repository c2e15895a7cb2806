"""`l2r up`: a whole training job on this host.

Starts a replay server (or --replay-shards of them), one learner and N actors (plus an
evaluator) as separate processes that talk over loopback Zenoh: the replay shards and the learner
listen on free 127.0.0.1 ports, everyone else connects to all of them, multicast scouting is off,
and no router is needed.
`l2r.job_plan` plans each process's command line from the flags and the recipe,
`l2r.supervise` restarts what exits and gives up on what keeps failing, `l2r.run_metrics`
writes what the daemons publish to metrics files, `l2r.best_policy` keeps the best evaluated
policy, `l2r.live_status` shows it all. The job stops when its budget is spent, on Ctrl-C /
SIGTERM, or when it gives up on a process: actors first, then the learner (which checkpoints),
then the replay shards (which snapshot).

The run directory `runs/<name>-<timestamp>/` keeps:
    launch.json           the run's flags (reused by --resume), the recipe they resolve to, Zenoh run
                          name, each session's ports
    logs/<process>.log    one log per process (a restarted one appends)
    learner/              the learner's checkpoints and best.pt (`l2r eval` takes this run directory)
    replay/               replay snapshots
    episodes/             MCAP logs of every Nth training episode and of evaluation episodes
    metrics/              TensorBoard event files and CSV files (see l2r.run_metrics)
    summary.json          how the job ended, the final figures, restarts, the best evaluation
                          episode (by the task family's score, l2r.families) and the best
                          evaluated policy
    best_eval.rrd         a Rerun recording of that same best evaluation episode
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import signal
import sys
import threading
import time
import tomllib
import zipfile
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import zenoh

import l2r.control  # noqa: F401  (registers the camera tasks' ids, so --env-id can name them)
import l2r.photo  # noqa: F401  (registers the photo tasks' ids)
from l2r import disk_budget, opensim_stage
from l2r.actors.curriculum import DifficultySchedule
from l2r.actors.noise import COLOURS
from l2r.best_policy import BestPolicy
from l2r.config import EXIT_FAILURE, EXIT_USAGE, CommandParser
from l2r.durable import DISK_ERRORS, MB, FileLogHandler, disk_failure, free_bytes
from l2r.encoders import DRQ, check_observation
from l2r.episodes.read import find_episode
from l2r.families import FAMILIES, PHOTO, PIXELS, RUNNER, Score, family_of, score_of
from l2r.job_plan import (
    IMAGE_CAPACITY, PHOTO_CAPACITY, VECTOR_CAPACITY, evaluator_env_ids, free_ports, loopback, plan_children,
    recipe_of, replay_capacity, shard_capacities, shown_evaluations, simulator_of_each_actor,
)
from l2r.learner.algorithms import ON_POLICY
from l2r.learner.checkpoint import CheckpointError, checkpoint_path, find_checkpoint, load_checkpoint
from l2r.learner.sac import HIDDEN_WIDTHS
from l2r.live_status import StatusDisplay
from l2r.photo.env import GOALS
from l2r.protocol import Keys, session_config
from l2r.recipes import ADDED_SINCE, CHOICES, RECIPES, SETTINGS, shown_values
from l2r.replay.queue import QueueConfig
from l2r.replay.snapshot import snapshot_path
from l2r.run_metrics import RunCounters, RunMetrics
from l2r.sim import PORT_ID, randomize_refusal
from l2r.sim.randomize import Randomization
from l2r.spaces import image_size_option, photo_goals_option, task_spaces
from l2r.supervise import ProcessGroup, last_lines

log = logging.getLogger("l2r.up")


# Flags a --resume does not take from launch.json: they name the run directory, not the job, or
# the --config file, whose values launch.json keeps as the flags they set.
NOT_REUSED = {"resume", "name", "runs_dir", "config"}


class _HelpDefaults(argparse.ArgumentDefaultsHelpFormatter):
    """Defaults shown in the help, except None: such a flag's help says what unset means."""

    def _get_help_string(self, action: argparse.Action) -> str:
        return action.help if action.default is None else super()._get_help_string(action)


# Recipe settings of text whose form a metavar says.
METAVARS = {"randomize": "NAME=FRACTION,...", "difficulty_schedule": "TRIGGER:DIFFICULTY,..."}


def _recipe_flag(name: str, text: str) -> dict:
    """add_argument's options for a setting of the recipes: no default (the recipe's), the type of
    the recipes' values, a switch with a --no- form for on/off ones."""
    kind = type(next(table[name] for table in RECIPES.values() if name in table))
    options = {"help": f"{text}; unset, the recipe's: {shown_values(name)}", "choices": CHOICES.get(name)}
    if kind is bool:
        return options | {"action": argparse.BooleanOptionalAction}
    metavar = {int: "N", float: "X"}.get(kind) or METAVARS.get(name)
    return options | {"type": kind} | ({"metavar": metavar} if metavar else {})


def build_parser() -> argparse.ArgumentParser:
    p = CommandParser(
        prog="l2r up",
        description="Train on this host: start a replay server, a learner and actors as separate "
                    "processes over loopback Zenoh, show their progress, restart what exits, give up on "
                    "what keeps failing, and stop everything when the budget is spent or on Ctrl-C. "
                    "Metrics go to RUN_DIR/metrics (TensorBoard and CSV: tensorboard --logdir runs/). "
                    "The defaults are a short CPU demo (what `make run` starts); raise --seconds for real "
                    "training.",
        epilog="Exit codes: 0 the budget was spent (or Ctrl-C); 1 the job gave up on a process, the disk "
               "filled, or the learner made no update; 2 bad usage, or a run that may not fit on its disk.",
        formatter_class=_HelpDefaults,
    )
    p.add_argument("--config", type=Path, metavar="FILE.toml",
                   help="TOML file of flags, keys being the long flag names (seconds = 7200, eval-env-id = "
                        "[\"l2r/Run-v0\"], mirror = false); the command line wins over it, and it wins over the "
                        "flags stored in launch.json on --resume")
    b = p.add_argument_group("budget of the whole run, whichever is spent first; time and env steps "
                             "continue across --resume")
    b.add_argument("--seconds", type=float, default=100.0, help="seconds of training (0: no limit)")
    b.add_argument("--env-steps", type=int, default=0, help="actor steps, summed over actors (0: no limit)")
    r = p.add_argument_group("run")
    r.add_argument("--name", default="l2r", help="run name; the directory is <runs-dir>/<name>-<UTC timestamp>")
    r.add_argument("--runs-dir", type=Path, default=Path("runs"), help="where run directories go")
    r.add_argument("--resume", type=Path, metavar="RUN_DIR",
                   help="continue a run directory with the flags in its launch.json (a flag given again "
                        "replaces the stored one): the learner resumes its checkpoint, replay restores its "
                        "snapshot, time and env-step counters go on")
    r.add_argument("--seed", type=int, default=0, help="base seed of the actors' episodes")
    r.add_argument("--force", action="store_true",
                   help="start even when the run may write more than its disk has free (the start-up estimate "
                        "of replay, episode logs, checkpoints and metrics, docs/training.md \"Disk use\"): a "
                        "warning instead of exit code 2. While it runs, the job stops when the free space falls "
                        "below what the learner's last checkpoint needs, whatever this flag says")
    r.add_argument("--max-restarts", type=int, default=3,
                   help="restarts of one process in a row without progress (learner updates, env steps, "
                        "replay inserts) before the job gives up on it and exits with code 1; a process that "
                        "refuses to start (exit code 2 or 3) is given up on at once")
    a = p.add_argument_group("actors")
    a.add_argument("--env-id", default=PORT_ID,
                   help="gymnasium id of the task: the runner; another with Box actions, such as Hopper-v5 (the "
                        "replay server and learner then take its observation spec, the job trains with the standard "
                        "recipe, and the runner's own options are off: --relative-x, --mirror, the actors' blow-up "
                        "check); or a camera task, l2r/dmc-<domain>-<task>-v0 such as l2r/dmc-cartpole-swingup-v0 "
                        "(84 x 84 frames, --algo td3: DrQ-v2's pixels recipe, --algo sac: DrQ's); or the photo "
                        "tuner l2r/PhotoTune-v0 (RLPixTuner's photo recipe, --algo td3, scored by PSNR in dB), or the photo enhancer "
                        "l2r/PhotoEnhanceStats-v0 (--algo ppo, the photo/ppo recipe, scored by PSNR in dB)")
    a.add_argument("--actors", type=int, default=1, help="actor processes")
    a.add_argument("--image-size", type=int, metavar="PIXELS",
                   help="a camera task's frames, pixels a side (default: the task's own, 84 as DrQ-v2's); smaller "
                        "frames render and train faster on a CPU (48: about 4x fewer updates' FLOPs than 84)")
    a.add_argument("--photo-goals", choices=GOALS,
                   help="the photo tuner's goals, for its actors and evaluators: random (the crop finished with hidden "
                        "random parameters), looks (the crop with another scene's look) or mixed (either, with even "
                        "odds each episode) (default: the task's own, random)")
    a.add_argument("--difficulty", type=int, choices=(0, 1, 2), default=0, help="0 flat, 1 obstacles, 2 obstacles + weak psoas")
    a.add_argument("--evaluators", type=int, default=1,
                   help="evaluator processes: deterministic episodes on fixed seeds for each new policy")
    a.add_argument("--eval-episodes", type=int, default=2,
                   help="episodes per evaluation round, on seeds --seed, --seed + 1, ... (the same every round)")
    a.add_argument("--eval-difficulty", type=int, choices=(0, 1, 2),
                   help="the evaluators' difficulty, the runner's (default: --difficulty): with --eval-difficulty 2 "
                        "and --eval-episodes 20, best.pt is the policy that ran furthest over seeds 0-19 of the "
                        "obstacle course, whatever the training actors run (--difficulty-schedule)")
    a.add_argument("--eval-interval", type=float, default=20.0, help="least seconds between evaluation rounds")
    a.add_argument("--eval-env-id", metavar="ENV_ID", action="append", default=[],
                   help="gymnasium id of the evaluators' environment, e.g. l2r/RunOpenSim-v0 to measure the policy "
                        "on OpenSim 4.6 as in 2017 while the actors train on MuJoCo. Repeatable: the evaluators take "
                        "the ids in turn, at least one evaluator per id, so --eval-env-id l2r/Run-v0 --eval-env-id "
                        "l2r/RunOpenSim-v0 draws the curves of both simulators; the first id judges learner/best.pt. "
                        "Unset, the evaluators run the actors' environment")
    a.add_argument("--opensim-actors", type=int, default=0,
                   help="of the --actors, how many step l2r/RunOpenSim-v0 (OpenSim 4.6, about 100 steps/s) instead "
                        "of the actors' environment: experience from the simulator that judges, mixed in replay")
    a.add_argument("--log-every", type=int, default=10,
                   help="actors log every Nth training episode as MCAP under episodes/ (0: none; the runner, "
                        "camera and photo tasks only); evaluation episodes are always logged")
    a.add_argument("--actor-nice", type=int, default=0,
                   help="niceness of actors and evaluators: above 0, on a machine with few cores the learner, at "
                        "normal priority, gets the CPU it needs and the actors use what is left (which two jobs "
                        "at once on 2 cores turn into actors all but stopped); 0: the job's processes share the CPU "
                        "evenly, as every figure in docs/ was measured")
    a.add_argument("--no-episode-logs", action="store_true", help="write no MCAP episode logs at all")
    a.add_argument("--compress-frames", choices=("on", "off"), default="on",
                   help="the actors send a camera task's frames zstd-compressed (l2r-actor --compress-frames): 3.5 "
                        "to 32 times fewer bytes through replay's write-ahead log and any link, for well under 1 %% "
                        "of an actor's CPU; off sends them raw. Other tasks send the same bytes either way")
    rb = p.add_argument_group("robustness: levers for gaits that survive OpenSim, for the training actors alone (the "
                              "evaluators run the plain env; --randomize and --difficulty-schedule, on in runner/sac, "
                              "and --frame-stack, the policy's own, are among the recipe's values); each off by "
                              "default, what each A/B "
                              "measured in docs/training.md, \"Levers for robustness\"")
    rb.add_argument("--observation-noise", type=float, default=0.0, metavar="STD",
                    help="std of Gaussian noise the actors add to every observed value, in its own units (m, rad, "
                         "m/s, rad/s on the runner); replay stores the noisy observations (0: off)")
    rb.add_argument("--action-noise", type=float, default=0.0, metavar="STD",
                    help="std of Gaussian noise the actors add to every action value before the env takes it (the "
                         "runner's excitations, then clipped to [0, 1]); replay stores the policy's action (0: off)")
    rb.add_argument("--exploration-noise", default="white", choices=tuple(COLOURS),
                    help="the colour of the policy's exploring draws over an episode: white, each step's drawn "
                         "anew; pink or red, a series whose power falls as 1/f or 1/f^2 (Eberhard et al., 2023), "
                         "so successive excitations are correlated, as muscles, which low-pass them, can feel")
    rb.add_argument("--parameter-noise", type=float, default=0.0, metavar="DISTANCE",
                    help="explore in parameter space: each training env's policy weights perturbed for each "
                         "episode, the perturbation's std adapted so its actions lie this RMS distance from the "
                         "policy's in (-1, 1) action space, e.g. 0.2 (Plappert et al., 2018; reason8's runner); "
                         "SAC and TD3 (0: off)")
    rb.add_argument("--opensim-stage", type=float, default=0.0, metavar="SECONDS",
                    help="the runner's OpenSim stage: after this many seconds of the job on the port's actors, the "
                         "learner goes on from its newest checkpoint in a run of its own, RUN_DIR-opensim, whose one "
                         "actor steps OpenSim 4.6 and whose replay holds that actor's experience alone (2,000 "
                         "transitions before learning, 128 samples of each, the actor held to the learner, on the "
                         "job's course where the port's actors left it); --seconds is the whole job's and the "
                         "evaluators are the job's. Gaits formed on the port part from OpenSim; their experience in "
                         "OpenSim mends that (docs/training.md, \"OpenSim's own experience once the port's gait has "
                         "parted\"). A --resume of the port's directory goes on with whichever stage is unfinished "
                         "(0: off)")
    rb.add_argument("--opensim-stage-parting", type=float, default=0.0, metavar="RATIO",
                    help="end the port's stage before --opensim-stage SECONDS once its gait parts from OpenSim: "
                         f"{opensim_stage.PARTED_ROUNDS} OpenSim evaluations in a row under RATIO (e.g. 0.7) of the "
                         "port's evaluation of the nearest policy version, where the port's ran "
                         f"{opensim_stage.GAIT:g} m or more; needs evaluators in both simulators (0: off, the stage "
                         "starts at SECONDS)")
    le = p.add_argument_group("learner and replay")
    le.add_argument("--device", default="cpu", choices=("auto", "cpu", "cuda"),
                    help="the learner's device, and the actors' where --env-id steps its worlds as one vector env "
                         "(l2r/RunWarp-v0: the worlds and the policy's batched call on the GPU with cuda)")
    le.add_argument("--colocated", action="store_true",
                    help="the learner steps the training worlds itself (--actors x --envs-per-actor of them, the "
                         "actors' env with --difficulty and --randomize) and keeps their transitions on its device: "
                         "no replay server and no training actors; evaluators as ever (every --algo but a3c; "
                         "vector observations). For l2r/RunWarp-v0 on a GPU (--device cuda): thousands of worlds, big "
                         "batches, nothing but weights, metrics and episode summaries over Zenoh (docs/training.md, "
                         "\"Colocated worlds\")")
    le.add_argument("--learner-threads", type=int, default=0,
                    help="torch CPU threads of the learner; 0: the cores left after one per actor or evaluator and "
                         "one per replay shard, at least 1 (oversubscribed threads wait on each other and slow every "
                         "update)")
    le.add_argument("--algo", choices=sorted({algo for _, algo in RECIPES}), default="sac",
                    help="the learner's algorithm: sac learns off-policy from the replay table, td3 too (with a "
                         "deterministic policy); ppo, a2c, reinforce, trpo and acktr on-policy from the "
                         "replay server's queue table, each transition once and none older than --queue-max-lag "
                         "policy versions; a3c from gradients the actors compute on their own rollouts "
                         "(--batch-size steps each) and send instead of experience")
    le.add_argument("--replay-shards", type=int, default=1, metavar="N",
                    help="replay server processes (SAC, TD3; at most --actors): actor i feeds shard i mod N and the "
                         "learner samples the shards in turn; --capacity and --min-replay are the job's, split over "
                         "the shards. More than 1 helps a fast learner (a GPU) whose one replay process cannot take "
                         "the actors' inserts while it serves the batches (docs/training.md, \"Replay shards\"); a "
                         "--resume keeps the run's number")
    le.add_argument("--capacity", type=int,
                    help=f"replay capacity in transitions of the whole job, split over the --replay-shards (SAC, TD3); "
                         f"unset: {VECTOR_CAPACITY:,}, and {IMAGE_CAPACITY:,} for camera tasks (2.4 GB of 84 x 84 "
                         f"frames; each shard logs its bytes at start), {PHOTO_CAPACITY:,} for photo tasks")
    le.add_argument("--queue-capacity", type=int,
                    help="transitions the queue table holds before it holds the actors back (on-policy algorithms; "
                         "unset: two batches)")
    le.add_argument("--queue-max-lag", type=int, default=QueueConfig().max_lag,
                    help="the queue drops transitions acted by a policy more than this many versions behind the "
                         "learner's newest, and counts them (on-policy algorithms)")
    le.add_argument("--keep-checkpoints", type=int, default=3,
                    help="learner checkpoints kept (learner/checkpoint-<updates>.pt; checkpoint.pt is the newest)")
    le.add_argument("--init-from", type=Path, metavar="CHECKPOINT",
                    help="the learner starts from this checkpoint (a file, or a run directory's): a training "
                         "checkpoint's networks, optimizers and counters (staged training: a run's "
                         "learner/checkpoint.pt goes on, say, with --difficulty 2 on the obstacle course), or a "
                         "policy checkpoint's policy alone (best.pt; the critics start fresh). A --resume of this run "
                         "takes its own checkpoint instead, once it has one")
    le.add_argument("--learner-arg", action="append", default=[], metavar="ARG",
                    help="extra argument for l2r-learner, e.g. --learner-arg=--lr=3e-4 (repeatable)")
    le.add_argument("--replay-arg", action="append", default=[], metavar="ARG",
                    help="extra argument for l2r-replay (repeatable)")
    le.add_argument("--actor-arg", action="append", default=[], metavar="ARG",
                    help="extra argument for every l2r-actor, evaluators included, e.g. "
                         "--actor-arg=--env-id=l2r/RunOpenSim-v0 (repeatable)")
    rc = p.add_argument_group("recipe: every hyperparameter of the job, from the recipe of the task's family and "
                              "algorithm (docs/training.md, \"Recipes\") unless its flag is given")
    rc.add_argument("--recipe", choices=FAMILIES,
                    help="train with this family's recipe (unset: the family of --env-id: runner for the runner's "
                         "l2r/Run ids, pixels for the camera tasks' l2r/dmc- ids, photo for the photo tasks' "
                         "l2r/Photo ids, standard for any other task), e.g. --recipe runner on Hopper-v5 to set the "
                         "two against each other")
    for name, text in SETTINGS.items():
        rc.add_argument(f"--{name.replace('_', '-')}", **_recipe_flag(name, text))
    o = p.add_argument_group("output")
    o.add_argument("--status-interval", type=float, default=2.0, help="seconds between status updates")
    o.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                   help="log level of every process")
    # Not a flag: an OpenSim stage's actors go on along the course from the port's stage (opensim_stage.stage_args).
    p.set_defaults(course_steps_before=0)
    return p


# -- run directory and resume ------------------------------------------------------------------

def _stored(value):
    """A flag's value as launch.json keeps it."""
    return str(value) if isinstance(value, Path) else value


def parse_args(argv: list[str]) -> tuple[argparse.Namespace, dict | None]:
    """The job's flags and, for --resume, the run's launch.json. Each flag's value comes from the
    first that has one: the command line, the --config file, launch.json on --resume, the default.
    Each change of a flag stored in launch.json is warned of."""
    parser = build_parser()
    given = parser.parse_args(argv)  # the command line alone
    launch, stored = _launch(parser, given) if given.resume is not None else (None, {})
    from_file = _config_file(parser, given.config) if given.config is not None else {}
    parser.set_defaults(**(stored | from_file))
    args = parser.parse_args(argv)
    # A repeatable flag on the command line replaces the file's or launch.json's list rather than adding to it.
    for action in parser._actions:
        if isinstance(action, argparse._AppendAction) and getattr(given, action.dest):
            setattr(args, action.dest, getattr(given, action.dest))
    if launch is None:
        return _checked(parser, args), None
    for dest, old in stored.items():
        if _stored(getattr(args, dest)) != old:
            print(f"l2r up: warning: --{dest.replace('_', '-')} {getattr(args, dest)} replaces {old} from "
                  f"{args.resume / 'launch.json'}", file=sys.stderr)
    args = _checked(parser, args)
    replay_dir = args.resume / "replay"
    shards_before = stored.get("replay_shards", 1)
    if args.replay_shards != shards_before and any(replay_dir.glob("replay-shard*")):
        # Actor i's experience lives in shard i mod N: another N would leave a shard's data unread.
        parser.error(f"--replay-shards {args.replay_shards}: the run's replay in {replay_dir} is kept by "
                     f"{shards_before} shard{'s' if shards_before > 1 else ''}; resume with --replay-shards "
                     f"{shards_before}, or move replay/ away to start with an empty replay")
    for shard, capacity in enumerate(shard_capacities(replay_capacity(args), args.replay_shards)):
        snapshot_capacity = replay_snapshot_capacity(replay_dir, shard)
        if snapshot_capacity not in (None, capacity):
            print(f"l2r up: warning: the replay snapshot {snapshot_path(replay_dir, shard)} holds "
                  f"{snapshot_capacity:,} transitions' capacity; the replay server cannot restore it with --capacity "
                  f"{replay_capacity(args):,}{f' ({capacity:,} a shard)' if args.replay_shards > 1 else ''} and the "
                  f"job will give up (move replay/ away to start with an empty replay)", file=sys.stderr)
    return args, launch


def _launch(parser: argparse.ArgumentParser, given: argparse.Namespace) -> tuple[dict, dict]:
    """The launch.json of the run directory to --resume, and the flags it stores that are reused."""
    launch_path = given.resume / "launch.json"
    if not given.resume.is_dir():
        parser.error(f"--resume {given.resume}: no such run directory")
    try:
        launch = json.loads(launch_path.read_text())
    except FileNotFoundError:
        parser.error(f"--resume {given.resume}: no launch.json there, so not a run directory of l2r up")
    except json.JSONDecodeError as e:
        parser.error(f"--resume: {launch_path} is not JSON ({e})")
    if "args" not in launch:
        print(f"l2r up: warning: {launch_path} stores no flags (an older l2r wrote it): the flags given and the "
              f"defaults apply", file=sys.stderr)
    stored = {k: v for k, v in launch.get("args", {}).items() if k in vars(given) and k not in NOT_REUSED}
    recorded = launch.get("recipe", {}).get("values", {})
    for name, before in ADDED_SINCE.items():  # a run from before a setting trained without it: so it goes on
        if name not in recorded and stored.get(name) is None:
            stored[name] = before
    if "args" in launch and "recipe" not in launch["args"]:
        # From before recipes, when every task trained with the runner's: the same job goes on.
        stored["recipe"] = RUNNER
        if family_of(stored.get("env_id", PORT_ID)) != RUNNER:
            print(f"l2r up: note: {launch_path} is from before recipes: the run goes on with the runner's recipe, "
                  f"which trained every task then", file=sys.stderr)
    eval_env_id = stored.get("eval_env_id", [])
    if not isinstance(eval_env_id, list):  # one id or none, from before the flag was repeatable
        stored["eval_env_id"] = [eval_env_id] if eval_env_id else []
    return launch, stored


def _config_file(parser: argparse.ArgumentParser, path: Path) -> dict:
    """The flags' values in a --config file, checked against the flags' types. A file's values are
    typed: "7200" is no number there, nor 7200 a string."""
    try:
        with open(path, "rb") as f:
            table = tomllib.load(f)
    except OSError as e:
        parser.error(f"--config {path}: {e.strerror}")
    except tomllib.TOMLDecodeError as e:
        parser.error(f"--config {path}: not TOML: {e}")
    flags = {action.dest: action for action in parser._actions
             if action.option_strings and action.dest not in ("help", "version", "config", "resume")}
    values = {}
    for key, value in table.items():
        action = flags.get(key.replace("-", "_"))
        if action is None:
            parser.error(f"--config {path}: unknown key {key!r} (keys are the long flag names, except resume "
                         f"and config)")
        try:
            values[action.dest] = _file_value(action, value)
        except ValueError as e:
            parser.error(f"--config {path}: {key} = {value!r}: {e}")
    return values


def _file_value(action: argparse.Action, value):
    """A --config file's ``value`` for the flag of ``action``, as the command line would set it;
    raises ValueError saying what it should be."""
    if action.nargs == 0:  # --flag, --[no-]flag
        kind, fits = "true or false", isinstance(value, bool)
    elif isinstance(action, argparse._AppendAction):
        kind, fits = "a list of strings", isinstance(value, list) and all(isinstance(v, str) for v in value)
    elif action.type in (int, float):
        kind = "an integer" if action.type is int else "a number"
        fits = isinstance(value, int if action.type is int else (int, float)) and not isinstance(value, bool)
    else:
        kind, fits = "a string", isinstance(value, str)
    if not fits:
        raise ValueError(f"should be {kind}")
    if action.type is not None:
        value = action.type(value)
    if action.choices is not None and value not in action.choices:
        raise ValueError(f"should be one of {', '.join(map(str, action.choices))}")
    return value


def replay_snapshot_capacity(directory: Path, shard: int) -> int | None:
    """The capacity the snapshot of replay shard `shard` in `directory` was taken with (the fourth
    of the storage's counters, see l2r.replay.storage), or None without a readable one."""
    try:
        with np.load(snapshot_path(directory, shard), allow_pickle=False) as snapshot:
            return int(snapshot["counters"][3])
    except (OSError, KeyError, IndexError, ValueError, zipfile.BadZipFile):
        return None


def _checked(parser: argparse.ArgumentParser, args: argparse.Namespace) -> argparse.Namespace:
    try:
        image_size_option(args.env_id, args.image_size)
    except ValueError as e:
        parser.error(f"--image-size {args.image_size}: {e}")
    try:
        photo_goals_option(args.env_id, args.photo_goals)
    except ValueError as e:
        parser.error(f"--photo-goals {args.photo_goals}: {e}")
    if family_of(args.env_id) != RUNNER:
        try:
            observation, _ = task_spaces(args.env_id, args.image_size)
        except ValueError as e:
            parser.error(f"--env-id {args.env_id}: {e}")
        if observation.vector_width is None and args.algo not in ("sac", "td3"):
            parser.error(f"--env-id {args.env_id}: its observation is {observation}; images train with --algo td3 "
                         f"(DrQ-v2) or sac (DrQ), not {args.algo}")
    family = args.recipe or family_of(args.env_id)
    if (family, args.algo) not in RECIPES:
        parser.error(f"there is no {family} recipe for --algo {args.algo}; {family}'s: "
                     f"{', '.join(algo for f, algo in RECIPES if f == family)}")
    recipe = recipe_of(args).values
    if family_of(args.env_id) != RUNNER and observation.vector_width is None:
        try:  # frames too small for the encoder's convolutions (--image-size)
            check_observation(observation, recipe.get("encoder") or DRQ)
        except ValueError as e:
            parser.error(f"--env-id {args.env_id}: {e}")
    if args.actors < 1 or recipe["envs_per_actor"] < 1:
        parser.error("--actors and --envs-per-actor must be at least 1")
    if args.init_from is not None and args.resume is None:  # on --resume the run's own checkpoint comes first
        try:
            args.init_from = find_checkpoint(args.init_from).resolve()
        except CheckpointError as e:
            parser.error(f"--init-from: {e}")
    if args.max_restarts < 0 or args.keep_checkpoints < 1 or recipe["action_repeat"] < 1:
        parser.error("--max-restarts must be at least 0, --keep-checkpoints and --action-repeat at least 1")
    if not HIDDEN_WIDTHS.fullmatch(recipe["hidden"]) or recipe.get("update_repeat", 1) < 1:
        parser.error(f"--hidden takes widths such as 256,256 (got {recipe['hidden']!r}), --update-repeat at least 1")
    if not 0 <= args.opensim_actors <= args.actors:
        parser.error(f"--opensim-actors must be between 0 and --actors ({args.actors}), got {args.opensim_actors}")
    if not 1 <= args.replay_shards <= args.actors:
        parser.error(f"--replay-shards must be between 1 and --actors ({args.actors}), got {args.replay_shards}: "
                     f"actor i feeds shard i mod N, so a shard beyond the actors would stay empty")
    if args.replay_shards > 1 and args.algo in ON_POLICY:
        parser.error(f"--replay-shards is for the replay table of sac and td3; --algo {args.algo} takes its "
                     f"batches from one replay server's queue")
    _check_robustness(parser, args)
    if refused := opensim_stage.refusal(args) or opensim_stage.parting_refusal(args, evaluator_env_ids(args)):
        parser.error(refused)
    if args.colocated:
        _check_colocated(parser, args)
    return args


def _check_colocated(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """What the learner's own worlds (--colocated) cannot take: the actors' levers and replay's options."""
    if args.algo == "a3c":
        parser.error("--colocated trains on the learner's own worlds; --algo a3c learns from the actors' gradients")
    if family_of(args.env_id) in (PIXELS, PHOTO):
        parser.error(f"--colocated steps worlds of vector observations, not {args.env_id}'s images")
    levers = {"--opensim-actors": args.opensim_actors, "--replay-shards": args.replay_shards > 1,
              "--difficulty-schedule": args.difficulty_schedule, "--observation-noise": args.observation_noise,
              "--action-noise": args.action_noise, "--exploration-noise": args.exploration_noise != "white",
              "--parameter-noise": args.parameter_noise,
              "--frame-stack": recipe_of(args).values.get("frame_stack", 1) > 1}
    given = [flag for flag, on in levers.items() if on]
    if given:
        parser.error(f"--colocated: {', '.join(given)} are the actors' and replay's, not the learner's own worlds'")


def _check_robustness(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """The robustness levers' values, and that the task takes them."""
    try:
        if args.randomize and Randomization.parse(args.randomize) and randomize_refusal(args.env_id):
            parser.error(f"--randomize: {randomize_refusal(args.env_id)}")  # as given; the recipe's is off there
        if args.difficulty_schedule:
            DifficultySchedule.parse(args.difficulty_schedule)
            if family_of(args.env_id) != RUNNER:
                parser.error(f"--difficulty-schedule is the runner's, not {args.env_id}'s")
        if args.eval_difficulty is not None and family_of(args.env_id) != RUNNER:
            parser.error(f"--eval-difficulty is the runner's, not {args.env_id}'s")
    except ValueError as e:
        parser.error(str(e))
    if not (args.observation_noise >= 0 and args.action_noise >= 0):
        parser.error("--observation-noise and --action-noise are standard deviations, at least 0")
    if args.observation_noise and family_of(args.env_id) != RUNNER and task_spaces(args.env_id)[0].vector_width is None:
        parser.error(f"--observation-noise is for vector observations, not {args.env_id}'s")
    if args.parameter_noise < 0:
        parser.error("--parameter-noise is a distance, at least 0")
    if args.parameter_noise and args.algo in ON_POLICY:
        parser.error(f"--parameter-noise: {args.algo.upper()} needs the log-probabilities of its own policy, not of "
                     "perturbed copies (SAC and TD3 take it)")


def make_run_dir(args: argparse.Namespace) -> Path:
    """A new run directory, or the one to --resume."""
    if args.resume:
        return args.resume
    stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S")
    run_dir = args.runs_dir / f"{args.name}-{stamp}"
    run_dir.mkdir(parents=True, exist_ok=False)
    return run_dir


def write_launch(run_dir: Path, args: argparse.Namespace, argv: list[str], launch: dict | None,
                 ports: dict[str, int]) -> None:
    """launch.json: the first session's command line, the run's flags as this session uses them
    (a recipe's setting left unset stays None, so --resume resolves it again), the recipe they
    resolve to, and every session's command line and ports."""
    record = launch or {"argv": argv, "zenoh_run": run_dir.name}
    record["args"] = {k: _stored(v) for k, v in vars(args).items() if k not in NOT_REUSED}
    record["recipe"] = recipe_of(args).to_dict()
    record.setdefault("sessions", []).append(
        {"started": datetime.now(timezone.utc).isoformat(timespec="seconds"), "argv": argv, **ports})
    tmp = run_dir / ".launch.json.tmp"
    tmp.write_text(json.dumps(record, indent=2) + "\n")
    os.replace(tmp, run_dir / "launch.json")


# -- the processes -------------------------------------------------------------------------------


# -- what the run leaves -------------------------------------------------------------------------

def after_run(run_dir: Path, metrics: RunMetrics, best: BestPolicy, group: ProcessGroup, outcome: str,
              code: int) -> dict:
    """summary.json, and best_eval.rrd: a Rerun recording of the evaluation episode that
    summary.json names as the best (by the task's score)."""
    figures = metrics.snapshot()
    score = metrics.score.name  # best_eval_distance on the runner, best_eval_return on a standard task
    summary = {"outcome": outcome, "exit_code": code, **figures,
               "score": score, "best_eval_score": figures[f"best_eval_{score}"]}
    summary["restarts_by_process"] = {c.name: c.restarts for c in group.children if c.restarts}
    summary["last_exit_by_process"] = {c.name: c.last_exit for c in group.children if c.last_exit}
    summary["failing"] = [group.failure(c) for c in group.failing()]
    episode = metrics.best_eval
    summary["best_eval_episode"] = None if episode is None else {
        "actor": int(episode["actor"]), "seed": int(episode["seed"]), "version": int(episode["version"]),
        "distance": float(episode["distance"]), "return": float(episode["return"]), "length": int(episode["length"]),
        score: float(episode[score])}  # a photo task's psnr beside the others
    summary["best_policy"] = None if best.best is None else {"path": str(best.path), **best.best}
    if episode is not None:
        found = find_episode(run_dir / "episodes", kind="eval", actor=int(episode["actor"]), seed=int(episode["seed"]),
                             policy_version=int(episode["version"]))
        if found is None:
            log.info("the best evaluation episode was not logged (episode logs off or skipped): no best_eval.rrd")
        else:
            summary["best_eval_episode"]["log"] = str(found)
            try:
                from l2r.view import write_recording  # Rerun loads here, not at every start of l2r up

                summary["best_eval_recording"] = str(write_recording([found], run_dir / "best_eval.rrd"))
            except Exception as e:  # a convenience: the run's results are saved whatever happens here
                log.warning("no recording of the best evaluation episode (%s): %s", found.name, e)
    try:
        (run_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    except OSError as e:
        if e.errno not in DISK_ERRORS:
            raise
        log.error("summary.json not written: %s", disk_failure(e, run_dir / "summary.json"))
    return summary


# What the default recipe reached on a 2-core CPU (docs/training.md, "The recipe"), for short runs to say.
LONGER_RUN_SECONDS = 1800
LONGER_RUN = ("a longer run: l2r up --seconds 3600 --evaluators 2 --eval-env-id l2r/RunOpenSim-v0 --eval-env-id "
              "l2r/Run-v0; alone on 2 CPU cores, three runs of the runner/sac recipe formed their gaits at 26, 52 and "
              "57 minutes, after a plateau of 1 m dives, and ran 11.2, 11.1 and 7.5 m in OpenSim by 60 minutes, "
              "the port's evaluations within 10 % of OpenSim's (docs/training.md)")


def eval_command(checkpoint: Path | str, env_id: str) -> str:
    """The `l2r eval` command line for a checkpoint trained on `env_id` (it runs the port unless told)."""
    return f"l2r eval {checkpoint}" + ("" if env_id == PORT_ID else f" --env-id {env_id}")


def final_report(run_dir: Path, summary: dict, args: argparse.Namespace, updates_before: int) -> list[str]:
    """What the last lines say, evaluations in the terms of the task's score: what happened, and
    only the commands that have something to show."""
    score = score_of(args.env_id)
    lines = [failure for failure in summary["failing"] if failure not in summary["outcome"]]
    lines += [f"{summary['env_steps']:,} env steps, {summary['updates']:,} updates "
             f"({summary['updates'] - updates_before:,} in this session), best evaluation episode "
             f"{score.text(summary['best_eval_score'])}", f"run directory: {run_dir}",
             f"metrics: tensorboard --logdir {run_dir / 'metrics'}  (CSV files beside)"]
    if summary["updates"] == 0:
        min_replay = recipe_of(args).values.get("min_replay", 0)
        waiting = summary["replay_size"] < min_replay and not summary["failing"]
        lines.append("the learner made no update, so there is nothing to evaluate" + (
            f" (replay holds {summary['replay_size']:,} of the --min-replay {min_replay:,} transitions it "
            f"waits for)" if waiting else ""))
    elif not checkpoint_path(run_dir).exists():
        lines.append("no learner checkpoint was written")
    else:
        lines.append(f"evaluate the newest checkpoint: {eval_command(run_dir, args.env_id)}")
    if summary["exit_code"]:
        lines.append(f"continue the run (once its cause is cleared): l2r up --resume {run_dir}")
    if summary["best_policy"]:
        bp = summary["best_policy"]
        lines.append(f"evaluate the best evaluated policy (v{bp['version']}, mean "
                     f"{score.text(bp[f'mean_{score.name}'])}): {eval_command(bp['path'], args.env_id)}")
    if "best_eval_recording" in summary:
        lines.append(f"watch the best evaluation episode: rerun {summary['best_eval_recording']}")
    if family_of(args.env_id) == RUNNER and summary["time"] < LONGER_RUN_SECONDS:
        lines.append(LONGER_RUN)
    return lines


# -- the job -------------------------------------------------------------------------------------

def cli(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    args, launch = parse_args(argv)
    if not args.opensim_stage:
        return job(args, argv, launch)
    return staged(args, argv, launch)


def staged(args: argparse.Namespace, argv: list[str], launch: dict | None) -> int:
    """--opensim-stage: the port's stage, then OpenSim's, each a run of its own; a --resume of the
    port's directory goes on with the stage that is unfinished."""
    if args.resume is None and not fits_on_disk(args):  # before the port's directory is made
        return EXIT_USAGE
    port_run = args.resume or make_run_dir(args)
    stage_run = opensim_stage.run_dir_of(port_run)
    if not stage_run.is_dir() and not opensim_stage.port_stage_ended(args, port_run):
        until = " (or until its gait parts from OpenSim's)" if args.opensim_stage_parting else ""
        print(f"l2r up: {args.opensim_stage:g} s on the port's actors{until} in {port_run}, then OpenSim's stage in "
              f"{stage_run}", file=sys.stderr)
        code = job(args, argv, launch, port_run)
        if code or not opensim_stage.port_stage_ended(args, port_run):
            return code
    try:
        stage = opensim_stage.stage_args(args, port_run)
    except CheckpointError as e:
        print(f"l2r up: failed: the port's stage left nothing to go on from: {e}", file=sys.stderr)
        return EXIT_FAILURE
    try:
        stage_launch = json.loads((stage_run / "launch.json").read_text()) if stage.resume else None
    except (OSError, ValueError) as e:
        print(f"l2r up: --resume: {stage_run / 'launch.json'} cannot be read ({e})", file=sys.stderr)
        return EXIT_USAGE
    stage_run.mkdir(exist_ok=True)
    print(f"l2r up: OpenSim's stage goes on in {stage_run}" if stage.resume else
          f"l2r up: the port's stage is over; OpenSim's stage starts from {stage.init_from} in {stage_run}",
          file=sys.stderr)
    code = job(stage, argv, stage_launch, stage_run)
    print(f"l2r up: {better_stage(port_run, stage_run, score_of(args.env_id))}", file=sys.stderr)
    return code


def better_stage(port_run: Path, stage_run: Path, score: Score) -> str:
    """Which stage's best.pt its judge scored higher, in one line."""
    kept = {}
    for name, run_dir in (("the port's", port_run), ("OpenSim's", stage_run)):
        try:
            best = json.loads((run_dir / "summary.json").read_text())["best_policy"]
        except (OSError, ValueError, KeyError):
            continue
        if best:
            kept[name] = best
    if not kept:
        return "neither stage kept an evaluated policy"
    name, best = max(kept.items(), key=lambda item: item[1][f"mean_{score.name}"])
    return (f"of the stages' best.pt, {name} scored higher: v{best['version']}, mean "
            f"{score.text(best[f'mean_{score.name}'])} ({best['path']})")


def job(args: argparse.Namespace, argv: list[str], launch: dict | None, run_dir: Path | None = None) -> int:
    """One run: in `run_dir` (unset: a new directory, or the one to --resume), unless its budget is
    spent or the disk cannot take it."""
    if args.resume and (spent := budget_spent(args, RunCounters.read(args.resume / "metrics"))):
        if not args.opensim_stage:
            print(f"l2r up: nothing to do: the run's {spent} (give a larger budget to train on)", file=sys.stderr)
        return 0
    if not fits_on_disk(args):
        return EXIT_USAGE
    try:
        return train(args, argv, launch, run_dir or make_run_dir(args))
    except OSError as e:  # a write of l2r up's own that its disk refused (the daemons' are theirs to report)
        if e.errno not in DISK_ERRORS:
            raise
        print(f"l2r up: failed: {disk_failure(e)}", file=sys.stderr)
        return EXIT_FAILURE


def fits_on_disk(args: argparse.Namespace) -> bool:
    """Whether what the run may write fits in the free space of its disk; one line if not (a
    warning with --force, which then goes on)."""
    where = args.resume or args.runs_dir
    children = plan_children(args, "estimate", where, [0] * args.replay_shards, 0)
    parts = disk_budget.estimate(args, recipe_of(args).values, children)
    needed = sum(parts.values()) - disk_budget.already_written(args.resume)
    free = free_bytes(where)
    if needed <= free:
        return True
    line = (f"the run may write {disk_budget.describe(parts)}, more than the {free / MB:,.0f} MB free at {where}"
            f"{' (less what the run directory holds)' if args.resume else ''}")
    if args.force:
        print(f"l2r up: warning: {line}; going on (--force)", file=sys.stderr)
        return True
    print(f"l2r up: {line}; free space, lower --capacity or the episode logs' budget "
          f"(--actor-arg=--log-budget-mb=N, --no-episode-logs), or pass --force", file=sys.stderr)
    return False


def train(args: argparse.Namespace, argv: list[str], launch: dict | None, run_dir: Path) -> int:
    (run_dir / "logs").mkdir(exist_ok=True)
    display = StatusDisplay(score_of(args.env_id))
    console = display.log_handler()
    file_handler = FileLogHandler(run_dir / "logs" / "up.log", console)
    file_handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.basicConfig(level=getattr(logging, args.log_level), handlers=[file_handler, console], force=True)
    run = run_dir.name
    *replay_ports, learner_port = free_ports(args.replay_shards + 1)
    write_launch(run_dir, args, argv, launch, {"learner_port": learner_port} | (
        {} if args.colocated else {"replay_port": replay_ports[0]}) | (
        {"replay_ports": replay_ports} if args.replay_shards > 1 else {}))
    if args.colocated:  # the learner's own worlds: no replay
        replay_ports = []
    recipe = recipe_of(args)
    log.info("%s", recipe.describe())
    if recipe.unused:
        log.warning("flags %s has no use for, ignored: %s", recipe.name,
                    ", ".join(f"--{name.replace('_', '-')}" for name in recipe.unused))

    stop = threading.Event()
    reason = ["interrupted"]

    def on_signal(signum, _frame):
        reason[0] = f"stopped by {signal.Signals(signum).name}"
        stop.set()

    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, on_signal)

    children = plan_children(args, run, run_dir, replay_ports, learner_port)
    conf = session_config(connect=[loopback(port) for port in [*replay_ports, learner_port]],
                          listen=["tcp/127.0.0.1:0"])
    print(f"l2r up: run directory {run_dir}  (Zenoh run {run!r}; Ctrl-C stops cleanly)", file=sys.stderr)
    code, spent = 0, None
    checkpoint_estimate = disk_budget.task_checkpoint_bytes(args.env_id, recipe.values["hidden"])
    shedding = disk_budget.Shedding(run_dir)
    with zenoh.open(conf) as session:
        token = session.liveliness().declare_token(Keys(run).alive("launcher", 0))
        simulators = simulator_of_each_actor(children) | ({0: args.env_id} if args.colocated else {})
        metrics = RunMetrics(session, Keys(run), run_dir / "metrics", env_id=args.env_id, simulators=simulators,
                             shown_eval_env_id=shown_evaluations(args.env_id, args.eval_env_id))
        parting = opensim_stage.Parting(args.opensim_stage_parting, args.eval_episodes, simulators) if (
            args.opensim_stage and args.opensim_stage_parting) else None
        parting_subscribers = [parting.listen(session, Keys(run))] if parting else []
        judge = args.eval_env_id[0] if args.eval_env_id else None
        best = BestPolicy(session, Keys(run), run_dir, args.eval_episodes, recipe.values["action_repeat"],
                          score_of(args.env_id),
                          judges={i for i, env_id in simulators.items() if judge is None or env_id == judge})
        group = ProcessGroup(children, run_dir / "logs", progress=metrics.rises, max_restarts=args.max_restarts,
                             resume=args.resume is not None,
                             on_exit=lambda child, exit_code: metrics.note_exit(child.name, exit_code, child.last_exit))
        log.info("starting %s", ", ".join(c.name for c in children))
        try:
            with display:
                group.start()
                next_status = time.monotonic() + args.status_interval
                while not stop.wait(0.25):
                    failed = group.poll()
                    if failed:
                        reason[0], code = f"gave up: {group.failure(failed)}", 1
                        break
                    if group.finished("learner"):
                        reason[0] = "the learner finished"
                        break
                    if not args.colocated and group.finished("actor-"):  # (colocated: none to finish)
                        reason[0] = "every actor finished"
                        break
                    spent = budget_spent(args, metrics.counters()) or (parting and parting.verdict)
                    if spent:
                        reason[0] = spent
                        break
                    if time.monotonic() >= next_status:
                        figures, free = metrics.record_status(), free_bytes(run_dir)
                        reserve = disk_budget.reserve_bytes(run_dir, checkpoint_estimate)
                        metrics.pause_events("TensorBoard events" in shedding.update(free, reserve))
                        if free < disk_budget.LOW_FACTOR * reserve:
                            figures["disk_free_mb"] = free / MB
                        display.update(figures, children)
                        next_status += args.status_interval
                        if free < reserve:
                            reason[0], code = f"disk full at {run_dir}: {free / MB:.1f} MB free", 1
                            break
                display.update(metrics.record_status(), children)
        finally:
            print(f"l2r up: stopping ({reason[0]})", file=sys.stderr)
            log.info("stopping: %s", reason[0])
            metrics.stop_clock()
            group.stop()
            best.close()
            for subscriber in parting_subscribers:
                subscriber.undeclare()
            metrics.record_status()
            metrics.close()
            token.undeclare()
    updates_before = metrics.before.updates if args.resume else updates_carried(args.init_from)
    trained_nothing = spent is not None and metrics.updates <= updates_before
    if trained_nothing:
        reason[0] += ", but the learner made no update"
        code = 1  # a training job that trained nothing has failed, whatever else ran
    summary = after_run(run_dir, metrics, best, group, reason[0], code)
    print(f"l2r up: {'failed' if code else 'done'}: {reason[0]}\n" + "\n".join(
        f"        {line}" for line in final_report(run_dir, summary, args, updates_before)), file=sys.stderr)
    for child in group.failing():  # their own words last, where they are seen
        print(f"l2r up: the last lines of {group.log_path(child)}:\n"
              + "\n".join(f"    {line}" for line in last_lines(group.log_path(child))), file=sys.stderr)
    return code


def updates_carried(init_from: Path | None) -> int:
    """The updates a new run's learner counts from: a training checkpoint's (--init-from), else 0."""
    if init_from is None:
        return 0
    try:
        saved = load_checkpoint(init_from)
    except CheckpointError:  # the learner says why, in its log
        return 0
    return 0 if saved.config is None else saved.updates


def budget_spent(args: argparse.Namespace, counters: RunCounters) -> str | None:
    """Which budget of the run is spent, in words, or None."""
    if opensim_stage.port_stage_over(args, counters):
        return f"port's stage of {args.opensim_stage:g} s spent"
    if args.seconds and counters.time >= args.seconds:
        return f"time budget of {args.seconds:g} s spent"
    if args.env_steps and counters.env_steps >= args.env_steps:
        return f"budget of {args.env_steps:,} env steps spent"
    return None
