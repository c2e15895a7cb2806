"""Recordings for the log tests: one evaluation episode logged as an actor logs it, and what
`l2r view --save` makes of episode files."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import gymnasium
import rerun as rr

from l2r.actors.actor import ActorConfig, make_episode_logger, run_deterministic
from tests.conftest import ROOT


def logged_evaluation(config: ActorConfig, policy, env: gymnasium.Env, seed: int, version: int) -> Path:
    """The MCAP file of one deterministic episode of ``policy`` on ``env`` from ``seed``, logged
    by the logger ``config`` asks for (its directory: ``config.episode_log``) as an evaluator
    logs it; ``env`` is closed after."""
    logger = make_episode_logger(config)
    try:
        run_deterministic(policy, [env], [seed], env_id=config.env_id, record=lambda env, seed: logger.begin_episode(
            {"env_id": config.env_id, "seed": seed, "evaluation": True, "policy_version": version}))  # fmt: skip
    finally:
        env.close()
        logger.close()
    assert logger.stats["episodes_written"] == 1, logger.stats
    (path,) = Path(config.episode_log["directory"]).glob("*.mcap")
    return path


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
