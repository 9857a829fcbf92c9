"""Names taken from data (ids in files and messages) checked before they become part of a file-system path.

A run id, actor id or episode id read from an MCAP file's metadata, a message or a file the project wrote
earlier is only trusted as one path component once `safe_name` accepted it: 1..128 characters from
A-Z a-z 0-9 . _ -, and not "." or "..". So no separator, no parent step, no absolute path, no empty
component, nothing a crafted file could use to write outside the directory it is joined to. The alphabet
is the wire identifiers' (common/wire_validate.py), so any id that passes the wire schema and is not "."
or ".." passes here too.
"""

from __future__ import annotations

import re

from .errors import RomannetError

MAX_NAME_CHARS = 128
_NAME_RE = re.compile(rf"[A-Za-z0-9._-]{{1,{MAX_NAME_CHARS}}}")
_SHOWN_CHARS = 80


class UnsafeNameError(RomannetError, ValueError):
    """A value from data cannot be one path component; the message names what it is and the value."""

    def __init__(self, what: str, value: object):
        self.what, self.value = what, value
        super().__init__(f"{what} = {_show(value)} cannot name a file or directory: it must be 1..{MAX_NAME_CHARS} "
                         "characters from A-Z a-z 0-9 . _ - and not '.' or '..'")


def _show(value: object) -> str:
    """repr of the value (one line, escapes visible), cut so that a hostile value cannot flood a log line."""
    text = repr(value)
    return text if len(text) <= _SHOWN_CHARS else text[: _SHOWN_CHARS - 3] + "..."


def is_safe_name(value: object) -> bool:
    """True if value can be one path component (see the module docstring)."""
    return isinstance(value, str) and value not in (".", "..") and _NAME_RE.fullmatch(value) is not None


def safe_name(value: object, what: str) -> str:
    """value, if it can be one path component; UnsafeNameError naming `what` and the value otherwise."""
    if not is_safe_name(value):
        raise UnsafeNameError(what, value)
    assert isinstance(value, str)
    return value
