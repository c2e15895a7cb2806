"""`l2r-actor`: command line of the actor daemon (see `l2r.actors.actor`)."""

from __future__ import annotations

import signal
import sys
import threading
from typing import Annotated, Literal, Sequence

from pydantic import Field, field_validator

from l2r.actors.actor import ActorConfig, main, registers_vector_env
from l2r.actors.curriculum import DifficultySchedule
from l2r.actors.noise import COLOURS
from l2r.config import CommandParser, FilePath, UsageError, load, run_command, setting, settings_parser
from l2r.durable import MB
from l2r.families import RUNNER, family_of
from l2r.photo.env import GOALS
from l2r.protocol import DaemonSettings, configure_logging
from l2r.sim import randomize_refusal
from l2r.sim.randomize import Randomization
from l2r.spaces import image_size_option, photo_goals_option

DEFAULTS = ActorConfig()
ACTING, EXPERIENCE, EVALUATION, LOGS = "acting", "experience", "evaluation role", "episode logs (MCAP)"
ROBUSTNESS = "robustness (each off by default; what each A/B measured: docs/training.md)"


class ActorSettings(DaemonSettings):
    actor_id: Annotated[int, Field(ge=0)] | Literal["auto"] = setting(
        DEFAULTS.actor_id, "this actor's number; unique within the run (it names its keys and picks its replay "
        "shard). auto: ask replay shard 0, which gives every actor process of the run an id of its own and a "
        "restarted container its id again (shard 0 needs --snapshot-dir to remember them)", group=ACTING,
        metavar="{N,auto}")
    num_envs: int = setting(DEFAULTS.num_envs, "environments stepped together, their observations batched into "
                            "one policy call", group=ACTING, ge=1)
    vector_env: Literal["auto", "on", "off"] = setting(
        "auto", "step the --num-envs envs as one gymnasium vector env, one call for all of them: auto when the env "
        "id registers a vector env of its own (l2r/RunWarp-v0: its worlds stepped together on a Warp device, the "
        "way to step thousands of runners on a GPU); on for any env (another one's single envs in a "
        "SyncVectorEnv: the same experience, for comparison); off: single envs one by one (l2r/RunWarp-v0 then one "
        "world each). Training actors only: an evaluator runs single envs", group=ACTING)
    device: Literal["auto", "cpu", "cuda"] = setting(
        "cpu", "where the policy acts, and where l2r/RunWarp-v0's worlds step (auto: cuda when there is a GPU)",
        group=ACTING)
    env_id: str = setting(DEFAULTS.env_id, "gymnasium id of the environment: l2r/Run-v0 (the MuJoCo port), "
                          "l2r/RunOpenSim-v0 (OpenSim 4.6, the 2017 simulator: about 100 steps/s; "
                          "pip install 'l2r[opensim]'), another task such as Hopper-v5, or a camera task "
                          "l2r/dmc-<domain>-<task>-v0, whose uint8 frames its replay shard must store "
                          "(l2r-replay --observation 'pixels: uint8[3, 84, 84]')", group=ACTING)
    image_size: int | None = setting(
        None, "a camera task's frames, pixels a side (default: the task's own, 84 as DrQ-v2's): smaller frames render "
        "and train faster on a CPU; its replay shard and learner take the observation they make (l2r up hands "
        "them over)", group=ACTING, ge=1, metavar="PIXELS")
    photo_goals: Literal[GOALS] | None = setting(
        None, "the photo tuner's goals: random (the crop finished with hidden random parameters), looks (the crop "
        "with another scene's look) or mixed (either, with even odds each episode) (default: the task's own, "
        "random)", group=ACTING)
    difficulty: int = setting(DEFAULTS.difficulty, "0 flat ground, 1 obstacles, 2 obstacles and random psoas "
                              "strengths", group=ACTING, ge=0, le=2, metavar="{0,1,2}")
    difficulty_schedule: str | None = setting(
        None, "train on a course of rising difficulty: stages TRIGGER:DIFFICULTY from step 0 on, entered in "
        "order, each when its trigger is met: an env step count of this actor's (its env_steps stat), e.g. "
        "0:0,300000:1,600000:2, or a distance, 6m: once this actor's last 20 training episodes of the stage "
        "before averaged 6 m, e.g. 0:0,6m:2 (a stage once entered is kept); each training episode starts at the "
        "difficulty of the stage it is on, in place of --difficulty (the runner; not with --evaluate)",
        group=ROBUSTNESS, metavar="TRIGGER:DIFFICULTY,...")
    env_steps_before: int = setting(
        0, "env steps this actor's place in the run took before this process started: the --difficulty-schedule "
        "goes on from there (l2r up gives each training actor its share of the run's env steps on --resume)",
        group=ROBUSTNESS, ge=0, metavar="N")
    randomize: str | None = setting(
        None, "draw a new body each episode (l2r/Run-v0 and l2r/RunWarp-v0 only): NAME=FRACTION items, each "
        "factor uniform in 1 +- FRACTION (at most 0.5): strength (max isometric force, per muscle), tendon_slack "
        "and fiber_length (tendon slack and optimal fibre length, per muscle), mass (per segment, inertia with it), "
        "contact_stiffness, contact_damping, friction (the feet's ground contact, per episode); and delay=P, the "
        "probability that an episode's excitations act one physics step (2.5 ms) late. E.g. "
        "strength=0.1,tendon_slack=0.03,fiber_length=0.03,mass=0.1,contact_stiffness=0.2,friction=0.2,delay=0.5",
        group=ROBUSTNESS, metavar="NAME=FRACTION,...")
    observation_noise: float = setting(DEFAULTS.observation_noise, "std of Gaussian noise added to every observed "
                                       "value, in its own units (m, rad, m/s, rad/s on the runner); the experience "
                                       "sent holds the noisy observations", group=ROBUSTNESS, ge=0)
    action_noise: float = setting(DEFAULTS.action_noise, "std of Gaussian noise added to every action value (the "
                                  "runner's excitations, then clipped to [0, 1]) before the env takes it, drawn anew "
                                  "for each repeat; the experience sent holds the policy's action",
                                  group=ROBUSTNESS, ge=0)
    exploration_noise: Literal[tuple(COLOURS)] = setting(
        DEFAULTS.exploration_noise, "the colour of the policy's exploring draws over an episode: white, each step's "
        "drawn anew; pink or red, a series whose power falls as 1/f or 1/f^2, so successive actions are correlated "
        "(each draw is still N(0, 1): the policy and its log-probabilities are unchanged)", group=ROBUSTNESS)
    parameter_noise: float = setting(DEFAULTS.parameter_noise, "explore in parameter space: each env's policy "
                                     "weights perturbed by Gaussian noise for each episode, its std adapted so the "
                                     "perturbed actions lie this RMS distance from the policy's, in its (-1, 1) "
                                     "action space (Plappert et al., 2018); off-policy learners only: the "
                                     "log-probabilities sent are the perturbed policy's (0: off)",
                                     group=ROBUSTNESS, ge=0)
    action_repeat: int = setting(DEFAULTS.action_repeat, "environment steps per policy action (0.01 s each on the "
                                 "runner; a camera task already holds each action for 2 suite steps itself, so 1 "
                                 "there trains as DrQ-v2 does)", group=ACTING, ge=1)
    random_steps: int = setting(DEFAULTS.random_steps, "uniform random excitations for this many of the actor's "
                                "first steps (skipped when the run's policy is already past version 0)",
                                group=ACTING, ge=0)
    seed: int = setting(DEFAULTS.seed, "base seed of episodes and random actions", group=ACTING)
    torch_threads: int = setting(DEFAULTS.torch_threads, "torch CPU threads for inference", group=ACTING, ge=1)
    max_speed: float = setting(DEFAULTS.max_speed, "pelvis speed (m/s) above which a step is a simulation blow-up: "
                               "the episode ends before it, as a terminal step without reward, and it is counted "
                               "(0: off)", group=ACTING, ge=0)
    stats_interval: float = setting(DEFAULTS.stats_interval, "seconds between stats reports", group=ACTING, gt=0)
    max_steps: int = setting(DEFAULTS.max_steps, "stop after this many steps (0: never)", group=ACTING, ge=0)
    chunk_size: int = setting(DEFAULTS.chunk_size, "transitions per experience chunk", group=EXPERIENCE, ge=1)
    chunk_delay: float = setting(DEFAULTS.chunk_delay, "seconds after which a partial chunk is sent anyway",
                                 group=EXPERIENCE, gt=0)
    num_shards: int = setting(DEFAULTS.num_shards, "replay shards of the run; this actor feeds shard "
                              "actor-id % num-shards", group=EXPERIENCE, ge=1)
    resend_buffer_mb: float = setting(DEFAULTS.resend_buffer_mb, "sent chunks kept until the replay shard "
                                      "acknowledges them, and sent again when lost in flight (a cut link, a "
                                      "restarted shard); beyond this the oldest are given up (0: no resends)",
                                      group=EXPERIENCE, ge=0)
    resend_delay: float = setting(DEFAULTS.resend_delay, "seconds after its last send before an unacknowledged "
                                  "chunk is sent again; the wait doubles with each resend, up to 30 s",
                                  group=EXPERIENCE, gt=0)
    compress_frames: Literal["on", "off"] = setting(
        "on", "send a camera task's frames (its uint8 observation fields) zstd-compressed, as protocol version 3: "
        "3.5x fewer bytes on walker, 32x on cartpole, for 1-3 ms of CPU per 64-step chunk against about 1.2 s of "
        "rendering; a replay shard older than version 3 rejects such chunks (logged as version), so give it off "
        "for one. Other tasks send the same bytes either way", group=EXPERIENCE)
    send_gradients: bool = setting(False, "A3C (l2r-learner --algo a3c): send the gradient of each chunk's rollout, "
                                   "computed at the weights that acted it, instead of the chunk; weights are "
                                   "swapped in only between chunks (--chunk-size: A2C's n-steps, 5)",
                                   group=EXPERIENCE)
    evaluate: bool = setting(False, "run deterministic episodes on fixed seeds for each new policy, report them as "
                             "evaluation episodes, and send no experience", group=EVALUATION)
    eval_episodes: int = setting(DEFAULTS.eval_episodes, "episodes per evaluation round, on seeds seed, seed+1, ...",
                                 group=EVALUATION, ge=1)
    eval_interval: float = setting(DEFAULTS.eval_interval, "least seconds between the starts of two evaluation "
                                   "rounds", group=EVALUATION, ge=0)
    episode_log_dir: FilePath | None = setting(None, "write logged episodes as MCAP files here (default: no logs)",
                                               group=LOGS)
    log_every: int = setting(10, "log every Nth training episode (0: none); evaluation episodes are always logged",
                             group=LOGS, ge=0)
    log_budget_mb: float = setting(256.0, "disk budget of this actor's logs, oldest removed first (the runner's "
                                   "actors log about 0.1 MB/s: 256 MB holds their last 45 minutes)", group=LOGS, gt=0)
    log_min_free_mb: float = setting(0.0, "begin no logged episode while the disk has less than this free, leaving "
                                     "the room to checkpoints and replay (l2r up sets it; 0: no floor)",
                                     group=LOGS, ge=0)

    @field_validator("randomize")
    @classmethod
    def _randomization(cls, text: str | None) -> str | None:
        if text is not None:
            Randomization.parse(text)
        return text

    @field_validator("difficulty_schedule")
    @classmethod
    def _schedule(cls, text: str | None) -> str | None:
        if text is not None:
            DifficultySchedule.parse(text)
        return text

    def check(self) -> None:
        if self.randomize and Randomization.parse(self.randomize) and randomize_refusal(self.env_id):
            raise UsageError(f"--randomize: {randomize_refusal(self.env_id)}")
        if self.difficulty_schedule is not None:
            if family_of(self.env_id) != RUNNER:
                raise UsageError(f"--difficulty-schedule is the runner's, not {self.env_id}'s")
            if self.evaluate:
                raise UsageError("--difficulty-schedule is for training actors: an evaluator keeps --difficulty")
        try:
            image_size_option(self.env_id, self.image_size)
        except ValueError as e:
            raise UsageError(f"--image-size {self.image_size}: {e}") from None
        try:
            photo_goals_option(self.env_id, self.photo_goals)
        except ValueError as e:
            raise UsageError(f"--photo-goals {self.photo_goals}: {e}") from None
        if self.native_vector_env and (self.observation_noise or self.action_noise):
            raise UsageError(f"--observation-noise and --action-noise wrap single envs, not {self.env_id}'s "
                             "vector env; add --vector-env off")

    @property
    def native_vector_env(self) -> bool:
        """Whether the actor steps the env id's own vector env (a training actor, --vector-env not off)."""
        return not self.evaluate and self.vector_env != "off" and registers_vector_env(self.env_id)

    def actor(self) -> ActorConfig:
        episode_log = {}
        if self.episode_log_dir is not None:
            episode_log = {"directory": self.episode_log_dir, "every": self.log_every,
                           "disk_budget_bytes": int(self.log_budget_mb * 2**20),
                           "min_free_bytes": int(self.log_min_free_mb * MB)}
        actor_id = None if self.actor_id == "auto" else self.actor_id  # None: asked of replay shard 0
        return ActorConfig(
            run=self.run, actor_id=actor_id, num_envs=self.num_envs, env_id=self.env_id,
            vector_env={"auto": None, "on": True, "off": False}[self.vector_env],
            device=self.device, image_size=self.image_size, photo_goals=self.photo_goals,
            difficulty=self.difficulty, action_repeat=self.action_repeat, random_steps=self.random_steps,
            difficulty_schedule=None if self.difficulty_schedule is None else
            DifficultySchedule.parse(self.difficulty_schedule), env_steps_before=self.env_steps_before,
            randomize=Randomization.parse(self.randomize or ""), observation_noise=self.observation_noise,
            action_noise=self.action_noise, exploration_noise=self.exploration_noise,
            parameter_noise=self.parameter_noise,
            chunk_size=self.chunk_size, chunk_delay=self.chunk_delay, seed=self.seed, num_shards=self.num_shards,
            evaluate=self.evaluate, eval_episodes=self.eval_episodes, eval_interval=self.eval_interval,
            torch_threads=self.torch_threads, max_steps=self.max_steps, stats_interval=self.stats_interval,
            max_speed=self.max_speed, resend_buffer_mb=self.resend_buffer_mb, resend_delay=self.resend_delay,
            compress_frames=self.compress_frames == "on",
            episode_log=episode_log, send_gradients=self.send_gradients,
        )


def build_parser() -> CommandParser:
    return settings_parser(
        ActorSettings, "l2r-actor",
        "Step several Learning to Run environments with the learner's newest policy and send the experience to "
        "the replay server(s) of a run. Stops cleanly on SIGINT/SIGTERM.")


def parse_settings(argv: Sequence[str] | None = None) -> ActorSettings:
    return load(ActorSettings, build_parser(), argv)


def cli(argv: Sequence[str] | None = None) -> int:
    return run_command("l2r-actor", lambda: act(parse_settings(argv)))


def act(s: ActorSettings) -> int:
    configure_logging(s.log_level)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return main(s.actor(), s.zenoh_session_config(), stop)


if __name__ == "__main__":
    sys.exit(cli())
