"""deploy/docker-compose.yml: valid Compose, and what it starts is what the daemons accept."""

from __future__ import annotations

import copy
import importlib
import importlib.metadata
import importlib.resources
import json
import os
import re
import subprocess
import sys
import time
import uuid
from pathlib import Path

import jsonschema
import pytest
import zenoh

from l2r.protocol.keys import Keys

from . import compose
from tests.conftest import free_port, wait_for

from .zenoh_helpers import DEPLOY, make_secrets, start_router, stop

DAEMONS = {"replay": "l2r.replay", "learner": "l2r.learner", "learner-gpu": "l2r.learner", "actor": "l2r.actors"}
ROLE = {"replay": "replay", "learner": "learner", "learner-gpu": "learner", "actor": "actor"}


def compose_validator() -> jsonschema.Draft202012Validator:
    schema_file = importlib.resources.files("check_jsonschema.builtin_schemas.vendor") / "compose-spec.json"
    schema = json.loads(schema_file.read_text())
    return jsonschema.Draft202012Validator(schema, format_checker=jsonschema.FormatChecker())


def seconds(duration: str) -> float:
    """A Compose duration such as ``1m30s`` in seconds."""
    units = {"h": 3600, "m": 60, "s": 1, "ms": 1e-3}
    parts = re.findall(r"(\d+(?:\.\d+)?)(ms|h|m|s)", duration)
    assert parts, f"not a duration: {duration}"
    return sum(float(n) * units[u] for n, u in parts)


def test_compose_file_follows_the_compose_specification():
    validator = compose_validator()
    doc = compose.load()
    assert [e.message for e in validator.iter_errors(doc)] == []
    broken = copy.deepcopy(doc)
    broken["services"]["replay"]["stop_grace_priod"] = "2m"  # a typo the schema must catch
    assert list(validator.iter_errors(broken))


def test_router_runs_the_zenoh_release_of_the_python_package():
    image = compose.load()["services"]["router"]["image"]
    assert image == f"eclipse/zenoh:{importlib.metadata.version('eclipse-zenoh')}"


@pytest.mark.parametrize("name", DAEMONS)
def test_daemons_are_supervised_and_stop_gracefully(name):
    spec = compose.load()["services"][name]
    assert spec["init"] is True
    assert spec["healthcheck"]["test"][0] == "CMD"
    assert spec["depends_on"]
    assert all(dep["condition"] == "service_healthy" for dep in spec["depends_on"].values())
    # Longer than a final replay snapshot or checkpoint takes (seconds for a million transitions).
    assert seconds(spec["stop_grace_period"]) >= (60 if ROLE[name] != "actor" else 20)


def test_gpu_learner_reserves_gpus():
    spec = compose.load()["services"]["learner-gpu"]
    (device,) = spec["deploy"]["resources"]["reservations"]["devices"]
    assert device["capabilities"] == ["gpu"] and spec["build"]["dockerfile"] == "deploy/Dockerfile.cuda"


@pytest.fixture
def argv_recorder(tmp_path):
    """A PATH on which l2r-replay, l2r-learner and l2r-actor only record the argv they got."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    for script in ("l2r-replay", "l2r-learner", "l2r-actor"):
        path = bin_dir / script
        path.write_text(f"#!{sys.executable}\nimport json, sys\nprint(json.dumps(sys.argv[1:]))\n")
        path.chmod(0o755)
    return {**os.environ, "PATH": f"{bin_dir}:{os.environ['PATH']}"}


@pytest.mark.parametrize("name", DAEMONS)
def test_each_daemon_accepts_its_compose_command(name, argv_recorder):
    """Run the service's command as Compose would (sh and all) and parse what reaches the daemon."""
    service = compose.services({"L2R_RUN": "exp7"})[name]
    out = subprocess.run(service.command, env=argv_recorder, capture_output=True, text=True, check=True, timeout=30)
    argv = json.loads(out.stdout)
    args = importlib.import_module(f"{DAEMONS[name]}.__main__").build_parser().parse_args(argv)
    assert args.run == "exp7"
    # Its Zenoh config is its role's, from the secrets directory mounted for this service alone.
    config = Path(args.zenoh_config)
    assert config.name == "zenoh.json5" and service.binds[str(config.parent)] == DEPLOY / "secrets" / ROLE[name]
    # What it writes goes to the run volume.
    written = {"replay": "snapshot_dir", "learner": "run_dir", "actor": "episode_log_dir"}[ROLE[name]]
    assert service.volumes.get("/srv/l2r/run") == "run" and str(getattr(args, written)).startswith("/srv/l2r/run")


def test_actor_replicas_get_different_ids(argv_recorder):
    """--scale actor=N runs one command N times; the id comes from each container's hostname."""
    service = compose.services({})["actor"]
    ids = set()
    for hostname in ("0b5e6f1c2d3a", "9f00c1d2e3b4", "0b5e6f2c2d3a"):
        cmd = ["unshare", "--uts", "sh", "-c", f'hostname {hostname} && exec "$@"', "sh", *service.command]
        if os.geteuid() != 0:
            pytest.skip("needs root for a UTS namespace per replica")
        argv = json.loads(subprocess.run(cmd, env=argv_recorder, capture_output=True, text=True, check=True).stdout)
        ids.add(argv[argv.index("--actor-id") + 1])
    assert len(ids) == 3


def test_healthcheck_sees_a_live_daemon_and_only_it(tmp_path):
    """deploy/healthcheck.py finds a role's liveliness token through a router, and no other role's."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = start_router(["-l", endpoint], tmp_path / "router.log")
    config = tmp_path / "client.json5"
    config.write_text(json.dumps({"mode": "client", "connect": {"endpoints": [endpoint]},
                                  "scouting": {"multicast": {"enabled": False}}}))
    run = f"hc-{uuid.uuid4().hex[:8]}"
    conf = zenoh.Config.from_file(str(config))
    try:
        with zenoh.open(conf) as session:
            token = session.liveliness().declare_token(Keys(run).alive("replay", 0))

            def check(role: str) -> int:
                cmd = [sys.executable, str(DEPLOY / "healthcheck.py"), "--zenoh-config", str(config),
                       "--run", run, "--role", role, "--timeout", "2"]
                return subprocess.run(cmd, capture_output=True, timeout=30).returncode

            assert check("replay") == 0
            assert check("learner") == 1
            token.undeclare()
    finally:
        assert stop(router) == 0, "the router did not stop cleanly on SIGTERM"


def test_a_daemon_waits_for_the_router_instead_of_exiting(tmp_path):
    """With its role config, l2r-replay started before any router keeps retrying, then joins it."""
    secrets = make_secrets(tmp_path / "secrets")
    endpoint = f"tls/127.0.0.1:{free_port()}"
    run = f"wait-{uuid.uuid4().hex[:8]}"
    replay_config = str(secrets / "replay" / "zenoh.json5")
    with open(tmp_path / "replay.log", "w") as out:
        replay = subprocess.Popen([sys.executable, "-m", "l2r.replay", "--run", run, "--zenoh-config", replay_config,
                                   "--connect", endpoint, "--capacity", "1000"], stdout=out, stderr=subprocess.STDOUT)
    router = None
    try:
        time.sleep(3)
        assert replay.poll() is None, (tmp_path / "replay.log").read_text()
        router = start_router(["-c", str(secrets / "router" / "zenoh.json5"), "-l", endpoint], tmp_path / "router.log")
        learner_config = tmp_path / "learner.json5"
        learner_config.write_text((secrets / "learner" / "zenoh.json5").read_text().replace("tls/router:7447", endpoint))
        healthcheck = [sys.executable, str(DEPLOY / "healthcheck.py"), "--zenoh-config", str(learner_config),
                       "--run", run, "--role", "replay", "--timeout", "2"]
        assert wait_for(lambda: subprocess.run(healthcheck, capture_output=True, timeout=30).returncode == 0,
                        timeout=30, interval=0.5), (tmp_path / "replay.log").read_text()
    finally:
        stop(replay)
        if router:
            stop(router)
