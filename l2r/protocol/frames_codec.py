"""Lossless compression of the frames an experience chunk carries (protocol version 3).

A camera chunk's frames are most of its bytes (1.4 MB for 64 steps of 84 x 84 RGB), and
consecutive frames of one episode are much alike. zstd at level 1 over a field's rows as one
zstd frame finds that likeness (a window of 512 KiB spans 24 frames of 84 x 84): 3.5x on
walker, 32x on cartpole, for 0.8 - 3 ms of the actor's CPU per chunk, where compressing each
frame alone gains 1.6 - 1.7x (bench/frame_compression.py, docs/performance.md).

On the wire a compressed field is an array map with a fourth key, ``codec``: the data are the
zstd frame of the field's C-order bytes, with its content size and checksum in it.
``inflate`` checks the content size against the declared dtype and shape before it allocates
anything, so a frame that claims more (a decompression bomb) or other than its array is
refused without being decompressed.
"""

from __future__ import annotations

import threading

import numpy as np
import zstandard

from l2r.protocol.errors import ProtocolError

ZSTD = "zstd"
CODECS = (ZSTD,)
"""The codecs a receiver of this version decompresses."""
LEVEL = 1
"""zstd's level for frames: levels 2 and 3 save 5 - 7 % more bytes on walker for 25 - 85 % more
CPU, and nothing on cartpole (docs/performance.md)."""


class FrameCompressor:
    """Compresses the rows of an image field into one zstd frame at ``level``. Not thread-safe
    (zstd's context is reused): one per thread that encodes."""

    codec = ZSTD

    def __init__(self, level: int = LEVEL):
        self._zstd = zstandard.ZstdCompressor(level=level, write_checksum=True, write_content_size=True)

    def compress(self, rows: np.ndarray) -> bytes:
        return self._zstd.compress(np.ascontiguousarray(rows).reshape(-1).view(np.uint8))


_local = threading.local()  # a decompressor per thread: zstd's context is reused, not shared


def _decompressor() -> zstandard.ZstdDecompressor:
    if not hasattr(_local, "zstd"):
        _local.zstd = zstandard.ZstdDecompressor()
    return _local.zstd


def inflate(where: str, codec: object, data: bytes | memoryview, nbytes: int) -> bytes:
    """The ``nbytes`` bytes that ``data`` compressed with ``codec`` holds, or ProtocolError:
    ``unknown_codec``, ``bad_array`` for a frame that declares another size (checked before
    decompressing), ``corrupt`` for one that does not decompress to what it declares."""
    if codec not in CODECS:
        raise ProtocolError(f"{where}: codec {codec!r}, this side decompresses {', '.join(CODECS)}", "unknown_codec")
    try:
        declared = zstandard.frame_content_size(data)
    except zstandard.ZstdError as e:
        raise ProtocolError(f"{where}: not a zstd frame ({e})", "corrupt") from None
    if declared != nbytes:
        said = "no size" if declared < 0 else f"{declared} bytes"
        raise ProtocolError(f"{where}: the zstd frame declares {said}, its dtype and shape need {nbytes}",
                            "bad_array")
    try:
        out = _decompressor().decompress(data, max_output_size=nbytes, allow_extra_data=False)
    except zstandard.ZstdError as e:
        raise ProtocolError(f"{where}: the zstd frame does not decompress ({e})", "corrupt") from None
    if len(out) != nbytes:
        raise ProtocolError(f"{where}: the zstd frame decompresses to {len(out)} bytes, not {nbytes}", "corrupt")
    return out
