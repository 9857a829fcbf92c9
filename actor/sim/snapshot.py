"""`write_snapshot`: the camera image and both heightmaps side by side in one PNG, for people to look at.

Layout (left to right): camera RGB (scaled to the heightmaps' display height), colour heightmap, depth
heightmap (colour-mapped, 0 .. 0.3 m). Heightmaps are shown 2x, robot x along columns, y along rows. An
action, if given, is drawn on both heightmaps: a circle at its pixel and a line along its angle (push: the
10 cm push; pick/place: the finger-closing axis).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import cv2
import numpy as np

from romannet.common.action import Action
from romannet.common.config import TaskConfig
from romannet.common.config_sim import SimConfig

from .env import SimEnv

log = logging.getLogger(__name__)

SCALE = 2  # heightmap display scale
DEPTH_DISPLAY_MAX_M = 0.3
ACTION_BGR = {"push": (0, 200, 255), "pick": (0, 255, 0), "place": (255, 0, 255)}


def _draw_action(img_bgr: np.ndarray, action: Action, length_px: float) -> None:
    c = (action.col * SCALE + SCALE // 2, action.row * SCALE + SCALE // 2)
    d = (math.cos(action.angle_rad), math.sin(action.angle_rad))
    color = ACTION_BGR[action.primitive]
    if action.primitive == "push":
        end = (round(c[0] + d[0] * length_px), round(c[1] + d[1] * length_px))
        cv2.arrowedLine(img_bgr, c, end, color, 2, tipLength=0.2)
    else:
        half = length_px / 2
        a = (round(c[0] - d[0] * half), round(c[1] - d[1] * half))
        b = (round(c[0] + d[0] * half), round(c[1] + d[1] * half))
        cv2.line(img_bgr, a, b, color, 2)
    cv2.circle(img_bgr, c, 5, color, 2)


def compose(env: SimEnv, action: Action | None = None) -> np.ndarray:
    """The side-by-side BGR image of env's current observation (uint8)."""
    obs = env.obs
    hm_h, hm_w = obs.depth_hm.shape
    color_hm = cv2.resize(cv2.cvtColor(obs.color_hm, cv2.COLOR_RGB2BGR), (hm_w * SCALE, hm_h * SCALE),
                          interpolation=cv2.INTER_NEAREST)
    depth_u8 = np.clip(obs.depth_hm / DEPTH_DISPLAY_MAX_M * 255.0, 0, 255).astype(np.uint8)
    depth = cv2.resize(cv2.applyColorMap(depth_u8, cv2.COLORMAP_VIRIDIS), (hm_w * SCALE, hm_h * SCALE),
                       interpolation=cv2.INTER_NEAREST)
    if action is not None:
        res = env.ws.resolution_m
        length = (env.sim.push_distance_m if action.primitive == "push" else 0.08) / res * SCALE
        for img in (color_hm, depth):
            _draw_action(img, action, length)
    cam = cv2.cvtColor(obs.camera_color, cv2.COLOR_RGB2BGR)
    cam_h = hm_h * SCALE
    cam = cv2.resize(cam, (round(cam.shape[1] * cam_h / cam.shape[0]), cam_h), interpolation=cv2.INTER_AREA)
    gap = np.full((cam_h, 8, 3), 255, np.uint8)
    return np.concatenate([cam, gap, color_hm, gap, depth], axis=1)


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
