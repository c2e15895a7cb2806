"""The range of every integer field of every message, checked at decode.

msgpack integers run from -2^63 to 2^64 - 1, but receivers keep these values in int64 arrays,
acks and snapshots. A value outside its range is rejected (reason ``out_of_range``) before any
code sees it, so no message can make a receiver overflow. docs/protocol.md lists the same table.
"""

from __future__ import annotations

INT64_MIN, INT64_MAX = -(2**63), 2**63 - 1

ID = (0, 2**32 - 1)
"""Actors, environments, shards: non-negative numbers, also written into key expressions."""
COUNT = (0, INT64_MAX)
"""Counters and nanosecond times."""
VERSION = (-1, INT64_MAX)
"""Policy versions; -1: none yet."""
ANY = (INT64_MIN, INT64_MAX)
"""Integers without a meaning of their own: the values of a ``numbers`` map."""

MAX_BATCH_SIZE = 2**20
MAX_BATCHES_PER_QUERY = 64
MAX_N_STEP = 20
"""Longest n-step return a replay shard builds."""
MAX_FRAME_STACK = 16
"""Most observations a replay shard stacks into one (``sample_request.frame_stack``)."""

INTEGER_LIMITS: dict[str, dict[str, tuple[int, int]]] = {
    "experience": {"actor_id": ID, "env_id": ID, "epoch": COUNT, "seq": COUNT, "policy_version": VERSION},
    "weights": {"version": VERSION},
    "gradient": {"actor_id": ID, "policy_version": VERSION, "env_steps": COUNT},
    "sample_request": {"batch_size": (1, MAX_BATCH_SIZE), "count": (1, MAX_BATCHES_PER_QUERY),
                       "learner_version": VERSION, "n_step": (1, MAX_N_STEP),
                       "frame_stack": (1, MAX_FRAME_STACK)},
    "sample_batch": {"shard": ID, "size": COUNT},
    "not_ready": {"shard": ID, "size": COUNT},
    "replay_ack": {"shard": ID},
    "priority_update": {},
    "episode": {"actor_id": ID, "env_id": ID, "length": COUNT, "policy_version": VERSION, "difficulty": ID,
                "seed": COUNT},
    "evaluation_round": {"actor_id": ID, "policy_version": VERSION},
    "stats": {},
    "learner_version": {"version": VERSION, "updates": COUNT},
    "frame": {"actor_id": ID, "env_id": ID, "episode": COUNT, "step": COUNT},
    "actor_id_request": {},
    "actor_id": {"actor_id": ID},
}
"""kind -> field -> (lowest, highest) accepted, both included."""
