"""The processes of an `l2r up` job, planned from its flags and recipe: each daemon's command line,
the ports they meet on, and what the replay holds.

`plan_children` turns the parsed flags (`l2r.up.parse_args`) into the replay shards, the learner,
the actors and the evaluators, in start order, each an `l2r.supervise.Child`; `l2r.up` starts and
watches them. Nothing here starts a process or touches the run directory but to read what a
resumed run has done.
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
from dataclasses import replace
from pathlib import Path

from l2r import disk_budget
from l2r.actors.__main__ import parse_settings as actor_settings
from l2r.actors.actor import registers_vector_env
from l2r.durable import MB
from l2r.families import PHOTO, PIXELS, RUNNER, family_of
from l2r.learner.algorithms import ON_POLICY
from l2r.recipes import ACTOR_SETTINGS, REPLAY_FLAGS, SETTINGS, Recipe, resolve
from l2r.run_metrics import RunCounters
from l2r.sim import OPENSIM_ID, randomize_refusal
from l2r.spaces import task_spaces
from l2r.supervise import Child

VECTOR_CAPACITY, IMAGE_CAPACITY, PHOTO_CAPACITY = 1_000_000, 100_000, 16_384  # photo: RLPixTuner's replay size
IMAGE_SIDE_FRACTION = 0.0625


# The recipes' learner settings, each an l2r-learner flag of the same name: every setting neither the
# replay server's nor the actors', but LayerNorm (`layer_norm_flag`).
LEARNER_FLAGS = {name: f"--{name.replace('_', '-')}" for name in SETTINGS
                 if name not in REPLAY_FLAGS and name not in ACTOR_SETTINGS and name != "layer_norm"}


def loopback(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def free_ports(count: int) -> list[int]:
    """`count` different TCP ports free on 127.0.0.1 right now (held together while they are
    drawn, so that none is drawn twice)."""
    sockets = [socket.socket() for _ in range(count)]
    try:
        for s in sockets:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in sockets]
    finally:
        for s in sockets:
            s.close()


def evaluator_env_ids(args: argparse.Namespace) -> list[str | None]:
    """The env id each evaluator is given (None: the actors' own): the --eval-env-id in turn."""
    ids = args.eval_env_id
    if not ids:
        return [None] * args.evaluators
    return [ids[i % len(ids)] for i in range(max(args.evaluators, len(ids)))]


def shown_evaluations(env_id: str, eval_env_ids: list[str]) -> str:
    """The simulator whose evaluations the status line shows: the actors' where evaluators run it,
    else the first other id but OpenSim's (whose evaluations the line shows beside them)."""
    if not eval_env_ids or env_id in eval_env_ids:
        return env_id
    return next((e for e in eval_env_ids if e != OPENSIM_ID), env_id)


def replay_capacity(args: argparse.Namespace) -> int:
    """--capacity, else the default for the task's observations: the job's, all shards together."""
    capacities = {PIXELS: IMAGE_CAPACITY, PHOTO: PHOTO_CAPACITY}
    return args.capacity or capacities.get(family_of(args.env_id), VECTOR_CAPACITY)


def shard_capacities(total: int, shards: int) -> list[int]:
    """A job's `total` of transitions split over its replay shards, the first ones a transition
    more where it does not divide."""
    return [total // shards + (shard < total % shards) for shard in range(shards)]


def replay_name(shard: int, shards: int) -> str:
    """The process name of a replay shard: `replay` for a job's only one, else `replay-<shard>`."""
    return "replay" if shards == 1 else f"replay-{shard}"


def task_flags(env_id: str, image_size: int | None = None) -> tuple[list[str], list[str]]:
    """The replay server's and learner's flags for the observations and actions of a task other
    than the runner (a camera task's frames `image_size` pixels a side): the vector's widths as
    before, else the observation spec; an image shard keeps side rows for a sixteenth of its
    capacity (docs/observations.md, "Replay storage")."""
    observation, act_dim = task_spaces(env_id, image_size)
    if observation.vector_width is not None:
        widths = ["--obs-dim", str(observation.vector_width), "--act-dim", str(act_dim)]
        return widths, widths
    spec = ["--observation", str(observation), "--act-dim", str(act_dim)]
    return [*spec, "--side-fraction", str(IMAGE_SIDE_FRACTION)], spec


def learner_threads(args: argparse.Namespace) -> int:
    others = len(evaluator_env_ids(args)) + (0 if args.colocated else args.actors + args.replay_shards)
    return args.learner_threads or max(1, (os.cpu_count() or 1) - others)


def recipe_of(args: argparse.Namespace) -> Recipe:
    """The recipe the job trains with: --recipe's, else the task family's, and the flags given; the
    recipe's course of difficulties off where the job asks for one difficulty (a --difficulty other
    than 0) or steps worlds that keep one (--colocated)."""
    recipe = resolve(args.env_id, args.algo, args.recipe, {name: getattr(args, name) for name in SETTINGS})
    course, origin = recipe.values.get("difficulty_schedule"), recipe.origins.get("difficulty_schedule")
    why = (f"off with --difficulty {args.difficulty}" if args.difficulty else
           "off with --colocated, whose worlds keep --difficulty" if args.colocated else None)
    if course and origin == "recipe" and why:
        return replace(recipe, values=recipe.values | {"difficulty_schedule": ""},
                       origins=recipe.origins | {"difficulty_schedule": why})
    return recipe


def daemon_flags(recipe: dict, flags: dict[str, str]) -> list[str]:
    """The recipe's settings among `flags` (setting: a daemon's flag) as that daemon's arguments:
    flag and value, a switch its flag when on (the daemons' switches are off unless given)."""
    arguments = []
    for name, flag in flags.items():
        value = recipe.get(name)
        if isinstance(value, bool):
            arguments += [flag] if value else []
        elif value is not None:
            arguments += [flag, str(value)]
    return arguments


def layer_norm_flag(recipe: dict, learner_arg: list[str]) -> list[str]:
    """LayerNorm, said either way, for the learner's SAC has it unless told --no-layer-norm and its
    PPO not; nothing where a --learner-arg says it, since the learner refuses both flags at once."""
    if {"--layer-norm", "--no-layer-norm"} & set(learner_arg):
        return []
    return ["--layer-norm" if recipe["layer_norm"] else "--no-layer-norm"]


def plan_children(args: argparse.Namespace, run: str, run_dir: Path, replay_ports: list[int],
                  learner_port: int) -> list[Child]:
    """The processes of the job, in start order (stopped in reverse): one replay shard on each of
    `replay_ports`, the learner on `learner_port`, the actors and evaluators."""
    learner_ep = loopback(learner_port)
    to_replay = [flag for port in replay_ports for flag in ("--connect", loopback(port))]
    # Everyone also listens on an ephemeral loopback port, so Zenoh's gossip meshes the peers.
    common = ["--run", run, "--log-level", args.log_level]
    py = [sys.executable, "-m"]
    recipe = recipe_of(args).values
    shards = len(replay_ports)
    if args.algo in ON_POLICY:  # the queue table alone; a learner asking for one batch at a time, the freshest
        tables = [["--capacity", "0", "--queue-capacity", str(args.queue_capacity or 2 * recipe["batch_size"]),
                   "--queue-max-lag", str(args.queue_max_lag)]]
        in_flight = ["--in-flight", "1"]
    else:
        tables = [["--capacity", str(capacity)] for capacity in shard_capacities(replay_capacity(args), shards)]
        in_flight = []
    # Each shard waits for its share of --min-replay, so that together they wait for about as much as one would.
    shard_recipe = recipe if shards <= 1 else recipe | {"min_replay": -(-recipe["min_replay"] // shards)}
    replay_task, learner_task = task_flags(args.env_id, args.image_size) if family_of(args.env_id) != RUNNER else ([], [])
    children = [Child(replay_name(shard, shards), tier=0, progress=("replay", str(shard), "inserted"),
                      argv=py + ["l2r.replay", *common, *shard_flags(shard, shards), "--listen", loopback(port),
                                 *tables[shard], *daemon_flags(shard_recipe, REPLAY_FLAGS), *replay_task,
                                 "--snapshot-dir", str(run_dir / "replay"), *args.replay_arg])
                for shard, port in enumerate(replay_ports)]
    children.append(Child("learner", tier=1, progress=("learner", "0", "updates"), resume_args=["--resume"],
                          argv=py + ["l2r.learner", *common, "--listen", learner_ep, *to_replay,
                                     *(colocated_flags(args, recipe) if args.colocated else []),
                                     "--device", args.device, "--algo", args.algo, *in_flight, *learner_task,
                                     *daemon_flags(recipe, LEARNER_FLAGS), *layer_norm_flag(recipe, args.learner_arg),
                                     "--threads", str(learner_threads(args)),
                                     "--action-repeat", str(recipe["action_repeat"]),
                                     "--keep-checkpoints", str(args.keep_checkpoints),
                                     *([] if args.init_from is None else ["--init-from", str(args.init_from)]),
                                     "--run-dir", str(run_dir), *args.learner_arg]))
    peers = [*to_replay, "--connect", learner_ep, "--listen", "tcp/127.0.0.1:0"]
    acting = ["--env-id", args.env_id, "--num-envs", str(recipe["envs_per_actor"]),
              "--difficulty", str(args.difficulty), "--action-repeat", str(recipe["action_repeat"]),
              "--seed", str(args.seed), *(["--device", args.device] if registers_vector_env(args.env_id) else []),
              *([] if family_of(args.env_id) == RUNNER else ["--max-speed", "0"]),  # a runner's speed limit
              *([] if args.image_size is None else ["--image-size", str(args.image_size)]),
              *([] if args.photo_goals is None else ["--photo-goals", args.photo_goals])]
    reserve = disk_budget.reserve_bytes(run_dir, disk_budget.task_checkpoint_bytes(args.env_id, recipe["hidden"]))
    # MCAP episode logs record the runner's body, or a camera or photo task's images: none for another task
    logs = [] if args.no_episode_logs or family_of(args.env_id) not in (RUNNER, PIXELS, PHOTO) else [
        "--episode-log-dir", str(run_dir / "episodes"), "--log-every", str(args.log_every),
        "--log-min-free-mb", f"{disk_budget.LOW_FACTOR * reserve / MB:.1f}"]
    # Each training actor's share of the env steps of the sessions before (and of the port's stage
    # before an OpenSim stage): where its course goes on.
    steps_before = args.course_steps_before + (
        RunCounters.read(args.resume / "metrics").env_steps // args.actors if args.resume else 0)
    for i in range(0 if args.colocated else args.actors):
        # Last on the command line, so it overrides an --env-id among the actor arguments.
        opensim = ["--env-id", OPENSIM_ID] if i >= args.actors - args.opensim_actors else []
        children.append(Child(f"actor-{i}", tier=2, nice=args.actor_nice, progress=("actor", str(i), "env_steps"),
                              argv=py + ["l2r.actors", *common, *peers, *acting, "--actor-id", str(i),
                                         *([] if shards == 1 else ["--num-shards", str(shards)]),
                                         "--random-steps", str(recipe["random_steps"]), *gradient_flags(args, recipe),
                                         "--compress-frames", args.compress_frames,
                                         *robustness_flags(args, opensim=bool(opensim), steps_before=steps_before),
                                         *logs, *args.actor_arg,
                                         *opensim]))
    for i, env_id in enumerate(evaluator_env_ids(args)):
        eval_env = [] if env_id is None else ["--env-id", env_id]
        # Evaluators take ids after the actors' (the colocated worlds' 0) so their keys never collide.
        actor_id = (1 if args.colocated else args.actors) + i
        children.append(Child(f"evaluator-{i}", tier=2, nice=args.actor_nice,
                              progress=("evaluator", str(actor_id), "env_steps"),
                              argv=py + ["l2r.actors", *common, *peers, *acting, "--evaluate",
                                         "--actor-id", str(actor_id),
                                         "--num-envs", str(min(args.eval_episodes, recipe["envs_per_actor"])),
                                         "--eval-episodes", str(args.eval_episodes),
                                         "--eval-interval", str(args.eval_interval), *logs, *args.actor_arg,
                                         *eval_env, *([] if args.eval_difficulty is None else
                                                      ["--difficulty", str(args.eval_difficulty)])]))
    return children


def colocated_flags(args: argparse.Namespace, recipe: dict) -> list[str]:
    """The learner's flags for the worlds it steps itself (--colocated): the actors' worlds, and for
    SAC and TD3 their warm-up and the replay's capacity (an on-policy recipe has neither)."""
    flags = ["--colocated-env", args.env_id, "--colocated-worlds", str(args.actors * recipe["envs_per_actor"]),
             "--colocated-difficulty", str(args.difficulty), "--seed", str(args.seed)]
    if args.algo not in ON_POLICY:
        flags += ["--colocated-capacity", str(replay_capacity(args)),
                  "--colocated-random-steps", str(args.actors * recipe["random_steps"]),
                  "--colocated-min-replay", str(recipe["min_replay"])]
    randomize = recipe.get("randomize")
    return flags + (["--colocated-randomize", randomize] if randomize else [])


def shard_flags(shard: int, shards: int) -> list[str]:
    """A replay server's flags for its place among the job's shards (none for a job's only one)."""
    return [] if shards == 1 else ["--shard", str(shard), "--num-shards", str(shards)]


def gradient_flags(args: argparse.Namespace, recipe: dict) -> list[str]:
    """A training actor's flags for A3C: a gradient of each rollout of the recipe's batch size, sent instead of it."""
    return ["--send-gradients", "--chunk-size", str(recipe["batch_size"])] if args.algo == "a3c" else []


def robustness_flags(args: argparse.Namespace, opensim: bool, steps_before: int) -> list[str]:
    """A training actor's flags for the robustness levers that are on (randomisation is the MuJoCo
    port's: not for an OpenSim actor); a difficulty schedule goes on after the `steps_before` its
    place in the run took in the sessions before."""
    flags = []
    recipe = recipe_of(args)
    if recipe.values.get("difficulty_schedule"):
        flags += ["--difficulty-schedule", recipe.values["difficulty_schedule"]]
        flags += ["--env-steps-before", str(steps_before)] if steps_before else []
    randomize = recipe.values.get("randomize")
    # The recipe's randomisation only where the actors' env takes it (an --actor-arg may give them OpenSim).
    takes_it = recipe.origins.get("randomize") == "flag" or not randomize_refusal(actors_env_id(args))
    if randomize and not opensim and takes_it:
        flags += ["--randomize", randomize]
    if args.observation_noise:
        flags += ["--observation-noise", str(args.observation_noise)]
    if args.action_noise:
        flags += ["--action-noise", str(args.action_noise)]
    if args.exploration_noise != "white":
        flags += ["--exploration-noise", args.exploration_noise]
    if args.parameter_noise:
        flags += ["--parameter-noise", str(args.parameter_noise)]
    return flags


def actors_env_id(args: argparse.Namespace) -> str:
    """The training actors' env: --env-id, or the last one an --actor-arg gives them."""
    env_id, words = args.env_id, iter(args.actor_arg)
    for word in words:
        if word == "--env-id":
            env_id = next(words, env_id)
        elif word.startswith("--env-id="):
            env_id = word.split("=", 1)[1]
    return env_id


def simulator_of_each_actor(children: list[Child]) -> dict[int, str]:
    """The env id each actor and evaluator steps, by actor id, as its own command line says."""
    settings = [actor_settings(c.argv[3:]) for c in children if c.argv[2] == "l2r.actors"]
    return {s.actor_id: s.env_id for s in settings}
