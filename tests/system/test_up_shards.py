"""`l2r up --replay-shards N`: the processes it plans (fast, none started), the resumes it refuses,
and a short job of two shards end to end: both take inserts and serve the learner, one killed is
restarted and serves again, and a resume restores both."""

import json
import os
import re
import signal
import uuid
from pathlib import Path

import pytest

from l2r import disk_budget
from l2r.actors.__main__ import parse_settings as actor_settings
from l2r.job_plan import plan_children, recipe_of
from l2r.learner.__main__ import parse_settings as learner_settings
from l2r.protocol.keys import shard_of
from l2r.replay.__main__ import parse_settings as replay_settings
from l2r.replay.storage import StorageConfig, storage_bytes
from l2r.up import parse_args
from tests.conftest import wait_for
from tests.system.test_up import SMALL, finish, l2r_up, pid_of, rows, up_log


def planned(*argv: str) -> tuple:
    args, _ = parse_args(list(argv))
    return args, plan_children(args, "run", Path("runs/x"), [7447, 7449], 7448)


def test_two_shards_split_the_job_s_capacity_and_warm_up_and_every_actor_feeds_one_of_them():
    args, children = planned("--replay-shards", "2", "--actors", "3", "--capacity", "1001", "--min-replay", "301")
    by_name = {c.name: c for c in children}
    shards = [replay_settings(by_name[f"replay-{k}"].argv[3:]) for k in (0, 1)]
    assert [(s.shard, s.num_shards, s.capacity, s.min_size) for s in shards] == [(0, 2, 501, 151), (1, 2, 500, 151)]
    assert [s.listen for s in shards] == [["tcp/127.0.0.1:7447"], ["tcp/127.0.0.1:7449"]]
    assert [s.snapshot_dir for s in shards] == [Path("runs/x/replay")] * 2  # replay-shard<k>.npz side by side
    assert [c.progress for c in children if c.argv[2] == "l2r.replay"] == [("replay", "0", "inserted"),
                                                                           ("replay", "1", "inserted")]
    shard_ports = ["tcp/127.0.0.1:7447", "tcp/127.0.0.1:7449"]
    assert learner_settings(by_name["learner"].argv[3:]).connect == shard_ports
    actors = [actor_settings(by_name[f"actor-{i}"].argv[3:]) for i in range(3)]
    assert [shard_of(a.actor_id, a.num_shards) for a in actors] == [0, 1, 0]
    assert all(a.connect[:2] == shard_ports for a in actors)
    assert actor_settings(by_name["evaluator-0"].argv[3:]).connect[:2] == shard_ports

    # The disk estimate counts each shard's table: two halves of a run long enough to fill them.
    recipe = recipe_of(args).values
    tables = [3 * storage_bytes(StorageConfig(capacity=capacity)) for capacity in (501, 500)]
    assert disk_budget.estimate(args, recipe, children)["replay"] == sum(tables)


@pytest.mark.parametrize("argv, error", [
    (["--replay-shards", "3", "--actors", "2"], "--replay-shards must be between 1 and --actors (2), got 3"),
    (["--replay-shards", "0"], "--replay-shards must be between 1 and --actors (1), got 0"),
    (["--replay-shards", "2", "--actors", "2", "--algo", "ppo"], "--replay-shards is for the replay table of sac"),
])
def test_shards_an_actor_cannot_feed_or_an_on_policy_job_are_refused_in_one_line(argv, error, capsys):
    with pytest.raises(SystemExit) as exit:
        parse_args(argv)
    assert exit.value.code == 2 and error in capsys.readouterr().err


@pytest.mark.parametrize("stored, given", [(2, "1"), (None, "2")])  # None: a run from before the flag
def test_a_resume_with_another_number_of_shards_than_the_replay_kept_is_refused(stored, given, tmp_path, capsys):
    (tmp_path / "replay").mkdir()
    (tmp_path / "replay" / "replay-shard0.npz").write_bytes(b"")
    (tmp_path / "launch.json").write_text(json.dumps({"args": {"actors": 2} | (
        {} if stored is None else {"replay_shards": stored})}))
    with pytest.raises(SystemExit) as exit:
        parse_args(["--resume", str(tmp_path), "--replay-shards", given])
    kept = stored or 1
    assert exit.value.code == 2
    assert (f"--replay-shards {given}: the run's replay in {tmp_path / 'replay'} is kept by {kept} shard"
            f"{'s' if kept > 1 else ''}; resume with --replay-shards {kept}") in capsys.readouterr().err
    (tmp_path / "replay" / "replay-shard0.npz").unlink()  # with replay/ moved away or empty, any number goes
    assert parse_args(["--resume", str(tmp_path), "--replay-shards", given])[0].replay_shards == int(given)


def logged(run_dir: Path, shard: int, pattern: str) -> list[int]:
    """The numbers a replay shard's log gives in the lines `pattern` matches."""
    path = run_dir / "logs" / f"replay-{shard}.log"
    return [int(n) for n in re.findall(pattern, path.read_text())] if path.exists() else []


def restored(run_dir: Path, shard: int) -> list[int]:
    return logged(run_dir, shard, r"restored (\d+) transitions from")


def shard_rows(run_dir: Path, shard: str) -> list[dict]:
    return [r for r in rows(run_dir / "metrics" / "replay.csv") if r["shard"] == shard]


def serves(row: dict) -> bool:
    """Whether a shard's stats say it took experience and answered the learner."""
    return int(row["inserted"]) > 0 and int(row["sampled_batches"]) > 0


@pytest.mark.slow
def test_a_job_of_two_shards_fills_and_samples_both_restarts_one_and_resumes_both(tmp_path):
    name = f"test-{uuid.uuid4().hex[:6]}"
    # Both actors at the learner's priority and the learner held to the actors' pace, so that on two
    # loaded cores neither actor starves while the other fills its shard.
    first = l2r_up(tmp_path / "first.out", "--seconds", "600", "--name", name, "--runs-dir", str(tmp_path),
                   "--actors", "2", "--envs-per-actor", "2", "--evaluators", "0", "--replay-shards", "2",
                   "--actor-nice", "0", "--samples-per-insert", "32", "--replay-arg=--stats-interval=1", *SMALL)
    try:
        run_dir = wait_for(lambda: next(tmp_path.glob(f"{name}-*"), None), timeout=60)
        assert run_dir, "no run directory"
        assert wait_for(lambda: all(any(map(serves, shard_rows(run_dir, k))) for k in "01"), timeout=180), \
            "a shard took no experience or served no batch"
        os.kill(pid_of(run_dir, "replay-1"), signal.SIGKILL)
        assert wait_for(lambda: "replay-1 killed by SIGKILL" in up_log(run_dir), timeout=10)
        before = len(shard_rows(run_dir, "1"))
        # The restarted shard counts from 0 again: its actor's experience and the learner come back to it.
        assert wait_for(lambda: any(map(serves, shard_rows(run_dir, "1")[before + 1:])), timeout=120), \
            "the restarted shard took no experience or served no batch"
        first.send_signal(signal.SIGTERM)
    finally:
        out = finish(first, tmp_path / "first.out", 120)
    assert first.returncode == 0, out
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["restarts_by_process"] == {"replay-1": 1}, summary
    last = [shard_rows(run_dir, k)[-1] for k in "01"]
    assert summary["updates"] > 0 and summary["replay_size"] == sum(int(r["size"]) for r in last), summary
    assert {p.name for p in (run_dir / "replay").glob("*.npz")} == {"replay-shard0.npz", "replay-shard1.npz"}
    kept = [logged(run_dir, k, r"snapshot: (\d+) transitions")[-1] for k in (0, 1)]
    restores = [len(restored(run_dir, k)) for k in (0, 1)]

    # Each shard restores its own snapshot; the job is stopped once both have.
    second = l2r_up(tmp_path / "second.out", "--resume", str(run_dir), "--env-steps", "1000000")
    try:
        assert wait_for(lambda: all(len(restored(run_dir, k)) > restores[k] for k in (0, 1)), timeout=120), \
            "a shard restored nothing"
        second.send_signal(signal.SIGTERM)
    finally:
        out = finish(second, tmp_path / "second.out", 120)
    assert second.returncode == 0, out
    assert [restored(run_dir, k)[-1] for k in (0, 1)] == kept
