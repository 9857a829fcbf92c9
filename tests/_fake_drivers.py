"""Put the fake ur_rtde / pyrealsense2 drivers (tests/fakes) in place of the real ones, in-process or for a
subprocess. The fakes act on fakeworld.World objects; see tests/fakes/fakeworld.py.

In-process:

    with fake_drivers(World(...)) as fw:        # registers the worlds; fw is the fakeworld module
        robot = URRobot(cfg); robot.connect()  # `import rtde_control` etc. now give the fakes

or as a pytest fixture: `with fake_drivers() as fw: yield fw`. Subprocess:

    World(..., state_path=str(tmp / "state.json")).save(tmp / "world.json")
    subprocess.run([...], env=fake_driver_env(tmp / "world.json"))
    final = World.load(tmp / "state.json")
"""

from __future__ import annotations

import importlib
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType

FAKES_DIR = Path(__file__).resolve().parent / "fakes"
DRIVER_MODULES = ("rtde_control", "rtde_receive", "rtde_io", "pyrealsense2")


def fakeworld() -> ModuleType:
    """The process's one `fakeworld` module (shared by the fakes and the tests, so one registry)."""
    if "fakeworld" not in sys.modules:
        sys.path.insert(0, str(FAKES_DIR))
        try:
            importlib.import_module("fakeworld")
        finally:
            sys.path.remove(str(FAKES_DIR))
    return sys.modules["fakeworld"]


def _is_driver(name: str) -> bool:
    return name in DRIVER_MODULES or name.startswith("pyrealsense2.")


@contextmanager
def fake_drivers(*worlds) -> Iterator[ModuleType]:
    """Within the block the driver module names import the fakes, and only `worlds` are registered.

    Real driver modules already imported are taken out of sys.modules and put back afterwards, as are
    sys.path and the registry (emptied on exit).
    """
    fw = fakeworld()
    fw.reset_registry()
    for world in worlds:
        world.register()
    saved_modules = {n: m for n, m in sys.modules.items() if _is_driver(n)}
    saved_path = list(sys.path)
    for name in saved_modules:
        del sys.modules[name]
    sys.path.insert(0, str(FAKES_DIR))
    try:
        for name in DRIVER_MODULES:
            module = importlib.import_module(name)
            if not Path(module.__file__).resolve().is_relative_to(FAKES_DIR):
                raise RuntimeError(f"{name} imported {module.__file__}, not the fake in {FAKES_DIR}")
        yield fw
    finally:
        for name in [n for n in sys.modules if _is_driver(n)]:
            del sys.modules[name]
        sys.modules.update(saved_modules)
        sys.path[:] = saved_path
        fw.reset_registry()


def fake_driver_env(world_json_path: str | os.PathLike) -> dict[str, str]:
    """os.environ plus what makes a subprocess import the fakes and load the world from that JSON file."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(FAKES_DIR), env.get("PYTHONPATH", "")) if p)
    env["ROMANNET_FAKE_WORLD"] = str(Path(world_json_path).resolve())
    return env
