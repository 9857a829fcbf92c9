"""Generic machinery for typed, frozen config dataclasses: TOML in, overrides, validation, TOML out.

Each component declares one frozen dataclass with a `validate()` method; this module turns dicts (from
TOML files and `section.field=value` command-line overrides) into those dataclasses, rejecting unknown
keys and wrong types with a ConfigError that names the field, the value and what is allowed.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import types
import typing
from collections.abc import Iterable
from pathlib import Path
from typing import Any, TypeVar

import tomli_w
import tomllib

from .errors import ConfigError

T = TypeVar("T")


def _type_name(tp: Any) -> str:
    return getattr(tp, "__name__", str(tp))


def _coerce(value: Any, tp: Any, field: str) -> Any:
    """Convert a TOML/override value to the declared field type, or raise ConfigError."""
    origin = typing.get_origin(tp)
    if origin is typing.Literal:
        allowed = typing.get_args(tp)
        if value not in allowed:
            raise ConfigError(field, value, f"must be one of {', '.join(repr(a) for a in allowed)}")
        return value
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        if value is None:
            return None
        return _coerce(value, args[0], field)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(field, value, f"must be a list of {_type_name(typing.get_args(tp)[0])}")
        args = typing.get_args(tp)
        item_tp = args[0]
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, item_tp, f"{field}[{i}]") for i, v in enumerate(value))
        if len(args) != len(value):
            raise ConfigError(field, value, f"must be a list of exactly {len(args)} values")
        return tuple(_coerce(v, a, f"{field}[{i}]") for i, (v, a) in enumerate(zip(value, args, strict=True)))
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(field, value, "must be true or false")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(field, value, "must be an integer")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(field, value, "must be a number")
        if not math.isfinite(value):
            raise ConfigError(field, value, "must be a finite number")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(field, value, "must be a string")
        return value
    if dataclasses.is_dataclass(tp):
        if not isinstance(value, dict):
            raise ConfigError(field, value, f"must be a table of {tp.__name__} fields")
        return from_dict(tp, value, prefix=field)
    raise TypeError(f"unsupported config type {tp!r} for field {field}")


def unknown_field_hint(key: str, fields: Iterable[str], prefix: str) -> str:
    """"unknown field; did you mean sim.hand?" for a near miss, else the section's fields."""
    names = sorted(fields)
    close = difflib.get_close_matches(key, names, n=2, cutoff=0.6)
    if close:
        return "unknown field; did you mean " + " or ".join(f"{prefix}.{c}" if prefix else c for c in close) + "?"
    where = f"[{prefix}]" if prefix else "the top level"
    return f"unknown field; {where} has: {', '.join(names)}"


def from_dict(cls: type[T], data: dict[str, Any], prefix: str = "") -> T:
    """Build config dataclass `cls` from a dict; missing keys take defaults, unknown keys are errors."""
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    kwargs: dict[str, Any] = {}
    for key, value in data.items():
        name = f"{prefix}.{key}" if prefix else key
        if key not in fields:
            raise ConfigError(name, value, unknown_field_hint(key, fields, prefix))
        kwargs[key] = _coerce(value, hints[key], name)
    try:
        obj = cls(**kwargs)
    except ConfigError as err:
        if prefix and not err.field.startswith(prefix):
            raise ConfigError(f"{prefix}.{err.field}", err.value, err.allowed) from None
        raise
    return obj


def to_dict(cfg: Any) -> dict[str, Any]:
    """Plain dict of a config dataclass (tuples become lists, None values are dropped for TOML)."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if value is None:
            continue
        if dataclasses.is_dataclass(value):
            value = to_dict(value)
        elif isinstance(value, tuple):
            value = list(value)
        out[f.name] = value
    return out


def parse_override(text: str) -> tuple[list[str], Any]:
    """Parse `section.field=value`; the value is read as TOML (numbers, booleans, lists), else a string."""
    if "=" not in text:
        raise ConfigError(text, text, "an override must look like section.field=value, e.g. reward.push_weight=0.5")
    key, raw = text.split("=", 1)
    key = key.strip()
    raw = raw.strip()
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw
    return key.split("."), value


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """Return a copy of `data` with each `a.b.c=value` override set."""
    merged = _deep_copy(data)
    for text in overrides:
        path, value = parse_override(text)
        node = merged
        for part in path[:-1]:
            child = node.setdefault(part, {})
            if not isinstance(child, dict):
                raise ConfigError(".".join(path), value, f"'{part}' is a value, not a section")
            node = child
        node[path[-1]] = value
    return merged


def drop_retired(data: dict[str, Any], retired: dict[str, Any]) -> dict[str, Any]:
    """A copy of `data` without the removed fields a saved config may still name (`retired`: `section.field`
    -> the value that kept the removed code path off): at that value a field is dropped, at any other it is
    a ConfigError saying the option is gone."""
    out = _deep_copy(data)
    for key, kept in retired.items():
        *sections, name = key.split(".")
        table: Any = out
        for section in sections:
            table = table.get(section) if isinstance(table, dict) else None
        if not isinstance(table, dict) or name not in table:
            continue
        value = table.pop(name)
        if value != kept:
            raise ConfigError(key, value, f"this option was removed; only its old default {kept!r} is accepted "
                              "(the behaviour that was kept): delete the line")
    return out


def _deep_copy(data: dict[str, Any]) -> dict[str, Any]:
    return {k: _deep_copy(v) if isinstance(v, dict) else v for k, v in data.items()}


def read_toml(path: str | Path) -> dict[str, Any]:
    """The TOML file as a dict; anything that keeps it from being read is one ConfigError naming the file."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise ConfigError("config file", str(path), "the file does not exist") from None
    except IsADirectoryError:
        raise ConfigError("config file", str(path), "is a directory, not a TOML file") from None
    except UnicodeDecodeError as err:  # tomllib decodes UTF-8 itself: a binary file ends up here
        raise ConfigError("config file", str(path), f"not valid TOML (not UTF-8 text: byte "
                          f"0x{err.object[err.start]:02x} at offset {err.start})") from None
    except tomllib.TOMLDecodeError as err:
        raise ConfigError("config file", str(path), f"not valid TOML ({err})") from None
    except OSError as err:  # no permission, an I/O error
        raise ConfigError("config file", str(path), f"cannot be read ({err.strerror or err})") from None


MAX_BASE_DEPTH = 8


def read_recipe(path: str | Path) -> dict[str, Any]:
    """A config file with its `base` chain merged in: a top-level `base = "other.toml"` (relative to the
    file) is read first and this file's values are laid over it, section by section, so a recipe states
    only what differs from the one it builds on."""
    return _read_with_bases(Path(path), [])


def _read_with_bases(path: Path, chain: list[Path]) -> dict[str, Any]:
    resolved = path.resolve()
    if resolved in chain:
        raise ConfigError("base", str(path), "the recipes name each other as base in a loop: "
                          + " -> ".join(p.name for p in (*chain, resolved)))
    if len(chain) >= MAX_BASE_DEPTH:
        raise ConfigError("base", str(path), f"more than {MAX_BASE_DEPTH} recipes deep")
    data = read_toml(path)
    base = data.pop("base", None)
    if base is None:
        return data
    if not isinstance(base, str) or not base:
        raise ConfigError("base", repr(base), f"in {path}: must be the path of another recipe, e.g. "
                          "base = \"clutter.toml\"")
    below = _read_with_bases(path.parent / base, [*chain, resolved])
    return merge_dicts(below, data)


def merge_dicts(below: dict[str, Any], above: dict[str, Any]) -> dict[str, Any]:
    """`above` laid over `below`: sections merge key by key, any other value of `above` replaces."""
    out = _deep_copy(below)
    for key, value in above.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge_dicts(out[key], value)
        else:
            out[key] = _deep_copy(value) if isinstance(value, dict) else value
    return out


def dumps_toml(cfg: Any) -> str:
    return tomli_w.dumps(to_dict(cfg))


def write_toml(cfg: Any, path: str | Path) -> Path:
    """Write the resolved config; written to a temporary file and renamed so a crash leaves no half file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(dumps_toml(cfg))
    tmp.replace(path)
    return path


def require(cond: bool, field: str, value: object, allowed: str) -> None:
    """Validation helper used in every config's __post_init__."""
    if not cond:
        raise ConfigError(field, value, allowed)
