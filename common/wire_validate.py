"""Field checks shared by the wire dataclasses (common/wire.py).

Each check raises ValueError naming the field, the (shortened) value and what is allowed. The dataclasses
run them in __post_init__, so a message that exists is valid; the decoders turn the ValueError into
DecodeError. Values are shown shortened so that a hostile message cannot blow up log lines.
"""

from __future__ import annotations

import math
import numbers
import re

import numpy as np

from .imagecodec import MAX_SIDE_PX

MAX_ID_CHARS = 128
MAX_TEXT_CHARS = 1024
# Identifiers become Zenoh key chunks and file names: ASCII letters, digits, '.', '_' and '-' only,
# which keeps out the key-expression specials ('*', '$', '?', '#', '/') and a leading '@'.
_TOKEN_RE = re.compile(rf"[A-Za-z0-9._-]{{1,{MAX_ID_CHARS}}}")
_SHA256_RE = re.compile(r"[0-9a-f]{64}")
UINT32_MAX = 2**32 - 1
UINT64_MAX = 2**64 - 1


def show(value: object, limit: int = 80) -> str:
    """repr of a value, cut to `limit` characters."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _fail(field: str, value: object, allowed: str) -> ValueError:
    return ValueError(f"{field} = {show(value)} is invalid: {allowed}")


def check_token(field: str, value: object, *, allow_empty: bool = False) -> None:
    """An identifier: 1..128 characters from [A-Za-z0-9._-] (empty too if allow_empty)."""
    if allow_empty and value == "":
        return
    if not isinstance(value, str) or _TOKEN_RE.fullmatch(value) is None:
        raise _fail(field, value, f"must be 1..{MAX_ID_CHARS} characters from A-Z a-z 0-9 . _ - "
                                  "(it is used as a Zenoh key chunk)" + ("" if allow_empty else "; missing?"))


def check_text(field: str, value: object, max_chars: int = MAX_TEXT_CHARS) -> None:
    """Free text for people: printable, at most max_chars characters, may be empty."""
    if not isinstance(value, str) or len(value) > max_chars or not value.isprintable():
        raise _fail(field, value, f"must be printable text of at most {max_chars} characters")


def check_sha256_hex(field: str, value: object) -> None:
    """A SHA-256 digest as 64 lowercase hex digits."""
    if not isinstance(value, str) or _SHA256_RE.fullmatch(value) is None:
        raise _fail(field, value, "must be a SHA-256 digest as 64 lowercase hex digits")


def check_int(field: str, value: object, lo: int, hi: int) -> None:
    """An integer (Python or numpy, not bool) in [lo, hi]."""
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Integral) or not lo <= value <= hi:
        raise _fail(field, value, f"must be an integer in [{lo}, {hi}]")


def check_float(field: str, value: object, lo: float = -math.inf, hi: float = math.inf,
                *, lo_open: bool = False) -> None:
    """A finite real number in [lo, hi] (or (lo, hi] with lo_open)."""
    if isinstance(value, bool | np.bool_) or not isinstance(value, numbers.Real) or not math.isfinite(value):
        raise _fail(field, value, "must be a finite number")
    if value > hi or value < lo or (lo_open and value == lo):
        raise _fail(field, value, f"must be in {'(' if lo_open else '['}{lo}, {hi}]")


def check_bool(field: str, value: object) -> None:
    """A bool (Python or numpy)."""
    if not isinstance(value, bool | np.bool_):
        raise _fail(field, value, "must be a bool")


def check_side_px(field: str, h: int, w: int) -> None:
    """Heightmap size: positive multiples of 4 (RoManNet downsamples twice by 2), at most MAX_SIDE_PX."""
    if not (4 <= h <= MAX_SIDE_PX and 4 <= w <= MAX_SIDE_PX and h % 4 == 0 and w % 4 == 0):
        raise _fail(field, (h, w), f"height and width must be multiples of 4 in [4, {MAX_SIDE_PX}] pixels")


def check_expected_shape(field: str, shape: tuple[int, int], expected: tuple[int, int] | None) -> None:
    """shape == expected, unless expected is None."""
    if expected is not None and tuple(shape) != tuple(expected):
        raise _fail(field, tuple(shape), f"heightmaps must be {expected[0]}x{expected[1]} pixels here")


def check_color(field: str, image: object) -> tuple[int, int]:
    """An RGB uint8 heightmap (h, w, 3); returns (h, w)."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"{field} must be a uint8 array of shape (h, w, 3); got "
                         f"{getattr(image, 'dtype', type(image).__name__)} {getattr(image, 'shape', '')}")
    check_side_px(f"{field}.shape", image.shape[0], image.shape[1])
    return image.shape[0], image.shape[1]


def check_depth(field: str, depth_m: object) -> tuple[int, int]:
    """A finite float32 depth heightmap (h, w) in metres; returns (h, w)."""
    if not isinstance(depth_m, np.ndarray) or depth_m.dtype != np.float32 or depth_m.ndim != 2:
        raise ValueError(f"{field} must be a float32 array of shape (h, w) in metres; got "
                         f"{getattr(depth_m, 'dtype', type(depth_m).__name__)} "
                         f"{getattr(depth_m, 'shape', '')}"
                         " (convert with .astype(np.float32))")
    check_side_px(f"{field}.shape", depth_m.shape[0], depth_m.shape[1])
    if not np.isfinite(depth_m).all():
        raise ValueError(f"{field} contains non-finite values; fill them (e.g. with 0) first")
    return depth_m.shape[0], depth_m.shape[1]


def check_heightmaps(color_before: object, depth_before: object, color_after: object,
                     depth_after: object) -> tuple[int, int]:
    """The four heightmaps of a transition, all of one (h, w); returns (h, w)."""
    shapes = {
        "color_before": check_color("color_before", color_before),
        "depth_before": check_depth("depth_before", depth_before),
        "color_after": check_color("color_after", color_after),
        "depth_after": check_depth("depth_after", depth_after),
    }
    if len(set(shapes.values())) != 1:
        raise ValueError(f"heightmaps differ in size: {shapes}; before and after, color and depth must match")
    return shapes["color_before"]
