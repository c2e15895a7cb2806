"""`l2r up --config FILE.toml`: the file's keys are the long flag names; a flag's value comes from the
command line, else the file, else launch.json on --resume, else the default."""

import json

import pytest

from l2r.job_plan import replay_capacity
from l2r.up import parse_args


@pytest.fixture
def config(tmp_path):
    """``config(text)``: the path of a TOML file holding ``text``."""
    def write(text: str) -> str:
        path = tmp_path / "up.toml"
        path.write_text(text)
        return str(path)
    return write


def test_the_file_sets_flags_and_the_command_line_wins(config):
    path = config('seconds = 7200\neval-env-id = ["l2r/RunOpenSim-v0", "l2r/Run-v0"]\nmirror = false\n'
                  'difficulty = 2\nruns-dir = "elsewhere"\n')
    args, _ = parse_args(["--config", path])
    assert (args.seconds, args.mirror, args.difficulty, str(args.runs_dir)) == (7200.0, False, 2, "elsewhere")
    assert args.eval_env_id == ["l2r/RunOpenSim-v0", "l2r/Run-v0"]
    args, _ = parse_args(["--config", path, "--seconds", "60", "--mirror", "--eval-env-id", "l2r/Run-v0"])
    assert (args.seconds, args.mirror, args.difficulty) == (60.0, True, 2)
    assert args.eval_env_id == ["l2r/Run-v0"]  # a repeatable flag replaces the file's list, as it does launch.json's
    assert args.actors == 1  # a flag in neither keeps its default


def test_on_resume_the_command_line_wins_over_the_file_and_the_file_over_launch_json(config, tmp_path, capsys):
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    stored = {"seconds": 100.0, "actors": 2, "batch_size": 64, "eval_env_id": ["l2r/Run-v0"]}
    (run_dir / "launch.json").write_text(json.dumps({"args": stored}))
    path = config('seconds = 7200\nactors = 3\neval-env-id = ["l2r/RunOpenSim-v0"]\n')
    args, _ = parse_args(["--resume", str(run_dir), "--config", path, "--actors", "4"])
    assert (args.actors, args.seconds, args.eval_env_id) == (4, 7200.0, ["l2r/RunOpenSim-v0"])
    assert (args.batch_size, replay_capacity(args)) == (64, 1_000_000)  # launch.json, then the default
    warnings = capsys.readouterr().err
    assert "--seconds 7200.0 replaces 100.0 from" in warnings and "--actors 4 replaces 2 from" in warnings


@pytest.mark.parametrize("toml, message", [
    ("bogus = 1", "unknown key 'bogus' (keys are the long flag names, except resume and config)"),
    ('resume = "runs/x"', "unknown key 'resume'"),
    ('seconds = "7200"', "seconds = '7200': should be a number"),
    ("actors = 1.5", "actors = 1.5: should be an integer"),
    ("actors = true", "actors = True: should be an integer"),
    ("mirror = 1", "mirror = 1: should be true or false"),
    ('eval-env-id = "l2r/Run-v0"', "eval-env-id = 'l2r/Run-v0': should be a list of strings"),
    ('device = "tpu"', "device = 'tpu': should be one of auto, cpu, cuda"),
    ("seconds = ", "not TOML"),
])
def test_a_bad_file_is_one_line_naming_the_key_and_exit_code_2(config, toml, message, capsys):
    path = config(toml + "\n")
    with pytest.raises(SystemExit) as exit_:
        parse_args(["--config", path])
    err = capsys.readouterr().err
    assert exit_.value.code == 2
    assert len(err.splitlines()) == 1 and err.startswith(f"l2r up: --config {path}: {message}"), err


def test_a_missing_file_is_a_usage_error(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        parse_args(["--config", str(tmp_path / "none.toml")])
    assert exit_.value.code == 2 and "No such file or directory" in capsys.readouterr().err
