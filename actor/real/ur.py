"""URRobot: a Universal Robots arm through ur_rtde (the `robot` extra: `pip install 'romannet[robot]'`).

Three RTDE interfaces, as ur_rtde splits them: RTDEReceiveInterface (pose, modes, inputs), RTDEControlInterface
(moveL, which uploads and runs ur_rtde's control script), RTDEIOInterface (digital outputs). The primitives,
the safety box and the stop handling are CartesianRobot's (robot.py); this file only talks to the controller.

Connect-time checks (a RobotError names what is wrong and what to do): the controller answers at the
address, the robot is powered on and running (robot mode 7), the safety mode is normal (1), no protective or
emergency stop, the control script runs, and the TCP is readable and finite. Connecting never moves the arm.

The TCP must be set on the teach pendant (or in the installation) to the suction cup's tip or the
fingertips' centre: every height here is the TCP's.
"""

from __future__ import annotations

import importlib
import logging
import time

import numpy as np

from romannet.common.config_robot import RobotConfig
from romannet.common.errors import RobotError

from .robot import CartesianRobot

log = logging.getLogger(__name__)

ROBOT_MODE_RUNNING = 7  # UR robot modes (RTDE "robot_mode")
SAFETY_MODE_NORMAL = 1
SAFETY_MODES = {1: "normal", 2: "reduced", 3: "protective_stop", 4: "recovery", 5: "safeguard_stop",
                6: "system_emergency_stop", 7: "robot_emergency_stop", 8: "violation", 9: "fault",
                10: "validate_joint_id", 11: "undefined_safety_mode", 12: "automatic_mode_safeguard_stop",
                13: "system_three_position_enabling_stop"}
ROBOT_MODES = {-1: "no_controller", 0: "disconnected", 1: "confirm_safety", 2: "booting", 3: "power_off",
               4: "power_on", 5: "idle", 6: "backdrive", 7: "running", 8: "updating_firmware"}


def import_driver(name: str):
    """Import one of ur_rtde's modules, or raise RobotError saying how to install it."""
    try:
        return importlib.import_module(name)
    except ImportError as err:
        raise RobotError(f"the UR driver module {name!r} is not installed ({err}); install the robot extra: "
                         "pip install 'romannet[robot]' (ur_rtde)") from None


class URRobot(CartesianRobot):
    """A UR arm with a suction cup or a gripper on its tool I/O; see the module docstring."""

    def __init__(self, cfg: RobotConfig):
        super().__init__(cfg)
        self._rcv = self._ctl = self._io = None
        self._tool_active = False  # vacuum on / fingers closed, as last commanded

    # --------------------------------------------------------------------------------- lifecycle
    def connect(self) -> None:
        if self._rcv is not None:
            return
        if not self.cfg.host:
            raise RobotError("robot.host is empty: set the UR controller's address in the robot config "
                             "([robot] host = \"192.168.1.10\") or with --set robot.host=...")
        rtde_receive, rtde_control, rtde_io = (import_driver(m) for m in ("rtde_receive", "rtde_control", "rtde_io"))
        host = self.cfg.host
        try:
            self._rcv = rtde_receive.RTDEReceiveInterface(host)
            self._check_ready()
            self._ctl = rtde_control.RTDEControlInterface(host)
            self._io = rtde_io.RTDEIOInterface(host)
        except RuntimeError as err:
            self.disconnect()
            raise RobotError(f"cannot connect to the UR controller at {host}: {err}. Is the robot on, the address "
                             "right, and the controller in remote control mode (e-Series)?") from None
        except RobotError:
            self.disconnect()
            raise
        if not self._ctl.isProgramRunning():
            self.disconnect()
            raise RobotError(f"the UR controller at {host} accepted the connection but ur_rtde's control script "
                             "is not running; check that no other program holds the robot, then retry")
        pose = self.tool_pose()
        log.info("connected to the UR controller at %s: TCP at %s, tool %s, safety box %s..%s, speed <= %.2f m/s",
                 host, np.round(pose[:3], 4).tolist(), self.cfg.tool, self.box.low, self.box.high,
                 self.box.max_speed_mps)
        self._set_tool(False)  # a known tool state: vacuum off / fingers open

    def _check_ready(self) -> None:
        """Raise RobotError unless the robot is running in normal safety mode without a stop."""
        why = self._stop_reason() or self._controller_ready(check_script=False)
        if why:
            raise RobotError(f"the UR controller at {self.cfg.host} is not ready: {why}. Power on and release "
                             "the brakes on the teach pendant, clear any stop, then retry")

    def disconnect(self) -> None:
        for name in ("_ctl", "_io", "_rcv"):
            iface = getattr(self, name)
            if iface is None:
                continue
            try:
                if name == "_ctl" and not self.stopped:
                    iface.stopL(self.cfg.max_accel_mps2)
                iface.disconnect()
            except RuntimeError as err:  # a lost connection: nothing more to release
                log.warning("disconnecting %s: %s", name.strip("_"), err)
            setattr(self, name, None)

    # ---------------------------------------------------------------------------------- queries
    def _require(self):
        if self._rcv is None or self._ctl is None or self._io is None:
            raise RobotError("the robot is not connected: call connect() (or use it as a context manager)")
        return self._rcv, self._ctl, self._io

    def tool_pose(self) -> np.ndarray:
        pose = np.asarray(self._rcv.getActualTCPPose() if self._rcv is not None else (), dtype=np.float64)
        if pose.shape != (6,) or not np.all(np.isfinite(pose)):
            raise RobotError(f"the controller reported an invalid TCP pose: {pose.tolist()}")
        return pose

    def _stop_reason(self) -> str:
        rcv = self._rcv
        if rcv is None:
            return "not_connected"
        if rcv.isEmergencyStopped():
            return "emergency_stop"
        if rcv.isProtectiveStopped():
            return "protective_stop"
        mode = int(rcv.getSafetyMode())
        if mode not in (SAFETY_MODE_NORMAL, 2):  # 2 = reduced mode: slower, but allowed to move
            return SAFETY_MODES.get(mode, f"safety_mode_{mode}")
        return ""

    def _controller_ready(self, check_script: bool = True) -> str:
        mode = int(self._rcv.getRobotMode()) if self._rcv is not None else -1
        if mode != ROBOT_MODE_RUNNING:
            return f"robot mode is {ROBOT_MODES.get(mode, mode)}, not running"
        if check_script and self._ctl is not None and not self._ctl.isProgramRunning():
            # After a protective stop the controller ends ur_rtde's script: a new control connection
            # uploads it again (the operator has cleared the stop; this moves nothing).
            self._reconnect_control()
            if not self._ctl.isProgramRunning():
                return "ur_rtde's control script does not run"
        return ""

    def _reconnect_control(self) -> None:
        rtde_control = import_driver("rtde_control")
        try:
            self._ctl.disconnect()
            self._ctl = rtde_control.RTDEControlInterface(self.cfg.host)
        except RuntimeError as err:
            raise RobotError(f"cannot reconnect to the UR controller at {self.cfg.host}: {err}") from None

    # ----------------------------------------------------------------------------------- motion
    def _move_linear(self, pose: np.ndarray, speed_mps: float, accel_mps2: float) -> bool:
        _, ctl, _ = self._require()
        return bool(ctl.moveL([float(v) for v in pose], float(speed_mps), float(accel_mps2)))

    # ------------------------------------------------------------------------------------- tool
    def _set_tool(self, active: bool) -> None:
        _, _, io = self._require()
        pin = self.cfg.tool_output_pin
        ok = io.setToolDigitalOut(pin, active) if self.cfg.tool_output == "tool" else \
            io.setStandardDigitalOut(pin, active)
        if not ok:
            raise RobotError(f"the controller refused to set {self.cfg.tool_output} digital output {pin}")
        changed, self._tool_active = active != self._tool_active, active
        # The output is written every time (cheap, and right even if something else changed it), but the wait
        # for the vacuum to build up / the fingers to travel only when the command changed: a suction push
        # starts by switching off a vacuum that is already off, and 0.3 s of every such action was idle.
        if changed:
            time.sleep(self.cfg.vacuum_settle_s)

    def gripper_width_m(self) -> float:
        """Finger width from the analog input (robot.width_per_volt_m * volts + robot.width_offset_m)."""
        rcv, _, _ = self._require()
        volts = rcv.getStandardAnalogInput0() if self.cfg.width_input == "analog0" else \
            rcv.getStandardAnalogInput1()
        return self.cfg.width_per_volt_m * float(volts) + self.cfg.width_offset_m

    def _grasp_sensed(self) -> bool:
        rcv, _, _ = self._require()
        if self.cfg.tool == "suction":
            return bool(rcv.getDigitalInState(self.cfg.vacuum_input))
        # Open fingers are wide without holding anything: only closed fingers that stopped wide hold.
        return self._tool_active and self.gripper_width_m() > self.cfg.grasp_min_width_m
