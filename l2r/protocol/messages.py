"""The messages l2r daemons exchange, and their msgpack wire format.

Every message is one msgpack map ``{"v": VERSION, "kind": KIND, <fields>}``, where VERSION is
the lowest protocol version that can read it: 3 for an experience chunk whose frames are
compressed (``frames_codec``), 2 for a message with observation fields other than the float32
vector, else 1, so older peers get the bytes they know.
An array field is a map ``{"dtype": "<f4", "shape": [T, 41], "data": <bin>}`` in C order,
decoded with ``numpy.frombuffer`` (a read-only view, no copy of the data; data of 64 KiB or
more is left in the payload, ``_unpackb``).
``decode`` checks everything a peer could get wrong, integer ranges included (``limits.py``),
and raises ``ProtocolError`` with the reason; it never raises anything else.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
from typing import Any, ClassVar, Mapping

import msgpack
import numpy as np

from l2r.protocol.errors import ProtocolError
from l2r.protocol.frames_codec import FrameCompressor, inflate
from l2r.protocol.limits import ANY, INTEGER_LIMITS
from l2r.protocol.observations import DTYPES as OBSERVATION_DTYPES
from l2r.protocol.observations import VECTOR_FIELD, ObservationSpec, as_fields

PROTOCOL_VERSION = 3
"""The newest version this side speaks; it reads every version from 1 on."""
COMPRESSED_VERSION = 3
"""The version of experience chunks with compressed frames (a map with ``codec``)."""
MAX_MESSAGE_BYTES = 256 * 1024 * 1024
MAX_ARRAY_DIMS = 4
MAX_GRADIENT_VALUES = 2**26
"""The most values of a gradient (256 MiB of float32, the size of the largest message)."""

# Field types: "int", "float", "bool", "str", "numbers" (str -> number), "dict" (free-form,
# msgpack-native), "arrays" (str -> float array), an array of one dtype such as "float32[]",
# "fields" (observation field name -> array with rows first, in the field's dtype: version 2
# on), or "observations": the float32[rows, width] array of the vector observation in
# version 1, fields in version 2, fields that may be compressed in version 3 (in memory, the
# array or the map of fields, never compressed).
# A trailing "?" marks a field added later: a sender may leave it out (it is then None), so
# messages of earlier senders still decode.
_SCALARS = {"int": (int,), "float": (float, int), "bool": (bool,), "str": (str,)}
# the dtypes arrays may have, by their little-endian wire name ("<f4", "|b1", ...)
_DTYPES = {d.str: d for d in map(np.dtype, ("float16", "float32", "float64", "int32", "int64", "uint8", "bool"))}
_BY_NAME = {d.name: d for d in _DTYPES.values()}
_WEIGHT_DTYPES = (_BY_NAME["float16"], _BY_NAME["float32"], _BY_NAME["float64"])


class Message:
    """Base of all messages: subclasses declare ``KIND`` and ``SCHEMA`` (field -> type)."""

    KIND: ClassVar[str]
    SCHEMA: ClassVar[dict[str, str]]

    def validate(self) -> None:
        """Cross-field checks (shapes that must agree); raise ProtocolError."""


def _kinds() -> dict[str, type[Message]]:
    return {cls.KIND: cls for cls in Message.__subclasses__()}


Observations = np.ndarray | dict[str, np.ndarray]
"""Rows of observations: the float32 matrix of the vector observation, or a map of field name
to array with the rows first (``observations.as_fields`` reads either as fields)."""


@dataclass
class ExperienceChunk(Message):
    """T consecutive transitions of one environment of one actor.

    ``obs`` has T+1 rows (of every field): ``obs[t]`` is seen before step t and ``obs[t+1]``
    after it, so consecutive steps share one row. When step t < T-1 ends an episode,
    ``obs[t+1]`` is the first observation of the next episode and the true next observation of
    step t is the next row of ``final_obs`` (rows in step order, the same fields as ``obs``);
    ``obs[T]`` is always the true next observation of the last step. ``terminated`` (no
    bootstrap) and ``truncated`` (time limit: bootstrap) are kept apart. ``(actor_id, epoch,
    seq)`` makes a chunk unique: ``epoch`` is fixed for one actor process (its start time in
    ns), ``seq`` counts its chunks from 0, one per chunk, across all its environments.
    """

    KIND: ClassVar[str] = "experience"
    SCHEMA: ClassVar[dict[str, str]] = {
        "actor_id": "int", "env_id": "int", "epoch": "int", "seq": "int", "policy_version": "int",
        "obs": "observations", "actions": "float32[]", "rewards": "float32[]",
        "terminated": "bool[]", "truncated": "bool[]", "final_obs": "observations", "log_probs": "float32[]?",
    }
    actor_id: int
    env_id: int
    epoch: int
    seq: int
    policy_version: int
    obs: Observations
    actions: np.ndarray
    rewards: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    final_obs: Observations
    log_probs: np.ndarray | None = None
    """log pi(action | obs) of each step under the policy that acted, in the policy's (-1, 1)
    action space (None from actors older than the queue table)."""

    @property
    def size(self) -> int:
        return len(self.actions)

    def validate(self) -> None:
        _ndim(self, actions=2, rewards=1, terminated=1, truncated=1)
        t = len(self.actions)
        if t == 0:
            raise ProtocolError("experience: empty chunk", "empty_chunk")
        _rows(self, t, "rewards", "terminated", "truncated")
        inner_ends = int(np.count_nonzero((self.terminated | self.truncated)[:-1]))
        spec = _observation_rows(self, "obs", t + 1, f"expected T+1 = {t + 1}")
        final_spec = _observation_rows(self, "final_obs", inner_ends,
                                       f"but {inner_ends} episodes end before the last step")
        if final_spec != spec:
            raise ProtocolError(f"experience: final_obs rows are {final_spec}, obs rows {spec}", "shape_mismatch")
        _finite(self, "actions", "rewards")
        if self.log_probs is not None:
            _ndim(self, log_probs=1)
            _rows(self, t, "log_probs")
            _finite(self, "log_probs")

    def next_obs(self) -> Observations:
        """The true next observation of every step, T rows in the form of ``obs`` (a copy; for
        tests and tools)."""
        ends = np.flatnonzero((self.terminated | self.truncated)[:-1])

        def after(rows: np.ndarray, final: np.ndarray) -> np.ndarray:
            nxt = np.array(rows[1:])
            nxt[ends] = final
            return nxt

        final = as_fields(self.final_obs)
        nxt = {name: after(rows, final[name]) for name, rows in as_fields(self.obs).items()}
        return nxt[VECTOR_FIELD] if isinstance(self.obs, np.ndarray) else nxt


@dataclass
class Weights(Message):
    """Policy weights with their version, and the spec an actor needs to build the network."""

    KIND: ClassVar[str] = "weights"
    SCHEMA: ClassVar[dict[str, str]] = {"version": "int", "params": "arrays", "spec": "dict",
                                        "value_params": "arrays?", "training": "dict?"}
    version: int
    params: dict[str, np.ndarray]
    spec: dict = field(default_factory=dict)
    value_params: dict[str, np.ndarray] | None = None
    """A3C: the value network's weights, which its actors need to compute gradients (None: the
    policy alone, as every other algorithm publishes it)."""
    training: dict | None = None
    """A3C: the algorithm's settings (A3CConfig as a dict), the loss the actors differentiate."""


@dataclass
class Gradient(Message):
    """A3C: the gradient of the actor-critic loss one actor computed on its own rollout, at the
    weights of ``policy_version``, flattened in the order of the learner's parameters (policy,
    then value network). ``obs_moments``, where the networks standardise observations, are the
    rollout's [count, sum, sum of squares] of the filtered observations, for the learner's running
    statistics (the rollout itself never reaches the learner)."""

    KIND: ClassVar[str] = "gradient"
    SCHEMA: ClassVar[dict[str, str]] = {"actor_id": "int", "policy_version": "int", "env_steps": "int",
                                        "gradient": "float32[]", "obs_moments": "float64[]?"}
    actor_id: int
    policy_version: int
    env_steps: int
    """Environment steps of the rollout the gradient was computed on."""
    gradient: np.ndarray
    obs_moments: np.ndarray | None = None

    def validate(self) -> None:
        _ndim(self, gradient=1)
        if len(self.gradient) > MAX_GRADIENT_VALUES:
            raise ProtocolError(f"gradient: {len(self.gradient)} values, more than {MAX_GRADIENT_VALUES}", "oversized")
        _finite(self, "gradient")
        if self.obs_moments is not None:
            _ndim(self, obs_moments=1)
            _finite(self, "obs_moments")
            if len(self.obs_moments) % 2 != 1 or self.obs_moments[0] < 1:
                raise ProtocolError(f"gradient: obs_moments of {len(self.obs_moments)} values, expected a count "
                                    "of at least 1 and two sums of one width", "shape_mismatch")


@dataclass
class SampleRequest(Message):
    """A learner asks one replay shard for a batch (query payload)."""

    KIND: ClassVar[str] = "sample_request"
    SCHEMA: ClassVar[dict[str, str]] = {"batch_size": "int", "count": "int", "prioritized": "bool",
                                        "learner_version": "int", "table": "str?", "n_step": "int?",
                                        "gamma": "float?", "frame_stack": "int?"}
    batch_size: int = 256
    count: int = 1  # batches in one reply, each a separate reply sample
    prioritized: bool = False
    learner_version: int = -1  # newest version the learner has published; for policy lag
    table: str | None = None
    """Which table of the shard to take from: "replay" (None means it too) or "queue"."""
    n_step: int | None = None
    """Steps of the return each transition of the batch carries, 1 to 20 (limits.MAX_N_STEP; None: 1)."""
    gamma: float | None = None
    """The discount of those returns, in [0, 1]; needed when n_step > 1."""
    frame_stack: int | None = None
    """Observations stacked into each transition's observation, 1 to 16 (limits.MAX_FRAME_STACK).
    Set, the batch comes in the frames form; None asks for the version-1 form of the float32
    vector, which a shard of any other observation refuses (``frames_only``)."""

    def validate(self) -> None:
        if self.gamma is not None and not 0.0 <= self.gamma <= 1.0:
            raise ProtocolError(f"sample_request.gamma: {self.gamma} not in [0, 1]", "out_of_range")
        if (self.n_step or 1) > 1 and self.gamma is None:
            raise ProtocolError(f"sample_request: n_step {self.n_step} needs gamma, the discount of its returns",
                                "missing_field")


@dataclass
class SampleBatch(Message):
    """One sampled batch (query reply). ``probabilities`` are the sampling probabilities
    (1/size when uniform); ``indices`` and ``generations`` address the slots for priority updates.

    Observations come in one of two forms: ``obs`` and ``next_obs``, float32 vectors of each
    transition (version 1); or ``frames``, each distinct observation of the batch once, with
    ``obs_frames`` and ``next_obs_frames`` saying which frames, oldest first, make the stacked
    observation before and after each transition (version 2).
    """

    KIND: ClassVar[str] = "sample_batch"
    SCHEMA: ClassVar[dict[str, str]] = {
        "shard": "int", "size": "int", "prioritized": "bool",
        "obs": "float32[]?", "actions": "float32[]", "rewards": "float32[]", "next_obs": "float32[]?",
        "frames": "fields?", "obs_frames": "int64[]?", "next_obs_frames": "int64[]?",
        "terminated": "bool[]", "truncated": "bool[]", "indices": "int64[]", "generations": "int64[]",
        "probabilities": "float64[]", "policy_versions": "int64[]",
        "log_probs": "float32[]?", "segment_ends": "bool[]?", "discounts": "float32[]?",
    }
    shard: int
    size: int
    prioritized: bool
    obs: np.ndarray | None
    actions: np.ndarray
    rewards: np.ndarray
    next_obs: np.ndarray | None
    terminated: np.ndarray
    truncated: np.ndarray
    indices: np.ndarray
    generations: np.ndarray
    probabilities: np.ndarray
    policy_versions: np.ndarray
    log_probs: np.ndarray | None = None
    """Queue batches: the acting policy's log pi(action | obs) of each transition."""
    segment_ends: np.ndarray | None = None
    """Queue batches: True where the next row does not continue this transition's trajectory
    (the end of a chunk, or of the batch)."""
    discounts: np.ndarray | None = None
    """Batches of n-step returns (``n_step`` > 1 asked): what multiplies the bootstrap value of
    ``next_obs``, gamma ** (steps summed in ``rewards``), or 0 where the last of them terminated."""
    frames: dict[str, np.ndarray] | None = None
    """Each distinct observation of the batch once: field name -> array (N, *field shape)."""
    obs_frames: np.ndarray | None = None
    """(B, k): the rows of ``frames`` whose fields, stacked oldest first, are each
    transition's observation (k: the stack the learner asked for)."""
    next_obs_frames: np.ndarray | None = None
    """(B, k): the same for the observation after each transition."""

    def validate(self) -> None:
        _ndim(self, actions=2, rewards=1, terminated=1, truncated=1,
              indices=1, generations=1, probabilities=1, policy_versions=1)
        b = len(self.actions)
        _rows(self, b, "rewards", "terminated", "truncated",
              "indices", "generations", "probabilities", "policy_versions")
        if (self.log_probs is None) != (self.segment_ends is None):
            raise ProtocolError("sample_batch: log_probs and segment_ends come together", "missing_field")
        if self.log_probs is not None:
            _ndim(self, log_probs=1, segment_ends=1)
            _rows(self, b, "log_probs", "segment_ends")
        if self.discounts is not None:
            _ndim(self, discounts=1)
            _rows(self, b, "discounts")
        self._check_observations(b)

    def _check_observations(self, b: int) -> None:
        if self.frames is None and self.obs_frames is None and self.next_obs_frames is None:
            if self.obs is None or self.next_obs is None:
                raise ProtocolError("sample_batch: expected obs and next_obs, or frames with obs_frames and "
                                    "next_obs_frames", "missing_field")
            _ndim(self, obs=2, next_obs=2)
            _rows(self, b, "obs", "next_obs")
            if self.next_obs.shape != self.obs.shape:
                raise ProtocolError(f"sample_batch: next_obs shape {self.next_obs.shape} != obs shape "
                                    f"{self.obs.shape}", "shape_mismatch")
            return
        if self.obs is not None or self.next_obs is not None:
            raise ProtocolError("sample_batch: obs and next_obs, or frames: not both", "invalid")
        if self.frames is None or self.obs_frames is None or self.next_obs_frames is None:
            raise ProtocolError("sample_batch: frames, obs_frames and next_obs_frames come together", "missing_field")
        ObservationSpec.of_rows(self.frames, "sample_batch.frames")
        counts = {name: len(rows) for name, rows in self.frames.items()}
        n = max(counts.values())
        if min(counts.values()) != n:
            raise ProtocolError(f"sample_batch: frames fields have different numbers of rows {counts}",
                                "shape_mismatch")
        _ndim(self, obs_frames=2, next_obs_frames=2)
        _rows(self, b, "obs_frames", "next_obs_frames")
        if self.obs_frames.shape != self.next_obs_frames.shape or self.obs_frames.shape[1] == 0:
            raise ProtocolError(f"sample_batch: obs_frames {self.obs_frames.shape} and next_obs_frames "
                                f"{self.next_obs_frames.shape} must be stacks of the same k >= 1 frames",
                                "shape_mismatch")
        for name in ("obs_frames", "next_obs_frames"):
            rows = getattr(self, name)
            if rows.size and (rows.min() < 0 or rows.max() >= n):
                raise ProtocolError(f"sample_batch: {name} has a row outside frames' {n}", "out_of_range")

    def importance_weights(self, beta: float) -> np.ndarray:
        """Prioritized-replay correction ``(size * p)^-beta``, normalised to a maximum of 1."""
        w = (self.size * self.probabilities) ** (-beta)
        return (w / w.max()).astype(np.float32)


@dataclass
class NotReady(Message):
    """Reply to a sample request the rate limiter holds back; ask again after ``retry_after`` s."""

    KIND: ClassVar[str] = "not_ready"
    SCHEMA: ClassVar[dict[str, str]] = {"shard": "int", "reason": "str", "size": "int", "retry_after": "float"}
    shard: int
    reason: str
    size: int
    retry_after: float


@dataclass
class ReplayAck(Message):
    """What a replay shard has stored of each actor's current epoch, so actors resend the rest.

    Row i is about actor ``actor_ids[i]`` in epoch ``epochs[i]``: every chunk with
    ``seq <= highest[i]`` is stored except the ``missing_counts[i]`` sequence numbers that are
    its part of ``missing`` (rows in order, each part ascending). Nothing is said of chunks
    above ``highest[i]``.
    """

    KIND: ClassVar[str] = "replay_ack"
    SCHEMA: ClassVar[dict[str, str]] = {
        "shard": "int", "actor_ids": "int64[]", "epochs": "int64[]", "highest": "int64[]",
        "missing_counts": "int64[]", "missing": "int64[]", "hold": "bool?",
    }
    shard: int
    actor_ids: np.ndarray
    epochs: np.ndarray
    highest: np.ndarray
    missing_counts: np.ndarray
    missing: np.ndarray
    hold: bool | None = None
    """True while the shard's queue is full and asks its actors to wait before stepping on."""

    def validate(self) -> None:
        _ndim(self, actor_ids=1, epochs=1, highest=1, missing_counts=1, missing=1)
        _rows(self, len(self.actor_ids), "epochs", "highest", "missing_counts")
        if np.any(self.missing_counts < 0) or int(self.missing_counts.sum()) != len(self.missing):
            raise ProtocolError(f"replay_ack: missing_counts sum to {int(self.missing_counts.sum())}, "
                                f"but missing has {len(self.missing)} entries", "shape_mismatch")

    def of(self, actor_id: int, epoch: int) -> tuple[int, np.ndarray] | None:
        """``(highest, missing)`` for this actor and epoch, or None when the ack says nothing of it."""
        rows = np.flatnonzero((self.actor_ids == actor_id) & (self.epochs == epoch))
        if not len(rows):
            return None
        i = int(rows[0])
        start = int(self.missing_counts[:i].sum())
        return int(self.highest[i]), self.missing[start:start + int(self.missing_counts[i])]


@dataclass
class PriorityUpdate(Message):
    """New priorities (before the server's exponent) for sampled slots of one shard.
    A slot whose generation changed since it was sampled has been overwritten: ignored."""

    KIND: ClassVar[str] = "priority_update"
    SCHEMA: ClassVar[dict[str, str]] = {"indices": "int64[]", "generations": "int64[]", "priorities": "float32[]"}
    indices: np.ndarray
    generations: np.ndarray
    priorities: np.ndarray

    def validate(self) -> None:
        _ndim(self, indices=1, generations=1, priorities=1)
        _rows(self, len(self.indices), "generations", "priorities")
        if not np.all(np.isfinite(self.priorities)) or np.any(self.priorities < 0):
            raise ProtocolError("priority_update: priorities must be finite and >= 0", "out_of_range")


@dataclass
class EpisodeSummary(Message):
    """One finished episode."""

    KIND: ClassVar[str] = "episode"
    SCHEMA: ClassVar[dict[str, str]] = {
        "actor_id": "int", "env_id": "int", "episode_return": "float", "distance": "float",
        "length": "int", "policy_version": "int", "difficulty": "int", "seed": "int",
        "evaluation": "bool", "time": "float", "psnr_db": "float?",
    }
    actor_id: int
    env_id: int
    episode_return: float
    distance: float
    length: int
    policy_version: int
    difficulty: int
    seed: int
    evaluation: bool = False
    time: float = 0.0  # sender's wall clock (s since epoch)
    psnr_db: float | None = None
    """The last image's PSNR to its goal, in dB: a photo task's score (its last step's
    `info["psnr_db"]`); None on other tasks, and from actors older than the field."""


@dataclass
class EvaluationRound(Message):
    """An evaluator starting a round of deterministic episodes of one policy version. It comes
    before the round's episodes, so that whoever keeps the best policy (`l2r up`) holds
    on to that version's weights, however many versions the learner publishes meanwhile."""

    KIND: ClassVar[str] = "evaluation_round"
    SCHEMA: ClassVar[dict[str, str]] = {"actor_id": "int", "policy_version": "int"}
    actor_id: int
    policy_version: int


@dataclass
class Stats(Message):
    """Free-form numbers a daemon reports about itself."""

    KIND: ClassVar[str] = "stats"
    SCHEMA: ClassVar[dict[str, str]] = {"role": "str", "instance": "str", "time": "float", "values": "numbers"}
    role: str
    instance: str
    time: float
    values: dict[str, float]


@dataclass
class LearnerVersion(Message):
    """The newest policy version a learner has published (a small beacon)."""

    KIND: ClassVar[str] = "learner_version"
    SCHEMA: ClassVar[dict[str, str]] = {"version": "int", "updates": "int", "time": "float"}
    version: int
    updates: int = 0
    time: float = 0.0


MAX_ACTOR_NAME = 300  # a host name (at most 253 characters), a colon and a process id


@dataclass
class ActorIdRequest(Message):
    """An actor asking replay shard 0 for its id (query payload): the same ``name`` always gets
    the same id, and no other name gets it."""

    KIND: ClassVar[str] = "actor_id_request"
    SCHEMA: ClassVar[dict[str, str]] = {"name": "str"}
    name: str

    def validate(self) -> None:
        if not 0 < len(self.name) <= MAX_ACTOR_NAME:
            raise ProtocolError(f"actor_id_request: a name of {len(self.name)} characters, expected 1 to "
                                f"{MAX_ACTOR_NAME}", "invalid")


@dataclass
class ActorId(Message):
    """Replay shard 0's reply to an ``ActorIdRequest``: the id of that name in this run."""

    KIND: ClassVar[str] = "actor_id"
    SCHEMA: ClassVar[dict[str, str]] = {"name": "str", "actor_id": "int"}
    name: str
    actor_id: int


@dataclass
class Frame(Message):
    """One step of a running episode for a live viewer: named arrays and numbers, and the camera
    frames of the observation after the step."""

    KIND: ClassVar[str] = "frame"
    SCHEMA: ClassVar[dict[str, str]] = {
        "actor_id": "int", "env_id": "int", "episode": "int", "step": "int",
        "arrays": "arrays", "values": "numbers", "images": "fields?",
    }
    actor_id: int
    env_id: int
    episode: int
    step: int
    arrays: dict[str, np.ndarray]
    values: dict[str, float] = field(default_factory=dict)
    images: dict[str, np.ndarray] | None = None
    """Observation fields of one row, each an RGB frame: uint8 (1, 3, H, W) by field name. A frame
    with images is version 2 (observation fields), so a version-1 viewer rejects it as ``version``."""

    def validate(self) -> None:
        if self.images is None:
            return
        _observation_rows(self, "images", 1, "expected 1 (the observation after the step)")
        for name, rows in self.images.items():
            if rows.dtype != np.uint8:
                raise ProtocolError(f"frame.images.{name}: dtype {rows.dtype}, expected uint8", "wrong_dtype")
            if rows.ndim != 4 or rows.shape[1] != 3:
                raise ProtocolError(f"frame.images.{name}: shape {list(rows.shape)}, expected [1, 3, height, width]",
                                    "wrong_shape")


# -- encoding -----------------------------------------------------------------------------

def encode(message: Message, frames: FrameCompressor | None = None) -> bytes:
    """msgpack bytes of ``message`` (validated first, so a sender cannot emit garbage). With
    ``frames``, its uint8 observation fields (an experience chunk's frames) go compressed, in
    version 3; a message without them is the same bytes as without ``frames``."""
    return _packb(_wire_map(message, frames))


def encode_gathered(batch: SampleBatch, sources: Mapping[str, np.ndarray], rows: np.ndarray) -> bytes | bytearray:
    """``encode`` of ``batch`` with ``frames`` of ``sources[name].take(rows, axis=0)`` for each
    field (``batch.frames`` is not read), byte for byte, the rows gathered straight into the
    message's buffer: a replay shard's frames are copied once on their way into a reply, not
    twice (gathered, then joined into the message: 2-7 ms for 20 MB on a loaded machine).
    ``rows`` are distinct rows of every source. A field of less than ``LARGE_ARRAY_BYTES``, or
    whose source is not a C-ordered little-endian array, is gathered first."""
    slots, frames = {}, {}
    for name, source in sources.items():
        direct = source.flags.c_contiguous and source.dtype.str[0] in "<|"
        if direct and len(rows) * math.prod(source.shape[1:]) * source.itemsize >= LARGE_ARRAY_BYTES:
            # the source's first rows stand in for the frames (no memory made, their bytes never
            # read): the encoder leaves their memory as one piece, where the rows go instead
            frames[name] = source[:len(rows)]
            slots[frames[name].ctypes.data] = source
        else:
            frames[name] = source.take(rows, axis=0)
    pieces = _pieces(_wire_map(replace(batch, frames=frames)))
    if not slots:
        return b"".join(pieces)
    message = bytearray(sum(len(piece) for piece in pieces))  # (a large piece is a 1-d memoryview of bytes)
    at, gathered = 0, 0
    for piece in pieces:
        end = at + len(piece)
        source = slots.get(np.frombuffer(piece, np.uint8).ctypes.data) if isinstance(piece, memoryview) else None
        if source is None:
            message[at:end] = piece
        else:
            out = np.frombuffer(message, source.dtype, (end - at) // source.dtype.itemsize, at)
            # mode "clip" (the rows are in range): numpy's default mode gathers into a temporary first
            source.take(rows, axis=0, out=out.reshape(len(rows), *source.shape[1:]), mode="clip")
            gathered += 1
        at = end
    if gathered != len(slots):  # a stand-in the encoder copied (never, for the arrays above)
        raise RuntimeError(f"encode_gathered: {len(slots) - gathered} of the frames' fields not found in the message")
    return message


def _wire_map(message: Message, frames: FrameCompressor | None = None) -> dict[str, Any]:
    """The map ``encode`` packs: version, kind and each field in its wire form (array data as
    memoryviews of the arrays; ``frames`` compresses uint8 observation fields), after checking
    ``message``."""
    message.validate()
    _check_ranges(message)
    version = _version(message, frames is not None)
    out: dict[str, Any] = {"v": version, "kind": message.KIND}
    for name, kind in message.SCHEMA.items():
        value = getattr(message, name)
        kind = kind.removesuffix("?")
        if value is None and kind != message.SCHEMA[name]:
            continue  # an optional field left out
        if kind == "observations" and version == 1:
            out[name] = _pack_array(as_fields(value)[VECTOR_FIELD])
        elif kind == "observations" and version == COMPRESSED_VERSION:
            out[name] = {field_name: _pack_compressed(rows, frames) if rows.dtype == np.uint8 else _pack_array(rows)
                         for field_name, rows in as_fields(value).items()}
        elif kind in ("observations", "fields"):
            out[name] = {field_name: _pack_array(rows) for field_name, rows in as_fields(value).items()}
        elif kind == "arrays":
            out[name] = {k: _pack_array(np.asarray(a)) for k, a in value.items()}
        elif kind.endswith("[]"):
            out[name] = _pack_array(np.asarray(value, dtype=_BY_NAME[kind[:-2]]))
        elif kind == "numbers":  # an integer beyond int64 (a huge sum) goes as a float, not as an error
            out[name] = {str(k): (v if isinstance(v, int) and ANY[0] <= v <= ANY[1] else float(v))
                         for k, v in value.items()}
        else:
            out[name] = value
    return out


LARGE_ARRAY_BYTES = 64 * 1024
"""Array data from this size on is joined into the message by ``_packb`` rather than packed by msgpack."""


def _packb(out: dict) -> bytes:
    """``msgpack.packb(out, use_bin_type=True)``, byte for byte, with the data of large arrays
    copied into the result once. msgpack would copy it into a buffer that grows by reallocation
    (fresh pages each time) and then again into its result: 16-78 ms for a batch of camera frames
    (20 MB) on a loaded machine, against 1.4-7 ms joined."""
    if not any(_large_data(value) for value in out.values()):
        return msgpack.packb(out, use_bin_type=True)
    return b"".join(_pieces(out))


def _pieces(out: dict) -> list[bytes | memoryview]:
    """The bytes of ``msgpack.packb(out, use_bin_type=True)`` in pieces: msgpack's for all but
    the data of large arrays, which are the arrays' own memory."""
    packer = msgpack.Packer(use_bin_type=True)
    pieces: list[bytes | memoryview] = []

    def walk(value: Any) -> None:
        if isinstance(value, dict):
            pieces.append(packer.pack_map_header(len(value)))
            for key, item in value.items():
                pieces.append(packer.pack(key))
                walk(item)
        elif isinstance(value, memoryview) and value.nbytes >= LARGE_ARRAY_BYTES:
            pieces.append(_bin_header(value.nbytes))
            pieces.append(value)
        else:
            pieces.append(packer.pack(value))

    walk(out)
    return pieces


def _large_data(value: Any) -> bool:
    """Whether ``value``, an array map or a map of them (or anything else), holds large array data."""
    if not isinstance(value, dict):
        return False
    data = value.get("data")
    if isinstance(data, memoryview):
        return data.nbytes >= LARGE_ARRAY_BYTES
    return any(_large_data(item) for item in value.values())


def _bin_header(size: int) -> bytes:
    """msgpack's header of a bin of ``size`` bytes (bin 8, 16 or 32, the shortest that fits, as msgpack writes it)."""
    if size < 1 << 8:
        return b"\xc4" + size.to_bytes(1, "big")
    if size < 1 << 16:
        return b"\xc5" + size.to_bytes(2, "big")
    return b"\xc6" + size.to_bytes(4, "big")


def _version(message: Message, compressing: bool = False) -> int:
    """The lowest protocol version that reads ``message``: 3 where it holds uint8 observation
    fields to be compressed (``compressing``), 2 where it holds observation fields other than
    the float32 vector alone, else 1."""
    if compressing and any(rows.dtype == np.uint8 for name, kind in message.SCHEMA.items()
                           if kind == "observations" for rows in as_fields(getattr(message, name)).values()):
        return COMPRESSED_VERSION
    for name, kind in message.SCHEMA.items():
        value = getattr(message, name)
        if kind.removesuffix("?") == "fields" and value is not None:
            return 2
        if kind == "observations" and not isinstance(value, np.ndarray):  # (a matrix is the vector)
            spec = ObservationSpec.of_rows(value, f"{message.KIND}.{name}")  # checked by validate
            if spec.vector_width is None:
                return 2
    return 1


def _pack_array(a: np.ndarray) -> dict:
    a = np.asarray(a, order="C")  # (ascontiguousarray would make a 0-d array 1-d)
    if a.dtype.byteorder == ">":
        a = a.astype(a.dtype.newbyteorder("<"))
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.reshape(-1).view(np.uint8).data}


def _pack_compressed(a: np.ndarray, frames: FrameCompressor) -> dict:
    return {"dtype": a.dtype.str, "shape": list(a.shape), "codec": frames.codec, "data": memoryview(frames.compress(a))}


# -- decoding -----------------------------------------------------------------------------

def decode(payload: bytes | bytearray | memoryview | Any, expected: type | tuple = Message) -> Message:
    """Parse and check one message; raise ProtocolError with the reason if it is not acceptable.

    ``payload`` may be a ``zenoh.ZBytes``; ``expected`` restricts the accepted classes.
    """
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        payload = payload.to_bytes()
    if len(payload) > MAX_MESSAGE_BYTES:
        raise ProtocolError(f"oversized message: {len(payload)} bytes > {MAX_MESSAGE_BYTES}", "oversized")
    try:
        raw = _unpackb(payload)
    except Exception as e:  # msgpack raises several types for truncated or malformed input
        raise ProtocolError(f"malformed msgpack ({type(e).__name__}: {e})", "malformed") from None
    if not isinstance(raw, dict):
        raise ProtocolError(f"message is a msgpack {type(raw).__name__}, expected a map", "not_a_map")
    version = raw.get("v")
    if type(version) is not int or not 1 <= version <= PROTOCOL_VERSION:  # not 1.0, not true
        raise ProtocolError(f"protocol version {version!r}, this side speaks 1 to {PROTOCOL_VERSION}", "version")
    kind = raw.get("kind")
    cls = _KINDS.get(kind) if isinstance(kind, str) else None
    if cls is None:
        raise ProtocolError(f"unknown message kind {kind!r}", "unknown_kind")
    if not issubclass(cls, expected):
        raise ProtocolError(f"unexpected message kind {kind!r} here", "unexpected_kind")
    inflation = _Inflation()
    values = {name: _field(kind, name, spec, raw.get(name, _MISSING), version, inflation)
              for name, spec in cls.SCHEMA.items()}
    message = cls(**values)
    try:
        message.validate()
    except ProtocolError:
        raise
    except Exception as e:  # a validation on absurd input must still end as a rejection
        raise ProtocolError(f"{kind}: invalid ({type(e).__name__}: {e})", "invalid") from None
    return message


_MISSING = object()


class _Inflation:
    """What the compressed fields of one message may decompress to, together: no more than a
    message may hold raw, so compression lets no peer make a receiver allocate more."""

    def __init__(self):
        self.left = MAX_MESSAGE_BYTES

    def take(self, where: str, nbytes: int) -> None:
        if nbytes > self.left:
            raise ProtocolError(f"{where}: compressed fields of more than {MAX_MESSAGE_BYTES} bytes in all",
                                "oversized")
        self.left -= nbytes


def _unpackb(payload: bytes | bytearray | memoryview) -> Any:
    """``msgpack.unpackb(payload)``, except that in a ``bytes`` payload the array data of
    ``LARGE_ARRAY_BYTES`` or more (a bin under the key "data" of a map at most three maps deep,
    as the encoder writes array maps) comes back as a read-only memoryview of the payload, not
    as msgpack's copy of it: a batch of camera frames (20 MB) is then copied once on its way
    from Zenoh to numpy (``to_bytes``), not twice. The views keep the payload alive; anything
    else in it is read by msgpack. A payload that may change under its views (a bytearray, a
    memoryview), or whose maps the walk does not read within ``_WALK_ITEMS`` items, is read by
    msgpack whole, which also raises its errors."""
    if isinstance(payload, bytes) and len(payload) >= LARGE_ARRAY_BYTES:
        try:
            walk = _ViewWalk(payload)
            value = walk.value(0, depth=3)
            if walk.at == len(payload):
                return value
        except Exception:  # malformed, or too many items to walk in Python: msgpack reads it (or says why not)
            pass
    return msgpack.unpackb(payload, raw=False, strict_map_key=True, use_list=True)


_WALK_ITEMS = 4096
"""The most msgpack items ``_ViewWalk`` steps over (a batch has about 150; a message of many
small items is read faster by msgpack than walked in Python)."""
# msgpack's first bytes: sizes of fixed-length values, and of the length fields of the others
_FIXED_SIZE = {0xc0: 1, 0xc2: 1, 0xc3: 1, 0xca: 5, 0xcb: 9, 0xcc: 2, 0xcd: 3, 0xce: 5, 0xcf: 9,
               0xd0: 2, 0xd1: 3, 0xd2: 5, 0xd3: 9, 0xd4: 3, 0xd5: 4, 0xd6: 6, 0xd7: 10, 0xd8: 18}
_BIN_LENGTH = {0xc4: 1, 0xc5: 2, 0xc6: 4}
_SIZED_LENGTH = {**_BIN_LENGTH, 0xd9: 1, 0xda: 2, 0xdb: 4}  # bin, str: length, then the bytes
_EXT_LENGTH = {0xc7: 1, 0xc8: 2, 0xc9: 4}  # length, type byte, then the bytes
_ARRAY_LENGTH, _MAP_LENGTH = {0xdc: 2, 0xdd: 4}, {0xde: 2, 0xdf: 4}


class _ViewWalk:
    """Reads a msgpack payload's maps in Python, leaving large array data in place (``_unpackb``)."""

    def __init__(self, payload: bytes):
        self.view = memoryview(payload)
        self.at = 0
        self.items = 0

    def value(self, at: int, depth: int, key: Any = None) -> Any:
        """The value at ``at``; sets ``at`` past it. Maps ``depth`` deep are walked, anything else
        is msgpack's, but a large bin under the key "data"."""
        first = self.view[at]
        pairs = self._map_length(at) if depth else None
        if pairs is not None:
            out = {}
            for _ in range(pairs):
                name = self.value(self.at, 0)
                if not isinstance(name, (str, bytes)):  # msgpack's strict_map_key
                    raise ValueError(f"map key of type {type(name).__name__}")
                out[name] = self.value(self.at, depth - 1, name)
            return out
        if key == "data" and first in _BIN_LENGTH:
            n = _BIN_LENGTH[first]
            size = int.from_bytes(self.view[at + 1:at + 1 + n], "big")
            if size >= LARGE_ARRAY_BYTES:
                start, self.at = at + 1 + n, at + 1 + n + size
                if self.at > len(self.view):
                    raise ValueError("truncated bin")
                return self.view[start:self.at]
        self.at = self._skip(at)
        return msgpack.unpackb(self.view[at:self.at], raw=False, strict_map_key=True, use_list=True)

    def _map_length(self, at: int) -> int | None:
        """The pairs of the map at ``at`` with ``at`` set past its header, or None for another type."""
        first = self.view[at]
        if 0x80 <= first <= 0x8f:
            self.at = at + 1
            return first & 0x0f
        if first in _MAP_LENGTH:
            n = _MAP_LENGTH[first]
            self.at = at + 1 + n
            return int.from_bytes(self.view[at + 1:self.at], "big")
        return None

    def _skip(self, at: int) -> int:
        """Where the value at ``at`` ends (counting its items against ``_WALK_ITEMS``)."""
        pending = 1
        while pending:
            pending -= 1
            self.items += 1
            if self.items > _WALK_ITEMS:
                raise ValueError("too many items to walk")
            first = self.view[at]
            if first <= 0x7f or first >= 0xe0:  # fixint
                at += 1
            elif first <= 0x8f:  # fixmap
                pending, at = pending + 2 * (first & 0x0f), at + 1
            elif first <= 0x9f:  # fixarray
                pending, at = pending + (first & 0x0f), at + 1
            elif first <= 0xbf:  # fixstr
                at += 1 + (first & 0x1f)
            elif first in _FIXED_SIZE:
                at += _FIXED_SIZE[first]
            elif first in _SIZED_LENGTH or first in _EXT_LENGTH:
                n = _SIZED_LENGTH.get(first) or _EXT_LENGTH[first]
                at += 1 + n + (first in _EXT_LENGTH) + int.from_bytes(self.view[at + 1:at + 1 + n], "big")
            elif first in _ARRAY_LENGTH or first in _MAP_LENGTH:
                n = _ARRAY_LENGTH.get(first) or _MAP_LENGTH[first]
                pending += (1 if first in _ARRAY_LENGTH else 2) * int.from_bytes(self.view[at + 1:at + 1 + n], "big")
                at += 1 + n
            else:
                raise ValueError(f"byte {first:#x} starts no msgpack value")
        if at > len(self.view):
            raise ValueError("truncated")
        return at


def _field(kind: str, name: str, spec: str, value: Any, version: int, inflation: _Inflation) -> Any:
    where = f"{kind}.{name}"
    if spec.endswith("?"):
        if value is _MISSING:
            return None
        spec = spec[:-1]
    if value is _MISSING:
        raise ProtocolError(f"{where}: missing", "missing_field")
    if spec == "fields" and version < 2:
        raise ProtocolError(f"{where}: observation fields in a version {version} message", "version")
    compressed = inflation if spec == "observations" and version >= COMPRESSED_VERSION else None
    if spec == "observations":
        spec = "fields" if version >= 2 else "float32[]"
    if spec == "fields":
        if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
            raise ProtocolError(f"{where}: expected a map of field names to arrays", "wrong_type")
        return {k: _unpack_array(f"{where}.{k}", v, tuple(OBSERVATION_DTYPES.values()), compressed)
                for k, v in value.items()}
    if spec in _SCALARS:
        ok = isinstance(value, _SCALARS[spec]) and not (spec != "bool" and isinstance(value, bool))
        if not ok:
            raise ProtocolError(f"{where}: expected {spec}, got {type(value).__name__}", "wrong_type")
        if spec == "float":
            value = float(value)
            if not math.isfinite(value):
                raise ProtocolError(f"{where}: not finite", "not_finite")
        if spec == "int":
            _in_range(where, value, INTEGER_LIMITS[kind][name])
        return value
    if spec == "dict":
        if not isinstance(value, dict):
            raise ProtocolError(f"{where}: expected a map, got {type(value).__name__}", "wrong_type")
        return value
    if spec == "numbers":
        if not isinstance(value, dict) or not all(
            isinstance(k, str) and isinstance(v, (int, float)) and not isinstance(v, bool) for k, v in value.items()
        ):
            raise ProtocolError(f"{where}: expected a map of names to numbers", "wrong_type")
        for k, v in value.items():
            if isinstance(v, int):
                _in_range(f"{where}.{k}", v, ANY)
        return value
    if spec == "arrays":
        if not isinstance(value, dict) or not all(isinstance(k, str) for k in value):
            raise ProtocolError(f"{where}: expected a map of names to arrays", "wrong_type")
        return {k: _unpack_array(f"{where}.{k}", v, _WEIGHT_DTYPES) for k, v in value.items()}
    return _unpack_array(where, value, (_BY_NAME[spec[:-2]],))


def _in_range(where: str, value: int, limits: tuple[int, int]) -> None:
    low, high = limits
    if not low <= value <= high:
        raise ProtocolError(f"{where}: {value} not in [{low}, {high}]", "out_of_range")


def _check_ranges(message: Message) -> None:
    """A sender's check that its integer fields are within the table (decode checks the same)."""
    for name, limits in INTEGER_LIMITS[message.KIND].items():
        if getattr(message, name) is not None:  # an optional field left out
            _in_range(f"{message.KIND}.{name}", getattr(message, name), limits)


def _unpack_array(where: str, value: Any, allowed: tuple[np.dtype, ...],
                  compressed: _Inflation | None = None) -> np.ndarray:
    """The array of an array map; with ``compressed``, the map may name a ``codec`` its data are
    compressed with (experience observations from version 3 on)."""
    codec = value.get("codec") if compressed is not None and isinstance(value, dict) else None
    if not isinstance(value, dict) or len(value) != 3 + (codec is not None):
        raise ProtocolError(f"{where}: expected an array map with dtype, shape and data", "bad_array")
    dtype_str, shape, data = value.get("dtype"), value.get("shape"), value.get("data")
    if not isinstance(dtype_str, str) or not isinstance(data, (bytes, memoryview)):
        raise ProtocolError(f"{where}: expected an array map with dtype (a string), shape and data (bytes)",
                            "bad_array")
    dtype = _DTYPES.get(dtype_str)
    if dtype is None or dtype not in allowed:  # (None == float64 in numpy: test it first)
        names = " or ".join(d.name for d in allowed)
        raise ProtocolError(f"{where}: dtype {dtype_str}, expected {names} (little-endian)", "wrong_dtype")
    if (not isinstance(shape, list) or len(shape) > MAX_ARRAY_DIMS
            or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in shape)):
        raise ProtocolError(f"{where}: bad shape {shape!r}", "bad_array")
    expected_bytes = math.prod(shape) * dtype.itemsize
    if codec is not None:
        compressed.take(where, expected_bytes)
        data = inflate(where, codec, data, expected_bytes)
    if expected_bytes != len(data):
        raise ProtocolError(f"{where}: shape {shape} of {dtype_str} needs {expected_bytes} bytes, got {len(data)}",
                            "bad_array")
    array = np.frombuffer(data, dtype=dtype).reshape(shape)
    if dtype.kind == "b" and array.size and array.view(np.uint8).max() > 1:
        raise ProtocolError(f"{where}: booleans must be the bytes 0 or 1", "bad_bool")
    return array


def _ndim(message: Message, **dims: int) -> None:
    for name, nd in dims.items():
        a = getattr(message, name)
        if not isinstance(a, np.ndarray) or a.ndim != nd:
            raise ProtocolError(f"{message.KIND}: {name} must be {nd}-d, got shape {getattr(a, 'shape', None)}",
                                "shape_mismatch")


def _rows(message: Message, n: int, *names: str) -> None:
    for name in names:
        if len(getattr(message, name)) != n:
            raise ProtocolError(f"{message.KIND}: {name} has {len(getattr(message, name))} rows, expected {n}",
                                "shape_mismatch")


def _observation_rows(message: Message, name: str, rows: int, expected: str) -> ObservationSpec:
    """Check that the observations in field ``name`` have ``rows`` rows of finite values (of a
    matrix, the vector observation; of a map, fields); return the spec of those rows."""
    value = getattr(message, name)
    if isinstance(value, np.ndarray):
        _ndim(message, **{name: 2})
    fields = as_fields(value)
    spec = ObservationSpec.of_rows(fields, f"{message.KIND}.{name}")
    for field_name, array in fields.items():
        label = name if isinstance(value, np.ndarray) else f"{name}.{field_name}"
        if len(array) != rows:
            raise ProtocolError(f"{message.KIND}: {label} has {len(array)} rows, {expected}", "shape_mismatch")
        if array.dtype.kind == "f" and not np.all(np.isfinite(array)):
            raise ProtocolError(f"{message.KIND}: {label} contains NaN or infinity", "not_finite")
    return spec


def _finite(message: Message, *names: str) -> None:
    for name in names:
        if not np.all(np.isfinite(getattr(message, name))):
            raise ProtocolError(f"{message.KIND}: {name} contains NaN or infinity", "not_finite")


_KINDS = _kinds()
