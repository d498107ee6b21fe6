"""One typed config <-> one command line: the parser, the parse and the argv all come from a table.

A service describes its flags once, as a `CommandLine` over its frozen config dataclass: each
`Flag` names the flag, its help and its check (a `dovesei.shared.validate` helper), keyed by the
dotted path of the config field it sets (``"sim.vehicle_id"`` reaches into a nested config).
Types and defaults come from the dataclass itself, never from the table, so a default has one
owner. From that table:

    CommandLine.add_to(parser)     argparse flags (help shows the dataclass defaults)
    CommandLine.from_args(args)    the parsed namespace -> the config (cross-field checks included)
    CommandLine.to_argv(config)    the config -> the flags that parse back to an equal config

`to_argv` emits only fields that differ from the defaults and proves the round trip before it
returns: a config that a command line cannot express (a changed field without a flag, two flags
of one exclusive group) is a `ConfigError`, never a silently different child process.

Why a table beside the dataclass and not field metadata: the nested configs (SimConfig,
SegmenterConfig, ControllerConfig) belong to each service's core, which knows nothing of flags;
the command line is the service edge's concern. The table is checked against the dataclass
when it is built (a path that names no field fails at import).

Bad values never get far: argparse calls the flag's converter, which raises one line naming the
flag and what it accepts (``argument --speed: must be a finite number > 0, got 0.0``).
`build_parser` adds the Zenoh connection flags as the one shared group of
`dovesei.shared.zconfig`, and `ProcessOptions`, the two flags every service has besides its config
(log level, stats file); `start` is the common head of every service's `main`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import types
import typing
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

import zenoh

from dovesei.shared import validate
from dovesei.shared.errors import ConfigError
from dovesei.shared.zconfig import add_zenoh_args, zenoh_config_from_args

C = TypeVar("C")
Check = Callable[[str, Any], Any]  # validate-style: check(what, value) raises ConfigError naming `what`

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")
LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


@dataclass(frozen=True)
class Flag:
    """How one config field appears on the command line.

    `check(what, value)` validates the converted value (its return value is ignored, so an int
    stays an int under `validate.in_range`). `choices` applies to each item of a tuple field.
    `parse`/`render` replace the built-in conversion for types it does not know (they must be
    inverses). A bool field is a switch: the flag sets True, or False with `negate`; `off` names a
    second flag that sets False (``--lockstep``/``--realtime``). Flags sharing a `group` are
    mutually exclusive.
    """

    name: str
    help: str = ""
    check: Check | None = None
    choices: Sequence[str] | None = None
    parse: Callable[[str], Any] | None = None
    render: Callable[[Any], str] | None = None
    metavar: str | None = None
    off: str | None = None
    off_help: str = ""
    negate: bool = False
    group: str | None = None

    def __post_init__(self) -> None:
        for name in (self.name, self.off):
            if name is not None and not (name.startswith("--") and len(name) > 2):
                raise ConfigError(f"flag {name!r} must look like --name")
        if (self.parse is None) != (self.render is None):
            raise ConfigError(f"{self.name}: parse and render come together (they are inverses)")


@dataclass(frozen=True)
class _Entry:
    path: str  # dotted field path inside the config
    flag: Flag
    kind: Any  # the field's type with Optional removed
    optional: bool  # None is an allowed value (the default, usually)
    default: Any
    dest: str


def _unwrap_optional(tp: Any) -> tuple[Any, bool]:
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(args) == 1 and len(args) < len(typing.get_args(tp)):
            return args[0], True
    return tp, False


def _field_type(cls: type, path: str) -> Any:
    """The annotated type of `path` (a.b.c) starting at dataclass `cls`."""
    tp: Any = cls
    for part in path.split("."):
        if not dataclasses.is_dataclass(tp):
            raise ConfigError(f"config path {path!r}: {part!r} is inside a non-dataclass")
        names = {f.name for f in dataclasses.fields(tp)}
        if part not in names:
            raise ConfigError(f"config path {path!r}: {tp.__name__} has no field {part!r}")
        tp = typing.get_type_hints(tp)[part]
    return tp


def get_path(obj: Any, path: str) -> Any:
    for part in path.split("."):
        obj = getattr(obj, part)
    return obj


REQUIRED = object()  # the "default" of a dataclass field without one: its flag is required


def _field_default(cls: type, path: str) -> Any:
    """The default of `path`: the top field's default (or factory), then attributes below it."""
    head, _, rest = path.partition(".")
    f = next(f for f in dataclasses.fields(cls) if f.name == head)
    if f.default is not dataclasses.MISSING:
        value = f.default
    elif f.default_factory is not dataclasses.MISSING:
        value = f.default_factory()
    else:
        return REQUIRED
    return get_path(value, rest) if rest else value


def _split(values: Mapping[str, Any]) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
    """{"a": 1, "b.c": 2} -> ({"a": 1}, {"b": {"c": 2}}): own fields, and values for nested ones."""
    own: dict[str, Any] = {}
    nested: dict[str, dict[str, Any]] = {}
    for p, v in values.items():
        head, dot, rest = p.partition(".")
        if dot:
            nested.setdefault(head, {})[rest] = v
        else:
            own[p] = v
    return own, nested


def _build(cls: type, values: Mapping[str, Any]) -> Any:
    """`cls(...)` with the dotted paths of `values` set; nested configs start from their defaults."""
    own, nested = _split(values)
    for head, sub in nested.items():
        own[head] = _with_values(_field_default(cls, head), sub)
    return cls(**own)


def _with_values(obj: Any, values: Mapping[str, Any]) -> Any:
    """`obj` with the dotted paths of `values` replaced (nested dataclasses rebuilt bottom-up)."""
    own, nested = _split(values)
    for head, sub in nested.items():
        own[head] = _with_values(getattr(obj, head), sub)
    return dataclasses.replace(obj, **own) if own else obj


class OneLineParser(argparse.ArgumentParser):
    """argparse whose usage errors are ONE line naming the flag and value, plus a pointer to --help.

    argparse's own error prints the whole usage (14 lines for `dovesei up`) above the message, which
    buries the one thing the user got wrong. `--help` still prints everything; the exit code stays 2.
    Every parser of the project (services and `dovesei` subcommands) is one of these.
    """

    def error(self, message: str) -> typing.NoReturn:
        text = " ".join(message.split())  # argparse's messages may hold newlines (long choice lists)
        self.exit(2, f"{self.prog}: error: {text} (see {self.prog} --help)\n")


class _RaisingParser(argparse.ArgumentParser):
    """A parser whose errors are ConfigErrors (for `parse` and the round-trip proof), not exits."""

    def error(self, message: str) -> typing.NoReturn:
        raise ConfigError(message)


class CommandLine(Generic[C]):
    """The flags of one config dataclass `cls`; see the module docstring.

    `derive(given)` may add values for fields whose default depends on other flags (it receives
    the paths given on the command line and returns extra path -> value pairs). `prog` and
    `description` name the service for `build_parser` and `start`.
    """

    def __init__(self, cls: type[C], flags: Mapping[str, Flag], *,
                 derive: Callable[[Mapping[str, Any]], Mapping[str, Any]] | None = None,
                 prog: str | None = None, description: str | None = None) -> None:
        if not dataclasses.is_dataclass(cls):
            raise ConfigError(f"{cls!r} is not a dataclass")
        self.cls, self.derive, self.prog, self.description = cls, derive, prog, description
        entries, seen = [], set()
        for path, flag in flags.items():
            kind, optional = _unwrap_optional(_field_type(cls, path))
            for name in (flag.name, flag.off):
                if name in seen:
                    raise ConfigError(f"flag {name} declared twice")
                if name is not None:
                    seen.add(name)
            default = _field_default(cls, path)
            if default is REQUIRED and (kind is bool or "." in path):
                raise ConfigError(f"{flag.name}: only a top-level, non-switch field may lack a default")
            if kind is bool and default is True and not (flag.negate or flag.off):
                raise ConfigError(f"{flag.name}: a switch for a field that defaults to True needs negate or off")
            dest = f"{cls.__name__}.{path}"
            entries.append(_Entry(path, flag, kind, optional, default, dest))
        self.entries: tuple[_Entry, ...] = tuple(entries)

    # ------------------------------------------------------------------ parser

    def flag_names(self) -> tuple[str, ...]:
        """Every flag this command line accepts (the public list argparse does not keep)."""
        return tuple(n for e in self.entries for n in (e.flag.name, e.flag.off) if n is not None)

    def add_to(self, parser: argparse.ArgumentParser) -> None:
        groups: dict[str, Any] = {}

        def target(e: _Entry) -> Any:
            if e.flag.off is not None or e.flag.group is not None:
                key = e.flag.group or e.path
                if key not in groups:
                    groups[key] = parser.add_mutually_exclusive_group()
                return groups[key]
            return parser

        for e in self.entries:
            f, where = e.flag, target(e)
            if e.kind is bool:
                on_value = not f.negate
                where.add_argument(f.name, dest=e.dest, action="store_const", const=on_value,
                                   default=argparse.SUPPRESS, help=self._help(e, on_value))
                if f.off is not None:
                    where.add_argument(f.off, dest=e.dest, action="store_const", const=not on_value,
                                       default=argparse.SUPPRESS, help=self._help(e, not on_value, f.off_help))
                continue
            metavar = f.metavar or ("{" + ",".join(map(str, f.choices)) + "}" if f.choices else f.name[2:].upper().replace("-", "_"))
            where.add_argument(f.name, dest=e.dest, default=argparse.SUPPRESS, metavar=metavar,
                               type=self._converter(e), help=self._help(e), required=e.default is REQUIRED)

    def _help(self, e: _Entry, switch_value: bool | None = None, text: str | None = None) -> str:
        text = e.flag.help if text is None else text
        if switch_value is not None:
            return f"{text} (default)" if switch_value == e.default and text else text
        if e.default is None or e.default is REQUIRED or e.default == ():
            return text
        shown = self._render(e, e.default)
        return f"{text} (default: {shown})" if text else f"default: {shown}"

    def _converter(self, e: _Entry) -> Callable[[str], Any]:
        def convert(text: str) -> Any:
            try:
                return self._convert(e, text)
            except ConfigError as exc:
                # argparse prefixes "argument --flag:"; drop the flag from our own message.
                msg = str(exc)
                msg = msg[len(e.flag.name):].lstrip(" :") if msg.startswith(e.flag.name) else msg
                raise argparse.ArgumentTypeError(msg) from None
        convert.__name__ = e.flag.name  # argparse names the converter in some messages
        return convert

    def _convert(self, e: _Entry, text: str) -> Any:
        f = e.flag
        if f.parse is not None:
            try:
                value = f.parse(text)
            except ConfigError:
                raise  # already names the flag
            except (ValueError, TypeError) as exc:
                raise ConfigError(f"{f.name} {text!r}: {exc}") from None
        else:
            value = _parse_as(e.kind, f.name, text)
        if f.choices is not None:
            for item in (value if isinstance(value, tuple) else (value,)):
                validate.one_of(f.name, item, f.choices)
        if f.check is not None:
            f.check(f.name, value)
        return value

    def build_parser(self) -> argparse.ArgumentParser:
        """The whole parser of a service: its config flags, the process flags, then the Zenoh group.

        Prefixes are not expanded (`allow_abbrev=False`): `--vehicle` must never silently mean
        `--vehicle-id`.
        """
        parser = OneLineParser(prog=self.prog, description=self.description, allow_abbrev=False)
        self.add_to(parser)
        PROCESS.add_to(parser)
        add_zenoh_args(parser)
        return parser

    def start(self, argv: Sequence[str] | None) -> tuple[C, ProcessOptions, zenoh.Config]:
        """What every service's `main` does first: parse, set up logging, build the config and the
        Zenoh config. A bad flag or config exits 2 with one line naming it (`OneLineParser`)."""
        parser = self.build_parser()
        args = parser.parse_args(argv)
        process = PROCESS.from_args(args)
        logging.basicConfig(level=process.log_level, format=LOG_FORMAT)
        try:
            return self.from_args(args), process, zenoh_config_from_args(args)
        except ConfigError as exc:
            parser.error(str(exc))

    # ------------------------------------------------------------------ namespace -> config

    def given(self, args: argparse.Namespace) -> dict[str, Any]:
        """The config paths set on the command line, with their converted values."""
        ns = vars(args)
        return {e.path: ns[e.dest] for e in self.entries if e.dest in ns}

    def from_args(self, args: argparse.Namespace) -> C:
        """The config the parsed flags describe; a cross-field problem raises ConfigError."""
        values = self.given(args)
        if self.derive is not None:
            values = {**self.derive(values), **values}
        return _build(self.cls, values)

    def parse(self, argv: Sequence[str]) -> C:
        """Parse only this command line's flags; errors raise ConfigError instead of exiting."""
        parser = _RaisingParser(add_help=False, allow_abbrev=False)
        self.add_to(parser)
        return self.from_args(parser.parse_args(list(argv)))

    # ------------------------------------------------------------------ config -> argv

    def to_argv(self, config: C) -> list[str]:
        """Flags that parse to a config equal to `config` (only the fields that differ from the defaults)."""
        if not isinstance(config, self.cls):
            raise ConfigError(f"to_argv: expected a {self.cls.__name__}, got {type(config).__name__}")
        values = {e.path: v for e in self.entries if (v := get_path(config, e.path)) != e.default}
        if self.derive is not None:
            # Derived defaults (the controller's timing and loop follow its vehicle) replace the
            # dataclass's: a value equal to the derived one is left out, any other is spelled out.
            for path, derived in self.derive(values).items():
                if get_path(config, path) == derived:
                    values.pop(path, None)
                else:
                    values[path] = get_path(config, path)
        argv: list[str] = []
        used_groups: dict[str, str] = {}
        for e in self.entries:
            if e.path not in values:
                continue
            value, f = values[e.path], e.flag
            if f.group is not None:
                if f.group in used_groups:
                    raise ConfigError(f"{used_groups[f.group]} and {f.name} cannot both be given (set only one)")
                used_groups[f.group] = f.name
            if e.kind is bool:
                if value == (not f.negate):
                    argv.append(f.name)
                elif f.off is not None:
                    argv.append(f.off)
                else:
                    raise ConfigError(f"{e.path}={value!r} cannot be expressed with {f.name}")
                continue
            if value is None:
                raise ConfigError(f"{e.path}=None cannot be expressed with {f.name} (its default is {e.default!r})")
            text = self._render(e, value)
            # "--flag=-5" keeps a value that starts with '-' from reading as a flag.
            argv += [f"{f.name}={text}"] if text.startswith("-") else [f.name, text]
        back = self.parse(argv)
        if back != config:
            raise ConfigError(f"{self.cls.__name__} cannot be passed as flags: "
                              f"{', '.join(_differences(config, back)) or 'it does not round-trip'}")
        return argv

    def _render(self, e: _Entry, value: Any) -> str:
        if e.flag.render is not None:
            return e.flag.render(value)
        return _render_as(e.kind, value)


def _differences(want: Any, got: Any, prefix: str = "") -> list[str]:
    """Dotted paths where two configs differ (for the round-trip error)."""
    if dataclasses.is_dataclass(want) and type(want) is type(got):
        out: list[str] = []
        for f in dataclasses.fields(want):
            if f.compare:
                out += _differences(getattr(want, f.name), getattr(got, f.name), f"{prefix}{f.name}.")
        return out
    return [] if want == got else [f"{prefix.rstrip('.')}={want!r} has no flag"]


# ---------------------------------------------------------------------- built-in conversions


def _parse_scalar(kind: Any, flag: str, text: str) -> Any:
    if kind is str:
        return text
    if kind is Path:
        if not text:
            raise ConfigError(f"{flag}: expected a path, got an empty string")
        return Path(text)
    if kind is int:
        try:
            return int(text)
        except ValueError:
            raise ConfigError(f"{flag} {text!r}: not an integer") from None
    if kind is float:
        try:
            value = float(text)
        except ValueError:
            raise ConfigError(f"{flag} {text!r}: not a number") from None
        return validate.finite(flag, value)
    raise ConfigError(f"{flag}: no conversion for {kind!r}; give the Flag parse and render")


def _parse_as(kind: Any, flag: str, text: str) -> Any:
    if typing.get_origin(kind) is tuple:
        args = typing.get_args(kind)
        items = [s.strip() for s in text.split(",")] if text.strip() else []
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_parse_scalar(args[0], flag, s) for s in items)
        if len(items) != len(args):
            raise ConfigError(f"{flag} {text!r}: expected {len(args)} comma-separated values")
        return tuple(_parse_scalar(a, flag, s) for a, s in zip(args, items))
    return _parse_scalar(kind, flag, text)


def _render_scalar(value: Any) -> str:
    if isinstance(value, float):
        return repr(value)  # repr round-trips every float exactly
    return str(value)


def _render_as(kind: Any, value: Any) -> str:
    if typing.get_origin(kind) is tuple:
        return ",".join(_render_scalar(v) for v in value)
    return _render_scalar(value)


# ---------------------------------------------------------------------- checks for the table


def integer_at_least(lo: int) -> Check:
    """A check for integers >= lo (`validate` covers floats)."""
    def check(what: str, value: Any) -> None:
        if isinstance(value, bool) or not isinstance(value, int) or value < lo:
            raise ConfigError(f"{what} must be an integer >= {lo}, got {value!r}")
    return check


def integer_in(lo: int, hi: int) -> Check:
    def check(what: str, value: Any) -> None:
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise ConfigError(f"{what} must be an integer in {lo}..{hi}, got {value!r}")
    return check


def in_range(lo: float, hi: float) -> Check:
    return lambda what, value: validate.in_range(what, value, lo, hi)


def non_blank(what: str, value: Any) -> None:
    if not isinstance(value, str) or not value.strip():
        raise ConfigError(f"{what} must not be empty")


def json_or_file(what: str, text: str) -> Any:
    """Inline JSON (text starting with '{' or '[') or the JSON in the file named by `text`."""
    if text.lstrip().startswith(("{", "[")):
        source, where = text, "inline JSON"
    else:
        try:
            source, where = Path(text).read_text(encoding="utf-8"), f"file {text!r}"
        except OSError as exc:
            raise ConfigError(f"{what} {text!r}: cannot read the file ({exc.strerror or exc})") from None
    try:
        return json.loads(source)
    except ValueError as exc:
        raise ConfigError(f"{what}: {where} is not valid JSON ({exc})") from None


# ---------------------------------------------------------------------- process options


@dataclass(frozen=True)
class ProcessOptions:
    """The flags every service has besides its config: how it logs and where its counters go."""

    log_level: str = "INFO"
    stats_out: Path | None = None  # JSON counters written when the service ends


PROCESS = CommandLine(ProcessOptions, {
    "log_level": Flag("--log-level", "logging threshold", choices=LOG_LEVELS),
    "stats_out": Flag("--stats-out", "write the run's counters as JSON when it ends", metavar="FILE"),
})
