"""`l2r up` hands env ids to its actors and evaluators: --actor-arg for all of them, --eval-env-id
for the evaluators alone."""

from pathlib import Path

from l2r.actors.__main__ import parse_settings as actor_settings
from l2r.up import build_parser, plan_children


def env_ids(*argv: str) -> dict[str, str]:
    """The env id each actor and evaluator of a planned job would run."""
    args = build_parser().parse_args(["--actors", "2", *argv])
    children = plan_children(args, "run", Path("runs/x"), 7447, 7448)
    ids = {}
    for child in children:
        if child.argv[2] == "l2r.actors":
            ids[child.name] = actor_settings(child.argv[3:]).env_id
    return ids


def test_everyone_runs_the_default_env_unless_told():
    assert env_ids() == {"actor-0": "l2r/Run-v0", "actor-1": "l2r/Run-v0", "evaluator-0": "l2r/Run-v0"}


def test_actor_arg_sets_every_actors_env():
    assert set(env_ids("--actor-arg=--env-id=l2r/RunOpenSim-v0").values()) == {"l2r/RunOpenSim-v0"}


def test_eval_env_id_sets_the_evaluators_alone():
    assert env_ids("--eval-env-id", "l2r/RunOpenSim-v0") == {
        "actor-0": "l2r/Run-v0", "actor-1": "l2r/Run-v0", "evaluator-0": "l2r/RunOpenSim-v0"}
    # It wins over an --env-id among the actor arguments.
    assert env_ids("--actor-arg=--env-id=l2r/RunOpenSim-v0", "--eval-env-id", "l2r/Run-v0") == {
        "actor-0": "l2r/RunOpenSim-v0", "actor-1": "l2r/RunOpenSim-v0", "evaluator-0": "l2r/Run-v0"}
