"""Live frames for `l2r view --live`: what an actor publishes, and only while someone watches.

An actor creates one ``LiveFrames`` next to its Zenoh session and calls ``publish`` after each
step of each environment::

    live = LiveFrames(session, Keys(run), actor_id, rate_hz=10)
    ...
    live.publish(env_id, episode, step, obs, reward, info)   # returns at once when no viewer watches

Viewers hold a liveliness token under ``Keys(run).viewers``; while none exists ``publish`` is
one attribute check. With a viewer it sends at most ``rate_hz`` frames per second per
environment: body poses, activations, reward and distance, and the observation's camera frames
(its uint8[3, H, W] fields, raw), best effort at background priority (``FRAMES_QOS``), so a
viewer never slows training down.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np
import zenoh

from l2r.episodes.schema import image_fields
from l2r.protocol.keys import FRAMES_QOS, Keys
from l2r.protocol.messages import Frame, encode

FRAME_ARRAYS = ("body_pos", "body_quat", "muscle_activation")  # from the env's info


def frame(actor_id: int, env_id: int, episode: int, step: int, observation: dict[str, np.ndarray], reward: float,
          info: dict[str, Any]) -> Frame:
    """The frame of one step: the env's poses and activations, the reward and the distance (of a
    task that has one), and the camera frames of the observation after the step (its fields)."""
    arrays = {name: np.asarray(info[name], dtype=np.float32) for name in FRAME_ARRAYS if name in info}
    values = {"reward": float(reward)} | ({"distance": float(info["distance"])} if "distance" in info else {})
    # Raw, not PNG: at 10 frames a second the bytes cost less than the encoding (docs/episodes.md).
    images = {name: image[None] for name, image in image_fields(observation).items()} or None
    return Frame(actor_id, env_id, episode, step, arrays, values, images)


class LiveFrames:
    """Publishes an actor's frames while a viewer's liveliness token exists."""

    def __init__(self, session: zenoh.Session, keys: Keys, actor_id: int, rate_hz: float = 10.0):
        self.keys, self.actor_id = keys, int(actor_id)
        self.period = 1.0 / rate_hz
        self.watched = False
        self.sent = 0
        self._session = session
        self._viewers: set[str] = set()
        self._lock = threading.Lock()
        self._publishers: dict[int, zenoh.Publisher] = {}
        self._last: dict[int, float] = {}
        self._sub = session.liveliness().declare_subscriber(keys.viewers, self._on_token, history=True)

    def _on_token(self, sample: zenoh.Sample) -> None:
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._viewers.add(str(sample.key_expr))
            else:
                self._viewers.discard(str(sample.key_expr))
            self.watched = bool(self._viewers)

    def publish(self, env_id: int, episode: int, step: int, observation: dict[str, np.ndarray], reward: float,
                info: dict[str, Any]) -> bool:
        """Send this step's frame if a viewer watches and the rate allows; whether it was sent."""
        if not self.watched:
            return False
        now = time.monotonic()
        if now - self._last.get(env_id, -np.inf) < self.period:
            return False
        self._last[env_id] = now
        publisher = self._publishers.get(env_id)
        if publisher is None:
            publisher = self._session.declare_publisher(self.keys.frames(self.actor_id, env_id), **FRAMES_QOS.publisher())
            self._publishers[env_id] = publisher
        publisher.put(encode(frame(self.actor_id, env_id, episode, step, observation, reward, info)))
        self.sent += 1
        return True

    def close(self) -> None:
        self._sub.undeclare()
        for publisher in self._publishers.values():
            publisher.undeclare()
