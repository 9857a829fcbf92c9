"""Fake `rtde_control` (ur_rtde): the RTDEControlInterface methods our code calls, with the real signatures.

Moves act on the fakeworld.World registered for the host (see fakeworld.py); tests/test_real_fakes.py checks
every name and signature here against the real module (tests/fakes/real_api.json).
"""

from __future__ import annotations

import fakeworld as _fw


class RTDEControlInterface:
    """Connects to the world registered at `hostname`; an unknown host fails as the real one does."""

    def __init__(self, hostname: str, frequency: float = -1.0, flags: int = 1, ur_cap_port: int = 50002,
                 rt_priority: int = 0) -> None:
        world = _fw.world_for_host(hostname)
        if world is None:
            raise RuntimeError(f"Error: Could not connect to: {hostname} at 30004, verify the IP")
        self._world, self._connected = world, True
        self._start_script()

    def _start_script(self) -> None:
        # Connecting uploads and starts ur_rtde's control script; it cannot run while the robot is stopped.
        with self._world._lock:
            if not self._world.stopped:
                self._world.program_running = True

    def moveL(self, pose: list[float], speed: float = 0.25, acceleration: float = 1.2,
              asynchronous: bool = False) -> bool:
        if not self._connected:
            return False
        return self._world.move_linear(pose, speed, acceleration, asynchronous)

    def stopL(self, a: float = 10.0, asynchronous: bool = False) -> None:
        self._world.log_call({"call": "stopL", "a": float(a), "asynchronous": bool(asynchronous)})

    def disconnect(self) -> None:
        self._connected = False

    def reconnect(self) -> bool:
        self._connected = True
        self._start_script()
        return True

    def isConnected(self) -> bool:
        return self._connected

    def isProgramRunning(self) -> bool:
        return self._connected and self._world.program_running

    def isSteady(self) -> bool:
        return True  # moves are instant and blocking: the robot is always at rest between calls
