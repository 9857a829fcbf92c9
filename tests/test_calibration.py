"""Camera-to-robot calibration (`romannet calibrate`), checked against synthetic checkerboard views.

The views are ray-cast by tests/fakes/checkerboard.py from a known camera pose and depth scale, so the
expected calibration comes from geometry, not from the code under test. A fake robot lands a few millimetres
off every commanded pose (and reports where it landed), so only a calibration that uses the measured pose
passes.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest
from fakes.checkerboard import render_board_view

from romannet.actor.real.calibrate import run_calibration
from romannet.actor.real.calibration import (
    FORMAT,
    FitResult,
    board_centre_pixel,
    board_depth,
    board_point_base,
    detect_corners,
    fit_similarity,
    grid_positions,
    load_calibration,
    tcp_matrix,
    write_calibration,
)
from romannet.common.config_calibration import CalibrationConfig
from romannet.common.errors import ConfigError, DecodeError, RobotError
from romannet.common.heightmap import look_at
from romannet.common.interfaces import Camera, CameraFrame, MotionResult, Robot

# A RealSense D435-like colour stream, 640x480, ~0.65 m above the table, looking down tilted ~20 degrees and
# rolled a little, so no axis of the answer is trivially aligned.
K = np.array([[615.3, 0.0, 322.4], [0.0, 615.8, 238.1], [0.0, 0.0, 1.0]])
SIZE_HW = (480, 640)
T_BASE_CAM = look_at(np.array([0.52, -0.23, 0.66]), np.array([0.5, 0.0, 0.0]), up=(-1.0, 0.15, 0.0))
DEPTH_SCALE = 1.02
HOME = np.array([0.3, -0.4, 0.4, np.pi, 0.0, 0.0])  # out of the camera's view
CFG = CalibrationConfig(board_offset_m=(0.01, -0.02, 0.03), settle_s=0.0)
SMALL = CalibrationConfig(grid_x_m=(0.44, 0.56, 2), grid_y_m=(-0.06, 0.06, 2), grid_z_m=(0.1, 0.2, 2),
                          board_offset_m=(0.01, -0.02, 0.03), settle_s=0.0, min_poses=4)


class FakeRobot:
    """A `Robot` that lands up to 4 mm off each commanded position (and says so in tool_pose)."""

    def __init__(self, stop_at_move: int = 0):
        self.stopped = ""
        self.pose = HOME.copy()
        self.moves: list[np.ndarray] = []
        self.homes = 0
        self._stop_at = stop_at_move
        self._rng = np.random.default_rng(7)

    def connect(self) -> None: ...
    def disconnect(self) -> None: ...
    def __enter__(self) -> FakeRobot: return self
    def __exit__(self, *exc: object) -> None: ...
    def tool_pose(self) -> np.ndarray: return self.pose.copy()
    def holding(self) -> bool: return False
    def resume(self) -> bool: return False
    def push(self, *a: float) -> MotionResult: return MotionResult(False, "not_supported")
    def pick(self, *a: float) -> MotionResult: return MotionResult(False, "not_supported")
    def place(self, *a: float) -> MotionResult: return MotionResult(False, "not_supported")
    def drop(self, *a: float) -> MotionResult: return MotionResult(False, "not_supported")

    def move_to(self, pose: np.ndarray) -> MotionResult:
        assert not self.stopped, "a stopped robot was commanded to move"
        self.moves.append(np.asarray(pose))
        if len(self.moves) == self._stop_at:
            self.stopped = "protective_stop"
            return MotionResult(False, "protective_stop", stopped="protective_stop")
        self.pose = np.asarray(pose, dtype=np.float64).copy()
        self.pose[:3] += self._rng.uniform(-0.004, 0.004, 3)
        return MotionResult(True)

    def go_home(self) -> MotionResult:
        assert not self.stopped, "a stopped robot was sent home"
        self.homes += 1
        self.pose = HOME.copy()
        return MotionResult(True)


class FakeCamera:
    """A `Camera` that renders the board on the fake robot's tool; some captures hidden or without depth."""

    def __init__(self, robot: FakeRobot, cfg: CalibrationConfig, hidden: tuple[int, ...] = (),
                 no_depth: tuple[int, ...] = ()):
        self.robot, self.cfg, self.hidden, self.no_depth = robot, cfg, hidden, no_depth
        self.captures = 0
        self._rng = np.random.default_rng(3)

    def connect(self) -> None: ...
    def disconnect(self) -> None: ...
    def __enter__(self) -> FakeCamera: return self
    def __exit__(self, *exc: object) -> None: ...

    def capture(self) -> CameraFrame:
        self.captures += 1
        if self.captures in self.hidden:  # someone's hand in front of the board
            color, depth = np.full((*SIZE_HW, 3), 90, np.uint8), np.full(SIZE_HW, 0.3, np.float32)
        else:
            color, depth = render_board_view(T_BASE_CAM, K, SIZE_HW, self.robot.pose, self.cfg.board_offset_m,
                                             self.cfg.pattern_corners, self.cfg.square_m, depth_scale=DEPTH_SCALE,
                                             depth_noise_m=0.001, rng=self._rng)
        if self.captures in self.no_depth:
            depth = np.zeros_like(depth)
        return CameraFrame(color, depth, K.copy(), float(self.captures))


def _rotation_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    cos = (np.trace(a[:3, :3].T @ b[:3, :3]) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


# ------------------------------------------------------------------------------------------ end to end
def test_recovers_known_camera_pose_and_depth_scale(tmp_path: Path) -> None:
    robot = FakeRobot()
    camera = FakeCamera(robot, CFG)
    assert isinstance(robot, Robot) and isinstance(camera, Camera)
    out = tmp_path / "cal" / "calibration.json"
    result = run_calibration(robot, camera, CFG, out)

    assert CFG.pose_count == 27 and len(robot.moves) == 27 and robot.homes == 2
    assert np.linalg.norm(result.fit.T_base_cam[:3, 3] - T_BASE_CAM[:3, 3]) < 0.002
    assert _rotation_error_deg(result.fit.T_base_cam, T_BASE_CAM) < 0.5
    assert result.fit.depth_scale == pytest.approx(DEPTH_SCALE, rel=0.005)
    assert result.fit.rms_error_m < 0.0005  # commanded poses would leave ~4 mm

    loaded = load_calibration(out)
    np.testing.assert_allclose(loaded.T_base_cam, result.fit.T_base_cam, atol=1e-12)
    assert loaded.depth_scale == pytest.approx(result.fit.depth_scale) and FORMAT in loaded.source
    doc = json.loads(out.read_text())
    assert doc["format"] == FORMAT and doc["poses"] == 27 and len(doc["residuals_m"]) == 27
    assert doc["rms_error_m"] == pytest.approx(result.fit.rms_error_m) and doc["created_utc"].endswith("+00:00")
    report = result.report_path.read_text()
    assert result.report_path == out.with_suffix(".md")
    assert sum(line.startswith("| ") and "| yes |" in line for line in report.splitlines()) == 27
    assert "RMS residual" in report and "depth scale: 1.0" in report and "camera position" in report
    assert not list(out.parent.glob("*.tmp"))


def test_hidden_board_and_missing_depth_are_skipped_and_reported(tmp_path: Path, caplog) -> None:
    robot = FakeRobot()
    camera = FakeCamera(robot, SMALL, hidden=(2,), no_depth=(5,))
    with caplog.at_level(logging.WARNING):
        result = run_calibration(robot, camera, SMALL, tmp_path / "c.json", tmp_path / "r.md")
    used = [p.index for p in result.poses if p.used]
    assert len(result.poses) == 8 and used == [0, 2, 3, 5, 6, 7]
    assert result.poses[1].note == "board not detected" and result.poses[1].residual_m is None
    assert "valid depth" in result.poses[4].note
    assert json.loads((tmp_path / "c.json").read_text())["poses"] == 6
    report = (tmp_path / "r.md").read_text()
    assert "| 2 |" in report and "board not detected" in report and "poses used: 6 of 8" in report
    assert sum("skipped" in r.message for r in caplog.records) == 2
    assert np.linalg.norm(result.fit.T_base_cam[:3, 3] - T_BASE_CAM[:3, 3]) < 0.002


def test_protective_stop_aborts_without_writing(tmp_path: Path) -> None:
    robot = FakeRobot(stop_at_move=3)
    out = tmp_path / "c.json"
    with pytest.raises(RobotError, match="stopped .*protective_stop.*nothing was written"):
        run_calibration(robot, FakeCamera(robot, SMALL), SMALL, out)
    assert len(robot.moves) == 3 and robot.homes == 1  # no motion after the stop, not even home
    assert not out.exists() and not out.with_suffix(".md").exists()


def test_too_few_views_refused_without_writing(tmp_path: Path) -> None:
    robot = FakeRobot()
    out = tmp_path / "c.json"
    out.write_text("previous")
    with pytest.raises(RobotError, match="nothing was written.*7 of 8 poses skipped"):
        run_calibration(robot, FakeCamera(robot, SMALL, hidden=tuple(range(2, 9))), SMALL, out)
    assert out.read_text() == "previous" and robot.homes == 2


# `romannet calibrate` through URRobot / RealSenseCamera on the fake drivers: tests/test_real_env.py.


# ------------------------------------------------------------------------------------------ the math
def _random_similarity(rng: np.random.Generator) -> tuple[np.ndarray, float]:
    pose = tcp_matrix(np.r_[rng.uniform(-1, 1, 3), rng.uniform(-2, 2, 3)])
    return pose, 0.97


def test_fit_recovers_an_exact_similarity() -> None:
    rng = np.random.default_rng(0)
    pose, scale = _random_similarity(rng)
    cam = rng.uniform(-0.3, 0.3, (12, 3)) + [0.0, 0.0, 0.6]
    base = scale * cam @ pose[:3, :3].T + pose[:3, 3]
    fit = fit_similarity(cam, base, min_points=10)
    np.testing.assert_allclose(fit.T_base_cam, pose, atol=1e-9)
    assert fit.depth_scale == pytest.approx(scale, abs=1e-12) and fit.max_error_m < 1e-9
    # One planar layer of poses is enough: det R = +1 removes the mirror solution.
    flat = cam.copy()
    flat[:, 2] = 0.6
    assert fit_similarity(flat, scale * flat @ pose[:3, :3].T + pose[:3, 3]).max_error_m < 1e-9


def test_fit_reports_the_residual_of_each_pose() -> None:
    rng = np.random.default_rng(1)
    pose, scale = _random_similarity(rng)
    cam = rng.uniform(-0.2, 0.2, (20, 3)) + [0.0, 0.0, 0.5]
    base = scale * cam @ pose[:3, :3].T + pose[:3, 3]
    base[7] += [0.005, 0.0, 0.0]
    fit = fit_similarity(cam, base)
    assert fit.residuals_m.shape == (20,) and int(np.argmax(fit.residuals_m)) == 7
    assert fit.residuals_m[7] > 0.004 and np.delete(fit.residuals_m, 7).max() < 0.001
    assert fit.rms_error_m == pytest.approx(np.sqrt(np.mean(fit.residuals_m**2)))
    assert fit.max_error_m == pytest.approx(fit.residuals_m[7])


def test_fit_refuses_degenerate_point_sets() -> None:
    rng = np.random.default_rng(2)
    cam = rng.uniform(-0.2, 0.2, (6, 3))
    with pytest.raises(ValueError, match="only 6 poses .* at least 10"):
        fit_similarity(cam, cam, min_points=10)
    line = np.outer(np.linspace(0, 1, 8), [0.1, 0.2, 0.05]) + rng.normal(0, 1e-6, (8, 3))
    with pytest.raises(ValueError, match="collinear"):
        fit_similarity(line, line + 0.5)
    with pytest.raises(ValueError, match="NaN"):
        fit_similarity(np.where(np.eye(6, 3) > 0, np.nan, cam), cam)
    with pytest.raises(ValueError, match="shape"):
        fit_similarity(cam, cam[:5])


def test_board_centre_is_exact_under_perspective() -> None:
    cols, rows = 5, 4
    homography = np.array([[40.0, 8.0, 200.0], [-5.0, 35.0, 150.0], [0.04, 0.03, 1.0]])  # strong tilt
    grid = np.array([(i, j, 1.0) for j in range(rows) for i in range(cols)])
    proj = grid @ homography.T
    corners = proj[:, :2] / proj[:, 2:]
    centre = homography @ [(cols - 1) / 2, (rows - 1) / 2, 1.0]
    centre = centre[:2] / centre[2]
    np.testing.assert_allclose(board_centre_pixel(corners, (cols, rows)), centre, atol=1e-6)
    np.testing.assert_allclose(board_centre_pixel(corners[::-1], (cols, rows)), centre, atol=1e-6)
    assert np.linalg.norm(corners.mean(axis=0) - centre) > 1.0  # why the mean of corners is not used


def test_board_depth_ignores_invalid_and_flying_pixels() -> None:
    rng = np.random.default_rng(4)
    pose = np.array([0.5, 0.05, 0.15, np.pi, 0.0, 0.0])
    color, depth = render_board_view(T_BASE_CAM, K, SIZE_HW, pose, (0, 0, 0), (5, 4), 0.02, depth_noise_m=0.001,
                                     rng=rng)
    corners = detect_corners(color, (5, 4))
    assert corners is not None and corners.shape == (20, 2)
    centre = board_centre_pixel(corners, (5, 4))
    truth = (np.linalg.inv(T_BASE_CAM) @ np.r_[board_point_base(pose, (0, 0, 0)), 1.0])[2]
    bad = rng.random(depth.shape)
    depth[bad < 0.05] = 0.0
    depth[(bad >= 0.05) & (bad < 0.08)] = np.nan
    depth[(bad >= 0.08) & (bad < 0.1)] = rng.uniform(0.2, 2.0, int(((bad >= 0.08) & (bad < 0.1)).sum()))
    assert board_depth(depth, corners, centre, 200) == pytest.approx(truth, abs=3e-4)
    assert board_depth(np.zeros_like(depth), corners, centre, 200) is None


def test_grid_and_tool_geometry() -> None:
    positions = grid_positions((0.4, 0.6, 3), (-0.1, 0.1, 3), (0.1, 0.3, 2))
    assert positions.shape == (18, 3) and len({tuple(p) for p in positions}) == 18
    assert positions.min(axis=0) == pytest.approx([0.4, -0.1, 0.1])
    assert positions.max(axis=0) == pytest.approx([0.6, 0.1, 0.3])
    # Serpentine: consecutive poses differ along one axis only, by one grid step.
    steps = np.diff(positions, axis=0)
    assert np.all(np.count_nonzero(np.abs(steps) > 1e-12, axis=1) == 1)
    # Tool pointing down (pi about x): TCP y and z are base -y and -z.
    point = board_point_base(np.array([0.5, 0.0, 0.3, np.pi, 0.0, 0.0]), (0.01, 0.02, 0.03))
    np.testing.assert_allclose(point, [0.51, -0.02, 0.27], atol=1e-12)


def test_config_validation_names_the_field() -> None:
    with pytest.raises(ConfigError, match="calibration.grid_z_m"):
        CalibrationConfig(grid_z_m=(0.3, 0.1, 3))
    with pytest.raises(ConfigError, match="fewer than calibration.min_poses"):
        CalibrationConfig(grid_x_m=(0.5, 0.5, 1), grid_y_m=(0.0, 0.0, 1), grid_z_m=(0.1, 0.2, 3))
    with pytest.raises(ConfigError, match="calibration.pattern_corners"):
        CalibrationConfig(pattern_corners=(2, 5))


# ------------------------------------------------------------------------------------------ the file
def _good_fit(scale: float = 1.01) -> FitResult:
    return FitResult(T_BASE_CAM.copy(), scale, np.array([0.001, 0.002]), 0.0016, 0.002)


def test_file_round_trip(tmp_path: Path) -> None:
    path = write_calibration(tmp_path / "sub" / "c.json", _good_fit())
    cal = load_calibration(path)
    np.testing.assert_array_equal(cal.T_base_cam, T_BASE_CAM)
    assert cal.depth_scale == 1.01 and str(path) in cal.source
    assert json.loads(path.read_text())["residuals_m"] == [0.001, 0.002]
    bad = _good_fit()
    bad.T_base_cam[0, 0] = 2.0
    with pytest.raises(ValueError, match="orthonormal"):
        write_calibration(tmp_path / "bad.json", bad)
    assert not (tmp_path / "bad.json").exists()


def test_vpg_text_format(tmp_path: Path) -> None:
    pose_file = tmp_path / "camera_pose.txt"
    pose_file.write_text("\n".join(" ".join(f"{v:.10f}" for v in row) for row in T_BASE_CAM) + "\n")
    cal = load_calibration(pose_file)
    np.testing.assert_allclose(cal.T_base_cam, T_BASE_CAM, atol=1e-9)
    assert cal.depth_scale == 1.0 and "VPG" in cal.source
    (tmp_path / "camera_depth_scale.txt").write_text("1.034\n")
    assert load_calibration(pose_file).depth_scale == 1.034
    (tmp_path / "camera_depth_scale.txt").write_text("one\n")
    with pytest.raises(DecodeError, match="camera_depth_scale.txt"):
        load_calibration(pose_file)


def _matrix_text(matrix: np.ndarray) -> str:
    return "\n".join(" ".join(repr(float(v)) for v in row) for row in matrix)


def _json_text(**changes: object) -> str:
    doc = {"format": FORMAT, "T_base_cam": T_BASE_CAM.tolist(), "depth_scale": 1.0}
    doc.update(changes)
    return json.dumps(doc)


_SHEARED = T_BASE_CAM.copy()
_SHEARED[0, 1] += 0.05
_MIRRORED = T_BASE_CAM @ np.diag([1.0, 1.0, -1.0, 1.0])
_BAD_ROW = T_BASE_CAM.copy()
_BAD_ROW[3, 0] = 0.1
_NAN = T_BASE_CAM.copy()
_NAN[1, 2] = np.nan


@pytest.mark.parametrize(("text", "why"), [
    ("{\"format\": \"romannet-calibration/1\", \"T_base", "not valid JSON"),
    (_json_text()[:-40], "not valid JSON"),
    (_json_text(format="other/2"), "format is 'other/2'"),
    (_json_text(T_base_cam=T_BASE_CAM[:3].tolist()), "4 rows of 4 numbers"),
    (_json_text(T_base_cam=[[1, 0, 0, 0]] * 4 + [[1]]), "4 rows of 4 numbers"),
    (_json_text(depth_scale="1.0"), "depth_scale must be a number"),
    (_json_text(depth_scale=3.0), "outside"),
    (_json_text(T_base_cam=_SHEARED.tolist()), "orthonormal"),
    (_json_text(T_base_cam=_MIRRORED.tolist()), "det"),
    (_matrix_text(_BAD_ROW), "0 0 0 1"),
    (_matrix_text(T_BASE_CAM)[:-30], "expected 16 whitespace-separated numbers"),
    (_matrix_text(_NAN), "NaN"),
    (_matrix_text(T_BASE_CAM) + " 7", "found 17"),
    ("0 0 zero 1", "non-numeric"),
    ("  \n", "empty"),
])
def test_bad_files_raise_decode_error_naming_the_file(tmp_path: Path, text: str, why: str) -> None:
    path = tmp_path / "calibration_file.json"
    path.write_text(text)
    with pytest.raises(DecodeError, match=why) as err:
        load_calibration(path)
    assert str(path) in str(err.value)


def test_unreadable_files_raise_decode_error(tmp_path: Path) -> None:
    with pytest.raises(DecodeError, match="does not exist"):
        load_calibration(tmp_path / "missing.json")
    (tmp_path / "binary.json").write_bytes(b"\x80\x03}q\x00(X\x06\x00\x00\x00format")  # a pickle: never loaded
    with pytest.raises(DecodeError, match="binary.json.*not text"):
        load_calibration(tmp_path / "binary.json")
