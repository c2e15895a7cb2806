"""Atomic replay snapshots: an uncompressed .npz written under a temporary name, fsynced, renamed."""

from __future__ import annotations

import json
import logging
import os
import time
import zipfile
from pathlib import Path

import numpy as np

from l2r.durable import write_durably

log = logging.getLogger("l2r.replay.snapshot")


def snapshot_path(directory: Path, shard: int) -> Path:
    return Path(directory) / f"replay-shard{shard}.npz"


def write(path: Path, arrays: dict[str, np.ndarray], meta: dict) -> int:
    """Write ``arrays`` and ``meta`` to ``path`` atomically; return the bytes written."""
    write_durably(path, lambda f: np.savez(f, meta=np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays))
    return path.stat().st_size


def read(path: Path) -> tuple[dict[str, np.ndarray], dict] | None:
    """The arrays and meta of a snapshot, or None if there is none.

    A snapshot that cannot be read is moved aside (kept for inspection) and None returned,
    so a damaged file never stops the server or gets overwritten.
    """
    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
        meta = json.loads(arrays.pop("meta").tobytes())
        return arrays, meta
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError) as e:
        aside = path.with_name(f"{path.name}.corrupt-{int(time.time())}")
        os.replace(path, aside)
        log.error("snapshot %s is unreadable (%s: %s); moved to %s, starting empty", path, type(e).__name__, e, aside)
        return None
