"""What `l2r up` makes of what its processes report: episodes by the simulator their actor steps, camera actors' frames, the status line's rates."""

import csv
from contextlib import contextmanager

import pytest
import zenoh
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from l2r.families import score_of
from l2r.job_plan import shown_evaluations
from l2r.live_status import status_line
from l2r.protocol import EpisodeSummary, Keys, Stats, encode, session_config
from l2r.run_metrics import RunMetrics
from tests.conftest import free_port, wait_for

PORT, OPENSIM = "l2r/Run-v0", "l2r/RunOpenSim-v0"


@contextmanager
def listening_metrics(directory, keys: Keys, **options):
    """A RunMetrics on one Zenoh session, and a second session connected to it to publish from."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(session_config(listen=[endpoint])) as listener, \
            zenoh.open(session_config(connect=[endpoint])) as sender:
        metrics = RunMetrics(listener, keys, directory, **options)
        try:
            yield metrics, sender
        finally:
            metrics.close()


def test_episodes_are_kept_apart_by_the_simulator_their_actor_steps(tmp_path):
    keys = Keys("metrics-test")
    with listening_metrics(tmp_path, keys, simulators={0: PORT, 1: PORT, 2: OPENSIM}) as (metrics, sender):
        publishers = {i: sender.declare_publisher(keys.episodes(i)) for i in range(3)}
        # A put before the sender has learnt of the listener's subscriber is dropped.
        assert wait_for(lambda: all(p.matching_status.matching for p in publishers.values()), 10)
        for actor_id, distance, evaluation in ((0, 0.5, False), (1, 1.0, True), (2, 3.0, True), (2, 5.0, True)):
            episode = EpisodeSummary(actor_id=actor_id, env_id=0, episode_return=distance, distance=distance,
                                     length=100, policy_version=1, difficulty=0, seed=0, evaluation=evaluation)
            publishers[actor_id].put(encode(episode))
        assert wait_for(lambda: metrics.episodes == 4, 10)
        figures = metrics.record_status()
    assert figures["eval_distance"] == 1.0 and figures["opensim_eval_distance"] == 4.0
    with open(tmp_path / "evaluation.csv", newline="") as f:
        assert [(r["simulator"], r["distance"]) for r in csv.DictReader(f)] == [
            (PORT, "1.0"), (OPENSIM, "3.0"), (OPENSIM, "5.0")]
    events = EventAccumulator(str(tmp_path))
    events.Reload()
    assert [e.value for e in events.Scalars("eval/distance")] == [1.0]
    assert [e.value for e in events.Scalars("eval/RunOpenSim-v0/distance")] == [3.0, 5.0]
    assert [e.value for e in events.Scalars("train/distance")] == [0.5]


def test_warp_actors_judged_by_port_evaluators_show_the_ports_evaluations(tmp_path):
    # l2r up --env-id l2r/RunWarp-v0 --eval-env-id l2r/Run-v0: no evaluator runs the actors' env.
    warp = "l2r/RunWarp-v0"
    assert shown_evaluations(warp, [PORT]) == PORT and shown_evaluations(warp, [OPENSIM, PORT]) == PORT
    assert shown_evaluations(warp, [OPENSIM]) == warp and shown_evaluations(PORT, [OPENSIM, PORT]) == PORT
    keys = Keys("warp-metrics-test")
    with listening_metrics(tmp_path, keys, env_id=warp, simulators={0: warp, 1: PORT, 2: OPENSIM},
                           shown_eval_env_id=PORT) as (metrics, sender):
        publishers = {i: sender.declare_publisher(keys.episodes(i)) for i in (1, 2)}
        assert wait_for(lambda: all(p.matching_status.matching for p in publishers.values()), 10)
        for actor_id, distance in ((1, 2.5), (2, 4.0)):
            publishers[actor_id].put(encode(EpisodeSummary(
                actor_id=actor_id, env_id=0, episode_return=distance, distance=distance, length=100,
                policy_version=1, difficulty=0, seed=0, evaluation=True)))
        assert wait_for(lambda: metrics.episodes == 2, 10)
        figures = metrics.record_status()
    assert figures["eval_distance"] == 2.5 and figures["opensim_eval_distance"] == 4.0
    assert "| eval distance 2.50 m (OpenSim 4.00 m) |" in status_line(figures, score_of(warp))


def test_camera_actors_frames_per_second_add_up_into_the_figures_and_the_status_line(tmp_path):
    keys = Keys("frames-test")
    with listening_metrics(tmp_path, keys, env_id="Hopper-v5") as (metrics, sender):
        publishers = [sender.declare_publisher(keys.stats("actor", i)) for i in range(2)]
        assert wait_for(lambda: all(p.matching_status.matching for p in publishers), 10)
        publishers[0].put(encode(Stats("actor", "0", 0.0, {"env_steps": 10, "env_steps_per_s": 100.0})))
        assert wait_for(lambda: metrics.snapshot()["env_steps_per_s"] == 100.0, 10)
        vector = metrics.snapshot()
        publishers[1].put(encode(Stats("actor", "1", 0.0, {"env_steps": 10, "env_steps_per_s": 50.0,
                                                            "frames_per_s": 50.0})))
        publishers[0].put(encode(Stats("actor", "0", 0.0, {"env_steps": 10, "env_steps_per_s": 100.0,
                                                            "frames_per_s": 100.0})))
        assert wait_for(lambda: metrics.snapshot().get("frames_per_s") == 150.0, 10)
        camera = metrics.snapshot()
    score = score_of("Hopper-v5")
    assert "frames_per_s" not in vector and "frames/s" not in status_line(vector, score)
    assert "] env     150 steps/s (20), 150 frames/s | learner" in status_line(camera, score)


def test_the_status_counts_env_steps_per_second_over_its_interval_while_actors_are_held(tmp_path):
    # A held actor's own rate is 0 in most of its two-second windows; the job still moves.
    keys = Keys("rate-test")
    with listening_metrics(tmp_path, keys, env_id="Hopper-v5") as (metrics, sender):
        actor = sender.declare_publisher(keys.stats("actor", 0))
        assert wait_for(lambda: actor.matching_status.matching, 10)
        actor.put(encode(Stats("actor", "0", 0.0, {"env_steps": 100, "env_steps_per_s": 0.0,
                                                    "frames": 200, "frames_per_s": 0.0})))
        assert wait_for(lambda: metrics.env_steps == 100, 10)
        first = metrics.record_status()
        actor.put(encode(Stats("actor", "0", 0.0, {"env_steps": 400, "env_steps_per_s": 0.0,
                                                    "frames": 800, "frames_per_s": 0.0})))
        assert wait_for(lambda: metrics.env_steps == 400, 10)
        second = metrics.record_status()
    assert first["env_steps_per_s"] == 0.0  # no interval yet: the actors' own rate
    elapsed = second["time"] - first["time"]
    assert second["env_steps_per_s"] == pytest.approx(300 / elapsed)
    assert second["frames_per_s"] == pytest.approx(600 / elapsed)
