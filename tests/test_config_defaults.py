"""configs/default.toml lists every config field with its declared default and a one-line comment.

Loading fills missing fields from the defaults, so `load_config(default.toml) == Config()` alone cannot notice a
field left out of the file; these tests read the file's text. A field whose declared default is None (unset) is
listed commented out (`# name = example`), since TOML has no null.
"""

import dataclasses
import re
from pathlib import Path
from typing import Any

import tomllib

from romannet.common.config import Config, load_config

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_TOML = ROOT / "configs" / "default.toml"
FILE = "configs/default.toml"

_SECTION = re.compile(r"\[(\w+)\]")
_ASSIGN = re.compile(r"(\w+)\s*=")
_UNSET = re.compile(r"#\s*(\w+)\s*=\s*\S")  # a commented-out assignment: a field unset by default
_INLINE_COMMENT = re.compile(r"\s#\s*\S")


@dataclasses.dataclass(frozen=True)
class Listed:
    """One field as the file lists it."""

    line: int
    unset: bool  # listed commented out
    described: bool  # a comment line above it or a comment after it


def _declared(f: dataclasses.Field) -> Any:
    return f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]


def declared_defaults(cls: type = Config, prefix: str = "") -> dict[str, Any]:
    """`section.field` -> declared default (None for an unset field), read from the dataclasses."""
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        default = _declared(f)
        if dataclasses.is_dataclass(default):
            out.update(declared_defaults(type(default), f"{prefix}{f.name}."))
        else:
            out[f"{prefix}{f.name}"] = default
    return out


def listed_fields(text: str) -> dict[str, Listed]:
    """`section.field` -> where and how the file lists it, read line by line (comments included)."""
    out: dict[str, Listed] = {}
    section, previous = "", ""
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        described = previous.startswith("#") and not _UNSET.match(previous)
        if m := _SECTION.match(line):
            section = f"{m[1]}."
        elif m := _ASSIGN.match(line):
            out[section + m[1]] = Listed(number, False, described or bool(_INLINE_COMMENT.search(line[m.end():])))
        elif m := _UNSET.match(line):
            out[section + m[1]] = Listed(number, True, described)
        previous = line
    return out


def _flat(table: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in table.items():
        out.update(_flat(value, f"{prefix}{key}.") if isinstance(value, dict) else {f"{prefix}{key}": value})
    return out


def _toml_value(value: Any) -> str:
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    return "true" if value is True else "false" if value is False else repr(value).replace("'", '"')


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    return isinstance(a, bool) == isinstance(b, bool) and a == b


def _missing(key: str, default: Any) -> str:
    section, _, name = key.rpartition(".")
    where = f"under [{section}]" if section else "at the top"
    if default is None:
        return (f"{FILE} lacks {key} (unset by default): add `# {name} = <example>` {where} with a comment "
                "line above it saying what unset means")
    return f"{FILE} lacks {key}: add `{name} = {_toml_value(default)}` {where} with a one-line comment above it"


def default_toml_problems(text: str) -> list[str]:
    """One actionable line per problem: a field missing, an unknown key, a value that is not the declared
    default, a key without a comment."""
    declared, listed, values = declared_defaults(), listed_fields(text), _flat(tomllib.loads(text))
    problems = [f"{FILE}: {key} is written as a dotted or quoted key: write `name = value` under its [section]"
                for key in values if key not in listed]
    for key, default in declared.items():
        at = listed.get(key)
        if at is None or at.unset != (default is None):
            problems.append(_missing(key, default))
        elif not at.described:
            problems.append(f"{FILE}:{at.line}: {key} has no comment: add a one-line `# ...` above it saying "
                            "what it is (units, valid range)")
        elif default is not None and not _same(values[key], default):
            problems.append(f"{FILE}:{at.line}: {key} = {_toml_value(values[key])}, but its declared default is "
                            f"{_toml_value(default)}: write that (or change the default in common/config*.py)")
    problems += [f"{FILE}:{at.line}: {key} is not a Config field: remove it, or declare it in common/config*.py"
                 for key, at in listed.items() if key not in declared]
    return problems


def test_default_toml_lists_every_field_with_its_default_and_a_comment():
    problems = default_toml_problems(DEFAULT_TOML.read_text())
    assert not problems, "\n".join(problems)


def test_default_toml_loads_to_the_defaults():
    assert load_config(DEFAULT_TOML) == Config()


def _edited(old: str, new: str) -> list[str]:
    text = DEFAULT_TOML.read_text()
    assert text.count(old) == 1, old
    return default_toml_problems(text.replace(old, new))


def test_each_kind_of_problem_is_one_line_naming_the_field():
    lr = re.search(r"\[learner\].*?\n(lr = [^\n]*\n)", DEFAULT_TOML.read_text(), re.S)
    assert lr is not None
    [missing] = _edited(lr[0], lr[0].replace(lr[1], ""))
    assert "lacks learner.lr" in missing and "`lr = 0.0001` under [learner]" in missing
    [unset] = _edited("# finger_force_n = ", "# (was finger_force_n) ")
    assert "lacks sim.finger_force_n (unset by default)" in unset
    [unknown] = _edited("[calibration]", "[calibration]\n# A key Config does not know.\nbogus_m = 1.0")
    assert "calibration.bogus_m is not a Config field" in unknown
    [value] = _edited("\ngamma = 0.5\n", "\ngamma = 0.6\n")
    assert "learner.gamma = 0.6, but its declared default is 0.5" in value
    comment = re.search(r"\n(#[^\n]*)\nfps = 30\n", DEFAULT_TOML.read_text())
    assert comment is not None
    [bare] = _edited(comment[0], "\nfps = 30\n")
    assert "realsense.fps has no comment" in bare
    assert _edited("\nfps = 30\n", "\nfps = 30  # frames per second\n") == []  # an inline comment counts
    assert all("\n" not in p for p in (missing, unset, unknown, value, bare))
