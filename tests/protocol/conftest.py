"""Loopback Zenoh for protocol tests: explicit endpoints, no scouting, a fresh run name."""

from __future__ import annotations

import socket
import uuid

import pytest


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture
def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def run_name() -> str:
    return f"test-{uuid.uuid4().hex[:10]}"
