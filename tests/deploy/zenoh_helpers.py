"""What the deployment tests share: the repository's deploy/ files, rendered keys, a router process."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import zenoh

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


def make_secrets(out: Path, mounted_at: str | None = None, names: tuple[str, ...] = ()) -> Path:
    """Run deploy/make-secrets.sh into ``out``; configs point at ``out/<role>`` unless told otherwise."""
    cmd = ["bash", str(DEPLOY / "make-secrets.sh"), "-o", str(out), "-m", mounted_at or f"{out}/{{role}}", "-d", "2"]
    for name in names:
        cmd += ["-n", name]
    subprocess.run(cmd, check=True, capture_output=True, timeout=60)
    return out


def role_config(secrets: Path, role: str, endpoint: str, timeout_ms: int = 3000, **overrides) -> zenoh.Config:
    """``role``'s rendered Zenoh config, connecting to ``endpoint`` and failing after ``timeout_ms``.

    ``overrides`` are Zenoh config keys with ``__`` for ``/``.
    """
    conf = zenoh.Config.from_file(str(secrets / role / "zenoh.json5"))
    conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    conf.insert_json5("connect/timeout_ms", str(timeout_ms))
    for key, value in overrides.items():
        conf.insert_json5(key.replace("__", "/"), json.dumps(value))
    return conf


def start_router(args: list[str], log_path: Path, ready_timeout: float = 20.0) -> subprocess.Popen:
    """Start ``l2r router ARGS`` and return the process once it logs that it is ready."""
    log = open(log_path, "w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "l2r.cli", "router", *args],
        stdout=log, stderr=subprocess.STDOUT, cwd=DEPLOY.parent,
    )
    deadline = time.monotonic() + ready_timeout
    while time.monotonic() < deadline:
        if "ready" in log_path.read_text():
            return proc
        if proc.poll() is not None:
            break
        time.sleep(0.05)
    stop(proc)
    raise RuntimeError(f"router did not start:\n{log_path.read_text()}")


def stop(proc: subprocess.Popen, timeout: float = 10.0) -> int:
    if proc.poll() is None:
        proc.terminate()
        try:
            return proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
    return proc.wait()
