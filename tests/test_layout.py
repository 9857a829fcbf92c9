"""The layering the user chose: actor/, learner/ and replay/ import common/ only; nothing uses pickle."""

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SIBLINGS = {"actor", "learner", "replay"}


def _imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the package folder
                base = path.relative_to(ROOT).parts[: -node.level]
                names.append(".".join(("romannet", *base, node.module or "")))
            else:
                names.append(node.module or "")
    return names


def _package_files(folder: str) -> list[Path]:
    return sorted((ROOT / folder).rglob("*.py"))


@pytest.mark.parametrize("folder", sorted(SIBLINGS | {"common"}))
def test_components_import_common_only(folder):
    forbidden = {f"romannet.{s}" for s in SIBLINGS - {folder}} | {"romannet.cli", "romannet.bench"}
    for path in _package_files(folder):
        for name in _imports(path):
            bad = [f for f in forbidden if name == f or name.startswith(f + ".")]
            assert not bad, f"{path.relative_to(ROOT)} imports {name}: {folder}/ may import common/ only"


def test_no_pickle_anywhere():
    for folder in ("common", "actor", "learner", "replay", "bench", "romannet"):
        for path in _package_files(folder):
            text = path.read_text()
            names = _imports(path)
            assert "pickle" not in names and "dill" not in names, f"{path} imports pickle"
            # torch.load unpickles; safetensors.torch.load does not (hence the look-behind).
            assert not re.search(r"(?<![\w.])torch\.load\(", text), f"{path} calls torch.load (use safetensors)"


def test_every_package_folder_is_listed_in_pyproject():
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(project["packages"])
    mapping = project["package-dir"]
    for pkg, folder in mapping.items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder).parts
            name = ".".join((pkg, *rel))
            assert name in listed, f"{init.parent} is a package but {name} is not in pyproject's packages"
