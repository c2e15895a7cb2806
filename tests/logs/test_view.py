"""Episode files in Rerun: through `l2r view --save`, and through Rerun's own MCAP reader."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import rerun as rr

from l2r.actors.episode_log import EpisodeLogger, LogPolicy
from l2r.config import EXIT_CANNOT_START
from l2r.episodes import schema
from l2r.sim.env import FOOT_SPHERES, RunEnv
from l2r.sim.ligaments import LIGAMENTS
from l2r.sim.model import BODIES, MUSCLES
from l2r.episodes.read import find_episode
from l2r.view import CAMERA, CAMERA_DISTANCE, CAMERA_HEIGHT, write_recording
from tests.logs.episode_writer import DIFFICULTY, RUN, meta, play

STEPS = 12


@pytest.fixture(scope="module")
def episodes(tmp_path_factory) -> tuple[list[Path], list[dict]]:
    """Two logged episodes (one training, one evaluation) and what the env produced in each."""
    directory = tmp_path_factory.mktemp("episodes")
    logger = EpisodeLogger(directory, RUN, actor_id=0, policy=LogPolicy(every=1), block_steps=5)
    env = RunEnv(difficulty=DIFFICULTY, max_steps=STEPS)
    produced = []
    for seed, evaluation in ((3, False), (4, True)):
        env.reset(seed=seed)
        recorder = logger.begin_episode({**meta(env, seed), "evaluation": evaluation})
        out = play(env, recorder, seed, STEPS)
        recorder.end({"return": float(np.sum(out["reward"])), "distance": out["info"][-1]["distance"]})
        produced.append(out)
    logger.close()
    return sorted(directory.glob("*.mcap")), produced


def temporal(chunks: list, entity: str, component: str) -> list:
    """The values of one component of one entity, in step order."""
    rows = []
    for chunk in chunks:
        if chunk.entity_path == entity and not chunk.is_static:
            batch = chunk.to_record_batch()
            if component in batch.schema.names:
                rows += zip(batch.column("step").to_pylist(), batch.column(component).to_pylist())
    return [value for _, value in sorted(rows, key=lambda r: r[0])]


@pytest.mark.slow
def test_l2r_view_saves_a_recording_of_several_episodes(episodes, tmp_path):
    files, produced = episodes
    out = tmp_path / "episodes.rrd"
    result = subprocess.run([sys.executable, "-m", "l2r.cli", "view", *map(str, files), "--save", str(out)],
                            capture_output=True, text=True, timeout=60)  # fmt: skip
    assert result.returncode == 0, result.stderr
    chunks = rr.chunk.RrdReader(out).stream().to_chunks()
    entities = {c.entity_path for c in chunks}
    assert {f"/world/ground/bodies/{b}" for b in BODIES} <= entities
    assert {"/world/ground/muscles", "/world/ground/floor/boxes", "/world/ground/obstacles", "/episodes"} <= entities
    assert {f"/plots/{n}" for n in ("reward", "distance", "pelvis_height", "muscle_activation", "muscle_force")} <= entities

    # Both episodes play one after the other, with the env's values.
    rewards = [v[0] for v in temporal(chunks, "/plots/reward", "Scalars:scalars")]
    assert rewards == pytest.approx([r for out in produced for r in out["reward"]], rel=0, abs=0)
    activations = temporal(chunks, "/plots/muscle_activation", "Scalars:scalars")
    assert np.array_equal(activations, [i["muscle_activation"] for out in produced for i in out["info"]])
    pelvis = np.array(temporal(chunks, "/world/ground/bodies/pelvis", "Transform3D:translation"))[:, 0]
    want = np.array([i["body_pos"][1] for out in produced for i in out["info"]])
    assert np.allclose(pelvis, want, atol=1e-6)
    strips = temporal(chunks, "/world/ground/muscles", "LineStrips3D:strips")
    assert len(strips) == len(want) and all(len(s) == len(MUSCLES) for s in strips)
    times = [t for c in chunks if c.entity_path == "/plots/reward"
             for t in c.to_record_batch().column("time").cast("int64").to_pylist()]  # fmt: skip
    assert len(set(times)) == len(rewards), "two episodes must not overlap in time"


def test_the_camera_follows_the_pelvis_and_plot_lines_are_named_after_the_model(episodes, tmp_path):
    files, produced = episodes
    out = write_recording(files, tmp_path / "episodes.rrd")
    chunks = rr.chunk.RrdReader(out).stream().to_chunks()
    camera = np.array(temporal(chunks, f"/{CAMERA}", "Transform3D:translation"))[:, 0]  # one per step
    pelvis = np.array([i["body_pos"][1] for run in produced for i in run["info"]])
    assert np.allclose(camera[:, 0], pelvis[:, 0], atol=1e-6)  # along the track with the runner,
    assert np.allclose(camera[:, 1:], [CAMERA_HEIGHT, CAMERA_DISTANCE])  # at a fixed height beside it

    def static(entity: str, component: str) -> list:
        return [v for c in chunks if c.entity_path == entity and c.is_static
                for v in c.to_record_batch().column(component).to_pylist()]  # fmt: skip

    assert static(f"/{CAMERA}", "Pinhole:camera_xyz")
    assert {tuple(names) for names in static("/plots/contact_force", "SeriesLines:names")} == {tuple(FOOT_SPHERES)}
    assert {tuple(names) for names in static("/plots/ligament_force", "SeriesLines:names")} == {tuple(LIGAMENTS)}
    # and the 3D view looks through that camera
    reader = rr.chunk.RrdReader(out)
    views = [c.to_record_batch() for c in reader.store(store=reader.blueprints()[0]).stream().to_chunks()]
    tracked = [v.column(n).to_pylist() for v in views for n in v.schema.names if n == "EyeControls3D:tracking_entity"]
    assert tracked == [[[CAMERA]]]


def test_rerun_opens_an_episode_file_directly_with_the_body_moving(episodes):
    path = episodes[0][0]
    chunks = rr.chunk.McapReader(path).stream().to_chunks()
    entities = {c.entity_path for c in chunks}
    drawn = {e.split("/")[3] for e in entities if e.startswith("/runner/visual_geometries/")}
    assert set(BODIES) | {"ground"} <= drawn  # the URDF from /robot_description, every body drawn
    frames = {f for c in chunks if c.entity_path == schema.TOPIC_TF and not c.is_static
              for row in c.to_record_batch().column("Transform3D:child_frame").to_pylist() for f in row}  # fmt: skip
    assert set(BODIES) | {"ground"} <= frames  # and each body's frame moves with /tf
    assert any(c.entity_path == schema.TOPIC_STEP and "l2r.episodes.Step:message" in c.to_record_batch().schema.names
               for c in chunks)  # fmt: skip


def test_find_episode_and_write_recording(episodes, tmp_path):
    files, produced = episodes
    directory = files[0].parent
    assert find_episode(directory, kind="eval") == files[1]
    assert find_episode(directory, kind="train", seed=3, actor=0) == files[0]
    assert find_episode(directory, kind="eval", seed=3) is None
    assert find_episode(tmp_path, kind="eval") is None
    out = write_recording([files[1]], tmp_path / "best.rrd")
    rewards = [v[0] for v in temporal(rr.chunk.RrdReader(out).stream().to_chunks(), "/plots/reward", "Scalars:scalars")]
    assert rewards == list(produced[1]["reward"])


@pytest.mark.slow
def test_view_rejects_bad_input_clearly(episodes, tmp_path):
    headless = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}

    def view(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "l2r.cli", "view", *args], capture_output=True, text=True,
                              timeout=60, env=headless)  # fmt: skip

    assert view().returncode == 2
    missing = view(str(tmp_path / "nope.mcap"), "--save", str(tmp_path / "x.rrd"))
    assert missing.returncode == 2 and "no such file" in missing.stderr
    no_screen = view(str(episodes[0][0]))
    assert no_screen.returncode == 2 and "--save" in no_screen.stderr
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"not an mcap file at all")
    result = view(str(junk), "--save", str(tmp_path / "x.rrd"))
    assert result.returncode == EXIT_CANNOT_START and "junk.mcap" in result.stderr
