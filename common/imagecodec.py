"""Lossless PNG coding of heightmaps, as they travel on the wire and sit in storage.

Color heightmaps are 8-bit RGB PNGs; depth heightmaps are 16-bit grayscale PNGs in units of 1e-5 m
(VPG's convention): lossless to 10 um from 0 up to 0.65535 m.

Depth encoding policy:
- values are rounded to the nearest 1e-5 m, so decode(encode(x)) is within 5e-6 m of x and
  encode(decode(y)) == y (quantisation is idempotent);
- negative values are clipped to 0: a heightmap is height above the workspace floor, and points below
  the floor are sensor noise (VPG clips them to 0 when it builds the heightmap too);
- values above DEPTH_MAX_M, NaN and inf raise ValueError: clipping them would silently corrupt the
  observation (e.g. a stack that reads lower than it is), so the producer must fix them.

Decoders trust nothing: before cv2 sees the bytes, the PNG header is checked (signature, IHDR size, bit
depth, colour type), so a small file claiming a huge image (a decompression bomb) is refused, and so is
the chunk structure (lengths within the data, CRCs, accepted chunk types), because cv2 allocates what a
chunk length claims. Every failure raises DecodeError.
"""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np

from .errors import DecodeError

DEPTH_SCALE_M = 1e-5  # metres per unit of the 16-bit depth PNG
DEPTH_MAX_M = 65535 * DEPTH_SCALE_M  # 0.65535 m, the largest encodable height
MAX_SIDE_PX = 2048  # largest width or height accepted, in pixels
MAX_PNG_BYTES = 32 * 1024 * 1024  # a 2048x2048 RGB PNG is at most ~12.6 MB even when incompressible
# zlib level 1: on noisy heightmaps level 6 saves ~5 % of the bytes for 2-4x the actor's encode time
# (docs/journal.md, "Measurements behind code comments").
PNG_COMPRESSION_LEVEL = 1

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_COLOR_TYPE_GRAY = 0
_COLOR_TYPE_RGB = 2
# Chunks a plain PNG writer emits. Everything else is refused: APNG frames (acTL, fcTL, fdAT) and
# compressed or EXIF metadata (iCCP, zTXt, iTXt, eXIf) take other decoder paths we have no use for.
_ALLOWED_CHUNKS = frozenset({b"IHDR", b"IDAT", b"IEND", b"gAMA", b"cHRM", b"sRGB", b"sBIT", b"pHYs", b"tIME",
                             b"tEXt"})


def _check_image_size(h: int, w: int, what: str) -> None:
    if not (1 <= h <= MAX_SIDE_PX and 1 <= w <= MAX_SIDE_PX):
        raise ValueError(f"{what} is {h}x{w} pixels; height and width must be 1..{MAX_SIDE_PX}")


def _encode_png(image: np.ndarray, level: int) -> bytes:
    if not 0 <= level <= 9:
        raise ValueError(f"PNG compression level {level} is invalid: must be 0..9")
    ok, buf = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, level])
    if not ok:  # cv2 reports failure by a flag, not an exception
        raise ValueError(f"cv2.imencode failed on a {image.shape} {image.dtype} image")
    return buf.tobytes()


def encode_color_png(rgb: np.ndarray, level: int = PNG_COMPRESSION_LEVEL) -> bytes:
    """PNG bytes of an RGB uint8 image of shape (h, w, 3); raises ValueError on another dtype or shape."""
    if not isinstance(rgb, np.ndarray) or rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"color image must be a uint8 array of shape (h, w, 3); got "
                         f"{getattr(rgb, 'dtype', type(rgb))} {getattr(rgb, 'shape', '')}")
    _check_image_size(rgb.shape[0], rgb.shape[1], "color image")
    # cv2 stores channels as BGR; the API is RGB everywhere else in the project.
    return _encode_png(cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR), level)


def depth_m_to_units(depth_m: np.ndarray) -> np.ndarray:
    """uint16 depth in units of 1e-5 m of a float depth heightmap in metres (see the module policy)."""
    if not isinstance(depth_m, np.ndarray) or not np.issubdtype(depth_m.dtype, np.floating):
        got = getattr(depth_m, "dtype", type(depth_m).__name__)
        raise ValueError(f"depth must be a floating-point array in metres; got {got}")
    if not np.isfinite(depth_m).all():
        raise ValueError(f"depth contains {int((~np.isfinite(depth_m)).sum())} non-finite values; "
                         "fill them (e.g. with 0) before encoding")
    units = np.rint(depth_m.astype(np.float64) / DEPTH_SCALE_M)
    if units.size and units.max() > 65535:
        raise ValueError(f"depth {float(depth_m.max()):.6f} m exceeds the encodable maximum {DEPTH_MAX_M} m "
                         "(16-bit PNG in units of 1e-5 m); clip the heightmap to the workspace height first")
    return np.clip(units, 0, 65535).astype(np.uint16)


def units_to_depth_m(units: np.ndarray) -> np.ndarray:
    """float32 depth in metres of uint16 depth in units of 1e-5 m."""
    return (units.astype(np.float64) * DEPTH_SCALE_M).astype(np.float32)


def encode_depth_png(depth_m: np.ndarray, level: int = PNG_COMPRESSION_LEVEL) -> bytes:
    """16-bit grayscale PNG bytes of a (h, w) depth heightmap in metres, quantised to 1e-5 m."""
    if not isinstance(depth_m, np.ndarray) or depth_m.ndim != 2:
        raise ValueError(f"depth must be a 2-D array (h, w) in metres; got shape "
                         f"{getattr(depth_m, 'shape', None)}")
    _check_image_size(depth_m.shape[0], depth_m.shape[1], "depth image")
    return _encode_png(depth_m_to_units(depth_m), level)


def read_png_header(data: bytes) -> tuple[int, int, int, int]:
    """(height, width, bit_depth, color_type) from a PNG's IHDR chunk, without decompressing anything.

    Raises DecodeError if the bytes do not start with a well-formed IHDR or claim a size out of range.
    """
    if not isinstance(data, bytes | bytearray | memoryview):
        raise DecodeError(f"PNG data must be bytes; got {type(data).__name__}")
    if len(data) > MAX_PNG_BYTES:
        raise DecodeError(f"PNG is {len(data)} bytes; at most {MAX_PNG_BYTES} are accepted")
    # signature (8) + chunk length (4) + b"IHDR" (4) + IHDR body (13) + CRC (4)
    if len(data) < 33 or bytes(data[:8]) != _PNG_SIGNATURE:
        raise DecodeError("not a PNG: missing the PNG signature or too short for a header")
    length, chunk_type = struct.unpack(">I4s", data[8:16])
    if length != 13 or chunk_type != b"IHDR":
        raise DecodeError("malformed PNG: the first chunk is not a 13-byte IHDR")
    width, height, bit_depth, color_type = struct.unpack(">IIBB", data[16:26])
    if not (1 <= height <= MAX_SIDE_PX and 1 <= width <= MAX_SIDE_PX):
        raise DecodeError(f"PNG header claims {height}x{width} pixels; height and width must be "
                          f"1..{MAX_SIDE_PX} (refused before decompressing)")
    return height, width, bit_depth, color_type


def check_png_chunks(data: bytes) -> None:
    """Walk the chunks: each fits in the data, has a valid CRC and an accepted type; IEND ends the data.

    cv2 allocates a buffer of whatever size a chunk claims before reading it (a 200-byte file claiming a
    4 GB IDAT costs 4 GB and seconds), so lengths are checked against the bytes actually present.
    """
    view = memoryview(data)
    pos, seen_idat = len(_PNG_SIGNATURE), False
    while True:
        if pos + 12 > len(data):
            raise DecodeError("truncated PNG: no IEND chunk before the end of the data")
        length, kind = struct.unpack_from(">I4s", data, pos)
        end = pos + 12 + length
        name = kind.decode("latin-1")
        if end > len(data):
            raise DecodeError(f"malformed PNG: chunk {name!r} claims {length} bytes but only "
                              f"{max(len(data) - pos - 12, 0)} remain")
        if kind not in _ALLOWED_CHUNKS:
            raise DecodeError(f"PNG chunk {name!r} is not accepted (allowed: "
                              f"{sorted(k.decode() for k in _ALLOWED_CHUNKS)})")
        if zlib.crc32(view[pos + 4:end - 4]) != struct.unpack_from(">I", data, end - 4)[0]:
            raise DecodeError(f"PNG chunk {name!r} has a bad CRC: the data is corrupt")
        seen_idat |= kind == b"IDAT"
        pos = end
        if kind == b"IEND":
            break
    if not seen_idat:
        raise DecodeError("malformed PNG: no IDAT chunk")
    if pos != len(data):
        raise DecodeError(f"malformed PNG: {len(data) - pos} bytes after IEND")


def _decode_png(data: bytes, bit_depth: int, color_type: int, what: str) -> np.ndarray:
    h, w, got_depth, got_type = read_png_header(data)
    if (got_depth, got_type) != (bit_depth, color_type):
        raise DecodeError(f"{what} PNG has bit depth {got_depth} and colour type {got_type}; "
                          f"expected bit depth {bit_depth} and colour type {color_type}")
    check_png_chunks(data)
    try:
        # IMREAD_UNCHANGED keeps 16 bits and ignores EXIF orientation, so pixels come back as stored.
        image = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise DecodeError(f"{what} PNG is corrupt: {exc}") from exc
    if image is None:
        raise DecodeError(f"{what} PNG is corrupt (cv2.imdecode could not decode it)")
    channels = 3 if color_type == _COLOR_TYPE_RGB else 1
    expected = (h, w, 3) if channels == 3 else (h, w)
    dtype = np.uint8 if bit_depth == 8 else np.uint16
    if image.shape != expected or image.dtype != dtype:
        raise DecodeError(f"{what} PNG decoded to {image.dtype} {image.shape}; "
                          f"expected {np.dtype(dtype)} {expected}")
    return image


def check_png_pixels(data: bytes, bit_depth: int, color_type: int, what: str) -> None:
    """Decode a PNG fully, as the learner will, and check the pixels against its header; DecodeError if not.

    For a check without the result (the replay server's insert): the same decoder the learner runs, so a
    PNG that passes here decodes there, but without the colour conversion or the depth scaling.
    """
    _decode_png(data, bit_depth, color_type, what)


def decode_color_png(data: bytes) -> np.ndarray:
    """RGB uint8 array (h, w, 3) of an 8-bit RGB PNG; raises DecodeError on anything else."""
    bgr = _decode_png(data, 8, _COLOR_TYPE_RGB, "color")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def decode_depth_png(data: bytes) -> np.ndarray:
    """float32 depth heightmap (h, w) in metres of a 16-bit grayscale PNG in units of 1e-5 m."""
    return units_to_depth_m(_decode_png(data, 16, _COLOR_TYPE_GRAY, "depth"))
