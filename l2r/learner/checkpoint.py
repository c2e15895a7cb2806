"""Learner checkpoints: the last few kept, each written atomically, and the best evaluated policy.

A checkpoint is a `torch.save` of one dict (loadable with `weights_only=True`):

    format          "l2r-learner-checkpoint"
    format_version  1
    algo            "sac", "ppo", "td3", "a2c", "a3c", "reinforce", "trpo" or "acktr", the algorithm that trained it
                    (absent: "sac", a file from before PPO)
    sac_config      SACConfig as a dict (algorithm settings the state was trained with);
                    None in a policy checkpoint and in a PPO or TD3 checkpoint, so that readers
                    from before PPO take those for a policy checkpoint
    ppo_config      PPOConfig as a dict, in a PPO checkpoint
    a2c_config, a3c_config, reinforce_config  A2CConfig, A3CConfig, ReinforceConfig as a dict, in their checkpoints
    trpo_config, acktr_config  TRPOConfig, ACKTRConfig as a dict, in their checkpoints
    td3_config      TD3Config as a dict, in a TD3 checkpoint
    obs_dim, act_dim  obs_dim 0 for observations other than the float32 vector (the policy spec's
                    "observation" says which)
    policy_spec     the architecture spec of the policy (see l2r.policy; "kind" "deterministic"
                    for TD3's)
    train_state     the algorithm's TrainState.state_dict(): for SAC actor, critic, target_critic
                    and their Adam states, log_alpha, updates, version, extra counters; for PPO,
                    A2C, A3C, REINFORCE and TRPO actor, value, optimizer (TRPO's the value network's
                    alone), updates, version, extra, and for ACKTR also curvature (its K-FAC
                    factors, l2r.learner.curvature.KFAC.state_dict); for TD3 actor,
                    target_actor, critic, target_critic, actor_opt, critic_opt, updates, version,
                    extra; a policy checkpoint holds only actor, updates and version
    action_repeat   0.01 s steps per action the actors trained with (None: not known, as in
                    files from before it was stored)
    evaluation      policy checkpoints: how the policy did ({"score": "distance", "mean_distance",
                    "episodes", ...}; "mean_return" on a standard task, see l2r.best_policy)
    saved_at        wall-clock time of the save (s since the epoch)

The files of a run, in `<run_dir>/learner/`:

    checkpoint-<updates>.pt  the newest `keep` checkpoints (the learner's --keep-checkpoints)
    checkpoint.pt            the newest of them under a second name (a hard link: no extra disk);
                             what `--resume` and `l2r eval RUN_DIR` read
    best.pt                  the policy with the best mean evaluation score (the task family's:
                             distance, return), written by `l2r up` (no critic or optimizer
                             state: `l2r eval` reads it, a learner cannot resume from it)

Each is written to a temporary file in the same directory, flushed to disk, made readable by
everyone (mode 0644: results are shared, temporary files are private), renamed over the old
name, and the directory is fsynced, so a crash at any point leaves the previous file intact
and a finished save survives a power cut.
"""

from __future__ import annotations

import io
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, BinaryIO, Mapping

import torch

from l2r.durable import fsync_directory, write_durably
from l2r.learner import acktr, ppo, sac, td3, trpo
from l2r.learner.a2c import A2CConfig
from l2r.learner.a3c import A3CConfig
from l2r.learner.acktr import ACKTRConfig
from l2r.learner.ppo import PPOConfig
from l2r.learner.reinforce import ReinforceConfig
from l2r.learner.sac import SACConfig
from l2r.learner.td3 import TD3Config
from l2r.learner.trpo import TRPOConfig
from l2r.policy import PolicyNetwork, build_policy
from l2r.protocol.observations import ObservationSpec

FORMAT = "l2r-learner-checkpoint"
FORMAT_VERSION = 1
RELATIVE_PATH = Path("learner") / "checkpoint.pt"
BEST_RELATIVE_PATH = Path("learner") / "best.pt"
UPDATES_DIGITS = 10  # checkpoint-0000012345.pt: names sort in the order of their updates


# What a checkpoint's "algo" names: the algorithm's config class and its module (init_state,
# TrainState, update, ...). A2C, A3C and REINFORCE are PPO's state at their own settings (A3C's update,
# on gradients, is l2r.learner.a3c.apply).
ALGORITHMS = {"sac": (SACConfig, sac), "ppo": (PPOConfig, ppo), "td3": (TD3Config, td3),
              "a2c": (A2CConfig, ppo), "a3c": (A3CConfig, ppo), "reinforce": (ReinforceConfig, ppo),
              "trpo": (TRPOConfig, trpo),
              "acktr": (ACKTRConfig, acktr)}
AlgorithmConfig = SACConfig | PPOConfig | TD3Config | TRPOConfig | ACKTRConfig
TrainState = sac.TrainState | ppo.TrainState | td3.TrainState | acktr.TrainState


def algorithm_of(config: AlgorithmConfig) -> str:
    """The name of the algorithm a config is for ("sac", "ppo", "a2c", ...)."""
    # Its exact class: an A2CConfig is also a PPOConfig.
    return next(name for name, (cls, _) in ALGORITHMS.items() if type(config) is cls)


class CheckpointError(RuntimeError):
    """A checkpoint that is missing, unreadable or not one of ours; the message says which."""


def checkpoint_path(run_dir: str | Path) -> Path:
    """Where the learner of a run keeps its checkpoint."""
    return Path(run_dir) / RELATIVE_PATH


def best_policy_path(run_dir: str | Path) -> Path:
    """Where `l2r up` keeps the policy with the best evaluation score of a run."""
    return Path(run_dir) / BEST_RELATIVE_PATH


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


def save_checkpoint(path: str | Path, state: TrainState, config: AlgorithmConfig,
                    obs_dim: int, act_dim: int, action_repeat: int | None = None, keep: int = 1) -> Path:
    """Write the training state to `path` atomically. With `keep` > 1 the checkpoint is also
    kept as `checkpoint-<updates>.pt` beside it, and all but the newest `keep` such files go."""
    path = Path(path)
    algo = algorithm_of(config)
    _write(path, {
        # sac_config stays None unless SAC trained it: readers from before PPO see a policy checkpoint
        "format": FORMAT, "format_version": FORMAT_VERSION, "algo": algo, "sac_config": None,
        f"{algo}_config": config.to_dict(),
        "obs_dim": obs_dim, "act_dim": act_dim, "policy_spec": dict(state.actor.spec),
        "train_state": state.state_dict(), "action_repeat": action_repeat, "saved_at": time.time(),
    })
    if keep > 1:
        numbered = path.with_name(f"{path.stem}-{state.updates:0{UPDATES_DIGITS}d}{path.suffix}")
        numbered.unlink(missing_ok=True)  # a learner resumed from an earlier save reached this count again
        os.link(path, numbered)
        kept = sorted(path.parent.glob(f"{path.stem}-{'[0-9]' * UPDATES_DIGITS}{path.suffix}"))
        for old in kept[:-keep]:
            old.unlink()
        fsync_directory(path.parent)
    return path


def save_policy_checkpoint(path: str | Path, policy_params: Mapping[str, Any], policy_spec: dict, version: int,
                           updates: int, action_repeat: int | None, evaluation: dict) -> Path:
    """Write a policy alone (float32 arrays as `policy_state` gives them, e.g. from a Weights
    message) as a checkpoint `l2r eval` reads, with how it did in `evaluation`."""
    return _write(Path(path), {
        "format": FORMAT, "format_version": FORMAT_VERSION, "sac_config": None,
        "obs_dim": int(policy_spec.get("obs_dim", 0)), "act_dim": int(policy_spec["act_dim"]),
        "policy_spec": dict(policy_spec), "action_repeat": action_repeat, "evaluation": dict(evaluation),
        "train_state": {"actor": {name: torch.tensor(value) for name, value in policy_params.items()},
                        "version": version, "updates": updates},
        "saved_at": time.time(),
    })


def _write(path: Path, payload: dict) -> Path:
    """torch.save into memory, then to a temporary file, fsynced and renamed over `path`
    (l2r.durable.write_durably). In memory first because torch's zip writer, when the disk refuses a
    write, raises a RuntimeError from its cleanup in place of the OSError that says why."""
    buffer = io.BytesIO()
    torch.save(payload, buffer)

    def write(f: BinaryIO) -> None:
        f.write(buffer.getbuffer())
        os.fchmod(f.fileno(), 0o644)  # readable by whoever evaluates it, whatever the learner's umask

    write_durably(path, write)
    return path


@dataclass
class Checkpoint:
    """A loaded checkpoint: settings, shapes and the saved training state."""

    path: Path
    config: AlgorithmConfig | None
    """None in a policy checkpoint."""
    obs_dim: int
    act_dim: int
    policy_spec: dict
    train_state: dict
    saved_at: float
    action_repeat: int | None = None
    """0.01 s steps per action in training; None when the file does not say."""
    evaluation: dict | None = None
    """How a policy checkpoint's policy did in evaluation."""
    algo: str = "sac"
    """The algorithm that trained it."""

    @property
    def version(self) -> int:
        return int(self.train_state["version"])

    @property
    def updates(self) -> int:
        return int(self.train_state["updates"])

    def policy(self, device: str | torch.device = "cpu") -> PolicyNetwork:
        """The trained policy, ready for `act` (evaluation mode, on `device`)."""
        policy = build_policy(self.policy_spec)
        policy.load_state_dict(self.train_state["actor"])
        return policy.to(device).eval()

    def restore(self, device: str | torch.device = "cpu") -> TrainState:
        """The full training state (networks, optimizers, counters) on `device`."""
        if self.config is None:
            raise CheckpointError(f"{self.path} holds a policy alone, not a training state to resume")
        # Image observations are saved with obs_dim 0: their spec is the policy spec's.
        observation = self.obs_dim or ObservationSpec.from_policy_spec(self.policy_spec)
        state = ALGORITHMS[self.algo][1].init_state(self.config, observation, self.act_dim, device)
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
    algo = raw.get("algo", "sac")
    if algo not in ALGORITHMS:
        raise CheckpointError(f"{path} was trained by {algo!r}; this l2r knows {', '.join(ALGORITHMS)}")
    try:
        settings = raw[f"{algo}_config"]
        config = None if settings is None else ALGORITHMS[algo][0](**settings)
        repeat = raw.get("action_repeat")
        return Checkpoint(path, config, int(raw["obs_dim"]), int(raw["act_dim"]), dict(raw["policy_spec"]),
                          raw["train_state"], float(raw["saved_at"]), None if repeat is None else int(repeat),
                          raw.get("evaluation"), algo)
    except (KeyError, TypeError, ValueError) as e:
        raise CheckpointError(f"{path} is incomplete or inconsistent: {type(e).__name__}: {e}") from None
