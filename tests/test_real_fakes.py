"""The fake ur_rtde / pyrealsense2 drivers (tests/fakes): their API against the real one, and the fake cell.

Conformance: every class and member a fake defines exists in the real API (snapshot tests/fakes/real_api.json,
re-checked against the installed drivers where they import) and its parameters (names, order, defaults)
match a real overload, so code that runs on the fakes calls nothing the real drivers lack.
"""

from __future__ import annotations

import ast
import enum
import inspect
import json
import math
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from _fake_drivers import FAKES_DIR, fake_driver_env, fake_drivers, fakeworld

sys.path.insert(0, str(FAKES_DIR))  # record_real_api is a script beside the fakes, not a package
import record_real_api as rec  # noqa: E402

sys.path.remove(str(FAKES_DIR))

fw = fakeworld()
SNAPSHOT = json.loads(rec.SNAPSHOT.read_text())
DOWN = (math.pi, 0.0, 0.0)  # tool pointing straight down


# ------------------------------------------------------------------------------------------ conformance
def parse_params(line: str) -> list[tuple[str, bool, object]]:
    """(name, has_default, default) per parameter of a pybind signature line `f(a: T, b: U = 1) -> R`."""
    body, depth, start = line[line.index("(") + 1:], 0, 0
    parts = []
    for i, ch in enumerate(body):
        if ch in "([<":
            depth += 1
        elif ch in ")]>" and depth:
            depth -= 1
        elif ch == ")" or (ch == "," and depth == 0):
            parts.append(body[start:i])
            start = i + 1
            if ch == ")":
                break
    out = []
    for part in filter(str.strip, parts):
        decl, sep, default = part.partition(" = ")
        out.append((decl.split(":")[0].strip(), bool(sep), _default(default.strip()) if sep else None))
    return out


def _default(text: str) -> object:
    enum_value = re.fullmatch(r"<[\w.]+: (-?\d+)>", text)  # pybind enum repr, e.g. <Flags.FLAG_UPLOAD_SCRIPT: 1>
    return int(enum_value.group(1)) if enum_value else ast.literal_eval(text)


def _same(a: object, b: object) -> bool:
    return isinstance(a, bool) == isinstance(b, bool) and a == b  # False == 0, but not the same default


def _serves(overload: list, params: list[inspect.Parameter], k: int) -> bool:
    """Is a call of the fake giving its first k parameters a valid call of this real overload, with the fake's
    defaults for the rest equal to the real ones (or None where the overload has no such parameter)?"""
    if [name for name, _, _ in overload[:k]] != [p.name for p in params[:k]]:
        return False
    if not all(has_default for _, has_default, _ in overload[k:]):
        return False
    for i, param in enumerate(params[k:], start=k):
        if i < len(overload):
            name, _, default = overload[i]
            if name != param.name or not _same(param.default, default):
                return False
        elif param.default is not None:
            return False
    return True


def signature_problem(func, real_lines: list[str]) -> str:
    """'' if every way of calling `func` positionally or by keyword is valid on one real overload."""
    params = list(inspect.signature(func).parameters.values())
    if any(p.kind not in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD) for p in params):
        return "takes *args, **kwargs or keyword-only parameters: spell out the real parameters"
    overloads = [parse_params(line) for line in real_lines]
    required = sum(p.default is p.empty for p in params)
    for k in range(required, len(params) + 1):
        if not any(_serves(o, params, k) for o in overloads):
            return f"{func.__name__}{inspect.signature(func)} (called with {k} arguments) matches none of {real_lines}"
    return ""


def api_problems(module: str, fake) -> list[str]:
    """Everything public the fake module defines that the real API (the snapshot) lacks or spells otherwise."""
    real, problems = SNAPSHOT[module]["classes"], []
    for name, value in vars(fake).items():
        if name.startswith("_") or type(value).__module__ == "__future__":
            continue
        if not (isinstance(value, type) and value.__module__ == fake.__name__):
            problems.append(f"{module}.{name}: public but not a class of the fake (import it as _{name})")
    for cls_name, cls in rec.fake_classes(fake).items():
        if cls_name not in real:
            problems.append(f"{module}.{cls_name}: no such class in the real module")
            continue
        for member in rec.fake_members(cls):
            where, entry = f"{module}.{cls_name}.{member}", real[cls_name].get(member)
            if entry is None:
                problems.append(f"{where}: not in the real API")
            elif issubclass(cls, enum.Enum):
                if int(cls[member]) != entry:
                    problems.append(f"{where} = {int(cls[member])}, the real value is {entry}")
            elif entry == "attribute":
                if callable(vars(cls)[member]):
                    problems.append(f"{where}: a method in the fake, an attribute in the real module")
            elif not callable(vars(cls)[member]):
                problems.append(f"{where}: an attribute in the fake, a method in the real module")
            else:
                problem = signature_problem(vars(cls)[member], entry)
                if problem:
                    problems.append(f"{where}: {problem}")
    return problems


@pytest.mark.parametrize("module", rec.MODULES)
def test_fake_api_is_the_real_api(module):
    problems = api_problems(module, rec.load_fake(module))
    assert not problems, "\n".join(problems)


def test_signature_check_catches_mismatches():
    move_l = ["moveL(self: C, path: list[list[float]], asynchronous: bool = False) -> bool",
              "moveL(self: C, pose: list[float], speed: float = 0.25, acceleration: float = 1.2, "
              "asynchronous: bool = False) -> bool"]

    def good(self, pose, speed=0.25, acceleration=1.2, asynchronous=False): ...
    def prefix(self, pose, speed=0.25): ...  # the real defaults fill the rest
    def renamed(self, pose, velocity=0.25, acceleration=1.2, asynchronous=False): ...
    def other_default(self, pose, speed=0.5, acceleration=1.2, asynchronous=False): ...
    def extra(self, pose, speed=0.25, acceleration=1.2, asynchronous=False, blend=0.0): ...
    def loose(self, pose, **kwargs): ...

    assert signature_problem(good, move_l) == signature_problem(prefix, move_l) == ""
    for bad in (renamed, other_default, extra, loose):
        assert signature_problem(bad, move_l), bad.__name__
    start = ["start(self: P) -> Q", "start(self: P, config: C) -> Q"]

    def start_opt(self, config=None): ...
    def start_bad(self, config=1): ...

    assert signature_problem(start_opt, start) == "" and signature_problem(start_bad, start)
    init = "__init__(self: C, hostname: str, frequency: float = -1.0, flags: int = <Flags.FLAG_UPLOAD_SCRIPT: 1>) -> None"
    assert parse_params(init)[3] == ("flags", True, 1)


@pytest.mark.parametrize("module", rec.MODULES)
def test_snapshot_is_what_the_installed_driver_says(module):
    try:
        real = rec.import_real(module)
    except (ImportError, OSError) as err:
        pytest.skip(f"the real {module} does not import here ({err}); real_api.json stands in for it")
    assert rec.record(real, rec.load_fake(module)) == SNAPSHOT[module]["classes"], \
        "the installed driver differs from tests/fakes/real_api.json: re-run tests/fakes/record_real_api.py"


# ----------------------------------------------------------------------------------------- the fake cell
@pytest.fixture
def drv():
    """The fake driver modules (registry empty: a test registers its worlds)."""
    with fake_drivers():
        yield {name: sys.modules[name] for name in rec.MODULES}


def arm(drv, world):
    world.register()
    host = world.host
    return (drv["rtde_control"].RTDEControlInterface(host), drv["rtde_receive"].RTDEReceiveInterface(host),
            drv["rtde_io"].RTDEIOInterface(host))


def down(yaw_rad: float = 0.0) -> tuple[float, float, float]:
    """Rotation vector of the tool pointing down, turned by yaw about base z: a half turn about a level axis."""
    return (math.pi * math.cos(yaw_rad / 2), math.pi * math.sin(yaw_rad / 2), 0.0)


def test_unknown_host_fails_like_the_real_driver(drv):
    for make in (drv["rtde_receive"].RTDEReceiveInterface, drv["rtde_control"].RTDEControlInterface,
                 drv["rtde_io"].RTDEIOInterface):
        with pytest.raises(RuntimeError, match=r"^Error: Could not connect to: 10\.0\.0\.9 at 30004, verify the IP$"):
            make("10.0.0.9")


def test_suction_picks_releases_and_stacks(drv):
    world = fw.World()
    a = world.add_box("a", (0.4, 0.1, 0.025), (0.05, 0.05, 0.05))
    world.add_box("b", (0.6, -0.1, 0.025), (0.05, 0.05, 0.05), yaw_rad=0.3)
    ctl, rcv, io = arm(drv, world)
    assert rcv.getRobotMode() == 7 and rcv.getSafetyMode() == 1 and ctl.isProgramRunning()
    assert rcv.getActualTCPPose() == pytest.approx(world.home_pose)
    assert ctl.moveL([0.4, 0.1, 0.15, *down()])
    assert io.setToolDigitalOut(0, True) and not rcv.getDigitalInState(16)  # vacuum on in the air
    assert ctl.moveL([0.4, 0.1, 0.04, *down()], 0.05)  # 1 cm into the (compliant) cup: seals
    assert rcv.getDigitalInState(16)
    assert ctl.moveL([0.6, -0.1, 0.2, *down(0.5)])
    assert a.center_m == pytest.approx([0.6, -0.1, 0.185]) and a.yaw_rad == pytest.approx(0.5)
    io.setToolDigitalOut(0, False)
    assert not rcv.getDigitalInState(16)
    assert a.center_m == pytest.approx([0.6, -0.1, 0.075])  # on b's top face
    # The cup reaches the top of the stack only, and a box released over the table lands on it.
    ctl.moveL([0.6, -0.1, 0.095, *down()])
    io.setToolDigitalOut(0, True)
    assert world.attached == "a"
    ctl.moveL([0.3, 0.2, 0.3, *down()])
    io.setToolDigitalOut(0, False)
    assert a.center_m == pytest.approx([0.3, 0.2, 0.025])
    ctl.moveL([0.5, 0.0, 0.1, *down()])  # nothing under the cup
    io.setToolDigitalOut(0, True)
    assert not rcv.getDigitalInState(16)


def test_vacuum_on_a_standard_output(drv):
    world = fw.World(tool_output="standard", tool_output_pin=3, vacuum_input=2)
    world.add_box("a", (0.4, 0.0, 0.02), (0.04, 0.04, 0.04))
    ctl, rcv, io = arm(drv, world)
    ctl.moveL([0.4, 0.0, 0.035, *down()])
    io.setToolDigitalOut(0, True)
    assert not rcv.getDigitalInState(2)
    io.setStandardDigitalOut(3, True)
    assert rcv.getDigitalInState(2) and rcv.getDigitalOutState(3)
    with pytest.raises(ValueError):
        io.setToolDigitalOut(2, True)


def test_gripper_width_along_the_fingers(drv):
    world = fw.World(tool="gripper", width_input=1, width_per_volt_m=0.01, width_offset_m=0.0)
    bar = world.add_box("bar", (0.5, 0.0, 0.02), (0.06, 0.03, 0.04))
    ctl, rcv, io = arm(drv, world)
    assert rcv.getStandardAnalogInput1() == pytest.approx(8.5)  # open: 85 mm
    ctl.moveL([0.5, 0.0, 0.03, *down()])
    io.setToolDigitalOut(0, True)
    assert rcv.getStandardAnalogInput1() == pytest.approx(6.0)  # fingers along x: the 6 cm side
    ctl.moveL([0.45, 0.05, 0.2, *down()])
    assert bar.center_m == pytest.approx([0.45, 0.05, 0.19])
    io.setToolDigitalOut(0, False)
    assert bar.center_m == pytest.approx([0.45, 0.05, 0.02])
    ctl.moveL([0.45, 0.05, 0.03, *down(math.pi / 2)])
    io.setToolDigitalOut(0, True)
    assert rcv.getStandardAnalogInput1() == pytest.approx(3.0)  # turned a quarter: the 3 cm side
    io.setToolDigitalOut(0, False)
    ctl.moveL([0.6, 0.1, 0.03, *down()])
    io.setToolDigitalOut(0, True)
    assert rcv.getStandardAnalogInput1() == pytest.approx(0.0)  # closed on nothing


def test_protective_stop_until_cleared_and_reconnected(drv):
    world = fw.World()
    ctl, rcv, _ = arm(drv, world)
    world.inject_protective_stop(after_moves=1)
    assert ctl.moveL([0.5, 0.0, 0.3, *down()])
    assert not ctl.moveL([0.5, 0.0, 0.1, *down()])
    assert rcv.getActualTCPPose()[2] == pytest.approx(0.2)  # stopped halfway
    assert rcv.isProtectiveStopped() and not rcv.isEmergencyStopped() and rcv.getSafetyMode() == 3
    assert not ctl.isProgramRunning() and not ctl.moveL([0.5, 0.0, 0.3, *down()])
    world.clear_stop()
    assert not rcv.isProtectiveStopped() and rcv.getSafetyMode() == 1
    assert not ctl.moveL([0.5, 0.0, 0.3, *down()])  # the controller ended the control script
    ctl = drv["rtde_control"].RTDEControlInterface(world.host)  # a new connection uploads it again
    assert ctl.isProgramRunning() and ctl.moveL([0.5, 0.0, 0.3, *down()])
    assert [m["result"] for m in world.moves()] == [True, False, False, False, True]


@pytest.mark.parametrize(("system", "mode"), [(False, 7), (True, 6)])
def test_emergency_stop_below_a_height(drv, system, mode):
    world = fw.World()
    ctl, rcv, _ = arm(drv, world)
    world.inject_emergency_stop(when_z_below=0.1, system=system)
    assert ctl.moveL([0.5, 0.0, 0.2, *down()])
    assert not ctl.moveL([0.5, 0.0, 0.0, *down()])
    assert rcv.getActualTCPPose()[2] == pytest.approx(0.1)
    assert rcv.isEmergencyStopped() and rcv.getSafetyMode() == mode and world.moves()[-1]["stopped"]


def test_reach_and_call_log(drv):
    world = fw.World(reach_m=0.8)
    ctl, rcv, io = arm(drv, world)
    assert not ctl.moveL([0.9, 0.0, 0.3, *down()])
    assert rcv.getActualTCPPose() == pytest.approx(world.home_pose)
    assert ctl.moveL([0.5, 0.1, 0.3, *down()], 0.1, 0.5)
    io.setToolDigitalOut(1, True)
    ctl.stopL(2.0)
    calls = world.calls
    assert calls[0]["refused"] == "out_of_reach" and calls[0]["result"] is False
    assert calls[1] == {"call": "moveL", "pose": pytest.approx([0.5, 0.1, 0.3, *down()]), "speed": 0.1,
                        "acceleration": 0.5, "asynchronous": False, "result": True}
    assert calls[2] == {"call": "setToolDigitalOut", "pin": 1, "level": True, "result": True}
    assert calls[3]["call"] == "stopL" and calls[3]["a"] == 2.0


def start_camera(rs, serial: str | None = None):
    """A pipeline streaming aligned depth (z16) and colour (rgb8), as our RealSense code opens it."""
    cfg = rs.config()
    if serial:
        cfg.enable_device(serial)
    cfg.enable_stream(rs.stream.depth, 640, 480, rs.format.z16, 30)
    cfg.enable_stream(rs.stream.color, 640, 480, rs.format.rgb8, 30)
    pipe = rs.pipeline(rs.context())
    return pipe, pipe.start(cfg)


def grab(rs, pipe, profile):
    """(colour, depth in metres, K, T_base_cam-independent deprojection helper inputs)."""
    frames = rs.align(rs.stream.color).process(pipe.wait_for_frames())
    scale = profile.get_device().first_depth_sensor().get_depth_scale()
    depth_m = np.asanyarray(frames.get_depth_frame().get_data()).astype(np.float64) * scale
    i = profile.get_stream(rs.stream.color).as_video_stream_profile().get_intrinsics()
    return np.asanyarray(frames.get_color_frame().get_data()), depth_m, (i.fx, i.fy, i.ppx, i.ppy)


def to_base(world, u, v, depth_m, k) -> np.ndarray:
    fx, fy, cx, cy = k
    p_cam = np.stack([(u - cx) / fx * depth_m, (v - cy) / fy * depth_m, depth_m, np.ones_like(depth_m)], -1)
    return p_cam @ np.asarray(world.camera.T_base_cam).T


def project(world, p_base) -> tuple[int, int]:
    p = np.linalg.inv(np.asarray(world.camera.T_base_cam)) @ np.append(p_base, 1.0)
    cam = world.camera
    return round(cam.fx * p[0] / p[2] + cam.cx), round(cam.fy * p[1] / p[2] + cam.cy)


def test_depth_of_the_table_and_a_box_top_matches_geometry(drv):
    rs = drv["pyrealsense2"]
    world = fw.World()
    world.camera.T_base_cam = fw.look_at((0.9, 0.45, 0.7), (0.5, 0.0, 0.0))  # oblique, as a real mount
    box = world.add_box("b", (0.5, 0.0, 0.03), (0.08, 0.06, 0.06), yaw_rad=0.4)
    world.register()
    assert [d.get_info(rs.camera_info.serial_number) for d in rs.context().query_devices()] == [world.camera.serial]
    pipe, profile = start_camera(rs, world.camera.serial)
    color, depth_m, k = grab(rs, pipe, profile)
    assert color.shape == (480, 640, 3) and color.dtype == np.uint8 and depth_m.shape == (480, 640)
    v, u = np.mgrid[0:480:5, 0:640:5]
    p = to_base(world, u, v, depth_m[v, u], k)
    far = np.hypot(p[..., 0] - 0.5, p[..., 1]) > 0.15  # no part of the box, nor its shadow
    assert far.sum() > 5000 and np.abs(p[..., 2][far]).max() < 1e-3  # the table, z = 0
    # Points of the top face (away from its edges) seen at their nearest pixel lie on the top, z = 6 cm.
    c, s = math.cos(box.yaw_rad), math.sin(box.yaw_rad)
    for a in np.linspace(-0.03, 0.03, 5):
        for b in np.linspace(-0.02, 0.02, 5):
            uu, vv = project(world, (0.5 + c * a - s * b, s * a + c * b, 0.06))
            assert to_base(world, np.float64(uu), np.float64(vv), depth_m[vv, uu], k)[2] == pytest.approx(0.06, abs=1e-3)
    assert tuple(color[vv, uu]) == tuple(box.rgb)  # the top face is lit fully
    pipe.stop()


def test_held_box_is_seen_at_the_tool(drv):
    rs = drv["pyrealsense2"]
    world = fw.World()  # camera straight down from 0.9 m
    box = world.add_box("b", (0.4, 0.0, 0.025), (0.05, 0.05, 0.05))
    ctl, _, io = arm(drv, world)
    ctl.moveL([0.4, 0.0, 0.045, *down()])
    io.setToolDigitalOut(0, True)
    ctl.moveL([0.55, 0.1, 0.3, *down()])
    pipe, profile = start_camera(rs)
    _, depth_m, _ = grab(rs, pipe, profile)
    assert depth_m[project(world, (0.55, 0.1, 0.3))[::-1]] == pytest.approx(0.9 - box.top_m, abs=1e-3)
    assert depth_m[project(world, (0.4, 0.0, 0.0))[::-1]] == pytest.approx(0.9, abs=1e-3)  # gone from the table


def test_camera_errors_are_the_real_ones(drv):
    rs = drv["pyrealsense2"]
    with pytest.raises(RuntimeError, match="^No device connected$"):
        rs.pipeline().start(rs.config())
    world = fw.World().register()
    pipe = rs.pipeline()
    with pytest.raises(RuntimeError, match="wait_for_frames cannot be called before start()"):
        pipe.wait_for_frames()
    bad = rs.config()
    bad.enable_stream(rs.stream.color, 1280, 720, rs.format.rgb8, 30)
    with pytest.raises(RuntimeError, match="^Couldn't resolve requests$"):
        pipe.start(bad)
    pipe.start()
    world.camera.timeout = True
    with pytest.raises(RuntimeError, match="^Frame didn't arrive within 100$"):
        pipe.wait_for_frames(100)
    assert not rs.frame() and not rs.composite_frame().get_depth_frame()


def test_board_on_the_tool_is_rendered(drv):
    world = fw.World(tcp_pose=[0.5, 0.0, 0.4, *down()])
    plain, _ = world.render()
    world.board = {"board_offset_m": [0.0, 0.0, 0.0], "pattern_corners": [7, 5], "square_m": 0.02}
    color, depth_m = world.render()
    u, v = project(world, (0.5, 0.0, 0.4))
    window = (slice(v - 40, v + 40), slice(u - 40, u + 40))
    assert (plain[window] < 60).all(axis=-1).sum() == 0 and (color[window] < 60).all(axis=-1).sum() > 500
    assert depth_m[v, u] == pytest.approx(0.5, abs=1e-3)


def test_world_json_round_trip_and_subprocess_state(tmp_path):
    world = fw.World(state_path=str(tmp_path / "state.json"))
    world.add_box("a", (0.5, 0.0, 0.025), (0.05, 0.05, 0.05), rgb=(20, 200, 40))
    world.inject_protective_stop(after_moves=1)
    assert fw.World.from_json(world.to_json()) == world
    world.save(tmp_path / "world.json")
    script = textwrap.dedent("""
        import pyrealsense2 as rs, rtde_control, rtde_io, rtde_receive
        ctl, rcv = rtde_control.RTDEControlInterface("ur-fake"), rtde_receive.RTDEReceiveInterface("ur-fake")
        rtde_io.RTDEIOInterface("ur-fake").setToolDigitalOut(0, True)
        print(ctl.moveL([0.5, 0.0, 0.3, 3.14159, 0, 0]), ctl.moveL([0.5, 0.0, 0.1, 3.14159, 0, 0]),
              rcv.isProtectiveStopped(), rs.context().query_devices()[0].get_info(rs.camera_info.serial_number),
              rtde_control.__file__)
    """)
    out = subprocess.run([sys.executable, "-c", script], env=fake_driver_env(tmp_path / "world.json"),
                         cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    moved, stopped, flag, serial, path = out.stdout.split()
    assert (moved, stopped, flag, serial) == ("True", "False", "True", world.camera.serial)
    assert Path(path).resolve().is_relative_to(FAKES_DIR)
    final = fw.World.load(tmp_path / "state.json")
    assert final.protective_stopped and [m["result"] for m in final.moves()] == [True, False]
    assert final.calls[0] == {"call": "setToolDigitalOut", "pin": 0, "level": True, "result": True}
    assert final.tcp_pose[2] == pytest.approx(0.2) and not final.stops
