"""The scene's statically mounted RGB-D camera: PyBullet's CPU renderer, made cheap without changing the image.

Why this module exists: ER_TINY_RENDERER shades every covered pixel (~0.25 us each here) and transforms every
vertex of every visible-or-not body. A frame of the table alone cost ~80 ms and the Panda's meshes another
~25 ms, although the table never changes and the arm at home is outside the view. So:

- The table is rendered once (`TableLayer`) and composited under every frame by depth test: a pixel keeps
  the rendered fragment where it is nearer than the table, else takes the table's colour and depth. The
  table is opaque, static and lit the same every frame, so this is the image a render with the table gives
  (objects below the table top stay hidden, as they would be).
- Bodies passed as `cull` (the robot) are hidden for the render when their every link's bounding box lies
  outside the view frustum: they could not have covered a pixel (frustum culling, conservative by a margin).

Frames: OpenCV camera frame (x right, y down, z forward); `T_world_cam` maps camera to world coordinates.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pybullet as p

from romannet.common.config import CameraConfig
from romannet.common.config_sim import SimConfig
from romannet.common.heightmap import look_at, vertical_fov_deg, zbuffer_to_depth

log = logging.getLogger(__name__)

CULL_MARGIN_PX = 4.0  # frustum planes pushed this far outside the image: culling stays conservative
_INVISIBLE = (0.0, 0.0, 0.0, 0.0)  # TinyRenderer skips fully transparent shapes (measured: as if removed)


@dataclass(frozen=True)
class Frame:
    """One camera capture: RGB uint8 (H, W, 3), metric depth float32 (H, W) along the camera z axis."""

    color: np.ndarray
    depth_m: np.ndarray


@dataclass(frozen=True)
class TableLayer:
    """What the camera sees of the table alone: RGB (H, W, 3) and the raw z-buffer (H, W), float32."""

    color: np.ndarray
    zbuf: np.ndarray


class Camera:
    """Renders client `client` through the configured pose and intrinsics; see the module docstring."""

    def __init__(self, client: int, cam: CameraConfig, sim: SimConfig):
        self.client, self.cam, self.sim = client, cam, sim
        # A PyBullet render has its principal point at the image centre, ((W-1)/2, (H-1)/2).
        self.intrinsics = np.array([[cam.fy_px, 0.0, (cam.width_px - 1) / 2.0],
                                    [0.0, cam.fy_px, (cam.height_px - 1) / 2.0],
                                    [0.0, 0.0, 1.0]])
        self.T_world_cam = look_at(np.array(sim.camera_eye_m), np.array(sim.camera_target_m),
                                   np.array(sim.camera_up))
        self._view = p.computeViewMatrix(sim.camera_eye_m, sim.camera_target_m, sim.camera_up,
                                         physicsClientId=client)
        self._proj = p.computeProjectionMatrixFOV(vertical_fov_deg(cam.fy_px, cam.height_px),
                                                  cam.width_px / cam.height_px, cam.near_m, cam.far_m,
                                                  physicsClientId=client)
        # Frustum side planes as slopes X/Z and Y/Z of the image borders (OpenCV camera frame).
        k, m = self.intrinsics, CULL_MARGIN_PX
        self._x_slopes = ((-0.5 - m - k[0, 2]) / k[0, 0], (cam.width_px - 0.5 + m - k[0, 2]) / k[0, 0])
        self._y_slopes = ((-0.5 - m - k[1, 2]) / k[1, 1], (cam.height_px - 0.5 + m - k[1, 2]) / k[1, 1])
        self._T_cam_world = np.linalg.inv(self.T_world_cam)
        self.table: TableLayer | None = None

    # ------------------------------------------------------------------------------------------ table
    def capture_table(self, half_extents_m: Sequence[float], centre_m: Sequence[float],
                      rgba: Sequence[float]) -> None:
        """Render a box (the table) alone in an otherwise empty client and keep it as the TableLayer.

        Call on an empty world: the box is a temporary visual-only body, removed again.
        """
        vis = p.createVisualShape(p.GEOM_BOX, halfExtents=list(half_extents_m), rgbaColor=list(rgba),
                                  physicsClientId=self.client)
        body = p.createMultiBody(0.0, -1, vis, list(centre_m), physicsClientId=self.client)
        rgb, zbuf = self._raw()
        p.removeBody(body, physicsClientId=self.client)
        self.table = TableLayer(rgb, zbuf)

    # ----------------------------------------------------------------------------------------- render
    def _raw(self) -> tuple[np.ndarray, np.ndarray]:
        """(RGB uint8 H x W x 3, z-buffer float32 H x W) of the client as it is."""
        cam = self.cam
        _, _, rgba, zbuf, _ = p.getCameraImage(cam.width_px, cam.height_px, self._view, self._proj,
                                               shadow=0, renderer=p.ER_TINY_RENDERER,
                                               flags=p.ER_NO_SEGMENTATION_MASK, physicsClientId=self.client)
        rgb = np.array(rgba, dtype=np.uint8).reshape(cam.height_px, cam.width_px, 4)[:, :, :3]
        return rgb, np.array(zbuf, dtype=np.float32).reshape(cam.height_px, cam.width_px)

    def outside_view(self, body_id: int) -> bool:
        """True when every link's world AABB of body_id lies entirely outside one side of the view frustum."""
        c = self.client
        links = range(-1, p.getNumJoints(body_id, physicsClientId=c))
        boxes = np.array([p.getAABB(body_id, link, physicsClientId=c) for link in links])  # (L, 2, 3)
        corners = np.stack([boxes[:, [i, j, k], [0, 1, 2]] for i in (0, 1) for j in (0, 1) for k in (0, 1)],
                           axis=1)  # (L, 8, 3)
        pts = corners @ self._T_cam_world[:3, :3].T + self._T_cam_world[:3, 3]
        x, y, z = pts[..., 0], pts[..., 1], pts[..., 2]
        outside = ((x < self._x_slopes[0] * z).all(axis=1) | (x > self._x_slopes[1] * z).all(axis=1)
                   | (y < self._y_slopes[0] * z).all(axis=1) | (y > self._y_slopes[1] * z).all(axis=1)
                   | (z < self.cam.near_m).all(axis=1))
        return bool(outside.all())

    def render(self, rng: np.random.Generator | None = None, cull: Sequence[int] = ()) -> Frame:
        """Capture the camera: colour, depth linearised from the z-buffer, Gaussian depth noise if configured.

        cull: bodies (the robot) hidden for this render when outside_view says they cannot be seen.
        rng: the episode's generator, required when sim.depth_noise_std_m > 0 (the noise is drawn from it,
        so a seed reproduces it).
        """
        if self.sim.depth_noise_std_m > 0.0 and rng is None:
            raise ValueError("depth noise is configured: render() needs the episode's rng")
        hidden = [b for b in cull if self.outside_view(b)]
        saved = [(b, d[1], d[7]) for b in hidden for d in p.getVisualShapeData(b, physicsClientId=self.client)]
        for body, link, _ in saved:
            p.changeVisualShape(body, link, rgbaColor=_INVISIBLE, physicsClientId=self.client)
        try:
            rgb, zbuf = self._raw()
        finally:
            for body, link, rgba in saved:
                p.changeVisualShape(body, link, rgbaColor=rgba, physicsClientId=self.client)
        if self.table is not None:
            behind = zbuf >= self.table.zbuf  # nothing drawn there in front of the table top
            np.copyto(rgb, self.table.color, where=behind[:, :, None])  # in place: both buffers are ours
            np.copyto(zbuf, self.table.zbuf, where=behind)
        depth = zbuffer_to_depth(zbuf, self.cam.near_m, self.cam.far_m)
        if self.sim.depth_noise_std_m > 0.0:
            assert rng is not None
            depth += rng.standard_normal(depth.shape, dtype=np.float32) * np.float32(self.sim.depth_noise_std_m)
        return Frame(np.ascontiguousarray(rgb), depth)
