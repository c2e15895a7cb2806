"""Three hosts on one machine (network namespaces): A runs the router, B the replay server and a
learner, C the actors. Each process runs its docker-compose service's command with its role's
rendered Zenoh config (mutual TLS, passwords, the router's access control), mounted where the
container would see it; the hosts share nothing but the network.
"""

from __future__ import annotations

import json
import os
import sys
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

import pytest

from . import compose
from .netns import Hosts, namespaces_available
from .zenoh_helpers import DEPLOY, make_secrets, wait_for

PROBE = Path(__file__).with_name("probe.py")
SECRETS_IN_CONTAINER = "/srv/l2r/secrets"
IMAGE_ROOT = "/opt/l2r"  # where the image installs the checkout (deploy/Dockerfile)


@dataclass
class Cluster:
    hosts: Hosts
    secrets: Path
    hosts_file: Path
    tmp: Path
    run: str

    @property
    def env(self) -> dict[str, str]:
        # The image's console scripts are this interpreter's; the role keys live in tmp, not deploy/.
        return {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}", "L2R_RUN": self.run}

    def service(self, name: str) -> compose.Service:
        return compose.services({"L2R_RUN": self.run})[name]

    def mounts(self, service: compose.Service, host: str) -> dict[str, Path]:
        """Compose's mounts for ``service`` on ``host``: secrets from tmp, the run volume per host."""
        mounts = {}
        for target, source in service.binds.items():
            mounts[target] = self.secrets / source.relative_to(DEPLOY / "secrets")
        for target, volume in service.volumes.items():
            mounts[target] = self.tmp / host / volume
            mounts[target].mkdir(parents=True, exist_ok=True)
        return mounts

    def start(self, name: str, host: str, extra: tuple[str, ...] = (), hostname: str | None = None):
        """Start compose service ``name`` on ``host`` and wait until its own health check passes."""
        service = self.service(name)
        command = service.command + list(extra)
        if name == "router":  # the image's entrypoint is zenohd; here its stand-in takes the same flags
            command = [sys.executable, "-m", "l2r.cli", "router", *command]
        hostname = hostname or f"{name}-{uuid.uuid4().hex[:6]}"
        log = self.tmp / f"{hostname}.log"
        proc = self.hosts.spawn(host, command, log, mounts=self.mounts(service, host), hostname=hostname,
                                hosts_file=self.hosts_file, env=self.env)
        return proc, log

    def healthy(self, name: str, host: str) -> bool:
        service = self.service(name)
        check = [sys.executable if c == "python" else c.replace(IMAGE_ROOT, str(DEPLOY.parent))
                 for c in service.healthcheck]
        result = self.hosts.run(host, check, mounts=self.mounts(service, host), hostname="healthcheck",
                                hosts_file=self.hosts_file, env=self.env)
        return result.returncode == 0

    def probe(self, host: str, role: str, *args: str, log_name: str):
        """Run tests/deploy/probe.py on ``host`` with ``role``'s credentials."""
        mounts = {SECRETS_IN_CONTAINER: self.secrets / role}
        cmd = [sys.executable, str(PROBE), *args, "--zenoh-config", f"{SECRETS_IN_CONTAINER}/zenoh.json5"]
        return self.hosts.spawn(host, cmd, self.tmp / f"{log_name}.log", mounts=mounts, hostname=log_name,
                                hosts_file=self.hosts_file, env=self.env)


@pytest.fixture
def cluster(tmp_path):
    reason = namespaces_available()
    if reason:
        pytest.skip(reason)
    secrets = make_secrets(tmp_path / "secrets", mounted_at=SECRETS_IN_CONTAINER, names=("router",))
    with Hosts() as hosts:
        for host in ("a", "b", "c"):
            hosts.add(host)
        hosts_file = hosts.hosts_file(tmp_path / "hosts", {"router": "a"})
        yield Cluster(hosts, secrets, hosts_file, tmp_path, run=f"mh-{uuid.uuid4().hex[:8]}")


def read_lines(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


def test_hosts_talk_only_through_the_router(cluster):
    """Plain publications from C reach B through the router on A, over TLS with the role keys."""
    router, router_log = cluster.start("router", "a")
    assert wait_for(lambda: cluster.healthy("router", "a"), timeout=20), router_log.read_text()
    key = f"l2r/{cluster.run}/experience/0/1"
    out = cluster.tmp / "received.jsonl"
    cluster.probe("b", "replay", "sub", "--key", key, "--out", str(out), log_name="sub")
    assert wait_for(lambda: any(r.get("ready") for r in read_lines(out)), timeout=20)
    cluster.probe("c", "actor", "pub", "--key", key, "--count", "20", "--interval", "0.05", log_name="pub")
    assert wait_for(lambda: len(read_lines(out)) >= 21, timeout=20), (cluster.tmp / "pub.log").read_text()
    assert [r["i"] for r in read_lines(out)[1:]] == list(range(20))
    # The router saw C connect from C's own address, authenticated as an actor.
    assert wait_for(lambda: f"{cluster.hosts.addresses['c']}" in router_log.read_text())
    assert "as actor" in router_log.read_text()
