"""``l2r-learner``: command line of the SAC learner (see ``l2r.learner.daemon``)."""

from __future__ import annotations

import os

# Set before torch loads OpenMP: idle OpenMP workers then sleep instead of spinning. The learner
# shares cores with actors; spinning workers waste them, and when the cores are oversubscribed
# every parallel region waits for a descheduled spinner (measured: 3-4x fewer updates/s).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import sys  # noqa: E402
from typing import Literal, Sequence  # noqa: E402

from pydantic import field_validator  # noqa: E402

from l2r.config import (  # noqa: E402
    CommandParser, FilePath, StartupFailure, UsageError, load, run_command, setting, settings_parser,
)
from l2r.learner.daemon import LearnerConfig, main  # noqa: E402
from l2r.learner.distributed import DeviceUnavailable  # noqa: E402
from l2r.learner.sac import HIDDEN_WIDTHS, SACConfig  # noqa: E402
from l2r.protocol import DaemonSettings, configure_logging  # noqa: E402

SAC_DEFAULTS = SACConfig()
PROCESS, PARALLEL, SAC = "learner process", "data parallel (torch.distributed; gloo on CPU, NCCL on CUDA)", "SAC"


class LearnerSettings(DaemonSettings):
    run_dir: FilePath | None = setting(None, "run directory; the checkpoint is <run-dir>/learner/checkpoint.pt "
                                       "(default: runs/<run>)", group=PROCESS)
    resume: bool = setting(False, "continue from the run directory's checkpoint if there is one (networks, "
                           "optimizers, alpha, version, counters)", group=PROCESS)
    device: Literal["auto", "cpu", "cuda"] = setting("auto", "where to train; auto = CUDA if available", group=PROCESS)
    threads: int = setting(0, "torch CPU threads; 0 = torch's default", group=PROCESS, ge=0)
    obs_dim: int = setting(41, "observation width", group=PROCESS, ge=1)
    act_dim: int = setting(18, "action width", group=PROCESS, ge=1)
    in_flight: int = setting(4, "sample requests kept in flight", group=PROCESS, ge=1)
    prioritized: bool = setting(False, "prioritized sampling, |TD error| sent back as priority", group=PROCESS)
    priority_beta: float = setting(0.4, "importance-weight exponent under prioritized sampling", group=PROCESS, ge=0)
    publish_every: int = setting(50, "updates between weight publications", group=PROCESS, ge=1)
    checkpoint_interval: float = setting(60.0, "seconds between checkpoints", group=PROCESS, gt=0)
    keep_checkpoints: int = setting(3, "checkpoints kept: checkpoint.pt is the newest, checkpoint-<updates>.pt "
                                    "the newest N", group=PROCESS, ge=1)
    action_repeat: int | None = setting(None, "the actors' action repeat; stored in checkpoints so `l2r eval` steps "
                                        "the env as training did (the learner itself does not use it)",
                                        group=PROCESS, ge=1)
    metrics_interval: float = setting(5.0, "seconds between metrics reports", group=PROCESS, gt=0)
    max_updates: int = setting(0, "stop after this many updates in total; 0 = until stopped", group=PROCESS, ge=0)
    seed: int | None = setting(None, "torch seed (each rank adds its rank)", group=PROCESS)

    # torchrun's variables, so that each rank it starts knows its place
    world_size: int = setting(1, "number of learners (default: $WORLD_SIZE or 1)", group=PARALLEL, ge=1,
                              variable="WORLD_SIZE")
    rank: int = setting(0, "this learner's rank; rank 0 publishes weights and checkpoints (default: $RANK or 0)",
                        group=PARALLEL, ge=0, variable="RANK")
    dist_url: str | None = setting(None, "rendezvous, e.g. tcp://127.0.0.1:29500 (default: env:// with $MASTER_ADDR "
                                   "and $MASTER_PORT)", group=PARALLEL)

    batch_size: int = setting(SAC_DEFAULTS.batch_size, "transitions per batch", group=SAC, ge=1)
    update_repeat: int = setting(SAC_DEFAULTS.update_repeat, "gradient steps per sampled batch", group=SAC, ge=1)
    gamma: float = setting(SAC_DEFAULTS.gamma, "discount", group=SAC, ge=0, le=1)
    tau: float = setting(SAC_DEFAULTS.tau, "Polyak rate of the target critics", group=SAC, gt=0, le=1)
    lr: float = setting(SAC_DEFAULTS.actor_lr, "Adam learning rate of actor, critics and alpha", group=SAC, gt=0)
    hidden: str = setting(",".join(map(str, SAC_DEFAULTS.hidden)), "hidden layer widths, comma-separated",
                          group=SAC)
    activation: Literal["elu", "relu", "tanh"] = setting(SAC_DEFAULTS.activation, "hidden activation", group=SAC)
    no_layer_norm: bool = setting(False, "no LayerNorm in hidden layers", group=SAC)
    reward_scale: float = setting(SAC_DEFAULTS.reward_scale, "reward multiplier", group=SAC)
    target_entropy: float | None = setting(None, "entropy target of alpha tuning (default: -act-dim)", group=SAC)
    initial_alpha: float = setting(SAC_DEFAULTS.initial_alpha, "starting temperature", group=SAC, gt=0)
    fixed_alpha: bool = setting(False, "keep alpha at --initial-alpha (no tuning)", group=SAC)
    relative_x: bool = setting(False, "networks see world x coordinates as distances from the pelvis", group=SAC)
    normalize_obs: bool = setting(False, "networks see observations standardised by running statistics (shipped "
                                  "with the weights)", group=SAC)
    mirror: bool = setting(False, "swap the legs of a random half of each batch (left-right symmetry as "
                           "augmentation)", group=SAC)
    precision: Literal["auto", "float32", "bfloat16"] = setting(
        SAC_DEFAULTS.precision, "hidden-layer matmul precision; auto = bfloat16 where the hardware has it", group=SAC)

    @field_validator("hidden")
    @classmethod
    def _widths(cls, hidden: str) -> str:
        if not HIDDEN_WIDTHS.fullmatch(hidden):
            raise ValueError("should be layer widths separated by commas, e.g. 512,512,512")
        return hidden

    def check(self) -> None:
        if self.rank >= self.world_size:
            raise UsageError(f"--rank {self.rank} must be below --world-size {self.world_size}")

    def sac(self) -> SACConfig:
        try:
            return SACConfig(
                gamma=self.gamma, tau=self.tau, actor_lr=self.lr, critic_lr=self.lr, alpha_lr=self.lr,
                batch_size=self.batch_size, hidden=tuple(int(h) for h in self.hidden.split(",")),
                activation=self.activation, layer_norm=not self.no_layer_norm, reward_scale=self.reward_scale,
                update_repeat=self.update_repeat, target_entropy=self.target_entropy,
                initial_alpha=self.initial_alpha, autotune_alpha=not self.fixed_alpha, relative_x=self.relative_x,
                normalize_obs=self.normalize_obs, mirror=self.mirror, precision=self.precision)
        except ValueError as e:  # a combination SACConfig refuses
            raise UsageError(str(e)) from None

    def learner(self) -> LearnerConfig:
        return LearnerConfig(
            run=self.run, run_dir=self.run_dir, resume=self.resume, device=self.device, threads=self.threads,
            obs_dim=self.obs_dim, act_dim=self.act_dim, prioritized=self.prioritized,
            priority_beta=self.priority_beta, in_flight=self.in_flight, publish_every=self.publish_every,
            checkpoint_interval=self.checkpoint_interval, keep_checkpoints=self.keep_checkpoints,
            action_repeat=self.action_repeat, metrics_interval=self.metrics_interval,
            max_updates=self.max_updates, seed=self.seed, world_size=self.world_size, rank=self.rank,
            dist_url=self.dist_url)


def build_parser() -> CommandParser:
    return settings_parser(
        LearnerSettings, "l2r-learner",
        "SAC learner of an l2r run: samples batches from the replay server(s) with several requests in flight, "
        "trains twin critics, a tanh-Gaussian policy and the entropy temperature, publishes versioned policy "
        "weights for actors, and checkpoints atomically.",
        "Example: l2r-learner --run exp1 --connect tcp/127.0.0.1:7447 --run-dir runs/exp1 --resume\n"
        "Two data-parallel learners: add --world-size 2 --rank 0|1 --dist-url tcp://127.0.0.1:29500")


def parse_settings(argv: Sequence[str] | None = None) -> LearnerSettings:
    return load(LearnerSettings, build_parser(), argv)


def cli(argv: Sequence[str] | None = None) -> int:
    return run_command("l2r-learner", lambda: train(parse_settings(argv)))


def train(s: LearnerSettings) -> int:
    sac = s.sac()
    configure_logging(s.log_level)
    try:
        return main(s.learner(), sac, s.zenoh_session_config())
    except DeviceUnavailable as e:
        raise StartupFailure(str(e)) from None


if __name__ == "__main__":
    sys.exit(cli())
