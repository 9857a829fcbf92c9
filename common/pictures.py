"""Drawing blocks shared by the pictures made for people (`romannet sim snapshot`, `romannet mcap export`).

One orientation everywhere: heightmaps are drawn as seen from above, world +x to the right and +y up (the
arrays' row 0 is y_min, so rows are drawn bottom-up), and the camera image is turned by the quarter turns
that bring its view to the same orientation (`camera_turns`, from the camera's pose; a camera looking down
needs a rotation, never a mirror). Actions are given in the arrays' (row, col, angle) (common.action: angle
0 along +col, positive toward +row) and drawn where they are in that view, so a positive angle turns
counter-clockwise like a yaw. Panels get a title bar, and a margin around heightmaps so an action at the
edge of the workspace is still drawn whole. Pure functions of arrays, BGR uint8 images.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

ACTION_BGR = {"push": (0, 200, 255), "pick": (0, 255, 0), "place": (255, 0, 255)}
TEXT_BGR, BACKGROUND_BGR, MARGIN_BGR = (235, 235, 235), (24, 24, 24), (48, 48, 48)
DEPTH_DISPLAY_MAX_M = 0.3
TITLE_PX = 28
_FONT = cv2.FONT_HERSHEY_SIMPLEX


def top_view(heightmap: np.ndarray) -> np.ndarray:
    """A heightmap array as seen from above: +x right, +y up (its rows drawn bottom-up)."""
    return np.ascontiguousarray(heightmap[::-1])


def camera_turns(T_world_cam: np.ndarray) -> int:
    """Counter-clockwise quarter turns (np.rot90's k) that bring a camera image to the top view: the one
    that sends the image's right (camera +x) nearest to the world direction it has in the top view."""
    right = np.asarray(T_world_cam, dtype=float)[:2, 0]  # camera +x in world x, y
    angle = math.atan2(right[1], right[0])  # counter-clockwise from +x, as the top view shows it
    return int(round(angle / (math.pi / 2))) % 4


def turn_camera(image: np.ndarray, turns: int) -> np.ndarray:
    return np.ascontiguousarray(np.rot90(image, turns))


def depth_colormap(depth_m: np.ndarray, max_m: float = DEPTH_DISPLAY_MAX_M) -> np.ndarray:
    """BGR uint8 of heights or depths, 0..max_m metres (VIRIDIS)."""
    depth_u8 = np.clip(np.nan_to_num(depth_m) / max_m * 255.0, 0, 255).astype(np.uint8)
    return cv2.applyColorMap(depth_u8, cv2.COLORMAP_VIRIDIS)


def resize(img: np.ndarray, height: int, nearest: bool) -> np.ndarray:
    """`img` scaled to `height` rows, aspect kept."""
    width = max(1, round(img.shape[1] * height / img.shape[0]))
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)


def titled(panel: np.ndarray, title: str) -> np.ndarray:
    """The panel under a title bar."""
    bar = np.full((TITLE_PX, panel.shape[1], 3), BACKGROUND_BGR, np.uint8)
    cv2.putText(bar, title, (6, TITLE_PX - 9), _FONT, 0.5, TEXT_BGR, 1, cv2.LINE_AA)
    return np.concatenate([bar, panel], axis=0)


def with_margin(panel: np.ndarray, margin: int) -> np.ndarray:
    return cv2.copyMakeBorder(panel, margin, margin, margin, margin, cv2.BORDER_CONSTANT, value=MARGIN_BGR)


def colorbar(height: int, colormap: int, lo: float, hi: float, label: str, ticks: int = 4) -> np.ndarray:
    """A vertical colour bar (hi at the top) with `ticks` + 1 labelled values and a label on top, BGR."""
    step = (hi - lo) / ticks
    values = [v if abs(v) > 1e-9 * abs(step) else 0.0 for v in (hi - i * step for i in range(ticks + 1))]
    labels = tick_labels(values)
    text_w = max(64, *(cv2.getTextSize(t, _FONT, 0.4, 1)[0][0] + 4 for t in labels))
    bar_w, top, bottom = 16, 22, 10
    panel = np.full((height, bar_w + text_w + 8, 3), BACKGROUND_BGR, np.uint8)
    span = height - top - bottom
    ramp = np.linspace(255, 0, span).astype(np.uint8)[:, None].repeat(bar_w, axis=1)
    panel[top:top + span, 4:4 + bar_w] = cv2.applyColorMap(ramp, colormap)
    cv2.putText(panel, label, (2, 14), _FONT, 0.42, TEXT_BGR, 1, cv2.LINE_AA)
    for i, text in enumerate(labels):
        y = top + round(i * (span - 1) / ticks)
        cv2.line(panel, (4 + bar_w, y), (8 + bar_w, y), TEXT_BGR, 1)
        cv2.putText(panel, text, (12 + bar_w, y + 4), _FONT, 0.4, TEXT_BGR, 1, cv2.LINE_AA)
    return panel


def tick_labels(values: list[float], most_extra_digits: int = 4) -> list[str]:
    """Labels of the values with the fewest digits that keep different values apart: a Q map's range can
    be a few thousandths of its values, where 3 significant digits label every tick alike."""
    for extra in range(most_extra_digits + 1):
        labels = [_tick(v, extra) for v in values]
        if len(set(labels)) == len(set(values)):
            break
    return labels


def side_by_side(panels: list[np.ndarray], gap: int = 8) -> np.ndarray:
    """Panels left to right, top-aligned on the background colour."""
    height = max(p.shape[0] for p in panels)
    spacer = np.full((height, gap, 3), BACKGROUND_BGR, np.uint8)
    cols = []
    for i, p in enumerate(panels):
        if p.shape[0] < height:
            p = np.concatenate([p, np.full((height - p.shape[0], p.shape[1], 3), BACKGROUND_BGR, np.uint8)])
        cols += [spacer, p] if i else [p]
    return np.concatenate(cols, axis=1)


@dataclass(frozen=True)
class ActionGlyph:
    """An action to draw on a top-view heightmap panel; lengths in heightmap pixels."""

    primitive: str
    row: int
    col: int
    angle_rad: float
    push_length_px: float
    gripper_width_px: float


def margin_px(push_length_px: float, gripper_width_px: float, scale: float, inner_px: int) -> int:
    """Room around a heightmap drawn `scale` times its size for any action at its edge to be drawn whole
    (the longer of the push arrow and half the gripper bar with its fingers), at most a third of it."""
    half_bar = math.hypot(gripper_width_px / 2, max(4.0 / scale, gripper_width_px / 6))
    return min(math.ceil(max(push_length_px, half_bar) * scale) + 8, inner_px // 3)


def _tick(value: float, extra_digits: int = 0) -> str:
    return f"{value:.{1 + extra_digits}e}" if 0 < abs(value) < 0.01 else f"{value:.{3 + extra_digits}g}"


def draw_action(img: np.ndarray, glyph: ActionGlyph, hm_rows: int, scale: float, offset: int) -> None:
    """The action on a top-view panel (in place): the heightmap of `hm_rows` rows drawn `scale` times its
    size, `offset` px inside the image (its margin). Push: an arrow of the push length; pick/place: the
    finger-closing axis the gripper's opening wide, with the fingers across its ends; a ring at the pixel."""
    c = np.array([(glyph.col + 0.5) * scale + offset, (hm_rows - glyph.row - 0.5) * scale + offset])
    d = np.array([math.cos(glyph.angle_rad), -math.sin(glyph.angle_rad)])  # rows drawn bottom-up
    color = ACTION_BGR.get(glyph.primitive, TEXT_BGR)
    thick = min(3, max(2, round(scale)))  # lines stay thin on a panel drawn many times its size

    def pt(v: np.ndarray) -> tuple[int, int]:
        return int(round(v[0])), int(round(v[1]))

    if glyph.primitive == "push":
        cv2.arrowedLine(img, pt(c), pt(c + d * glyph.push_length_px * scale), color, thick, cv2.LINE_AA,
                        tipLength=0.25)
    else:
        half = d * glyph.gripper_width_px * scale / 2
        normal = np.array([-d[1], d[0]]) * max(4.0, glyph.gripper_width_px * scale / 6)
        cv2.line(img, pt(c - half), pt(c + half), color, thick, cv2.LINE_AA)
        for end in (c - half, c + half):
            cv2.line(img, pt(end - normal), pt(end + normal), color, thick + 1, cv2.LINE_AA)
    cv2.circle(img, pt(c), max(5, thick * 3), (0, 0, 0), thick + 2, cv2.LINE_AA)  # dark rim: seen on any colour
    cv2.circle(img, pt(c), max(5, thick * 3), color, thick, cv2.LINE_AA)


def heightmap_panel(image: np.ndarray, height_px: int, glyph: ActionGlyph | None, margin: int) -> np.ndarray:
    """A heightmap image (array orientation) as a top-view panel `height_px` tall (margin included), the
    action drawn on it."""
    inner = height_px - 2 * margin
    scale = inner / image.shape[0]
    panel = with_margin(resize(top_view(image), inner, nearest=True), margin)
    if glyph is not None:
        draw_action(panel, glyph, image.shape[0], scale, margin)
    return panel
