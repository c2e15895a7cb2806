"""A replay shard's write-ahead log: every chunk it stores is on disk before it is acknowledged.

Chunks are appended, as the bytes that arrived, to numbered segment files
``replay-shard<k>.wal.<n>`` beside the snapshot. A record is

    u32 length | u32 CRC-32 of the payload | payload        (little-endian)

``append`` writes into a buffer; ``flush`` hands the buffer to the operating system and returns
what has to be fsynced, and ``sync`` fsyncs it. The shard calls ``flush`` under the lock it
stores chunks under and builds its ack at the same moment, then fsyncs outside the lock, so
inserts go on meanwhile and an ack names only chunks already on disk. A snapshot starts a new
segment when it takes its copy (``rotate``); once the snapshot file is durable the segments
before it are deleted, so the log holds about one snapshot interval. At start the shard
replays the segments from its snapshot's on (``records``); a record cut short by the crash
ends its segment.

A write or fsync that fails (a full disk) leaves the log ``failed``: the shard stops storing and
acknowledging. The log keeps the payloads appended since its last good fsync, and ``retry``
writes them to a new segment (the failed one may end in a record cut short) and fsyncs it; once
that succeeds, the log is whole again and the shard acknowledges again.
"""

from __future__ import annotations

import logging
import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from l2r.durable import close_quietly, fsync_directory

log = logging.getLogger("l2r.replay.wal")

HEADER = struct.Struct("<II")
BUFFER_BYTES = 1 << 20


@dataclass
class SyncPoint:
    """What one ``sync`` must make durable: segments closed by ``rotate`` and the current one."""

    closed: list[BinaryIO] = field(default_factory=list)
    current: BinaryIO | None = None
    directory: bool = False  # a segment was created since the last sync
    payloads: list[bytes] = field(default_factory=list)  # appended since the last flush, kept until synced


class WriteAheadLog:
    """See the module docstring. Not thread-safe except as described there."""

    def __init__(self, directory: Path, shard: int):
        self.directory = Path(directory)
        self.prefix = f"replay-shard{shard}.wal."
        self.segment = -1  # number of the segment being written
        self.failed: str | None = None  # the error that stopped the log; nothing is acknowledged after it
        self._file: BinaryIO | None = None
        self._pending = SyncPoint()
        self._unsynced: list[bytes] = []  # while failed: every payload not known durable, in order
        self._abandoned: list[BinaryIO] = []  # while failed: segments a write or fsync failed on

    def segments(self) -> list[int]:
        """Numbers of the segments on disk, ascending."""
        found = []
        for path in self.directory.glob(self.prefix + "*"):
            suffix = path.name[len(self.prefix):]
            if suffix.isdigit():
                found.append(int(suffix))
        return sorted(found)

    def path(self, segment: int) -> Path:
        return self.directory / f"{self.prefix}{segment}"

    def records(self, first: int) -> Iterator[bytes]:
        """The payloads of every segment numbered ``first`` or above, in the order written."""
        for segment in (s for s in self.segments() if s >= first):
            path = self.path(segment)
            with open(path, "rb") as f:
                while header := f.read(HEADER.size):
                    length, crc = HEADER.unpack(header) if len(header) == HEADER.size else (0, None)
                    payload = f.read(length)
                    if crc is None or len(payload) < length or zlib.crc32(payload) != crc:
                        end = f.tell() - len(header) - len(payload)
                        log.warning("%s: %d bytes after the last whole record ignored (cut short by a crash)",
                                    path.name, path.stat().st_size - end)
                        break
                    yield payload

    def start(self, after: int) -> None:
        """Begin writing a new segment numbered above ``after`` and above every segment on disk."""
        self.directory.mkdir(parents=True, exist_ok=True)
        self._open(max([after, *self.segments()]) + 1)

    def _open(self, segment: int) -> None:
        self._file = open(self.path(segment), "xb", buffering=BUFFER_BYTES)
        self.segment = segment
        self._pending.directory = True

    def append(self, payload: bytes) -> None:
        self._pending.payloads.append(payload)
        self._file.write(HEADER.pack(len(payload), zlib.crc32(payload)))
        self._file.write(payload)

    def flush(self) -> SyncPoint:
        """Hand what was appended to the OS; return what ``sync`` must fsync to make it durable."""
        self._file.flush()
        point, self._pending = self._pending, SyncPoint()
        point.current = self._file
        return point

    def sync(self, point: SyncPoint) -> None:
        """fsync a ``flush``'s files (outside the shard's lock); raises OSError."""
        for f in point.closed:
            os.fsync(f.fileno())
            f.close()
        os.fsync(point.current.fileno())
        if point.directory:
            fsync_directory(self.directory)

    def rotate(self) -> int:
        """Start the next segment (a snapshot is being taken); return its number. Raises OSError,
        and then changes nothing."""
        self._file.flush()
        previous = self._file
        self._open(self.segment + 1)
        self._pending.closed.append(previous)
        return self.segment

    def delete_before(self, segment: float) -> None:
        """Drop the segments a durable snapshot has made unnecessary."""
        for old in self.segments():
            if old < segment:
                self.path(old).unlink(missing_ok=True)

    def fail(self, error: OSError, point: SyncPoint | None = None) -> None:
        """Stop the log after ``error``, keeping what it has not made durable: the payloads of a
        ``point`` whose sync failed, and those appended since. Called under the shard's lock."""
        self.failed = f"{type(error).__name__}: {error}"
        self._unsynced = (point.payloads if point else []) + self._pending.payloads
        self._abandoned += [*(point.closed if point else []), *self._pending.closed, self._file]
        self._pending = SyncPoint()

    def retry(self) -> int:
        """After ``fail``: write the payloads kept to a new segment and fsync it; return how many.
        Raises OSError, and then stays failed. Called under the shard's lock."""
        try:
            self._open(self.segment + 1)
            for payload in self._unsynced:
                self.append(payload)
            self.sync(self.flush())
        except OSError:
            if self._file not in self._abandoned:  # the new segment: acknowledged nothing, frees its space
                close_quietly(self._file)
                self.path(self.segment).unlink(missing_ok=True)
            self._file, self._pending = self._abandoned[-1], SyncPoint()
            raise
        for f in self._abandoned:
            close_quietly(f)  # what they still buffer is in the new segment too: replayed as duplicates
        written, self._unsynced, self._abandoned, self.failed = len(self._unsynced), [], [], None
        return written

    def close(self) -> None:
        self.sync(self.flush())
        self._file.close()
