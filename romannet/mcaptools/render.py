"""Drawing one recorded step for people: camera image, heightmap with the Q map over it, the action, text.

Layout (left to right, then a text bar below): the camera image before the action (or, without a
recorded camera, the depth heightmap colour-mapped), and the colour heightmap before the action with the
executed net's Q map blended over it (JET, scaled min..max as recorded) and the executed action drawn:
an arrow for a push (its direction and recorded push length), a gripper bar for pick/place (the
finger-closing axis, fingers at its ends, the gripper's opening wide). Pure functions of arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from romannet.common.errors import DecodeError

ACTION_BGR = {"push": (0, 200, 255), "pick": (0, 255, 0), "place": (255, 0, 255)}
OK_BGR, FAIL_BGR, TEXT_BGR = (80, 220, 80), (60, 60, 255), (235, 235, 235)
DEPTH_DISPLAY_MAX_M = 0.3
_LINE_PX = 26
_FONT = cv2.FONT_HERSHEY_SIMPLEX


@dataclass(frozen=True)
class StepView:
    """What one frame shows. Images are BGR uint8; lengths are in heightmap pixels."""

    heightmap_bgr: np.ndarray
    left_bgr: np.ndarray  # the camera image, or the depth heightmap colour-mapped when none was recorded
    q_bgr: np.ndarray | None
    primitive: str
    row: int
    col: int
    angle_rad: float
    push_length_px: float
    gripper_width_px: float
    lines: tuple[tuple[str, tuple[int, int, int]], ...]  # (text, BGR colour) per line of the text bar


def decode_compressed(data: bytes) -> np.ndarray:
    """BGR uint8 image of a foxglove.CompressedImage message (PNG or JPEG)."""
    msg = CompressedImage.FromString(data)
    image = cv2.imdecode(np.frombuffer(msg.data, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        raise DecodeError(f"a recorded {msg.format or 'compressed'} image does not decode")
    return image


def decode_raw16(data: bytes) -> np.ndarray:
    """uint16 (h, w) array of a foxglove.RawImage 16UC1 message."""
    msg = RawImage.FromString(data)
    if msg.encoding != "16UC1" or msg.step != 2 * msg.width or len(msg.data) != msg.step * msg.height:
        raise DecodeError(f"a recorded RawImage is not a packed 16UC1 image ({msg.encoding}, "
                          f"{msg.width}x{msg.height}, step {msg.step})")
    return np.frombuffer(msg.data, "<u2").reshape(msg.height, msg.width)


def depth_colormap(depth_m: np.ndarray) -> np.ndarray:
    """BGR uint8 of a depth heightmap, 0..DEPTH_DISPLAY_MAX_M metres (VIRIDIS)."""
    depth_u8 = np.clip(np.nan_to_num(depth_m) / DEPTH_DISPLAY_MAX_M * 255.0, 0, 255).astype(np.uint8)
    return cv2.applyColorMap(depth_u8, cv2.COLORMAP_VIRIDIS)


def _even(n: int) -> int:
    return n + (n % 2)


def _resize(img: np.ndarray, width: int, height: int, nearest: bool) -> np.ndarray:
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)


def draw_action(img: np.ndarray, view: StepView, scale: float) -> None:
    """The action on a heightmap panel shown `scale` times the heightmap's size (in place)."""
    c = np.array([(view.col + 0.5) * scale, (view.row + 0.5) * scale])
    d = np.array([math.cos(view.angle_rad), math.sin(view.angle_rad)])  # (d_col, d_row): common.action
    color = ACTION_BGR.get(view.primitive, TEXT_BGR)
    thick = max(2, round(scale))

    def pt(v: np.ndarray) -> tuple[int, int]:
        return int(round(v[0])), int(round(v[1]))

    if view.primitive == "push":
        cv2.arrowedLine(img, pt(c), pt(c + d * view.push_length_px * scale), color, thick, cv2.LINE_AA,
                        tipLength=0.25)
    else:
        half = d * view.gripper_width_px * scale / 2
        normal = np.array([-d[1], d[0]]) * max(4.0, view.gripper_width_px * scale / 6)
        cv2.line(img, pt(c - half), pt(c + half), color, thick, cv2.LINE_AA)
        for end in (c - half, c + half):  # the fingers, across the closing axis
            cv2.line(img, pt(end - normal), pt(end + normal), color, thick + 1, cv2.LINE_AA)
    cv2.circle(img, pt(c), max(3, thick * 2), color, thick, cv2.LINE_AA)


def compose(view: StepView, panel_px: int = 448, q_alpha: float = 0.35) -> np.ndarray:
    """The frame (BGR uint8, even width and height) of one step."""
    h, w = view.heightmap_bgr.shape[:2]
    scale = panel_px / h
    panel_w = round(w * scale)
    hm = _resize(view.heightmap_bgr, panel_w, panel_px, nearest=True)
    if view.q_bgr is not None:
        q = _resize(view.q_bgr, panel_w, panel_px, nearest=True)
        hm = cv2.addWeighted(hm, 1.0 - q_alpha, q, q_alpha, 0.0)
    draw_action(hm, view, scale)
    left = view.left_bgr
    left_w = round(left.shape[1] * panel_px / left.shape[0])
    cam = _resize(left, left_w, panel_px, nearest=left.shape[:2] == (h, w))
    gap = np.full((panel_px, 8, 3), 32, np.uint8)
    top = np.concatenate([cam, gap, hm], axis=1)
    width, height = _even(top.shape[1]), _even(panel_px + _LINE_PX * len(view.lines) + 8)
    frame = np.full((height, width, 3), 24, np.uint8)
    frame[:panel_px, :top.shape[1]] = top
    for i, (text, color) in enumerate(view.lines):
        cv2.putText(frame, text, (8, panel_px + _LINE_PX * (i + 1)), _FONT, 0.55, color, 1, cv2.LINE_AA)
    return frame
