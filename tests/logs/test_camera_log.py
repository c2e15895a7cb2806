"""A camera task's episodes on record: the frames its policy saw, logged by the actor's own
logger and evaluation loop on a real camera task, read back, and drawn by `l2r view`; the
runner's files stay as they were."""

from __future__ import annotations

from pathlib import Path

import gymnasium
import numpy as np
import pytest
import rerun as rr
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from l2r.actors.actor import ActorConfig, make_task
from l2r.actors.episode_log import EpisodeLogger, LogPolicy
from l2r.episodes import schema
from l2r.episodes.read import read_episode
from l2r.policy import build_policy
from l2r.sim.env import RunEnv
from tests.actors.camera import CAMERA, EPISODE_STEPS, IMAGE_SIZE, RENDERER
from tests.logs.episode_writer import DIFFICULTY, RUN, meta, play
from tests.logs.recording import logged_evaluation, saved_view, view_origins

pytestmark = pytest.mark.skipif(not RENDERER, reason="no EGL or OSMesa to render with")

SEED = 5
POLICY = {"observation": [{"name": "pixels", "dtype": "uint8", "shape": [3, IMAGE_SIZE, IMAGE_SIZE]}],
          "frame_stack": 1, "act_dim": 1, "hidden": [8], "activation": "elu", "layer_norm": False}


class Rendered(gymnasium.Wrapper):
    """Keeps a copy of every frame the env returns from a step."""

    def __init__(self, env: gymnasium.Env):
        super().__init__(env)
        self.frames: list[np.ndarray] = []

    def step(self, action):
        obs, *rest = self.env.step(action)
        self.frames.append(obs["pixels"].copy())
        return obs, *rest


@pytest.fixture(scope="module")
def camera_episode(tmp_path_factory) -> tuple[Path, np.ndarray]:
    """One evaluation episode of the small camera task, logged as an actor logs it (small
    chunks, so that the file has several), and the frames the env rendered in it."""
    directory = tmp_path_factory.mktemp("camera")
    config = ActorConfig(run=RUN, actor_id=0, env_id=CAMERA,
                         episode_log={"directory": directory, "block_steps": 4, "chunk_bytes": 1024})
    env = Rendered(make_task(CAMERA))
    return logged_evaluation(config, build_policy(POLICY), env, SEED, version=3), np.stack(env.frames)


def test_a_camera_episode_holds_the_frames_its_env_rendered(camera_episode):
    path, rendered = camera_episode
    assert rendered.shape == (EPISODE_STEPS, 3, IMAGE_SIZE, IMAGE_SIZE) and rendered.std() > 10  # a real render
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        assert {s.name for s in summary.schemas.values()} == {schema.STEP_MESSAGE, schema.IMAGE_MESSAGE}  # no body
        topics = {c.topic: c.id for c in summary.channels.values()}
        assert topics.keys() == {schema.TOPIC_STEP, "/pixels"}
        counts = summary.statistics.channel_message_counts
        assert counts[topics["/pixels"]] == counts[topics[schema.TOPIC_STEP]] == EPISODE_STEPS
        # Decoded with the schemas in the file alone: a PNG per step, stamped with its step's time.
        images = list(reader.iter_decoded_messages(topics=["/pixels"]))
        steps = list(reader.iter_decoded_messages(topics=[schema.TOPIC_STEP]))
        assert [m.log_time for _, _, m, _ in images] == [m.log_time for _, _, m, _ in steps]
        first = images[0][3]
        assert first.format == "png" and first.frame_id == "pixels" and first.data.startswith(b"\x89PNG")
        assert first.timestamp.ToNanoseconds() == images[0][2].log_time
    episode = read_episode(path)
    assert episode.complete and episode.body is None and len(episode) == EPISODE_STEPS
    frames = episode.images["pixels"]
    assert frames.dtype == np.uint8 and frames.shape == rendered.shape
    np.testing.assert_array_equal(frames, rendered)
    assert int(episode.result["length"]) == 2 * EPISODE_STEPS  # suite steps: the env repeats each action twice
    assert episode.episode["env_id"] == CAMERA and episode.episode["evaluation"] == "true"


def test_an_interrupted_camera_file_reads_the_frames_it_has(camera_episode, tmp_path):
    path, rendered = camera_episode
    data = path.read_bytes()
    cut = tmp_path / (path.name + ".part")
    cut.write_bytes(data[: len(data) * 2 // 3])  # a crash mid-write: the last chunks and the summary lost
    episode = read_episode(cut)
    n = len(episode.images["pixels"])
    assert not episode.complete and 0 < n <= len(episode) < EPISODE_STEPS
    np.testing.assert_array_equal(episode.images["pixels"], rendered[:n])


@pytest.mark.slow
def test_l2r_view_saves_a_camera_episode_with_its_frames(camera_episode, tmp_path):
    path, rendered = camera_episode
    reader = saved_view(path, tmp_path / "camera.rrd")
    chunks = [c for c in reader.stream().to_chunks() if not c.is_static]
    assert not any(c.entity_path.startswith("/world") for c in chunks)  # no body to draw
    rows = []
    for chunk in chunks:
        if chunk.entity_path == "/images/pixels":
            batch = chunk.to_record_batch()
            rows += zip(batch.column("step").to_pylist(), batch.column("Image:buffer").to_pylist(),
                        batch.column("Image:format").to_pylist())  # fmt: skip
    rows.sort(key=lambda row: row[0])
    assert [step for step, _, _ in rows] == list(range(EPISODE_STEPS))  # one image a step, on the step timeline
    frames = np.array([np.frombuffer(bytes(buffer[0]), np.uint8) for _, buffer, _ in rows])
    np.testing.assert_array_equal(frames.reshape(-1, IMAGE_SIZE, IMAGE_SIZE, 3), rendered.transpose(0, 2, 3, 1))
    assert {(f[0]["width"], f[0]["height"]) for _, _, f in rows} == {(IMAGE_SIZE, IMAGE_SIZE)}
    rewards = [v for c in chunks if c.entity_path == "/plots/reward" for v in c.to_record_batch().column("Scalars:scalars").to_pylist()]
    assert len(rewards) == EPISODE_STEPS
    origins = view_origins(reader)
    assert "/images/pixels" in origins and "/world" not in origins  # the frames in place of the runner's 3D view


def test_rerun_opens_a_camera_episode_file_directly_with_its_frames(camera_episode):
    path, rendered = camera_episode
    chunks = [c for c in rr.chunk.McapReader(path).stream().to_chunks() if c.entity_path == "/pixels" and not c.is_static]
    blobs = [b for c in chunks for b in c.to_record_batch().column("EncodedImage:blob").to_pylist()]
    assert len(blobs) == EPISODE_STEPS and all(bytes(b[0]).startswith(b"\x89PNG") for b in blobs)


def test_a_runner_episode_logged_from_the_actor_s_fields_is_the_vector_one(tmp_path):
    """The actor hands the logger the observation's fields; for the runner that is the one
    vector field, and the file has the runner's channels and the same Step bytes as before."""
    env = RunEnv(difficulty=DIFFICULTY, max_steps=8)
    files = {}
    for name, as_fields in (("vector", False), ("fields", True)):
        logger = EpisodeLogger(tmp_path / name, RUN, actor_id=0, policy=LogPolicy(every=1), block_steps=3)
        env.reset(seed=0)
        recorder = logger.begin_episode(meta(env, 0))

        class Fields:
            def log_step(self, obs, *rest):
                recorder.log_step({"state": obs} if as_fields else obs, *rest)

        play(env, Fields(), 0, 8)
        recorder.end({"return": 0.0})
        logger.close()
        (files[name],) = (tmp_path / name).glob("*.mcap")

    def content(path: Path) -> tuple:
        with open(path, "rb") as f:
            reader = make_reader(f)
            topics = sorted(c.topic for c in reader.get_summary().channels.values())
            steps = [m.data for _, _, m in reader.iter_messages(topics=[schema.TOPIC_STEP])]
        return topics, steps

    vector, fields = content(files["vector"]), content(files["fields"])
    assert vector[0] == sorted([schema.TOPIC_ROBOT, schema.TOPIC_SCENE, schema.TOPIC_TF, schema.TOPIC_STEP])
    assert len(vector[1]) == 8 and fields == vector
