"""Sequence tracking: duplicates, gaps kept as runs, the bounds on what one actor can make a
shard remember, acks, and snapshots of it."""

from __future__ import annotations

import json
import time

from l2r.replay.sequences import MAX_MISSING_RUNS, MAX_MISSING_SPAN, MissingRuns, SequenceTracker


def test_sequences_drop_duplicates_and_count_gaps():
    seqs = SequenceTracker()
    assert [seqs.accept(1, 10, s) for s in (0, 1, 1, 4, 2)] == [True, True, False, True, True]
    assert (seqs.total("duplicates"), seqs.total("gaps")) == (1, 1)  # 3 is still missing
    assert seqs.accept(1, 10, 3) and seqs.total("gaps") == 0
    assert not seqs.accept(1, 9, 50) and seqs.total("superseded") == 1  # an older incarnation of the actor
    assert seqs.accept(1, 11, 0) and seqs.restarts == 1  # restarted actor counts again from 0
    copy = SequenceTracker()
    copy.restore(seqs.state())
    assert copy.state() == seqs.state()


def test_acks_say_what_is_stored_within_a_bounded_missing_list():
    seqs = SequenceTracker()
    for s in (0, 1, 4, 2, 9):
        seqs.accept(1, 10, s)
    seqs.accept(2, 20, 0)
    assert seqs.acks() == [(1, 10, 9, [3, 5, 6, 7, 8]), (2, 20, 0, [])]
    # Too many missing to list: highest drops below the first one left out, so the ack stays true.
    assert seqs.acks(limit=2) == [(1, 10, 5, [3, 5]), (2, 20, 0, [])]


def test_filling_a_gap_splits_its_run():
    runs = MissingRuns([(3, 10)])
    assert runs.discard(5) and runs.discard(3) and runs.discard(9) and not runs.discard(5)
    assert runs.runs == [(4, 5), (6, 9)] and len(runs) == 4
    assert runs.first(2) == [4, 6]
    assert runs.forget_below(7) == 2 and runs.runs == [(7, 9)]


def test_a_jump_costs_the_same_whatever_its_size():
    seqs = SequenceTracker()
    seqs.accept(1, 10, 10_000)  # 10,000 missing already: where the old bookkeeping began to stall
    seq = 10_000
    for jump in [*range(1, 2000), 10**11]:
        seq += 10_000 * jump
        start = time.perf_counter()
        assert seqs.accept(1, 10, seq)
        assert time.perf_counter() - start < 0.05, jump  # was 5 s per jump of 10^4 or more
    record = seqs.actors[1]
    # what the shard still waits for stays within the span; the far jump is counted, not its size
    assert len(record.missing) <= MAX_MISSING_SPAN and record.gaps < 2000 * MAX_MISSING_SPAN
    assert record.jumps >= 1 and seqs.acks()[0][2] == seq - MAX_MISSING_SPAN + 4096 - 1
    assert len(json.dumps(seqs.state())) < 1000


def test_one_actor_cannot_make_the_shard_remember_more_than_the_run_bound():
    seqs = SequenceTracker()
    for seq in range(1, 2 * (MAX_MISSING_RUNS + 100), 2):  # every other chunk lost: one run each
        seqs.accept(1, 10, seq)
    record = seqs.actors[1]
    assert len(record.missing.runs) == MAX_MISSING_RUNS
    assert record.given_up == 100 and record.gaps == MAX_MISSING_RUNS + 100
    assert not seqs.accept(1, 10, 0)  # given up: a late chunk is dropped like a duplicate
    assert seqs.accept(1, 10, 2 * (MAX_MISSING_RUNS + 100) - 2)  # still waited for


def test_restore_drops_records_no_chunks_could_make_and_reads_older_snapshots():
    saved = {"restarts": 0, "actors": {
        "1": {"epoch": 5, "highest": 2**64 - 1, "missing_runs": [], "chunks": 1},  # the overflow of old
        "2": {"epoch": 5, "highest": 9, "missing": [3, 4, 7], "chunks": 7, "transitions": 70, "gaps": 3},
        str(2**63): {"epoch": 5, "highest": 1, "missing_runs": []},
        "3": {"epoch": 5, "highest": 9, "missing_runs": [[4, 2]]},
    }}
    seqs = SequenceTracker()
    seqs.restore(saved)
    assert list(seqs.actors) == [2]
    assert seqs.actors[2].missing.runs == [(3, 4), (4, 5), (7, 8)]
    assert seqs.acks() == [(2, 5, 9, [3, 4, 7])]
    assert seqs.accept(2, 5, 4) and not seqs.accept(2, 5, 5)
