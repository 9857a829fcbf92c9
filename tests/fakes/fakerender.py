"""The camera of fakeworld.World: its model (CameraModel, look_at) and the ray caster behind `World.render`.

The scene is the table (the plane z = 0 of the robot base frame) and the world's boxes, cast per pixel with
a slab test, plus the checkerboard on the tool (if any) composited from checkerboard.py's view of it. Like
fakeworld, a top-level module: tests/fakes goes on sys.path, it is not a package. fakeworld re-exports
TABLE_RGB, CameraModel and look_at, so use them from there.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from romannet.common import heightmap

if TYPE_CHECKING:
    from fakeworld import Box, World

TABLE_RGB = (110, 100, 90)  # the colour checkerboard.py gives the table, so a board's blended edges match


@dataclass
class CameraModel:
    """The world's RGB-D camera: OpenCV frame, p_base = T_base_cam @ p_cam; depth and colour aligned."""

    serial: str = "fake-d435-0001"
    T_base_cam: list[list[float]] = field(default_factory=lambda: look_at((0.5, 0.0, 0.9), (0.5, 0.0, 0.0)))
    width: int = 640
    height: int = 480
    fx: float = 615.0
    fy: float = 615.0
    cx: float = 320.0
    cy: float = 240.0
    depth_scale: float = 0.001  # metres per z16 unit
    depth_error_scale: float = 1.0  # the device reports true depth / this (a calibration must find it)
    depth_noise_m: float = 0.0  # Gaussian, on every valid depth pixel
    connected: bool = True  # False: the device is unplugged (no device connected)
    timeout: bool = False  # True: wait_for_frames times out

    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


def look_at(eye, target, up=(1.0, 0.0, 0.0)) -> list[list[float]]:
    """T_base_cam (4x4, nested lists: the world's JSON form) of a camera at `eye` looking at `target`; `up`
    points to the image top (common.heightmap.look_at, the project's own)."""
    return heightmap.look_at(eye, target, up).tolist()


def render(world: World) -> tuple[np.ndarray, np.ndarray]:
    """`world.render()`: what its camera sees now, colour uint8 (H, W, 3) RGB and true depth_m float32 (H, W),
    0 = none. Uses the world's lock (to copy the scene), its per-camera ray cache and its noise generator."""
    cam = world.camera
    T = np.asarray(cam.T_base_cam, float)
    key = (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, T.tobytes())
    if world._rays is None or world._rays[0] != key:
        u, v = np.meshgrid(np.arange(cam.width, dtype=float), np.arange(cam.height, dtype=float))
        d_cam = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], axis=-1)
        world._rays = (key, d_cam @ T[:3, :3].T)  # base-frame directions with unit camera z: t is depth
    rays, origin = world._rays[1], T[:3, 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t_table = np.where(rays[..., 2] < 0, -origin[2] / rays[..., 2], np.inf)
    depth = np.where(t_table > 0, t_table, np.inf)
    color = np.zeros(depth.shape + (3,), np.float64)
    color[np.isfinite(depth)] = TABLE_RGB
    with world._lock:
        boxes = [dataclasses.replace(o) for o in world.objects]
        tcp, board = list(world.tcp_pose), world.board
    for box in boxes:
        _cast_box(cam, box, rays, origin, T, depth, color)
    depth = np.where(np.isfinite(depth), depth, 0.0)
    color = np.clip(np.rint(color), 0, 255).astype(np.uint8)
    if board:
        color, depth = _composite_board(cam, board, tcp, color, depth)
    depth = depth / cam.depth_error_scale
    if cam.depth_noise_m > 0:
        depth = np.where(depth > 0, depth + world._rng.normal(0.0, cam.depth_noise_m, depth.shape), 0.0)
    return color, depth.astype(np.float32)


def _cast_box(cam: CameraModel, box: Box, rays, origin, T, depth, color) -> None:
    """Slab test of one box against the rays of its image-space bounding rectangle; nearer hits win."""
    half = np.asarray(box.size_m) / 2
    c, s = math.cos(box.yaw_rad), math.sin(box.yaw_rad)
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # box -> base
    signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    p_cam = (np.asarray(box.center_m) + (signs * half) @ rot.T - T[:3, 3]) @ T[:3, :3]
    rows, cols = slice(None), slice(None)
    if np.all(p_cam[:, 2] > 1e-6):  # all corners in front: only the projected rectangle can be hit
        u = cam.fx * p_cam[:, 0] / p_cam[:, 2] + cam.cx
        v = cam.fy * p_cam[:, 1] / p_cam[:, 2] + cam.cy
        cols = slice(max(int(u.min()) - 1, 0), max(min(int(u.max()) + 2, cam.width), 0))
        rows = slice(max(int(v.min()) - 1, 0), max(min(int(v.max()) + 2, cam.height), 0))
    d = rays[rows, cols] @ rot  # ray directions in the box frame
    if d.size == 0:
        return
    o = rot.T @ (origin - np.asarray(box.center_m))
    d = np.where(np.abs(d) < 1e-12, 1e-12, d)
    t1, t2 = (-half - o) / d, (half - o) / d
    t_near, t_far = np.minimum(t1, t2), np.maximum(t1, t2)
    t_in, t_out = t_near.max(axis=-1), t_far.min(axis=-1)
    sub = depth[rows, cols]
    hit = (t_in <= t_out) & (t_in > 0) & (t_in < sub)
    face = t_near.argmax(axis=-1)  # the slab entered last is the face hit: z = top, shaded sides
    shade = np.choose(face, [0.75, 0.6, 1.0])
    sub[hit] = t_in[hit]
    color[rows, cols][hit] = (np.asarray(box.rgb, float) * shade[..., None])[hit]


def _composite_board(cam: CameraModel, board: dict, tcp, color, depth):
    """Overlay checkerboard.py's view of the board on the tool where it is nearer than the scene."""
    module = sys.modules.get("checkerboard")
    if module is None:
        spec = importlib.util.spec_from_file_location("checkerboard", Path(__file__).with_name("checkerboard.py"))
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        sys.modules["checkerboard"] = module
    extra = {k: v for k, v in board.items() if k not in ("board_offset_m", "pattern_corners", "square_m")}
    b_color, b_depth = module.render_board_view(
        np.asarray(cam.T_base_cam, float), cam.K(), (cam.height, cam.width), np.asarray(tcp, float),
        board["board_offset_m"], tuple(board["pattern_corners"]), board["square_m"],
        background_depth_m=0.0, **extra)
    touched = np.any(b_color != np.asarray(TABLE_RGB, np.uint8), axis=-1) | (b_depth > 0)
    nearer = (b_depth <= 0) | (depth <= 0) | (b_depth <= depth)
    mask = touched & nearer
    color = np.where(mask[..., None], b_color, color)
    depth = np.where(mask & (b_depth > 0), b_depth, depth)
    return color, depth
