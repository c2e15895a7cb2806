"""Typed settings of l2r's commands, read from flags, a TOML file and the environment.

A command describes its settings once, as a `Settings` model whose fields carry their help
(`setting`). Its flags come from that model (`settings_parser`), and `load` takes each field's
value from the first of these that has one:

    --flag VALUE  >  --config FILE.toml  >  L2R_<FLAG> environment variable  >  the default

Keys in the file are the long flag names (``batch-size = 128``); a variable is the flag's
name in capitals (``L2R_BATCH_SIZE=128``; a list is comma-separated). A field may also name a
variable of another tool, read below its L2R_ one (l2r-learner's --world-size reads torchrun's
``$WORLD_SIZE``). Every value is checked against its field's type and limits wherever it came
from, and one that does not fit is a `UsageError` saying where it came from, which key, and
what it should be.

Exit codes, the same in every command (`run_command`):
    0  done
    1  failure at run time, which may pass: a crash, a Zenoh session that cannot open (a port
       in use)
    2  bad usage: an unknown flag or key, a value of the wrong type or out of range, a file
       named that does not exist -- the command line, file or environment must change
    3  cannot start: the settings are valid, but this machine cannot serve them (too little
       memory for the capacity, no CUDA device, an unreadable checkpoint) -- the same command
       fails the same way until something changes, so a supervisor does not restart it
"""

from __future__ import annotations

import argparse
import os
import re
import sys
import tomllib
import types
import typing
from pathlib import Path
from typing import Annotated, Any, Callable, Mapping, Sequence, TypeVar

import zenoh
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, Strict, ValidationError

from l2r import __version__

EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_CANNOT_START = 3
ENV_PREFIX = "L2R_"


class UsageError(Exception):
    """Settings the command cannot take (exit code 2)."""


class StartupFailure(Exception):
    """Valid settings this machine cannot serve, which starting again would repeat (exit code 3)."""


def zenoh_error_text(error: zenoh.ZError) -> str:
    """Zenoh's message on one line, without the Rust source locations it appends."""
    return " ".join(re.sub(r" at /\S+:\d+\.?", "", str(error)).split())


def one_line(error: Exception) -> str:
    return " ".join(str(error).split())


def run_command(prog: str, body: Callable[[], int | None]) -> int:
    """Run a command; a usage error or a failure to start is one line on stderr and exit 2 or 3.
    One line even where a library's message has several: a supervisor reads the last as the reason."""
    try:
        return body() or 0
    except UsageError as e:
        print(f"{prog}: {one_line(e)} (see {prog} --help)", file=sys.stderr)
        return EXIT_USAGE
    except StartupFailure as e:
        print(f"{prog}: {one_line(e)}", file=sys.stderr)
        return EXIT_CANNOT_START
    except zenoh.ZError as e:  # opening the session: a port in use, an address that does not resolve
        print(f"{prog}: cannot open the Zenoh session: {zenoh_error_text(e)}", file=sys.stderr)
        return EXIT_FAILURE


class _LineFormatter(argparse.HelpFormatter):
    """Wraps description and epilog line by line, so examples stay on lines of their own."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        return "\n".join(super(_LineFormatter, self)._fill_text(line, width, indent) for line in text.splitlines())


class CommandParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line and exit 2, with ``--version``."""

    def __init__(self, *args, **kwargs):
        kwargs.setdefault("formatter_class", _LineFormatter)
        super().__init__(*args, **kwargs)
        self.add_argument("--version", action="version", version=f"%(prog)s {__version__}")

    def error(self, message: str) -> typing.NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: {message} (see {self.prog} --help)\n")


# -- settings models ----------------------------------------------------------------------------

class Settings(BaseModel):
    """Base of a command's settings: every field is a flag; unknown keys and loose types are errors."""

    # Strict: in a TOML file 1.5 is no integer and "64" no number. Values typed as text (flags,
    # variables) are converted from text instead (`_validated`).
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    def check(self) -> None:
        """Rules between fields, checked once every source is merged; raise UsageError."""


def setting(default: Any = None, help: str = "", *, group: str, metavar: str | None = None,
            positional: bool = False, variable: str | None = None, **limits) -> Any:
    """A field of a `Settings` model: its default, flag help, help group and limits (ge=, gt=,
    le=...); ``variable``: an environment variable of another tool that supplies the field when
    its L2R_<FLAG> variable does not.

    The help shows the default, unless it is None, False or empty (say then what happens in the help)."""
    extra = {"group": group, "metavar": metavar, "positional": positional, "variable": variable}
    return Field(default, description=help, json_schema_extra=extra, **limits)


S = TypeVar("S", bound=Settings)

FilePath = Annotated[Path, Strict(False)]
"""A path field: a string is a path, even in a strict model."""
ONE_OR_MANY = BeforeValidator(lambda v: [v] if isinstance(v, str) else v)
"""For a list field: one string is a list of one (``connect = "tcp/..."`` in a file)."""
METAVARS = {int: "N", float: "X", FilePath: "PATH"}


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def _kind(annotation: Any) -> Any:
    """The type a field holds, without ``| None`` (a union of several types stays what it is)."""
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        inner = [a for a in typing.get_args(annotation) if a is not type(None)]
        if len(inner) == 1:
            return inner[0]
    return annotation


def _is_list(annotation: Any) -> bool:
    return typing.get_origin(_kind(annotation)) is list


def settings_parser(model: type[Settings], prog: str, description: str, epilog: str | None = None) -> CommandParser:
    """The command line of ``model``: one flag per field, grouped as the fields say, each default
    shown once. Flags not given are absent from the parsed namespace, so `load` can tell them apart."""
    parser = CommandParser(prog=prog, description=description, epilog=epilog)
    parser.add_argument("--config", metavar="FILE.toml",
                        help="TOML file of settings, keys being the long flag names (e.g. batch-size = 128); "
                             f"flags win over it, and it wins over {ENV_PREFIX}<FLAG> environment variables")
    groups: dict[str, argparse._ArgumentGroup] = {}
    for name, info in model.model_fields.items():
        extra = info.json_schema_extra or {}
        if extra["group"] not in groups:
            groups[extra["group"]] = parser.add_argument_group(extra["group"])
        group = groups[extra["group"]]
        kind = _kind(info.annotation)
        help_ = info.description or ""
        if info.default is not None and info.default is not False and info.default != [] \
                and "(default" not in help_:
            help_ += f" (default: {info.default})"
        options: dict[str, Any] = {"default": argparse.SUPPRESS, "help": help_.replace("%", "%%")}
        if kind is bool:
            options["action"] = "store_true"
        elif _is_list(info.annotation):
            options["action"] = "append"
        if typing.get_origin(kind) is typing.Literal:
            options["metavar"] = "{" + ",".join(map(str, typing.get_args(kind))) + "}"
        elif kind in METAVARS:
            options["metavar"] = METAVARS[kind]
        if extra.get("metavar"):
            options["metavar"] = extra["metavar"]
        if extra.get("positional"):  # a list of operands, such as l2r view's files
            group.add_argument(name, nargs="*", **{k: v for k, v in options.items() if k != "action"})
        else:
            group.add_argument(_flag(name), dest=name, **options)
    return parser


def load(model: type[S], parser: argparse.ArgumentParser, argv: Sequence[str] | None = None,
         environ: Mapping[str, str] | None = None) -> S:
    """Settings from ``argv`` (parsed by ``parser``, made by `settings_parser`), the ``--config`` file
    and the environment, checked; raises UsageError naming the source and key of a bad value."""
    given = vars(parser.parse_args(argv))
    path = given.pop("config", None)
    environ = os.environ if environ is None else environ
    values: dict[str, Any] = {}
    for name, info in model.model_fields.items():
        variable = (info.json_schema_extra or {}).get("variable")
        if variable and variable in environ:
            values |= _validated(model, {name: environ[variable]}, f"${variable}", strict=False)
    values |= _validated(model, _environment(model, environ), "env", strict=False)
    if path:
        values |= _validated(model, _toml(model, path), f"--config {path}", strict=True)
    values |= _validated(model, given, "flag", strict=False)
    settings = model.model_validate(values)  # typed already: this only assembles them
    settings.check()
    return settings


def _environment(model: type[Settings], environ: Mapping[str, str]) -> dict[str, Any]:
    found = {}
    for name, info in model.model_fields.items():
        text = environ.get(ENV_PREFIX + name.upper())
        if text is not None:
            found[name] = [item for item in text.split(",") if item] if _is_list(info.annotation) else text
    return found


def _toml(model: type[Settings], path: str) -> dict[str, Any]:
    try:
        with open(path, "rb") as f:
            table = tomllib.load(f)
    except OSError as e:
        raise UsageError(f"--config {path}: {e.strerror}") from None
    except tomllib.TOMLDecodeError as e:
        raise UsageError(f"--config {path}: not TOML: {e}") from None
    values = {}
    for key, value in table.items():
        name = key.replace("-", "_")
        if name not in model.model_fields:
            raise UsageError(f"--config {path}: unknown key {key!r} (keys are the long flag names)")
        values[name] = value
    return values


def _validated(model: type[Settings], values: dict[str, Any], source: str, strict: bool) -> dict[str, Any]:
    """``values`` checked and converted to their fields' types (fields not in ``values`` keep
    their defaults, which are valid, so rules between fields wait for `Settings.check`)."""
    if not values:
        return {}
    try:
        checked = model.model_validate(values, strict=strict)
    except ValidationError as e:
        raise UsageError("; ".join(_describe(error, source) for error in e.errors())) from None
    return {name: getattr(checked, name) for name in values}


def _describe(error: Mapping[str, Any], source: str) -> str:
    """One pydantic error as "<where the value came from>: <what it should be>"."""
    name = str(error["loc"][0]) if error["loc"] else ""
    value = error["input"]
    if source == "env":
        where = f"${ENV_PREFIX}{name.upper()}={value!r}" if name else "environment"
    elif source.startswith("$"):  # a variable of another tool, such as $WORLD_SIZE
        where = f"{source}={value!r}"
    elif source == "flag":
        where = f"{_flag(name)} {value}" if name else "command line"
    else:
        where = f"{source}: {name.replace('_', '-')} = {value!r}" if name else source
    message = error["msg"]
    message = message.removeprefix("Value error, ").replace("Input should be", "should be")
    return f"{where}: {message}"
