"""`l2r router`: a Zenoh router for hosts without `zenohd` (a zenoh-python session in router mode).

It takes zenohd's own flags for what our deployments use (`-c` config file in Zenoh's JSON5,
`-l` listen, `-e` connect), so the command line of the `router` service in
deploy/docker-compose.yml runs unchanged with `l2r router` in place of `zenohd`. TLS, user/password
authentication and access control are Zenoh settings in that file; this process only logs who
comes and goes.
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import threading
from typing import Sequence

import zenoh

from l2r.config import CommandParser
from l2r.protocol.session import configure_logging, session_config, wait_until_stopped

log = logging.getLogger("l2r.router")

DEFAULT_LISTEN = "tcp/[::]:7447"  # zenohd's default


def router_config(
    listen: Sequence[str] = (), connect: Sequence[str] = (), config_file: str | None = None
) -> zenoh.Config:
    """The router's Zenoh config: the file as given, the flags on top, router mode always.

    With neither a file nor --listen, it listens where zenohd does.
    """
    if not listen and not config_file:
        listen = [DEFAULT_LISTEN]
    return session_config(connect=connect, listen=listen, mode="router", config_file=config_file)


def describe(conf: zenoh.Config) -> str:
    """One line on what the router listens on and enforces, for the start-up log."""

    def get(key: str):
        try:
            return json.loads(conf.get_json(key))
        except zenoh.ZError:
            return None

    listen = get("listen/endpoints")
    if isinstance(listen, dict):  # mode-dependent default: {"router": [...], "peer": [...]}
        listen = listen.get("router")
    tls = get("transport/link/tls") or {}
    usrpwd = get("transport/auth/usrpwd") or {}
    acl = get("access_control") or {}
    return (
        f"listen={listen} connect={get('connect/endpoints') or []} "
        f"mtls={bool(tls.get('enable_mtls'))} "
        f"user/password={'on' if usrpwd.get('dictionary_file') else 'off'} "
        f"access_control={'on, default ' + acl.get('default_permission', 'deny') if acl.get('enabled') else 'off'}"
    )


def log_transport_event(session: zenoh.Session, event: zenoh.TransportEvent) -> None:
    """Log a peer coming or going, with its address and the identity it authenticated as."""
    t = event.transport
    if event.kind == zenoh.SampleKind.PUT:
        links = [link for link in session.info.links() if str(link.zid) == str(t.zid)]
        where = ", ".join(f"{link.dst} as {link.auth_identifier or 'anonymous'}" for link in links) or "?"
        log.info("connected: %s %s from %s", t.whatami, t.zid, where)
    else:
        log.info("disconnected: %s %s", t.whatami, t.zid)


def main(conf: zenoh.Config, stop: threading.Event) -> None:
    """Run the router until ``stop`` is set."""
    log.info("starting: %s", describe(conf))
    with zenoh.open(conf) as session:
        listener = session.info.declare_transport_events_listener(
            lambda event: log_transport_event(session, event), history=True
        )
        log.info("router %s ready", session.info.zid())
        wait_until_stopped(stop)
        listener.undeclare()
        log.info("stopping")


def parser() -> argparse.ArgumentParser:
    p = CommandParser(
        prog="l2r router",
        description=(
            "Run a Zenoh router (a stand-in for zenohd). Daemons on other hosts connect to it as "
            "clients; TLS, user/password and access control come from the Zenoh config file. "
            "See docs/deploy.md and deploy/zenoh/router.json5."
        ),
    )
    p.add_argument("-c", "--zenoh-config", metavar="FILE",
                   help="Zenoh JSON5 config, as zenohd -c takes it; the flags below apply on top")
    p.add_argument("-l", "--listen", action="append", default=[], metavar="ENDPOINT",
                   help=f"endpoint to listen on, e.g. tls/0.0.0.0:7447 (repeatable; default without a "
                        f"config file: {DEFAULT_LISTEN})")
    p.add_argument("-e", "--connect", action="append", default=[], metavar="ENDPOINT",
                   help="another router to connect to, for a mesh of routers (repeatable)")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                   help="log level (default: %(default)s)")
    return p


def cli(argv: list[str]) -> int:
    args = parser().parse_args(argv)
    configure_logging(args.log_level)
    try:
        conf = router_config(args.listen, args.connect, args.zenoh_config)
    except (zenoh.ZError, OSError) as e:
        log.error("bad Zenoh config %s: %s", args.zenoh_config, e)
        return 2
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        main(conf, stop)
    except zenoh.ZError as e:
        log.error("cannot start the router: %s", e)
        return 1
    return 0
