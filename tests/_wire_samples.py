"""Valid sample messages for the wire tests (test_wire.py, test_wire_fuzz.py); small heightmaps; and
crafted PNGs that pass every header and CRC check but do not decode."""

from __future__ import annotations

import dataclasses
import struct
import zlib
from collections.abc import Callable
from typing import Any

import numpy as np

from romannet.common import romannet_pb2 as pb
from romannet.common import wire
from romannet.common.action import Action
from romannet.common.imagecodec import units_to_depth_m


def heightmaps(h: int = 8, w: int = 8, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(color uint8 (h, w, 3), depth float32 (h, w) m) with depth already on the 1e-5 m grid."""
    rng = np.random.default_rng(seed)
    color = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    depth = units_to_depth_m(rng.integers(0, 65536, (h, w)).astype(np.uint16))
    return color, depth


def transition(h: int = 8, w: int = 8, seed: int = 0, **overrides: Any) -> wire.TransitionMsg:
    """A valid transition; keyword arguments replace fields."""
    color_b, depth_b = heightmaps(h, w, seed)
    color_a, depth_a = heightmaps(h, w, seed + 1)
    fields: dict[str, Any] = dict(
        actor_id="sim-0.lab_1", episode_id="ep-000042", step=7, start_ns=1_700_000_000_000_000_000,
        end_ns=1_700_000_000_500_000_000, task="stacking", color_before=color_b, depth_before=depth_b,
        color_after=color_a, depth_after=depth_a,
        action=Action("place", h - 1, w - 1, -1.25, 0.875, explored=True),
        success=True, progress_before=0.25, progress_after=0.5, reward=0.5, done=True,
        done_reason="goal_reached", holding_before=True, holding_after=False, policy_version=12,
        explore_rate=0.3, initial_priority=2.5, sim_seed=2**63 + 5,
    )
    fields.update(overrides)
    return wire.TransitionMsg(**fields)


def assert_transitions_equal(a: wire.TransitionMsg, b: wire.TransitionMsg) -> None:
    """Field-by-field equality (TransitionMsg compares by identity because it holds arrays)."""
    for f in dataclasses.fields(wire.TransitionMsg):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape, f.name
            np.testing.assert_array_equal(x, y, err_msg=f.name)
        else:
            assert x == y, f"{f.name}: {x!r} != {y!r}"


def weights_msgs() -> tuple[wire.WeightsMsg, wire.WeightsAnnouncementMsg]:
    """A small weights version without importing torch (payload: hand-made safetensors bytes)."""
    header = b'{"w":{"dtype":"F32","shape":[2],"data_offsets":[0,8]}}'
    payload = len(header).to_bytes(8, "little") + header + np.array([1.0, -2.0], np.float32).tobytes()
    digest = wire.sha256_hex(payload)
    return (wire.WeightsMsg(3, digest, payload),
            wire.WeightsAnnouncementMsg(3, digest, len(payload), 1_700_000_000_000_000_000))


def sample_batch(h: int = 8, w: int = 8) -> wire.SampleBatchMsg:
    """Two items: one as a TransitionMsg, one as already-encoded bytes."""
    items = (wire.SampleItem(11, 0.25, 1.0, transition(h, w, seed=0)),
             wire.SampleItem(2**64 - 1, 1.0, 0.5, wire.encode_transition(transition(h, w, seed=5, done=False,
                                                                                   done_reason=""))))
    return wire.SampleBatchMsg("req-1", items, 1000)


def all_messages(h: int = 8, w: int = 8) -> dict[str, tuple[Any, Callable[[Any], bytes], Callable[..., Any]]]:
    """name -> (valid message, encoder, decoder) for every message type."""
    weights, announcement = weights_msgs()
    return {
        "transition": (transition(h, w), wire.encode_transition, wire.decode_transition),
        "weights_announcement": (announcement, wire.encode_weights_announcement, wire.decode_weights_announcement),
        "weights": (weights, wire.encode_weights, wire.decode_weights),
        "exploration_rate": (wire.ExplorationRateMsg(12, 0.125, "lae"), wire.encode_exploration_rate,
                             wire.decode_exploration_rate),
        "priority_update": (wire.PriorityUpdateMsg((0, 5, 2**64 - 1), (0.0, 1.5, 1e9)),
                            wire.encode_priority_update, wire.decode_priority_update),
        "sample_request": (wire.SampleRequestMsg("req-1", 32), wire.encode_sample_request, wire.decode_sample_request),
        "sample_batch": (sample_batch(h, w), wire.encode_sample_batch, wire.decode_sample_batch),
        "insert_ack": (wire.InsertAckMsg("sim-0", "ep-1", 3, "duplicate", 77), wire.encode_insert_ack,
                       wire.decode_insert_ack),
    }


def pb_message(name: str) -> Any:
    """The protobuf message of all_messages()[name], parsed from its encoding, ready to be tampered with."""
    msg, encode, _ = all_messages()[name]
    out = getattr(pb, "".join(part.capitalize() for part in name.split("_")))()
    out.ParseFromString(encode(msg))
    return out


def pb_transition(**overrides: Any) -> pb.Transition:
    """The protobuf message of transition(**overrides)."""
    out = pb.Transition()
    out.ParseFromString(wire.encode_transition(transition(**overrides)))
    return out


def png_chunks(png: bytes) -> list[tuple[bytes, bytes]]:
    """[(type, data)] of a well-formed PNG."""
    out, pos = [], 8
    while pos < len(png):
        length, kind = struct.unpack_from(">I4s", png, pos)
        out.append((kind, png[pos + 8:pos + 8 + length]))
        pos += 12 + length
    return out


def png_from_chunks(chunks: list[tuple[bytes, bytes]]) -> bytes:
    """A PNG of these chunks, each with a valid CRC: what a crafted file would carry."""
    return b"\x89PNG\r\n\x1a\n" + b"".join(struct.pack(">I", len(data)) + kind + data
                                           + struct.pack(">I", zlib.crc32(kind + data)) for kind, data in chunks)


def _with_idat(png: bytes, idat: bytes) -> bytes:
    chunks = png_chunks(png)
    return png_from_chunks([chunks[0], (b"IDAT", idat), (b"IEND", b"")])


def png_with_bad_zlib(png: bytes) -> bytes:
    """The PNG with its image data replaced by a zlib header and a deflate block of the reserved type 3:
    the stream cannot inflate, yet every chunk's CRC is valid."""
    return _with_idat(png, b"\x78\x01\x07" + b"\x00" * 16)


def png_missing_rows(png: bytes) -> bytes:
    """The PNG whose IHDR still claims all rows but whose (valid) zlib stream holds only the first half."""
    chunks = png_chunks(png)
    raw = zlib.decompress(b"".join(data for kind, data in chunks if kind == b"IDAT"))
    height = struct.unpack(">I", chunks[0][1][4:8])[0]
    row = len(raw) // height  # filter byte + pixels
    return _with_idat(png, zlib.compress(raw[:row * (height // 2)]))


CRAFTED_PNGS: dict[str, Callable[[bytes], bytes]] = {
    "zlib stream that does not inflate": png_with_bad_zlib,
    "IHDR claims rows the data lacks": png_missing_rows,
}
