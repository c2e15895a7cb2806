"""A real `l2r-actor` on a real camera task (the suite's cartpole, 16 × 16 frames, rendered) feeding
a real `l2r-replay` started with `--observation`, over loopback Zenoh: one uint8 frame per step
reaches the shard, compressed, the frames of the chunks are the environment's own, resets go
where they belong, policies for other observations are refused, and the actor's stats count its
frames."""

from __future__ import annotations

import subprocess
import sys
import uuid

import msgpack
import numpy as np
import pytest

from l2r.actors.actor import ActorConfig, episode_seed, make_task
from l2r.policy import build_policy, policy_state
from l2r.protocol import (
    ExperienceChunk, Keys, SampleBatch, SampleRequest, Stats, Weights, decode, encode, wait_alive,
)
from tests.actors.camera import CAMERA, EPISODE_STEPS, IMAGE_SIZE, RENDERER, camera_shard, stop_all
from tests.actors.test_actor import SPEC
from tests.conftest import ROOT, wait_for

pytestmark = [pytest.mark.slow, pytest.mark.skipif(not RENDERER, reason="no EGL or OSMesa to render with")]

CHUNK = 4


def replayed(actions: np.ndarray, episodes: int) -> list[list[np.ndarray]]:
    """The frames env 0 of actor 0 (seed 0) shows over its first ``episodes`` episodes under
    ``actions``, episode by episode, made again here."""
    env = make_task(CAMERA)
    config, out, taken = ActorConfig(seed=0, actor_id=0), [], 0
    try:
        for episode in range(episodes):
            obs, _ = env.reset(seed=episode_seed(config, 0, episode))
            frames = [obs["pixels"]]
            for _ in range(EPISODE_STEPS):
                obs, *_ = env.step(actions[taken])
                frames.append(obs["pixels"])
                taken += 1
            out.append(frames)
    finally:
        env.close()
    return out


def test_a_camera_actor_sends_its_environment_s_frames_one_a_step_to_a_camera_replay_shard(tmp_path):
    run = f"test-camera-{uuid.uuid4().hex[:8]}"
    keys = Keys(run)
    replay, session = camera_shard(run, tmp_path)
    payloads: list[bytes] = []
    stats: dict[str, dict] = {}
    vector_weights = encode(Weights(3, policy_state(build_policy(SPEC)), SPEC))  # a policy of 41 floats
    subs = [session.declare_subscriber(keys.experience_of_shard(0), lambda s: payloads.append(s.payload.to_bytes())),
            session.declare_subscriber(keys.all_stats, lambda s: stats.update({str(s.key_expr): decode(s.payload, Stats).values})),
            session.declare_queryable(keys.weights_query, lambda q: q.reply(keys.weights_query, vector_weights))]
    actor = None
    try:
        assert wait_alive(session, keys.alive("replay", 0), timeout=20), replay.log()
        actor = subprocess.Popen(
            [sys.executable, "-m", "l2r.actors", "--run", run, "--connect", replay.endpoint, "--env-id", CAMERA,
             "--num-envs", "2", "--chunk-size", str(CHUNK), "--action-repeat", "1", "--max-speed", "0",
             "--random-steps", "1000000", "--stats-interval", "0.3", "--chunk-delay", "60"],  # full chunks only
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)

        def shard() -> dict:
            return stats.get(keys.stats("replay", 0), {})

        def of_actor() -> dict:
            return stats.get(keys.stats("actor", 0), {})

        assert wait_for(lambda: shard().get("size", 0) >= 4 * EPISODE_STEPS and of_actor().get("rejected_weights"), 90), \
            f"{shard()}\n{of_actor()}\n{replay.log()[-2000:]}"
        assert shard()["rejected"] == 0 and shard()["gaps"] == 0
        assert of_actor()["policy_version"] == -1  # the vector policy was refused: it goes on acting randomly
        # cartpole repeats each action twice itself: two of the frames papers count per env step
        assert of_actor()["frames_per_s"] > 0 and of_actor()["frames_per_s"] == 2 * of_actor()["env_steps_per_s"]
        assert of_actor()["frames"] == 2 * of_actor()["env_steps"]

        batch = None
        for reply in session.get(keys.sample(0), payload=encode(SampleRequest(batch_size=16, frame_stack=3)), timeout=10):
            batch = decode(reply.ok.payload)
        assert isinstance(batch, SampleBatch), batch
        assert batch.frames["pixels"].dtype == np.uint8 and batch.frames["pixels"].shape[1:] == (3, IMAGE_SIZE, IMAGE_SIZE)
    finally:
        out = stop_all(actor, subs, session, replay)
    assert actor.returncode == 0, out
    assert "bad_spec" in out and "the environment gives {pixels: uint8[3, 16, 16]}" in out, out

    assert {msgpack.unpackb(p)["v"] for p in payloads} == {3}  # frames compressed, the actor's default
    chunks: list[ExperienceChunk] = [decode(p) for p in payloads]
    # Env 0's first three chunks (12 steps, 2 episodes): each row the frame its env showed, the
    # step that ended an episode closed by its true last frame, the next episode's first frame after.
    mine = sorted((c for c in chunks if c.env_id == 0), key=lambda c: c.seq)
    firsts = {c.seq: c for c in mine}
    first = list(firsts.values())[:3]
    assert len(first) == 3 and all(c.size == CHUNK for c in first)
    actions = np.concatenate([c.actions for c in first])
    episodes = replayed(actions, 2)
    rows = [c.obs["pixels"] for c in first]
    assert all(r.dtype == np.uint8 and r.shape == (CHUNK + 1, 3, IMAGE_SIZE, IMAGE_SIZE) for r in rows)
    sent = [rows[0][:4], rows[1][:2], first[1].final_obs["pixels"], rows[1][2:4], rows[2][:4], rows[2][4:]]
    truth = [episodes[0][:4], episodes[0][4:6], episodes[0][6:], episodes[1][:2], episodes[1][2:6], episodes[1][6:]]
    for got, want in zip(sent, truth):
        np.testing.assert_array_equal(got, np.stack(want))
    assert first[1].truncated.tolist() == [False, True, False, False] and first[2].truncated[-1]
    assert first[0].obs["pixels"].std() > 10  # a real render, not a blank frame
