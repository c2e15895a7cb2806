"""Settings of the commands: flags, --config file and L2R_ variables in that order, checked types,
one-line errors with exit code 2 for bad usage, 3 for settings this machine cannot serve and 1 for
failures at run time, and --version."""

from __future__ import annotations

import json
import shutil
import socket
import subprocess
import sys
from importlib.metadata import version
from pathlib import Path

import pytest

from l2r.actors.__main__ import build_parser as actor_parser
from l2r.config import EXIT_CANNOT_START, UsageError, load
from l2r.evaluate import build_parser as eval_parser
from l2r.learner.__main__ import LearnerSettings, build_parser as learner_parser
from l2r.replay.__main__ import ReplaySettings, build_parser as replay_parser
from l2r.replay.storage import Storage, StorageConfig, storage_bytes
from l2r.up import build_parser as up_parser
from l2r.view import build_parser as view_parser


def replay_settings(argv: list[str], environ: dict[str, str] | None = None) -> ReplaySettings:
    return load(ReplaySettings, replay_parser(), argv, environ or {})


def learner_settings(argv: list[str], environ: dict[str, str] | None = None) -> LearnerSettings:
    return load(LearnerSettings, learner_parser(), argv, environ or {})


def test_flags_win_over_the_file_the_file_over_the_environment_and_that_over_defaults(tmp_path):
    path = tmp_path / "replay.toml"
    path.write_text('capacity = 500\nmin-size = 7\nlisten = ["tcp/127.0.0.1:7001"]\n')
    environ = {"L2R_CAPACITY": "300", "L2R_MIN_SIZE": "3", "L2R_SEED": "9", "L2R_LISTEN": "tcp/127.0.0.1:1,tcp/127.0.0.1:2"}
    settings = replay_settings(["--config", str(path), "--capacity", "100"], environ)
    assert (settings.capacity, settings.min_size, settings.seed, settings.num_shards) == (100, 7, 9, 1)
    assert settings.listen == ["tcp/127.0.0.1:7001"]  # a list from a higher source replaces a lower one's
    assert replay_settings([], environ).listen == ["tcp/127.0.0.1:1", "tcp/127.0.0.1:2"]
    assert replay_settings([], {"L2R_UNRELATED": "x"}).capacity == 1_000_000  # other L2R_ variables are not errors


def test_one_endpoint_given_as_a_string_is_a_list_of_one(tmp_path):
    path = tmp_path / "actor.toml"
    path.write_text('connect = "tcp/127.0.0.1:7447"\n')
    settings = replay_settings(["--config", str(path)])
    assert settings.connect == ["tcp/127.0.0.1:7447"]
    assert json.loads(settings.zenoh_session_config().get_json("connect/endpoints")) == ["tcp/127.0.0.1:7447"]


@pytest.mark.parametrize("toml, message", [
    ('device = "tpu"', "device = 'tpu': should be 'auto', 'cpu' or 'cuda'"),
    ("batch-size = 1.5", "batch-size = 1.5: should be a valid integer"),
    ('batch-size = "64"', "batch-size = '64': should be a valid integer"),  # a file's values are typed
    ("resume = 1", "resume = 1: should be a valid boolean"),
    ('connect = ["tcp/127.0.0.1:1", 7447]', "connect = 7447: should be a valid string"),
    ('listen = "bogus"', "listen = 'bogus': not a Zenoh endpoint"),
    ("gamma = 2.0", "gamma = 2.0: should be less than or equal to 1"),
    ("bogus = 1", "unknown key 'bogus' (keys are the long flag names)"),
    ("run = ", "not TOML"),
])
def test_a_bad_file_value_names_the_file_the_key_and_what_it_should_be(tmp_path, toml, message):
    path = tmp_path / "learner.toml"
    path.write_text(toml + "\n")
    with pytest.raises(UsageError) as error:
        learner_settings(["--config", str(path)])
    assert str(error.value).startswith(f"--config {path}: {message}")


@pytest.mark.parametrize("environ, message", [
    ({"L2R_BATCH_SIZE": "1.5"}, "$L2R_BATCH_SIZE='1.5': should be a valid integer"),
    ({"L2R_DEVICE": "tpu"}, "$L2R_DEVICE='tpu': should be 'auto', 'cpu' or 'cuda'"),
    ({"L2R_RUN": "a/b"}, "$L2R_RUN='a/b': invalid run name"),
])
def test_a_bad_environment_value_names_the_variable(environ, message):
    with pytest.raises(UsageError) as error:
        learner_settings([], environ)
    assert str(error.value).startswith(message)


def test_the_replays_observation_is_its_text_form_and_defaults_to_the_vector_of_obs_dim():
    assert str(replay_settings(["--obs-dim", "24"]).observation_spec()) == "{state: float32[24]}"
    camera = replay_settings(["--observation", "pixels: uint8[3, 84, 84], state: float32[24]"])
    assert str(camera.observation_spec()) == "{pixels: uint8[3, 84, 84], state: float32[24]}"
    for argv, message in (
            (["--observation", "pixels: int8[3]"], "--observation: observation.pixels: dtype 'int8', expected one"),
            (["--observation", "pixels uint8[3]"], "--observation: observation 'pixels uint8[3]': cannot read"),
            (["--observation", "pixels: uint8[3, 8, 8]", "--queue-capacity", "100"],
             "--queue-capacity 100: the queue table keeps the float32 vector alone")):
        with pytest.raises(UsageError) as error:
            replay_settings(argv)
        assert str(error.value).startswith(message), error.value


def test_torchruns_variables_come_below_flags_and_l2r_variables():
    def place(argv: list[str], environ: dict[str, str]) -> tuple[int, int]:
        settings = learner_settings(argv, environ)
        return settings.world_size, settings.rank

    torchrun = {"WORLD_SIZE": "4", "RANK": "3"}
    assert place([], torchrun) == (4, 3)
    assert place(["--rank", "1"], torchrun | {"L2R_WORLD_SIZE": "2"}) == (2, 1)
    assert place([], {}) == (1, 0)


def test_the_memory_check_counts_what_storage_allocates():
    for capacity, side_fraction in ((2, 0.125), (1000, 0.125), (12345, 1.0), (777, 0.001)):
        config = StorageConfig(capacity=capacity, side_fraction=side_fraction)
        assert storage_bytes(config) == Storage(config).nbytes


@pytest.mark.parametrize("parser", [replay_parser, learner_parser, actor_parser, view_parser, up_parser, eval_parser])
def test_help_shows_each_default_once(parser):
    parser = parser()
    formatter = parser._get_formatter()
    for action in parser._actions:
        if action.help:  # as --help prints it, with what the formatter adds
            assert formatter._expand_help(action).count("(default") <= 1, action.option_strings


# -- real processes -------------------------------------------------------------------------------

def run(*argv: str, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *argv], capture_output=True, text=True, timeout=timeout)


def test_every_command_has_the_packages_version():
    expected = version("l2r")
    assert run("l2r.cli", "--version").stdout == f"l2r {expected}\n"
    for module, prog in (("l2r.replay", "l2r-replay"), ("l2r.learner", "l2r-learner"), ("l2r.actors", "l2r-actor")):
        result = run(module, "--version")
        assert (result.returncode, result.stdout) == (0, f"{prog} {expected}\n")


def test_a_source_tree_never_installed_imports_with_its_pyproject_s_version(tmp_path):
    # A copy of the package's root and pyproject.toml, no metadata beside them (a checkout's own
    # l2r.egg-info, left by the editable install, would answer); -S: no site-packages either.
    checkout = Path(__file__).resolve().parent.parent
    (tmp_path / "l2r").mkdir()
    shutil.copy(checkout / "l2r" / "__init__.py", tmp_path / "l2r")
    shutil.copy(checkout / "pyproject.toml", tmp_path)
    result = subprocess.run([sys.executable, "-S", "-c", f"import sys; sys.path.insert(0, {str(tmp_path)!r}); "
                             "import l2r; print(l2r.__version__)"], capture_output=True, text=True, timeout=60,
                            cwd=tmp_path)
    assert (result.returncode, result.stdout) == (0, f"{version('l2r')}\n"), result.stderr


@pytest.mark.parametrize("argv, message", [
    (["l2r.cli", "bogus"], "l2r: unknown command 'bogus'"),
    (["l2r.cli", "up", "--actors", "0"], "l2r up: --actors and --envs-per-actor must be at least 1"),
    (["l2r.cli", "up", "--no-such-flag"], "l2r up: unrecognized arguments: --no-such-flag"),
    (["l2r.cli", "eval", "runs/x", "--episodes", "0"], "l2r eval: --episodes"),
    (["l2r.cli", "view", "--live", "--save", "a.rrd", "--web"], "l2r view: --save and --web exclude each other"),
    (["l2r.cli", "validate", "--policy", "x"], "l2r validate: --policy needs --dynamics"),
    (["l2r.replay", "--capacity", "1.5"], "l2r-replay: --capacity 1.5: should be a valid integer"),
    (["l2r.replay", "--zenoh-config", "/no/such/zenoh.json5"], "l2r-replay: --zenoh-config /no/such/zenoh.json5: "
                                                                "No such file or directory"),
    (["l2r.learner", "--device", "tpu"], "l2r-learner: --device tpu: should be 'auto', 'cpu' or 'cuda'"),
    (["l2r.actors", "--listen", "bogus"], "l2r-actor: --listen bogus: not a Zenoh endpoint"),
])
def test_bad_usage_is_one_line_and_exit_code_2_in_every_command(argv, message):
    result = run(*argv)
    assert result.returncode == 2, result.stderr
    assert len(result.stderr.splitlines()) == 1 and result.stderr.startswith(message), result.stderr


def test_a_port_in_use_is_one_line_and_exit_code_1():
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        result = run("l2r.replay", "--listen", f"tcp/127.0.0.1:{port}", "--capacity", "100")
    assert result.returncode == 1, result.stderr
    assert "Traceback" not in result.stderr
    assert result.stderr.splitlines()[-1].startswith(
        f"l2r-replay: cannot open the Zenoh session: Can not create a new TCP listener bound to tcp/127.0.0.1:{port}")


def test_a_replay_larger_than_memory_is_one_line_and_exit_code_3():
    result = run("l2r.replay", "--capacity", "2000000000")
    assert result.returncode == EXIT_CANNOT_START, result.stderr
    assert len(result.stderr.splitlines()) == 1, result.stderr
    assert result.stderr.startswith("l2r-replay: --capacity 2000000000 needs 584.3 GiB of memory; ")
