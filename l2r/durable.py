"""Making a rename or a deletion survive a power cut, and saying in one line why a write did not:
what the learner's checkpoints, the replay server's snapshots, write-ahead log and actor ids, the
episode logs and `l2r up`'s metrics share.

A write that fails for want of a working disk (full, read-only, failing, or its directory deleted:
`DISK_ERRORS`) is not a bug, and a traceback per attempt buries the one thing to say. Writers
catch these errors and log `disk_failure(error, path)` once per cause (`FailureLog`), then go on
without the write where the process can.
"""

from __future__ import annotations

import errno
import logging
import os
import shutil
import sys
from pathlib import Path
from typing import IO, BinaryIO, Callable

# What a disk, not the program, makes fail: no space or quota left, a read-only or failing device,
# a directory deleted under a running process.
DISK_ERRORS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EIO, errno.ENOENT})
MB = 1e6


def free_bytes(path: Path) -> int:
    """Bytes free to an unprivileged writer on the file system holding `path` (or its nearest
    ancestor that exists)."""
    path = Path(path).absolute()
    while not path.exists():
        path = path.parent
    return shutil.disk_usage(path).free


def disk_failure(error: OSError, path: Path | str | None = None) -> str:
    """Why a write failed, in one line that names the path: `disk full at PATH: N MB free`."""
    path = Path(path or error.filename or ".")
    if error.errno in (errno.ENOSPC, errno.EDQUOT):
        return f"disk full at {path}: {free_bytes(path) / MB:.1f} MB free"
    if error.errno == errno.EROFS:
        return f"read-only file system at {path}"
    if error.errno == errno.ENOENT:
        return f"{path} no longer exists (deleted while the run wrote to it?)"
    return f"{os.strerror(error.errno) if error.errno else error} at {path}"


def close_quietly(file: IO | None) -> None:
    """Close a file whose writes failed: what it still buffers is lost, and so is the error."""
    try:
        if file is not None:
            file.close()
    except OSError:
        pass


class FailureLog:
    """Logs each cause of failed writes once (an errno and a directory), and once again when
    writes there succeed after it."""

    def __init__(self, logger: logging.Logger, what: str):
        self.logger, self.what = logger, what
        self.failing: dict[tuple[int | None, Path], str] = {}
        self.count = 0

    def failed(self, error: OSError, path: Path | str, consequence: str) -> None:
        """Note a failed write to `path`; the first of its cause is logged with `consequence`."""
        self.count += 1
        cause = (error.errno, Path(path).parent)
        if cause not in self.failing:
            self.failing[cause] = disk_failure(error, path)
            self.logger.error("%s: %s; %s", self.what, self.failing[cause], consequence)

    def succeeded(self) -> None:
        """A write went through: each cause logged as failing is logged as cleared."""
        for reason in self.failing.values():
            self.logger.info("%s: writing again (it failed: %s)", self.what, reason)
        self.failing.clear()


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


class FileLogHandler(logging.FileHandler):
    """A log file (`l2r up`'s logs/up.log) whose failed writes are one line on `console` per spell
    of failing, not a traceback per record; the records still reach the console meanwhile."""

    def __init__(self, path: Path, console: logging.Handler):
        super().__init__(path)
        self.console = console
        self.failing: str | None = None
        self._failed_now = False

    def emit(self, record: logging.LogRecord) -> None:
        self._failed_now = False
        super().emit(record)
        if self.failing and not self._failed_now:
            self.console.handle(logging.makeLogRecord({"name": record.name, "levelno": logging.INFO,
                                                       "levelname": "INFO", "msg": f"{self.baseFilename}: writing again"}))
            self.failing = None

    def handleError(self, record: logging.LogRecord) -> None:
        error = sys.exc_info()[1]
        if not (isinstance(error, OSError) and error.errno in DISK_ERRORS):
            super().handleError(record)
            return
        self._failed_now = True
        if self.failing is None:
            self.failing = disk_failure(error, self.baseFilename)
            self.console.handle(logging.makeLogRecord({
                "name": record.name, "levelno": logging.ERROR, "levelname": "ERROR",
                "msg": f"{self.failing}: {Path(self.baseFilename).name} misses lines until a write succeeds "
                       "(the console has them)"}))
