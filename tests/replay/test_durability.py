"""An ack means on disk: a real l2r-replay killed with -9 at any moment comes back with every
chunk it acknowledged, from its snapshot and its write-ahead log. With --no-wal it writes no
log, but still replays one an earlier session left."""

from __future__ import annotations

import time

import pytest

from l2r.protocol import EXPERIENCE_QOS, Keys, encode
from tests.conftest import wait_for
from tests.protocol.factories import make_chunk

pytestmark = pytest.mark.slow


def send(session, run: str, seqs, actor_id: int = 2, steps: int = 10) -> None:
    for seq in seqs:
        session.put(Keys(run).experience(actor_id), encode(make_chunk(actor_id=actor_id, seq=seq, steps=steps)),
                    **EXPERIENCE_QOS.put())


def all_stored_up_to(highest: int, actor_id: int = 2, epoch: int = 1):
    def check(ack) -> bool:
        row = ack.of(actor_id, epoch)
        return row is not None and row[0] >= highest and len(row[1]) == 0
    return check


def killed_after_acks(start_replay, connect, acks_of, run: str, args, seqs, **start):
    """A replay server started with `args` that acknowledged the chunks `seqs` and was then killed
    with -9 (after its last snapshot, only its write-ahead log holds them)."""
    replay = start_replay(*args, **start)
    session = connect(replay)
    send(session, run, seqs)
    acks_of(session).wait(all_stored_up_to(seqs[-1]))
    replay.proc.kill()
    replay.proc.wait()
    return replay


def test_what_was_acknowledged_survives_kill_9_between_snapshots(start_replay, connect, ask_stats, acks_of,
                                                                 run_name, tmp_path):
    snap = tmp_path / "snap"
    replay = start_replay("--snapshot-dir", str(snap), "--snapshot-interval", "0.3")
    session = connect(replay)
    send(session, run_name, range(20))
    acks_of(session).wait(all_stored_up_to(19))
    assert wait_for(lambda: replay.log().count("snapshot: 200 transitions") >= 2), replay.log()
    assert len(list(snap.glob("replay-shard0.wal.*"))) <= 2  # each snapshot lets the log before it go
    assert replay.stop() == 0

    args = ("--snapshot-dir", str(snap), "--snapshot-interval", "3600")
    # After the last snapshot: only the log has these.
    replay = killed_after_acks(start_replay, connect, acks_of, run_name, args, range(20, 50), endpoint=replay.endpoint)

    again = start_replay(*args, endpoint=replay.endpoint)
    session = connect(again)
    stats = ask_stats(session)
    assert stats["size"] == 500 and stats["actor.2.transitions"] == 500, again.log()[-3000:]
    send(session, run_name, [49, 50])  # a resend of the last acknowledged chunk is still a duplicate
    acks_of(session).wait(all_stored_up_to(50))
    assert ask_stats(session)["duplicates"] == 1


def test_a_record_cut_short_by_the_crash_ends_the_log(start_replay, connect, ask_stats, acks_of, run_name, tmp_path):
    snap = tmp_path / "snap"
    args = ("--snapshot-dir", str(snap), "--snapshot-interval", "3600")
    replay = killed_after_acks(start_replay, connect, acks_of, run_name, args, range(5))
    segment = max(snap.glob("replay-shard0.wal.*"), key=lambda p: int(p.suffix[1:]))
    with open(segment, "ab") as f:
        f.write(b"\x00\x10\x00\x00half a header and no payload")

    again = start_replay(*args, endpoint=replay.endpoint)
    session = connect(again)
    assert ask_stats(session)["size"] == 50
    assert "bytes after the last whole record ignored" in again.log()


def test_no_wal_writes_no_log(start_replay, connect, acks_of, run_name, tmp_path):
    snap = tmp_path / "snap"
    replay = start_replay("--snapshot-dir", str(snap), "--snapshot-interval", "0.3", "--no-wal")
    session = connect(replay)
    send(session, run_name, range(5))
    acks_of(session).wait(all_stored_up_to(4))
    assert wait_for(lambda: "snapshot: 50 transitions" in replay.log()), replay.log()
    assert replay.stop() == 0
    assert [path.name for path in snap.iterdir()] == ["replay-shard0.npz"]


def test_no_wal_still_replays_the_log_an_earlier_session_left(start_replay, connect, ask_stats, acks_of, run_name,
                                                               tmp_path):
    snap = tmp_path / "snap"
    args = ("--snapshot-dir", str(snap), "--snapshot-interval", "3600")
    replay = killed_after_acks(start_replay, connect, acks_of, run_name, args, range(5))
    logged = {path: path.stat().st_size for path in snap.glob("replay-shard0.wal.*")}

    again = start_replay(*args, "--no-wal", endpoint=replay.endpoint)
    session = connect(again)
    assert ask_stats(session)["size"] == 50, again.log()[-3000:]
    send(session, run_name, range(5, 10))
    acks_of(session).wait(all_stored_up_to(9))
    assert {path: path.stat().st_size for path in snap.glob("replay-shard0.wal.*")} == logged  # nor adds to it


def test_a_full_disk_stops_acks_until_space_comes_back_and_loses_nothing_acknowledged(
        start_replay, connect, ask_stats, acks_of, run_name, small_disk):
    disk = small_disk(4)
    snap = disk.path / "snap"
    args = ("--snapshot-dir", str(snap), "--snapshot-interval", "3600")
    replay = start_replay(*args)
    session = connect(replay)
    acks = acks_of(session)
    send(session, run_name, range(10))
    acks.wait(all_stored_up_to(9))

    disk.fill()
    send(session, run_name, range(10, 20))  # stored, but their log cannot be written: no ack names them
    assert wait_for(lambda: "write-ahead log failed" in replay.log()), replay.log()[-2000:]
    failure = [line for line in replay.log().splitlines() if "write-ahead log failed" in line]
    assert len(failure) == 1 and f"disk full at {snap}" in failure[0] and "MB free" in failure[0], failure
    send(session, run_name, range(20, 25))  # refused while the log fails: their sender keeps them
    time.sleep(1.0)
    assert acks.acks[-1].of(2, 1)[0] == 9, "acknowledged chunks the log does not hold"
    assert "Traceback" not in replay.log()

    disk.free()
    freed = time.monotonic()
    acks.wait(lambda ack: ack.of(2, 1)[0] >= 19, timeout=5)
    assert time.monotonic() - freed < 2.0, "no ack within 2 s of space coming back"
    send(session, run_name, range(20, 25))  # what an actor resends of the chunks refused
    acks.wait(all_stored_up_to(24))
    assert "write-ahead log writes again" in replay.log()

    replay.proc.kill()
    replay.proc.wait()
    again = start_replay(*args, endpoint=replay.endpoint)
    assert ask_stats(connect(again))["size"] == 250, again.log()[-3000:]
