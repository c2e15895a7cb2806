"""Separate hosts on one Linux machine: network namespaces on a bridge, one mount namespace each.

Every host gets its own network namespace with one interface, ``eth0``, plugged into a bridge
that lives in a namespace of its own, so nothing is added to the machine's own network. Each
process also gets a private mount namespace (the container paths of deploy/docker-compose.yml
bind-mounted from per-host directories, a hosts file naming the router) and its own hostname,
so it sees what it would see in its container and shares nothing with other hosts but the network.
Needs root.
"""

from __future__ import annotations

import os
import secrets
import shlex
import subprocess
from pathlib import Path


def ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=30)


def namespaces_available() -> str | None:
    """None if this process can make network namespaces, else why not."""
    if os.geteuid() != 0:
        return "network namespaces need root"
    probe = f"l2rprobe{secrets.token_hex(3)}"
    try:
        ip("netns", "add", probe)
        ip("netns", "del", probe)
    except (OSError, subprocess.CalledProcessError) as e:
        return f"cannot create a network namespace here: {getattr(e, 'stderr', b'') or e}"
    return None


class Hosts:
    """A bridge and named hosts on ``subnet``.0/24; use as a context manager so it always goes away."""

    def __init__(self, subnet: str = "10.47.0"):
        self.prefix = f"l2r{secrets.token_hex(2)}"
        self.subnet = subnet
        self.switch = f"{self.prefix}-sw"
        self.addresses: dict[str, str] = {}
        self.processes: list[subprocess.Popen] = []
        self._made: list[str] = []

    def __enter__(self) -> Hosts:
        ip("netns", "add", self.switch)
        self._made.append(self.switch)
        ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
        ip("-n", self.switch, "link", "set", "br0", "up")
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def ns(self, host: str) -> str:
        return f"{self.prefix}-{host}"

    @staticmethod
    def port(host: str) -> str:
        """The switch's end of ``host``'s cable."""
        return f"port-{host}"

    def add(self, host: str) -> str:
        """Add a host; returns its address."""
        ns = self.ns(host)
        ip("netns", "add", ns)
        self._made.append(ns)
        address = f"{self.subnet}.{len(self.addresses) + 1}"
        # The veth pair is made inside the switch namespace with its far end in the host's.
        ip("-n", self.switch, "link", "add", self.port(host), "type", "veth", "peer", "name", "eth0", "netns", ns)
        ip("-n", self.switch, "link", "set", self.port(host), "master", "br0", "up")
        ip("-n", ns, "addr", "add", f"{address}/24", "dev", "eth0")
        ip("-n", ns, "link", "set", "eth0", "up")
        ip("-n", ns, "link", "set", "lo", "up")
        self.addresses[host] = address
        return address

    def link(self, host: str, up: bool) -> None:
        """Plug or unplug ``host``'s cable at the switch."""
        ip("-n", self.switch, "link", "set", self.port(host), "up" if up else "down")

    def hosts_file(self, path: Path, names: dict[str, str]) -> Path:
        """An /etc/hosts for the hosts: ``names`` maps a DNS name to a host."""
        lines = ["127.0.0.1 localhost"] + [f"{self.addresses[h]} {name}" for name, h in names.items()]
        path.write_text("\n".join(lines) + "\n")
        return path

    def command(self, host: str, cmd: list[str], mounts: dict[str, Path], hostname: str, hosts_file: Path) -> list[str]:
        """``cmd`` run on ``host``: its network, its hostname, ``mounts`` (container path -> host path)."""
        # A private /dev/shm too: Zenoh hands payloads over in shared memory when both ends see the
        # same one, which would bypass the network between these hosts (containers have their own).
        setup = [f"hostname {shlex.quote(hostname)}", "mount -t tmpfs l2r /srv", "mount -t tmpfs shm /dev/shm",
                 f"mount --bind {shlex.quote(str(hosts_file))} /etc/hosts"]
        for target, source in mounts.items():
            if not target.startswith("/srv/"):
                raise ValueError(f"container path {target} is outside /srv")
            setup += [f"mkdir -p {shlex.quote(target)}", f"mount --bind {shlex.quote(str(source))} {shlex.quote(target)}"]
        script = " && ".join(setup) + ' && exec "$@"'
        return ["ip", "netns", "exec", self.ns(host), "unshare", "--mount", "--uts", "--propagation", "private",
                "sh", "-c", script, "sh", *cmd]

    def spawn(self, host: str, cmd: list[str], log: Path, **kwargs) -> subprocess.Popen:
        """Start a process on ``host`` (see ``command``), its output in ``log``; stopped by close()."""
        env = kwargs.pop("env", None)
        with open(log, "ab") as out:
            proc = subprocess.Popen(self.command(host, cmd, **kwargs), stdout=out, stderr=subprocess.STDOUT, env=env)
        self.processes.append(proc)
        return proc

    def run(self, host: str, cmd: list[str], timeout: float = 30, **kwargs) -> subprocess.CompletedProcess:
        env = kwargs.pop("env", None)
        return subprocess.run(self.command(host, cmd, **kwargs), capture_output=True, text=True, timeout=timeout, env=env)

    def close(self, grace_s: float = 15.0) -> None:
        for proc in self.processes:
            if proc.poll() is None:
                proc.terminate()
        for proc in self.processes:
            try:
                proc.wait(grace_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        self.processes.clear()
        for ns in reversed(self._made):
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=30)
        self._made.clear()
