"""Messages of every kind with recognisable contents, for protocol and replay tests."""

from __future__ import annotations

import numpy as np

from l2r.protocol import (
    ActorId, ActorIdRequest, EpisodeSummary, EvaluationRound, ExperienceChunk, Frame, Gradient, LearnerVersion,
    NotReady, PriorityUpdate, ReplayAck, SampleBatch, SampleRequest, Stats, Weights,
)


def make_chunk(actor_id: int = 0, seq: int = 0, steps: int = 10, ends: tuple[int, ...] = (), epoch: int = 1,
               version: int = 0, obs_dim: int = 41, act_dim: int = 18, truncate: tuple[int, ...] = ()) -> ExperienceChunk:
    """A chunk whose observation rows say where they come from: row t of chunk seq holds
    ``seq * 1000 + t`` (an episode's final observation after step t holds its negative)."""
    base = seq * 1000 + actor_id * 1_000_000
    obs = np.repeat(np.arange(base, base + steps + 1, dtype=np.float32)[:, None], obs_dim, axis=1)
    terminated = np.zeros(steps, bool)
    terminated[list(ends)] = True
    truncated = np.zeros(steps, bool)
    truncated[list(truncate)] = True
    inner = [t for t in range(steps - 1) if terminated[t] or truncated[t]]
    final_obs = np.array([np.full(obs_dim, -(base + t + 1), np.float32) for t in inner], np.float32).reshape(-1, obs_dim)
    actions = np.repeat(np.arange(base, base + steps, dtype=np.float32)[:, None], act_dim, axis=1) / 1e6
    rewards = np.arange(base, base + steps, dtype=np.float32)
    return ExperienceChunk(actor_id, 0, epoch, seq, version, obs, actions, rewards, terminated, truncated, final_obs)


def stream_chunk(first: int, size: int, seq: int, env_id: int = 0, ends=(), truncate=(), actor_id: int = 0,
                 obs_dim: int = 2, act_dim: int = 1) -> ExperienceChunk:
    """Steps ``first`` .. ``first + size - 1`` of one environment's stream: step k sees observation
    k + 1000 * env_id and earns reward k + 1; an episode that ends at step k (``ends``: terminated,
    ``truncate``: time limit; global step numbers) has the final observation -(k + 1) - 1000 * env_id,
    and the next episode starts at observation k + 1."""
    offset = 1000 * env_id
    k = np.arange(first, first + size)
    terminated, truncated = np.isin(k, ends), np.isin(k, truncate)
    obs = (np.arange(first, first + size + 1) + offset).astype(np.float32)
    if terminated[-1] or truncated[-1]:
        obs[-1] = -(first + size) - offset
    inner = k[:-1][(terminated | truncated)[:-1]]
    return ExperienceChunk(actor_id, env_id, 1, seq, 0, np.repeat(obs[:, None], obs_dim, 1),
                           np.zeros((size, act_dim), np.float32), (k + 1).astype(np.float32), terminated, truncated,
                           np.repeat((-(inner + 1) - offset).astype(np.float32)[:, None], obs_dim, 1))


def every_message() -> list:
    rng = np.random.default_rng(0)
    b = 8
    return [
        make_chunk(3, 7, steps=12, ends=(4,), truncate=(11,)),
        Weights(5, {"pi.0.weight": rng.random((4, 41), np.float32), "pi.0.bias": np.zeros(4, np.float16),
                    "observation_filter.count": np.array(3.0, np.float32)},  # a 0-d buffer keeps its shape
                {"hidden": [512, 512], "activation": "elu"}),
        SampleRequest(256, 2, True, 9, n_step=3, gamma=0.99),
        SampleBatch(1, 1000, True, rng.random((b, 41), np.float32), rng.random((b, 18), np.float32),
                    rng.random(b, np.float32), rng.random((b, 41), np.float32), np.zeros(b, bool), np.ones(b, bool),
                    np.arange(b, dtype=np.int64), np.arange(b, dtype=np.int64) + 5, np.full(b, 1e-3),
                    np.arange(b, dtype=np.int64)),
        NotReady(0, "waiting for data", 12, 0.05),
        PriorityUpdate(np.arange(4, dtype=np.int64), np.arange(4, dtype=np.int64), np.ones(4, np.float32)),
        ReplayAck(0, np.array([3, 5]), np.array([17, 2**62]), np.array([40, 9]), np.array([2, 0]), np.array([7, 31])),
        EpisodeSummary(1, 2, 12.5, 3.25, 300, 7, 1, 42, evaluation=True, time=1.5),
        EvaluationRound(1, 7),
        Stats("replay", "0", 123.0, {"size": 10, "inserts_per_s": 2.5}),
        LearnerVersion(11, 2200, 5.0),
        Frame(1, 0, 3, 17, {"xpos": rng.random((12, 3))}, {"reward": 0.5}),
        Frame(2, 1, 0, 4, {}, {"reward": 1.0}, {"pixels": np.arange(60, dtype=np.uint8).reshape(1, 3, 4, 5)}),
        ActorIdRequest("actor-7f3a:7"),
        ActorId("actor-7f3a:7", 12),
        Gradient(3, 5, 5, rng.random(300, np.float32), np.array([5.0, *rng.random(82)])),  # last: rng order
    ]


def make_image_chunk(steps: int = 6, ends: tuple[int, ...] = (2,), side: int = 84, seq: int = 0) -> ExperienceChunk:
    """A camera task's chunk: pixels uint8[3, side, side] beside a float32[5] state. Every byte
    of pixel row t is t, and of the final observation after step t, 200 + t; the state rows
    hold t, and -(t + 1)."""
    rows = np.arange(steps + 1)
    inner = np.array([t for t in ends if t < steps - 1], int)
    terminated = np.zeros(steps, bool)
    terminated[list(ends)] = True

    def pixels(values: np.ndarray) -> np.ndarray:
        return np.broadcast_to(values.astype(np.uint8)[:, None, None, None], (len(values), 3, side, side)).copy()

    obs = {"pixels": pixels(rows), "state": np.repeat(rows[:, None], 5, axis=1).astype(np.float32)}
    final_obs = {"pixels": pixels(200 + inner), "state": np.repeat(-(inner[:, None] + 1), 5, axis=1).astype(np.float32)}
    return ExperienceChunk(4, 1, 9, seq, 3, obs, np.full((steps, 6), 0.5, np.float32), rows[:-1].astype(np.float32),
                           terminated, np.zeros(steps, bool), final_obs)


def make_frames_batch(b: int = 4, k: int = 3, side: int = 84) -> SampleBatch:
    """A batch of b transitions in a row, stacks of k frames: frame i is all i, transition i's
    observation is frames i .. i+k-1 and its next observation frames i+1 .. i+k, so the
    batch carries b + k distinct frames."""
    frames = np.broadcast_to(np.arange(b + k, dtype=np.uint8)[:, None, None, None], (b + k, 3, side, side)).copy()
    stacks = np.arange(b)[:, None] + np.arange(k)
    return SampleBatch(2, 500, False, None, np.zeros((b, 6), np.float32), np.ones(b, np.float32), None,
                       np.zeros(b, bool), np.zeros(b, bool), np.arange(b, dtype=np.int64),
                       np.arange(b, dtype=np.int64), np.full(b, 1 / 500), np.zeros(b, np.int64),
                       frames={"pixels": frames}, obs_frames=stacks, next_obs_frames=stacks + 1)
