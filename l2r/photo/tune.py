"""Tuners of the pipeline's nine parameters towards a goal image, each counted in queries (one
pipeline run on the working image, as `l2r/PhotoTune-v0` counts its steps): random search,
CMA-ES (the `cma` package) and a trained tuner's policy, and the held-out problems they are
compared on.

Both optimisers search the nine actions in [-1, 1] for the highest PSNR to the goal and return
the best query so far; neither depends on its budget (random search draws independently, CMA-ES
runs its default population of 10 with sigma0 0.5, a quarter of the range, from the neutral
settings), so one run of N queries gives the result of every budget up to N: the best of its
first n queries is what a run of budget n returns. A policy returns its last query, as its
episode ends: that image is the one `l2r/PhotoTune-v0` scores.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from l2r.photo import TUNE_IDS, photos
from l2r.photo.env import PhotoTuneEnv, psnr_db
from l2r.photo.pipeline import PARAMETERS, finish, params_from_actions

BUDGETS = (10, 50, 200, 500)
"""The query budgets the optimisers are compared at (RLPixTuner's figures: its tuner at about 10
queries, optimisers at about 200, CMA-ES at 500)."""
POLICY_QUERIES = 10
CMA_SIGMA0 = 0.5


@dataclass(frozen=True)
class Problem:
    """A working image (float32 [3, 256, 256] in [0, 1]) and the goal to tune it towards."""

    name: str
    source: np.ndarray
    goal: np.ndarray


@dataclass
class Trace:
    """The queries of one tuner on one problem, in order: actions [n, 9], PSNR [n] in dB."""

    actions: np.ndarray
    psnr_db: np.ndarray

    def best(self, budget: int | None = None) -> int:
        """The index of the best of the first `budget` queries (all: None)."""
        return int(np.argmax(self.psnr_db[:budget]))


def finished(problem: Problem, actions: np.ndarray) -> np.ndarray:
    """The problem's source through the pipeline with these actions' parameters."""
    return finish(problem.source[None], params_from_actions(actions))[0]


def query(problem: Problem, actions: np.ndarray) -> float:
    """One query: the PSNR in dB of the source finished with `actions` to the goal."""
    return float(psnr_db(finished(problem, actions)[None], problem.goal[None])[0])


def ssim(image: np.ndarray, goal: np.ndarray) -> float:
    """SSIM of float [3, H, W] images in [0, 1] (scikit-image's, over the three channels)."""
    from skimage.metrics import structural_similarity

    return float(structural_similarity(image, goal, channel_axis=0, data_range=1.0))


def random_search(problem: Problem, queries: int, seed: int = 0) -> Trace:
    """`queries` actions drawn uniformly in [-1, 1]^9."""
    actions = np.random.default_rng(seed).uniform(-1.0, 1.0, (queries, len(PARAMETERS))).astype(np.float32)
    return Trace(actions, np.array([query(problem, a) for a in actions]))


def cmaes(problem: Problem, queries: int, seed: int = 0) -> Trace:
    """CMA-ES from the neutral actions with step size CMA_SIGMA0, inside the bounds [-1, 1],
    minimising -PSNR; the queries of a generation cut short by the budget still count."""
    import cma

    # cma's seed 0 means "from the clock": shifted by one so that every seed reproduces.
    strategy = cma.CMAEvolutionStrategy(np.zeros(len(PARAMETERS)), CMA_SIGMA0,
                                        {"bounds": [-1.0, 1.0], "seed": seed + 1, "verbose": -9})
    tried, values = [], []
    while len(values) < queries:
        candidates = strategy.ask()
        scores = []
        for x in candidates[:queries - len(values)]:
            tried.append(np.clip(x, -1.0, 1.0).astype(np.float32))
            scores.append(query(problem, tried[-1]))
        values += scores
        if len(scores) == len(candidates):
            strategy.tell(candidates, [-v for v in scores])
    return Trace(np.array(tried), np.array(values))


def policy_tune(policy, problem: Problem, env_ids: tuple[str, ...] = TUNE_IDS) -> Trace:
    """The deterministic actions of a policy (l2r.policy) through the photo task of `env_ids` it
    was trained on (by default `l2r/PhotoTune-v0` or `l2r/PhotoTuneStats-v0`; told by its observation spec)
    as an actor makes it (l2r.actors.actor.make_task), posed this problem: one query per step, up
    to 10. ValueError when the policy takes other observations or actions than each task's."""
    from l2r.actors.actor import fields_of, make_task
    from l2r.actors.frame_stack import FrameStack, frame_stack_of
    from l2r.policy import act
    from l2r.protocol import ObservationSpec

    trained = ObservationSpec.from_policy_spec(policy.spec), policy.spec["act_dim"]
    tasks = {env_id: ObservationSpec.from_space(make_task(env_id).observation_space) for env_id in env_ids}
    env_id = next((env_id for env_id, spec in tasks.items() if trained == (spec, len(PARAMETERS))), None)
    if env_id is None:
        raise ValueError(f"the policy takes observations {trained[0]} and gives {trained[1]} actions; " + "; ".join(
            f"{env_id} gives {spec}" for env_id, spec in tasks.items()) + f", and each takes {len(PARAMETERS)}")
    env, spec = make_task(env_id), tasks[env_id]
    frames = FrameStack(spec, frame_stack_of(policy.spec), 1)
    obs, _ = env.reset(options={"source": problem.source, "goal": problem.goal})
    frames.reset(0, fields_of(spec, obs, env_id))
    tried, values, over = [], [], False
    while not over:
        excitation = act(policy, frames.stacked(), deterministic=True)[0]
        obs, _, terminated, truncated, info = env.step(excitation)
        tried.append(2.0 * excitation - 1.0)  # what the task's rescaling hands the pipeline
        values.append(float(info["psnr_db"]))
        frames.push(0, fields_of(spec, obs, env_id))
        over = terminated or truncated
    env.close()
    return Trace(np.array(tried, np.float32), np.array(values))


def held_out_problems(count: int, seed: int = 0, folder: str | Path | None = None,
                      task: type[PhotoTuneEnv] = PhotoTuneEnv, goals: str = "random") -> list[Problem]:
    """`count` problems as `task` poses them on seeds seed, seed + 1, ...: crops of the held-out
    photos (the test split, or the test split of a FiveK folder's inputs) and goals made with
    hidden random parameters (RLPixTuner's FiveK-Random) or, with `goals="looks"`, with another
    held-out scene's look; with `PhotoEnhanceEnv`, the random edits are the sources and the
    crops the goals."""
    sources = None
    if folder is not None:
        pairs = photos.fivek_split(photos.fivek_pairs(folder), "test")
        sources = {source.stem: photos.read_image(source) for source, _ in pairs}
    env = task(split="test", sources=sources, goals=goals)
    problems = []
    for i in range(count):
        _, info = env.reset(seed=seed + i)
        look = f" in {info['look']}'s look" if info["look"] else ""
        problems.append(Problem(f"{env.photo_name}@{seed + i}{look}", env.source, env.goal))
    return problems


def compare(problems: list[Problem], budgets: tuple[int, ...] = BUDGETS, policy=None, seed: int = 0) -> dict:
    """Mean PSNR (dB) and SSIM to the goal over the problems: of the untouched input, of random
    search and CMA-ES at each budget, and of the policy's 10 queries (None without a policy)."""
    sums: dict[str, list[tuple[float, float]]] = {}

    def add(key: str, image: np.ndarray, problem: Problem, psnr: float) -> None:
        sums.setdefault(key, []).append((psnr, ssim(image, problem.goal)))

    for i, problem in enumerate(problems):
        add("input", problem.source, problem, float(psnr_db(problem.source[None], problem.goal[None])[0]))
        for method, search in (("random", random_search), ("cmaes", cmaes)):
            trace = search(problem, max(budgets), seed + i)
            for budget in budgets:
                best = trace.best(budget)
                add(f"{method}/{budget}", finished(problem, trace.actions[best]), problem, trace.psnr_db[best])
        if policy is not None:
            trace = policy_tune(policy, problem)
            add("policy", finished(problem, trace.actions[-1]), problem, trace.psnr_db[-1])

    def mean(key: str, which: int) -> float | None:
        return float(np.mean([pair[which] for pair in sums[key]])) if key in sums else None

    result = {"photos": len(problems), "input_psnr_db": mean("input", 0), "input_ssim": mean("input", 1),
              "policy_queries": POLICY_QUERIES, "policy_psnr_db": mean("policy", 0), "policy_ssim": mean("policy", 1)}
    for method in ("random", "cmaes"):
        result[f"{method}_psnr_db"] = {str(b): mean(f"{method}/{b}", 0) for b in budgets}
        result[f"{method}_ssim"] = {str(b): mean(f"{method}/{b}", 1) for b in budgets}
    return result
