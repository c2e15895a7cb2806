"""A warm start of the photo tuner, learnt with supervision from its random goals' hidden parameters.

Each random goal of `l2r/PhotoTune-v0` (and `-Stats-v0`, `-Compare-v0`) is the crop finished with parameters
the task draws and hides (`env.goal_params`), so for every observation of such an episode the
answer in one query is known: those parameters, as actions. Regressing the policy's
deterministic actions onto them is supervised learning, far cheaper than reinforcement learning
on two cores, and what the tuner learns does not depend on a critic's estimates:

1. round 1: episodes whose queries are the answer blurred by Gaussian noise of a random scale
   per episode (up to `first_noise`, each parameter's share of it drawn anew each query), so
   the observations range from far off to nearly there;
2. each round: `updates` Adam steps of mean squared error in action units over all the
   observations so far; then, but for the last round, `episodes // 2` episodes of the policy's
   own deterministic queries with Gaussian noise of a random scale (up to `policy_noise`) added,
   each labelled with the same answer (DAgger: Ross, Gordon and Bagnell, 2011).

Rounds after the first were meant to teach the policy to refine its own queries; measured, the
three of the old default cost it 2.0 dB on held-out random edits (0.5 gained on other scenes'
looks), and one round of more episodes gained more (0.9 dB from 1,500 to 3,000, 0.4 from 3,000 to
6,000, 1.7 from 6,000 to 12,000, 1.8 from 12,000 to 24,000 over three seeds' medians; docs/photo.md):
the default is one round of 24,000, the least that passes CMA-ES at 200 queries in PSNR and SSIM
on every seed tried.

Playing the episodes takes most of the time on one core; `workers` processes play them in
chunks. Each episode's noise comes from its own seed (the run's seed, the round and the
episode's index), so the result is the same whatever the number of workers (since 2026-11-28:
the figures before then drew every episode's noise from one stream, and the same flags now give
other figures of the same spread).

The networks are those of the photo/td3 recipe (l2r.recipes), so the policy checkpoint it
writes is one `l2r photo compare`/`tune` run and `l2r up --algo td3 --init-from` starts from.
Goals from other scenes' looks have no parameters to learn from: they stay the reinforcement
learner's.
"""

from __future__ import annotations

import math
import multiprocessing
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from l2r.learner import td3
from l2r.photo.pipeline import PARAMETERS, actions_from_params
from l2r.photo.tune import TUNE_IDS
from l2r.policy import build_policy, load_policy_state, policy_state

CPU = torch.device("cpu")
LR_SCHEDULES = ("constant", "cosine")
EVAL_SEED = 10**9
"""Seeds of the closing evaluation episodes start here, far from the rounds' (below 10^8)."""


@dataclass(frozen=True)
class PretrainConfig:
    env_id: str = "l2r/PhotoTuneCompare-v0"
    """The comparison's tuner: 2.3 dB above the statistics' on held-out random edits, 0.8 below on
    other scenes' looks (one round of 3,000 episodes each, docs/photo.md)."""
    rounds: int = 1
    episodes: int = 24000
    """Episodes of the first round (10 queries each); each later round adds half as many."""
    updates: int = 96000
    """Adam steps a round."""
    batch_size: int = 256
    lr: float = 1e-3
    lr_schedule: str = "constant"
    """"cosine": each round's learning rate falls from `lr` to 0 along half a cosine over its
    `updates`, so that its last steps average the noise of the batches away rather than follow it."""
    first_noise: float = 0.6
    policy_noise: float = 0.2
    eval_episodes: int = 50
    """Deterministic episodes on the training photos that judge the result (its checkpoint's evaluation)."""
    source_variety: float = 0.5
    """The training crops varied before each hidden edit (flipped, finished at random within ± this
    much of each action's range: `PhotoTuneEnv`'s source_variety), so that six training scenes
    show many colourings: over seeds 0-2 at 12,000 episodes the held-out results lie within 0.5 dB
    of each other (28.73-29.23) where without it they spread over 3.0 (27.25-30.26), their median
    0.21 dB lower and SSIM's 0.014 higher (docs/photo.md)."""
    workers: int = 1
    """Processes that play the episodes (one: this one). Each episode's noise is drawn from its own
    seed (`episode_rng`) and the workers' episodes are kept in order, so the result does not depend
    on how many play them: on a 16-core box the episodes, most of the time on one core, take a
    sixteenth of it."""
    residual: bool = False
    """Each query a change to the last one (the "residual" policy kind, l2r.policy): a query nearly
    right then stays so where the head gives nearly 0. Off: on held-out problems it gained 0.2 dB
    with the comparison view and lost 2.1 with the statistics alone (docs/photo.md)."""
    seed: int = 0

    def __post_init__(self) -> None:
        if self.env_id not in TUNE_IDS:
            raise ValueError(f"the warm start learns the tuner's tasks, {' or '.join(TUNE_IDS)}, not {self.env_id}")
        if min(self.rounds, self.episodes, self.updates, self.batch_size, self.eval_episodes, self.workers) < 1:
            raise ValueError("rounds, episodes, updates, batch_size, eval_episodes and workers must be at least 1")
        if self.lr <= 0 or min(self.first_noise, self.policy_noise) < 0:
            raise ValueError("lr must be positive, the noises at least 0")
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule must be {' or '.join(LR_SCHEDULES)}, got {self.lr_schedule!r}")
        if not 0.0 <= self.source_variety <= 1.0:
            raise ValueError(f"source_variety must be in [0, 1], got {self.source_variety}")


def recipe_networks(residual: int | None = None) -> td3.TD3Config:
    """The photo/td3 recipe's networks: what its learner builds for the same task (with
    `--residual-from` `residual`, where given)."""
    from l2r.recipes import PHOTO, RECIPES

    recipe = RECIPES[PHOTO, "td3"]
    return td3.TD3Config(hidden=tuple(int(h) for h in recipe["hidden"].split(",")), activation=recipe["activation"],
                         layer_norm=recipe["layer_norm"], encoder=recipe["encoder"], precision="float32",
                         residual=residual)


class Episodes:
    """The task's episodes on random goals, as the policy sees them, each observation with its answer."""

    def __init__(self, env_id: str, source_variety: float = 0.0):
        import gymnasium

        from l2r.actors.actor import unit_actions
        from l2r.actors.frame_stack import FrameStack
        from l2r.protocol import ObservationSpec

        self.env_id = env_id
        self.env = unit_actions(gymnasium.make(env_id, goals="random", source_variety=source_variety))
        self.spec = ObservationSpec.from_space(self.env.observation_space)
        self.frames = FrameStack(self.spec, 1, 1)
        self.observations: list = []
        self.answers: list[np.ndarray] = []

    def play(self, seed: int, queries: Callable[[object, np.ndarray], np.ndarray], keep: bool = True) -> float:
        """One episode whose queries (actions in [-1, 1]) `queries(observation, answer)` makes; its
        observations and answers kept (`keep`). Returns the last query's PSNR to the goal, in dB."""
        from l2r.actors.actor import fields_of

        obs, info = self.env.reset(seed=seed)
        answer = actions_from_params(self.env.unwrapped.goal_params).astype(np.float32)
        self.frames.reset(0, fields_of(self.spec, obs, self.env_id))
        over = False
        while not over:
            observation = self.frames.stacked()
            if keep:
                self.observations.append(observation)
                self.answers.append(answer)
            action = np.clip(queries(observation, answer), -1.0, 1.0)
            obs, _, terminated, truncated, info = self.env.step((action + 1.0) / 2.0)  # the task takes [0, 1]
            self.frames.push(0, fields_of(self.spec, obs, self.env_id))
            over = terminated or truncated
        return float(info["psnr_db"])

    def taken(self) -> tuple[np.ndarray | dict[str, np.ndarray], np.ndarray]:
        """Every observation kept since the last call (one array, or arrays by field) and its answer,
        stacked; none kept after it."""
        kept = concatenated(self.observations), np.stack(self.answers)
        self.observations, self.answers = [], []
        return kept


def concatenated(observations: list) -> np.ndarray | dict[str, np.ndarray]:
    """Observations (arrays, or maps of arrays by field) joined in order along their first axis."""
    if isinstance(observations[0], dict):
        return {name: np.concatenate([o[name] for o in observations]) for name in observations[0]}
    return np.concatenate(observations)


CHUNK = 250
"""Most episodes a worker plays at a call: enough that the observations sent back outweigh the call."""


class Player:
    """Plays a round's episodes, in this process or in a worker: round 1's queries are the answer
    blurred, later rounds' the policy's own with noise, each episode's noise from its own seed."""

    def __init__(self, config: PretrainConfig, episodes: Episodes, actor: td3.DeterministicPolicy):
        self.config, self.episodes, self.actor = config, episodes, actor

    def deterministic(self, observation, _answer=None) -> np.ndarray:
        with torch.no_grad():
            return self.actor.mean_action(self.actor.observation_tensors(observation, CPU))[0].numpy()

    def play(self, round_: int, indices: range) -> tuple[np.ndarray | dict[str, np.ndarray], np.ndarray, list[float]]:
        """Episodes `indices` of the round: their observations and answers, stacked, and each one's last PSNR."""
        first_seed = self.config.seed * 10**7 + round_ * 10**5
        ends = [self.episodes.play(first_seed + i, self.queries(round_, episode_rng(self.config, round_, i)))
                for i in indices]
        return *self.episodes.taken(), ends

    def queries(self, round_: int, rng: np.random.Generator) -> Callable[[object, np.ndarray], np.ndarray]:
        scale = rng.uniform(0.0, self.config.first_noise if round_ == 0 else self.config.policy_noise)
        if round_ == 0:
            return lambda _observation, answer: answer + rng.normal(0.0, scale, answer.shape) * rng.random(answer.shape)
        return lambda observation, answer: self.deterministic(observation) + rng.normal(0.0, scale, answer.shape)


def episode_rng(config: PretrainConfig, round_: int, index: int) -> np.random.Generator:
    """The noise of a round's `index`-th episode, the same whichever process plays it."""
    return np.random.default_rng((config.seed, round_, index))


def played(player: Player, round_: int, count: int) -> Iterator[tuple]:
    """The round's `count` episodes as `Player.play` gives them, in chunks, in order: played here,
    or by `config.workers` processes each with its own copy of the task and of the policy."""
    size = max(1, min(CHUNK, count // 10))
    chunks = [range(first, min(first + size, count)) for first in range(0, count, size)]
    config = player.config
    if config.workers == 1:
        yield from (player.play(round_, chunk) for chunk in chunks)
        return
    weights = (dict(player.actor.spec), policy_state(player.actor)) if round_ > 0 else None
    with multiprocessing.get_context("spawn").Pool(config.workers, _start_worker, (config, weights)) as pool:
        yield from pool.imap(_play_in_worker, [(round_, chunk) for chunk in chunks])


_worker: Player | None = None
"""A worker process's player (`_start_worker`)."""


def _start_worker(config: PretrainConfig, weights: tuple[dict, dict] | None) -> None:
    global _worker
    torch.set_num_threads(1)
    actor = None
    if weights is not None:
        actor = build_policy(weights[0])
        load_policy_state(actor, weights[1])
        actor.eval()
    _worker = Player(config, Episodes(config.env_id, config.source_variety), actor)


def _play_in_worker(job: tuple[int, range]) -> tuple:
    return _worker.play(*job)


def pretrain(config: PretrainConfig, progress: Callable[[str], None] = print) -> tuple[td3.DeterministicPolicy, dict]:
    """The policy learnt as the module says, and how it did: `mean_psnr` over `eval_episodes`
    deterministic episodes on the training photos, the rounds' losses, samples and seconds."""
    started = time.monotonic()
    episodes = Episodes(config.env_id, config.source_variety)
    residual = episodes.env.unwrapped.parameters_at if config.residual else None
    actor = td3.init_state(recipe_networks(residual), episodes.spec, len(PARAMETERS), seed=config.seed).actor
    optimizer = torch.optim.Adam(actor.parameters(), lr=config.lr)
    player = Player(config, episodes, actor)

    losses, ends, kept = [], [], []
    for round_ in range(config.rounds):
        count = config.episodes if round_ == 0 else config.episodes // 2
        done = 0
        for observations, answers, chunk_ends in played(player, round_, count):
            kept.append((observations, answers))
            ends += chunk_ends
            before, done = done, done + len(chunk_ends)
            if passed_a_tenth(before, done, count):
                progress(f"round {round_ + 1}/{config.rounds}: {done:,} of {count:,} episodes played "
                         f"({time.monotonic() - started:.0f} s)")
        observations, answers = concatenated([o for o, _ in kept]), np.concatenate([a for _, a in kept])
        inputs, answers = actor.observation_tensors(observations, CPU), torch.as_tensor(answers)
        for step in range(config.updates):
            index = torch.randint(len(answers), (config.batch_size,))
            batch = {k: v[index] for k, v in inputs.items()} if isinstance(inputs, dict) else inputs[index]
            loss = torch.nn.functional.mse_loss(actor.mean_action(batch), answers[index])
            optimizer.zero_grad()
            loss.backward()
            for group in optimizer.param_groups:
                group["lr"] = learning_rate(config, step)
            optimizer.step()
            if passed_a_tenth(step, step + 1, config.updates):
                progress(f"round {round_ + 1}/{config.rounds}: {step + 1:,} of {config.updates:,} steps, loss "
                         f"{float(loss.detach()):.4f} ({time.monotonic() - started:.0f} s)")
        losses.append(float(loss.detach()))
        progress(f"round {round_ + 1}/{config.rounds}: {len(answers):,} observations, loss {losses[-1]:.4f}; its "
                 f"{count} new episode{'s' if count != 1 else ''} ended at {np.mean(ends[-count:]):.2f} dB "
                 f"({time.monotonic() - started:.0f} s)")
    actor.eval()
    psnr = [episodes.play(EVAL_SEED + i, player.deterministic, keep=False) for i in range(config.eval_episodes)]
    progress(f"the policy's 10 queries on {config.eval_episodes} training episodes: {np.mean(psnr):.2f} dB")
    episodes.env.close()
    return actor, {"score": "psnr", "mean_psnr": float(np.mean(psnr)), "episodes": config.eval_episodes,
                   "losses": losses, "observations": len(answers),
                   "seconds": round(time.monotonic() - started, 1)}


def learning_rate(config: PretrainConfig, step: int) -> float:
    """The learning rate of a round's `step`-th Adam step (from 0), by `config.lr_schedule`."""
    if config.lr_schedule == "constant":
        return config.lr
    return config.lr * 0.5 * (1.0 + math.cos(math.pi * step / config.updates))


def passed_a_tenth(before: int, after: int, count: int) -> bool:
    """Whether `after` of `count` items done completes another tenth of them (count // 10, at least
    1) that `before` did not, the last aside (its round's line says it): where long work reports
    its progress."""
    every = max(count // 10, 1)
    return after // every > before // every and after < count


def save(path: Path, actor: td3.DeterministicPolicy, config: PretrainConfig, evaluation: dict) -> Path:
    """The policy as a policy checkpoint (what best.pt is), its evaluation beside it."""
    from l2r.learner.checkpoint import save_policy_checkpoint

    return save_policy_checkpoint(path, policy_state(actor), dict(actor.spec), version=config.rounds,
                                  updates=config.rounds * config.updates, action_repeat=1,
                                  evaluation=evaluation | {"warm_start": "hidden parameters of random goals"})
