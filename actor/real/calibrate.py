"""`romannet calibrate`: move a checkerboard on the tool over a grid of poses, fit the camera pose and the depth
scale, write the calibration file the actor loads and a Markdown report of the residual error per pose.

The math and the file format are in actor/real/calibration.py; this module only drives a `Robot` and a
`Camera` (common/interfaces.py). Safety: a protective or emergency stop aborts the run at once; the robot is
then left where it stopped (no motion is commanded) and nothing is written.
"""

from __future__ import annotations

import argparse
import logging
import time
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from romannet.common.config_calibration import CalibrationConfig
from romannet.common.errors import RobotError
from romannet.common.interfaces import Camera, MotionResult, Robot

from .calibration import (
    FitResult,
    board_point_base,
    fit_similarity,
    grid_positions,
    observe_board,
    write_calibration,
    write_text_atomic,
)

log = logging.getLogger("romannet.actor.calibrate")


@dataclass(frozen=True, eq=False)
class PoseRecord:
    """One grid pose: commanded and measured TCP poses (base frame, m / rotation vector), the board centre
    seen by the camera (camera frame, reported depth) and from the robot (base frame), the residual after the
    fit (m), or why the pose was skipped (`note`)."""

    index: int
    commanded: np.ndarray
    measured: np.ndarray | None = None
    point_cam: np.ndarray | None = None
    point_base: np.ndarray | None = None
    residual_m: float | None = None
    note: str = ""

    @property
    def used(self) -> bool:
        return self.point_cam is not None


@dataclass(frozen=True, eq=False)
class CalibrationResult:
    """The fit, every pose's record (skipped ones included) and where the file and the report went."""

    fit: FitResult
    poses: tuple[PoseRecord, ...]
    out_path: Path
    report_path: Path


class _Stopped(RobotError):
    """The robot reported a protective / emergency stop: abort without moving it again."""


def _check_stop(robot: Robot, result: MotionResult, what: str) -> None:
    reason = result.stopped or robot.stopped
    if reason:
        raise _Stopped(f"the robot stopped ({reason}) while {what}; calibration aborted and nothing was written. "
                       "Clear the stop on the teach pendant, then run `romannet calibrate` again")


def _visit(robot: Robot, camera: Camera, cfg: CalibrationConfig, index: int, pose: np.ndarray,
           total: int) -> PoseRecord:
    """Move to one grid pose, capture, and find the board from both sides."""
    result = robot.move_to(pose)
    _check_stop(robot, result, f"moving to calibration pose {index + 1}/{total}")
    if not result.success:
        log.warning("pose %d/%d: move failed (%s); skipped", index + 1, total, result.reason)
        return PoseRecord(index, pose, note=f"move failed: {result.reason}")
    if cfg.settle_s > 0:
        time.sleep(cfg.settle_s)  # let the arm stop swaying and the camera deliver a frame taken at rest
    # The measured pose, not the commanded one: the robot may have clamped it or stopped a little off.
    measured = np.asarray(robot.tool_pose(), dtype=np.float64).reshape(6)
    frame = camera.capture()
    point_cam, why = observe_board(frame.color, frame.depth_m, frame.intrinsics, cfg.pattern_corners,
                                   cfg.min_valid_depth_px)
    note = "clamped to the safety box" if result.clamped else ""
    if point_cam is None:
        log.warning("pose %d/%d: %s; skipped", index + 1, total, why)
        return PoseRecord(index, pose, measured, note=why)
    log.info("pose %d/%d: board at %s m (camera frame)", index + 1, total, np.round(point_cam, 4).tolist())
    return PoseRecord(index, pose, measured, point_cam, board_point_base(measured, cfg.board_offset_m), note=note)


def _go_home(robot: Robot) -> None:
    """Home at the end, also after an error (the caller skips it after a stop: the robot must not move)."""
    if robot.stopped:
        log.error("robot stopped (%s): not moving it home", robot.stopped)
        return
    try:
        result = robot.go_home()
    except RobotError as err:
        log.error("could not move home after calibration: %s", err)
        return
    if not result.success:
        log.error("could not move home after calibration: %s", result.reason or result.stopped)


def _fit(records: list[PoseRecord], cfg: CalibrationConfig) -> tuple[FitResult, list[PoseRecord]]:
    used = [r for r in records if r.used]
    try:
        fit = fit_similarity(np.array([r.point_cam for r in used]).reshape(-1, 3),
                             np.array([r.point_base for r in used]).reshape(-1, 3), cfg.min_poses)
    except ValueError as err:
        raise RobotError(f"calibration failed, nothing was written: {err} ({len(records) - len(used)} of "
                         f"{len(records)} poses skipped; see the warnings above)") from None
    residual = {r.index: float(e) for r, e in zip(used, fit.residuals_m, strict=True)}
    return fit, [PoseRecord(r.index, r.commanded, r.measured, r.point_cam, r.point_base,
                            residual.get(r.index), r.note) for r in records]


def _xyz(pose: np.ndarray | None) -> str:
    return "-" if pose is None else " ".join(f"{v:.4f}" for v in pose[:3])


def format_report(fit: FitResult, records: list[PoseRecord], out_path: Path) -> str:
    """The Markdown report: one row per grid pose, then the summary."""
    lines = ["# Camera-to-robot calibration", "",
             f"Written {datetime.now(timezone.utc).isoformat(timespec='seconds')} with the calibration file "
             f"`{out_path.name}` (set `robot.calibration_file` to it).", "",
             "| pose | commanded x y z (m) | measured x y z (m) | board | residual (mm) | note |",
             "|---:|---|---|:---:|---:|---|"]
    for r in records:
        residual = "-" if r.residual_m is None else f"{r.residual_m * 1000:.2f}"
        lines.append(f"| {r.index + 1} | {_xyz(r.commanded)} | {_xyz(r.measured)} | {'yes' if r.used else 'no'} "
                     f"| {residual} | {r.note} |")
    cam = fit.T_base_cam[:3, 3]
    view = fit.T_base_cam[:3, 2]  # the camera's optical axis in the base frame
    lines += ["", f"- poses used: {len(fit.residuals_m)} of {len(records)}",
              f"- RMS residual: {fit.rms_error_m * 1000:.2f} mm; max: {fit.max_error_m * 1000:.2f} mm",
              f"- depth scale: {fit.depth_scale:.5f} (true depth = reported depth x scale)",
              f"- camera position (base frame): {cam[0]:.4f} {cam[1]:.4f} {cam[2]:.4f} m; "
              f"optical axis {view[0]:.3f} {view[1]:.3f} {view[2]:.3f}", ""]
    return "\n".join(lines)


def run_calibration(robot: Robot, camera: Camera, cfg: CalibrationConfig, out_path: str | Path,
                    report_path: str | Path | None = None) -> CalibrationResult:
    """Calibrate with a connected robot and camera; write the calibration file and the report.

    The report goes to report_path (default: out_path with suffix .md). Raises RobotError, with nothing
    written, if the robot stops or too few poses give a usable view.
    """
    out_path = Path(out_path)
    report_path = Path(report_path) if report_path is not None else out_path.with_suffix(".md")
    positions = grid_positions(cfg.grid_x_m, cfg.grid_y_m, cfg.grid_z_m)
    poses = [np.concatenate([p, cfg.tool_rotvec]) for p in positions]
    records: list[PoseRecord] = []
    log.info("calibrating over %d poses; the calibration goes to %s", len(poses), out_path)
    stopped = False
    try:
        _check_stop(robot, robot.go_home(), "moving home before calibration")
        for i, pose in enumerate(poses):
            records.append(_visit(robot, camera, cfg, i, pose, len(poses)))
    except _Stopped:
        stopped = True
        raise
    finally:
        if not stopped:
            _go_home(robot)
    fit, records = _fit(records, cfg)
    write_calibration(out_path, fit)
    write_text_atomic(report_path, format_report(fit, records, out_path))
    cam = fit.T_base_cam[:3, 3]
    log.info("calibration written to %s (report %s): %d poses, RMS %.2f mm, max %.2f mm, depth scale %.4f, "
             "camera at %.3f %.3f %.3f m", out_path, report_path, len(fit.residuals_m), fit.rms_error_m * 1000,
             fit.max_error_m * 1000, fit.depth_scale, *cam)
    return CalibrationResult(fit, tuple(records), out_path, report_path)


def run(args: argparse.Namespace) -> int:
    """`romannet calibrate`: 0 on success, 2 if the RMS residual exceeds calibration.max_rms_error_m."""
    from romannet.common.config import load_config

    cfg = load_config(args.config, args.overrides)
    # The drivers need the optional `robot` extra; imported here so the rest of the CLI works without it.
    from romannet.actor.real.realsense import RealSenseCamera
    from romannet.actor.real.ur import URRobot

    with URRobot(cfg.robot) as robot, RealSenseCamera(cfg.realsense) as camera:
        result = run_calibration(robot, camera, cfg.calibration, args.out, args.report)
    limit = cfg.calibration.max_rms_error_m
    if result.fit.rms_error_m > limit:
        log.warning("RMS residual %.2f mm exceeds calibration.max_rms_error_m = %.2f mm: check the board offset, "
                    "that the board is flat and fixed, and the report %s", result.fit.rms_error_m * 1000,
                    limit * 1000, result.report_path)
        return 2
    return 0
