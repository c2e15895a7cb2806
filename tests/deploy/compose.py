"""deploy/docker-compose.yml read the way Docker Compose reads it: services, commands, mounts.

The multi-host test runs what this returns, so the compose file stays the one description of
how each daemon is started.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from ruamel.yaml import YAML

COMPOSE_FILE = Path(__file__).resolve().parents[2] / "deploy" / "docker-compose.yml"
_VARIABLE = re.compile(r"\$\$|\$\{(\w+)(?::-([^}]*))?\}")


def seconds(duration: str) -> float:
    """A Compose duration such as ``1m30s`` in seconds."""
    units = {"h": 3600, "m": 60, "s": 1, "ms": 1e-3}
    parts = re.findall(r"(\d+(?:\.\d+)?)(ms|h|m|s)", duration)
    assert parts, f"not a duration: {duration}"
    return sum(float(n) * units[u] for n, u in parts)


def load(path: Path = COMPOSE_FILE) -> dict:
    """The compose document as YAML data (merge keys resolved, variables not yet)."""
    return YAML(typ="safe").load(path.read_text())


def interpolate(value, env: dict[str, str]):
    """Compose's variable interpolation: ``${NAME}``, ``${NAME:-default}``, ``$$`` for ``$``."""
    if isinstance(value, str):
        return _VARIABLE.sub(lambda m: "$" if m.group(0) == "$$" else env.get(m.group(1)) or m.group(2) or "", value)
    if isinstance(value, list):
        return [interpolate(v, env) for v in value]
    if isinstance(value, dict):
        return {k: interpolate(v, env) for k, v in value.items()}
    return value


@dataclass
class Service:
    name: str
    command: list[str]
    binds: dict[str, Path]  # container path -> host path (bind mounts, relative to the compose file)
    volumes: dict[str, str]  # container path -> named volume
    healthcheck: list[str] | None  # the command, or None


def services(env: dict[str, str], path: Path = COMPOSE_FILE) -> dict[str, Service]:
    doc = interpolate(load(path), env)
    out = {}
    for name, spec in doc["services"].items():
        binds, volumes = {}, {}
        for mount in spec.get("volumes", []):
            source, target = mount.split(":")[:2]
            if source.startswith((".", "/")):
                binds[target] = (path.parent / source).resolve()
            else:
                volumes[target] = source
        test = spec.get("healthcheck", {}).get("test")
        if test and test[0] == "CMD-SHELL":
            test = ["sh", "-c", test[1]]
        elif test:
            test = test[1:]
        out[name] = Service(name, list(spec.get("command", [])), binds, volumes, test)
    return out
