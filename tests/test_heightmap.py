"""Heightmap geometry and stack measurement, checked on synthetic scenes whose answer is known.

Depth images are ray-cast analytically (pinhole camera onto a floor plane plus axis-aligned boxes), so every
expected height, footprint and occlusion shadow comes from geometry, not from the code under test.
"""

from __future__ import annotations

import numpy as np
import pytest

from romannet.common.action import pixel_to_position
from romannet.common.config import CameraConfig, WorkspaceConfig
from romannet.common.heightmap import (
    depth_to_points,
    get_heightmaps,
    look_at,
    vertical_fov_deg,
    zbuffer_to_depth,
)
from romannet.common.stack import stack_height

WS = WorkspaceConfig()
CAM = CameraConfig()
K = np.asarray(CAM.intrinsics)
FLOOR_RGB = (90, 90, 90)
BOX_RGB = (200, 30, 30)
# A box that does not line up with heightmap pixel edges, 10 cm tall.
BOX_MIN = np.array([0.4513, -0.0611, 0.0])
BOX_MAX = np.array([0.5297, 0.0203, 0.10])
STRAIGHT_DOWN = look_at((0.5, 0.0, 0.75), (0.5, 0.0, 0.0), up=(-1.0, 0.0, 0.0))
TILTED = look_at((0.25, 0.15, 0.55), (0.5, 0.0, 0.0), up=(0.0, 0.0, 1.0))


# ---------------------------------------------------------------- analytic ray-caster (test helper)

def _ray_box(origin: np.ndarray, dirs: np.ndarray, bmin: np.ndarray, bmax: np.ndarray) -> np.ndarray:
    """Ray parameter of the first hit of rays origin + t*dirs with an axis-aligned box (inf: miss)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (bmin - origin) / dirs
        t2 = (bmax - origin) / dirs
    t_near = np.nanmax(np.minimum(t1, t2), axis=-1)
    t_far = np.nanmin(np.maximum(t1, t2), axis=-1)
    hit = (t_near <= t_far) & (t_near > 0)
    return np.where(hit, t_near, np.inf)


def render(T_world_cam: np.ndarray, boxes: list[tuple[np.ndarray, np.ndarray]], floor_z: float = 0.0):
    """Colour (RGB uint8) and depth (m along camera z) of the floor plane plus boxes, seen by CAM."""
    v, u = np.mgrid[0:CAM.height_px, 0:CAM.width_px].astype(np.float64)
    rays_cam = np.stack([(u - CAM.cx_px) / CAM.fx_px, (v - CAM.cy_px) / CAM.fy_px, np.ones_like(u)], axis=-1)
    dirs = rays_cam @ T_world_cam[:3, :3].T  # camera-z component 1, so the ray parameter is the depth
    origin = T_world_cam[:3, 3]
    with np.errstate(divide="ignore"):
        t_floor = (floor_z - origin[2]) / dirs[..., 2]
    depth = np.where(t_floor > 0, t_floor, np.inf)
    color = np.zeros((*depth.shape, 3), np.uint8)
    color[np.isfinite(depth)] = FLOOR_RGB
    for bmin, bmax in boxes:
        t_box = _ray_box(origin, dirs, bmin, bmax)
        closer = t_box < depth
        depth[closer] = t_box[closer]
        color[closer] = BOX_RGB
    depth[~np.isfinite(depth)] = 0.0  # no return, as a real sensor reports it
    return color, depth.astype(np.float32)


def _pixel_samples(ws: WorkspaceConfig) -> np.ndarray:
    """World x, y of each heightmap pixel's centre and 4 corners (inset 1 %): h x w x 5 x 2."""
    res = ws.resolution_m
    offsets = np.array([[0.5, 0.5], [0.01, 0.01], [0.99, 0.01], [0.01, 0.99], [0.99, 0.99]]) * res
    rows, cols = np.mgrid[0:ws.height_px, 0:ws.width_px]
    corner = np.stack([cols * res + ws.x_min_m, rows * res + ws.y_min_m], axis=-1)
    return corner[:, :, None, :] + offsets


def _floor_visible(T_world_cam: np.ndarray, xy: np.ndarray, bmin: np.ndarray, bmax: np.ndarray) -> np.ndarray:
    """Whether floor points (..., 2) project into the image and are not hidden by the box."""
    pts = np.concatenate([xy, np.zeros((*xy.shape[:-1], 1))], axis=-1)
    cam = (pts - T_world_cam[:3, 3]) @ T_world_cam[:3, :3]
    u = CAM.fx_px * cam[..., 0] / cam[..., 2] + CAM.cx_px
    v = CAM.fy_px * cam[..., 1] / cam[..., 2] + CAM.cy_px
    in_image = (cam[..., 2] > 0) & (u > 0) & (u < CAM.width_px - 1) & (v > 0) & (v < CAM.height_px - 1)
    t_box = _ray_box(T_world_cam[:3, 3], pts - T_world_cam[:3, 3], bmin, bmax)  # t = 1 at the floor point
    return in_image & (t_box > 1.0 - 1e-9)


def _footprint_masks(ws: WorkspaceConfig, bmin: np.ndarray, bmax: np.ndarray, margin_px: int = 1):
    """(inside, outside): pixels fully inside the box footprint shrunk by margin_px, and pixels clear of it
    grown by margin_px: the +-1 px tolerance on where the box's edges land."""
    res = ws.resolution_m
    x0 = ws.x_min_m + np.arange(ws.width_px) * res
    y0 = ws.y_min_m + np.arange(ws.height_px) * res
    m = margin_px * res
    in_x = (x0 >= bmin[0] + m) & (x0 + res <= bmax[0] - m)
    in_y = (y0 >= bmin[1] + m) & (y0 + res <= bmax[1] - m)
    out_x = (x0 + res <= bmin[0] - m) | (x0 >= bmax[0] + m)
    out_y = (y0 + res <= bmin[1] - m) | (y0 >= bmax[1] + m)
    return in_y[:, None] & in_x[None, :], out_y[:, None] | out_x[None, :]


# ---------------------------------------------------------------- heightmaps

def test_default_geometry_shapes_and_dtypes():
    color, depth = render(STRAIGHT_DOWN, [])
    assert color.shape == (480, 640, 3) and depth.shape == (480, 640)
    color_hm, depth_hm = get_heightmaps(color, depth, K, STRAIGHT_DOWN, WS)
    assert (WS.height_px, WS.width_px) == (224, 224)
    assert color_hm.shape == (224, 224, 3) and color_hm.dtype == np.uint8
    assert depth_hm.shape == (224, 224) and depth_hm.dtype == np.float32


@pytest.mark.parametrize("pose", [STRAIGHT_DOWN, TILTED], ids=["straight_down", "tilted"])
def test_box_reads_its_height_on_its_footprint(pose):
    color, depth = render(pose, [(BOX_MIN, BOX_MAX)])
    color_hm, depth_hm = get_heightmaps(color, depth, K, pose, WS)
    inside, outside = _footprint_masks(WS, BOX_MIN, BOX_MAX)
    assert inside.sum() > 30 * 30
    np.testing.assert_allclose(depth_hm[inside], BOX_MAX[2], atol=0.002)
    assert np.all(color_hm[inside] == BOX_RGB)
    # Off the footprint: floor (~0) or unseen (exactly 0) -- never part of the box.
    assert np.all(depth_hm[outside] < 0.002)
    visible = _floor_visible(pose, _pixel_samples(WS), BOX_MIN, BOX_MAX)
    seen, unseen = visible.all(axis=-1) & outside, ~visible.any(axis=-1) & outside
    assert seen.sum() > 0.8 * WS.height_px * WS.width_px
    assert np.all(color_hm[seen] == FLOOR_RGB)
    assert np.all(depth_hm[unseen] == 0) and np.all(color_hm[unseen] == 0)
    if pose is TILTED:
        assert unseen.sum() > 100  # the box's shadow: the test really exercises occlusion


def test_floor_below_z_min_and_objects_outside_workspace_are_dropped():
    # A tall box just outside the x limits and one beyond the far y edge: none of it may land in the map.
    outside_boxes = [(np.array([0.20, -0.05, 0.0]), np.array([WS.x_min_m - 1e-4, 0.05, 0.2])),
                     (np.array([0.45, WS.y_max_m + 1e-4, 0.0]), np.array([0.55, 0.30, 0.2]))]
    color, depth = render(TILTED, outside_boxes)
    _, depth_hm = get_heightmaps(color, depth, K, TILTED, WS)
    assert depth_hm.max() < 0.002
    # The same floor 3 cm below z_min: beyond floor_tolerance_m, so nothing is seen at all.
    color, depth = render(STRAIGHT_DOWN, [], floor_z=-0.03)
    color_hm, depth_hm = get_heightmaps(color, depth, K, STRAIGHT_DOWN, WS)
    assert not depth_hm.any() and not color_hm.any()
    # 3 mm below z_min (sensor noise on the floor): kept, as height 0 with the floor's colour.
    color, depth = render(STRAIGHT_DOWN, [], floor_z=-0.003)
    color_hm, depth_hm = get_heightmaps(color, depth, K, STRAIGHT_DOWN, WS)
    assert not depth_hm.any() and np.all(color_hm == FLOOR_RGB)


def test_points_above_z_max_are_dropped():
    ws = WorkspaceConfig(z_max_m=0.06)
    color, depth = render(STRAIGHT_DOWN, [(BOX_MIN, BOX_MAX)])
    color_hm, depth_hm = get_heightmaps(color, depth, K, STRAIGHT_DOWN, ws)
    inside, _ = _footprint_masks(ws, BOX_MIN, BOX_MAX)
    assert depth_hm.max() <= 0.06
    assert not depth_hm[inside].any() and not color_hm[inside].any()  # the top at 0.10 m is gone


def test_invalid_depth_is_ignored():
    color, depth = render(STRAIGHT_DOWN, [(BOX_MIN, BOX_MAX)])
    ref_color_hm, ref_depth_hm = get_heightmaps(color, depth, K, STRAIGHT_DOWN, WS)
    rng = np.random.default_rng(0)
    corrupt = depth.copy()
    idx = rng.choice(corrupt.size, size=2000, replace=False)
    corrupt.flat[idx] = np.array([0.0, np.nan, np.inf, -np.inf, -0.5], np.float32)[np.arange(2000) % 5]
    color_hm, depth_hm = get_heightmaps(color, corrupt, K, STRAIGHT_DOWN, WS)
    assert np.all(np.isfinite(depth_hm)) and depth_hm.min() >= 0
    # 2000 of 307200 readings lost: a pixel may only change by losing all its points (becoming empty),
    # never by gaining something from an invalid reading.
    changed = (depth_hm != ref_depth_hm) | np.any(color_hm != ref_color_hm, axis=-1)
    assert changed.sum() < 0.002 * changed.size
    assert not depth_hm[changed].any() and not color_hm[changed].any()
    all_bad = np.full_like(depth, np.nan)
    color_hm, depth_hm = get_heightmaps(color, all_bad, K, STRAIGHT_DOWN, WS)
    assert not depth_hm.any() and not color_hm.any()


@pytest.mark.parametrize("high_first", [True, False])
def test_highest_point_wins_with_its_colour(high_first):
    # Two image pixels whose rays are 5 um apart at 0.5 m (fx = 1e5), both inside one heightmap pixel.
    k = np.array([[1e5, 0.0, 0.5], [0.0, 1e5, 0.0], [0.0, 0.0, 1.0]])
    row, col = 100, 60
    x, y, _ = pixel_to_position(row, col, np.zeros((WS.height_px, WS.width_px)), WS)
    pose = look_at((x + 0.001, y + 0.001, 0.5), (x + 0.001, y + 0.001, 0.0), up=(-1.0, 0.0, 0.0))
    depth = np.array([[0.5 - 0.03, 0.5 - 0.08]], np.float32)  # heights 3 cm and 8 cm
    color = np.array([[[10, 20, 30], [200, 100, 50]]], np.uint8)
    if not high_first:
        depth, color = depth[:, ::-1].copy(), color[:, ::-1].copy()
    color_hm, depth_hm = get_heightmaps(color, depth, k, pose, WS)
    assert depth_hm[row, col] == pytest.approx(0.08, abs=1e-5)
    assert tuple(color_hm[row, col]) == (200, 100, 50)
    assert np.count_nonzero(depth_hm) == 1


def test_matches_a_per_point_reference_on_random_clouds():
    # Coarse camera pixels and a fine heightmap-sized cloud: many points per heightmap pixel, many ties to
    # break, checked against the obvious loop over points.
    rng = np.random.default_rng(7)
    ws = WorkspaceConfig(x_min_m=0.4, x_max_m=0.424, y_min_m=-0.012, y_max_m=0.012)
    k = np.array([[900.0, 0.0, 30.0], [0.0, 900.0, 20.0], [0.0, 0.0, 1.0]])
    pose = look_at((0.41, 0.002, 0.6), (0.412, 0.0, 0.0), up=(-1.0, 0.2, 0.0))
    depth = rng.uniform(0.45, 0.62, (40, 60)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.05] = np.nan
    color = rng.integers(0, 256, (40, 60, 3), dtype=np.uint8)
    color_hm, depth_hm = get_heightmaps(color, depth, k, pose, ws)

    pts = depth_to_points(depth, k).reshape(-1, 3).astype(np.float64) @ pose[:3, :3].T + pose[:3, 3]
    want_depth = np.zeros((ws.height_px, ws.width_px))
    want_color = np.zeros((ws.height_px, ws.width_px, 3), np.uint8)
    for (x, y, z), rgb in zip(pts, color.reshape(-1, 3), strict=True):
        if not np.isfinite(z) or not -0.01 <= z <= ws.z_max_m:
            continue
        r, c = int(np.floor((y - ws.y_min_m) / ws.resolution_m)), int(np.floor((x - ws.x_min_m) / ws.resolution_m))
        if 0 <= r < ws.height_px and 0 <= c < ws.width_px and max(z, 0.0) >= want_depth[r, c]:
            if max(z, 0.0) > want_depth[r, c] or tuple(rgb) > tuple(want_color[r, c]):
                want_depth[r, c], want_color[r, c] = max(z, 0.0), rgb
    assert np.count_nonzero(want_depth) > 100
    np.testing.assert_allclose(depth_hm, want_depth, atol=1e-5)
    assert np.array_equal(color_hm, want_color)


def test_heightmap_pixel_matches_action_pixel_to_position():
    # A point just inside pixel (row, col)'s far corner lands in that pixel: binning is floor, and
    # pixel_to_position returns the pixel's (x_min, y_min) corner, so the two agree.
    row, col = 37, 150
    x, y, _ = pixel_to_position(row, col, np.zeros((WS.height_px, WS.width_px)), WS)
    for dx, dy in [(0.0002, 0.0002), (0.0018, 0.0018)]:
        pose = look_at((x + dx, y + dy, 0.5), (x + dx, y + dy, 0.0), up=(-1.0, 0.0, 0.0))
        k = np.array([[500.0, 0.0, 0.0], [0.0, 500.0, 0.0], [0.0, 0.0, 1.0]])
        _, depth_hm = get_heightmaps(np.full((1, 1, 3), 255, np.uint8), np.array([[0.45]], np.float32), k, pose, WS)
        assert np.argwhere(depth_hm).tolist() == [[row, col]]


def test_depth_to_points_pinhole():
    depth = np.full((480, 640), 2.0, np.float32)
    depth[0, 0] = 0.0
    pts = depth_to_points(depth, K)
    assert pts.shape == (480, 640, 3) and pts.dtype == np.float32
    np.testing.assert_allclose(pts[240, 320], [0.0, 0.0, 2.0])
    np.testing.assert_allclose(pts[480 - 1, 640 - 1], [2.0 * 319 / 618.62, 2.0 * 239 / 618.62, 2.0], rtol=1e-6)
    assert np.all(np.isnan(pts[0, 0]))
    with pytest.raises(ValueError):
        depth_to_points(depth, np.eye(2))


def test_look_at_is_an_opencv_camera():
    pose = look_at((0.2, 0.1, 0.6), (0.5, 0.0, 0.0), up=(0.0, 0.0, 1.0))
    rot = pose[:3, :3]
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
    assert np.linalg.det(rot) == pytest.approx(1.0)
    target_cam = np.linalg.inv(pose) @ np.array([0.5, 0.0, 0.0, 1.0])
    np.testing.assert_allclose(target_cam[:2], 0.0, atol=1e-12)  # target on the optical axis
    assert rot[2, 1] < 0  # camera +y (image down) points to world -z: world up is up in the image
    with pytest.raises(ValueError):
        look_at((0.5, 0.0, 0.7), (0.5, 0.0, 0.0), up=(0.0, 0.0, 1.0))


def test_zbuffer_to_depth_inverts_the_opengl_projection():
    near, far = 0.01, 10.0
    depth_m = np.array([near, 0.3, 0.75, 2.0, far])
    ndc = (far + near) / (far - near) - 2.0 * far * near / ((far - near) * depth_m)
    zbuf = (ndc + 1.0) / 2.0
    np.testing.assert_allclose(zbuffer_to_depth(zbuf, near, far), depth_m, rtol=1e-5)
    assert zbuffer_to_depth(zbuf, near, far).dtype == np.float32
    with pytest.raises(ValueError):
        zbuffer_to_depth(zbuf, far, near)


def test_pybullet_render_round_trip():
    """The chain the sim uses: computeViewMatrix(eye, target, up) + look_at(eye, target, up)."""
    p = pytest.importorskip("pybullet")
    eye, target, up = (0.3, 0.12, 0.6), (0.5, 0.0, 0.0), (0.0, 0.0, 1.0)
    client = p.connect(p.DIRECT)
    try:
        floor = p.createVisualShape(p.GEOM_BOX, halfExtents=[1, 1, 0.01], rgbaColor=[0.4, 0.4, 0.4, 1],
                                    physicsClientId=client)
        p.createMultiBody(baseVisualShapeIndex=floor, basePosition=[0.5, 0, -0.01], physicsClientId=client)
        half = (BOX_MAX - BOX_MIN) / 2
        box = p.createVisualShape(p.GEOM_BOX, halfExtents=half.tolist(), rgbaColor=[0.8, 0.1, 0.1, 1],
                                  physicsClientId=client)
        p.createMultiBody(baseVisualShapeIndex=box, basePosition=(BOX_MIN + half).tolist(), physicsClientId=client)
        view = p.computeViewMatrix(eye, target, up)
        proj = p.computeProjectionMatrixFOV(vertical_fov_deg(CAM.fy_px, CAM.height_px),
                                            CAM.width_px / CAM.height_px, CAM.near_m, CAM.far_m)
        _, _, rgba, zbuf, _ = p.getCameraImage(CAM.width_px, CAM.height_px, view, proj,
                                               renderer=p.ER_TINY_RENDERER, physicsClientId=client)
    finally:
        p.disconnect(client)
    rgb = np.reshape(np.asarray(rgba, np.uint8), (CAM.height_px, CAM.width_px, 4))[..., :3].copy()
    depth = zbuffer_to_depth(np.reshape(zbuf, (CAM.height_px, CAM.width_px)), CAM.near_m, CAM.far_m)
    # OpenGL puts the optical axis at the image centre, (W - 1) / 2 in pixel-index coordinates; with the
    # default cx = 320 the map shifts by half a camera pixel (~0.5 mm here), inside the +-1 px tolerance.
    k_gl = K.copy()
    k_gl[:2, 2] = (CAM.width_px - 1) / 2, (CAM.height_px - 1) / 2
    _, depth_hm = get_heightmaps(rgb, depth, k_gl, look_at(eye, target, up), WS)
    inside, outside = _footprint_masks(WS, BOX_MIN, BOX_MAX)
    np.testing.assert_allclose(depth_hm[inside], BOX_MAX[2], atol=0.002)
    assert np.all(depth_hm[outside] < 0.002)


# ---------------------------------------------------------------- stack height and occupancy

def _stack_scene(k: int, seed: int) -> np.ndarray:
    """Floor noise, loose single cubes, a k-cube stack (50 mm = 25 px squares) and speckle outliers."""
    rng = np.random.default_rng(seed)
    hm = np.abs(rng.normal(0.0, 0.001, (224, 224))).astype(np.float32)
    for r, c in [(20, 20), (20, 150), (170, 40)]:  # loose cubes on the floor
        hm[r:r + 25, c:c + 25] = 0.05 + rng.normal(0.0, 0.002, (25, 25))
    if k:
        hm[100:125, 110:135] = k * 0.05 + rng.normal(0.0, 0.003, (25, 25))
    spikes = rng.integers(0, 224, (8, 2))
    hm[spikes[:, 0], spikes[:, 1]] = 0.35  # speckle: taller than any stack
    hm[200:202, 200:202] = 0.35  # a 2x2 flying-pixel cluster
    return hm


@pytest.mark.parametrize("k", [1, 2, 3, 4, 5])
def test_stack_height_counts_cubes(k):
    assert stack_height(_stack_scene(k, seed=k)) == k


def test_stack_height_5_is_not_capped():
    hm = np.zeros((224, 224), np.float32)
    hm[100:125, 100:125] = 0.25
    assert stack_height(hm) == 5


def test_stack_height_empty_and_spike():
    hm = np.abs(np.random.default_rng(1).normal(0.0, 0.001, (224, 224))).astype(np.float32)
    assert stack_height(hm) == 0
    hm[50, 60] = 0.3  # one flying pixel is not a stack
    assert stack_height(hm) == 0
    hm[70, 80] = np.nan
    assert stack_height(hm) == 0
    with pytest.raises(ValueError):
        stack_height(hm, median_ksize=7)

