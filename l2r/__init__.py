"""l2r: distributed actor/learner reinforcement learning over Eclipse Zenoh."""

import importlib.metadata
import tomllib
from pathlib import Path


def _version() -> str:
    """The installed distribution's version; from a source tree that was never installed (on the
    path by PYTHONPATH), its pyproject.toml's, so that the package imports all the same."""
    try:
        return importlib.metadata.version("l2r")
    except importlib.metadata.PackageNotFoundError:
        try:
            with open(Path(__file__).resolve().parent.parent / "pyproject.toml", "rb") as f:
                return tomllib.load(f)["project"]["version"]
        except (OSError, KeyError, tomllib.TOMLDecodeError):
            return "unknown"


__version__ = _version()
