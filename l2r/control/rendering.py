"""Which OpenGL the control tasks render with, chosen once per process and reported.

MuJoCo renders off screen through EGL (the GPU where there is one, Mesa's llvmpipe on a CPU)
or, failing that, OSMesa (Mesa's software rasteriser, no display or device needed). mujoco and
dm_control read the choice from MUJOCO_GL when they are imported, and PyOpenGL fixes its
platform at its own import, so `choose_backend` runs before any of them and a process cannot
switch later. A MUJOCO_GL the user set is kept as it is.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from typing import Any, NamedTuple

log = logging.getLogger(__name__)

EGL = "egl"
OSMESA = "osmesa"
PROBE_TIMEOUT_S = 60.0

# Makes a 1×1 EGL context the way mujoco does (through an EGL device, as dm_control does too).
EGL_PROBE = "import mujoco; context = mujoco.GLContext(1, 1); context.make_current(); context.free()"


class GLReport(NamedTuple):
    """What renders the frames: the backend (MUJOCO_GL) and OpenGL's own renderer and version."""

    backend: str
    renderer: str
    version: str


_report: GLReport | None = None


def choose_backend() -> str:
    """Set MUJOCO_GL for this process (and the processes it starts) unless it is set already,
    and return it: egl where an EGL context can be made here, osmesa otherwise."""
    if not os.environ.get("MUJOCO_GL"):
        failure = egl_failure()
        if failure:
            log.warning("EGL cannot render here (%s); rendering with OSMesa", failure)
        os.environ["MUJOCO_GL"] = OSMESA if failure else EGL
    # dm_control renders OSMesa frames on a thread of its own, which interpreter exit stops before
    # dm_control frees an unclosed env's context (tracebacks at exit); render on the stepping
    # thread instead, as it always does with EGL.
    os.environ.setdefault("DISABLE_RENDER_THREAD_OFFLOADING", "1")
    return os.environ["MUJOCO_GL"]


def egl_failure() -> str | None:
    """Why no EGL context can be made on this machine, or None when one can.

    Tried in a child process: once PyOpenGL has loaded EGL, this process could not fall back.
    """
    env = {**os.environ, "MUJOCO_GL": EGL}
    env.pop("PYOPENGL_PLATFORM", None)  # mujoco's EGL module sets it, and refuses another value
    try:
        probe = subprocess.run(
            [sys.executable, "-c", EGL_PROBE], env=env, capture_output=True, text=True, timeout=PROBE_TIMEOUT_S
        )
    except subprocess.TimeoutExpired:
        return f"no EGL context within {PROBE_TIMEOUT_S:.0f} s"
    if probe.returncode == 0:
        return None
    lines = probe.stderr.strip().splitlines()
    return lines[-1] if lines else f"the probe exited with code {probe.returncode}"


def gl_report(physics: Any) -> GLReport:
    """The backend and OpenGL renderer that `physics` (a dm_control Physics) renders with;
    logged the first time it is asked for in a process."""
    global _report
    if _report is None:
        from OpenGL import GL  # only now: dm_control has set PyOpenGL's platform by its import

        with physics.contexts.gl.make_current() as context:
            renderer, version = (context.call(GL.glGetString, name).decode() for name in (GL.GL_RENDERER, GL.GL_VERSION))
        _report = GLReport(os.environ["MUJOCO_GL"], renderer, version)
        log.info("Rendering with MUJOCO_GL=%s: %s, OpenGL %s", *_report)
    return _report
