"""`l2r up` hands env ids to its actors and evaluators: --actor-arg for all of them, --eval-env-id
for the evaluators alone."""

import json
from pathlib import Path

import pytest

from l2r.actors.__main__ import parse_settings as actor_settings
from l2r.config import UsageError
from l2r.families import PIXELS, RUNNER, family_of
from l2r.job_plan import plan_children, simulator_of_each_actor
from l2r.learner.__main__ import parse_settings as learner_settings
from l2r.replay.__main__ import parse_settings as replay_settings
from l2r.sim.randomize import Randomization
from l2r.up import build_parser, parse_args


def env_ids(*argv: str) -> dict[str, str]:
    """The env id each actor and evaluator of a planned job would run."""
    args, _ = parse_args(["--actors", "2", *argv])
    children = plan_children(args, "run", Path("runs/x"), [7447], 7448)
    ids = {}
    for child in children:
        if child.argv[2] == "l2r.actors":
            ids[child.name] = actor_settings(child.argv[3:]).env_id
    return ids


def test_everyone_runs_the_default_env_unless_told():
    assert env_ids() == {"actor-0": "l2r/Run-v0", "actor-1": "l2r/Run-v0", "evaluator-0": "l2r/Run-v0"}


def difficulties(*argv: str) -> dict[str, int]:
    """The difficulty each actor and evaluator of a planned job would start its episodes at."""
    args, _ = parse_args(["--actors", "2", *argv])
    return {c.name: actor_settings(c.argv[3:]).difficulty for c in plan_children(args, "run", Path("runs/x"), [7447], 7448)
            if c.argv[2] == "l2r.actors"}


def test_eval_difficulty_sets_the_evaluators_alone():
    assert difficulties("--difficulty", "1") == {"actor-0": 1, "actor-1": 1, "evaluator-0": 1}
    assert difficulties("--eval-difficulty", "2", "--difficulty-schedule", "0:0,1000:2") == {
        "actor-0": 0, "actor-1": 0, "evaluator-0": 2}
    with pytest.raises(SystemExit):
        parse_args(["--env-id", "Hopper-v5", "--eval-difficulty", "2"])


def test_actor_arg_sets_every_actors_env():
    assert set(env_ids("--actor-arg=--env-id=l2r/RunOpenSim-v0").values()) == {"l2r/RunOpenSim-v0"}
    assert set(env_ids("--actor-arg=--env-id", "--actor-arg=l2r/RunOpenSim-v0").values()) == {"l2r/RunOpenSim-v0"}


def test_eval_env_id_sets_the_evaluators_alone():
    assert env_ids("--eval-env-id", "l2r/RunOpenSim-v0") == {
        "actor-0": "l2r/Run-v0", "actor-1": "l2r/Run-v0", "evaluator-0": "l2r/RunOpenSim-v0"}
    # It wins over an --env-id among the actor arguments.
    assert env_ids("--actor-arg=--env-id=l2r/RunOpenSim-v0", "--eval-env-id", "l2r/Run-v0") == {
        "actor-0": "l2r/RunOpenSim-v0", "actor-1": "l2r/RunOpenSim-v0", "evaluator-0": "l2r/Run-v0"}


def test_repeated_eval_env_ids_give_one_evaluator_per_simulator_at_least():
    assert env_ids("--eval-env-id", "l2r/Run-v0", "--eval-env-id", "l2r/RunOpenSim-v0") == {
        "actor-0": "l2r/Run-v0", "actor-1": "l2r/Run-v0",
        "evaluator-0": "l2r/Run-v0", "evaluator-1": "l2r/RunOpenSim-v0"}
    assert list(env_ids("--evaluators", "3", "--eval-env-id", "l2r/RunOpenSim-v0").values())[2:] == [
        "l2r/RunOpenSim-v0"] * 3


def test_opensim_actors_are_the_last_of_the_actors():
    assert env_ids("--actors", "3", "--opensim-actors", "1") == {
        "actor-0": "l2r/Run-v0", "actor-1": "l2r/Run-v0", "actor-2": "l2r/RunOpenSim-v0",
        "evaluator-0": "l2r/Run-v0"}
    with pytest.raises(SystemExit):
        env_ids("--opensim-actors", "3")


def test_the_job_knows_which_simulator_each_actor_id_steps():
    args = build_parser().parse_args(["--actors", "2", "--opensim-actors", "1", "--eval-env-id", "l2r/RunOpenSim-v0"])
    assert simulator_of_each_actor(plan_children(args, "run", Path("runs/x"), [7447], 7448)) == {
        0: "l2r/Run-v0", 1: "l2r/RunOpenSim-v0", 2: "l2r/RunOpenSim-v0"}


def test_resume_takes_the_stored_env_ids_and_a_repeated_flag_given_again_replaces_them(tmp_path, capsys):
    launch = {"args": {"eval_env_id": ["l2r/Run-v0", "l2r/RunOpenSim-v0"], "actor_arg": ["--chunk-size=16"]}}
    (tmp_path / "launch.json").write_text(json.dumps(launch))
    args, _ = parse_args(["--resume", str(tmp_path)])
    assert args.eval_env_id == ["l2r/Run-v0", "l2r/RunOpenSim-v0"] and args.actor_arg == ["--chunk-size=16"]
    args, _ = parse_args(["--resume", str(tmp_path), "--eval-env-id", "l2r/RunOpenSim-v0"])
    assert args.eval_env_id == ["l2r/RunOpenSim-v0"] and args.actor_arg == ["--chunk-size=16"]
    assert "replaces" in capsys.readouterr().err
    # launch.json of a run from before the flag was repeatable: one id, or none.
    for old, new in (("l2r/RunOpenSim-v0", ["l2r/RunOpenSim-v0"]), (None, [])):
        (tmp_path / "launch.json").write_text(json.dumps({"args": {"eval_env_id": old}}))
        assert parse_args(["--resume", str(tmp_path)])[0].eval_env_id == new


def learner_config(*argv: str):
    """The SAC settings the learner of a planned job would train with."""
    args, _ = parse_args(list(argv))
    learner = next(c for c in plan_children(args, "run", Path("runs/x"), [7447], 7448) if c.name == "learner")
    return learner_settings(learner.argv[3:]).sac()


def test_the_learner_trains_with_up_s_recipe_and_a_learner_arg_wins():
    config = learner_config()
    assert (config.hidden, config.update_repeat, config.batch_size) == ((256, 256), 1, 256)
    assert config.relative_x and config.normalize_obs and config.mirror
    config = learner_config("--no-mirror", "--no-normalize-obs", "--hidden", "64,64", "--learner-arg=--update-repeat=2")
    assert (config.hidden, config.update_repeat, config.normalize_obs, config.mirror) == ((64, 64), 2, False, False)
    assert config.relative_x


def test_a_ppo_job_feeds_a_queue_table_and_its_learner_takes_one_fresh_batch_at_a_time():
    args, _ = parse_args(["--algo", "ppo"])
    children = {c.name: c.argv[3:] for c in plan_children(args, "run", Path("runs/x"), [7447], 7448)}
    replay, learner = replay_settings(children["replay"]), learner_settings(children["learner"])
    assert (replay.capacity, replay.queue_capacity, replay.queue_max_lag) == (0, 2 * 2048, 3)
    config = learner.algorithm()  # the learner's own checks pass: no SAC-only option reaches it
    assert (learner.algo, learner.in_flight, config.batch_size, config.hidden) == ("ppo", 1, 2048, (64, 64))
    assert config.relative_x and config.normalize_obs
    assert actor_settings(children["actor-0"]).random_steps == 0
    args, _ = parse_args(["--algo", "ppo", "--batch-size", "512", "--random-steps", "100"])
    children = {c.name: c.argv[3:] for c in plan_children(args, "run", Path("runs/x"), [7447], 7448)}
    assert replay_settings(children["replay"]).queue_capacity == 1024
    assert learner_settings(children["learner"]).algorithm().batch_size == 512
    assert actor_settings(children["actor-0"]).random_steps == 100


def test_another_task_than_the_runner_sets_its_widths_and_turns_the_runner_s_options_off():
    # The runner's recipe, which turns them on, and the flags themselves: off all the same.
    args, _ = parse_args(["--env-id", "Hopper-v5", "--recipe", "runner", "--relative-x", "--mirror"])
    children = {c.name: c.argv[3:] for c in plan_children(args, "run", Path("runs/x"), [7447], 7448)}
    replay, learner = replay_settings(children["replay"]), learner_settings(children["learner"])
    assert (replay.obs_dim, replay.act_dim, learner.obs_dim, learner.act_dim) == (11, 3, 11, 3)
    config = learner.algorithm()
    assert not config.relative_x and not config.mirror and config.normalize_obs
    for name in ("actor-0", "evaluator-0"):
        actor = actor_settings(children[name])
        assert (actor.env_id, actor.max_speed, actor.episode_log_dir) == ("Hopper-v5", 0, None)


def test_a_camera_task_plans_its_observation_spec_and_the_pixels_recipe():
    assert family_of("l2r/dmc-cartpole-swingup-v0") == PIXELS and family_of("l2r/RunOpenSim-v0") == RUNNER
    args, _ = parse_args(["--env-id", "l2r/dmc-cartpole-swingup-v0", "--algo", "td3"])
    children = {c.name: c.argv[3:] for c in plan_children(args, "run", Path("runs/x"), [7447], 7448)}
    replay, learner = replay_settings(children["replay"]), learner_settings(children["learner"])
    assert replay.observation == learner.observation == "{pixels: uint8[3, 84, 84]}"
    assert (replay.act_dim, learner.act_dim, replay.capacity, replay.side_fraction) == (1, 1, 100_000, 0.0625)
    config = learner.algorithm()
    assert (config.frame_stack, config.augment_pad, config.n_step, config.hidden) == (3, 4, 3, (1024, 1024))
    # The task holds each action for 2 suite steps itself; the actors add no repeat of their own.
    assert actor_settings(children["actor-0"]).action_repeat == 1
    assert actor_settings(children["actor-0"]).actor().compress_frames  # frames go compressed unless told
    # SAC on the same task is DrQ: its recipe, the learner's image defaults.
    args, _ = parse_args(["--env-id", "l2r/dmc-cartpole-swingup-v0", "--algo", "sac"])
    children = {c.name: c.argv[3:] for c in plan_children(args, "run", Path("runs/x"), [7447], 7448)}
    drq = learner_settings(children["learner"]).algorithm()
    assert (type(drq).__name__, drq.frame_stack, drq.augment_pad, drq.batch_size, drq.actor_lr) == (
        "SACConfig", 3, 4, 512, 1e-3)


def test_compress_frames_off_reaches_the_actors():
    args, _ = parse_args(["--env-id", "l2r/dmc-cartpole-swingup-v0", "--algo", "td3", "--compress-frames", "off"])
    children = {c.name: c.argv[3:] for c in plan_children(args, "run", Path("runs/x"), [7447], 7448)}
    assert not actor_settings(children["actor-0"]).actor().compress_frames


def test_a_camera_task_s_frame_size_reaches_every_daemon():
    args, _ = parse_args(["--env-id", "l2r/dmc-cartpole-swingup-v0", "--algo", "td3", "--image-size", "48"])
    children = {c.name: c.argv[3:] for c in plan_children(args, "run", Path("runs/x"), [7447], 7448)}
    replay, learner = replay_settings(children["replay"]), learner_settings(children["learner"])
    assert replay.observation == learner.observation == "{pixels: uint8[3, 48, 48]}"
    assert [actor_settings(children[name]).actor().image_size for name in ("actor-0", "evaluator-0")] == [48, 48]


def test_the_photo_tuner_s_goals_reach_its_actors_and_evaluators():
    args, _ = parse_args(["--env-id", "l2r/PhotoTuneStats-v0", "--algo", "td3", "--photo-goals", "mixed"])
    children = {c.name: c.argv[3:] for c in plan_children(args, "run", Path("runs/x"), [7447], 7448)}
    assert [actor_settings(children[name]).actor().photo_goals for name in ("actor-0", "evaluator-0")] == ["mixed"] * 2
    args, _ = parse_args(["--env-id", "l2r/PhotoTuneStats-v0", "--algo", "td3"])
    flags = {flag for c in plan_children(args, "run", Path("runs/x"), [7447], 7448) for flag in c.argv}
    assert "--photo-goals" not in flags
    with pytest.raises(UsageError, match="--photo-goals looks: goals are the photo tuner's"):
        actor_settings(["--env-id", "l2r/PhotoEnhanceStats-v0", "--photo-goals", "looks"])


def test_a_task_l2r_cannot_train_is_refused_in_one_line(capsys):
    for argv, why in ((["--env-id", "l2r/dmc-cartpole-swingup-v0", "--algo", "ppo"],
                       "images train with --algo td3 (DrQ-v2) or sac (DrQ), not ppo"),
                      (["--env-id", "Nope-v0"], "doesn't exist"),
                      (["--env-id", "Hopper-v5", "--recipe", "pixels", "--algo", "ppo"], "no pixels recipe for --algo ppo"),
                      (["--env-id", "Hopper-v5", "--image-size", "48"], "--image-size 48: an image size is for the camera tasks"),
                      (["--env-id", "Hopper-v5", "--photo-goals", "looks"], "--photo-goals looks: goals are the photo tuner's"),
                      (["--env-id", "l2r/dmc-cartpole-swingup-v0", "--algo", "td3", "--image-size", "12"],
                       "the drq encoder takes uint8[C, H, W] images of at least 15 x 15")):
        with pytest.raises(SystemExit) as exit_:
            parse_args(argv)
        assert exit_.value.code == 2
        err = capsys.readouterr().err.strip().splitlines()[-1]
        assert err.startswith("l2r up: ") and why in err, err


def test_the_robustness_levers_reach_the_training_actors_alone():
    args, _ = parse_args(["--actors", "2", "--opensim-actors", "1", "--randomize", "mass=0.1,delay=0.5",
                          "--observation-noise", "0.01", "--action-noise", "0.02", "--exploration-noise", "pink",
                          "--difficulty-schedule", "0:0,1000:2", "--parameter-noise", "0.2"])
    children = {c.name: actor_settings(c.argv[3:]) for c in plan_children(args, "run", Path("runs/x"), [7447], 7448)
                if c.argv[2] == "l2r.actors"}
    port, opensim, evaluator = children["actor-0"], children["actor-1"], children["evaluator-0"]
    for actor in (port, opensim):
        config = actor.actor()
        assert (config.observation_noise, config.action_noise, config.exploration_noise,
                config.parameter_noise) == (0.01, 0.02, "pink", 0.2)
        assert str(config.difficulty_schedule) == "0:0,1000:2"
    assert port.actor().randomize == Randomization(mass=0.1, delay=0.5)
    assert not opensim.actor().randomize  # the MuJoCo port's alone
    config = evaluator.actor()
    assert (config.randomize, config.observation_noise, config.action_noise, config.exploration_noise,
            config.difficulty_schedule, config.parameter_noise) == (Randomization(), 0.0, 0.0, "white", None, 0.0)
    # Off, the actors' command lines are those of before the levers (runner/sac randomises: said off here).
    args, _ = parse_args(["--randomize", "", "--difficulty-schedule", ""])
    assert not {"--randomize", "--observation-noise", "--action-noise", "--exploration-noise",
                "--difficulty-schedule", "--parameter-noise"} & {
        flag for c in plan_children(args, "run", Path("runs/x"), [7447], 7448) for flag in c.argv}


@pytest.mark.parametrize("argv", [
    ["--randomize", "mass=0.7"], ["--randomize", "speed=0.1"], ["--difficulty-schedule", "5:1"],
    ["--observation-noise", "-1"], ["--env-id", "Hopper-v5", "--randomize", "mass=0.1"],
    ["--env-id", "Hopper-v5", "--difficulty-schedule", "0:1"], ["--parameter-noise", "-0.1"],
    ["--algo", "ppo", "--parameter-noise", "0.2"],
])
def test_bad_robustness_levers_are_refused_in_one_line(argv, capsys):
    with pytest.raises(SystemExit):
        parse_args(argv)
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_actors_of_a_vector_env_step_their_worlds_on_the_job_s_device():
    args, _ = parse_args(["--env-id", "l2r/RunWarp-v0", "--envs-per-actor", "256", "--device", "cuda"])
    settings = {c.name: actor_settings(c.argv[3:]) for c in plan_children(args, "run", Path("runs/x"), [7447], 7448)
                if c.argv[2] == "l2r.actors"}
    assert settings["actor-0"].device == "cuda" and settings["actor-0"].num_envs == 256
    assert settings["actor-0"].native_vector_env and not settings["evaluator-0"].native_vector_env
    args, _ = parse_args(["--device", "cuda"])  # single envs: the actors' policy stays on the CPU
    assert all(actor_settings(c.argv[3:]).device == "cpu"
               for c in plan_children(args, "run", Path("runs/x"), [7447], 7448) if c.argv[2] == "l2r.actors")
