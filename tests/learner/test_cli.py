"""The l2r-learner command line: help, and clear errors for bad input."""

import pytest

from l2r.config import EXIT_CANNOT_START
from l2r.learner.__main__ import cli, parse_settings


def test_help_explains_and_exits_zero(capsys):
    with pytest.raises(SystemExit) as exit_:
        cli(["--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    for flag in ("--resume", "--device", "--world-size", "--update-repeat", "--publish-every", "--precision",
                 "--compile"):
        assert flag in out


@pytest.mark.parametrize("argv, message", [
    (["--hidden", "512,x"], "--hidden 512,x: should be layer widths separated by commas"),
    (["--gamma", "1.5"], "--gamma 1.5: should be less than or equal to 1"),
    (["--world-size", "2", "--rank", "2"], "--rank 2 must be below --world-size 2"),
    (["--in-flight", "0"], "--in-flight 0: should be greater than or equal to 1"),
    (["--device", "tpu"], "--device tpu: should be 'auto', 'cpu' or 'cuda'"),
    (["--compile", "graphs", "--device", "cpu"], "--compile graphs captures CUDA graphs: it needs --device cuda"),
    (["--compile", "inductor", "--algo", "ppo"], "--compile inductor is for one SAC or TD3 learner"),
    (["--compile", "graphs", "--world-size", "2"], "--compile graphs is for one SAC or TD3 learner"),
    (["--algo", "trpo", "--world-size", "2"], "--algo trpo runs on one learner"),
    (["--algo", "acktr", "--layer-norm"], "ACKTR's K-FAC covers Linear layers alone"),
    (["--algo", "trpo", "--line-search-shrink", "1"], "--line-search-shrink 1: should be less than 1"),
    (["--colocated-env", "Pendulum-v1", "--algo", "a3c"], "--algo a3c takes the actors' gradients"),
    (["--colocated-env", "Pendulum-v1", "--prioritized"], "--colocated-env samples uniformly, on one learner"),
    (["--colocated-env", "Pendulum-v1", "--n-step", "3"], "--n-step 3: colocated worlds keep one-step transitions"),
    (["--colocated-env", "Pendulum-v1", "--frame-stack", "2"], "colocated worlds give one float32 vector at a time"),
    (["--colocated-env", "Pendulum-v1", "--colocated-randomize", "speed=0.1"],
     "--colocated-randomize: randomize has no speed"),
    (["--colocated-env", "NoSuchEnv-v0"], "NoSuchEnv-v0: "),
    (["--critics", "2", "--critics-in-min", "3"], "need 1 <= critics_in_min <= critics, got 3 of 2"),
    (["--algo", "td3", "--critics", "4"], "--critics and --critics-in-min are SAC's; --algo td3 has its own"),
    (["--colocated-env", "Pendulum-v1", "--env-id", "Hopper-v5"], "the networks take the colocated worlds' spaces"),
])
def test_bad_arguments_are_usage_errors(argv, message, capsys):
    assert cli(argv) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("algo", ["sac", "td3"])
def test_both_off_policy_learners_ask_for_n_step_returns(algo):
    # The daemon asks the replay server for the n its algorithm's config holds.
    assert parse_settings(["--algo", algo, "--n-step", "3"]).algorithm().n_step == 3
    assert parse_settings(["--algo", algo]).algorithm().n_step == 1


@pytest.mark.parametrize("variables, message", [
    ({"WORLD_SIZE": "two"}, "$WORLD_SIZE='two': should be a valid integer"),
    ({"RANK": "-1"}, "$RANK='-1': should be greater than or equal to 0"),
    ({"WORLD_SIZE": "2", "RANK": "2"}, "--rank 2 must be below --world-size 2"),
])
def test_malformed_torchrun_variables_are_usage_errors(variables, message, capsys, monkeypatch):
    monkeypatch.setattr("l2r.learner.__main__.train", lambda settings: 0)  # settings that pass must not train
    for name, value in variables.items():
        monkeypatch.setenv(name, value)
    assert cli([]) == 2
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and err.startswith(f"l2r-learner: {message}"), err


def test_cuda_without_cuda_is_a_clear_error_not_a_traceback(capsys, monkeypatch):
    monkeypatch.setattr("torch.cuda.is_available", lambda: False)
    assert cli(["--device", "cuda", "--run", "nothing-here"]) == EXIT_CANNOT_START
    assert "no CUDA device" in capsys.readouterr().err
    assert cli(["--compile", "graphs", "--run", "nothing-here"]) == EXIT_CANNOT_START  # --device auto found no GPU
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and "--compile graphs captures CUDA graphs: it needs a CUDA device" in err, err


def test_config_file_supplies_defaults(tmp_path):
    config = tmp_path / "learner.toml"
    config.write_text('run = "exp7"\nbatch-size = 128\nprecision = "float32"\n')
    settings = parse_settings(["--config", str(config), "--batch-size", "32"])
    assert (settings.run, settings.batch_size, settings.precision) == ("exp7", 32, "float32")


def test_resume_from_a_corrupt_checkpoint_fails_clearly_and_keeps_the_file(tmp_path, capsys):
    path = tmp_path / "learner" / "checkpoint.pt"
    path.parent.mkdir()
    path.write_bytes(b"not a checkpoint")
    # Fails before any network traffic, so the endpoint need not exist.
    code = cli(["--run", "x", "--run-dir", str(tmp_path), "--resume", "--device", "cpu",
                "--connect", "tcp/127.0.0.1:9"])
    assert code == EXIT_CANNOT_START
    err = capsys.readouterr().err  # one line, though torch's own message has several
    assert len(err.splitlines()) == 1 and err.startswith(f"l2r-learner: cannot read checkpoint {path}"), err
    assert path.read_bytes() == b"not a checkpoint"
