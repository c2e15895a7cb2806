"""A small camera task for actor tests: the suite's cartpole seen in 16 × 16 frames (a render
costs a fraction of an 84 × 84 one), its episodes cut at 6 steps so that a few seconds see resets."""

import ctypes.util
import signal
import subprocess

import gymnasium
import zenoh

from l2r.protocol import session_config
from tests.conftest import free_port
from tests.replay.conftest import Replay

CAMERA = "tests.actors.camera:SmallCamera-v0"
IMAGE_SIZE = 16
EPISODE_STEPS = 6
RENDERER = bool(ctypes.util.find_library("EGL") or ctypes.util.find_library("OSMesa"))
"""Whether this machine has an OpenGL the control tasks can render with (tests skip without)."""

gymnasium.register("SmallCamera-v0", entry_point="l2r.control.env:ControlEnv", max_episode_steps=EPISODE_STEPS,
                   kwargs={"domain": "cartpole", "task": "swingup", "image_size": IMAGE_SIZE})


def camera_shard(run: str, tmp_path) -> tuple[Replay, zenoh.Session]:
    """A real replay shard of the small camera task's frames, and a session connected to it."""
    replay = Replay(run, f"tcp/127.0.0.1:{free_port()}", tmp_path / "replay.log",
                    ["--observation", f"pixels: uint8[3, {IMAGE_SIZE}, {IMAGE_SIZE}]", "--act-dim", "1"])
    return replay, zenoh.open(session_config(connect=[replay.endpoint]))


def stop_all(actor: subprocess.Popen | None, subscribers, session, replay) -> str | None:
    """The end of a test of a real actor: the actor stopped as l2r up stops it (SIGTERM), then the
    test's subscribers, session and replay shard; the actor's output (None if it never started)."""
    out = None
    if actor is not None:
        actor.send_signal(signal.SIGTERM)
        out, _ = actor.communicate(timeout=30)
    for subscriber in subscribers:
        subscriber.undeclare()
    session.close()
    replay.stop()
    return out
