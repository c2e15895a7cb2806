"""What tests in every directory share: the repository root, a free loopback port, waiting for a
condition, and a small file system of their own to fill."""

from __future__ import annotations

import errno
import os
import socket
import subprocess
import time
from pathlib import Path
from typing import Callable, TypeVar

import pytest

T = TypeVar("T")

ROOT = Path(__file__).resolve().parents[1]


# Ports below the kernel's ephemeral range (32768 up on Linux), a block for each xdist worker: a
# port the kernel picked (bind to 0) could be picked again for the other worker, or for any
# connection, between the draw and the daemon's bind ("Address already in use"); these it hands to
# no one, and the workers' blocks do not overlap.
_WORKER = int(os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw"))
_BLOCK = (32768 - 16384) // int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))
_PORTS = iter(range(16384 + _WORKER * _BLOCK, 16384 + (_WORKER + 1) * _BLOCK))


def free_port() -> int:
    """A TCP port free on 127.0.0.1, drawn once a session from this worker's own block (a port
    an earlier test's daemon held may still be closing)."""
    for port in _PORTS:
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port
    raise RuntimeError(f"test worker {_WORKER} has used up its {_BLOCK} ports")


PROCESS_START_S = 60.0
"""How long a test waits for a daemon process it has just started to do its first thing: the
imports alone (torch, Zenoh, MuJoCo) take tens of seconds on a loaded 2-core machine."""


def wait_for(predicate: Callable[[], T], timeout: float = 15.0, interval: float = 0.05) -> T:
    """Poll ``predicate`` until it returns something true or ``timeout`` seconds pass; return its
    last value, so callers write ``assert wait_for(...), "what never happened"``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    return predicate()


class SmallDisk:
    """A tmpfs of a few MB mounted for one test (CI runs as root), and ballast to fill it with."""

    def __init__(self, path: Path):
        self.path = path
        self.ballast = path / "ballast"

    def fill(self, leave: int = 0) -> None:
        """Write ballast until the file system is full (tmpfs: every later write gets ENOSPC), or
        until only `leave` bytes are free (a whole number of 4 KB pages)."""
        block = b"\0" * (1 << 16)
        with open(self.ballast, "ab", buffering=0) as f:
            try:
                while f.write(block):
                    pass
            except OSError as e:
                if e.errno != errno.ENOSPC:
                    raise
            if leave:
                f.truncate(f.tell() - leave)

    def free(self) -> None:
        self.ballast.unlink()


@pytest.fixture
def small_disk(tmp_path, request):
    """``small_disk(mb)``: a SmallDisk of ``mb`` MB under tmp_path, unmounted after the test;
    the test is skipped where mounting is not permitted (not root, a container without the
    capability)."""
    mounted: list[Path] = []

    def mount(mb: int) -> SmallDisk:
        path = tmp_path / f"disk{len(mounted)}"
        path.mkdir()
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={mb}m", "tmpfs", str(path)],
                              capture_output=True, text=True)
        if done.returncode:
            pytest.skip(f"cannot mount a tmpfs here ({done.stderr.strip() or done.returncode}): a full disk "
                        "is tested as root")
        mounted.append(path)
        return SmallDisk(path)

    yield mount
    for path in mounted:
        subprocess.run(["umount", "-l", str(path)], check=False)
