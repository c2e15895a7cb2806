"""Loopback Zenoh for protocol tests: explicit endpoints, no scouting, a fresh run name."""

from __future__ import annotations

import uuid

import pytest

from tests.conftest import free_port


@pytest.fixture
def endpoint() -> str:
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def run_name() -> str:
    return f"test-{uuid.uuid4().hex[:10]}"
