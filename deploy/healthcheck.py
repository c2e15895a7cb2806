"""Container health check: is a daemon of this role alive on the run's Zenoh network?

    python deploy/healthcheck.py --zenoh-config FILE --run NAME --role replay

Opens a session with the role's own Zenoh config (so it passes the router's TLS, password and
access control like the daemon does) and asks for the role's liveliness tokens. Exits 0 when
one answers, 1 otherwise. A token only exists while the daemon is up and connected. Without
--run, the run is $L2R_RUN, as the daemons read it (Kubernetes probes cannot expand variables).
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Mapping

import zenoh

from l2r.protocol.keys import Keys
from l2r.protocol.session import session_config


def alive(config_file: str, run: str, role: str, timeout_s: float) -> bool:
    conf = session_config(mode=None, config_file=config_file)
    conf.insert_json5("connect/timeout_ms", str(int(timeout_s * 1000)))  # never wait forever here
    try:
        with zenoh.open(conf) as session:
            replies = session.liveliness().get(Keys(run).alive_role(role), timeout=timeout_s)
            return any(reply.ok is not None for reply in replies)
    except zenoh.ZError as e:
        print(f"healthcheck: {e}", file=sys.stderr)
        return False


def build_parser(environ: Mapping[str, str] = os.environ) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--zenoh-config", required=True, metavar="FILE")
    p.add_argument("--run", default=environ.get("L2R_RUN"), required="L2R_RUN" not in environ,
                   help="run name (default: $L2R_RUN)")
    p.add_argument("--role", required=True, choices=("replay", "learner", "actor"))
    p.add_argument("--timeout", type=float, default=3.0, help="seconds (default: %(default)s)")
    return p


def cli(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    return 0 if alive(args.zenoh_config, args.run, args.role, args.timeout) else 1


if __name__ == "__main__":
    sys.exit(cli())
