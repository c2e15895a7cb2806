"""deploy/docker-compose.yml: valid Compose, and what it starts is what the daemons accept."""

from __future__ import annotations

import copy
import importlib.metadata
import importlib.resources
import json
import subprocess
import sys
import time
import uuid
from pathlib import Path

import jsonschema
import pytest
import zenoh

from l2r.protocol.keys import Keys
from l2r.router import parser as router_parser

from . import compose
from tests.conftest import free_port, wait_for

from .daemons import SECRETS, WRITES_TO, daemon_settings, healthcheck_args
from .zenoh_helpers import DEPLOY, make_secrets, start_router, stop

ROLE = {"replay": "replay", "learner": "learner", "learner-gpu": "learner", "actor": "actor"}
"""daemon service -> its role"""


def compose_validator() -> jsonschema.Draft202012Validator:
    schema_file = importlib.resources.files("check_jsonschema.builtin_schemas.vendor") / "compose-spec.json"
    schema = json.loads(schema_file.read_text())
    return jsonschema.Draft202012Validator(schema, format_checker=jsonschema.FormatChecker())


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


def test_the_router_override_runs_l2r_router_from_the_l2r_image_with_the_same_flags():
    """deploy/docker-compose.l2r-router.yml, for hosts that cannot pull eclipse/zenoh."""
    override = compose.load(DEPLOY / "docker-compose.l2r-router.yml")
    assert [e.message for e in compose_validator().iter_errors(override)] == []
    router, services = override["services"]["router"], compose.load()["services"]
    assert router["image"] == services["replay"]["image"] and router["build"] == services["replay"]["build"]
    assert router["command"] == ["l2r", "router", *services["router"]["command"]]
    router_parser().parse_args(router["command"][2:])


@pytest.mark.parametrize("name", ROLE)
def test_daemons_are_supervised_and_stop_gracefully(name):
    spec = compose.load()["services"][name]
    assert spec["init"] is True
    assert spec["healthcheck"]["test"][0] == "CMD"
    assert spec["depends_on"]
    assert all(dep["condition"] == "service_healthy" for dep in spec["depends_on"].values())
    # Longer than a final replay snapshot or checkpoint takes (seconds for a million transitions).
    assert compose.seconds(spec["stop_grace_period"]) >= (60 if ROLE[name] != "actor" else 20)


def test_gpu_learner_reserves_gpus():
    spec = compose.load()["services"]["learner-gpu"]
    (device,) = spec["deploy"]["resources"]["reservations"]["devices"]
    assert device["capabilities"] == ["gpu"] and spec["build"]["dockerfile"] == "deploy/Dockerfile.cuda"


@pytest.mark.parametrize("name", ROLE)
def test_each_daemon_accepts_its_compose_command(name, rendered_secrets):
    """The service's command and health check, read by the daemon's and the health check's own parsers."""
    service = compose.services({"L2R_RUN": "exp7"})[name]
    # Its Zenoh config is its role's, from the secrets directory mounted for this service alone.
    assert service.binds[SECRETS] == DEPLOY / "secrets" / ROLE[name]
    mounts = {SECRETS: rendered_secrets / ROLE[name]}
    settings = daemon_settings(service.command, {}, mounts)
    assert settings.run == "exp7" and settings.zenoh_config == rendered_secrets / ROLE[name] / "zenoh.json5"
    # What it writes goes to the run volume.
    written = getattr(settings, WRITES_TO[ROLE[name]])
    assert service.volumes.get("/srv/l2r/run") == "run" and str(written).startswith("/srv/l2r/run")
    check = healthcheck_args(service.healthcheck, {}, mounts)
    assert (check.run, check.role, Path(check.zenoh_config)) == ("exp7", ROLE[name], settings.zenoh_config)


def test_actor_replicas_ask_replay_shard_0_for_ids_of_their_own(rendered_secrets):
    """--scale actor=N runs one command N times: each replica asks replay shard 0 for its id, which
    never gives one twice (tests/replay/test_actor_ids.py) when it keeps a snapshot directory."""
    services = compose.services({})
    actor = daemon_settings(services["actor"].command, {}, {SECRETS: rendered_secrets / "actor"})
    replay = daemon_settings(services["replay"].command, {}, {SECRETS: rendered_secrets / "replay"})
    assert actor.actor_id == "auto" and replay.shard == 0 and replay.snapshot_dir is not None


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
