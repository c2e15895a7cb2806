"""Small Zenoh clients the multi-host tests run on their hosts (inside namespaces they cannot reach).

    probe.py pub   --zenoh-config F --key K --count N --interval S
    probe.py sub   --zenoh-config F --key K --out FILE
    probe.py watch --zenoh-config F --run R --out FILE    # the run's stats, metrics, version beacons,
                                                          # episodes and (with an actor's keys) acks

``sub`` and ``watch`` append one JSON object per line to FILE, flushed, until SIGTERM; ``Watch``
reads what ``watch`` wrote.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from l2r.protocol import messages
from l2r.protocol.keys import Keys
from l2r.protocol.session import session_config


def open_session(config_file: str) -> zenoh.Session:
    return zenoh.open(session_config(mode=None, config_file=config_file))


def writer(path: str):
    out = open(path, "a", buffering=1)
    lock = threading.Lock()

    def write(record: dict) -> None:
        with lock:
            out.write(json.dumps(record) + "\n")

    return write


def watch_record(sample: zenoh.Sample) -> dict:
    message = messages.decode(sample.payload.to_bytes())
    record = {"t": time.time(), "key": str(sample.key_expr), "kind": type(message).__name__}
    if isinstance(message, messages.Stats):
        record["values"] = message.values
    elif isinstance(message, messages.LearnerVersion):
        record["version"] = message.version
    elif isinstance(message, messages.EpisodeSummary):
        record["actor"] = message.actor_id
    elif isinstance(message, messages.ReplayAck):
        missing = np.split(message.missing, np.cumsum(message.missing_counts)[:-1])
        record["acks"] = {str(a): [int(e), int(h), m.tolist()]
                          for a, e, h, m in zip(message.actor_ids, message.epochs, message.highest, missing)}
    return record


def read_lines(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]


class Watch:
    """The run's stats, metrics, version beacons, episodes and acks as a watch probe saw them."""

    def __init__(self, path: Path):
        self.path = path

    def records(self) -> list[dict]:
        return read_lines(self.path)

    def replay(self) -> list[dict]:
        return [r["values"] | {"t": r["t"]} for r in self.records() if "/stats/replay/" in r.get("key", "")]

    def actors(self) -> dict[str, list[dict]]:
        out: dict[str, list[dict]] = {}
        for r in self.records():
            if "/stats/actor/" in r.get("key", ""):
                out.setdefault(r["key"].rsplit("/", 1)[1], []).append(r["values"] | {"t": r["t"]})
        return out

    def versions(self) -> list[tuple[float, int]]:
        return [(r["t"], r["version"]) for r in self.records() if "version" in r]

    def episodes(self) -> list[tuple[float, int]]:
        """(when, which actor) of every finished episode."""
        return [(r["t"], r["actor"]) for r in self.records() if "actor" in r]

    def acks(self) -> list[tuple[float, dict[str, list]]]:
        """(when, {actor: [epoch, highest, missing]}) of every replay ack."""
        return [(r["t"], r["acks"]) for r in self.records() if "acks" in r]

    def stored(self, actor: str) -> float:
        """Transitions of ``actor`` the replay server holds, by its latest stats."""
        replay = self.replay()
        return replay[-1].get(f"actor.{actor}.transitions", 0) if replay else 0


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("action", choices=("pub", "sub", "watch"))
    p.add_argument("--zenoh-config", required=True)
    p.add_argument("--key")
    p.add_argument("--run")
    p.add_argument("--out")
    p.add_argument("--count", type=int, default=10)
    p.add_argument("--interval", type=float, default=0.1)
    args = p.parse_args(argv)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    with open_session(args.zenoh_config) as session:
        if args.action == "pub":
            for i in range(args.count):
                session.put(args.key, json.dumps({"i": i, "t": time.time()}))
                time.sleep(args.interval)
            return 0
        write = writer(args.out)
        if args.action == "sub":
            subs = [session.declare_subscriber(args.key, lambda s: write(json.loads(s.payload.to_string())))]
        else:
            keys = Keys(args.run)

            def on_sample(sample: zenoh.Sample) -> None:
                try:
                    write(watch_record(sample))
                except messages.ProtocolError as e:
                    write({"t": time.time(), "key": str(sample.key_expr), "error": str(e)})

            # Acks reach actors alone: with other keys that subscription gets nothing.
            subs = [session.declare_subscriber(k, on_sample) for k in (
                keys.all_stats, keys.all_metrics, keys.learner_version, keys.all_episodes, keys.replay_ack(0))]
        write({"ready": True, "t": time.time()})
        stop.wait()
        for sub in subs:
            sub.undeclare()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
