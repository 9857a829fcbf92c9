"""Fake `rtde_io` (ur_rtde): RTDEIOInterface setting the registered fakeworld.World's digital outputs."""

from __future__ import annotations

import fakeworld as _fw


class RTDEIOInterface:
    """Outputs of the world registered at `hostname`; an unknown host fails as the real one does."""

    def __init__(self, hostname: str, verbose: bool = False, use_upper_range_registers: bool = False) -> None:
        world = _fw.world_for_host(hostname)
        if world is None:
            raise RuntimeError(f"Error: Could not connect to: {hostname} at 30004, verify the IP")
        self._world, self._connected = world, True

    def setToolDigitalOut(self, arg0: int, arg1: bool) -> bool:
        return self._world.set_digital_out("tool", arg0, arg1)

    def setStandardDigitalOut(self, arg0: int, arg1: bool) -> bool:
        return self._world.set_digital_out("standard", arg0, arg1)

    def disconnect(self) -> None:
        self._connected = False

    def reconnect(self) -> bool:
        self._connected = True
        return True

    def isConnected(self) -> bool:
        return self._connected
