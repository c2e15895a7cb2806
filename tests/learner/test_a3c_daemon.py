"""A3C through a real learner process and real Zenoh: a gradient sent at the published version is
applied and the next weights follow; stale, ill-fitting, non-finite and unreadable ones are
logged and counted, and the learner goes on; one from a version ahead of the learner's (it
resumed from an older checkpoint) moves its weights above that version."""

import signal

import msgpack
import numpy as np

from l2r.learner import a3c
from l2r.learner.checkpoint import load_checkpoint
from l2r.protocol import GRADIENT_QOS, Gradient, Keys, encode
from l2r.protocol.messages import PROTOCOL_VERSION
from tests.learner.conftest import WeightsWatcher, learner_args

A3C_LEARNER = ["--algo", "a3c", "--obs-dim", "3", "--act-dim", "2", "--hidden", "8,8", "--max-gradient-staleness", "1"]


def test_the_learner_applies_fresh_gradients_and_counts_the_ones_it_refuses(network, tmp_path):
    run_dir = tmp_path / "run"
    watcher = WeightsWatcher(network.session, network.run)
    learner = network.start("l2r.learner", *learner_args(network, run_dir, *A3C_LEARNER), name="learner")
    watcher.wait(lambda v: v, 60, "the first weights", learner)
    first = watcher.last
    assert first.value_params is not None and first.training["max_gradient_staleness"] == 1
    replica, _ = a3c.replica_of(first)  # what an actor builds of them
    size = sum(p.numel() for p in replica.parameters())
    moments = np.array([1.0, *np.zeros(6)])  # --normalize-obs is off: no moments expected

    sent = network.session.declare_publisher(Keys(network.run).gradients(0), **GRADIENT_QOS.publisher())

    def send(version: int, values: np.ndarray, obs_moments=None) -> None:
        sent.put(encode(Gradient(0, version, 5, values.astype(np.float32), obs_moments)))

    ones = np.full(size, 1e-3)
    send(first.version, ones)
    watcher.wait(lambda v: v[-1] == first.version + 1, 30, "weights after the gradient", learner)
    send(first.version + 1, ones)
    watcher.wait(lambda v: v[-1] == first.version + 2, 30, "weights after the second gradient", learner)
    send(first.version, ones)  # two versions behind now: stale
    send(first.version + 2, ones[:-1])  # wrong size
    send(first.version + 2, ones, moments)  # moments it does not take
    nan = msgpack.packb({"v": 1, "kind": "gradient", "actor_id": 0, "policy_version": first.version + 2,
                         "env_steps": 5, "gradient": {"dtype": "<f4", "shape": [size],
                                                      "data": np.full(size, np.nan, np.float32).tobytes()}})
    sent.put(nan)
    sent.put(encode(Gradient(0, first.version + 2, 5, ones.astype(np.float32))).replace(
        b"\xa1v\x01", b"\xa1v" + bytes([PROTOCOL_VERSION + 1])))  # a version this side does not speak
    send(first.version + 2, ones)  # and a good one still goes through
    watcher.wait(lambda v: v[-1] == first.version + 3, 30, "weights after the third gradient", learner)

    def counted(metrics: dict) -> bool:
        return (metrics.get("rejected.stale", 0), metrics.get("rejected.wrong_size", 0),
                metrics.get("rejected.not_finite", 0), metrics.get("rejected.version", 0)) == (1, 2, 1, 1)
    watcher.wait(lambda _: any(counted(m) for m in watcher.metrics), 30, "the refusals counted", learner)
    send(first.version + 10, ones)  # from weights of an earlier life of the learner
    watcher.wait(lambda v: v[-1] == first.version + 11, 30, "weights above the actors' version", learner)
    assert learner.stop(signal.SIGTERM) == 0
    saved = load_checkpoint(run_dir / "learner" / "checkpoint.pt")
    assert saved.algo == "a3c" and saved.train_state["updates"] == 3 and saved.train_state["version"] == first.version + 11
