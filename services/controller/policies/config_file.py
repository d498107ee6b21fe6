"""A policy's constants from a user's TOML file (`--policy-config FILE`), and the defaults file.

    FILE (TOML: one `name = value` per constant, any subset) --load_policy_config(policy, file, timing)
        --> the timing preset's config with those values replaced, validated by the config itself

Every value is checked before any process starts: an unknown name, a value of the wrong kind, or
one the config refuses is ONE line naming the file and the key. Not in a file: the timing preset's
fields (chosen with `--timing`) and the mission's hand-over altitude (`--handover-alt-m`, handed
to the policy by the controller), so a file can never disagree with the controller's own settings.
`defaults_toml(policy)` writes every settable constant with its default (`dovesei policy-config`).
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any

from dovesei.controller.policies.registry import POLICIES
from dovesei.shared.errors import ConfigError

# Fields a file may not set, and the flag that owns each.
_OWNED_ELSEWHERE = {"timing_name": "--timing", "timer_scale": "--timing", "decision_period_s": "--timing",
                    "handover_alt_m": "--handover-alt-m"}


def _config_kind(policy: str) -> tuple[type, typing.Callable[[str], Any]]:
    try:
        found = POLICIES[policy]
    except KeyError:
        raise ConfigError(f"policy {policy!r} has no configuration file; choose one of {', '.join(POLICIES)}") from None
    return found.config_type, found.preset


def settable_fields(policy: str) -> dict[str, Any]:
    """Name -> type hint of every constant a file may set for `policy`."""
    kind, _ = _config_kind(policy)
    hints = typing.get_type_hints(kind)
    return {f.name: hints[f.name] for f in dataclasses.fields(kind) if f.name not in _OWNED_ELSEWHERE}


def _checked_value(where: str, hint: Any, value: Any) -> Any:
    """`value` as the field's type, or a ConfigError naming `where` and what was expected."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    optional = origin in (typing.Union, types.UnionType) and type(None) in args
    if optional:
        if value is None:  # a recording's "unset" (TOML has no null: a file leaves the key out)
            return None
        hint = next(a for a in args if a is not type(None))
        origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{where} must be true or false, got {value!r}")
    if hint is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise ConfigError(f"{where} must be an integer, got {value!r}")
    if hint is float:
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value):
            return float(value)
        raise ConfigError(f"{where} must be a finite number, got {value!r}")
    if hint is str:
        if isinstance(value, str):
            return value
        raise ConfigError(f"{where} must be a string, got {value!r}")
    if origin is tuple:
        if not isinstance(value, (list, tuple)):  # a file's array, or a spec's tuple
            raise ConfigError(f"{where} must be an array of numbers, got {value!r}")
        return tuple(_checked_value(f"{where}[{i}]", args[0], v) for i, v in enumerate(value))
    raise ConfigError(f"{where}: cannot be set from a file")  # a field type this loader does not know


def load_policy_config(policy: str, path: str | Path, timing: str) -> Any:
    """The config `policy` flies with: the `timing` preset with the file's values, validated."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"--policy-config {str(path)!r}: cannot read it ({exc.strerror})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"--policy-config {str(path)!r}: not TOML ({exc})") from None
    return config_from_values(policy, doc, timing, f"--policy-config {path.name}")


def config_from_values(policy: str, doc: dict[str, Any], timing: str, what: str = "policy config") -> Any:
    """The `timing` preset's config with `doc`'s values (a file's, or a recording's), each checked;
    a ConfigError naming `what` and the key otherwise."""
    _, preset = _config_kind(policy)
    fields = settable_fields(policy)
    values: dict[str, Any] = {}
    for key, value in doc.items():
        where = f"{what}: {key}"
        if key in _OWNED_ELSEWHERE:
            raise ConfigError(f"{where} is set with {_OWNED_ELSEWHERE[key]}, not in a policy file")
        if key not in fields:
            raise ConfigError(f"{where} is not a constant of the {policy} policy (see `dovesei policy-config "
                              f"--defaults {policy}`)")
        values[key] = _checked_value(where, fields[key], value)
    try:
        return preset(timing).replace(**values)
    except ConfigError as exc:  # the config's own check: a value out of range, two that disagree
        raise ConfigError(f"{what}: {exc}") from None


def preset_config(policy: str, timing: str) -> Any:
    """The config `policy` flies with under `timing` when no file is given."""
    return _config_kind(policy)[1](timing)


def policy_values(policy: str, config: Any) -> dict[str, Any]:
    """The settable constants of a config as plain values (for reports and recordings)."""
    return {name: (list(v) if isinstance(v := getattr(config, name), tuple) else v) for name in settable_fields(policy)}


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(value)


def defaults_toml(policy: str, timing: str = "real") -> str:
    """Every constant a file may set for `policy`, with the `timing` preset's value, as TOML."""
    _, preset = _config_kind(policy)
    config = preset(timing)
    lines = [f"# {policy} policy constants (defaults under --timing {timing}); keep the ones you change.",
             "# Set the timing with --timing and the hand-over altitude with --handover-alt-m, not here."]
    for name in settable_fields(policy):
        value = getattr(config, name)
        lines.append(f"# {name} = (unset: the policy's own choice)" if value is None else
                     f"{name} = {_toml_value(value)}")
    return "\n".join(lines) + "\n"
