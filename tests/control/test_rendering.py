"""Choosing the OpenGL backend: a user's MUJOCO_GL kept, EGL probed, OSMesa where EGL fails."""

import ctypes.util
import json
import os
import subprocess
import sys

import pytest

from l2r.control import rendering
from tests.conftest import ROOT

# libglvnd loads the EGL drivers this file lists: none, so no EGL device can be opened.
NO_EGL_DRIVER = {"__EGL_VENDOR_LIBRARY_FILENAMES": "/nonexistent/egl_vendor.json"}


def test_a_mujoco_gl_the_user_set_is_kept(monkeypatch):
    monkeypatch.setenv("MUJOCO_GL", "osmesa")
    monkeypatch.setattr(rendering, "egl_failure", lambda: pytest.fail("probed EGL although MUJOCO_GL was set"))
    assert rendering.choose_backend() == "osmesa"
    assert os.environ["MUJOCO_GL"] == "osmesa"


@pytest.mark.skipif(not ctypes.util.find_library("EGL"), reason="no libEGL on this machine")
def test_egl_works_here_and_a_failure_says_why(monkeypatch):
    assert rendering.egl_failure() is None
    for name, value in NO_EGL_DRIVER.items():
        monkeypatch.setenv(name, value)
    assert "EGL" in rendering.egl_failure()


@pytest.mark.skipif(not ctypes.util.find_library("OSMesa"), reason="no libOSMesa (apt-get install libosmesa6)")
def test_without_egl_the_env_renders_with_osmesa_and_exits_cleanly():
    script = (
        "import json, os, l2r.control.env as e\n"
        "env = e.ControlEnv('cartpole', 'swingup')\n"
        "obs, _ = env.reset(seed=0)\n"
        "print(json.dumps({'report': env.gl, 'std': float(obs['pixels'].std()), 'gl': os.environ['MUJOCO_GL']}))\n"
    )  # and no env.close(): the process must still exit cleanly
    chosen_here = ("MUJOCO_GL", "PYOPENGL_PLATFORM", "DISABLE_RENDER_THREAD_OFFLOADING")
    env = {k: v for k, v in os.environ.items() if k not in chosen_here}
    child = subprocess.run(
        [sys.executable, "-c", script], env={**env, **NO_EGL_DRIVER, "PYTHONPATH": str(ROOT)},
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )
    assert child.returncode == 0, child.stderr
    assert "EGL cannot render here" in child.stderr, "the fallback is not logged with its reason"
    assert "Traceback" not in child.stderr, child.stderr
    result = json.loads(child.stdout.strip().splitlines()[-1])
    assert result["gl"] == "osmesa" and result["report"][0] == "osmesa"
    assert result["std"] > 10
