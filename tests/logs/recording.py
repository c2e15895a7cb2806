"""What tests read of a Rerun recording that `l2r view --save` wrote."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import rerun as rr

from tests.conftest import ROOT


def saved_view(episodes: Path, out: Path) -> rr.chunk.RrdReader:
    """`l2r view EPISODES --save OUT`, run as a user runs it, and the recording it wrote."""
    result = subprocess.run([sys.executable, "-m", "l2r.cli", "view", str(episodes), "--save", str(out)],
                            capture_output=True, text=True, timeout=60, cwd=ROOT)  # fmt: skip
    assert result.returncode == 0, result.stderr
    return rr.chunk.RrdReader(out)


def view_origins(reader: rr.chunk.RrdReader) -> set[str]:
    """The entity paths the views of every layout in the recording are rooted at."""
    views = [c.to_record_batch() for store in reader.blueprints() for c in reader.store(store=store).stream().to_chunks()]
    return {o for v in views for n in v.schema.names if n.endswith(":space_origin")
            for row in v.column(n).to_pylist() for o in row or ()}  # fmt: skip
