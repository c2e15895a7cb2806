"""`l2r up`'s recipes (l2r.recipes): the task's family picks one, --recipe another, a flag replaces
one value; every value reaches the daemon that uses it, as that daemon's own parser reads it; the
runner trains as before recipes, and a run from before them resumes as it began."""

import json
from pathlib import Path

import pytest

from l2r import disk_budget
from l2r.actors.__main__ import parse_settings as actor_settings
from l2r.job_plan import LEARNER_FLAGS, plan_children, recipe_of
from l2r.learner.__main__ import parse_settings as learner_settings
from l2r.recipes import PHOTO, PIXELS, RECIPES, RUNNER, RUNNER_CURRICULUM, RUNNER_RANDOMIZATION, SETTINGS, STANDARD
from l2r.replay.__main__ import parse_settings as replay_settings
from l2r.up import build_parser, parse_args, write_launch

REPLAY = "--run run --log-level INFO --listen tcp/127.0.0.1:7447"
LEARNER = "--run run --log-level INFO --listen tcp/127.0.0.1:7448 --connect tcp/127.0.0.1:7447 --device cpu"
ACTOR = "--run run --log-level INFO --connect tcp/127.0.0.1:7447 --connect tcp/127.0.0.1:7448 --listen tcp/127.0.0.1:0"
RUNNER_LOGS = "--episode-log-dir runs/x/episodes --log-every 10"
EVALUATOR = "--evaluate --actor-id 1 --num-envs 2 --eval-episodes 2 --eval-interval 20.0"
# The command lines `l2r up --learner-threads 1` planned before recipes, with --algo and, for
# Hopper-v5, --env-id Hopper-v5 --action-repeat 1; but for --random-steps 0, the warm-up those
# actors had in effect (the learner's first, untrained policy ended it, so it was as if 0).
BEFORE = {
    ("l2r/Run-v0", "sac"): {
        "replay": f"{REPLAY} --capacity 1000000 --min-size 10000 --samples-per-insert 0.0 --snapshot-dir runs/x/replay",
        "learner": f"{LEARNER} --update-repeat 1 --batch-size 256 --hidden 256,256 --relative-x --normalize-obs "
                   f"--mirror --threads 1 --action-repeat 3 --keep-checkpoints 3 --run-dir runs/x",
        "actor-0": f"{ACTOR} --env-id l2r/Run-v0 --num-envs 4 --difficulty 0 --action-repeat 3 --seed 0 --actor-id 0 "
                   f"--random-steps 0 {RUNNER_LOGS}",
        "evaluator-0": f"{ACTOR} --env-id l2r/Run-v0 --num-envs 4 --difficulty 0 --action-repeat 3 --seed 0 "
                       f"{EVALUATOR} {RUNNER_LOGS}"},
    ("l2r/Run-v0", "ppo"): {
        "replay": f"{REPLAY} --capacity 0 --queue-capacity 4096 --queue-max-lag 3 --snapshot-dir runs/x/replay",
        "learner": f"{LEARNER} --algo ppo --in-flight 1 --relative-x --normalize-obs --threads 1 --action-repeat 3 "
                   f"--keep-checkpoints 3 --run-dir runs/x",
        "actor-0": f"{ACTOR} --env-id l2r/Run-v0 --num-envs 4 --difficulty 0 --action-repeat 3 --seed 0 --actor-id 0 "
                   f"--random-steps 0 {RUNNER_LOGS}",
        "evaluator-0": f"{ACTOR} --env-id l2r/Run-v0 --num-envs 4 --difficulty 0 --action-repeat 3 --seed 0 "
                       f"{EVALUATOR} {RUNNER_LOGS}"},
    ("Hopper-v5", "sac"): {
        "replay": f"{REPLAY} --capacity 1000000 --min-size 10000 --samples-per-insert 0.0 --obs-dim 11 --act-dim 3 "
                  f"--snapshot-dir runs/x/replay",
        "learner": f"{LEARNER} --update-repeat 1 --batch-size 256 --hidden 256,256 --obs-dim 11 --act-dim 3 "
                   f"--normalize-obs --threads 1 --action-repeat 1 --keep-checkpoints 3 --run-dir runs/x",
        "actor-0": f"{ACTOR} --env-id Hopper-v5 --num-envs 4 --difficulty 0 --action-repeat 1 --seed 0 --max-speed 0 "
                   f"--actor-id 0 --random-steps 0",
        "evaluator-0": f"{ACTOR} --env-id Hopper-v5 --num-envs 4 --difficulty 0 --action-repeat 1 --seed 0 "
                       f"--max-speed 0 {EVALUATOR}"},
    ("Hopper-v5", "ppo"): {
        "replay": f"{REPLAY} --capacity 0 --queue-capacity 4096 --queue-max-lag 3 --obs-dim 11 --act-dim 3 "
                  f"--snapshot-dir runs/x/replay",
        "learner": f"{LEARNER} --algo ppo --in-flight 1 --obs-dim 11 --act-dim 3 --normalize-obs --threads 1 "
                   f"--action-repeat 1 --keep-checkpoints 3 --run-dir runs/x",
        "actor-0": f"{ACTOR} --env-id Hopper-v5 --num-envs 4 --difficulty 0 --action-repeat 1 --seed 0 --max-speed 0 "
                   f"--actor-id 0 --random-steps 0",
        "evaluator-0": f"{ACTOR} --env-id Hopper-v5 --num-envs 4 --difficulty 0 --action-repeat 1 --seed 0 "
                       f"--max-speed 0 {EVALUATOR}"},
}


def old_launch(env_id: str, algo: str) -> dict:
    """launch.json's flags as l2r up stored them before recipes: the on/off options as true."""
    return {"args": {
        "seconds": 100.0, "env_steps": 0, "seed": 0, "max_restarts": 3, "env_id": env_id, "actors": 1,
        "envs_per_actor": 4, "difficulty": 0, "action_repeat": 3 if env_id.startswith("l2r/") else 1,
        "random_steps": None, "evaluators": 1, "eval_episodes": 2, "eval_interval": 20.0, "eval_env_id": [],
        "opensim_actors": 0, "log_every": 10, "actor_nice": 0, "no_episode_logs": False, "device": "cpu",
        "learner_threads": 0, "algo": algo, "batch_size": None, "hidden": None, "update_repeat": 1, "relative_x": True,
        "normalize_obs": True, "mirror": True, "min_replay": 10000, "samples_per_insert": 0.0, "capacity": 1000000,
        "queue_capacity": None, "queue_max_lag": 3, "keep_checkpoints": 3, "learner_arg": [], "replay_arg": [],
        "actor_arg": [], "status_interval": 2.0, "log_level": "INFO"}}


def planned(*argv: str) -> dict[str, list[str]]:
    """Each process's arguments in the job `l2r up ARGV` plans."""
    args, _ = parse_args(list(argv))
    return {c.name: c.argv[3:] for c in plan_children(args, "run", Path("runs/x"), [7447], 7448)}


def assert_same_settings(now: dict[str, list[str]], before: dict[str, str]) -> None:
    """Every daemon of both jobs is started with the same settings, as its own parser reads them."""
    before = {name: line.split() for name, line in before.items()}
    assert now.keys() == before.keys()
    assert replay_settings(now["replay"]) == replay_settings(before["replay"])
    learner_now, learner_before = learner_settings(now["learner"]), learner_settings(before["learner"])
    assert learner_now.algorithm() == learner_before.algorithm()
    assert learner_now.learner() == learner_before.learner()
    for name in ("actor-0", "evaluator-0"):
        # The episode logs' floor of free space came later: it trains nothing differently.
        assert actor_settings(now[name]).model_copy(update={"log_min_free_mb": 0.0}) == actor_settings(before[name])


def reached(children: dict[str, list[str]], recipe: dict) -> dict:
    """The value of each setting of `recipe` as the planned daemons take it."""
    replay, learner, actor = (replay_settings(children["replay"]), learner_settings(children["learner"]),
                              actor_settings(children["actor-0"]))
    values = {name: getattr(learner, name) for name in LEARNER_FLAGS}
    values |= {"layer_norm": learner.algorithm().layer_norm, "min_replay": replay.min_size,
               "samples_per_insert": replay.samples_per_insert, "hold_actors": replay.hold_actors,
               "random_steps": actor.random_steps, "envs_per_actor": actor.num_envs,
               "action_repeat": actor.action_repeat, "randomize": actor.randomize or "",
               "difficulty_schedule": actor.difficulty_schedule or ""}
    assert learner.action_repeat == actor.action_repeat  # the learner stores it for l2r eval
    return {name: values[name] for name in recipe}


# The levers runner/sac took on 2026-11-27, off: the runner then trains as it did before recipes.
SINCE_RECIPES = {"sac": ["--randomize", "", "--target-entropy-per-action", "-1", "--difficulty-schedule", ""],
                 "ppo": []}


@pytest.mark.parametrize("algo", ["sac", "ppo"])
def test_the_runner_trains_as_before_recipes(algo):
    assert_same_settings(planned("--algo", algo, "--learner-threads", "1", *SINCE_RECIPES[algo]),
                         BEFORE["l2r/Run-v0", algo])


def test_runner_sac_draws_a_body_each_episode_on_the_port_alone_and_halves_the_entropy_target():
    children = planned("--algo", "sac")
    assert actor_settings(children["actor-0"]).randomize == RUNNER_RANDOMIZATION
    assert actor_settings(children["evaluator-0"]).randomize is None  # the evaluators run the plain env
    assert learner_settings(children["learner"]).sac().target_entropy == -9.0  # -0.5 x 18 excitations
    assert learner_settings(planned("--algo", "sac", "--learner-arg=--target-entropy=-4")["learner"]).sac(
        ).target_entropy == -4.0
    assert actor_settings(planned("--randomize", "")["actor-0"]).randomize in (None, "")
    on_opensim = parse_args(["--env-id", "l2r/RunOpenSim-v0"])[0]
    assert recipe_of(on_opensim).values["randomize"] == "" and "off on l2r/RunOpenSim-v0" in recipe_of(
        on_opensim).origins["randomize"]
    assert actor_settings(planned("--algo", "ppo")["actor-0"]).randomize in (None, "")  # measured with SAC alone


def test_runner_sac_trains_on_the_obstacle_course_from_a_million_steps_unless_the_job_asks_for_one_difficulty():
    children = planned("--algo", "sac")
    assert actor_settings(children["actor-0"]).difficulty_schedule == RUNNER_CURRICULUM == "0:0,1000000:2"
    assert actor_settings(children["evaluator-0"]).difficulty_schedule is None  # the evaluators keep --difficulty
    for argv, why in ((["--difficulty", "2"], "off with --difficulty 2"),
                      (["--colocated"], "off with --colocated, whose worlds keep --difficulty"),
                      (["--env-id", "Hopper-v5", "--recipe", "runner"], "off on Hopper-v5, the runner's alone")):
        args, _ = parse_args(argv)
        recipe = recipe_of(args)
        assert (recipe.values["difficulty_schedule"], recipe.origins["difficulty_schedule"]) == ("", why)
        assert "--difficulty-schedule" not in {flag for c in plan_children(args, "run", Path("runs/x"), [7447], 7448)
                                               for flag in c.argv}
    assert actor_settings(planned("--difficulty-schedule", "0:0,5000:1")["actor-0"]).difficulty_schedule == "0:0,5000:1"
    assert actor_settings(planned("--difficulty", "1", "--difficulty-schedule", "0:1,5000:2")["actor-0"]
                          ).difficulty_schedule == "0:1,5000:2"  # given, it is what the job asks for
    assert actor_settings(planned("--algo", "ppo")["actor-0"]).difficulty_schedule is None  # measured with SAC alone


def test_a_resumed_run_s_actors_go_on_with_the_course_from_their_share_of_its_env_steps(tmp_path):
    args, launch = parse_args(["--actors", "2"])
    write_launch(tmp_path, args, ["--actors", "2"], launch, {})
    (tmp_path / "metrics").mkdir()
    (tmp_path / "metrics" / "status.csv").write_text("time,env_steps,updates,episodes\n3600,1700000,134000,9000\n")
    resumed = planned("--resume", str(tmp_path))
    assert [actor_settings(resumed[f"actor-{i}"]).actor().env_steps_before for i in (0, 1)] == [850_000, 850_000]
    assert actor_settings(planned("--actors", "2")["actor-0"]).env_steps_before == 0  # a new run starts the course


@pytest.mark.parametrize("family, algo", RECIPES)
def test_the_env_id_picks_the_family_and_each_value_reaches_its_daemon(family, algo):
    recipe = RECIPES[family, algo]
    # PPO takes no images: the photo family's PPO recipe is for its statistics views.
    photo = "l2r/PhotoTune-v0" if algo == "td3" else "l2r/PhotoEnhanceStats-v0"
    env_id = {RUNNER: "l2r/RunOpenSim-v0", PIXELS: "l2r/dmc-walker-walk-v0", PHOTO: photo,
              STANDARD: "Walker2d-v5"}[family]
    # Randomisation is the MuJoCo runner's: off on OpenSim (the test above has it on l2r/Run-v0).
    expected = recipe | ({"randomize": ""} if family == RUNNER else {})
    assert reached(planned("--env-id", env_id, "--algo", algo), recipe) == expected


def test_a_td3_job_samples_the_replay_table_as_sac_does_with_a_td3_learner():
    children = planned("--algo", "td3")
    replay, learner = replay_settings(children["replay"]), learner_settings(children["learner"])
    assert (replay.capacity, replay.min_size, replay.queue_capacity) == (1_000_000, 10_000, 0)
    config = learner.algorithm()
    assert (learner.algo, type(config).__name__, learner.in_flight) == ("td3", "TD3Config", 4)
    assert (config.batch_size, config.hidden, config.update_repeat, config.policy_delay) == (256, (256, 256), 1, 2)
    assert actor_settings(children["actor-0"]).random_steps == 0
    assert learner_settings(planned("--algo", "td3", "--scheduled-target-noise")["learner"]).td3().target_noise is None


@pytest.mark.parametrize("algo, batch_size, queue", [("a2c", 32, 64), ("reinforce", 4000, 8000), ("trpo", 2048, 4096),
                                                     ("acktr", 2500, 5000)])
def test_an_l2r_up_job_trains_each_on_policy_algorithm_from_the_queue_table(algo, batch_size, queue):
    children = planned("--env-id", "Hopper-v5", "--algo", algo)
    replay, learner = replay_settings(children["replay"]), learner_settings(children["learner"])
    # The queue alone, two batches long: an actor's chunk of 64 transitions must fit.
    assert (replay.capacity, replay.queue_capacity, learner.in_flight) == (0, queue, 1)
    assert (learner.algo, learner.algorithm().batch_size) == (algo, batch_size)


def test_an_a3c_job_s_actors_send_gradients_of_five_step_rollouts_to_an_a3c_learner():
    children = planned("--env-id", "Hopper-v5", "--algo", "a3c")
    learner, actor = learner_settings(children["learner"]), actor_settings(children["actor-0"])
    config = learner.algorithm()
    assert (learner.algo, type(config).__name__, config.batch_size, config.max_gradient_staleness) == (
        "a3c", "A3CConfig", 5, 4)
    assert (actor.send_gradients, actor.chunk_size) == (True, 5)
    assert not actor_settings(children["evaluator-0"]).send_gradients
    assert not actor_settings(planned("--env-id", "Hopper-v5", "--algo", "a2c")["actor-0"]).send_gradients


def test_recipe_forces_a_family_but_the_runner_s_body_options_stay_on_the_runner():
    assert reached(planned("--recipe", "standard"), RECIPES[STANDARD, "sac"]) == RECIPES[STANDARD, "sac"]
    on_hopper = reached(planned("--env-id", "Hopper-v5", "--recipe", "runner"), RECIPES[RUNNER, "sac"])
    assert on_hopper == RECIPES[RUNNER, "sac"] | {"relative_x": False, "mirror": False, "randomize": "",
                                                 "difficulty_schedule": ""}


def test_a_flag_replaces_one_value_and_launch_json_says_where_each_came_from(tmp_path):
    argv = ["--env-id", "Hopper-v5", "--reward-scale", "5", "--layer-norm", "--no-hold-actors", "--envs-per-actor", "2"]
    changed = {"reward_scale": 5.0, "layer_norm": True, "hold_actors": False, "envs_per_actor": 2}
    assert reached(planned(*argv), RECIPES[STANDARD, "sac"]) == RECIPES[STANDARD, "sac"] | changed
    args, launch = parse_args(argv)
    write_launch(tmp_path, args, argv, launch, {})
    written = json.loads((tmp_path / "launch.json").read_text())
    assert written["recipe"]["name"] == "standard/sac"
    assert written["recipe"]["values"]["reward_scale"] == {"value": 5.0, "from": "flag"}
    assert written["recipe"]["values"]["initial_alpha"] == {"value": 1.0, "from": "recipe"}
    assert (written["args"]["reward_scale"], written["args"]["initial_alpha"]) == (5.0, None)  # as given
    assert "from flags: layer_norm on, reward_scale 5, hold_actors off, envs_per_actor 2" in recipe_of(args).describe()


def test_the_photo_tuner_takes_the_dual_path_encoder_from_a_flag():
    tuner = RECIPES[PHOTO, "td3"]
    assert reached(planned("--env-id", "l2r/PhotoTune-v0", "--algo", "td3", "--encoder", "dual"), tuner) == \
        tuner | {"encoder": "dual"}


def test_every_setting_of_the_recipes_is_described_and_of_one_type():
    in_recipes = {name for table in RECIPES.values() for name in table}
    assert in_recipes == set(SETTINGS)
    for name in in_recipes:  # the type of its flag: 1 where 1.0 is meant would refuse --reward-scale 0.5
        assert len({type(table[name]) for table in RECIPES.values() if name in table}) == 1, name


def test_each_flag_s_help_names_the_recipes_values():
    help_ = {action.dest: action.help for action in build_parser()._actions}
    assert help_["reward_scale"].endswith("runner/sac 10, standard/sac 1, runner/ppo 1, standard/ppo 1, "
                                          "runner/a2c 1, standard/a2c 1, runner/reinforce 1, standard/reinforce 1, "
                                          "runner/trpo 1, standard/trpo 1, runner/acktr 1, standard/acktr 1, "
                                          "runner/td3 10, standard/td3 1, pixels/td3 1, pixels/sac 1, photo/td3 1, "
                                          "photo/ppo 1, runner/a3c 1, standard/a3c 1")
    assert help_["mirror"].endswith("runner/sac on, standard/sac off, runner/td3 on, standard/td3 off, pixels/td3 off, "
                                    "pixels/sac off, photo/td3 off")
    assert help_["policy_delay"].endswith("runner/td3 2, standard/td3 2, pixels/td3 1, photo/td3 2")


def test_a_learner_arg_still_wins_over_the_recipe():
    learner = planned("--learner-arg=--no-layer-norm", "--learner-arg=--reward-scale=1")["learner"]
    config = learner_settings(learner).sac()  # the learner refuses --layer-norm and --no-layer-norm at once
    assert (config.layer_norm, config.reward_scale, config.activation) == (False, 1.0, "elu")


def test_init_from_hands_the_learner_the_checkpoint_a_run_directory_holds(tmp_path, capsys):
    checkpoint = tmp_path / "old" / "learner" / "checkpoint.pt"
    checkpoint.parent.mkdir(parents=True)
    checkpoint.write_bytes(b"")  # found by l2r up; read by the learner (tests/learner/test_init_from.py)
    assert learner_settings(planned("--init-from", str(tmp_path / "old"))["learner"]).init_from == checkpoint
    assert learner_settings(planned()["learner"]).init_from is None
    with pytest.raises(SystemExit):
        parse_args(["--init-from", str(tmp_path / "none")])
    assert f"--init-from: no such checkpoint: {tmp_path / 'none'}" in capsys.readouterr().err


@pytest.mark.parametrize("env_id, algo", BEFORE)
def test_a_run_from_before_recipes_resumes_as_it_began(env_id, algo, tmp_path):
    (tmp_path / "launch.json").write_text(json.dumps(old_launch(env_id, algo)))
    assert_same_settings(planned("--resume", str(tmp_path), "--learner-threads", "1"), BEFORE[env_id, algo])


def test_a_run_resumes_with_the_recipe_it_resolved_and_the_flags_it_was_given(tmp_path):
    argv = ["--env-id", "Hopper-v5", "--batch-size", "64"]
    args, launch = parse_args(argv)
    write_launch(tmp_path, args, argv, launch, {})
    resumed = planned("--resume", str(tmp_path))
    assert reached(resumed, RECIPES[STANDARD, "sac"]) == RECIPES[STANDARD, "sac"] | {"batch_size": 64}


def test_a_run_recorded_before_a_setting_was_added_resumes_with_the_value_it_trained_with(tmp_path):
    args, launch = parse_args([])
    write_launch(tmp_path, args, [], launch, {})
    record = json.loads((tmp_path / "launch.json").read_text())
    for name in ("randomize", "target_entropy_per_action", "difficulty_schedule"):  # runner/sac before 2026-11-27
        del record["recipe"]["values"][name]
    (tmp_path / "launch.json").write_text(json.dumps(record))
    resumed = planned("--resume", str(tmp_path))
    assert actor_settings(resumed["actor-0"]).randomize in (None, "")
    assert learner_settings(resumed["learner"]).sac().target_entropy == -18.0
    assert actor_settings(resumed["actor-0"]).difficulty_schedule is None
    given = planned("--resume", str(tmp_path), "--randomize", "mass=0.1")  # a flag given again still wins
    assert actor_settings(given["actor-0"]).randomize == "mass=0.1"


def test_actors_log_episodes_of_the_runner_and_of_camera_tasks_alone():
    for env_id, logged in (("l2r/Run-v0", True), ("l2r/dmc-cartpole-swingup-v0", True), ("Hopper-v5", False)):
        children = planned("--env-id", env_id, "--algo", "td3")
        for name in ("actor-0", "evaluator-0"):
            assert (actor_settings(children[name]).episode_log_dir is not None) == logged, (env_id, name)


def test_actors_stop_logging_episodes_where_the_status_line_starts_showing_the_disk():
    children = planned("--env-id", "l2r/Run-v0")
    reserve = disk_budget.reserve_bytes(Path("runs/x"), disk_budget.task_checkpoint_bytes("l2r/Run-v0", "256,256"))
    floor = actor_settings(children["actor-0"]).actor().episode_log["min_free_bytes"]
    assert floor == pytest.approx(disk_budget.LOW_FACTOR * reserve, rel=0.01) and floor > reserve
