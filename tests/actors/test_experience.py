"""ChunkBuilder: the chunks it cuts decode to exactly the transitions that were added."""

import numpy as np
import pytest

from l2r.actors.experience import ChunkBuilder
from l2r.protocol import ExperienceChunk, decode, encode


def run(builder: ChunkBuilder, ends: dict[int, str], steps: int, rng: np.random.Generator):
    """Feed `steps` steps; `ends[t]` ends the episode at step t ("terminated" or "truncated").
    Returns the chunks taken whenever the builder is full, and the true transitions."""
    obs = rng.normal(size=4).astype(np.float32)
    builder.begin(obs)
    chunks, truth = [], []
    for t in range(steps):
        action = rng.random(2).astype(np.float32)
        next_obs = rng.normal(size=4).astype(np.float32)
        kind = ends.get(t)
        start = rng.normal(size=4).astype(np.float32) if kind else None
        builder.add(action, float(t), kind == "terminated", kind == "truncated", next_obs, start, now=float(t),
                    log_prob=-0.5 * t)
        truth.append((obs, action, float(t), kind == "terminated", kind == "truncated", next_obs, -0.5 * t))
        obs = start if kind else next_obs
        if builder.full:
            chunks.append(builder.take(seq=len(chunks), policy_version=7))
    return chunks, truth


@pytest.mark.parametrize("ends", [{}, {3: "terminated"}, {7: "truncated"}, {0: "terminated", 1: "truncated", 9: "terminated"}])
def test_chunks_round_trip_to_the_transitions_added(ends):
    rng = np.random.default_rng(0)
    builder = ChunkBuilder(actor_id=2, env_id=1, epoch=5, capacity=4)
    chunks, truth = run(builder, ends, 12, rng)
    assert [c.seq for c in chunks] == [0, 1, 2] and all(c.size == 4 for c in chunks)
    got = []
    for chunk in chunks:
        back = decode(encode(chunk), ExperienceChunk)
        assert (back.actor_id, back.env_id, back.epoch, back.policy_version) == (2, 1, 5, 7)
        nxt = back.next_obs()
        for t in range(back.size):
            got.append((back.obs[t], back.actions[t], back.rewards[t], back.terminated[t], back.truncated[t], nxt[t],
                        back.log_probs[t]))
    assert len(got) == len(truth)
    for g, w in zip(got, truth):
        np.testing.assert_array_equal(g[0], w[0])
        np.testing.assert_array_equal(g[1], w[1])
        assert (g[2], g[3], g[4], g[6]) == (w[2], w[3], w[4], w[6])
        np.testing.assert_array_equal(g[5], w[5])


def test_take_of_an_empty_builder_is_none_and_a_partial_chunk_is_sent():
    rng = np.random.default_rng(1)
    builder = ChunkBuilder(0, 0, 0, capacity=64)
    builder.begin(rng.normal(size=4))
    assert builder.take(0, 0) is None
    builder.add(np.zeros(2), 1.0, False, False, np.ones(4), None, now=3.0, log_prob=0.0)
    assert builder.started_at == 3.0 and len(builder) == 1
    chunk = builder.take(0, 0)
    assert chunk.size == 1 and len(builder) == 0
    np.testing.assert_array_equal(chunk.obs[1], np.ones(4))
