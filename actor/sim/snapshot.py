"""`write_snapshot`: the camera image and both heightmaps side by side in one PNG, for people to look at.

Panels (left to right, each titled): the camera image turned to the heightmaps' orientation, the colour
heightmap and the depth heightmap (colour-mapped 0 .. 0.3 m above the table, with its colour bar), both
seen from above with world x to the right and y up (common.pictures). An action, if given in the
heightmap's (row, col, angle), is drawn on both heightmaps: a ring at its pixel and an arrow of the push
length (push) or the gripper's opening across the fingers (pick/place); the margin around each heightmap
keeps an action at the workspace's edge whole.
"""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np

from romannet.common.action import Action
from romannet.common.config import TaskConfig
from romannet.common.config_sim import SimConfig
from romannet.common.pictures import (
    DEPTH_DISPLAY_MAX_M,
    ActionGlyph,
    camera_turns,
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

from .env import SimEnv

log = logging.getLogger(__name__)

SCALE = 2  # heightmap display scale


def lengths_px(sim: SimConfig, resolution_m: float) -> tuple[float, float]:
    """The push length and the hand's full opening, in heightmap pixels."""
    return sim.push_distance_m / resolution_m, 2 * sim.finger_travel_m / resolution_m


def compose(env: SimEnv, action: Action | None = None) -> np.ndarray:
    """The titled side-by-side BGR image of env's current observation (uint8)."""
    obs = env.obs
    inner = obs.depth_hm.shape[0] * SCALE
    push_px, gripper_px = lengths_px(env.sim, env.ws.resolution_m)
    margin = margin_px(push_px, gripper_px, SCALE, inner)  # the same for every action: one layout
    height = inner + 2 * margin
    glyph = None if action is None else ActionGlyph(action.primitive, action.row, action.col, action.angle_rad,
                                                    push_px, gripper_px)
    color = heightmap_panel(cv2.cvtColor(obs.color_hm, cv2.COLOR_RGB2BGR), height, glyph, margin)
    depth = heightmap_panel(depth_colormap(obs.depth_hm), height, glyph, margin)
    cam = turn_camera(cv2.cvtColor(obs.camera_color, cv2.COLOR_RGB2BGR), camera_turns(env.scene.T_world_cam))
    cam = with_margin(resize(cam, inner, nearest=False), margin)
    bar = colorbar(height, cv2.COLORMAP_VIRIDIS, 0.0, DEPTH_DISPLAY_MAX_M, "height m", ticks=6)
    return side_by_side([titled(cam, "camera, turned to the heightmaps' view"),
                         titled(color, "colour heightmap, from above (x right, y up)"),
                         titled(side_by_side([depth, bar], gap=0), "depth heightmap (height above the table)")])


def write_snapshot(task: str, seed: int, out_png: str | Path, action: Action | None = None,
                   sim: SimConfig | None = None) -> Path:
    """Build task `task` ("clutter" | "arrangement" | "stacking") from `seed` and write its snapshot PNG."""
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    with SimEnv(task=TaskConfig(kind=task), sim=sim or SimConfig()) as env:
        env.reset(seed)
        image = compose(env, action)
    if not cv2.imwrite(str(out), image):
        raise OSError(f"could not write {out}")
    log.info("snapshot of %s seed %d -> %s", task, seed, out)
    return out
