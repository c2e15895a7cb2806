"""The photo tuner's two encoders side by side (`--encoder drq` and `dual`, photo/td3's networks):
their size, the speed of the TD3 update, and a supervised proxy of what each learns. Not RL.

The proxy: each encoder with the policy's projection and hidden layers, trained by Adam to output
the goal's hidden parameters (the answer in one query) from the first observation of an episode
(the untouched crop, the goal, the state); its mean squared error on first observations of the
held-out photos, every quarter of --steps (outputting 0 scores about 0.32).

Prints one JSON line. Figures, per encoder:
  parameters, policy_values      actor and critics' parameters; what a published policy holds
  updates_per_s, updates_range   the photo/td3 update on one batch of --batch-size (median, slowest
                                 and fastest of --rounds interleaved rounds of --updates each)
  proxy_test_mse                 [step, held-out error] pairs; proxy_cpu_s its CPU seconds
Figures of 2026-11-26: docs/photo.md ("The dual-path encoder against DrQ-v2's").
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import gymnasium
import numpy as np
import torch

import l2r.photo  # noqa: F401  (registers the tasks)
from l2r.encoders import IMAGE_VIEWS
from l2r.learner.sac import batch_from_frames
from l2r.learner.steps import GradientSteps
from l2r.learner.td3 import TD3Config, init_state, update
from l2r.photo.pipeline import actions_from_params
from l2r.policy import DeterministicPolicy
from l2r.spaces import task_spaces

sys.path.insert(0, str(Path(__file__).parent))
from env_speed import cpu_flags, cpu_model  # noqa: E402  (this folder's: the same machine record)

TASK = "l2r/PhotoTune-v0"


def photo_td3(encoder: str, batch_size: int) -> TD3Config:
    """The learner's TD3 as `l2r up --env-id l2r/PhotoTune-v0` configures it (l2r.recipes, PHOTO)."""
    return TD3Config(hidden=(400, 300), activation="relu", layer_norm=False, batch_size=batch_size, actor_lr=1e-4,
                     critic_lr=1e-4, gamma=0.9, tau=0.007, policy_delay=2, target_noise=0.04, noise_clip=0.01,
                     precision="float32", frame_stack=1, augment_pad=0, encoder=encoder)


def first_observations(split: str, n: int, seed: int) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """n first observations of the split's episodes, and the goal's parameters as actions."""
    env = gymnasium.make(TASK, split=split).unwrapped
    fields, answers = {}, []
    for i in range(n):
        obs, _ = env.reset(seed=seed + i)
        for name, value in obs.items():
            fields.setdefault(name, []).append(value)
        answers.append(actions_from_params(env.goal_params))
    return ({name: torch.as_tensor(np.stack(values)) for name, values in fields.items()},
            torch.as_tensor(np.stack(answers), dtype=torch.float32))


def update_rates(observation, act_dim: int, batch_size: int, updates: int, rounds: int) -> dict[str, list[float]]:
    rng = np.random.default_rng(0)
    frames = {name: (rng.integers(0, 256, (2 * batch_size, *f.shape), dtype=np.uint8) if f.dtype == np.uint8
                     else rng.normal(size=(2 * batch_size, *f.shape)).astype(np.float32))
              for name, f in observation.fields.items()}
    rows = np.arange(2 * batch_size).reshape(batch_size, 2)
    batch = batch_from_frames(frames, rows[:, :1], rows[:, 1:], rng.random((batch_size, act_dim), dtype=np.float32),
                              rng.random(batch_size, dtype=np.float32), np.zeros(batch_size, bool), device="cpu")
    runs = {}
    for encoder in IMAGE_VIEWS:
        config = photo_td3(encoder, batch_size)
        state = init_state(config, observation, act_dim, seed=0)
        runs[encoder] = state, GradientSteps(update, config, "off", "cpu", policy_delay=config.policy_delay)
        runs[encoder][1](state, batch)  # allocator, lazy initialisation
    rates: dict[str, list[float]] = {encoder: [] for encoder in runs}
    for _ in range(rounds):
        for encoder, (state, steps) in runs.items():
            started = time.perf_counter()
            for _ in range(updates):
                steps(state, batch)
            rates[encoder].append(updates / (time.perf_counter() - started))
    return rates


def proxy(encoder: str, observation, act_dim: int, train, test, steps: int, batch_size: int) -> dict:
    spec = init_state(photo_td3(encoder, batch_size), observation, act_dim).actor.spec
    torch.manual_seed(0)
    policy = DeterministicPolicy(spec)
    opt = torch.optim.Adam(policy.parameters(), lr=1e-4)
    rng = np.random.default_rng(0)

    def test_mse() -> float:
        with torch.no_grad():
            return round(float(((policy(test[0]) - test[1]) ** 2).mean()), 4)

    curve, cpu = [(0, test_mse())], time.process_time()
    for step in range(1, steps + 1):
        rows = torch.as_tensor(rng.integers(0, len(train[1]), batch_size))
        loss = ((policy({name: field[rows] for name, field in train[0].items()}) - train[1][rows]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
        if step % max(1, steps // 4) == 0:
            curve.append((step, test_mse()))
    return {"proxy_test_mse": curve, "proxy_cpu_s": round(time.process_time() - cpu)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--batch-size", type=int, default=128, help="the update's batch (default: photo/td3's %(default)s)")
    p.add_argument("--updates", type=int, default=10, help="updates per timing round (default: %(default)s)")
    p.add_argument("--rounds", type=int, default=3, help="interleaved timing rounds (default: %(default)s)")
    p.add_argument("--steps", type=int, default=400, help="proxy training steps (default: %(default)s)")
    p.add_argument("--proxy-batch", type=int, default=32, help="proxy batch (default: %(default)s)")
    p.add_argument("--train", type=int, default=1024, help="proxy training observations (default: %(default)s)")
    p.add_argument("--test", type=int, default=128, help="held-out observations (default: %(default)s)")
    p.add_argument("--threads", type=int, default=2, help="torch threads (default: %(default)s)")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    observation, act_dim = task_spaces(TASK)
    started = time.perf_counter()
    result = {"bench": "photo_encoders", "cpu": cpu_model(), "cpu_flags": cpu_flags(), "torch": torch.__version__, "threads": args.threads,
              "batch_size": args.batch_size, "proxy_steps": args.steps, "proxy_batch": args.proxy_batch}
    rates = update_rates(observation, act_dim, args.batch_size, args.updates, args.rounds)
    train = first_observations("train", args.train, 0)
    test = first_observations("test", args.test, 10_000)
    result["proxy_zero_mse"] = round(float((test[1] ** 2).mean()), 4)
    for encoder, values in rates.items():
        state = init_state(photo_td3(encoder, args.batch_size), observation, act_dim)
        result[encoder] = {
            "parameters": sum(p.numel() for p in [*state.actor.parameters(), *state.critic.parameters()]),
            "policy_values": sum(t.numel() for t in state.actor.state_dict().values()),
            "updates_per_s": round(statistics.median(values), 3),
            "updates_range": [round(min(values), 3), round(max(values), 3)],
            **proxy(encoder, observation, act_dim, train, test, args.steps, args.proxy_batch)}
    result["seconds"] = round(time.perf_counter() - started, 1)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
