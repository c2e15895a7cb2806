"""`l2r up --opensim-stage-parting`: the port's stage ends as soon as OpenSim's evaluations part
from the port's, not at a time that suits one machine. The rule is heard over loopback Zenoh from
evaluator-like peers, and a real staged job goes on to OpenSim's stage when told of a parting."""

import json
import logging
import signal
import subprocess
import sys

import pytest
import zenoh

from l2r import opensim_stage
from l2r.opensim_stage import GAIT, PARTED, PARTED_ROUNDS, Parting
from l2r.protocol import EpisodeSummary, Keys, encode, session_config
from l2r.run_metrics import RunCounters
from l2r.sim import OPENSIM_ID, PORT_ID
from l2r.up import parse_args
from tests.conftest import free_port, wait_for

OPENSIM_EVALUATOR, PORT_EVALUATOR, ACTOR = 1, 2, 0
SIMULATORS = {ACTOR: PORT_ID, OPENSIM_EVALUATOR: OPENSIM_ID, PORT_EVALUATOR: PORT_ID}


def rounds(parting: Parting, *pairs: tuple[int, float, float], port_after: int = 3) -> None:
    """Each (version, OpenSim's metres, the port's metres): OpenSim's round, then the port's of a
    version `port_after` later, as two evaluators start their rounds at different moments."""
    for version, opensim, port in pairs:
        parting.add(OPENSIM_ID, version, opensim)
        parting.add(PORT_ID, version + port_after, port)


def test_three_opensim_rounds_in_a_row_under_the_ratio_part_the_gait(caplog):
    parting = Parting(0.7, episodes_per_round=1, simulators=SIMULATORS)
    with caplog.at_level(logging.INFO, logger="l2r.up"):
        rounds(parting, (40, 9.0, 10.0), (80, 2.0, 14.0), (120, 3.0, 15.0))
    assert parting.verdict is None
    # Each round on the way is said, for whoever watches the run.
    assert [r.getMessage() for r in caplog.records] == [
        "OpenSim's evaluation of v80, 2.00 m, under 0.7 of the port's of v83, 14.00 m: 1 of 3 in a row ends the "
        "port's stage",
        "OpenSim's evaluation of v120, 3.00 m, under 0.7 of the port's of v123, 15.00 m: 2 of 3 in a row ends the "
        "port's stage"]
    rounds(parting, (160, 2.5, 16.0))
    assert parting.verdict == (f"{PARTED}: {PARTED_ROUNDS} OpenSim evaluations in a row under 0.7 of the port's, "
                               "the last v160 2.50 m against v163 16.00 m")


def test_a_round_that_keeps_with_the_port_starts_the_count_again():
    parting = Parting(0.7, episodes_per_round=1, simulators=SIMULATORS)
    rounds(parting, (40, 2.0, 14.0), (80, 3.0, 15.0), (120, 11.0, 15.0), (160, 2.0, 16.0), (200, 2.0, 16.0))
    assert parting.verdict is None and parting.under == 2


def test_no_gait_in_the_port_is_no_parting_and_leaves_the_count_where_it_was():
    parting = Parting(0.7, episodes_per_round=1, simulators=SIMULATORS)
    rounds(parting, (40, 0.5, 3.0), (80, 0.5, GAIT - 0.01), (120, 1.0, 12.0), (160, 1.0, 2.0), (200, 1.0, 12.0))
    assert parting.verdict is None and parting.under == 2


def test_rounds_are_set_against_the_nearest_port_round_within_ten_versions_and_wait_for_it():
    parting = Parting(0.7, episodes_per_round=1, simulators=SIMULATORS)
    for version in (40, 80, 120):  # OpenSim's rounds first: the port's may still come
        parting.add(OPENSIM_ID, version, 1.0)
    assert parting.waiting == [40, 80, 120]
    parting.add(PORT_ID, 30, 20.0)  # 10 before the first: set against it
    parting.add(PORT_ID, 95, 20.0)  # 15 from 80: too far, so 80 goes unjudged, and 11 before 120 too far for it
    assert parting.under == 1 and parting.waiting == [120]
    parting.add(PORT_ID, 125, 20.0)
    assert parting.under == 2 and parting.waiting == []


def test_a_round_counts_once_all_its_episodes_are_in_and_by_their_mean():
    parting = Parting(0.5, episodes_per_round=2, simulators=SIMULATORS)
    for version in (40, 80, 120):
        parting.add(OPENSIM_ID, version, 1.0)
        parting.add(PORT_ID, version, 20.0)
        parting.add(PORT_ID, version, 2.0)  # the port's mean 11: a gait
        assert parting.under == version // 40 - 1  # OpenSim's round has one episode of two
        parting.add(OPENSIM_ID, version, 9.0)  # mean 5.0, under 0.5 x 11
    assert parting.verdict is not None


def test_the_evaluators_episodes_are_heard_over_zenoh_and_training_episodes_are_not():
    endpoint, keys = f"tcp/127.0.0.1:{free_port()}", Keys("parting-test")
    with zenoh.open(session_config(listen=[endpoint])) as listener, \
            zenoh.open(session_config(connect=[endpoint])) as sender:
        parting = Parting(0.7, episodes_per_round=1, simulators=SIMULATORS)
        subscriber = parting.listen(listener, keys)
        publishers = {actor: sender.declare_publisher(keys.episodes(actor)) for actor in SIMULATORS}
        assert wait_for(lambda: all(p.matching_status.matching for p in publishers.values()), 10)

        def episode(actor: int, version: int, distance: float, evaluation: bool = True) -> None:
            publishers[actor].put(encode(EpisodeSummary(
                actor_id=actor, env_id=0, episode_return=distance, distance=distance, length=1000,
                policy_version=version, difficulty=0, seed=0, evaluation=evaluation)))

        for version in (40, 80, 120):
            episode(ACTOR, version, 1.0, evaluation=False)  # a training episode of the port: not a round
            episode(OPENSIM_EVALUATOR, version, 1.0)
            episode(PORT_EVALUATOR, version, 15.0)
        assert wait_for(lambda: parting.verdict is not None, 10), parting.rounds
        assert parting.rounds[PORT_ID] == {40: [15.0], 80: [15.0], 120: [15.0]}
        subscriber.undeclare()


BOTH = ["--evaluators", "2", "--eval-env-id", OPENSIM_ID, "--eval-env-id", PORT_ID]


@pytest.mark.parametrize("flags, refusal", [
    (["--opensim-stage-parting", "0.7", *BOTH], "give its latest end as --opensim-stage SECONDS"),
    (["--opensim-stage", "60", "--opensim-stage-parting", "1.5", *BOTH], "a fraction of the port's distance in (0, 1]"),
    (["--opensim-stage", "60", "--opensim-stage-parting", "0.7"], "give evaluators in both"),
    (["--opensim-stage", "60", "--opensim-stage-parting", "0.7", "--evaluators", "1"], "give evaluators in both"),
    (["--opensim-stage", "60", "--opensim-stage-parting", "0.7", "--evaluators", "2", "--eval-env-id", OPENSIM_ID],
     "give evaluators in both"),
])
def test_a_parting_the_job_cannot_see_is_refused_in_one_line(flags, refusal, capsys):
    with pytest.raises(SystemExit) as stopped:
        parse_args(["--seconds", "120", *flags])
    assert stopped.value.code == 2 and refusal in capsys.readouterr().err


def test_a_port_stage_that_parted_is_over_whatever_its_time(tmp_path):
    args, _ = parse_args(["--seconds", "7200", "--opensim-stage", "3600", "--opensim-stage-parting", "0.7", *BOTH])
    port_run = tmp_path / "runner-20261127-120000"
    (port_run / "learner").mkdir(parents=True)
    (port_run / "learner" / "checkpoint.pt").write_bytes(b"")
    (port_run / "metrics").mkdir()
    (port_run / "metrics" / "status.csv").write_text("time,env_steps,updates,episodes\n1500,1000000,50000,900\n")
    assert not opensim_stage.port_stage_ended(args, port_run)
    (port_run / "summary.json").write_text(json.dumps({"outcome": "time budget of 60 s spent"}))
    assert not opensim_stage.port_stage_ended(args, port_run)
    (port_run / "summary.json").write_text(json.dumps({"outcome": f"{PARTED}: 3 OpenSim evaluations ..."}))
    assert opensim_stage.port_stage_ended(args, port_run)
    stage = opensim_stage.stage_args(args, port_run)
    # OpenSim's stage takes the rest of the job's time, and watches for no parting of its own.
    assert (stage.seconds, stage.opensim_stage, stage.opensim_stage_parting) == (5700, 0, 0)


@pytest.mark.slow
def test_a_staged_job_goes_on_to_opensim_s_stage_when_its_evaluations_part(tmp_path):
    runs, log = tmp_path / "runs", tmp_path / "up.err"
    with open(log, "w") as err:
        job = subprocess.Popen(
            [sys.executable, "-m", "l2r.cli", "up", "--seconds", "300", "--opensim-stage", "200",
             "--opensim-stage-parting", "0.7", *BOTH, "--eval-episodes", "1", "--eval-interval", "1000",
             "--runs-dir", str(runs), "--name", "parting", "--replay-arg=--min-size=32", "--status-interval", "5"],
            stdout=subprocess.DEVNULL, stderr=err)
    try:
        assert wait_for(lambda: list(runs.glob("*/metrics/status.csv")), 120), "the port's run never started"
        port_run = next(runs.iterdir())
        assert wait_for(lambda: RunCounters.read(port_run / "metrics").updates > 0, 240), "no update on the port"
        launch = json.loads((port_run / "launch.json").read_text())
        opensim, port = launch["args"]["actors"], launch["args"]["actors"] + 1  # the evaluators' ids
        keys = Keys(launch["zenoh_run"])
        with zenoh.open(session_config(connect=[f"tcp/127.0.0.1:{launch['sessions'][0]['learner_port']}"])) as peer:
            # As the job's evaluators would say of a gait parted from OpenSim.
            publishers = {actor: peer.declare_publisher(keys.episodes(actor)) for actor in (opensim, port)}
            assert wait_for(lambda: all(p.matching_status.matching for p in publishers.values()), 10)
            for version in (100_000, 100_040, 100_080):
                for actor, distance in ((opensim, 1.0), (port, 15.0)):
                    publishers[actor].put(encode(EpisodeSummary(
                        actor_id=actor, env_id=0, episode_return=distance, distance=distance, length=1000,
                        policy_version=version, difficulty=0, seed=0, evaluation=True)))
            stage_run = opensim_stage.run_dir_of(port_run)
            assert wait_for(lambda: (stage_run / "launch.json").exists(), 120), "OpenSim's stage never started"
        summary = json.loads((port_run / "summary.json").read_text())
        assert summary["outcome"].startswith(f"{PARTED}: 3 OpenSim evaluations in a row under 0.7"), summary
        assert summary["time"] < 200
        # OpenSim's stage has the rest of the job's 300 s, not the 100 a port's stage of 200 s leaves.
        stage_seconds = json.loads((stage_run / "launch.json").read_text())["args"]["seconds"]
        assert stage_seconds == pytest.approx(300 - RunCounters.read(port_run / "metrics").time)
        assert stage_seconds > 150
    finally:
        job.send_signal(signal.SIGINT)
        try:
            job.wait(60)
        except subprocess.TimeoutExpired:
            job.kill()
    assert job.returncode == 0, log.read_text()[-3000:]
