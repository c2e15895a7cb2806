"""Episode files written by a real process: schemas, summary, metadata, values, recovery, budget."""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import mcap.writer
import numpy as np
import pytest
import rerun as rr
from mcap.exceptions import McapError
from mcap.reader import make_reader
from mcap.stream_reader import StreamReader
from mcap_protobuf.decoder import DecoderFactory

from l2r.actors import episode_log
from l2r.actors.episode_log import EpisodeLogger, LogPolicy
from l2r.episodes import schema
from l2r.episodes.read import read_episode
from l2r.episodes.write import EpisodeFile
from l2r.sim.env import RunEnv
from l2r.view import write_recording
from tests.conftest import wait_for
from tests.logs.episode_writer import DIFFICULTY, RUN, meta, play

WRITER = Path(__file__).with_name("episode_writer.py")
STEPS = 40


def run_writer(directory: Path, *args: str) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[2])}
    return subprocess.Popen([sys.executable, str(WRITER), str(directory), *args],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env)  # fmt: skip


class Collect:
    """A recorder that keeps nothing: ``play`` returns what the env produced."""

    def log_step(self, *args) -> None:
        pass


def expected(seed: int, steps: int, across_resets: bool = False) -> dict:
    env = RunEnv(difficulty=DIFFICULTY, max_steps=steps)
    env.reset(seed=seed)
    return play(env, Collect(), seed, steps, across_resets)


def assert_steps_equal(episode, want: dict, n: int) -> None:
    s = episode.steps
    assert np.array_equal(s["step"], np.arange(n))
    assert np.array_equal(s["observation"], np.array(want["obs"][:n], dtype=np.float64))
    assert np.array_equal(s["action"], np.array(want["action"][:n]))
    assert np.array_equal(s["reward"], np.array(want["reward"][:n]))
    info = want["info"][:n]
    for name in episode_log.INFO_VECTORS:
        assert np.array_equal(s[name], np.array([np.ravel(i[name]) for i in info])), name
    assert np.array_equal(s["distance"], [i["distance"] for i in info])
    assert np.array_equal(episode.pos, np.array([i["body_pos"][1:] for i in info]))
    assert np.array_equal(episode.quat, np.array([i["body_quat"][1:] for i in info]))
    pelvis = episode.names["bodies"].index("pelvis")
    assert np.array_equal(s["pelvis_height"], episode.pos[:, pelvis, 1])


@pytest.mark.slow
def test_a_writer_process_leaves_complete_self_describing_files(tmp_path):
    proc = run_writer(tmp_path, "--episodes", "2", "--steps", str(STEPS), "--block-steps", "16")
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, out
    files = sorted(tmp_path.glob("*.mcap"))
    assert len(files) == 2 and not list(tmp_path.glob("*.part"))

    for seed, path in enumerate(files):
        with open(path, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            summary = reader.get_summary()
            schemas = {s.name: s.encoding for s in summary.schemas.values()}
            assert schemas == {"std_msgs/msg/String": "ros2msg", "foxglove.SceneUpdate": "protobuf",
                               "foxglove.FrameTransforms": "protobuf", schema.STEP_MESSAGE: "protobuf"}  # fmt: skip
            topics = {c.topic: c for c in summary.channels.values()}
            want = expected(seed, STEPS)
            n = len(want["reward"])
            counts = summary.statistics.channel_message_counts
            assert counts[topics[schema.TOPIC_STEP].id] == n and counts[topics[schema.TOPIC_TF].id] == n
            assert summary.chunk_indexes and {c.compression for c in summary.chunk_indexes} == {"zstd"}
            assert topics[schema.TOPIC_STEP].metadata["muscles"].split(",")[0] == "hamstrings_r"
            metadata = {m.name: m.metadata for m in reader.iter_metadata()}
            info = metadata[schema.METADATA_EPISODE]
            assert (info["run"], info["actor"], info["seed"], info["difficulty"]) == (RUN, "0", str(seed), "1")
            assert info["policy_version"] == "7" and info["model"].startswith("runner.xml sha256:") and info["env_version"]
            result = metadata[schema.METADATA_RESULT]
            assert float(result["return"]) == pytest.approx(float(np.sum(want["reward"])))
            assert int(result["length"]) == n and float(result["distance"]) == want["info"][-1]["distance"]
            # Decoded with the schemas in the file alone: the first step's numbers are the env's.
            step = next(m for _, c, _, m in reader.iter_decoded_messages(topics=[schema.TOPIC_STEP]))
            assert list(step.action) == want["action"][0].tolist() and step.reward == want["reward"][0]
            tf = next(m for _, c, _, m in reader.iter_decoded_messages(topics=[schema.TOPIC_TF]))
            pelvis = next(t for t in tf.transforms if t.child_frame_id == "pelvis")
            assert pelvis.parent_frame_id == schema.GROUND_FRAME
            assert pelvis.translation.x == want["info"][0]["body_pos"][1][0]

        with open(path, "rb") as f:  # every chunk and the data section pass their CRC checks
            assert sum(1 for _ in StreamReader(f, validate_crcs=True).records) > 2 * n
        episode = read_episode(path)
        assert episode.complete
        assert_steps_equal(episode, want, n)


@pytest.mark.slow
def test_a_killed_writer_leaves_a_part_file_that_recovers(tmp_path):
    steps = 90
    proc = run_writer(tmp_path, "--episodes", "1", "--steps", str(steps), "--block-steps", "10",
                      "--chunk-bytes", "8192", "--hang")  # fmt: skip
    try:
        assert proc.stdout.readline().strip() == "hanging"
        part = next(tmp_path.glob("*.mcap.part"))
        deadline = time.monotonic() + 10  # the writer thread may still be writing the last block
        while part.stat().st_size < 40_000 and time.monotonic() < deadline:
            time.sleep(0.05)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    assert not list(tmp_path.glob("*.mcap")), "an unfinished episode must never look complete"
    with open(part, "rb") as f, pytest.raises(McapError):
        make_reader(f).get_summary()  # no footer: the standard reader needs recovery first

    result = subprocess.run([sys.executable, "-m", "l2r.episodes.recover", str(part)],
                            capture_output=True, text=True, timeout=60)  # fmt: skip
    assert result.returncode == 0, result.stderr
    recovered = part.with_name(part.name.removesuffix(".mcap.part") + ".recovered.mcap")
    with open(recovered, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_summary().statistics.message_count > 0
        assert schema.METADATA_EPISODE in {m.name for m in reader.iter_metadata()}
    episode = read_episode(recovered)
    n = len(episode)
    assert 10 <= n <= steps and episode.result == {}
    assert_steps_equal(episode, expected(0, steps, across_resets=True), n)
    # The viewer plays the interrupted file itself just as far.
    assert len(read_episode(part)) == n and not read_episode(part).complete
    chunks = rr.chunk.RrdReader(write_recording([part], tmp_path / "part.rrd")).stream().to_chunks()
    assert sum(c.num_rows for c in chunks if c.entity_path == "/plots/reward" and not c.is_static) == n


def small_logger(tmp_path: Path, **kwargs) -> EpisodeLogger:
    return EpisodeLogger(tmp_path, RUN, actor_id=1, block_steps=5, **kwargs)


def log_episode(logger: EpisodeLogger, env: RunEnv, seed: int, steps: int = 8, evaluation: bool = False,
                ret: float | None = None) -> None:  # fmt: skip
    env.reset(seed=seed)
    recorder = logger.begin_episode({**meta(env, seed), "evaluation": evaluation})
    out = play(env, recorder, seed, steps)
    recorder.end({"return": float(np.sum(out["reward"])) if ret is None else ret, "distance": 0.0})


def kinds(directory: Path) -> list[str]:
    return [p.name.removesuffix(".mcap").rsplit("-", 1)[1] for p in sorted(directory.glob("*.mcap"))]


def test_every_nth_evaluation_and_best_episodes_are_chosen(tmp_path):
    env = RunEnv(difficulty=DIFFICULTY)
    logger = small_logger(tmp_path, policy=LogPolicy(every=3, evaluation=True, best=True))
    for seed, ret in enumerate([1.0, 0.5, 2.0, 1.5, 0.1, 3.0, 0.2]):
        log_episode(logger, env, seed, ret=ret)
    log_episode(logger, env, 99, evaluation=True)
    logger.close()
    # training episodes 0, 3, 6 by count; 2 and 5 beat the best return so far; then the evaluation one
    names = sorted(tmp_path.glob("*.mcap"))
    assert [int(p.name.split("-e")[1][:6]) for p in names] == [0, 2, 3, 5, 6, 7]
    assert kinds(tmp_path) == ["train", "best", "train", "best", "train", "eval"]
    assert logger.stats["episodes_written"] == 6


def test_the_disk_budget_removes_the_oldest_files_first(tmp_path):
    env = RunEnv(difficulty=DIFFICULTY)
    probe = small_logger(tmp_path / "probe", policy=LogPolicy(every=1))
    log_episode(probe, env, 0)
    probe.close()
    size = next((tmp_path / "probe").glob("*.mcap")).stat().st_size

    logger = small_logger(tmp_path / "logs", policy=LogPolicy(every=1), disk_budget_bytes=int(2.5 * size))
    for seed in range(5):
        log_episode(logger, env, seed)
        time.sleep(0.01)  # distinct modification times
    logger.close()
    left = sorted((tmp_path / "logs").glob("*.mcap"))
    assert [int(p.name.split("-e")[1][:6]) for p in left] == [3, 4]
    assert sum(p.stat().st_size for p in left) <= 2.5 * size
    assert logger.stats["files_removed"] == 3


def test_a_slow_disk_skips_the_episode_instead_of_blocking(tmp_path, monkeypatch):
    disk_free = threading.Event()  # every write waits until the test frees the disk
    write_block = EpisodeFile.write_block

    def stuck_write_block(self, *args):
        disk_free.wait()
        write_block(self, *args)

    monkeypatch.setattr(EpisodeFile, "write_block", stuck_write_block)
    env = RunEnv(difficulty=DIFFICULTY)
    logger = EpisodeLogger(tmp_path, RUN, actor_id=2, policy=LogPolicy(every=1), block_steps=1, queue_blocks=2)
    env.reset(seed=0)
    recorder = logger.begin_episode(meta(env, 0))
    obs, info = env.reset(seed=0)

    def ten_steps() -> None:
        for _ in range(10):
            recorder.log_step(obs, np.zeros(18), 0.0, info)

    stepping = threading.Thread(target=ten_steps, daemon=True)
    stepping.start()
    stepping.join(timeout=30)  # at once, unless log_step waits for the stuck disk
    waited_for_the_disk = stepping.is_alive()
    disk_free.set()
    stepping.join()
    recorder.end({"return": 0.0})
    logger.close()
    assert not waited_for_the_disk, "log_step waited for the disk"
    assert logger.stats["episodes_skipped"] == 1
    assert not list(tmp_path.glob("*.mcap")) and not list(tmp_path.glob("*.part"))


def test_a_full_disk_drops_episodes_with_one_line_and_logging_goes_on_once_there_is_room(small_disk, caplog):
    caplog.set_level(logging.INFO)
    disk = small_disk(2)
    env = RunEnv(difficulty=DIFFICULTY)
    logger = small_logger(disk.path, policy=LogPolicy(every=1))
    disk.fill()
    for seed in range(4):
        log_episode(logger, env, seed, steps=40)
    assert wait_for(lambda: logger.stats["write_errors"] == 4), logger.stats
    refused = [r.getMessage() for r in caplog.records if "disk full at" in r.getMessage()]
    assert len(refused) == 1 and "episodes are dropped" in refused[0], refused
    assert not [r for r in caplog.records if r.exc_info], "a traceback for a full disk"
    assert not list(disk.path.glob("*.part")), "a dropped episode left its partial file"

    disk.free()
    log_episode(logger, env, 10, steps=40)
    logger.close()
    assert logger.stats["episodes_written"] == 1 and kinds(disk.path) == ["train"]
    assert any("episode logs: writing again" in r.getMessage() for r in caplog.records)


def test_a_failure_other_than_the_disk_is_logged_with_its_traceback_once_then_counted(tmp_path, caplog, monkeypatch):
    """A writer that fails the same way for every episode (here mcap without its zstandard
    package, as on a machine where it was left out) logs one traceback, not one per episode."""
    monkeypatch.setattr(mcap.writer, "zstandard", None)
    env = RunEnv(difficulty=DIFFICULTY)
    logger = small_logger(tmp_path, policy=LogPolicy(every=1))
    for seed in range(3):
        log_episode(logger, env, seed, steps=20)
    assert wait_for(lambda: logger.stats["write_errors"] == 3), logger.stats
    logger.close()
    tracebacks = [r for r in caplog.records if r.exc_info]
    assert len(tracebacks) == 1 and "zstandard" in str(tracebacks[0].exc_info[1]), tracebacks
    assert not list(tmp_path.glob("*.mcap"))


def test_below_its_floor_of_free_space_an_actor_begins_no_logged_episode_and_says_so_once(small_disk, caplog):
    caplog.set_level(logging.INFO)
    disk = small_disk(4)
    env = RunEnv(difficulty=DIFFICULTY)
    logger = small_logger(disk.path, policy=LogPolicy(every=1), min_free_bytes=2 << 20)
    disk.fill(leave=1 << 20)  # room for an episode, but below the floor
    for seed in range(3):
        log_episode(logger, env, seed, steps=40)
    assert logger.stats["episodes_shed"] == 3 and not list(disk.path.glob("*.mcap*"))
    shed = [r.getMessage() for r in caplog.records if "below the floor of 2.1 MB" in r.getMessage()]
    assert len(shed) == 1 and "episodes are not logged until there is room" in shed[0], shed

    disk.free()
    log_episode(logger, env, 10, steps=40)
    logger.close()
    assert logger.stats["episodes_written"] == 1 and kinds(disk.path) == ["train"]
    assert any("again: logging episodes" in r.getMessage() for r in caplog.records)
