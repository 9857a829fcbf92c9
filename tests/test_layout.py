"""The layering the user chose: actor/, learner/ and replay/ import common/ and themselves only, and common/
holds only what they use; nothing uses pickle."""

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SIBLINGS = {"actor", "learner", "replay"}


def _imports(path: Path) -> list[str]:
    """Every module a file imports, absolute; `from X import y` gives X and X.y (y may be a module)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    names: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the package folder
                base = path.relative_to(ROOT).parts[: -node.level]
                parent = ".".join(("romannet", *base, *([node.module] if node.module else [])))
            else:
                parent = node.module or ""
            names += [parent, *(f"{parent}.{a.name}" for a in node.names)]
    return names


def _package_files(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


def _setuptools() -> dict:
    import tomllib

    return tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]


def installed_names() -> set[str]:
    """Every top-level romannet.* package and module: the folders pyproject maps, and each module and package
    of romannet/, found on disk so that a new one is covered without editing this test."""
    mapping = _setuptools()["package-dir"]
    names = {pkg for pkg in mapping if pkg != "romannet"}
    for child in (ROOT / mapping["romannet"]).iterdir():
        if child.suffix == ".py" and child.stem != "__init__":
            names.add(f"romannet.{child.stem}")
        elif (child / "__init__.py").is_file():
            names.add(f"romannet.{child.name}")
    return names


def forbidden_for(folder: str) -> set[str]:
    """What folder/ must not import: every romannet.* package and module but romannet.common and its own.
    (romannet itself, whose __init__ holds only the version, stays allowed.)"""
    return installed_names() - {"romannet.common", f"romannet.{folder}"}


def test_the_forbidden_names_are_every_other_package_and_the_cli_side():
    forbidden = forbidden_for("actor")
    assert {"romannet.learner", "romannet.replay", "romannet.bench", "romannet.cli", "romannet.up",
            "romannet.analyse", "romannet.deploy", "romannet.evaluate", "romannet.mcaptools",
            "romannet.sweep"} <= forbidden
    assert "romannet.common" not in forbidden and "romannet.actor" not in forbidden
    assert "romannet.actor" in forbidden_for("common")


@pytest.mark.parametrize("folder", sorted(SIBLINGS | {"common"}))
def test_components_import_common_and_themselves_only(folder):
    forbidden = forbidden_for(folder)
    for path in _package_files(folder):
        for name in _imports(path):
            bad = [f for f in forbidden if name == f or name.startswith(f + ".")]
            assert not bad, f"{path.relative_to(ROOT)} imports {name}: {folder}/ may import common/ only"


def test_every_common_module_is_used_by_a_component():
    """common/ holds what actor/, learner/ and replay/ use: each of its modules is imported by one of them,
    directly or through a common module they use. Code only the CLI side uses belongs in romannet/."""
    modules = {f"romannet.common.{p.stem}": p for p in (ROOT / "common").glob("*.py") if p.stem != "__init__"}
    used: set[str] = set()
    todo = [p for folder in sorted(SIBLINGS) for p in _package_files(folder)]
    while todo:
        for name in _imports(todo.pop()):
            for module, path in modules.items():
                if module not in used and (name == module or name.startswith(module + ".")):
                    used.add(module)
                    todo.append(path)
    unused = sorted(m.rsplit(".", 1)[1] for m in set(modules) - used)
    assert not unused, f"common/ modules no actor, learner or replay module uses (move them to romannet/): {unused}"


def test_no_pickle_anywhere():
    for folder in ("common", "actor", "learner", "replay", "bench", "romannet"):
        for path in _package_files(folder):
            text = path.read_text()
            names = _imports(path)
            assert "pickle" not in names and "dill" not in names, f"{path} imports pickle"
            # torch.load unpickles; safetensors.torch.load does not (hence the look-behind).
            assert not re.search(r"(?<![\w.])torch\.load\(", text), f"{path} calls torch.load (use safetensors)"


def test_every_package_folder_is_listed_in_pyproject():
    project = _setuptools()
    listed = set(project["packages"])
    mapping = project["package-dir"]
    for pkg, folder in mapping.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder).parts
            name = ".".join((pkg, *rel))
            assert name in listed, f"{init.parent} is a package but {name} is not in pyproject's packages"
