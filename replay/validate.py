"""Validate an incoming transition at the replay server's insert, without keeping its heightmaps.

The server stores the encoded bytes as they came and never needs the pixels, so nothing decoded is kept:
- protobuf framing, schema version, required fields, enum values, every scalar's range and finiteness
  (by building a TransitionMsg, whose constructor runs the same checks as the full decoder);
- each PNG's header (size, bit depth, colour type; all four equal; the expected heightmap shape) and its
  chunk structure with every chunk's CRC-32, so transport or disk corruption is caught cheaply (~0.4 ms);
- with decode_pixels (the server's default), each PNG decoded in full by the learner's own decoder, its
  pixels' shape and dtype checked against the header. Why: a crafted PNG (valid CRCs around a zlib stream
  that does not inflate, or an IHDR claiming more pixels than the data holds) passes the checks above;
  stored, it is sampled again and again and refused by the learner each time. Refused here, the actor
  hears "bad_image" and sets it aside. Its cost per insert is in docs/benchmarks.md (`romannet bench
  replay`, the `without_pixel_decode` row).
The returned TransitionMsg holds zero-stride placeholder heightmaps: use it for its fields only, and the
encoded bytes for the pixels (ReplayStore.insert(msg, encoded=data) does exactly that).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from romannet.common import romannet_pb2 as pb
from romannet.common import wire
from romannet.common.errors import DecodeError
from romannet.common.imagecodec import check_png_chunks, check_png_pixels, read_png_header

# (field, bit depth, PNG colour type): color is 8-bit RGB (type 2), depth 16-bit grayscale (type 0).
_PNG_FORMATS = (("color_before_png", 8, 2), ("depth_before_png", 16, 0),
                ("color_after_png", 8, 2), ("depth_after_png", 16, 0))


def _placeholders(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    # Zero-stride views: the right dtype and shape for TransitionMsg's checks, no memory.
    return (np.broadcast_to(np.zeros(3, np.uint8), (h, w, 3)),
            np.broadcast_to(np.zeros(1, np.float32), (h, w)))


def check_transition(data: bytes, expected_shape: tuple[int, int] | None = None,
                     max_bytes: int = 64 * 1024 * 1024, decode_pixels: bool = True) -> wire.TransitionMsg:
    """The transition's fields from encoded bytes, validated; the decoded pixels are not kept.

    expected_shape: (h, w) in pixels every heightmap must have, or None. decode_pixels: decode every PNG
    in full (False: headers and chunk CRCs only). Raises DecodeError (with the same messages as
    wire.decode_transition for what both check) when anything is wrong.
    """
    try:
        if len(data) > max_bytes:
            raise ValueError(f"message is {len(data)} bytes; at most {max_bytes} are accepted")
        t = pb.Transition()
        try:
            t.ParseFromString(data)
        except Exception as exc:
            raise ValueError(f"not a protobuf Transition message ({exc})") from exc
        primitive = wire.checked_primitive(t)  # the wire decoder's checks: same refusals, same messages
        # Each read of a bytes field copies it out of the parsed message: read each PNG once.
        pngs = {name: getattr(t, name) for name, _, _ in _PNG_FORMATS}
        wire.check_png_sizes(SimpleNamespace(**pngs), expected_shape)  # type: ignore[arg-type]
        for name, bit_depth, color_type in _PNG_FORMATS:
            png = pngs[name]
            got = read_png_header(png)[2:]
            if got != (bit_depth, color_type):
                raise ValueError(f"{name}: bit depth {got[0]} and colour type {got[1]}; expected bit depth "
                                 f"{bit_depth} and colour type {color_type}")
            if decode_pixels:
                check_png_pixels(png, bit_depth, color_type, name)  # walks the chunks first
            else:
                check_png_chunks(png)
        h, w = read_png_header(pngs["color_before_png"])[:2]
        color, depth = _placeholders(h, w)
        return wire.transition_msg(t, primitive, color, depth, color, depth)
    except DecodeError as exc:
        raise DecodeError(f"invalid Transition: {exc}") from exc
    except Exception as exc:  # the contract, as for wire's decoders: DecodeError and nothing else
        text = str(exc) if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}"
        raise DecodeError(f"invalid Transition: {text}") from exc
