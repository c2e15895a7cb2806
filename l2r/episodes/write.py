"""One episode's MCAP file: the static channels when it opens, blocks of steps and frames, the result.

The file is written as ``<name>.mcap.part`` and becomes ``<name>.mcap`` only in ``finish``
(after an fsync), so a ``.mcap`` is always whole. Each block is flushed to the OS when written,
so a crash loses at most the block in progress and the chunk not yet closed.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import build_file_descriptor_set

import l2r
from l2r.episodes import schema
from l2r.episodes.body import BodyModel
from l2r.episodes.encode import StepLayout, TransformEncoder, cdr_string, compressed_image

CHUNK_BYTES = 256 * 1024  # MCAP chunk size before compression (about 100 steps)


class EpisodeFile:
    """An episode file being written. ``metadata`` is the ``episode`` record; ``names`` the
    entry names of the Step vectors (muscles, ligaments, contacts, bodies). ``body`` None: a
    task without the runner's body (a camera task), whose file has no body channels."""

    def __init__(
        self,
        path: Path,
        body: BodyModel | None,
        metadata: dict[str, str],
        names: dict[str, Sequence[str]],
        start_ns: int,
        obstacles: Sequence[tuple[float, float, float]] = (),
        chunk_bytes: int = CHUNK_BYTES,
        transforms: TransformEncoder | None = None,
        body_json: str | None = None,
    ):
        self.path, self.start_ns, self.names = path, start_ns, names
        self.part = path.with_name(path.name + ".part")
        self.file = open(self.part, "wb")
        try:  # a header the disk refuses leaves no .part behind
            w = self.writer = Writer(self.file, chunk_size=chunk_bytes, compression=CompressionType.ZSTD)
            w.start(profile=schema.PROFILE, library=f"l2r {l2r.__version__}")
            w.add_metadata(schema.METADATA_EPISODE, metadata)
            self.tf: int | None = None
            if body is not None:
                self.transforms = transforms or TransformEncoder(body.bodies)
                w.add_metadata("body", {"json": body_json or body.to_json()})
                string = w.register_schema(schema.STRING_SCHEMA_NAME, "ros2msg", schema.STRING_SCHEMA)
                robot = w.register_channel(schema.TOPIC_ROBOT, "cdr", string)
                w.add_message(robot, start_ns, cdr_string(body.urdf(obstacles)), start_ns)
                scene_update = body.scene_update(start_ns, obstacles)
                scene = w.register_channel(schema.TOPIC_SCENE, "protobuf", _register(w, type(scene_update)))
                w.add_message(scene, start_ns, scene_update.SerializeToString(), start_ns)
                self.tf = w.register_channel(schema.TOPIC_TF, "protobuf", _register(w, FrameTransforms))
            self.step: int | None = None  # registered with the first block, when the vector sizes are known
            self.images: dict[str, int] = {}  # image channels by field, registered with the first block too
            self.file.flush()
        except BaseException:
            self.discard()
            raise

    def write_block(self, layout: StepLayout, block: np.ndarray, pos: np.ndarray | None, quat: np.ndarray | None,
                    first_step: int, count: int, images: dict[str, np.ndarray]) -> None:  # fmt: skip
        """Rows ``[0, count)`` of a block: Step rows, body positions and wxyz quaternions (None
        without a body), and frames (count, 3, H, W) by image field, encoded here as PNG."""
        w = self.writer
        if self.step is None:
            sid = w.register_schema(schema.STEP_MESSAGE, "protobuf", schema.step_schema())
            names = {k: ",".join(v) for k, v in self.names.items()}
            self.step = w.register_channel(schema.TOPIC_STEP, "protobuf", sid, names)
            for field in images:
                self.images[field] = w.register_channel(schema.image_topic(field), "protobuf",
                                                        _register(w, CompressedImage))  # fmt: skip
        times = (self.start_ns + np.rint(block["time"][:count] * 1e9).astype(np.int64)).tolist()
        transforms = self.transforms.encode_block(times, pos[:count], quat[:count]) if self.tf is not None else None
        for i, message in enumerate(layout.messages(block, first_step, count)):
            t, sequence = times[i], first_step + i
            if transforms is not None:
                w.add_message(self.tf, t, transforms[i], t, sequence=sequence)
            w.add_message(self.step, t, message, t, sequence=sequence)
            for field, frames in images.items():  # after its step: a cut file has no frame without one
                w.add_message(self.images[field], t, compressed_image(t, field, frames[i]), t, sequence=sequence)
        self.file.flush()

    def finish(self, result: dict[str, Any]) -> None:
        """Write the ``result`` record, the summary and the footer; rename to the final name."""
        self.writer.add_metadata(schema.METADATA_RESULT, {k: text(v) for k, v in result.items()})
        self.writer.finish()
        self.file.flush()
        os.fsync(self.file.fileno())
        self.file.close()
        os.replace(self.part, self.path)

    def discard(self) -> None:
        """Give the episode up: close and remove the partial file."""
        try:
            self.file.close()
        except OSError:
            pass  # a full disk refusing what the file still buffered: given up with it
        self.part.unlink(missing_ok=True)


def text(value: Any) -> str:
    """A metadata value: floats exactly (repr), booleans as true/false."""
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    return str(value)


@functools.cache
def _descriptor_set(message_class: type) -> bytes:
    return build_file_descriptor_set(message_class).SerializeToString()


def _register(writer: Writer, message_class: type) -> int:
    return writer.register_schema(message_class.DESCRIPTOR.full_name, "protobuf", _descriptor_set(message_class))
