"""Test-case files of the "challenging arrangements" task, in VPG's text format.

One object per line, whitespace separated: `mesh r g b x y z rx ry rz`
- mesh: one of our BLOCK_SHAPES ("arch"), a VPG block mesh path ending in `blocks/<i>.obj` or `<i>.obj`
  (i = 0..8, mapped to BLOCK_SHAPES[i], see block_meshes.py), "urdf:<path>" or a path to another .obj
  (relative paths are relative to the case file).
- r g b: colour in [0, 1].
- x y z: position in VPG's simulation frame (metres), whose workspace is x in [-0.724, -0.276],
  y in [-0.224, 0.224] with the floor at z = 0 (VPG's z_min is -0.0001: negligible). z is the object
  frame's height above the floor; for VPG's meshes and our blocks that is the bounding-box centre.
  We translate VPG's workspace square onto ours: x = x_vpg + 0.724 + ws.x_min_m,
  y = y_vpg + 0.224 + ws.y_min_m, z = z_vpg + ws.z_min_m (no rotation between the frames).
- rx ry rz: CoppeliaSim Euler angles (alpha, beta, gamma) in radians. CoppeliaSim's manual ("Euler
  angles", positionOrientationTransformation.htm): rotate about the object's own x by alpha, then its own
  y by beta, then its own z by gamma, i.e. R = Rx(alpha) Ry(beta) Rz(gamma). (PyBullet's
  getQuaternionFromEuler is the other order, Rz Ry Rx, so we build the rotation ourselves.) VPG's own
  recorded cases confirm it: with this order every settled block has one body axis exactly vertical.
  Caveat: CoppeliaSim re-frames imported meshes, so a VPG file's angles applied to our blocks may not
  put a block on the same face as in VPG; position and shape are kept and the scene still settles.

`jitter_case` moves a loaded case rigidly (a small shift and turn of the whole arrangement, drawn from the
episode's rng), so that the evaluation's runs of one case differ; the objects keep their relative poses.

Case sets: `actor/sim/cases/` holds our 11 cases (the default, and what arrangement training draws from);
`actor/sim/cases_heldout/` 11 harder ones that nothing is tuned on. `cases_dir` resolves a set's name
("ours", "heldout") or a directory, as `romannet eval --cases` does.

Blank lines and `#` comments are allowed. Objects outside the workspace (x, y) or below the floor are
skipped with a warning; a malformed line raises CaseFormatError naming the file and the line number.
"""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path

import numpy as np

from romannet.common.config import WorkspaceConfig

from .block_meshes import BLOCK_SHAPES
from .objects import ObjectSpec

logger = logging.getLogger(__name__)

VPG_WORKSPACE_X_MIN_M = -0.724
VPG_WORKSPACE_Y_MIN_M = -0.224
_VPG_BLOCK = re.compile(r"^(?:(?:.*[/\\])?blocks[/\\])?([0-8])\.obj$")
_CASES_DIR = Path(__file__).resolve().parent / "cases"
# Named case sets shipped with the package. "heldout": 11 harder arrangements (denser, angled, mixed, against
# the workspace edge) that no setting is tuned on, so they measure generalisation rather than our tuning.
CASE_SETS = {"ours": _CASES_DIR, "heldout": Path(__file__).resolve().parent / "cases_heldout"}


class CaseFormatError(ValueError):
    """A test-case file line could not be read; the message names the file and the line."""

    def __init__(self, path: Path, line_no: int, problem: str) -> None:
        super().__init__(f"{path}:{line_no}: {problem}")
        self.path, self.line_no, self.problem = path, line_no, problem


def default_cases_dir() -> Path:
    """Directory of our 11 arrangement cases (actor/sim/cases)."""
    return _CASES_DIR


def default_cases() -> list[Path]:
    """Our 11 arrangement case files, sorted by name."""
    return sorted(_CASES_DIR.glob("case_*.txt"))


def cases_dir(name_or_dir: str | Path | None) -> Path:
    """The directory of a case set: a name of CASE_SETS ("ours", "heldout"), a directory path, or None for
    ours. A name wins over a same-named relative directory; `./heldout` names the directory."""
    if name_or_dir is None:
        return _CASES_DIR
    if isinstance(name_or_dir, str) and name_or_dir in CASE_SETS:
        return CASE_SETS[name_or_dir]
    return Path(name_or_dir)


def coppeliasim_euler_to_quaternion(alpha: float, beta: float, gamma: float) -> tuple[float, float, float, float]:
    """Quaternion (x, y, z, w) of R = Rx(alpha) Ry(beta) Rz(gamma) (CoppeliaSim's convention)."""
    def half(angle: float, axis: int) -> np.ndarray:
        q = np.zeros(4)
        q[axis], q[3] = math.sin(angle / 2), math.cos(angle / 2)
        return q

    qx, qy, qz = half(alpha, 0), half(beta, 1), half(gamma, 2)
    return tuple(float(v) for v in _quat_mul(_quat_mul(qx, qy), qz))  # type: ignore[return-value]


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    (ax, ay, az, aw), (bx, by, bz, bw) = a, b
    return np.array([
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
        aw * bw - ax * bx - ay * by - az * bz,
    ])


def _resolve_mesh(token: str, case_dir: Path) -> str | None:
    """Our shape name, "urdf:<abs path>" or an absolute .obj path; None if the mesh is unknown."""
    if token in BLOCK_SHAPES:
        return token
    vpg = _VPG_BLOCK.search(token)
    if vpg and not (case_dir / token).is_file():
        return BLOCK_SHAPES[int(vpg.group(1))]
    if token.startswith("urdf:"):
        path = case_dir / token[len("urdf:"):]
        return f"urdf:{path.resolve()}" if path.is_file() else None
    if token.lower().endswith(".obj"):
        path = case_dir / token
        return str(path.resolve()) if path.is_file() else None
    return None


def _parse_line(tokens: list[str], path: Path, line_no: int) -> tuple[str, list[float]]:
    if len(tokens) != 10:
        raise CaseFormatError(path, line_no, f"expected 10 fields 'mesh r g b x y z rx ry rz', got {len(tokens)}")
    values = []
    for name, text in zip(("r", "g", "b", "x", "y", "z", "rx", "ry", "rz"), tokens[1:], strict=True):
        try:
            value = float(text)
        except ValueError:
            raise CaseFormatError(path, line_no, f"field {name} is not a number: {text!r}") from None
        if not math.isfinite(value):
            raise CaseFormatError(path, line_no, f"field {name} is not finite: {text!r}")
        values.append(value)
    if not all(0.0 <= c <= 1.0 for c in values[:3]):
        raise CaseFormatError(path, line_no, f"colour r g b must be in [0, 1], got {values[:3]}")
    mesh = _resolve_mesh(tokens[0], path.parent)
    if mesh is None:
        raise CaseFormatError(path, line_no, f"unknown mesh {tokens[0]!r}: expected one of "
                              f"{', '.join(BLOCK_SHAPES)}, a VPG 'blocks/<0-8>.obj', 'urdf:<path>' or an existing .obj")
    return mesh, values


def load_case(path: str | Path, ws: WorkspaceConfig) -> list[ObjectSpec]:
    """Read a test-case file into ObjectSpecs in our world frame (see the module docstring).

    Raises CaseFormatError (file and line) for a malformed line, FileNotFoundError if the file is missing.
    """
    path = Path(path)
    specs: list[ObjectSpec] = []
    for line_no, raw in enumerate(path.read_text().splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        mesh, (r, g, b, x, y, z, rx, ry, rz) = _parse_line(line.split(), path, line_no)
        pos = (x - VPG_WORKSPACE_X_MIN_M + ws.x_min_m, y - VPG_WORKSPACE_Y_MIN_M + ws.y_min_m, z + ws.z_min_m)
        inside = ws.x_min_m <= pos[0] <= ws.x_max_m and ws.y_min_m <= pos[1] <= ws.y_max_m
        if not inside or pos[2] < ws.z_min_m:
            logger.warning("%s:%d: skipping %s at (%.3f, %.3f, %.3f) m: %s", path, line_no, mesh, *pos, "outside the workspace" if not inside else "below the table")
            continue
        specs.append(ObjectSpec(mesh, (r, g, b, 1.0), pos, coppeliasim_euler_to_quaternion(rx, ry, rz)))
    return specs


def jitter_case(specs: list[ObjectSpec], rng: np.random.Generator, ws: WorkspaceConfig, shift_m: float,
                turn_rad: float) -> list[ObjectSpec]:
    """The case moved as one rigid body: turned by an angle uniform in [-turn_rad, turn_rad] about the centre
    of its objects' x, y, then shifted by dx, dy uniform in [-shift_m, shift_m] (one draw for the whole case,
    so packed objects stay packed). Where that would put an object's centre outside the workspace, the case
    is returned as written. Draws three numbers from rng even when shift_m and turn_rad are 0.
    """
    dx, dy = (float(v) for v in rng.uniform(-1.0, 1.0, 2) * shift_m)
    turn = float(rng.uniform(-1.0, 1.0) * turn_rad)
    if not specs or (shift_m == 0.0 and turn_rad == 0.0):
        return list(specs)
    centre = np.mean([s.position_m[:2] for s in specs], axis=0)
    c, s_ = math.cos(turn), math.sin(turn)
    q_turn = np.array([0.0, 0.0, math.sin(turn / 2), math.cos(turn / 2)])
    out = []
    for spec in specs:
        ox, oy = np.subtract(spec.position_m[:2], centre)
        x, y = centre[0] + c * ox - s_ * oy + dx, centre[1] + s_ * ox + c * oy + dy
        if not (ws.x_min_m <= x <= ws.x_max_m and ws.y_min_m <= y <= ws.y_max_m):
            return list(specs)
        orn = tuple(float(v) for v in _quat_mul(q_turn, np.asarray(spec.orientation_xyzw)))
        out.append(ObjectSpec(spec.shape, spec.color_rgba, (float(x), float(y), spec.position_m[2]), orn, spec.scale))
    return out
