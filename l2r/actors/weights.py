"""Following the learner's policy: the newest weights arrive on a Zenoh thread and wait
there until the stepping loop swaps them in between two steps.

Weights come from three places: the published updates, a query for the latest weights on
join (repeated while none has arrived, or when the version beacon shows that a published
update was dropped), and nothing else. A malformed message, weights that do not fit the
network, or a policy built for other observations than the environment's are logged and
counted, never raised.
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np
import zenoh

from l2r.actors.frame_stack import frame_stack_of
from l2r.policy import PolicyNetwork, build_policy, check_spec, load_policy_state
from l2r.protocol import (
    WEIGHTS_QOS, Keys, LearnerVersion, ObservationSpec, ProtocolError, Rejections, Weights, decode,
)

log = logging.getLogger("l2r.actor.weights")


class WeightFollower:
    """Keeps the newest `Weights` seen and turns them into a policy on request."""

    def __init__(self, session: zenoh.Session, keys: Keys, observation: ObservationSpec, device: str = "cpu",
                 query_every: float = 2.0):
        self._session = session
        self.device = device  # where the policy is built and acts
        self.observation = observation  # the environment's: weights of a policy for others are refused
        self._keys = keys
        self._query_every = query_every
        self._lock = threading.Lock()
        self._pending: Weights | None = None
        self._last_query = 0.0
        self.rejections = Rejections(log)
        self.version = -1  # version of the policy in use; -1 before any
        self.newest_seen = -1  # newest version announced by weights or the learner's beacon
        self.swaps = 0
        self.policy: PolicyNetwork | None = None
        self.in_use: Weights | None = None  # the message of the policy in use (A3C's actors differentiate it)
        self.frame_stack = 1  # observations stacked into one input of the policy in use
        self._subscriber = session.declare_subscriber(keys.weights, self._on_weights)
        self._beacon = session.declare_subscriber(keys.learner_version, self._on_beacon)

    @property
    def staleness(self) -> int:
        """How many versions the policy in use trails the newest one seen (0 before any)."""
        return max(0, self.newest_seen - self.version) if self.version >= 0 else 0

    def _on_weights(self, sample: zenoh.Sample) -> None:
        self._offer(sample.payload, str(sample.key_expr))

    def _on_reply(self, reply: zenoh.Reply) -> None:
        if reply.ok is not None:
            self._offer(reply.ok.payload, str(reply.ok.key_expr))

    def _offer(self, payload, source: str) -> None:
        try:
            weights = decode(payload, Weights)
            check_spec(weights.spec)
            self.check_observation(weights.spec)
        except ProtocolError as e:
            self.rejections.add(e, source)
            return
        except ValueError as e:
            self.rejections.add(ProtocolError(f"weights: {e}", "bad_spec"), source)
            return
        with self._lock:
            self.newest_seen = max(self.newest_seen, weights.version)
            if weights.version > self.version and (self._pending is None or weights.version > self._pending.version):
                self._pending = weights

    def check_observation(self, spec: dict) -> None:
        """Raise ProtocolError (``bad_spec``) unless a policy of ``spec`` takes the environment's
        observations, in stacks of a depth the replay can build."""
        observation = ObservationSpec.from_policy_spec(spec)
        if observation != self.observation:
            raise ProtocolError(f"weights: the policy takes {observation}, the environment gives {self.observation}",
                                "bad_spec")
        frame_stack_of(spec)

    def _on_beacon(self, sample: zenoh.Sample) -> None:
        try:
            beacon = decode(sample.payload, LearnerVersion)
        except ProtocolError as e:
            self.rejections.add(e, str(sample.key_expr))
            return
        with self._lock:
            self.newest_seen = max(self.newest_seen, beacon.version)

    def query(self) -> None:
        """Ask the learner for its latest weights; the reply arrives like a published update."""
        self._last_query = time.monotonic()
        self._session.get(self._keys.weights_query, self._on_reply, timeout=5.0, **WEIGHTS_QOS.put())

    def poll(self) -> bool:
        """Swap in pending weights, if any (call between steps). True if the policy changed.

        Also re-queries when no weights came yet, or when the beacon shows a newer version
        than any weights that arrived (a dropped update)."""
        with self._lock:
            weights, self._pending = self._pending, None
            behind = self.newest_seen > self.version
        if weights is None:
            if (self.version < 0 or behind) and time.monotonic() - self._last_query > self._query_every:
                self.query()
            return False
        try:
            policy = self.policy
            if policy is None or policy.spec != check_spec(weights.spec):
                policy = build_policy(weights.spec).to(self.device)
                policy.eval()
            # Decoded arrays are read-only views of the message; torch wants writable ones.
            load_policy_state(policy, {k: np.array(v) for k, v in weights.params.items()})
        except ValueError as e:
            self.rejections.add(ProtocolError(f"weights v{weights.version} do not fit: {e}", "bad_spec"),
                                self._keys.weights)
            return False
        first = self.policy is None
        self.policy, self.version, self.in_use = policy, weights.version, weights
        self.frame_stack = frame_stack_of(weights.spec)
        self.swaps += 1
        log.log(logging.INFO if first else logging.DEBUG, "policy version %d in use", weights.version)
        return True

    def close(self) -> None:
        self._subscriber.undeclare()
        self._beacon.undeclare()

