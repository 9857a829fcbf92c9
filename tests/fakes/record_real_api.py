"""Record the real driver API that the fakes mirror into real_api.json (committed).

For every class the fakes define, and every member of it, the real module's pybind docstring signature
lines (all overloads), "attribute" for properties, or an enum's member values. The snapshot lets
tests/test_real_fakes.py check the fakes on machines without the drivers; where the drivers are installed
the test also checks the snapshot is what they say. Re-record after changing a fake or the driver versions:

    .venv/bin/python tests/fakes/record_real_api.py
"""

from __future__ import annotations

import enum
import importlib
import importlib.util
import json
import re
import sys
from importlib import metadata
from pathlib import Path
from types import ModuleType

FAKES_DIR = Path(__file__).resolve().parent
SNAPSHOT = FAKES_DIR / "real_api.json"
MODULES = ("rtde_control", "rtde_receive", "rtde_io", "pyrealsense2")
# Class-dict entries every Python class has; they say nothing about the API.
_IGNORED = {"__module__", "__doc__", "__dict__", "__weakref__", "__qualname__", "__annotations__",
            "__firstlineno__", "__static_attributes__", "__annotate_func__", "__annotations_cache__"}


def _load(name: str, path: Path, package: bool = False) -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        name, path, submodule_search_locations=[str(path.parent)] if package else None)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # dataclasses look their module up while the class body runs
    spec.loader.exec_module(module)
    return module


def load_fakeworld() -> ModuleType:
    """The one `fakeworld` module the fakes share (loaded by path: tests/fakes need not be on sys.path)."""
    return sys.modules.get("fakeworld") or _load("fakeworld", FAKES_DIR / "fakeworld.py")


def load_fake(name: str) -> ModuleType:
    """A fake driver module under a private name, so the real one can be imported beside it."""
    load_fakeworld()
    if name == "pyrealsense2":
        return _load("_fake_pyrealsense2", FAKES_DIR / "pyrealsense2" / "__init__.py", package=True)
    return _load(f"_fake_{name}", FAKES_DIR / f"{name}.py")


def import_real(name: str) -> ModuleType:
    """The installed driver module; ImportError if it is missing (or only a fake is on the path)."""
    if name == "pyrealsense2":
        # The wheel links against libusb-1.0, which libusb-package ships where the system lacks it.
        import ctypes

        import libusb_package
        ctypes.CDLL(str(libusb_package.get_library_path()), mode=ctypes.RTLD_GLOBAL)
    module = importlib.import_module(name)
    if Path(module.__file__).resolve().is_relative_to(FAKES_DIR):
        raise ImportError(f"{name} resolves to the fake at {module.__file__}")
    return module


def fake_classes(fake: ModuleType) -> dict[str, type]:
    """The classes a fake module defines (its API surface)."""
    return {n: c for n, c in vars(fake).items()
            if isinstance(c, type) and c.__module__ == fake.__name__ and not n.startswith("_")}


def fake_members(cls: type) -> list[str]:
    """Members a fake class defines itself: public names and dunders (private helpers are not API)."""
    if issubclass(cls, enum.Enum):
        return list(cls.__members__)
    return [n for n in vars(cls) if n not in _IGNORED and (not n.startswith("_") or n.startswith("__"))]


def signature_lines(name: str, doc: str | None) -> list[str]:
    """The signature lines of a pybind docstring: one, or one per overload ("1. f(...) -> T")."""
    pattern = re.compile(rf"^(?:\d+\.\s+)?({re.escape(name)}\(.*\).*)$")
    lines = [m.group(1) for m in map(pattern.match, (doc or "").splitlines()) if m]
    return [line for line in lines if not line.startswith(f"{name}(*args, **kwargs)")]


def record(real: ModuleType, fake: ModuleType) -> dict:
    """What the real module says about every class and member the fake defines (absent ones are left out)."""
    out: dict[str, dict] = {}
    for cls_name, fake_cls in sorted(fake_classes(fake).items()):
        real_cls = getattr(real, cls_name, None)
        if not isinstance(real_cls, type):
            continue
        entry: dict = {}
        for member in fake_members(fake_cls):
            if not hasattr(real_cls, member):
                continue
            attr = getattr(real_cls, member)
            if issubclass(fake_cls, enum.Enum):
                entry[member] = int(attr)
            elif isinstance(attr, property) or not callable(attr):
                entry[member] = "attribute"
            else:
                entry[member] = signature_lines(member, attr.__doc__)
        out[cls_name] = entry
    return out


def main() -> None:
    # Run as a script, this folder is sys.path[0]: drop it so `import rtde_control` finds the real module.
    sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != FAKES_DIR]
    snapshot = {}
    for name in MODULES:
        real = import_real(name)
        dist = "ur_rtde" if name.startswith("rtde_") else name
        snapshot[name] = {"version": metadata.version(dist), "classes": record(real, load_fake(name))}
    SNAPSHOT.write_text(json.dumps(snapshot, indent=1, sort_keys=True) + "\n")
    print(f"wrote {SNAPSHOT}")  # a command-line script: the path is its output


if __name__ == "__main__":
    main()
