"""PNG coding of heightmaps: exact round trips, the depth quantisation policy, and hostile input."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from romannet.common import imagecodec as ic
from romannet.common.errors import DecodeError

# Decoding yields float32; its rounding adds at most half a float32 ulp at 0.65 m (~3e-8 m) to the 5e-6 m
# of quantisation.
DEPTH_TOL_M = 5e-6 + 6e-8


def png_with_header(width: int, height: int, bit_depth: int = 8, color_type: int = 2) -> bytes:
    """A PNG whose IHDR claims the given size, followed by a tiny (wrong-sized) IDAT and IEND."""
    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))
    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, color_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")


@pytest.mark.parametrize("shape", [(224, 224), (8, 8), (3, 5), (1, 2048)])
def test_color_round_trip_is_exact(shape: tuple[int, int]) -> None:
    rgb = np.random.default_rng(1).integers(0, 256, (*shape, 3), dtype=np.uint8)
    out = ic.decode_color_png(ic.encode_color_png(rgb))
    assert out.dtype == np.uint8 and out.shape == rgb.shape
    np.testing.assert_array_equal(out, rgb)


def test_color_keeps_rgb_order_and_writes_a_standard_png() -> None:
    rgb = np.zeros((4, 4, 3), np.uint8)
    rgb[..., 0] = 255  # red
    data = ic.encode_color_png(rgb)
    assert ic.decode_color_png(data)[0, 0].tolist() == [255, 0, 0]
    # Any other reader sees red too: cv2 itself returns BGR, so red is the last channel.
    assert cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)[0, 0].tolist() == [0, 0, 255]


@pytest.mark.parametrize("level", [0, 1, 3, 6, 9])
def test_every_compression_level_is_lossless(level: int) -> None:
    rgb = np.random.default_rng(2).integers(0, 256, (16, 16, 3), dtype=np.uint8)
    np.testing.assert_array_equal(ic.decode_color_png(ic.encode_color_png(rgb, level)), rgb)
    depth = np.random.default_rng(3).uniform(0, 0.6, (16, 16)).astype(np.float32)
    assert np.abs(ic.decode_depth_png(ic.encode_depth_png(depth, level)) - depth).max() <= DEPTH_TOL_M


@settings(max_examples=200)
@given(arrays(np.float32, st.tuples(st.integers(1, 12), st.integers(1, 12)),
              elements=st.floats(0.0, float(np.float32(0.655349)), width=32)))
def test_depth_round_trip_within_half_a_unit_and_idempotent(depth: np.ndarray) -> None:
    data = ic.encode_depth_png(depth)
    once = ic.decode_depth_png(data)
    assert once.dtype == np.float32 and once.shape == depth.shape
    assert np.abs(once.astype(np.float64) - depth).max() <= DEPTH_TOL_M
    np.testing.assert_array_equal(ic.decode_depth_png(ic.encode_depth_png(once)), once)
    assert ic.encode_depth_png(once) == data


def test_every_depth_unit_survives_metres_and_back() -> None:
    units = np.arange(65536, dtype=np.uint16).reshape(256, 256)
    np.testing.assert_array_equal(ic.depth_m_to_units(ic.units_to_depth_m(units)), units)
    np.testing.assert_array_equal(ic.depth_m_to_units(ic.decode_depth_png(ic.encode_depth_png(
        ic.units_to_depth_m(units)))), units)


def test_depth_limits_and_negative_clipping() -> None:
    depth = np.array([[-0.5, -1e-7, 0.0, ic.DEPTH_MAX_M]], np.float32)
    out = ic.decode_depth_png(ic.encode_depth_png(depth))
    assert out[0, :3].tolist() == [0.0, 0.0, 0.0]  # below the floor: clipped to 0 (documented policy)
    assert abs(out[0, 3] - ic.DEPTH_MAX_M) <= DEPTH_TOL_M
    with pytest.raises(ValueError, match="exceeds the encodable maximum 0.65535"):
        ic.encode_depth_png(np.full((2, 2), 0.66, np.float32))
    for bad in (np.nan, np.inf, -np.inf):
        with pytest.raises(ValueError, match="non-finite"):
            ic.encode_depth_png(np.array([[0.1, bad]], np.float32))


@pytest.mark.parametrize("image, match", [
    (np.zeros((4, 4, 3), np.float32), "uint8"),
    (np.zeros((4, 4), np.uint8), "uint8 array of shape"),
    (np.zeros((4, 4, 4), np.uint8), r"\(h, w, 3\)"),
    (np.zeros((0, 4, 3), np.uint8), "1..2048"),
    (np.zeros((2049, 1, 3), np.uint8), "1..2048"),
])
def test_encode_color_rejects_bad_arrays(image: np.ndarray, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        ic.encode_color_png(image)


def test_encode_rejects_bad_depth_arrays_and_levels() -> None:
    with pytest.raises(ValueError, match="floating-point"):
        ic.encode_depth_png(np.zeros((4, 4), np.uint16))
    with pytest.raises(ValueError, match="2-D"):
        ic.encode_depth_png(np.zeros((4, 4, 1), np.float32))
    with pytest.raises(ValueError, match="level 10"):
        ic.encode_color_png(np.zeros((4, 4, 3), np.uint8), level=10)


def test_decoders_reject_the_other_format() -> None:
    color = ic.encode_color_png(np.zeros((4, 4, 3), np.uint8))
    depth = ic.encode_depth_png(np.zeros((4, 4), np.float32))
    with pytest.raises(DecodeError, match="bit depth 16 and colour type 0; expected bit depth 8 and colour type 2"):
        ic.decode_color_png(depth)
    with pytest.raises(DecodeError, match="bit depth 8 and colour type 2; expected bit depth 16 and colour type 0"):
        ic.decode_depth_png(color)


@pytest.mark.parametrize("image, decoder", [
    (np.zeros((4, 4), np.uint8), ic.decode_color_png),  # 8-bit gray
    (np.zeros((4, 4, 4), np.uint8), ic.decode_color_png),  # RGBA
    (np.zeros((4, 4), np.uint8), ic.decode_depth_png),  # 8-bit gray
    (np.zeros((4, 4, 3), np.uint16), ic.decode_depth_png),  # 16-bit RGB
])
def test_decoders_reject_other_channel_layouts(image: np.ndarray, decoder) -> None:
    ok, buf = cv2.imencode(".png", image)
    assert ok
    with pytest.raises(DecodeError, match="expected bit depth"):
        decoder(buf.tobytes())


@pytest.mark.parametrize("width, height", [(100_000, 100_000), (2049, 4), (4, 2049), (0, 4)])
def test_header_claiming_a_huge_image_is_refused_before_decompressing(monkeypatch, width, height) -> None:
    def never(*_args, **_kwargs):
        raise AssertionError("cv2.imdecode must not run on a refused header")
    monkeypatch.setattr(ic.cv2, "imdecode", never)
    with pytest.raises(DecodeError, match="refused before decompressing"):
        ic.decode_color_png(png_with_header(width, height))


def test_lying_header_within_limits_is_rejected_by_the_decoder() -> None:
    with pytest.raises(DecodeError, match="corrupt"):
        ic.decode_color_png(png_with_header(64, 64))


@pytest.mark.parametrize("data, match", [
    (b"", "not a PNG"),
    (b"GIF89a" + b"\0" * 40, "not a PNG"),
    (b"\x89PNG\r\n\x1a\n" + b"\0" * 30, "not a 13-byte IHDR"),
    ("not bytes", "must be bytes"),
    (b"\x89PNG\r\n\x1a\n" + b"\0" * ic.MAX_PNG_BYTES, "at most"),
])
def test_decoders_reject_non_png_input(data, match: str) -> None:
    with pytest.raises(DecodeError, match=match):
        ic.decode_color_png(data)
    with pytest.raises(DecodeError, match=match):
        ic.decode_depth_png(data)


def test_truncated_and_corrupted_pngs_raise_decode_error() -> None:
    data = ic.encode_color_png(np.random.default_rng(4).integers(0, 256, (32, 32, 3), dtype=np.uint8))
    for cut in (40, len(data) // 2, len(data) - 13):
        with pytest.raises(DecodeError):
            ic.decode_color_png(data[:cut])
    corrupt = bytearray(data)
    corrupt[len(data) // 2] ^= 0xFF  # inside IDAT: its CRC no longer matches
    with pytest.raises(DecodeError, match="corrupt"):
        ic.decode_color_png(bytes(corrupt))


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def _split_png(data: bytes) -> tuple[bytes, bytes, bytes]:
    """(signature + IHDR chunk, the chunks between, IEND chunk) of a PNG."""
    return data[:33], data[33:-12], data[-12:]


def test_chunk_claiming_gigabytes_is_refused_without_allocating(monkeypatch) -> None:
    # cv2 would allocate the claimed 4 GB (found by the fuzz test): the length is checked against the data.
    head, _, _ = _split_png(ic.encode_depth_png(np.zeros((8, 8), np.float32)))
    data = head + struct.pack(">I", 0xFFFF_FF00) + b"IDAT" + b"\0" * 40

    def never(*_args, **_kwargs):
        raise AssertionError("cv2.imdecode must not run on a malformed chunk")
    monkeypatch.setattr(ic.cv2, "imdecode", never)
    with pytest.raises(DecodeError, match="chunk 'IDAT' claims 4294967040 bytes but only 36 remain"):
        ic.decode_depth_png(data)


def test_chunk_structure_rules() -> None:
    head, middle, tail = _split_png(ic.encode_color_png(np.zeros((8, 8, 3), np.uint8)))
    assert ic.decode_color_png(head + _chunk(b"tEXt", b"Comment\0ok") + middle + tail).shape == (8, 8, 3)
    with pytest.raises(DecodeError, match="chunk 'acTL' is not accepted"):  # APNG
        ic.decode_color_png(head + _chunk(b"acTL", b"\0" * 8) + middle + tail)
    with pytest.raises(DecodeError, match="chunk 'eXIf' is not accepted"):  # EXIF could rotate the image
        ic.decode_color_png(head + _chunk(b"eXIf", b"MM\0*") + middle + tail)
    with pytest.raises(DecodeError, match="bad CRC"):
        ic.decode_color_png(head + middle[:-1] + bytes([middle[-1] ^ 1]) + tail)
    with pytest.raises(DecodeError, match="no IDAT chunk"):
        ic.decode_color_png(head + tail)
    with pytest.raises(DecodeError, match="3 bytes after IEND"):
        ic.decode_color_png(head + middle + tail + b"abc")
    with pytest.raises(DecodeError, match="no IEND chunk"):
        ic.decode_color_png(head + middle)
