"""Making a rename or a deletion survive a power cut: what the learner's checkpoints and the
replay server's snapshots, write-ahead log and actor ids share."""

from __future__ import annotations

import os
from pathlib import Path
from typing import BinaryIO, Callable


def fsync_directory(directory: Path) -> None:
    """Make the names created, renamed or deleted in ``directory`` durable."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def write_durably(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """Replace ``path`` with what ``write`` writes into the open file it is given, so that a crash
    at any moment leaves the old file or the new one whole: a temporary file, fsynced, renamed
    over ``path``, and the rename itself made durable."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    fsync_directory(path.parent)
