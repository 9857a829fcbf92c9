"""Fake `rtde_receive` (ur_rtde): RTDEReceiveInterface reading the registered fakeworld.World."""

from __future__ import annotations

import fakeworld as _fw


class RTDEReceiveInterface:
    """State of the world registered at `hostname`; an unknown host fails as the real one does."""

    def __init__(self, hostname: str, frequency: float = -1.0, variables: list[str] = [],  # noqa: B006 (the real default; never mutated)
                 verbose: bool = False, use_upper_range_registers: bool = False, rt_priority: int = 0) -> None:
        world = _fw.world_for_host(hostname)
        if world is None:
            raise RuntimeError(f"Error: Could not connect to: {hostname} at 30004, verify the IP")
        self._world, self._connected = world, True

    def getActualTCPPose(self) -> list[float]:
        return list(self._world.tcp_pose)

    def getSafetyMode(self) -> int:
        return int(self._world.safety_mode)

    def getRobotMode(self) -> int:
        return int(self._world.robot_mode)

    def isProtectiveStopped(self) -> bool:
        return bool(self._world.protective_stopped)

    def isEmergencyStopped(self) -> bool:
        return bool(self._world.emergency_stopped)

    def getDigitalInState(self, arg0: int) -> bool:
        return self._world.digital_input(arg0)

    def getDigitalOutState(self, arg0: int) -> bool:
        # 0-7 standard, 8-15 configurable (always low here), 16-17 tool, as getActualDigitalOutputBits.
        w = self._world
        return bool(w.standard_out[arg0]) if arg0 < 8 else bool(w.tool_out[arg0 - 16]) if arg0 >= 16 else False

    def getStandardAnalogInput0(self) -> float:
        return self._world.analog_input(0)

    def getStandardAnalogInput1(self) -> float:
        return self._world.analog_input(1)

    def disconnect(self) -> None:
        self._connected = False

    def reconnect(self) -> bool:
        self._connected = True
        return True

    def isConnected(self) -> bool:
        return self._connected
