"""Fake `pyrealsense2`: the classes and methods our RealSense code calls, with the real names and signatures.

Devices are the cameras of the registered fakeworld.World objects (by serial); frames are the world rendered
by numpy ray casting at wait_for_frames time, depth and colour already aligned (same intrinsics), so
`align.process` returns them unchanged. tests/test_real_fakes.py checks every name and signature here
against the real module (tests/fakes/real_api.json). Errors carry the real library's messages.
"""

from __future__ import annotations

import enum as _enum
import time as _time

import fakeworld as _fw
import numpy as _np


class stream(_enum.IntEnum):
    any = 0
    depth = 1
    color = 2
    infrared = 3


class format(_enum.IntEnum):
    any = 0
    z16 = 1
    rgb8 = 5
    bgr8 = 6


class camera_info(_enum.IntEnum):
    name = 0
    serial_number = 1
    firmware_version = 2
    product_line = 10


_FPS = (6, 15, 30, 60)


class intrinsics:
    """Pinhole intrinsics of a stream (no distortion)."""

    width: int = 0
    height: int = 0
    ppx: float = 0.0
    ppy: float = 0.0
    fx: float = 0.0
    fy: float = 0.0
    coeffs: list[float] = [0.0] * 5  # read-only, as the real default


class depth_sensor:
    def get_depth_scale(self) -> float:
        return self._scale


class device:
    def __init__(self) -> None:
        self._world: _fw.World | None = None

    def get_info(self, info: camera_info) -> str:
        cam = self._world.camera
        values = {camera_info.name: "Intel RealSense D435", camera_info.serial_number: cam.serial,
                  camera_info.firmware_version: "5.16.0.1", camera_info.product_line: "D400"}
        if info not in values:
            raise RuntimeError(f"Device does not support {info!r}")
        return values[info]

    def supports(self, info: camera_info) -> bool:
        return info in (camera_info.name, camera_info.serial_number, camera_info.firmware_version,
                        camera_info.product_line)

    def first_depth_sensor(self) -> depth_sensor:
        sensor = depth_sensor()
        sensor._scale = float(self._world.camera.depth_scale)
        return sensor


def _device(world: _fw.World) -> device:
    dev = device()
    dev._world = world
    return dev


class device_list:
    def __init__(self) -> None:
        self._devices: list[device] = []

    def __len__(self) -> int:
        return len(self._devices)

    def __getitem__(self, arg0: int) -> device:
        return self._devices[arg0]

    def __iter__(self):
        return iter(self._devices)

    def size(self) -> int:
        return len(self._devices)

    def front(self) -> device:
        return self._devices[0]

    def back(self) -> device:
        return self._devices[-1]


class context:
    def __init__(self) -> None:
        pass

    def query_devices(self) -> device_list:
        devices = device_list()
        devices._devices = [_device(_fw.world_for_serial(s)) for s in _fw.camera_serials()]
        return devices


class stream_profile:
    def __init__(self) -> None:
        self._stream, self._format, self._fps, self._intrinsics = stream.any, format.any, 0, intrinsics()

    def stream_type(self) -> stream:
        return self._stream

    def format(self) -> format:
        return self._format

    def fps(self) -> int:
        return self._fps

    def as_video_stream_profile(self) -> video_stream_profile:
        return self


class video_stream_profile(stream_profile):
    def get_intrinsics(self) -> intrinsics:
        return self._intrinsics

    def width(self) -> int:
        return self._intrinsics.width

    def height(self) -> int:
        return self._intrinsics.height


class config:
    def __init__(self) -> None:
        self._serial: str | None = None
        self._streams: dict[stream, tuple[int, int, format, int]] = {}

    def enable_device(self, serial: str) -> None:
        self._serial = serial

    def enable_stream(self, stream_type: stream, width: int, height: int, format: format, framerate: int) -> None:
        self._streams[stream(stream_type)] = (width, height, format, framerate)

    def disable_all_streams(self) -> None:
        self._streams.clear()


class pipeline_profile:
    def __init__(self) -> None:
        self._world: _fw.World | None = None
        self._profiles: dict[stream, video_stream_profile] = {}

    def get_device(self) -> device:
        return _device(self._world)

    def get_stream(self, stream_type: stream, stream_index: int = -1) -> stream_profile:
        if stream_type not in self._profiles:
            raise RuntimeError("Profile does not contain the requested stream")
        return self._profiles[stream_type]

    def get_streams(self) -> list[stream_profile]:
        return list(self._profiles.values())


def _resolve(world: _fw.World, requests: dict) -> dict[stream, video_stream_profile]:
    """Stream profiles the fake camera can give for the requests (its one resolution, z16 / rgb8 / bgr8)."""
    cam = world.camera
    requests = requests or {stream.depth: (0, 0, format.z16, 30), stream.color: (0, 0, format.rgb8, 30)}
    formats = {stream.depth: (format.z16,), stream.color: (format.rgb8, format.bgr8)}
    profiles = {}
    for kind, (w, h, fmt, fps) in requests.items():
        fmt = formats.get(kind, (None,))[0] if fmt == format.any else fmt
        if (kind not in formats or fmt not in formats[kind] or w not in (0, cam.width) or h not in (0, cam.height)
                or fps not in (0, *_FPS)):
            raise RuntimeError("Couldn't resolve requests")
        prof = video_stream_profile()
        prof._stream, prof._format, prof._fps = kind, format(fmt), fps or 30
        i = prof._intrinsics = intrinsics()
        i.width, i.height, i.fx, i.fy, i.ppx, i.ppy = cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy
        profiles[kind] = prof
    return profiles


class frame:
    def __init__(self) -> None:
        self._data: _np.ndarray | None = None
        self._timestamp_ms, self._number, self._units = 0.0, 0, 0.0

    def __bool__(self) -> bool:
        return self._data is not None

    def _check(self) -> None:
        if self._data is None:
            raise RuntimeError('null pointer passed for argument "frame_ref"')

    def get_data(self) -> _np.ndarray:
        self._check()
        return self._data

    def get_timestamp(self) -> float:
        self._check()
        return self._timestamp_ms

    def get_frame_number(self) -> int:
        self._check()
        return self._number


class video_frame(frame):
    def get_width(self) -> int:
        self._check()
        return int(self._data.shape[1])

    def get_height(self) -> int:
        self._check()
        return int(self._data.shape[0])


class depth_frame(video_frame):
    def get_units(self) -> float:
        self._check()
        return self._units

    def get_distance(self, x: int, y: int) -> float:
        self._check()
        return float(self._data[y, x]) * self._units


class composite_frame(frame):
    _frames: list[frame] = []  # replaced per instance by pipeline.wait_for_frames

    def get_depth_frame(self) -> depth_frame:
        return next((f for f in self._frames if isinstance(f, depth_frame)), depth_frame())

    def get_color_frame(self, index: int = 0) -> video_frame:
        return next((f for f in self._frames if not isinstance(f, depth_frame)), video_frame())

    def size(self) -> int:
        return len(self._frames)

    def __len__(self) -> int:
        return len(self._frames)

    def __getitem__(self, arg0: int) -> frame:
        return self._frames[arg0]

    def __iter__(self):
        return iter(self._frames)


class align:
    def __init__(self, align_to: stream) -> None:
        self._align_to = align_to

    def process(self, frames: composite_frame) -> composite_frame:
        return frames  # the fake streams share one set of intrinsics: already aligned


class pipeline:
    def __init__(self, ctx: context = None) -> None:
        self._profile: pipeline_profile | None = None
        self._frame_number = 0

    def start(self, config: config = None) -> pipeline_profile:
        if self._profile is not None:
            raise RuntimeError("start() cannot be called before stop()")
        serials = _fw.camera_serials()
        if not serials:
            raise RuntimeError("No device connected")
        serial = config._serial if config is not None and config._serial else serials[0]
        if serial not in serials:
            raise RuntimeError("Couldn't resolve requests")
        profile = pipeline_profile()
        profile._world = _fw.world_for_serial(serial)
        profile._profiles = _resolve(profile._world, config._streams if config is not None else {})
        self._profile = profile
        return profile

    def stop(self) -> None:
        if self._profile is None:
            raise RuntimeError("stop() cannot be called before start()")
        self._profile = None

    def get_active_profile(self) -> pipeline_profile:
        if self._profile is None:
            raise RuntimeError("get_active_profile() can only be called between a start() and a following stop()")
        return self._profile

    def wait_for_frames(self, timeout_ms: int = 5000) -> composite_frame:
        if self._profile is None:
            raise RuntimeError("wait_for_frames cannot be called before start()")
        world = self._profile._world
        if world.camera.timeout or not world.camera.connected:
            raise RuntimeError(f"Frame didn't arrive within {timeout_ms}")
        color, depth_m = world.render()
        self._frame_number += 1
        frames = composite_frame()
        frames._frames = []
        frames._timestamp_ms, frames._number = _time.time() * 1000.0, self._frame_number
        frames._data = _np.zeros(0, _np.uint8)
        for kind, prof in self._profile._profiles.items():
            if kind == stream.depth:
                f = depth_frame()
                f._units = float(world.camera.depth_scale)
                f._data = _np.clip(_np.rint(depth_m / f._units), 0, 65535).astype(_np.uint16)
            else:
                f = video_frame()
                f._data = _np.ascontiguousarray(color if prof._format == format.rgb8 else color[..., ::-1])
            f._timestamp_ms, f._number = frames._timestamp_ms, frames._number
            frames._frames.append(f)
        return frames
