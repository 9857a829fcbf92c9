"""Drawing one recorded step for people: camera image, heightmaps with the Q map and the action, text.

Panels (left to right, each titled; then a text bar below): the camera image before the action turned to
the heightmaps' orientation (when one was recorded); the colour heightmap before the action with the
executed net's Q map blended over it (JET, scaled min..max as recorded, with its colour bar when the range
is known); the depth heightmap (0 .. 0.3 m above the table, with its colour bar). Heightmaps are seen from
above, world x right and y up, the action drawn on both: an arrow for a push (its direction and recorded
push length), a gripper bar for pick/place (the finger-closing axis, fingers at its ends, the hand's
opening wide); a margin keeps an action at the workspace's edge whole (common.pictures). Pure functions.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage

from romannet.common.errors import DecodeError
from romannet.common.pictures import (
    BACKGROUND_BGR,
    DEPTH_DISPLAY_MAX_M,
    ActionGlyph,
    colorbar,
    depth_colormap,
    heightmap_panel,
    margin_px,
    resize,
    side_by_side,
    titled,
    turn_camera,
    with_margin,
)

OK_BGR, FAIL_BGR = (80, 220, 80), (60, 60, 255)
_LINE_PX = 26
_FONT = cv2.FONT_HERSHEY_SIMPLEX


@dataclass(frozen=True)
class StepView:
    """What one frame shows. Images are BGR uint8 (heightmaps in the arrays' orientation)."""

    heightmap_bgr: np.ndarray
    depth_m: np.ndarray  # the depth heightmap, metres above the table
    camera_bgr: np.ndarray | None  # None when no camera image was recorded
    camera_turns: int  # quarter turns that bring the camera image to the heightmaps' view
    q_bgr: np.ndarray | None
    q_range: tuple[float, float] | None  # the Q map's min..max, when recorded
    glyph: ActionGlyph
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


def _even(n: int) -> int:
    return n + (n % 2)


def compose(view: StepView, panel_px: int = 448, q_alpha: float = 0.35) -> np.ndarray:
    """The frame (BGR uint8, even width and height) of one step; heightmaps `panel_px` tall."""
    g = view.glyph
    margin = margin_px(g.push_length_px, g.gripper_width_px, panel_px / view.heightmap_bgr.shape[0], panel_px)
    height = panel_px + 2 * margin
    hm = view.heightmap_bgr
    if view.q_bgr is not None:
        q = cv2.resize(view.q_bgr, (hm.shape[1], hm.shape[0]), interpolation=cv2.INTER_NEAREST)
        hm = cv2.addWeighted(hm, 1.0 - q_alpha, q, q_alpha, 0.0)
    primitive = view.glyph.primitive
    colour = [heightmap_panel(hm, height, view.glyph, margin)]
    if view.q_bgr is not None and view.q_range is not None:
        colour.append(colorbar(height, cv2.COLORMAP_JET, *view.q_range, f"Q {primitive}"))
    depth = [heightmap_panel(depth_colormap(view.depth_m), height, view.glyph, margin),
             colorbar(height, cv2.COLORMAP_VIRIDIS, 0.0, DEPTH_DISPLAY_MAX_M, "height m", ticks=6)]
    q_title = f" + {primitive} Q map" if view.q_bgr is not None else ""
    panels = [titled(side_by_side(colour, gap=0), f"colour heightmap{q_title}, from above (x right, y up)"),
              titled(side_by_side(depth, gap=0), "depth heightmap (height above the table)")]
    if view.camera_bgr is not None:
        cam = resize(turn_camera(view.camera_bgr, view.camera_turns), panel_px, nearest=False)
        panels.insert(0, titled(with_margin(cam, margin), "camera, turned to the heightmaps' view"))
    top = side_by_side(panels)
    width, frame_h = _even(top.shape[1]), _even(top.shape[0] + _LINE_PX * len(view.lines) + 8)
    frame = np.full((frame_h, width, 3), BACKGROUND_BGR, np.uint8)
    frame[:top.shape[0], :top.shape[1]] = top
    for i, (text, color) in enumerate(view.lines):
        cv2.putText(frame, text, (8, top.shape[0] + _LINE_PX * (i + 1)), _FONT, 0.55, color, 1, cv2.LINE_AA)
    return frame
