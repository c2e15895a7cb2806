"""Read an episode file back into numpy arrays.

The reader walks the file's records front to back and decodes every message with the schema
registered in the file, so it reads complete files and interrupted ones (a ``.part`` left by a
crash: everything up to the last whole chunk) alike. Camera frames come back decoded from PNG.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mcap.reader import SeekingReader
from mcap.records import Channel, Message, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap_protobuf.decoder import DecoderFactory
from PIL import Image

from l2r.episodes import schema
from l2r.episodes.body import BodyModel


@dataclass
class Episode:
    path: Path
    episode: dict[str, str]  # metadata "episode": run, actor, seed, difficulty, ...
    result: dict[str, str]  # metadata "result" (empty when the episode did not finish)
    body: BodyModel | None
    names: dict[str, tuple[str, ...]]  # muscles, ligaments, contacts, bodies
    steps: dict[str, np.ndarray] = field(default_factory=dict)  # Step fields, one row per step
    log_time: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3)))  # (steps, bodies, 3)
    quat: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 4)))  # (steps, bodies, 4) wxyz
    images: dict[str, np.ndarray] = field(default_factory=dict)  # uint8 (frames, 3, H, W) by observation field:
    # frame k is step k's; an interrupted file may hold fewer frames than steps
    complete: bool = False  # the file ended with its footer

    def __len__(self) -> int:
        return len(self.log_time)


def iter_records(path: str | Path):
    """The file's records in order, up to the first that cannot be read: an interrupted file
    ends at its last whole record, a damaged one (bad magic, a chunk that does not decompress)
    at the damage."""
    with open(path, "rb") as f:
        try:
            yield from StreamReader(f, record_size_limit=1 << 30).records
        except Exception:  # whatever the damage, what came before it stays readable
            return


def read_episode(path: str | Path) -> Episode:
    """Decode one episode file (``ValueError`` if it holds no l2r episode)."""
    path = Path(path)
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    decoders: dict[int, object] = {}
    factory = DecoderFactory()
    metadata: dict[str, dict[str, str]] = {}
    rows: list = []
    tf: dict[int, object] = {}
    frames: dict[str, list[np.ndarray]] = {}
    complete = False
    for record in iter_records(path):
        if isinstance(record, Schema):
            schemas[record.id] = record
        elif isinstance(record, Channel):
            channels[record.id] = record
        elif isinstance(record, Metadata):
            metadata[record.name] = dict(record.metadata)
        elif isinstance(record, Message) and record.channel_id in channels:
            channel = channels[record.channel_id]
            image = schemas.get(channel.schema_id) is not None and schemas[channel.schema_id].name == schema.IMAGE_MESSAGE
            if channel.topic not in (schema.TOPIC_STEP, schema.TOPIC_TF) and not image:
                continue
            if channel.id not in decoders:
                decoders[channel.id] = factory.decoder_for(channel.message_encoding, schemas.get(channel.schema_id))
            message = decoders[channel.id](record.data)
            if image:
                frames.setdefault(channel.topic.removeprefix("/"), []).append(_frame(message.data))
            elif channel.topic == schema.TOPIC_STEP:
                rows.append((record.log_time, message))
            else:
                tf[record.log_time] = message
        elif type(record).__name__ == "Footer":
            complete = True
    if schema.METADATA_EPISODE not in metadata and not rows:
        raise ValueError(f"{path}: not an l2r episode file (no episode metadata, no steps)")
    step_channel = next((c for c in channels.values() if c.topic == schema.TOPIC_STEP), None)
    names = {k: tuple(filter(None, step_channel.metadata.get(k, "").split(","))) for k in schema.NAME_KEYS} if step_channel else {}
    body = BodyModel.from_json(metadata["body"]["json"]) if "body" in metadata else None
    episode = Episode(path, metadata.get(schema.METADATA_EPISODE, {}), metadata.get(schema.METADATA_RESULT, {}),
                      body, names, images={name: np.stack(f) for name, f in frames.items()}, complete=complete)  # fmt: skip
    _fill(episode, rows, tf)
    return episode


def _frame(png: bytes) -> np.ndarray:
    """A PNG image as uint8 (3, H, W), channels first as the observation had it."""
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).transpose(2, 0, 1)


def _fill(episode: Episode, rows: list, tf: dict[int, object]) -> None:
    if not rows:
        return
    messages = [m for _, m in rows]
    episode.log_time = np.array([t for t, _ in rows], dtype=np.int64)
    episode.steps["step"] = np.array([m.step for m in messages], dtype=np.int64)
    for name, _ in schema.STEP_SCALARS:
        episode.steps[name] = np.array([getattr(m, name) for m in messages])
    for name, _ in schema.STEP_VECTORS:
        episode.steps[name] = np.array([list(getattr(m, name)) for m in messages])
    bodies = episode.names.get("bodies") or (episode.body.bodies if episode.body else ())
    index = {b: i for i, b in enumerate(bodies)}
    pos = np.full((len(rows), len(bodies), 3), np.nan)
    quat = np.full((len(rows), len(bodies), 4), np.nan)
    for k, (t, _) in enumerate(rows):
        message = tf.get(t)
        for transform in message.transforms if message is not None else ():
            i = index.get(transform.child_frame_id)
            if i is not None and transform.parent_frame_id == schema.GROUND_FRAME:
                tr, r = transform.translation, transform.rotation
                pos[k, i] = (tr.x, tr.y, tr.z)
                quat[k, i] = (r.w, r.x, r.y, r.z)
    episode.pos, episode.quat = pos, quat


def find_episode(directory: str | Path, **episode: str | int) -> Path | None:
    """The first episode file in ``directory`` whose "episode" metadata holds every item of
    ``episode`` (``kind="eval", actor=1, seed=0, policy_version=12``), or None."""
    wanted = {name: str(value) for name, value in episode.items()}
    for path in sorted(Path(directory).glob("*.mcap")):
        meta = episode_metadata(path).get("episode", {})
        if all(meta.get(name) == value for name, value in wanted.items()):
            return path
    return None


def episode_metadata(path: str | Path) -> dict[str, dict[str, str]]:
    """The metadata records of an episode file, by name: read through the summary's index in
    a complete file, by a scan in a damaged one."""
    try:
        with open(path, "rb") as f:
            return {m.name: dict(m.metadata) for m in SeekingReader(f).iter_metadata()}
    except Exception:  # no usable summary: scan what can be read
        return {r.name: dict(r.metadata) for r in iter_records(path) if isinstance(r, Metadata)}
