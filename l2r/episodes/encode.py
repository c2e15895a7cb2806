"""Fast protobuf and CDR encoders for the per-step messages.

Logging runs on the actor's CPU, so the two per-step messages are laid out in advance and
filled with numpy a block of steps at a time, instead of being built field by field (which
costs about 50 µs a step for the frame transforms alone):

- ``StepLayout``: ``l2r.episodes.Step`` minus its step index is fixed-size once the vector
  lengths are known, so a block of steps is one numpy structured array whose tag and length
  bytes are filled once; the actor copies a step into its row, and the row's bytes are the
  message.
- ``TransformEncoder``: ``foxglove.FrameTransforms`` for every body is a byte template with the
  frame names in place; the timestamps and the poses are scattered into it.
- ``compressed_image``: a camera frame as ``foxglove.CompressedImage`` holding a PNG (Pillow's
  encoder at its fastest level: the writer thread shares the actor's CPU with the renderer).

Both produce standard protobuf that the registered schemas decode (the tests check this
against the protobuf library).
"""

from __future__ import annotations

import io
import struct
from collections.abc import Iterator, Sequence

import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from PIL import Image

from l2r.episodes.schema import (
    GROUND_FRAME, IMAGE_FORMAT, STEP_FIELD_NUMBER, STEP_SCALARS, STEP_VECTORS, WORLD_FRAME,
)

_FIXED64, _LEN, _VARINT = 1, 2, 0


def varint(value: int) -> bytes:
    if value < 0x80:
        return bytes((value,))
    out = bytearray()
    while value >= 0x80:
        out.append(value & 0x7F | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _tag(number: int, wire: int) -> bytes:
    return varint(number << 3 | wire)


def _len_field(number: int, payload: bytes) -> bytes:
    return _tag(number, _LEN) + varint(len(payload)) + payload


def cdr_string(text: str) -> bytes:
    """A ROS 2 ``std_msgs/msg/String`` in little-endian CDR."""
    data = text.encode() + b"\0"
    return b"\x00\x01\x00\x00" + struct.pack("<I", len(data)) + data


def timestamp(ns: int) -> bytes:
    """A ``google.protobuf.Timestamp`` message body for ``ns`` nanoseconds since the epoch."""
    seconds, nanos = divmod(int(ns), 1_000_000_000)
    out = _tag(1, _VARINT) + varint(seconds) if seconds else b""
    return out + (_tag(2, _VARINT) + varint(nanos) if nanos else b"")


class StepLayout:
    """Blocks of ``l2r.episodes.Step`` rows as numpy structured arrays.

    ``sizes`` gives the length of each vector field (missing or 0: the field is left out);
    ``scalars`` the scalar fields to keep (all by default). Fill a row through
    ``block[name][i] = value``; ``messages`` turns rows into protobuf.
    """

    def __init__(self, sizes: dict[str, int], scalars: Sequence[str] = tuple(name for name, _ in STEP_SCALARS)):
        fields: list[tuple] = []
        self._headers: list[tuple[str, bytes]] = []
        for name, number in STEP_SCALARS:
            if name not in scalars:
                continue
            self._headers.append((f"_{name}", _tag(number, _FIXED64)))
            fields += [(f"_{name}", f"V{len(self._headers[-1][1])}"), (name, "<f8")]
        for name, number in STEP_VECTORS:
            n = int(sizes.get(name, 0))
            if n:
                self._headers.append((f"_{name}", _tag(number, _LEN) + varint(8 * n)))
                fields += [(f"_{name}", f"V{len(self._headers[-1][1])}"), (name, "<f8", (n,))]
        self.dtype = np.dtype(fields)
        self.sizes = {name: int(sizes.get(name, 0)) for name, _ in STEP_VECTORS}

    def new_block(self, rows: int) -> np.ndarray:
        block = np.zeros(rows, self.dtype)
        for name, header in self._headers:
            block[name] = np.void(header)
        return block

    def messages(self, block: np.ndarray, first_step: int, count: int) -> Iterator[bytes]:
        raw, size = block[:count].tobytes(), self.dtype.itemsize
        tag = _tag(STEP_FIELD_NUMBER, _VARINT)
        for i in range(count):
            yield tag + varint(first_step + i) + raw[i * size : (i + 1) * size]


PNG_LEVEL = 1  # zlib's fastest: 84 x 84 frames in half the time of the default 6, 7 % larger


def png(frame: np.ndarray) -> bytes:
    """A uint8 (3, H, W) frame, channels first, as PNG."""
    out = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(frame.transpose(1, 2, 0))).save(out, "PNG", compress_level=PNG_LEVEL)
    return out.getvalue()


def compressed_image(time_ns: int, field: str, frame: np.ndarray) -> bytes:
    """``foxglove.CompressedImage`` of one frame: PNG data, the field's name as its frame id."""
    message = CompressedImage(frame_id=field, data=png(frame), format=IMAGE_FORMAT)
    message.timestamp.FromNanoseconds(int(time_ns))
    return message.SerializeToString()


class TransformEncoder:
    """``foxglove.FrameTransforms``: ``world -> ground`` (z up -> the model's y up), then
    ``ground -> body`` for each body, all stamped with the step's time."""

    # The model's y-up frame seen from a z-up world: +90 degrees about x.
    GROUND_IN_WORLD = (0.0, 0.0, 0.0, np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5))  # x y z qx qy qz qw

    def __init__(self, bodies: Sequence[str]):
        self.bodies = tuple(bodies)
        self._templates: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def encode(self, time_ns: int, pos: np.ndarray, quat_wxyz: np.ndarray) -> bytes:
        """One message: pos (bodies, 3), quat_wxyz (bodies, 4) in the ground frame."""
        return self.encode_block([time_ns], pos[None], quat_wxyz[None])[0]

    def encode_block(self, times_ns: Sequence[int], pos: np.ndarray, quat_wxyz: np.ndarray) -> list[bytes]:
        """One message per step: pos (steps, bodies, 3), quat_wxyz (steps, bodies, 4)."""
        n = len(times_ns)
        values = np.empty((n, len(self.bodies), 7), "<f8")
        values[..., :3] = pos
        values[..., 3:6] = quat_wxyz[..., 1:]
        values[..., 6] = quat_wxyz[..., 0]
        value_bytes = values.view(np.uint8).reshape(n, -1)
        stamps = [timestamp(t) for t in times_ns]
        out: list[bytes] = [b""] * n
        for ts_len in set(map(len, stamps)):  # one or two lengths in a block
            rows = [i for i, ts in enumerate(stamps) if len(ts) == ts_len]
            template, ts_at, values_at = self._templates.get(ts_len) or self._build(ts_len)
            buf = np.tile(template, (len(rows), 1))
            ts = np.frombuffer(b"".join(stamps[i] for i in rows), np.uint8).reshape(len(rows), 1, ts_len)
            buf[:, ts_at] = ts
            buf[:, values_at] = value_bytes[rows]
            raw, size = buf.tobytes(), template.size
            for k, i in enumerate(rows):
                out[i] = raw[k * size : (k + 1) * size]
        return out

    def _build(self, ts_len: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The message for timestamps of ``ts_len`` bytes, with the offsets of the timestamps
        and of the pose doubles (x y z qx qy qz qw per body) to fill in."""
        out = bytearray()
        ts_at: list[int] = []
        values_at: list[int] = []
        frames = [(WORLD_FRAME, GROUND_FRAME, self.GROUND_IN_WORLD)]
        frames += [(GROUND_FRAME, body, None) for body in self.bodies]
        for parent, child, fixed in frames:
            head = _tag(1, _LEN) + varint(ts_len)
            names = _len_field(2, parent.encode()) + _len_field(3, child.encode())
            vec3_head, quat_head = _tag(4, _LEN) + varint(27), _tag(5, _LEN) + varint(36)
            entry_len = len(head) + ts_len + len(names) + len(vec3_head) + 27 + len(quat_head) + 36
            out += _tag(1, _LEN) + varint(entry_len) + head
            ts_at.append(len(out))
            out += bytes(ts_len) + names + vec3_head
            vec3_at = len(out)
            out += b"".join(_tag(i, _FIXED64) + bytes(8) for i in (1, 2, 3)) + quat_head
            quat_at = len(out)
            out += b"".join(_tag(i, _FIXED64) + bytes(8) for i in (1, 2, 3, 4))
            # each double follows its one-byte tag
            offsets = [vec3_at + 1 + 9 * i for i in range(3)] + [quat_at + 1 + 9 * i for i in range(4)]
            if fixed is None:
                values_at += offsets
            else:
                for at, value in zip(offsets, fixed):
                    out[at : at + 8] = struct.pack("<d", value)
        template = np.frombuffer(bytes(out), np.uint8).copy()
        ts_index = np.array(ts_at)[:, None] + np.arange(ts_len)
        values_index = (np.array(values_at)[:, None] + np.arange(8)).reshape(-1)
        self._templates[ts_len] = (template, ts_index, values_index)
        return self._templates[ts_len]
