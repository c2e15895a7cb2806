"""Small Zenoh clients the multi-host tests run on their hosts (inside namespaces they cannot reach).

    probe.py pub   --zenoh-config F --key K --count N --interval S
    probe.py sub   --zenoh-config F --key K --out FILE
    probe.py watch --zenoh-config F --run R --out FILE    # the run's stats, metrics and version beacons

``sub`` and ``watch`` append one JSON object per line to FILE, flushed, until SIGTERM.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
import time

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
    return record


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

            subs = [session.declare_subscriber(k, on_sample)
                    for k in (keys.all_stats, keys.all_metrics, keys.learner_version)]
        write({"ready": True, "t": time.time()})
        stop.wait()
        for sub in subs:
            sub.undeclare()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
