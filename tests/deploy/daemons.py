"""What a deployment file starts, read by the daemons' own code: a command line and an environment
in, the settings the daemon would run with out. The compose and Kubernetes tests share it."""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import os
from pathlib import Path
from unittest import mock

from l2r.protocol import DaemonSettings

from .zenoh_helpers import DEPLOY

MODULES = {"l2r-replay": "l2r.replay", "l2r-learner": "l2r.learner", "l2r-actor": "l2r.actors"}
"""console script -> the package whose __main__ it runs"""
WRITES_TO = {"replay": "snapshot_dir", "learner": "run_dir", "actor": "episode_log_dir"}
"""role -> the setting naming the directory its daemon writes (snapshots, checkpoints, episode logs)"""
HEALTHCHECK = ["python", "/opt/l2r/deploy/healthcheck.py"]
"""how the images run deploy/healthcheck.py (deploy/Dockerfile installs it there)"""
SECRETS = "/srv/l2r/secrets"
"""where every container sees its role's keys and Zenoh config (deploy/make-secrets.sh's default)"""

Mounts = dict[str, Path]
"""a directory in the container -> the directory on this host that stands in for it"""


def daemon_settings(argv: list[str], environ: dict[str, str], mounts: Mounts) -> DaemonSettings:
    """The settings of daemon ``argv[0]`` (a console script) started with the rest of ``argv`` in an
    environment of ``environ`` alone, as its own parser and settings loader read them; paths under
    ``mounts`` are read from their stand-ins here (the loader reads the Zenoh config file)."""
    main = importlib.import_module(f"{MODULES[argv[0]]}.__main__")
    with mock.patch.dict(os.environ, environ, clear=True):
        return main.parse_settings(on_host(argv[1:], mounts))


def healthcheck_args(command: list[str], environ: dict[str, str], mounts: Mounts) -> argparse.Namespace:
    """The arguments deploy/healthcheck.py reads from ``command`` (as the images run it) and ``environ``."""
    assert command[:len(HEALTHCHECK)] == HEALTHCHECK, command
    spec = importlib.util.spec_from_file_location("healthcheck", DEPLOY / "healthcheck.py")
    healthcheck = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(healthcheck)
    return healthcheck.build_parser(environ).parse_args(on_host(command[len(HEALTHCHECK):], mounts))


def on_host(argv: list[str], mounts: Mounts) -> list[str]:
    """``argv`` with every path under a mounted directory replaced by its path on this host."""
    def place(arg: str) -> str:
        for inside, outside in mounts.items():
            if arg == inside or arg.startswith(inside.rstrip("/") + "/"):
                return str(outside) + arg[len(inside.rstrip("/")):]
        return arg
    return [place(arg) for arg in argv]
