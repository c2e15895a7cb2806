"""Whole-system speed: `l2r up` against the reference solution's architecture, on our env.

The baseline is that architecture rebuilt here from its description: worker processes step
the runner (action repeat 3) with the policy read from torch shared memory and push every
transition through a multiprocessing manager proxy around a list buffer (one call per
transition); a trainer process draws a batch of 640 with `random.sample` inside the manager
and runs 3 SAC gradient steps on it, updating the shared networks in place.

l2r runs twice through `l2r up` on the same machine, with the same networks (3 x 512, ELU,
LayerNorm), batch 640 and 3 gradient steps per batch:
  matched: the replay rate limiter holds samples-per-insert at the baseline's measured ratio;
  free:    no ratio limit, actors as fast as they go while the learner trains.
Env steps are transitions (one action-repeated step = 3 x 0.01 s); updates are gradient steps.

Prints one JSON line. `--quick` shortens every phase (about 1.5 minutes in all).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import random
import subprocess
import sys
import tempfile
import time
from multiprocessing.managers import BaseManager
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

ROOT = Path(__file__).resolve().parents[1]
BATCH, REPEAT, HIDDEN = 640, 3, (512, 512, 512)
OBS, ACT = 41, 18


# -- the reference architecture ------------------------------------------------------------------

class ListBuffer:
    """The reference's replay: a Python list, one transition per push, random.sample per batch."""

    def __init__(self, capacity: int = 1_000_000):
        self.items: list = []
        self.capacity = capacity
        self.pushed = 0

    def push(self, transition) -> None:
        if len(self.items) >= self.capacity:
            self.items.pop(0)
        self.items.append(transition)
        self.pushed += 1

    def sample(self, k: int) -> list:
        return random.sample(self.items, k)

    def size(self) -> int:
        return len(self.items)

    def total(self) -> int:
        return self.pushed


class BufferManager(BaseManager):
    pass


BufferManager.register("ListBuffer", ListBuffer)


def mlp(inp: int, out: int) -> nn.Sequential:
    layers, width = [], inp
    for h in HIDDEN:
        layers += [nn.Linear(width, h), nn.LayerNorm(h), nn.ELU()]
        width = h
    return nn.Sequential(*layers, nn.Linear(width, out))


def sample_action(actor: nn.Module, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    mean, log_std = actor(obs).chunk(2, -1)
    log_std = log_std.clamp(-5, 2)
    dist = torch.distributions.Normal(mean, log_std.exp())
    u = dist.rsample()
    a = torch.tanh(u)
    return a, (dist.log_prob(u) - torch.log(1 - a.pow(2) + 1e-6)).sum(-1)


def worker(buffer, actor: nn.Module, seed: int, steps, stop) -> None:
    """Step one env with the shared policy; push every transition through the proxy."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 2)  # MuJoCo's instability warnings would flood the bench's output
    torch.set_num_threads(1)
    import gymnasium
    import l2r.sim  # noqa: F401
    from l2r.sim.wrappers import ActionRepeat
    env = ActionRepeat(gymnasium.make("l2r/Run-v0", difficulty=0, seed=seed), 3)
    obs, _ = env.reset(seed=seed)
    while not stop.is_set():
        with torch.no_grad():
            a, _ = sample_action(actor, torch.as_tensor(obs).unsqueeze(0))
        action = ((a[0] + 1) / 2).numpy()
        nxt, reward, terminated, truncated, _ = env.step(action)
        buffer.push((obs.tolist(), action.tolist(), float(reward), nxt.tolist(), bool(terminated)))
        with steps.get_lock():
            steps.value += 1
        obs = env.reset()[0] if terminated or truncated else nxt


def trainer(buffer, actor: nn.Module, critic1: nn.Module, critic2: nn.Module, updates, stop) -> None:
    """Batches of 640 from the proxy, 3 SAC steps each, on the shared networks."""
    torch.set_num_threads(1)
    targ1, targ2 = mlp(OBS + ACT, 1), mlp(OBS + ACT, 1)
    targ1.load_state_dict(critic1.state_dict())
    targ2.load_state_dict(critic2.state_dict())
    log_alpha = torch.zeros(1, requires_grad=True)
    opt_q = torch.optim.Adam([*critic1.parameters(), *critic2.parameters()], lr=3e-4)
    opt_pi = torch.optim.Adam(actor.parameters(), lr=3e-4)
    opt_alpha = torch.optim.Adam([log_alpha], lr=3e-4)
    while buffer.size() < BATCH and not stop.is_set():
        time.sleep(0.05)
    while not stop.is_set():
        o, a, r, o2, d = zip(*buffer.sample(BATCH))
        o, a, o2 = (torch.tensor(x, dtype=torch.float32) for x in (o, a, o2))
        a = a * 2 - 1
        r, d = torch.tensor(r, dtype=torch.float32), torch.tensor(d, dtype=torch.float32)
        for _ in range(REPEAT):
            alpha = log_alpha.exp().detach()
            with torch.no_grad():
                a2, logp2 = sample_action(actor, o2)
                x2 = torch.cat([o2, a2], -1)
                q_targ = torch.min(targ1(x2), targ2(x2)).squeeze(-1) - alpha * logp2
                y = 10.0 * r + 0.99 * (1 - d) * q_targ
            x = torch.cat([o, a], -1)
            q_loss = F.mse_loss(critic1(x).squeeze(-1), y) + F.mse_loss(critic2(x).squeeze(-1), y)
            opt_q.zero_grad()
            q_loss.backward()
            opt_q.step()
            pi, logp = sample_action(actor, o)
            xp = torch.cat([o, pi], -1)
            pi_loss = (alpha * logp - torch.min(critic1(xp), critic2(xp)).squeeze(-1)).mean()
            opt_pi.zero_grad()
            pi_loss.backward()
            opt_pi.step()
            alpha_loss = -(log_alpha * (logp.detach() - ACT)).mean()
            opt_alpha.zero_grad()
            alpha_loss.backward()
            opt_alpha.step()
            with torch.no_grad():
                for net, targ in ((critic1, targ1), (critic2, targ2)):
                    for p, tp in zip(net.parameters(), targ.parameters()):
                        tp.mul_(0.995).add_(0.005 * p)
            with updates.get_lock():
                updates.value += 1


def run_baseline(seconds: float, workers: int) -> dict:
    ctx = mp.get_context("fork")
    manager = BufferManager()
    manager.start()
    buffer = manager.ListBuffer()
    actor, critic1, critic2 = mlp(OBS, 2 * ACT), mlp(OBS + ACT, 1), mlp(OBS + ACT, 1)
    for net in (actor, critic1, critic2):
        net.share_memory()
    steps, updates, stop = ctx.Value("q", 0), ctx.Value("q", 0), ctx.Event()
    procs = [ctx.Process(target=worker, args=(buffer, actor, 100 + i, steps, stop)) for i in range(workers)]
    procs.append(ctx.Process(target=trainer, args=(buffer, actor, critic1, critic2, updates, stop)))
    for p in procs:
        p.start()
    # Measure once training is under way, as for l2r.
    deadline = time.monotonic() + 120
    while updates.value == 0 and time.monotonic() < deadline:
        time.sleep(0.1)
    s0, u0, t0 = steps.value, updates.value, time.monotonic()
    time.sleep(seconds)
    s1, u1, t1 = steps.value, updates.value, time.monotonic()
    stop.set()
    for p in procs:
        p.join(10)
        if p.is_alive():
            p.kill()
    manager.shutdown()
    return {"env_steps_per_s": (s1 - s0) / (t1 - t0), "updates_per_s": (u1 - u0) / (t1 - t0)}


# -- l2r -------------------------------------------------------------------------------------------

def run_l2r(seconds: float, actors: int, samples_per_insert: float, runs_dir: Path, warmup: float,
            extra: list[str]) -> dict:
    """`l2r up` for warm-up + seconds; rates over the measured window from its metrics.jsonl."""
    name = f"bench-{'matched' if samples_per_insert else 'free'}"
    cmd = [sys.executable, "-m", "l2r.cli", "up", "--seconds", str(seconds + warmup), "--name", name,
           "--runs-dir", str(runs_dir), "--actors", str(actors), "--envs-per-actor", "4", "--evaluators", "0",
           "--no-episode-logs", "--random-steps", "0", "--min-replay", str(4 * BATCH),
           "--batch-size", str(BATCH), "--samples-per-insert", str(samples_per_insert),
           "--device", "cpu", "--status-interval", "1", "--log-level", "WARNING",
           "--learner-arg=--update-repeat=3", "--learner-arg=--metrics-interval=1", *extra]
    subprocess.run(cmd, cwd=ROOT, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    run_dir = max(runs_dir.glob(f"{name}-*"))
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    status = [r for r in rows if r["type"] == "status" and r["elapsed"] >= warmup]
    first, last = status[0], status[-1]
    dt = last["elapsed"] - first["elapsed"]
    return {"env_steps_per_s": (last["env_steps"] - first["env_steps"]) / dt,
            "updates_per_s": (last["updates"] - first["updates"]) / dt}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=50.0, help="measured seconds per phase")
    p.add_argument("--warmup", type=float, default=15.0, help="seconds of each l2r phase not measured (start-up)")
    p.add_argument("--workers", type=int, default=2, help="baseline workers = l2r actors")
    p.add_argument("--quick", action="store_true", help="20 s phases")
    p.add_argument("--learner-threads", type=int, default=0, help="passed to l2r up (0: its default)")
    p.add_argument("--actor-nice", type=int, default=10, help="passed to l2r up")
    args = p.parse_args()
    seconds = 20.0 if args.quick else args.seconds
    base = run_baseline(seconds, args.workers)
    # The baseline's samples-per-insert: transitions sampled (one batch per 3 steps) per transition stored.
    ratio = base["updates_per_s"] / REPEAT * BATCH / max(base["env_steps_per_s"], 1e-9)
    extra = ["--learner-threads", str(args.learner_threads), "--actor-nice", str(args.actor_nice)]
    with tempfile.TemporaryDirectory() as tmp:
        matched = run_l2r(seconds, args.workers, ratio, Path(tmp), args.warmup, extra)
        free = run_l2r(seconds, args.workers, 0.0, Path(tmp), args.warmup, extra)
    out = {
        "matched_updates_per_s": matched["updates_per_s"],
        "matched_env_steps_per_s": matched["env_steps_per_s"],
        "matched_samples_per_insert": ratio,
        "free_env_steps_per_s": free["env_steps_per_s"],
        "free_updates_per_s": free["updates_per_s"],
        "baseline_env_steps_per_s": base["env_steps_per_s"],
        "baseline_updates_per_s": base["updates_per_s"],
        "matched_updates_ratio": matched["updates_per_s"] / max(base["updates_per_s"], 1e-9),
        "free_env_steps_ratio": free["env_steps_per_s"] / max(base["env_steps_per_s"], 1e-9),
        "learner_threads": args.learner_threads, "actor_nice": args.actor_nice, "workers": args.workers, "batch_size": BATCH, "update_repeat": REPEAT, "seconds_per_phase": seconds,
        "cpus": os.cpu_count(),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
