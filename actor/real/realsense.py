"""RealSenseCamera: an Intel RealSense D4xx through pyrealsense2 (the `robot` extra).

Streams depth (z16) and colour (rgb8) at the configured size and rate, aligns depth to colour with
`rs.align`, converts depth to metres with the device's depth scale, and reports the colour stream's
intrinsics from the device. Connect-time checks (RobotError naming what is wrong): the driver imports, a
camera is attached (the one with the configured serial number, or exactly one), streaming starts, and the
first frames arrive (dropped while auto-exposure settles).
"""

from __future__ import annotations

import ctypes
import importlib
import logging

import numpy as np

from romannet.common.config_robot import RealSenseConfig
from romannet.common.errors import RobotError
from romannet.common.interfaces import CameraFrame

log = logging.getLogger(__name__)


def import_pyrealsense2():
    """Import pyrealsense2; where the system has no libusb-1.0, load the one libusb-package carries first."""
    try:
        return importlib.import_module("pyrealsense2")
    except ImportError as err:
        if "libusb" not in str(err):
            raise RobotError(f"pyrealsense2 is not installed ({err}); install the robot extra: "
                             "pip install 'romannet[robot]'") from None
        first = err
    try:
        import libusb_package

        ctypes.CDLL(str(libusb_package.get_library_path()), mode=ctypes.RTLD_GLOBAL)
        return importlib.import_module("pyrealsense2")
    except (ImportError, OSError, TypeError) as err:
        raise RobotError(f"pyrealsense2 needs libusb-1.0 ({first}); install the system package (libusb-1.0-0) or "
                         f"pip install libusb-package ({err})") from None


def intrinsics_matrix(intr) -> np.ndarray:
    """3x3 pinhole matrix from a pyrealsense2 intrinsics object (fx, fy, ppx, ppy)."""
    return np.array([[intr.fx, 0.0, intr.ppx], [0.0, intr.fy, intr.ppy], [0.0, 0.0, 1.0]], dtype=np.float64)


class RealSenseCamera:
    """The Camera interface (common.interfaces.Camera) on pyrealsense2; see the module docstring."""

    def __init__(self, cfg: RealSenseConfig):
        self.cfg = cfg
        self.rs = None
        self._pipeline = None
        self._align = None
        self.depth_scale_m = 0.0  # metres per z16 unit, from the device
        self.intrinsics = np.eye(3)
        self.serial = ""

    def __enter__(self) -> RealSenseCamera:
        self.connect()
        return self

    def __exit__(self, *exc: object) -> None:
        self.disconnect()

    def _pick_serial(self, rs) -> str:
        serials = [dev.get_info(rs.camera_info.serial_number) for dev in rs.context().query_devices()]
        if not serials:
            raise RobotError("no RealSense camera is connected (pyrealsense2 sees none): check the USB 3 cable "
                             "and the udev rules (librealsense's 99-realsense-libusb.rules)")
        if self.cfg.serial:
            if self.cfg.serial not in serials:
                raise RobotError(f"no RealSense camera with serial {self.cfg.serial!r}; connected: {serials}")
            return self.cfg.serial
        if len(serials) > 1:
            raise RobotError(f"{len(serials)} RealSense cameras are connected ({serials}): set realsense.serial")
        return serials[0]

    def connect(self) -> None:
        if self._pipeline is not None:
            return
        rs = self.rs = import_pyrealsense2()
        self.serial = self._pick_serial(rs)
        c = self.cfg
        config = rs.config()
        config.enable_device(self.serial)
        config.enable_stream(rs.stream.depth, c.width_px, c.height_px, rs.format.z16, c.fps)
        config.enable_stream(rs.stream.color, c.width_px, c.height_px, rs.format.rgb8, c.fps)
        pipeline = rs.pipeline()
        try:
            profile = pipeline.start(config)
        except RuntimeError as err:
            raise RobotError(f"cannot start the RealSense {self.serial} at {c.width_px}x{c.height_px}@{c.fps}: "
                             f"{err} (another program using it? a mode the model lacks?)") from None
        self._pipeline = pipeline
        try:
            self.depth_scale_m = float(profile.get_device().first_depth_sensor().get_depth_scale())
            intr = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
            self.intrinsics = intrinsics_matrix(intr)
            if not (0 < self.depth_scale_m < 0.1) or not np.all(np.isfinite(self.intrinsics)):
                raise RobotError(f"the RealSense {self.serial} reports depth scale {self.depth_scale_m} and "
                                 f"intrinsics {self.intrinsics.tolist()}: not usable")
            self._align = rs.align(rs.stream.color)
            for _ in range(c.warmup_frames):
                self._frames()
        except BaseException:
            self.disconnect()
            raise
        log.info("RealSense %s streaming %dx%d@%d, depth scale %.6f m, fx %.1f fy %.1f cx %.1f cy %.1f",
                 self.serial, c.width_px, c.height_px, c.fps, self.depth_scale_m, self.intrinsics[0, 0],
                 self.intrinsics[1, 1], self.intrinsics[0, 2], self.intrinsics[1, 2])

    def disconnect(self) -> None:
        if self._pipeline is None:
            return
        try:
            self._pipeline.stop()
        except RuntimeError as err:  # unplugged: nothing left to release
            log.warning("stopping the RealSense %s: %s", self.serial, err)
        self._pipeline = None

    def _frames(self):
        if self._pipeline is None:
            raise RobotError("the camera is not connected: call connect() (or use it as a context manager)")
        try:
            frames = self._pipeline.wait_for_frames(int(self.cfg.timeout_s * 1000))
        except RuntimeError as err:
            raise RobotError(f"no frames from the RealSense {self.serial} within {self.cfg.timeout_s} s: {err}") \
                from None
        return self._align.process(frames)

    def capture(self) -> CameraFrame:
        aligned = self._frames()
        depth, color = aligned.get_depth_frame(), aligned.get_color_frame()
        if not depth or not color:
            raise RobotError(f"the RealSense {self.serial} delivered a frame set without depth or colour")
        z16 = np.asanyarray(depth.get_data())
        rgb = np.asanyarray(color.get_data())
        shape = (self.cfg.height_px, self.cfg.width_px)
        if z16.shape != shape or rgb.shape != (*shape, 3) or rgb.dtype != np.uint8:
            raise RobotError(f"the RealSense {self.serial} delivered depth {z16.shape} / colour {rgb.shape} "
                             f"{rgb.dtype}; expected {shape} z16 and {(*shape, 3)} uint8")
        depth_m = z16.astype(np.float32) * np.float32(self.depth_scale_m)  # 0 stays 0: no reading
        return CameraFrame(np.ascontiguousarray(rgb), depth_m, self.intrinsics.copy(),
                           float(color.get_timestamp()) / 1000.0)
