"""The `l2r` command: one entry point whose subcommands live in their own modules."""

import importlib
import sys

from l2r import __version__
from l2r.config import EXIT_USAGE

# subcommand -> (module exposing `cli(argv) -> int`, one-line help)
SUBCOMMANDS = {
    "up": ("l2r.up", "run a whole training job on this host (replay, learner, actors)"),
    "eval": ("l2r.evaluate", "run deterministic episodes of a checkpoint and print their scores"),
    "photo": ("l2r.photo.cli", "tune a photo's finishing towards a goal image; compare tuners on held-out photos"),
    "view": ("l2r.view", "replay MCAP episode logs into Rerun, or watch a run live"),
    "router": ("l2r.router", "run a Zenoh router (a stand-in for zenohd)"),
    "validate": ("l2r.sim.validate", "compare the MuJoCo body with OpenSim reference figures"),
}


def usage() -> str:
    lines = ["usage: l2r COMMAND [ARGS...]", "", "commands:"]
    lines += [f"  {name:<10} {help_}" for name, (_, help_) in SUBCOMMANDS.items()]
    lines += ["", "`l2r COMMAND --help` explains each one; `l2r --version` prints the version."]
    return "\n".join(lines)


def cli(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ("-h", "--help"):
        print(usage())
        return 0
    if argv[0] == "--version":
        print(f"l2r {__version__}")
        return 0
    name, rest = argv[0], argv[1:]
    if name not in SUBCOMMANDS:
        print(f"l2r: unknown command {name!r} (see l2r --help)", file=sys.stderr)
        return EXIT_USAGE
    module = importlib.import_module(SUBCOMMANDS[name][0])
    return module.cli(rest) or 0


if __name__ == "__main__":
    sys.exit(cli())
