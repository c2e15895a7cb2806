"""Fixtures of the deployment tests."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from .daemons import SECRETS
from .zenoh_helpers import make_secrets


@pytest.fixture(scope="session")
def rendered_secrets(tmp_path_factory) -> Path:
    """deploy/make-secrets.sh's output for containers (configs pointing at /srv/l2r/secrets):
    ``rendered_secrets / role`` stands in for what a container of that role mounts there."""
    if not shutil.which("openssl"):
        pytest.skip("needs the openssl CLI (deploy/make-secrets.sh)")
    return make_secrets(tmp_path_factory.mktemp("rendered") / "secrets", mounted_at=SECRETS)
