"""Every key expression of an l2r run, with the QoS each one travels with.

Read top to bottom, this module is the system's data-flow graph:

    actor   --experience/<shard>/<actor>-->  replay shard      (chunks of transitions)
    learner --replay/<shard>/sample?-->      replay shard      (query; reply = batch)
    learner --replay/<shard>/priorities-->   replay shard      (priority updates)
    replay  --replay/<shard>/ack-->          actors            (what is stored; actors resend the rest)
    learner --weights-->                     actors            (new policy, versioned)
    actor   --gradients/<actor>-->           learner           (A3C: gradients instead of experience)
    actor   --weights/latest?-->             learner           (query on join)
    actor   --actor_ids?-->                  replay shard 0    (query at start, for --actor-id auto)
    learner --learner/version-->             everyone          (small version beacon)
    actor   --episodes/<actor>-->            launcher, viewers (episode summaries)
    evaluator --rounds/<actor>-->            launcher          (the version a round evaluates)
    actor   --frames/<actor>/<env>-->        viewer            (only while alive/viewer/* exists)
    anyone  --stats/<role>/<instance>-->     launcher, logs
    learner --metrics/<rank>-->              launcher, logs
    anyone  --alive/<role>/<id>              liveliness tokens

Every key starts with ``l2r/<run>/`` so two runs on one Zenoh network never mix.
"""

from __future__ import annotations

from dataclasses import dataclass

import zenoh

PREFIX = "l2r"
ROLES = ("actor", "learner", "replay", "viewer", "launcher", "evaluator")
_FORBIDDEN = set("/*$?#@ ")


def check_name(name: str, what: str = "run name") -> str:
    """Return ``name`` if it is usable as one key expression chunk, else raise ValueError."""
    if not name or _FORBIDDEN & set(name):
        raise ValueError(f"invalid {what} {name!r}: must be non-empty, without / * $ ? # @ or spaces")
    return name


@dataclass(frozen=True)
class QoS:
    """How one kind of traffic is sent: reliability, congestion control, priority, express."""

    congestion_control: zenoh.CongestionControl
    priority: zenoh.Priority
    express: bool = False
    reliable: bool = True

    def publisher(self) -> dict:
        """Keyword arguments for ``Session.declare_publisher``."""
        return {
            "congestion_control": self.congestion_control,
            "priority": self.priority,
            "express": self.express,
            "reliability": zenoh.Reliability.RELIABLE if self.reliable else zenoh.Reliability.BEST_EFFORT,
        }

    def put(self) -> dict:
        """Keyword arguments for ``Session.put`` and ``Session.get``."""
        return {"congestion_control": self.congestion_control, "priority": self.priority, "express": self.express}


# Experience is the training data: never dropped; a slow replay server slows actors down.
EXPERIENCE_QOS = QoS(zenoh.CongestionControl.BLOCK, zenoh.Priority.DATA)
# Acks are periodic and the next one says it all again; never hold the shard up for a slow actor.
ACK_QOS = QoS(zenoh.CongestionControl.DROP, zenoh.Priority.DATA_HIGH, express=True)
# A3C's gradients are its training data, as experience is: never dropped (a stale one is refused
# by the learner, not by the link).
GRADIENT_QOS = QoS(zenoh.CongestionControl.BLOCK, zenoh.Priority.DATA)
# Only the newest weights matter, so a congested link may drop one; a newer one follows.
WEIGHTS_QOS = QoS(zenoh.CongestionControl.DROP, zenoh.Priority.DATA_HIGH)
# Sample queries sit on the learner's critical path; replies inherit the query's QoS.
SAMPLE_QOS = QoS(zenoh.CongestionControl.BLOCK, zenoh.Priority.INTERACTIVE_HIGH)
# A lost priority update only leaves an old priority in place.
PRIORITY_QOS = QoS(zenoh.CongestionControl.DROP, zenoh.Priority.DATA_HIGH)
# Small and rare, and each one is a result a person wants to see.
EPISODE_QOS = QoS(zenoh.CongestionControl.BLOCK, zenoh.Priority.DATA_LOW)
# Small and rare, and it must reach the launcher while the launcher still holds the weights it
# names, which at hundreds of versions a second is tens of milliseconds: sent at once, as weights are.
ROUND_QOS = QoS(zenoh.CongestionControl.BLOCK, zenoh.Priority.DATA_HIGH, express=True)
# Version beacons, stats and metrics are periodic: the next one replaces a lost one.
VERSION_QOS = QoS(zenoh.CongestionControl.DROP, zenoh.Priority.INTERACTIVE_LOW, express=True)
STATS_QOS = QoS(zenoh.CongestionControl.DROP, zenoh.Priority.DATA_LOW, express=True)
# Live frames for a viewer: best effort, the lowest priority, never in training's way.
FRAMES_QOS = QoS(zenoh.CongestionControl.DROP, zenoh.Priority.BACKGROUND, express=True, reliable=False)


@dataclass(frozen=True)
class Keys:
    """Key expressions of one run. ``Keys("exp1").weights`` == ``"l2r/exp1/weights"``."""

    run: str

    def __post_init__(self) -> None:
        check_name(self.run)

    @property
    def root(self) -> str:
        return f"{PREFIX}/{self.run}"

    # -- experience: actor -> replay shard (EXPERIENCE_QOS) --------------------------------
    def experience(self, actor_id: int, num_shards: int = 1) -> str:
        """Where actor ``actor_id`` publishes its chunks: shard ``actor_id % num_shards``."""
        return f"{self.root}/experience/{shard_of(actor_id, num_shards)}/{actor_id}"

    def experience_of_shard(self, shard: int) -> str:
        """What replay shard ``shard`` subscribes to."""
        return f"{self.root}/experience/{shard}/*"

    # -- sampling: learner -> replay shard, query/reply (SAMPLE_QOS) -----------------------
    def sample(self, shard: int) -> str:
        return f"{self.root}/replay/{shard}/sample"

    # -- priority updates: learner -> replay shard (PRIORITY_QOS) --------------------------
    def priorities(self, shard: int) -> str:
        return f"{self.root}/replay/{shard}/priorities"

    # -- acknowledgements: replay shard -> its actors (ACK_QOS) ------------------------------
    def replay_ack(self, shard: int) -> str:
        return f"{self.root}/replay/{shard}/ack"

    # -- weights: learner -> actors, published (WEIGHTS_QOS) and queryable on join ----------
    @property
    def weights(self) -> str:
        return f"{self.root}/weights"

    @property
    def weights_query(self) -> str:
        return f"{self.root}/weights/latest"

    # -- gradients: actor -> learner, A3C alone (GRADIENT_QOS) ------------------------------
    def gradients(self, actor_id: int) -> str:
        return f"{self.root}/gradients/{actor_id}"

    @property
    def all_gradients(self) -> str:
        return f"{self.root}/gradients/*"

    # -- actor ids: actor -> replay shard 0, query/reply, once per actor process -----------
    @property
    def actor_ids(self) -> str:
        return f"{self.root}/actor_ids"

    # -- learner version beacon (VERSION_QOS) ----------------------------------------------
    @property
    def learner_version(self) -> str:
        return f"{self.root}/learner/version"

    # -- learner metrics (STATS_QOS) -------------------------------------------------------
    def metrics(self, rank: int = 0) -> str:
        return f"{self.root}/metrics/{rank}"

    @property
    def all_metrics(self) -> str:
        return f"{self.root}/metrics/*"

    # -- episode summaries: actor -> anyone (EPISODE_QOS) ----------------------------------
    def episodes(self, actor_id: int) -> str:
        return f"{self.root}/episodes/{actor_id}"

    @property
    def all_episodes(self) -> str:
        return f"{self.root}/episodes/*"

    # -- evaluation rounds: evaluator -> launcher, as each round starts (ROUND_QOS) ----------
    def rounds(self, actor_id: int) -> str:
        return f"{self.root}/rounds/{actor_id}"

    @property
    def all_rounds(self) -> str:
        return f"{self.root}/rounds/*"

    # -- live frames for a viewer (FRAMES_QOS), sent only while a viewer token exists ------
    def frames(self, actor_id: int, env_id: int) -> str:
        return f"{self.root}/frames/{actor_id}/{env_id}"

    @property
    def all_frames(self) -> str:
        return f"{self.root}/frames/**"

    # -- stats of any daemon (STATS_QOS) ---------------------------------------------------
    def stats(self, role: str, instance: str | int) -> str:
        return f"{self.root}/stats/{_role(role)}/{check_name(str(instance), 'instance')}"

    @property
    def all_stats(self) -> str:
        return f"{self.root}/stats/**"

    # -- liveliness tokens -----------------------------------------------------------------
    def alive(self, role: str, instance: str | int) -> str:
        return f"{self.root}/alive/{_role(role)}/{check_name(str(instance), 'instance')}"

    def alive_role(self, role: str) -> str:
        return f"{self.root}/alive/{_role(role)}/*"

    @property
    def alive_all(self) -> str:
        return f"{self.root}/alive/**"

    @property
    def viewers(self) -> str:
        """Actors publish frames only while a token matches this."""
        return self.alive_role("viewer")


def shard_of(actor_id: int, num_shards: int) -> int:
    """The replay shard an actor feeds."""
    if num_shards < 1:
        raise ValueError(f"num_shards must be >= 1, got {num_shards}")
    return int(actor_id) % num_shards


def parse_alive(key: str) -> tuple[str, str]:
    """``(role, instance)`` of a liveliness key ``l2r/<run>/alive/<role>/<id>``."""
    parts = str(key).split("/")
    if len(parts) != 5 or parts[2] != "alive":
        raise ValueError(f"not a liveliness key: {key}")
    return parts[3], parts[4]


def _role(role: str) -> str:
    if role not in ROLES:
        raise ValueError(f"unknown role {role!r}; known roles: {', '.join(ROLES)}")
    return role
