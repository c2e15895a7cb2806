"""Zenoh session configuration and the command-line shape every l2r daemon shares."""

from __future__ import annotations

import argparse
import json
import logging
import threading
import time
import tomllib
from collections import Counter
from pathlib import Path
from typing import Sequence

import zenoh

from l2r.protocol.keys import check_name
from l2r.protocol.messages import ProtocolError

LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


def session_config(
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    mode: str | None = "peer",
    config_file: str | Path | None = None,
) -> zenoh.Config:
    """A Zenoh config: ``config_file`` (Zenoh's own JSON5) if given, with the arguments on top.

    Explicit endpoints turn multicast scouting off, so a process only talks to the
    endpoints it was given. ``mode=None`` keeps the file's mode.
    """
    conf = zenoh.Config.from_file(str(config_file)) if config_file else zenoh.Config()
    if mode:
        conf.insert_json5("mode", json.dumps(mode))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect or listen:
        conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


class DefaultsHelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Shows "(default: X)" after each flag's help, except where there is no default to show."""

    def _get_help_string(self, action: argparse.Action) -> str:
        if action.default is None or action.default is False or action.default is argparse.SUPPRESS \
                or action.default == []:
            return action.help or ""
        return super()._get_help_string(action)


def add_daemon_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the flags every daemon takes: run name, Zenoh endpoints and config, TOML config, logging."""
    g = parser.add_argument_group("run and network (common to all l2r daemons)")
    g.add_argument("--run", default="default", help="run name; keys are l2r/<run>/..., so runs never mix (default: %(default)s)")
    g.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)")
    g.add_argument("--mode", choices=("peer", "client", "router"), default=None,
                   help="Zenoh mode (default: the --zenoh-config file's, else peer)")
    g.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config file; the flags above apply on top")
    g.add_argument("--config", metavar="FILE.toml",
                   help="TOML file whose keys are long flag names (e.g. run = \"exp1\"); flags on the command line win")
    g.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"),
                   help="log level (default: %(default)s)")


def parse_daemon_args(parser: argparse.ArgumentParser, argv: Sequence[str] | None = None) -> argparse.Namespace:
    """Parse ``argv`` with values from ``--config FILE.toml`` as defaults; exits with a clear error on a bad file."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--config")
    known, _ = pre.parse_known_args(argv)
    if known.config:
        parser.set_defaults(**_toml_defaults(parser, known.config))
    args = parser.parse_args(argv)
    try:
        check_name(args.run)
    except ValueError as e:
        parser.error(str(e))
    return args


def _toml_defaults(parser: argparse.ArgumentParser, path: str) -> dict:
    try:
        with open(path, "rb") as f:
            table = tomllib.load(f)
    except (OSError, tomllib.TOMLDecodeError) as e:
        parser.error(f"cannot read --config {path}: {e}")
    dests = {a.dest for a in parser._actions}
    defaults = {}
    for key, value in table.items():
        dest = key.replace("-", "_")
        if dest not in dests or dest in ("help", "config"):
            parser.error(f"--config {path}: unknown key {key!r} (keys are the long flag names)")
        defaults[dest] = value
    return defaults


def config_from_args(args: argparse.Namespace) -> zenoh.Config:
    """The Zenoh config the common flags describe."""
    mode = args.mode or (None if args.zenoh_config else "peer")
    return session_config(args.connect, args.listen, mode=mode, config_file=args.zenoh_config)


def configure_logging(level: str = "INFO") -> None:
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO), format=LOG_FORMAT)


class Rejections:
    """Counts rejected messages by reason (``ProtocolError.reason``) and logs them without
    flooding the log: the first of each reason at once, then at most one line per reason every
    ``interval`` seconds, so one noisy reason never hides another."""

    def __init__(self, logger: logging.Logger, interval: float = 10.0):
        self._log = logger
        self._interval = interval
        self._lock = threading.Lock()
        self.by_reason: Counter[str] = Counter()
        self._last_line: dict[str, tuple[float, int]] = {}  # reason -> (time, count) of its last log line
        self.total = 0

    def add(self, error: ProtocolError, source: str = "") -> None:
        reason, now = error.reason, time.monotonic()
        with self._lock:
            self.total += 1
            self.by_reason[reason] += 1
            n = self.by_reason[reason]
            last = self._last_line.get(reason)
            if last is not None and now - last[0] < self._interval:
                return
            self._last_line[reason] = (now, n)
        self._log.warning("rejected message%s (%s: %d so far, %d since the last line): %s",
                          f" from {source}" if source else "", reason, n, n - last[1] if last else 1, error)

    def counters(self) -> dict[str, int]:
        """``rejected`` and ``rejected.<reason>`` for a daemon's stats."""
        with self._lock:
            return {"rejected": self.total, **{f"rejected.{r}": n for r, n in self.by_reason.items()}}


def wait_alive(session: zenoh.Session, key_expr: str, timeout: float = 10.0) -> list[str]:
    """Wait until a liveliness token matches ``key_expr``; return the matching keys ([] on timeout)."""
    deadline = time.monotonic() + timeout
    while True:
        found = [str(r.ok.key_expr) for r in session.liveliness().get(key_expr, timeout=1.0) if r.ok]
        if found or time.monotonic() >= deadline:
            return found
        time.sleep(0.05)
