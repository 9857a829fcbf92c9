"""The simulated cell behind the fake drivers (rtde_control / rtde_receive / rtde_io / pyrealsense2).

A `World` is a UR arm's TCP, its tool (suction cup or gripper on a digital output), boxes on a table (the
plane z = 0 of the robot base frame) and one RGB-D camera, with fault injection and a log of every command.
It is geometry, not physics: moves are instant, an attached box follows the TCP, a released one drops
straight down onto the highest surface under its footprint, so stacking works.

Fake drivers find their world in one process-wide registry, by controller host name or camera serial:
`World(...).register()` in-process, or the JSON file named by $ROMANNET_FAKE_WORLD, loaded on first use
(subprocess tests). A world with `state_path` set rewrites that file (atomically, as `to_json()`) after
every command, so a test can read a subprocess's final world back with `World.load(state_path)`.

The camera (CameraModel, look_at, TABLE_RGB, re-exported here) and `World.render`'s ray casting live in
fakerender.py.
"""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import math
import os
import sys
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

try:
    import fakerender
except ModuleNotFoundError:  # this file was loaded by path, tests/fakes off sys.path (record_real_api.py)
    _spec = importlib.util.spec_from_file_location("fakerender", Path(__file__).with_name("fakerender.py"))
    fakerender = sys.modules["fakerender"] = importlib.util.module_from_spec(_spec)
    _spec.loader.exec_module(fakerender)
from fakerender import TABLE_RGB, CameraModel, look_at  # noqa: F401  (re-exported)

ENV_WORLD = "ROMANNET_FAKE_WORLD"
ROBOT_MODE_RUNNING = 7
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP = 1, 3
SAFETY_SYSTEM_EMERGENCY_STOP, SAFETY_ROBOT_EMERGENCY_STOP = 6, 7
_SUPPORT_EPS_M = 0.005  # a surface this far above a released box's bottom still catches it


@dataclass
class Box:
    """A box: centre and size in metres (base frame), yaw about base z, colour as 0-255 RGB."""

    name: str
    center_m: list[float]
    size_m: list[float]
    yaw_rad: float = 0.0
    rgb: list[int] = field(default_factory=lambda: [200, 40, 40])

    @property
    def top_m(self) -> float:
        return self.center_m[2] + self.size_m[2] / 2

    @property
    def bottom_m(self) -> float:
        return self.center_m[2] - self.size_m[2] / 2

    def contains_xy(self, x: float, y: float) -> bool:
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        dx, dy = x - self.center_m[0], y - self.center_m[1]
        return abs(c * dx + s * dy) <= self.size_m[0] / 2 and abs(-s * dx + c * dy) <= self.size_m[1] / 2

    def corners_xy(self) -> np.ndarray:
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        hx, hy = self.size_m[0] / 2, self.size_m[1] / 2
        local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
        return local @ np.array([[c, s], [-s, c]]) + np.asarray(self.center_m[:2])


def rotvec_to_matrix(rv) -> np.ndarray:
    """Rodrigues' formula (UR poses carry orientation as a rotation vector)."""
    rv = np.asarray(rv, float)
    angle = float(np.linalg.norm(rv))
    if angle < 1e-12:
        return np.eye(3)
    k = rv / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


def _tool_yaw(pose) -> float:
    r = rotvec_to_matrix(pose[3:6])
    return math.atan2(r[1, 0], r[0, 0])  # heading of the tool x axis; the tool points down, so x is level


def _overlap_xy(a: Box, b: Box) -> bool:
    """Do two yawed footprints overlap by more than 1 mm (separating axis test)?"""
    ca, cb = a.corners_xy(), b.corners_xy()
    for yaw in (a.yaw_rad, b.yaw_rad):
        for axis in (np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])):
            pa, pb = ca @ axis, cb @ axis
            if min(pa.max(), pb.max()) - max(pa.min(), pb.min()) < 1e-3:
                return False
    return True


@dataclass
class World:
    """One cell; fields are the JSON form (see the module docstring), methods the behaviour the fakes drive."""

    host: str = "ur-fake"
    home_pose: list[float] = field(default_factory=lambda: [0.5, -0.35, 0.35, math.pi, 0.0, 0.0])
    tcp_pose: list[float] | None = None  # None: starts at home_pose
    tool: str = "suction"  # or "gripper"
    tool_output: str = "tool"  # "tool" (setToolDigitalOut) or "standard" (setStandardDigitalOut)
    tool_output_pin: int = 0
    vacuum_input: int = 16  # getDigitalInState index: 0-7 standard, 8-15 configurable, 16-17 tool
    width_input: int = 0  # the gripper's width on getStandardAnalogInput0 / 1
    width_per_volt_m: float = 0.01  # width = width_per_volt_m * volts + width_offset_m
    width_offset_m: float = 0.0
    gripper_open_width_m: float = 0.085
    finger_axis_tool: list[float] = field(default_factory=lambda: [1.0, 0.0, 0.0])  # fingers close along it
    suction_reach_m: float = 0.01  # the cup attaches this far above a top face ...
    suction_press_m: float = 0.02  # ... or pressed (compliant cup) this far below it
    reach_m: float | None = None  # moveL to a TCP farther than this from the base origin returns False
    objects: list[Box] = field(default_factory=list)
    camera: CameraModel = field(default_factory=CameraModel)
    board: dict | None = None  # checkerboard on the tool: board_offset_m, pattern_corners, square_m
    robot_mode: int = ROBOT_MODE_RUNNING
    safety_mode: int = SAFETY_NORMAL
    protective_stopped: bool = False
    emergency_stopped: bool = False
    program_running: bool = True  # ur_rtde's control script; a stop ends it, a new control connection restarts it
    stops: list[dict] = field(default_factory=list)  # pending injections, see inject_protective_stop
    standard_out: list[bool] = field(default_factory=lambda: [False] * 8)
    tool_out: list[bool] = field(default_factory=lambda: [False] * 2)
    digital_in: list[bool] = field(default_factory=lambda: [False] * 18)
    analog_in: list[float] = field(default_factory=lambda: [0.0, 0.0])
    attached: str | None = None  # name of the box the tool holds
    attach_offset: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0, 0.0])  # TCP yaw frame: xyz, yaw
    grip_width_m: float = 0.0  # the closed fingers' width (0: closed on nothing)
    move_count: int = 0
    calls: list[dict] = field(default_factory=list)
    state_path: str | None = None

    def __post_init__(self) -> None:
        self.objects = [o if isinstance(o, Box) else Box(**o) for o in self.objects]
        if isinstance(self.camera, dict):
            self.camera = CameraModel(**self.camera)
        if self.tcp_pose is None:
            self.tcp_pose = [float(v) for v in self.home_pose]
        self._lock = threading.RLock()  # an actor may read the camera in one thread while moving in another
        self._rng = np.random.default_rng(0)
        self._rays: tuple | None = None

    # ----------------------------------------------------------------------------------------- setup
    def register(self, host: str | None = None, serial: str | None = None) -> World:
        """Make the fake drivers find this world at `host` (default self.host) and camera `serial`."""
        self.host = host or self.host
        self.camera.serial = serial or self.camera.serial
        _HOSTS[self.host] = self
        _SERIALS[self.camera.serial] = self
        return self

    def add_box(self, name: str, center_m, size_m, yaw_rad: float = 0.0, rgb=(200, 40, 40)) -> Box:
        box = Box(name, [float(v) for v in center_m], [float(v) for v in size_m], float(yaw_rad), list(rgb))
        self.objects.append(box)
        return box

    def box(self, name: str) -> Box:
        return next(o for o in self.objects if o.name == name)

    def inject_protective_stop(self, after_moves: int | None = None, when_z_below: float | None = None) -> None:
        """The moveL after `after_moves` more moveL calls (stopping halfway), or the first that would take the
        TCP below `when_z_below` (stopping there), stops early and returns False; the robot stays stopped
        (further moveL return False, the control script ends) until `clear_stop()`."""
        self._inject("protective", after_moves, when_z_below)

    def inject_emergency_stop(self, after_moves: int | None = None, when_z_below: float | None = None,
                              system: bool = False) -> None:
        """Like inject_protective_stop, as an emergency stop: safety mode 7 (robot), or 6 with system=True."""
        self._inject("system_emergency" if system else "emergency", after_moves, when_z_below)

    def _inject(self, kind: str, after_moves: int | None, when_z_below: float | None) -> None:
        if (after_moves is None) == (when_z_below is None):
            raise ValueError("give exactly one of after_moves or when_z_below")
        at = None if after_moves is None else self.move_count + int(after_moves) + 1
        self.stops.append({"kind": kind, "at_move": at, "when_z_below": when_z_below})

    def clear_stop(self) -> None:
        """The operator clears the stop on the pendant; the control script stays ended until reconnected."""
        with self._lock:
            self.protective_stopped = self.emergency_stopped = False
            self.safety_mode = SAFETY_NORMAL
            self._log({"call": "clear_stop"})

    def moves(self) -> list[dict]:
        """Every moveL call so far: pose, speed, acceleration, asynchronous, result."""
        return [c for c in self.calls if c["call"] == "moveL"]

    # --------------------------------------------------------------------------------- robot behaviour
    @property
    def stopped(self) -> bool:
        return self.protective_stopped or self.emergency_stopped

    def move_linear(self, pose, speed: float, acceleration: float, asynchronous: bool) -> bool:
        with self._lock:
            pose = [float(v) for v in pose]
            record = {"call": "moveL", "pose": pose, "speed": float(speed), "acceleration": float(acceleration),
                      "asynchronous": bool(asynchronous)}
            self.move_count += 1
            ok = self._move(pose, record)
            record["result"] = ok
            self._log(record)
            return ok

    def _move(self, pose: list[float], record: dict) -> bool:
        if len(pose) != 6 or not all(math.isfinite(v) for v in pose):
            raise ValueError(f"moveL needs 6 finite numbers, got {pose}")
        if self.stopped or not self.program_running:
            return False
        if self.reach_m is not None and float(np.linalg.norm(pose[:3])) > self.reach_m:
            record["refused"] = "out_of_reach"
            return False
        start = np.asarray(self.tcp_pose, float)
        for stop in list(self.stops):
            frac = None
            if stop["at_move"] is not None and self.move_count >= stop["at_move"]:
                frac = 0.5
            elif stop["when_z_below"] is not None and pose[2] < stop["when_z_below"]:
                z0, z1 = start[2], pose[2]
                frac = 0.0 if z0 <= stop["when_z_below"] else (z0 - stop["when_z_below"]) / (z0 - z1)
            if frac is not None:
                self.stops.remove(stop)
                self._set_tcp(list(start + frac * (np.asarray(pose) - start)))
                self._trip(stop["kind"])
                record["stopped"] = stop["kind"]
                return False
        self._set_tcp(pose)
        if self.tool == "suction" and self._tool_on() and self.attached is None:
            self._try_suction()  # the cup seals as it touches with the vacuum already on
        return True

    def _trip(self, kind: str) -> None:
        self.program_running = False  # the controller ends ur_rtde's script on any stop
        if kind == "protective":
            self.protective_stopped, self.safety_mode = True, SAFETY_PROTECTIVE_STOP
        else:
            self.emergency_stopped = True
            self.safety_mode = SAFETY_SYSTEM_EMERGENCY_STOP if kind.startswith("system") else \
                SAFETY_ROBOT_EMERGENCY_STOP

    def _set_tcp(self, pose: list[float]) -> None:
        self.tcp_pose = [float(v) for v in pose]
        if self.attached is not None:
            box, (ox, oy, oz, oyaw) = self.box(self.attached), self.attach_offset
            yaw = _tool_yaw(self.tcp_pose)
            c, s = math.cos(yaw), math.sin(yaw)
            box.center_m = [pose[0] + c * ox - s * oy, pose[1] + s * ox + c * oy, pose[2] + oz]
            box.yaw_rad = yaw + oyaw

    def _attach(self, box: Box) -> None:
        yaw = _tool_yaw(self.tcp_pose)
        c, s = math.cos(yaw), math.sin(yaw)
        dx, dy = box.center_m[0] - self.tcp_pose[0], box.center_m[1] - self.tcp_pose[1]
        self.attached = box.name
        self.attach_offset = [c * dx + s * dy, -s * dx + c * dy, box.center_m[2] - self.tcp_pose[2],
                              box.yaw_rad - yaw]

    def _under_tcp(self) -> list[Box]:
        x, y = self.tcp_pose[0], self.tcp_pose[1]
        return sorted((o for o in self.objects if o.name != self.attached and o.contains_xy(x, y)),
                      key=lambda o: o.top_m, reverse=True)

    def _try_suction(self) -> None:
        under = self._under_tcp()
        if under and under[0].top_m - self.suction_press_m <= self.tcp_pose[2] <= under[0].top_m + self.suction_reach_m:
            self._attach(under[0])

    def _close_gripper(self) -> None:
        axis = rotvec_to_matrix(self.tcp_pose[3:6]) @ np.asarray(self.finger_axis_tool, float)
        axis = axis[:2] / max(float(np.linalg.norm(axis[:2])), 1e-9)
        z = self.tcp_pose[2]
        for box in self._under_tcp():
            if box.bottom_m - _SUPPORT_EPS_M <= z <= box.top_m:  # the fingertips straddle this box
                c, s = math.cos(box.yaw_rad), math.sin(box.yaw_rad)
                width = abs(axis @ (c, s)) * box.size_m[0] + abs(axis @ (-s, c)) * box.size_m[1]
                if width <= self.gripper_open_width_m:
                    self.grip_width_m = float(width)
                    self._attach(box)
                return
        self.grip_width_m = 0.0

    def _release(self) -> None:
        if self.attached is None:
            return
        box = self.box(self.attached)
        self.attached, self.grip_width_m = None, 0.0
        support = max([o.top_m for o in self.objects if o is not box and o.top_m <= box.bottom_m + _SUPPORT_EPS_M
                       and _overlap_xy(o, box)], default=0.0)
        box.center_m[2] = support + box.size_m[2] / 2

    def _tool_on(self) -> bool:
        outs = self.tool_out if self.tool_output == "tool" else self.standard_out
        return bool(outs[self.tool_output_pin])

    def set_digital_out(self, kind: str, pin: int, level: bool) -> bool:
        with self._lock:
            outs = self.tool_out if kind == "tool" else self.standard_out
            if not 0 <= pin < len(outs):
                raise ValueError(f"{kind} digital output id {pin} is out of range [0:{len(outs) - 1}]")
            was = self._tool_on()
            outs[pin] = bool(level)
            now = self._tool_on()
            if now and not was:
                self._try_suction() if self.tool == "suction" else self._close_gripper()
            elif was and not now:
                self._release()
            name = "setToolDigitalOut" if kind == "tool" else "setStandardDigitalOut"
            self._log({"call": name, "pin": int(pin), "level": bool(level), "result": True})
            return True

    def digital_input(self, index: int) -> bool:
        if self.tool == "suction" and index == self.vacuum_input:
            return self._tool_on() and self.attached is not None
        return bool(self.digital_in[index])

    def analog_input(self, index: int) -> float:
        if self.tool == "gripper" and index == self.width_input:
            width = self.grip_width_m if self._tool_on() else self.gripper_open_width_m
            return (width - self.width_offset_m) / self.width_per_volt_m
        return float(self.analog_in[index])

    def log_call(self, record: dict) -> None:
        with self._lock:
            self._log(record)

    def _log(self, record: dict) -> None:
        self.calls.append(record)
        if self.state_path:
            self.save(self.state_path)

    # ------------------------------------------------------------------------------------------ camera
    def render(self) -> tuple[np.ndarray, np.ndarray]:
        """What the camera sees now: colour uint8 (H, W, 3) RGB and true depth_m float32 (H, W), 0 = none."""
        return fakerender.render(self)

    # -------------------------------------------------------------------------------------------- JSON
    def to_json(self) -> str:
        data = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        data["objects"] = [dataclasses.asdict(o) for o in self.objects]
        data["camera"] = dataclasses.asdict(self.camera)
        return json.dumps(data)

    @classmethod
    def from_json(cls, text: str) -> World:
        return cls(**json.loads(text))

    def save(self, path: str | os.PathLike) -> None:
        """Write to_json() atomically (a reader never sees half a file)."""
        tmp = f"{path}.tmp{os.getpid()}"
        Path(tmp).write_text(self.to_json())
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: str | os.PathLike) -> World:
        return cls.from_json(Path(path).read_text())


# ---------------------------------------------------------------------------------------------- registry
_HOSTS: dict[str, World] = {}
_SERIALS: dict[str, World] = {}
_env_loaded = False


def reset_registry() -> None:
    """Forget every registered world (and reload $ROMANNET_FAKE_WORLD on next use, if set)."""
    global _env_loaded
    _HOSTS.clear()
    _SERIALS.clear()
    _env_loaded = False


def _load_env() -> None:
    global _env_loaded
    if not _env_loaded and not _HOSTS and not _SERIALS and os.environ.get(ENV_WORLD):
        World.load(os.environ[ENV_WORLD]).register()
    _env_loaded = True


def world_for_host(host: str) -> World | None:
    _load_env()
    return _HOSTS.get(host)


def world_for_serial(serial: str) -> World | None:
    _load_env()
    return _SERIALS.get(serial)


def camera_serials() -> list[str]:
    """Serials of the connected cameras, in registration order."""
    _load_env()
    return [s for s, w in _SERIALS.items() if w.camera.connected]
