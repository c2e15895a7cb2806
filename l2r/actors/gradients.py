"""A3C's side of an actor: each finished rollout's gradient goes to the learner instead of the rollout.

The rollouts are the actor's experience chunks (`--chunk-size` steps of one environment, A2C's
n_steps); the stepping loop swaps weights in only between them, so each chunk was acted by one
policy version, the one whose weights `send` is given. The gradient is A2C's loss's at those
weights (`l2r.learner.a3c`). Chunks acted at random (warm-up, no weights yet) and weights that do
not carry A3C's value network are not the learner's algorithm: such chunks are dropped and counted.
"""

from __future__ import annotations

import logging

import zenoh

from l2r.learner import a3c
from l2r.protocol import GRADIENT_QOS, ExperienceChunk, Gradient, Keys, ProtocolError, Rejections, Weights, encode

log = logging.getLogger("l2r.actor.gradients")


class GradientSender:
    """Computes and publishes the gradient of each rollout at the weights that acted it."""

    def __init__(self, session: zenoh.Session, keys: Keys, actor_id: int):
        self.actor_id = actor_id
        self._publisher = session.declare_publisher(keys.gradients(actor_id), **GRADIENT_QOS.publisher())
        self._weights: Weights | None = None  # the weights the replica below was built from
        self._replica: tuple[a3c.Replica, a3c.A3CConfig] | None = None
        self.rejections = Rejections(log)
        self.sent = 0
        self.bytes_sent = 0
        self.dropped = 0
        """Rollouts without a gradient: acted at random, or under weights without A3C's value network."""

    def send(self, chunk: ExperienceChunk, weights: Weights | None) -> None:
        """Publish the gradient of `chunk`, acted by the policy of `weights` (None: at random)."""
        replica = weights and self._replica_for(weights)
        if replica is None:
            self.dropped += 1
            return
        networks, config = replica
        a3c.load_weights(networks, weights)  # afresh: the last gradient moved the statistics
        gradient, moments = a3c.gradient(networks, a3c.batch_from_chunk(chunk), config)
        payload = encode(Gradient(self.actor_id, weights.version, chunk.size, gradient, moments))
        self._publisher.put(payload)
        self.sent += 1
        self.bytes_sent += len(payload)

    def _replica_for(self, weights: Weights) -> tuple[a3c.Replica, a3c.A3CConfig] | None:
        if weights is not self._weights:
            self._weights = weights
            try:
                self._replica = a3c.replica_of(weights)
            except (ValueError, TypeError) as e:  # not an A3C learner's weights, or settings it cannot take
                self._replica = None
                self.rejections.add(ProtocolError(f"weights v{weights.version}: {e}", "not_a3c"), "weights")
        return self._replica

    def counters(self) -> dict[str, int]:
        """For the actor's stats."""
        return {"gradients_sent": self.sent, "gradient_bytes_sent": self.bytes_sent,
                "rollouts_without_gradient": self.dropped, "rejected_a3c_weights": self.rejections.total}

    def close(self) -> None:
        self._publisher.undeclare()
