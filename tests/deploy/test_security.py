"""The deployment's security, through a real `l2r router` running deploy/zenoh/router.json5.

Every session uses the role configs deploy/make-secrets.sh renders (mutual TLS, user/password);
the router's access control must let each role do its part of the data flow and nothing else.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import threading
import time
import uuid
from typing import Callable

import msgpack
import numpy as np
import pytest
import zenoh

from l2r.policy import build_policy, default_spec, policy_state
from l2r.protocol import messages
from l2r.protocol.keys import Keys

from tests.conftest import free_port, wait_for

from .zenoh_helpers import make_secrets, role_config, start_router, stop

pytestmark = pytest.mark.skipif(not shutil.which("openssl"), reason="needs the openssl CLI")

SETTLE_S = 0.5  # after the allowed message arrived, how long a forbidden one gets to show up


@pytest.fixture(scope="module")
def secure_router(tmp_path_factory):
    """A router with the deployment's router config, listening on a loopback port; its keys."""
    tmp = tmp_path_factory.mktemp("secure")
    secrets = make_secrets(tmp / "secrets")
    endpoint = f"tls/127.0.0.1:{free_port()}"
    proc = start_router(["-c", str(secrets / "router" / "zenoh.json5"), "-l", endpoint], tmp / "router.log")
    yield secrets, endpoint, tmp / "router.log"
    stop(proc)


@pytest.fixture
def open_as(secure_router):
    """Open a session as a role: ``open_as("actor")``, or with another role's password."""
    secrets, endpoint, _ = secure_router
    sessions = []

    def _open(role: str, password_of: str | None = None, **overrides) -> zenoh.Session:
        if password_of:
            other = zenoh.Config.from_file(str(secrets / password_of / "zenoh.json5"))
            overrides["transport__auth__usrpwd"] = json.loads(other.get_json("transport/auth/usrpwd"))
        session = zenoh.open(role_config(secrets, role, endpoint, **overrides))
        sessions.append(session)
        return session

    yield _open
    for session in sessions:
        session.close()


@pytest.fixture
def keys():
    return Keys(f"sec-{uuid.uuid4().hex[:8]}")


class Inbox:
    """Payloads a subscriber received, by text."""

    def __init__(self):
        self.items: list[str] = []
        self._lock = threading.Lock()

    def __call__(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.items.append(sample.payload.to_string())

    def got(self, text: str) -> bool:
        with self._lock:
            return text in self.items


def assert_only_allowed_arrive(inbox: Inbox, forbidden: dict[str, zenoh.Session], allowed, key: str) -> None:
    """Send from every forbidden session, then from the allowed one; only the allowed one arrives."""
    for name, session in forbidden.items():
        session.put(key, f"from-{name}")
    allowed.put(key, "from-allowed")
    assert wait_for(lambda: inbox.got("from-allowed")), "the allowed publisher's message never arrived"
    time.sleep(SETTLE_S)
    assert inbox.items == ["from-allowed"], f"forbidden messages got through: {inbox.items}"


@pytest.mark.parametrize(
    "what, overrides",
    [
        ("no client certificate", {"transport__link__tls__enable_mtls": False,
                                   "transport__link__tls__connect_certificate": None,
                                   "transport__link__tls__connect_private_key": None}),
        ("wrong password", {"transport__auth__usrpwd": {"user": "actor", "password": "guess"}}),
        ("no user name", {"transport__auth__usrpwd": {"user": None, "password": None}}),
        ("plain tcp", {"transport__link__protocols": ["tcp"]}),
    ],
)
def test_a_peer_without_credentials_cannot_connect(secure_router, what, overrides):
    secrets, endpoint, _ = secure_router
    if what == "plain tcp":
        endpoint = endpoint.replace("tls/", "tcp/")
    # The same role config with every credential in place connects: the refusals below are real.
    zenoh.open(role_config(secrets, "actor", secure_router[1])).close()
    with pytest.raises(zenoh.ZError):
        zenoh.open(role_config(secrets, "actor", endpoint, timeout_ms=500, **overrides)).close()


def test_the_router_logs_who_connects_and_as_whom(secure_router, open_as):
    _, _, log = secure_router
    open_as("learner")
    assert wait_for(lambda: "as learner" in log.read_text()), log.read_text()[-2000:]


# (who may publish, who listens, the key listened to, the key published, who may not,
#  whose password the allowed role's certificate tries): an ack makes actors forget chunks, so
#  from anyone but a replay server it would lose their experience.
ONLY_ONE_ROLE_PUBLISHES = {
    "experience": ("actor", "replay", lambda k: k.experience_of_shard(0), lambda k: k.experience(actor_id=3),
                   ("learner", "replay"), "learner"),
    "weights": ("learner", "actor", lambda k: k.weights, lambda k: k.weights, ("actor", "replay"), "actor"),
    "acks": ("replay", "actor", lambda k: k.replay_ack(0), lambda k: k.replay_ack(0), ("actor", "learner"), "actor"),
}


@pytest.mark.parametrize("what", ONLY_ONE_ROLE_PUBLISHES)
def test_only_one_role_may_publish(what, open_as, keys):
    allowed, listener, listened, published, others, password_of = ONLY_ONE_ROLE_PUBLISHES[what]
    inbox = Inbox()
    sub = open_as(listener).declare_subscriber(listened(keys), inbox)
    forbidden = {role: open_as(role) for role in others}
    forbidden[f"{allowed}-cert-with-{password_of}-password"] = open_as(allowed, password_of=password_of)
    time.sleep(SETTLE_S)  # let the subscription reach every session through the router
    assert_only_allowed_arrive(inbox, forbidden, open_as(allowed), published(keys))
    sub.undeclare()


@pytest.fixture
def replay_daemon(secure_router, keys, tmp_path):
    """A real l2r-replay with the replay role's config, connected to the secure router."""
    secrets, endpoint, _ = secure_router
    log = tmp_path / "replay.log"
    cmd = [sys.executable, "-m", "l2r.replay", "--run", keys.run, "--zenoh-config", str(secrets / "replay" / "zenoh.json5"),
           "--connect", endpoint, "--capacity", "1000", "--min-size", "1", "--stats-interval", "0.3",
           "--snapshot-dir", str(tmp_path / "snapshots")]  # with which shard 0 gives actors their ids
    with open(log, "w") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)
    yield log
    stop(proc)


def chunk(seq: int, steps: int = 4) -> messages.ExperienceChunk:
    rng = np.random.default_rng(seq)
    return messages.ExperienceChunk(
        actor_id=1, env_id=0, epoch=7, seq=seq, policy_version=0,
        obs=rng.standard_normal((steps + 1, 41), dtype=np.float32), actions=np.zeros((steps, 18), np.float32),
        rewards=np.ones(steps, np.float32), terminated=np.zeros(steps, bool), truncated=np.zeros(steps, bool),
        final_obs=np.zeros((0, 41), np.float32))


def replay_stats(session: zenoh.Session, keys: Keys) -> Callable[[], dict]:
    """The replay server's latest published stats, as a function to poll."""
    latest: dict = {}
    session.declare_subscriber(keys.stats("replay", 0), lambda s: latest.update(messages.decode(s.payload.to_bytes()).values))
    return lambda: dict(latest)


def test_only_learners_may_query_the_replay_server(open_as, keys, replay_daemon):
    learner = open_as("learner")
    stats = replay_stats(learner, keys)
    assert wait_for(lambda: "size" in stats(), timeout=20), replay_daemon.read_text()[-2000:]
    open_as("actor").put(keys.experience(actor_id=1), messages.encode(chunk(0)))
    assert wait_for(lambda: stats().get("size") == 4, timeout=20), replay_daemon.read_text()[-2000:]
    request = messages.encode(messages.SampleRequest(batch_size=2))
    queriers = {"learner": learner, "actor": open_as("actor"), "replay": open_as("replay"),
                "learner-cert-with-replay-password": open_as("learner", password_of="replay")}
    answered = {
        name: [type(messages.decode(r.ok.payload.to_bytes())).__name__
               for r in session.get(keys.sample(0), payload=request, timeout=3.0) if r.ok is not None]
        for name, session in queriers.items()
    }
    assert answered == {"learner": ["SampleBatch"], "actor": [], "replay": [], "learner-cert-with-replay-password": []}


def test_learners_and_actors_may_ask_a_replay_server_for_its_stats_and_only_it_answers(open_as, keys,
                                                                                       replay_daemon):
    def answers(session: zenoh.Session, shard: int) -> list[str]:
        replies = session.get(keys.stats("replay", shard), timeout=3.0)
        return [messages.decode(r.ok.payload.to_bytes()).role for r in replies if r.ok is not None]

    for role in ("learner", "actor"):
        session = open_as(role)
        assert wait_for(lambda: answers(session, 0) == ["replay"], timeout=20), role
    impostor = open_as("learner")
    queryable = impostor.declare_queryable(
        keys.stats("replay", 1), lambda q: q.reply(q.key_expr, messages.encode(messages.Stats("replay", "1", 0.0, {}))))
    time.sleep(SETTLE_S)
    assert answers(open_as("actor"), 1) == []
    queryable.undeclare()


def test_only_actors_may_ask_replay_shard_0_for_an_id(open_as, keys, replay_daemon):
    request = messages.encode(messages.ActorIdRequest("actor-7f3a:7"))

    def ids(session: zenoh.Session) -> list[int]:
        replies = session.get(keys.actor_ids, payload=request, timeout=3.0)
        return [messages.decode(r.ok.payload.to_bytes(), messages.ActorId).actor_id for r in replies if r.ok is not None]

    actor = open_as("actor")
    assert wait_for(lambda: ids(actor) == [0], timeout=20), replay_daemon.read_text()[-2000:]
    askers = {"learner": open_as("learner"), "replay": open_as("replay"),
              "actor-cert-with-learner-password": open_as("actor", password_of="learner")}
    assert {name: ids(session) for name, session in askers.items()} == {name: [] for name in askers}


def test_experience_of_another_protocol_version_or_run_is_dropped(open_as, keys, replay_daemon):
    """Through the router into the real replay server: a chunk from a newer protocol is rejected
    and logged; a chunk under another run's keys never reaches it; the good chunk is stored."""
    stats = replay_stats(open_as("learner"), keys)
    actor = open_as("actor")
    assert wait_for(lambda: "size" in stats(), timeout=20), replay_daemon.read_text()[-2000:]
    future = msgpack.unpackb(messages.encode(chunk(0)), raw=False)
    future["v"] = messages.PROTOCOL_VERSION + 1
    actor.put(keys.experience(actor_id=1), msgpack.packb(future, use_bin_type=True))
    actor.put(Keys(keys.run + "x").experience(actor_id=1), messages.encode(chunk(1)))
    actor.put(keys.experience(actor_id=1), messages.encode(chunk(2)))
    assert wait_for(lambda: stats().get("size") == 4 and stats().get("rejected") == 1, timeout=20), stats()
    time.sleep(2 * SETTLE_S)
    assert stats()["size"] == 4 and stats()["rejected"] == 1
    assert "version" in "".join(line for line in replay_daemon.read_text().splitlines() if "rejected" in line)


@pytest.mark.slow
def test_weights_of_another_protocol_version_are_dropped_by_the_actor(secure_router, open_as, keys, tmp_path):
    """Through the router into a real l2r-actor: weights from a newer protocol are rejected and logged."""
    secrets, endpoint, _ = secure_router
    log = tmp_path / "actor.log"
    cmd = [sys.executable, "-m", "l2r.actors", "--run", keys.run, "--actor-id", "5", "--num-envs", "1",
           "--zenoh-config", str(secrets / "actor" / "zenoh.json5"), "--connect", endpoint, "--torch-threads", "1"]
    learner = open_as("learner")
    latest: dict = {}
    learner.declare_subscriber(keys.stats("actor", 5), lambda s: latest.update(messages.decode(s.payload.to_bytes()).values))
    with open(log, "w") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)
    try:
        assert wait_for(lambda: "rejected_weights" in latest, timeout=30), log.read_text()[-2000:]
        spec = default_spec()
        spec["hidden"] = [8]
        weights = msgpack.unpackb(messages.encode(messages.Weights(3, policy_state(build_policy(spec)), spec)), raw=False)
        weights["v"] = messages.PROTOCOL_VERSION + 1
        learner.put(keys.weights, msgpack.packb(weights, use_bin_type=True))
        assert wait_for(lambda: latest["rejected_weights"] == 1, timeout=20), latest
        assert latest["policy_version"] != 3
        assert any("rejected" in line and "version" in line for line in log.read_text().splitlines())
    finally:
        stop(proc)


def test_a_session_that_matches_no_role_gets_nothing(open_as, keys):
    """Valid certificate and valid password, but of two different roles: no subject matches."""
    stranger = open_as("actor", password_of="learner")
    inbox = Inbox()
    subs = [stranger.declare_subscriber(k, inbox) for k in (keys.experience_of_shard(0), keys.weights, keys.all_stats)]
    time.sleep(SETTLE_S)
    open_as("actor").put(keys.experience(actor_id=0), "experience")
    open_as("learner").put(keys.weights, "weights")
    open_as("replay").put(keys.stats("replay", 0), "stats")
    time.sleep(2 * SETTLE_S)
    assert inbox.items == []
    for sub in subs:
        sub.undeclare()
