"""A photo tuner's episodes on record: the images of each query and the goal, and the PSNR of
each step, logged by the actor's own logger and evaluation loop on the real task observed
through statistics (its images come from the step's info), read back, and drawn by `l2r view`."""

from __future__ import annotations

from pathlib import Path

import gymnasium
import numpy as np
import pytest

from l2r.actors.actor import ActorConfig, make_episode_logger, make_task
from l2r.episodes import schema
from l2r.episodes.read import read_episode
from l2r.learner import td3
from l2r.photo import TUNE_STATS_ID
from l2r.photo.env import MAX_STEPS
from l2r.spaces import task_spaces
from tests.logs.episode_writer import RUN
from tests.logs.recording import logged_evaluation, saved_view, view_origins

SEED = 3


class Seen(gymnasium.Wrapper):
    """Keeps each step's images and PSNR as the env's info gives them."""

    def __init__(self, env: gymnasium.Env):
        super().__init__(env)
        self.images: list[dict[str, np.ndarray]] = []
        self.psnr: list[float] = []

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(action)
        self.images.append({name: image.copy() for name, image in info["frames"].items()})
        self.psnr.append(info["psnr_db"])
        return obs, reward, terminated, truncated, info


@pytest.fixture(scope="module")
def photo_episode(tmp_path_factory) -> tuple[Path, Seen]:
    """One evaluation episode of the tuner observed through statistics, by an untrained policy,
    logged as an actor logs it, and what its env showed at each step."""
    directory = tmp_path_factory.mktemp("photo")
    config = ActorConfig(run=RUN, actor_id=0, env_id=TUNE_STATS_ID, episode_log={"directory": directory})
    observation, act_dim = task_spaces(TUNE_STATS_ID)
    policy = td3.init_state(td3.TD3Config(hidden=(16,), precision="float32"), observation, act_dim, seed=0).actor
    env = Seen(make_task(TUNE_STATS_ID))
    return logged_evaluation(config, policy, env, SEED, version=1), env


def test_a_photo_episode_holds_each_query_s_image_the_goal_and_the_psnr_of_each_step(photo_episode):
    path, seen = photo_episode
    steps = len(seen.psnr)
    assert 1 <= steps <= MAX_STEPS
    episode = read_episode(path)
    assert episode.complete and episode.body is None and len(episode) == steps
    assert episode.images.keys() == {"pixels", "goal"}
    for name in ("pixels", "goal"):
        assert episode.images[name].shape == (steps, 3, 64, 64)
        np.testing.assert_array_equal(episode.images[name], np.stack([images[name] for images in seen.images]))
    assert len({image.tobytes() for image in episode.images["goal"]}) == 1  # one goal all episode
    assert len({image.tobytes() for image in episode.images["pixels"]}) > 1  # each query its own image
    np.testing.assert_allclose(episode.steps["psnr_db"], seen.psnr)
    assert float(episode.result["psnr_db"]) == pytest.approx(seen.psnr[-1])


def test_only_a_photo_task_s_steps_carry_a_psnr(tmp_path):
    camera = make_episode_logger(ActorConfig(env_id="l2r/dmc-cartpole-swingup-v0", episode_log={"directory": tmp_path}))
    photo = make_episode_logger(ActorConfig(env_id=TUNE_STATS_ID, episode_log={"directory": tmp_path}))
    try:
        sizes = {"observation": 4, "action": 1}
        assert "psnr_db" not in camera.layout(sizes).dtype.names
        assert "psnr_db" in photo.layout(sizes).dtype.names
        assert schema.PHOTO_SCALARS == ("psnr_db",)
    finally:
        camera.close()
        photo.close()


@pytest.mark.slow
def test_l2r_view_shows_a_photo_episode_s_images_step_by_step_and_its_psnr(photo_episode, tmp_path):
    path, seen = photo_episode
    reader = saved_view(path, tmp_path / "photo.rrd")
    chunks = [c for c in reader.stream().to_chunks() if not c.is_static]
    rows = sorted((step, bytes(buffer[0])) for c in chunks if c.entity_path == "/images/pixels"
                  for step, buffer in zip(c.to_record_batch().column("step").to_pylist(),
                                          c.to_record_batch().column("Image:buffer").to_pylist()))
    assert [step for step, _ in rows] == list(range(len(seen.psnr)))
    for (_, buffer), images in zip(rows, seen.images):
        assert buffer == images["pixels"].transpose(1, 2, 0).tobytes()
    psnr = [v[0] for c in chunks if c.entity_path == "/plots/psnr_db"
            for v in c.to_record_batch().column("Scalars:scalars").to_pylist()]
    np.testing.assert_allclose(psnr, seen.psnr)
    origins = view_origins(reader)
    assert {"/images/pixels", "/images/goal", "/plots/psnr_db"} <= origins and "/world" not in origins
