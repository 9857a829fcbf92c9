"""Camera-to-robot calibration math and its file format; no hardware I/O (actor/real/calibrate.py moves).

Frames and units (those of common/heightmap.py): camera points in the OpenCV frame (x right, y down, z
forward), pixel centres at integer (u, v); robot poses UR style (x, y, z metres, rotation vector) in the
base frame; `T_base_cam` maps camera points to base points, p_base = T_base_cam @ p_cam.

The calibration: at each pose the checkerboard's centre is found in the image (pixel) and in the depth map
(depth at that pixel), back-projected into the camera frame as the device reports it, and paired with the
same point from the robot's measured pose (T_base_tcp @ board offset). A similarity fit
p_base = s R p_cam + t over all poses gives the camera pose (R, t) and the depth scale s: every
back-projected coordinate is proportional to the reported depth, so a depth error by a constant factor is
exactly the fit's scale (VPG searches for it separately; here it is closed form). True depth = reported
depth * depth_scale, as in VPG's camera_depth_scale.txt.

The calibration file: JSON, format "romannet-calibration/1" (written atomically), or VPG's text format
(camera_pose.txt: the 4x4 matrix, whitespace-separated; camera_depth_scale.txt beside it, optional).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import cv2
import numpy as np

from romannet.common.errors import DecodeError
from romannet.common.fsutil import fsync_directory

FORMAT = "romannet-calibration/1"
VPG_DEPTH_SCALE_FILE = "camera_depth_scale.txt"
DEPTH_SCALE_RANGE = (0.5, 2.0)  # outside it the depth is not a scaled distance but something broken
_ROTATION_TOL = 1e-3
_MAX_FILE_BYTES = 1 << 20  # a calibration file is a few kB; anything larger is not one
_SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)


# ------------------------------------------------------------------------------------------ geometry
def tcp_matrix(pose: np.ndarray) -> np.ndarray:
    """T_base_tcp (4x4) of a UR pose (x, y, z metres, rotation vector rx, ry, rz; base frame)."""
    pose = np.asarray(pose, dtype=np.float64).reshape(6)
    out = np.eye(4)
    out[:3, :3] = cv2.Rodrigues(pose[3:6].reshape(3, 1))[0]
    out[:3, 3] = pose[:3]
    return out


def board_point_base(tcp_pose: np.ndarray, board_offset_m: tuple[float, float, float]) -> np.ndarray:
    """The board centre in the base frame (metres): T_base_tcp(pose) @ board_offset_m (TCP frame)."""
    t = tcp_matrix(tcp_pose)
    return t[:3, :3] @ np.asarray(board_offset_m, dtype=np.float64) + t[:3, 3]


def grid_positions(grid_x_m: tuple[float, float, int], grid_y_m: tuple[float, float, int],
                   grid_z_m: tuple[float, float, int]) -> np.ndarray:
    """(n, 3) TCP positions (base frame, metres) of a (start, stop, count) grid per axis, x varying fastest
    within a layer and z slowest, so consecutive poses are close (short moves)."""
    xs, ys, zs = (np.linspace(a, b, int(n)) for a, b, n in (grid_x_m, grid_y_m, grid_z_m))
    rows: list[tuple[float, float, float]] = []
    for k, z in enumerate(zs):
        for y in ys if k % 2 == 0 else ys[::-1]:
            xs_row = xs if (len(rows) // len(xs)) % 2 == 0 else xs[::-1]  # serpentine: every row turns back
            rows.extend((x, y, z) for x in xs_row)
    return np.asarray(rows, dtype=np.float64)


# ------------------------------------------------------------------------------------------ image side
def detect_corners(color: np.ndarray, pattern_corners: tuple[int, int]) -> np.ndarray | None:
    """Inner corners (cols*rows, 2) in pixels, OpenCV's order, refined to sub-pixel; None if not found.

    color: uint8 (H, W, 3) RGB. The classic detector with the fast check is tried first (milliseconds, and
    quick to give up on a frame without a board); the sector-based detector copes with blur and low contrast.
    """
    gray = cv2.cvtColor(np.ascontiguousarray(color), cv2.COLOR_RGB2GRAY)
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_FAST_CHECK
    found, corners = cv2.findChessboardCorners(gray, pattern_corners, flags=flags)
    if found:
        pts = corners.reshape(-1, 2)
        spacing_px = float(np.median(np.linalg.norm(np.diff(pts, axis=0), axis=1)))
        # The refinement window must stay inside one square, or it pulls toward a neighbouring corner.
        half = int(np.clip(spacing_px / 3.0, 2, 10))
        corners = cv2.cornerSubPix(gray, corners, (half, half), (-1, -1), _SUBPIX_CRITERIA)
        return corners.reshape(-1, 2).astype(np.float64)
    found, corners = cv2.findChessboardCornersSB(gray, pattern_corners, flags=cv2.CALIB_CB_ACCURACY)
    return corners.reshape(-1, 2).astype(np.float64) if found else None


def board_centre_pixel(corners_px: np.ndarray, pattern_corners: tuple[int, int]) -> np.ndarray:
    """(u, v) of the centre of the inner-corner grid, exact under perspective.

    The board plane maps to the image by a homography; the centre is mapped through the homography fitted
    to all corners (the mean of the projected corners is biased toward the nearer side). The centre is
    symmetric in the grid, so it does not matter which corner OpenCV numbered first.
    """
    cols, rows = pattern_corners
    grid = np.array([(i, j) for j in range(rows) for i in range(cols)], dtype=np.float64)
    homography, _ = cv2.findHomography(grid, corners_px, 0)
    if homography is None:
        raise ValueError("board_centre_pixel: the corners do not determine a homography")
    centre = homography @ np.array([(cols - 1) / 2.0, (rows - 1) / 2.0, 1.0])
    return centre[:2] / centre[2]


def board_depth(depth_m: np.ndarray, corners_px: np.ndarray, centre_px: np.ndarray,
                min_valid_px: int) -> float | None:
    """Depth (metres, as reported) of the board at centre_px; None with fewer than min_valid_px readings.

    Over the pixels inside the corners' convex hull with a valid reading (finite, > 0), 1/z is fitted as an
    affine function of (u, v), which a plane seen in perspective is exactly; then evaluated at the centre.
    Readings more than 3 robust sigmas off the plane (edge artefacts, flying pixels) are dropped and the
    plane refitted, twice.
    """
    depth = np.asarray(depth_m, dtype=np.float64)
    mask = np.zeros(depth.shape, dtype=np.uint8)
    cv2.fillConvexPoly(mask, cv2.convexHull(np.rint(corners_px).astype(np.int32)), 1)
    v, u = np.nonzero(mask & np.isfinite(depth) & (depth > 0))
    if u.size < min_valid_px:
        return None
    z = depth[v, u]
    design = np.column_stack([u, v, np.ones_like(u)]).astype(np.float64)
    keep = np.ones(z.size, dtype=bool)
    for _ in range(3):
        coef, *_ = np.linalg.lstsq(design[keep], 1.0 / z[keep], rcond=None)
        err = z - 1.0 / (design @ coef)
        sigma = 1.4826 * float(np.median(np.abs(err[keep])))
        keep = np.abs(err) <= max(3.0 * sigma, 1e-6)
        if keep.sum() < min_valid_px:
            return None
    inv_z = float(coef @ np.array([centre_px[0], centre_px[1], 1.0]))
    return 1.0 / inv_z if inv_z > 0 else None


def back_project(centre_px: np.ndarray, depth_m: float, intrinsics: np.ndarray) -> np.ndarray:
    """Camera-frame point (metres, OpenCV frame) seen at pixel (u, v) with depth along the camera z axis."""
    k = np.asarray(intrinsics, dtype=np.float64)
    x = (centre_px[0] - k[0, 2]) / k[0, 0]
    y = (centre_px[1] - k[1, 2]) / k[1, 1]
    return depth_m * np.array([x, y, 1.0])


def observe_board(color: np.ndarray, depth_m: np.ndarray, intrinsics: np.ndarray,
                  pattern_corners: tuple[int, int], min_valid_px: int) -> tuple[np.ndarray | None, str]:
    """The board centre in the camera frame (as the device reports depth), or None and why not."""
    corners = detect_corners(color, pattern_corners)
    if corners is None:
        return None, "board not detected"
    centre = board_centre_pixel(corners, pattern_corners)
    z = board_depth(depth_m, corners, centre, min_valid_px)
    if z is None:
        return None, f"fewer than {min_valid_px} valid depth readings on the board"
    return back_project(centre, z, intrinsics), ""


# ------------------------------------------------------------------------------------------ the fit
@dataclass(frozen=True, eq=False)
class FitResult:
    """p_base = depth_scale * R @ p_cam + t, as T_base_cam (R, t) and depth_scale; residuals per pose (m)."""

    T_base_cam: np.ndarray
    depth_scale: float
    residuals_m: np.ndarray
    rms_error_m: float
    max_error_m: float


def _check_spread(points: np.ndarray, name: str) -> None:
    """Refuse points on (or within noise of) one line: the rotation about that line is then undetermined.
    Coplanar points are fine: the det(R) = +1 constraint picks the one rotation that fits."""
    sv = np.linalg.svd(points - points.mean(axis=0), compute_uv=False)
    if sv[0] < 1e-6 or sv[1] < 1e-3 * sv[0]:
        raise ValueError(f"the {name} points are collinear (singular values {sv.round(6).tolist()}); "
                         "the grid must span at least two directions")


def fit_similarity(points_cam: np.ndarray, points_base: np.ndarray, min_points: int = 3) -> FitResult:
    """Umeyama's closed-form least-squares similarity from camera points to base points (metres).

    Raises ValueError for fewer than max(3, min_points) pairs, mismatched shapes, non-finite values or
    collinear points.
    """
    cam = np.asarray(points_cam, dtype=np.float64)
    base = np.asarray(points_base, dtype=np.float64)
    if cam.ndim != 2 or cam.shape[1] != 3 or cam.shape != base.shape:
        raise ValueError(f"need two (n, 3) point sets of one shape; got {cam.shape} and {base.shape}")
    need = max(3, min_points)
    if len(cam) < need:
        raise ValueError(f"only {len(cam)} poses with a detected board and depth; need at least {need}")
    if not (np.all(np.isfinite(cam)) and np.all(np.isfinite(base))):
        raise ValueError("the points contain NaN or inf")
    _check_spread(base, "robot-side")
    _check_spread(cam, "camera-side")
    mu_cam, mu_base = cam.mean(axis=0), base.mean(axis=0)
    dc, db = cam - mu_cam, base - mu_base
    u, d, vt = np.linalg.svd(db.T @ dc / len(cam))
    sign = np.diag([1.0, 1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt))])  # no reflections
    rot = u @ sign @ vt
    scale = float(np.trace(np.diag(d) @ sign) / (dc**2).sum(axis=1).mean())
    trans = mu_base - scale * rot @ mu_cam
    residuals = np.linalg.norm(scale * cam @ rot.T + trans - base, axis=1)
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rot, trans
    return FitResult(pose, scale, residuals, float(np.sqrt(np.mean(residuals**2))), float(residuals.max()))


# ------------------------------------------------------------------------------------------ the file
@dataclass(frozen=True, eq=False)
class Calibration:
    """What an actor needs: T_base_cam (4x4; p_base = T_base_cam @ p_cam, metres) and depth_scale (true depth
    = reported depth * depth_scale); source says which file and format it came from."""

    T_base_cam: np.ndarray
    depth_scale: float
    source: str


def calibration_problem(T_base_cam: np.ndarray, depth_scale: float) -> str:
    """"" if the pair is a usable calibration, else what is wrong with it (one line)."""
    t = np.asarray(T_base_cam, dtype=np.float64)
    if t.shape != (4, 4):
        return f"T_base_cam must be 4x4, not {t.shape}"
    if not np.all(np.isfinite(t)):
        return "T_base_cam has NaN or inf entries"
    if not np.allclose(t[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        return f"T_base_cam's last row must be 0 0 0 1, not {t[3].tolist()}"
    rot = t[:3, :3]
    ortho_err = float(np.abs(rot.T @ rot - np.eye(3)).max())
    if ortho_err > _ROTATION_TOL or abs(np.linalg.det(rot) - 1.0) > _ROTATION_TOL:
        return (f"T_base_cam's rotation is not orthonormal with det +1 (|R^T R - I| = {ortho_err:.2g}, "
                f"det = {np.linalg.det(rot):.4g})")
    lo, hi = DEPTH_SCALE_RANGE
    if not (isinstance(depth_scale, (int, float)) and math.isfinite(depth_scale) and lo < depth_scale < hi):
        return f"depth scale {depth_scale!r} is outside ({lo}, {hi})"
    return ""


def write_text_atomic(path: Path, text: str) -> None:
    """tmp file, fsync, rename, fsync the directory: a crash leaves the old file or the new one, never half."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    with tmp.open("w", encoding="utf-8") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
    tmp.replace(path)
    fsync_directory(path.parent)


def write_calibration(path: str | Path, fit: FitResult) -> Path:
    """Write `fit` as a romannet-calibration/1 JSON file, atomically; ValueError if it is not usable."""
    problem = calibration_problem(fit.T_base_cam, fit.depth_scale)
    if problem:
        raise ValueError(f"refusing to write calibration {path}: {problem}")
    doc = {
        "format": FORMAT,
        "T_base_cam": np.asarray(fit.T_base_cam, dtype=np.float64).tolist(),
        "depth_scale": float(fit.depth_scale),
        "rms_error_m": float(fit.rms_error_m),
        "max_error_m": float(fit.max_error_m),
        "residuals_m": [float(r) for r in fit.residuals_m],
        "poses": len(fit.residuals_m),
        "created_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
    path = Path(path)
    write_text_atomic(path, _format_json(doc))
    return path


def _format_json(doc: dict) -> str:
    """JSON with one key per line and the matrix one row per line, so a person can read the file."""
    fields = {key: json.dumps(value) for key, value in doc.items()}
    fields["T_base_cam"] = "[\n  " + ",\n  ".join(json.dumps(row) for row in doc["T_base_cam"]) + "\n ]"
    return "{\n" + ",\n".join(f" {json.dumps(key)}: {value}" for key, value in fields.items()) + "\n}\n"


def _read_text(path: Path) -> str:
    try:
        if path.stat().st_size > _MAX_FILE_BYTES:
            raise DecodeError(f"calibration file {path}: larger than {_MAX_FILE_BYTES} bytes; not a calibration")
        return path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise DecodeError(f"calibration file {path} does not exist") from None
    except UnicodeDecodeError:
        raise DecodeError(f"calibration file {path}: not text (invalid UTF-8)") from None
    except OSError as err:
        raise DecodeError(f"calibration file {path} cannot be read: {err}") from None


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _parse_json(path: Path, text: str) -> tuple[np.ndarray, float, str]:
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as err:
        raise DecodeError(f"calibration file {path}: not valid JSON ({err}); truncated or corrupt?") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        got = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise DecodeError(f"calibration file {path}: format is {got!r}, expected {FORMAT!r}")
    matrix, scale = doc.get("T_base_cam"), doc.get("depth_scale")
    if not (isinstance(matrix, list) and len(matrix) == 4
            and all(isinstance(row, list) and len(row) == 4 and all(map(_is_number, row)) for row in matrix)):
        raise DecodeError(f"calibration file {path}: T_base_cam must be 4 rows of 4 numbers")
    if not _is_number(scale):
        raise DecodeError(f"calibration file {path}: depth_scale must be a number, not {scale!r}")
    return np.array(matrix, dtype=np.float64), float(scale), FORMAT


def _parse_numbers(path: Path, text: str, count: int) -> list[float]:
    fields = text.split()
    try:
        values = [float(f) for f in fields]
    except ValueError:
        raise DecodeError(f"calibration file {path}: expected {count} numbers, found non-numeric text") from None
    if len(values) != count:
        raise DecodeError(f"calibration file {path}: expected {count} whitespace-separated numbers, found "
                          f"{len(values)}; truncated or not this format?")
    return values


def _parse_vpg(path: Path, text: str) -> tuple[np.ndarray, float, str]:
    matrix = np.array(_parse_numbers(path, text, 16), dtype=np.float64).reshape(4, 4)
    scale_path = path.with_name(VPG_DEPTH_SCALE_FILE)
    if not scale_path.exists():
        return matrix, 1.0, f"VPG text (no {VPG_DEPTH_SCALE_FILE}: depth scale 1.0)"
    (scale,) = _parse_numbers(scale_path, _read_text(scale_path), 1)
    return matrix, scale, f"VPG text, depth scale from {scale_path}"


def load_calibration(path: str | Path) -> Calibration:
    """Read a romannet-calibration/1 JSON file or VPG's camera_pose.txt (by content, not by name).

    Raises DecodeError naming the file and what is wrong: missing, unreadable, truncated, not a number,
    wrong shape, last row not 0 0 0 1, rotation not orthonormal with det +1, depth scale outside (0.5, 2).
    """
    path = Path(path)
    text = _read_text(path)
    if not text.strip():
        raise DecodeError(f"calibration file {path} is empty")
    parse = _parse_json if text.lstrip().startswith("{") else _parse_vpg
    matrix, scale, fmt = parse(path, text)
    problem = calibration_problem(matrix, scale)
    if problem:
        raise DecodeError(f"calibration file {path}: {problem}")
    return Calibration(T_base_cam=matrix, depth_scale=scale, source=f"{path} ({fmt})")
