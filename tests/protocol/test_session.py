"""Session configuration, key expressions, and messages over real Zenoh (the daemons' shared
settings are in tests/test_config.py)."""

from __future__ import annotations

import json
import signal
import threading
import time

import pytest
import zenoh

from l2r.protocol import Keys, decode, encode, parse_alive, session_config, shard_of, wait_alive
from l2r.protocol.session import wait_until_stopped
from tests.protocol.factories import every_message
from tests.protocol.test_messages import assert_same


def test_explicit_endpoints_turn_scouting_off():
    conf = session_config(connect=["tcp/127.0.0.1:7000"], listen=["tcp/127.0.0.1:7001"])
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7000"]
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7001"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("mode")) == "peer"


def test_zenoh_config_file_is_passed_through_with_flags_on_top(tmp_path):
    path = tmp_path / "z.json5"
    path.write_text('{ mode: "client", // Zenoh\'s own JSON5\n  connect: { endpoints: ["tcp/10.0.0.1:7447"] } }')
    conf = session_config(listen=["tcp/127.0.0.1:7002"], mode=None, config_file=path)
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/10.0.0.1:7447"]
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7002"]


def test_run_names_that_would_break_keys_are_refused():
    with pytest.raises(ValueError):
        Keys("runs/*")


def test_keys_are_scoped_by_run_and_shard():
    a, b = Keys("a"), Keys("b")
    assert a.experience(7, num_shards=3) == "l2r/a/experience/1/7" and shard_of(7, 3) == 1
    assert zenoh.KeyExpr(a.experience_of_shard(1)).intersects(zenoh.KeyExpr(a.experience(7, 3)))
    assert not zenoh.KeyExpr(b.experience_of_shard(1)).intersects(zenoh.KeyExpr(a.experience(7, 3)))
    assert not zenoh.KeyExpr(a.experience_of_shard(0)).intersects(zenoh.KeyExpr(a.experience(7, 3)))
    assert parse_alive(a.alive("actor", 4)) == ("actor", "4")
    assert zenoh.KeyExpr(a.viewers).intersects(zenoh.KeyExpr(a.alive("viewer", "me")))
    with pytest.raises(ValueError):
        a.alive("wizard", 1)


def test_every_message_crosses_real_zenoh(endpoint, run_name):
    keys = Keys(run_name)
    received, done = [], threading.Event()
    messages = every_message()

    def on_sample(sample: zenoh.Sample) -> None:
        received.append(decode(sample.payload))
        if len(received) == len(messages):
            done.set()

    with zenoh.open(session_config(listen=[endpoint])) as listener, \
            zenoh.open(session_config(connect=[endpoint])) as sender:
        sub = listener.declare_subscriber(keys.all_stats, on_sample)
        token = listener.liveliness().declare_token(keys.alive("replay", 0))
        assert [parse_alive(k) for k in wait_alive(sender, keys.alive_role("replay"))] == [("replay", "0")]
        for message in messages:
            sender.put(keys.stats("actor", 0), encode(message))
        assert done.wait(10), f"{len(received)} of {len(messages)} arrived"
        sub.undeclare()
        token.undeclare()
    for sent, got in zip(messages, received):
        assert_same(got, sent)


def test_a_stop_signal_delivered_to_another_thread_ends_the_wait():
    # The kernel may hand a process's SIGTERM to any thread (a Zenoh thread, in a daemon); Python
    # runs the handler in the main thread only when that thread next runs Python.
    stop, idle = threading.Event(), threading.Event()
    bystander = threading.Thread(target=idle.wait)
    bystander.start()
    previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        threading.Timer(0.2, signal.pthread_kill, (bystander.ident, signal.SIGTERM)).start()
        started = time.monotonic()
        wait_until_stopped(stop, 10.0)
        assert stop.is_set() and time.monotonic() - started < 2.0
    finally:
        signal.signal(signal.SIGTERM, previous)
        idle.set()
        bystander.join()


def test_the_wait_ends_after_its_seconds_when_nothing_stops_it():
    started = time.monotonic()
    wait_until_stopped(threading.Event(), 0.3)
    assert 0.3 <= time.monotonic() - started < 1.5
