"""A synthetic RGB-D view of a checkerboard held by the robot's tool: pure numpy ray casting, no simulator.

Used by the calibration tests, and by fake camera drivers that want a board in view. Keep the signature of
`render_board_view` stable.

Frames and conventions (those of common/heightmap.py)
- Camera: OpenCV frame (x right, y down, z forward); pixel (row v, col u) centres at integer (u, v);
  `T_base_cam` is the camera pose in the robot base frame: p_base = T_base_cam @ p_cam.
- TCP pose: UR style (x, y, z, rx, ry, rz) in the base frame, metres and a rotation vector.
- Board frame: origin at the board centre, `board_offset_m` in the TCP frame, axes parallel to the TCP's.
  The board is the plane z = 0 of that frame (the TCP x-y plane), seen from both sides. The pattern has
  (cols + 1) x (rows + 1) squares for `pattern_corners` = (cols, rows) inner corners, columns along board
  x, centred on the board centre (so the centre of the inner-corner grid is the board centre), the square
  at the (-x, -y) corner dark, and a white border one square wide around it.
"""

from __future__ import annotations

import numpy as np

_DARK = np.array([25, 25, 25], dtype=np.float64)
_LIGHT = np.array([235, 235, 235], dtype=np.float64)
_TABLE = np.array([110, 100, 90], dtype=np.float64)


def pose_to_matrix(pose: np.ndarray) -> np.ndarray:
    """4x4 T_base_tcp of a UR pose (x, y, z metres, rotation vector rx, ry, rz), by Rodrigues' formula."""
    pose = np.asarray(pose, dtype=np.float64)
    rotvec = pose[3:6]
    angle = float(np.linalg.norm(rotvec))
    rot = np.eye(3)
    if angle > 1e-12:
        k = rotvec / angle
        kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
        rot = np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * (kx @ kx)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rot, pose[:3]
    return out


def _plane_to_pixel_inverse(T_cam_plane: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """Inverse of the homography K [r1 r2 t] that maps plane points (a, b, 1) to pixels.

    Applied to (u, v, 1) it gives (a, b, 1) / z, with z the depth along the camera axis of the plane point
    seen at that pixel: a third component <= 0 means the plane is behind the camera there.
    """
    h = intrinsics @ np.column_stack([T_cam_plane[:3, 0], T_cam_plane[:3, 1], T_cam_plane[:3, 3]])
    return np.linalg.inv(h)


def _cast(h_inv: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plane coordinates (a, b) and camera depth z (inf where the plane is behind or edge-on) per pixel."""
    (h00, h01, h02), (h10, h11, h12), (h20, h21, h22) = h_inv.tolist()  # Python floats keep u's dtype
    w = h20 * u + h21 * v + h22
    hit = w > 1e-12
    safe_w = np.where(hit, w, np.float32(1.0))
    a = (h00 * u + h01 * v + h02) / safe_w
    b = (h10 * u + h11 * v + h12) / safe_w
    return a, b, np.where(hit, 1.0 / safe_w, np.float32(np.inf))


def _board_shade(a: np.ndarray, b: np.ndarray, cols: int, rows: int, square_m: float) -> np.ndarray:
    """1.0 on light squares and the border, 0.0 on dark squares (board coordinates a, b in metres)."""
    i = np.floor(a / square_m + (cols + 1) / 2.0).astype(np.int32)
    j = np.floor(b / square_m + (rows + 1) / 2.0).astype(np.int32)
    in_pattern = (i >= 0) & (i <= cols) & (j >= 0) & (j <= rows)
    dark = in_pattern & (((i + j) & 1) == 0)
    return (~dark).astype(np.float32)


def render_board_view(
    T_base_cam: np.ndarray,
    intrinsics: np.ndarray,
    size_hw: tuple[int, int],
    tcp_pose: np.ndarray,
    board_offset_m: tuple[float, float, float] | np.ndarray,
    pattern_corners: tuple[int, int],
    square_m: float,
    background_depth_m: float | None = None,
    depth_scale: float = 1.0,
    depth_noise_m: float = 0.0,
    rng: np.random.Generator | None = None,
    supersample: int = 3,
) -> tuple[np.ndarray, np.ndarray]:
    """Render what an RGB-D camera sees of a checkerboard fixed to the tool (module docstring: frames).

    T_base_cam: 4x4 camera pose (base frame); intrinsics: 3x3 pinhole (pixels, no distortion); size_hw:
    (height, width). tcp_pose: (6,) UR pose; board_offset_m: board centre in the TCP frame; pattern_corners:
    inner corners (cols, rows); square_m: side of a square (metres).
    background_depth_m: None = rays that miss the board hit the table, the plane z = 0 of the base frame
    (a ray that misses the table too reads depth 0); a number = a constant depth for them (0 = no reading).
    depth_scale: the device's depth error; it reports true depth / depth_scale (so a calibration must find
    depth_scale to turn reported depth back into metres). depth_noise_m: Gaussian noise (std, metres) added
    to every non-zero reported depth, drawn from `rng` (default: a generator seeded with 0).
    supersample: n x n colour samples per pixel, so the board's edges fall between pixels as a real
    sensor's do (depth uses the pixel centre ray, like a stereo depth map without sub-pixel blending).

    Returns color uint8 (H, W, 3) RGB and depth_m float32 (H, W), metres along the camera z axis.
    """
    k = np.asarray(intrinsics, dtype=np.float64)
    h, w = size_hw
    cols, rows = pattern_corners
    T_cam_base = np.linalg.inv(np.asarray(T_base_cam, dtype=np.float64))
    T_base_board = pose_to_matrix(tcp_pose)
    T_base_board[:3, 3] = T_base_board[:3, :3] @ np.asarray(board_offset_m, dtype=np.float64) + T_base_board[:3, 3]
    board_inv = _plane_to_pixel_inverse(T_cam_base @ T_base_board, k)
    table_inv = _plane_to_pixel_inverse(T_cam_base, k)  # plane z = 0 of the base frame: (x, y) -> pixel
    half_a, half_b = (cols + 3) * square_m / 2.0, (rows + 3) * square_m / 2.0  # pattern + one-square border

    def sample(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(on-board mask, shade, depth of what the ray hits first) for pixel coordinates u, v."""
        a, b, z_board = _cast(board_inv, u, v)
        on_board = np.isfinite(z_board) & (np.abs(a) <= half_a) & (np.abs(b) <= half_b)
        if background_depth_m is None:
            _, _, z_back = _cast(table_inv, u, v)
            z_back = np.where(np.isfinite(z_back), z_back, 0.0)
        else:
            z_back = np.full(np.broadcast(u, v).shape, float(background_depth_m))
        on_board &= (z_back <= 0) | (z_board <= z_back)  # the nearer surface wins
        return on_board, _board_shade(a, b, cols, rows, square_m), np.where(on_board, z_board, z_back)

    # float32 keeps the 9 samples per pixel cheap; board coordinates stay good to ~1e-7 m.
    u = np.arange(w, dtype=np.float32)[None, :]
    v = np.arange(h, dtype=np.float32)[:, None]
    on_sum = np.zeros((h, w), dtype=np.float32)  # samples on the board ...
    light_sum = np.zeros((h, w), dtype=np.float32)  # ... and on its light part
    offsets = ((np.arange(supersample) + 0.5) / supersample - 0.5).astype(np.float32)
    for dv in offsets:
        for du in offsets:
            on_board, shade, _ = sample(u + du, v + dv)
            on_sum += on_board
            light_sum += on_board * shade
    n = float(supersample * supersample)
    # The colour is linear in the two fractions, so it is composed once, not per sample.
    color = (_DARK * (on_sum / n)[..., None] + (_LIGHT - _DARK) * (light_sum / n)[..., None]
             + _TABLE * (1.0 - on_sum / n)[..., None])

    _, _, depth_true = sample(np.broadcast_to(u, (h, w)), np.broadcast_to(v, (h, w)))
    depth = depth_true / depth_scale
    if depth_noise_m > 0:
        rng = rng if rng is not None else np.random.default_rng(0)
        depth = np.where(depth > 0, depth + rng.normal(0.0, depth_noise_m, depth.shape), 0.0)
    return np.clip(np.rint(color), 0, 255).astype(np.uint8), depth.astype(np.float32)
