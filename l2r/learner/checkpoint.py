"""Learner checkpoints: one file per run, replaced atomically.

A checkpoint is a `torch.save` of one dict (loadable with `weights_only=True`):

    format          "l2r-learner-checkpoint"
    format_version  1
    sac_config      SACConfig as a dict (algorithm settings the state was trained with)
    obs_dim, act_dim
    policy_spec     the architecture spec of the policy (see l2r.policy)
    train_state     TrainState.state_dict(): actor, critic, target_critic and their Adam
                    states, log_alpha, updates, version, extra counters
    saved_at        wall-clock time of the save (s since the epoch)

It lives at `<run_dir>/learner/checkpoint.pt`. It is written to a temporary file in the same
directory, flushed to disk, then renamed over the old one, so a crash during a save leaves
the previous checkpoint intact.
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from l2r.learner.sac import SACConfig, TrainState, init_state
from l2r.policy import Policy, build_policy

FORMAT = "l2r-learner-checkpoint"
FORMAT_VERSION = 1
RELATIVE_PATH = Path("learner") / "checkpoint.pt"


class CheckpointError(RuntimeError):
    """A checkpoint that is missing, unreadable or not one of ours; the message says which."""


def checkpoint_path(run_dir: str | Path) -> Path:
    """Where the learner of a run keeps its checkpoint."""
    return Path(run_dir) / RELATIVE_PATH


def find_checkpoint(path_or_run_dir: str | Path) -> Path:
    """The checkpoint file named, or the one inside a run directory; CheckpointError if none."""
    path = Path(path_or_run_dir)
    if path.is_dir():
        for candidate in (checkpoint_path(path), path / RELATIVE_PATH.name):
            if candidate.is_file():
                return candidate
        raise CheckpointError(f"no learner checkpoint in {path} (looked for {RELATIVE_PATH})")
    if not path.is_file():
        raise CheckpointError(f"no such checkpoint: {path}")
    return path


def save_checkpoint(path: str | Path, state: TrainState, config: SACConfig, obs_dim: int, act_dim: int) -> Path:
    """Write the training state to `path` atomically (temporary file, fsync, rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": FORMAT, "format_version": FORMAT_VERSION, "sac_config": config.to_dict(),
        "obs_dim": obs_dim, "act_dim": act_dim, "policy_spec": dict(state.actor.spec),
        "train_state": state.state_dict(), "saved_at": time.time(),
    }
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(payload, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


@dataclass
class Checkpoint:
    """A loaded checkpoint: settings, shapes and the saved training state."""

    path: Path
    config: SACConfig
    obs_dim: int
    act_dim: int
    policy_spec: dict
    train_state: dict
    saved_at: float

    @property
    def version(self) -> int:
        return int(self.train_state["version"])

    @property
    def updates(self) -> int:
        return int(self.train_state["updates"])

    def policy(self, device: str | torch.device = "cpu") -> Policy:
        """The trained policy, ready for `act` (evaluation mode, on `device`)."""
        policy = build_policy(self.policy_spec)
        policy.load_state_dict(self.train_state["actor"])
        return policy.to(device).eval()

    def restore(self, device: str | torch.device = "cpu") -> TrainState:
        """The full training state (networks, optimizers, alpha, counters) on `device`."""
        state = init_state(self.config, self.obs_dim, self.act_dim, device)
        state.load_state_dict(self.train_state)
        return state


def load_checkpoint(path_or_run_dir: str | Path, map_location: str | torch.device = "cpu") -> Checkpoint:
    """Read a checkpoint file, or the checkpoint of a run directory; CheckpointError if unusable."""
    path = find_checkpoint(path_or_run_dir)
    try:
        raw = torch.load(path, map_location=map_location, weights_only=True)
    except Exception as e:  # torch raises many types for a truncated or foreign file
        raise CheckpointError(f"cannot read checkpoint {path}: {type(e).__name__}: {e}") from None
    if not isinstance(raw, dict) or raw.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not an l2r learner checkpoint")
    if raw.get("format_version") != FORMAT_VERSION:
        raise CheckpointError(f"{path} has checkpoint format version {raw.get('format_version')!r}, "
                              f"this l2r reads {FORMAT_VERSION}")
    try:
        config = SACConfig(**raw["sac_config"])
        return Checkpoint(path, config, int(raw["obs_dim"]), int(raw["act_dim"]), dict(raw["policy_spec"]),
                          raw["train_state"], float(raw["saved_at"]))
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path} is incomplete or inconsistent: {type(e).__name__}: {e}") from None
