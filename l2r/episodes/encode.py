"""Fast protobuf and CDR encoders for the per-step messages.

A logged step must cost the stepping thread next to nothing, so the two per-step messages are
laid out in advance and filled with numpy instead of being built field by field:

- ``StepLayout``: ``l2r.episodes.Step`` minus its step index is fixed-size once the vector
  lengths are known, so a block of steps is one numpy structured array whose tag and length
  bytes are filled once; a step's message is a slice of its bytes.
- ``TransformEncoder``: ``foxglove.FrameTransforms`` for every body is a byte template with the
  frame names in place; the timestamp and the poses are scattered into it.

Both produce standard protobuf that the registered schemas decode (the tests check this
against the protobuf library).
"""

from __future__ import annotations

import struct
from collections.abc import Iterator, Sequence

import numpy as np

from l2r.episodes.schema import GROUND_FRAME, STEP_FIELD_NUMBER, STEP_SCALARS, STEP_VECTORS, WORLD_FRAME

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

    ``sizes`` gives the length of each vector field (missing or 0: the field is left out).
    Fill a row through ``block[name][i] = value``; ``messages`` turns rows into protobuf.
    """

    def __init__(self, sizes: dict[str, int]):
        fields: list[tuple] = []
        self._headers: list[tuple[str, bytes]] = []
        for name, number in STEP_SCALARS:
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


class TransformEncoder:
    """``foxglove.FrameTransforms``: ``world -> ground`` (z up -> the model's y up), then
    ``ground -> body`` for each body, all stamped with the step's time."""

    # The model's y-up frame seen from a z-up world: +90 degrees about x.
    GROUND_IN_WORLD = (0.0, 0.0, 0.0, np.sqrt(0.5), 0.0, 0.0, np.sqrt(0.5))  # x y z qx qy qz qw

    def __init__(self, bodies: Sequence[str]):
        self.bodies = tuple(bodies)
        self._templates: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def encode(self, time_ns: int, pos: np.ndarray, quat_wxyz: np.ndarray) -> bytes:
        """pos (bodies, 3), quat_wxyz (bodies, 4) in the ground frame."""
        ts = timestamp(time_ns)
        template, ts_at, values_at = self._templates.get(len(ts)) or self._build(len(ts))
        buf = template.copy()
        buf[ts_at] = np.frombuffer(ts, np.uint8)
        values = np.empty((len(self.bodies), 7), "<f8")
        values[:, :3] = pos
        values[:, 3:6] = quat_wxyz[:, 1:]
        values[:, 6] = quat_wxyz[:, 0]
        buf[values_at] = values.view(np.uint8).reshape(-1)
        return buf.tobytes()

    def _build(self, ts_len: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        out = bytearray()
        ts_at: list[int] = []
        values_at: list[int] = []
        frames = [(WORLD_FRAME, GROUND_FRAME, self.GROUND_IN_WORLD)]
        frames += [(GROUND_FRAME, body, None) for body in self.bodies]
        for parent, child, fixed in frames:
            vec3 = b"".join(_tag(i, _FIXED64) + bytes(8) for i in (1, 2, 3))
            quat = b"".join(_tag(i, _FIXED64) + bytes(8) for i in (1, 2, 3, 4))
            head = _tag(1, _LEN) + varint(ts_len)
            body = (
                head + bytes(ts_len)
                + _len_field(2, parent.encode()) + _len_field(3, child.encode())
                + _len_field(4, vec3) + _len_field(5, quat)
            )  # fmt: skip
            start = len(out) + len(_tag(1, _LEN) + varint(len(body)))
            out += _tag(1, _LEN) + varint(len(body)) + body
            ts_at.append(start + len(head))
            # Each double sits after its one-byte tag; the vector and quaternion end the entry.
            end = start + len(body)
            offsets = [end - 36 - 2 - 27 + 1 + 9 * i for i in range(3)] + [end - 36 + 1 + 9 * i for i in range(4)]
            if fixed is None:
                values_at += offsets
            else:
                for at, value in zip(offsets, fixed):
                    out[at : at + 8] = struct.pack("<d", value)
        template = np.frombuffer(bytes(out), np.uint8).copy()
        ts_index = (np.array(ts_at)[:, None] + np.arange(ts_len)).reshape(-1)
        ts_index = ts_index.reshape(len(ts_at), ts_len)
        values_index = (np.array(values_at)[:, None] + np.arange(8)).reshape(-1)
        self._templates[ts_len] = (template, ts_index, values_index)
        return self._templates[ts_len]
