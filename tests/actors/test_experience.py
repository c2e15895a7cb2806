"""ChunkBuilder: the chunks it cuts decode to exactly the transitions that were added, the float32
vector in the version-1 form and a camera's fields, each in its own dtype, in the version-2 form."""

import msgpack
import numpy as np
import pytest

from l2r.actors.experience import ChunkBuilder
from l2r.protocol import ExperienceChunk, ObservationSpec, decode, encode

VECTOR = ObservationSpec.vector(4)
CAMERA = ObservationSpec.parse("pixels: uint8[3, 6, 5], state: float32[2]")


def observation(spec: ObservationSpec, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Random fields of ``spec``, as `ObservationSpec.fields_of` gives them."""
    return {name: (rng.integers(0, 256, field.shape) if field.dtype == np.uint8 else rng.normal(size=field.shape))
            .astype(field.dtype) for name, field in spec.fields.items()}


def run(builder: ChunkBuilder, ends: dict[int, str], steps: int, rng: np.random.Generator):
    """Feed `steps` steps; `ends[t]` ends the episode at step t ("terminated" or "truncated").
    Returns the chunks taken whenever the builder is full, and the true transitions."""
    spec = builder.observation
    obs = observation(spec, rng)
    builder.begin(obs)
    chunks, truth = [], []
    for t in range(steps):
        action = rng.random(2).astype(np.float32)
        next_obs = observation(spec, rng)
        kind = ends.get(t)
        start = observation(spec, rng) if kind else None
        builder.add(action, float(t), kind == "terminated", kind == "truncated", next_obs, start, now=float(t),
                    log_prob=-0.5 * t)
        truth.append((obs, action, float(t), kind == "terminated", kind == "truncated", next_obs, -0.5 * t))
        obs = start if kind else next_obs
        if builder.full:
            chunks.append(builder.take(seq=len(chunks), policy_version=7))
    return chunks, truth


def fields(spec: ObservationSpec, rows, t: int) -> dict[str, np.ndarray]:
    """Row t of a chunk's observations, as fields."""
    return {"state": rows[t]} if spec.vector_width is not None else {name: rows[name][t] for name in rows}


@pytest.mark.parametrize("spec", [VECTOR, CAMERA], ids=["vector", "camera"])
@pytest.mark.parametrize("ends", [{}, {3: "terminated"}, {7: "truncated"}, {0: "terminated", 1: "truncated", 9: "terminated"}])
def test_chunks_round_trip_to_the_transitions_added(ends, spec):
    rng = np.random.default_rng(0)
    builder = ChunkBuilder(actor_id=2, env_id=1, epoch=5, capacity=4, observation=spec)
    chunks, truth = run(builder, ends, 12, rng)
    assert [c.seq for c in chunks] == [0, 1, 2] and all(c.size == 4 for c in chunks)
    got = []
    for chunk in chunks:
        payload = encode(chunk)
        assert msgpack.unpackb(payload)["v"] == (1 if spec == VECTOR else 2)
        back = decode(payload, ExperienceChunk)
        assert (back.actor_id, back.env_id, back.epoch, back.policy_version) == (2, 1, 5, 7)
        nxt = back.next_obs()
        for t in range(back.size):
            got.append((fields(spec, back.obs, t), back.actions[t], back.rewards[t], back.terminated[t],
                        back.truncated[t], fields(spec, nxt, t), back.log_probs[t]))
    assert len(got) == len(truth)
    for g, w in zip(got, truth):
        for name, field in spec.fields.items():
            assert g[0][name].dtype == g[5][name].dtype == field.dtype  # a frame never became float32
            np.testing.assert_array_equal(g[0][name], w[0][name])
            np.testing.assert_array_equal(g[5][name], w[5][name])
        np.testing.assert_array_equal(g[1], w[1])
        assert (g[2], g[3], g[4], g[6]) == (w[2], w[3], w[4], w[6])


def test_a_vector_chunk_is_the_version_1_chunk_byte_for_byte():
    rng = np.random.default_rng(3)
    builder = ChunkBuilder(actor_id=2, env_id=1, epoch=5, capacity=4, observation=VECTOR)
    (chunk, *_), truth = run(builder, {1: "terminated"}, 4, rng)
    rows = [step[0]["state"] for step in truth] + [truth[-1][5]["state"]]
    rows[2] = truth[2][0]["state"]  # the next episode's first observation
    by_hand = ExperienceChunk(
        2, 1, 5, 0, 7, np.stack(rows), np.stack([step[1] for step in truth]),
        np.arange(4, dtype=np.float32), np.array([False, True, False, False]), np.zeros(4, bool),
        truth[1][5]["state"][None], np.array([step[6] for step in truth], np.float32))
    assert encode(chunk) == encode(by_hand)


def test_take_of_an_empty_builder_is_none_and_a_partial_chunk_is_sent():
    builder = ChunkBuilder(0, 0, 0, capacity=64, observation=VECTOR)
    builder.begin({"state": np.zeros(4, np.float32)})
    assert builder.take(0, 0) is None
    builder.add(np.zeros(2), 1.0, False, False, {"state": np.ones(4, np.float32)}, None, now=3.0, log_prob=0.0)
    assert builder.started_at == 3.0 and len(builder) == 1
    chunk = builder.take(0, 0)
    assert chunk.size == 1 and len(builder) == 0
    np.testing.assert_array_equal(chunk.obs[1], np.ones(4))
    assert chunk.final_obs.shape == (0, 4) and chunk.final_obs.dtype == np.float32


def test_a_camera_chunk_without_episode_ends_has_empty_final_rows_of_every_field():
    builder = ChunkBuilder(0, 0, 0, capacity=64, observation=CAMERA)
    builder.begin(observation(CAMERA, np.random.default_rng(0)))
    builder.add(np.zeros(2), 1.0, False, False, observation(CAMERA, np.random.default_rng(1)), None, now=0.0,
                log_prob=0.0)
    chunk = decode(encode(builder.take(0, 0)), ExperienceChunk)
    assert {name: (rows.dtype, rows.shape) for name, rows in chunk.final_obs.items()} == {
        "pixels": (np.uint8, (0, 3, 6, 5)), "state": (np.float32, (0, 2))}
