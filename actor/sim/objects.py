"""Objects of the paper's tasks: toy blocks, stacking cubes, novel objects and user meshes.

Frames and units: positions in metres in the world frame, which is the robot base frame; the table top
is the plane z = 0. Orientations are quaternions (x, y, z, w). `ObjectSpec.position_m` is the origin of
the body's frame: for the built-in blocks that is the centre of the bounding box (block_meshes.py), for
URDFs and user meshes whatever origin the file defines.

Object sets:
- "blocks": the nine toy shapes of block_meshes.BLOCK_SHAPES (2.5-5 cm), compound convex collision.
- "cubes": CUBE_SIZE_M cubes for stacking (the "cube" block).
- "novel": a fixed subset of pybullet_data/random_urdfs (see novel_object_paths), scaled by
  NOVEL_OBJECT_SCALE so that they fit the Panda's 8 cm gripper opening.
- user meshes: any .obj path; decomposed into convex parts with VHACD once, cached by file hash.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from xml.etree import ElementTree

import numpy as np
import pybullet as p
import pybullet_data

from romannet.common.config import WorkspaceConfig

from .block_meshes import BLOCK_SHAPES, CUBE_SIZE_M, block_parts, block_volume_m3

logger = logging.getLogger(__name__)

__all__ = [
    "BLOCK_SHAPES", "CUBE_SIZE_M", "NOVEL_OBJECT_SCALE", "OBJECT_SETS", "PALETTE_RGBA", "ObjectSpec",
    "LATERAL_FRICTION", "block_mesh_path", "novel_object_paths", "random_object_specs", "random_xy", "spawn_object",
    "urdf_lateral_friction",
]

OBJECT_SETS = ("blocks", "cubes", "novel")
ASSETS_DIR = Path(__file__).resolve().parent / "assets"

# VPG's ten colours (blue, green, brown, orange, yellow, gray, red, purple, cyan, pink).
PALETTE_RGBA: tuple[tuple[float, float, float, float], ...] = tuple(
    (r / 255.0, g / 255.0, b / 255.0, 1.0)
    for r, g, b in (
        (78, 121, 167), (89, 161, 79), (156, 117, 95), (242, 142, 43), (237, 201, 72),
        (186, 176, 172), (255, 87, 89), (176, 122, 161), (118, 183, 178), (255, 157, 167),
    )
)

BLOCK_DENSITY_KG_M3 = 800.0  # wooden toy blocks; a 5 cm cube weighs 0.1 kg
NOVEL_OBJECT_MASS_KG = 0.1  # what random_urdfs declare
# random_urdfs are ~4-10 x 10 x 10-13 cm at their own scale: halved, every one has a side <= 5 cm
# (gripper opens 8 cm) and the largest of the subset is <= 8 cm long.
NOVEL_OBJECT_SCALE = 0.5
NOVEL_STRIDE, NOVEL_COUNT = 20, 49  # random_urdfs 000, 020, ..., 960: 49 objects, as EGAD's evaluation set
LATERAL_FRICTION = 0.6
SPINNING_FRICTION = 0.001  # without it, objects pivot forever about a single contact point
ROLLING_FRICTION = 0.0001  # Bullet's rolling resistance (m): without any, resting bodies creep
# The cylinder lies on its side after most drops and then rolls: with ROLLING_FRICTION one rolling at 0.3 m/s
# went 56 cm (1 m/s: 1.2 m), off the workspace and, in 30-block scenes, off the table while the scene was
# built. 0.005 m (a table mat) stops it within 4 cm (1 m/s: 30 cm). Not for every object: a rolling
# resistance this large also lets a 3 cm pillar balance on an edge with its centre of mass 2 mm past it.
ROUND_ROLLING_FRICTION = 0.005
_ROUND_SHAPES = ("cylinder",)
_BOX_SHAPES = ("square_slab", "cuboid", "cube", "pillar")  # single boxes: use Bullet's box primitive


@dataclass(frozen=True)
class ObjectSpec:
    """One object to spawn.

    shape: a name from BLOCK_SHAPES (CUBE_SIZE_M stacking cubes are "cube"), "urdf:<path>" (novel
    objects) or a path to a user .obj mesh (metres). scale multiplies the file's / block's size.
    position_m: body frame origin in the world (= robot base) frame, metres, table top at z = 0.
    orientation_xyzw: unit quaternion of the body frame in the world frame.
    """

    shape: str
    color_rgba: tuple[float, float, float, float]
    position_m: tuple[float, float, float]
    orientation_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)
    scale: float = 1.0


def block_mesh_path(shape: str) -> Path:
    """The committed OBJ mesh of a built-in block (assets/blocks/<shape>.obj)."""
    if shape not in BLOCK_SHAPES:
        raise KeyError(f"unknown block shape {shape!r}; known: {', '.join(BLOCK_SHAPES)}")
    return ASSETS_DIR / "blocks" / f"{shape}.obj"


def _set_dynamics(client: int, body: int, mass_kg: float | None = None,
                  rolling_friction: float = ROLLING_FRICTION, lateral_friction: float = LATERAL_FRICTION) -> None:
    kwargs = {} if mass_kg is None else {"mass": mass_kg}
    p.changeDynamics(body, -1, lateralFriction=lateral_friction, spinningFriction=SPINNING_FRICTION,
                     rollingFriction=rolling_friction, restitution=0.0, physicsClientId=client, **kwargs)


@cache
def urdf_lateral_friction(path: str) -> float | None:
    """The lateral friction a URDF declares for its base link (<contact><lateral_friction value=...>), None
    where it declares none or the file does not parse (the caller then keeps LATERAL_FRICTION)."""
    try:
        root = ElementTree.parse(path).getroot()
    except (OSError, ElementTree.ParseError):
        return None
    link = root.find("link")
    node = link.find("contact/lateral_friction") if link is not None else None
    try:
        value = float(node.get("value", "")) if node is not None else math.nan
    except ValueError:
        return None
    return value if math.isfinite(value) and 0.0 < value <= 10.0 else None


def _spawn_block(client: int, spec: ObjectSpec) -> int:
    s = spec.scale
    mesh = str(block_mesh_path(spec.shape))
    if spec.shape in _BOX_SHAPES:
        (part,) = block_parts(spec.shape)
        half = (part.vertices().max(axis=0) * s).tolist()
        col = p.createCollisionShape(p.GEOM_BOX, halfExtents=half, physicsClientId=client)
    else:
        # A multi-group OBJ becomes a compound of one convex hull per group (exact concave collision).
        col = p.createCollisionShape(p.GEOM_MESH, fileName=mesh, meshScale=[s, s, s], physicsClientId=client)
    vis = p.createVisualShape(p.GEOM_MESH, fileName=mesh, meshScale=[s, s, s], rgbaColor=list(spec.color_rgba),
                              physicsClientId=client)
    mass = BLOCK_DENSITY_KG_M3 * block_volume_m3(spec.shape) * s**3
    body = p.createMultiBody(mass, col, vis, list(spec.position_m), list(spec.orientation_xyzw),
                             physicsClientId=client)
    _set_dynamics(client, body,
                  rolling_friction=ROUND_ROLLING_FRICTION if spec.shape in _ROUND_SHAPES else ROLLING_FRICTION)
    return body


def _spawn_urdf(client: int, spec: ObjectSpec) -> int:
    path = spec.shape[len("urdf:"):]
    if not Path(path).is_file():
        raise FileNotFoundError(f"object URDF not found: {path}")
    # Inertia is computed by PyBullet from the collision shapes (random_urdfs declare an absurd 1 kg m^2).
    body = p.loadURDF(path, list(spec.position_m), list(spec.orientation_xyzw), globalScaling=spec.scale,
                      physicsClientId=client)
    p.changeVisualShape(body, -1, rgbaColor=list(spec.color_rgba), physicsClientId=client)
    # The file's own friction where it has one: random_urdfs declare 1.0 (with the pads' 1.5, Bullet's product
    # 1.5). At the blocks' 0.6 the scripted oracle lost 57 of 61 failed picks on 30 novel objects in the lift.
    _set_dynamics(client, body, lateral_friction=urdf_lateral_friction(path) or LATERAL_FRICTION)
    return body


def _cache_dir() -> Path:
    root = os.environ.get("ROMANNET_CACHE_DIR") or os.path.join(
        os.environ.get("XDG_CACHE_HOME", os.path.expanduser("~/.cache")), "romannet")
    return Path(root) / "vhacd"


def convex_decomposition(client: int, obj_path: Path) -> Path:
    """VHACD convex decomposition of a mesh, cached by the file's SHA-256 (computed once per mesh)."""
    digest = hashlib.sha256(obj_path.read_bytes()).hexdigest()[:24]
    out = _cache_dir() / f"{digest}.obj"
    if not out.is_file():
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_suffix(f".{os.getpid()}.tmp.obj")  # rename at the end: concurrent actors never read half a file
        log = out.with_suffix(".log")
        logger.info("convex decomposition of %s (VHACD) -> %s", obj_path, out)
        p.vhacd(str(obj_path), str(tmp), str(log), resolution=50000, maxNumVerticesPerCH=32,
                physicsClientId=client)
        if not tmp.is_file() or tmp.stat().st_size == 0:
            raise RuntimeError(f"VHACD produced no output for {obj_path} (see {log})")
        os.replace(tmp, out)
    return out


def _spawn_user_mesh(client: int, spec: ObjectSpec) -> int:
    path = Path(spec.shape).expanduser().resolve()
    if not path.is_file():
        raise FileNotFoundError(f"object mesh not found: {path}")
    s = spec.scale
    collision_mesh = convex_decomposition(client, path)
    col = p.createCollisionShape(p.GEOM_MESH, fileName=str(collision_mesh), meshScale=[s, s, s],
                                 physicsClientId=client)
    vis = p.createVisualShape(p.GEOM_MESH, fileName=str(path), meshScale=[s, s, s],
                              rgbaColor=list(spec.color_rgba), physicsClientId=client)
    if col < 0 or vis < 0:
        raise ValueError(f"PyBullet could not load the mesh {path}")
    body = p.createMultiBody(1.0, col, vis, list(spec.position_m), list(spec.orientation_xyzw),
                             physicsClientId=client)
    lo, hi = p.getAABB(body, physicsClientId=client)
    # Mass from the bounding box at half the block density: meshes carry no mass, and a hollow-ish
    # object of unknown fill is lighter than its box.
    volume_m3 = float(np.prod(np.subtract(hi, lo)))
    _set_dynamics(client, body, mass_kg=max(0.02, 0.5 * BLOCK_DENSITY_KG_M3 * volume_m3))
    return body


def spawn_object(client: int, spec: ObjectSpec) -> int:
    """Create the object in PyBullet client `client`; returns its body id.

    Mass from volume (blocks), the file (URDFs) or the bounding box (user meshes); friction from this
    module's constants, or a URDF's own lateral friction where it declares one. Raises ValueError for an
    unknown shape, FileNotFoundError for a missing file.
    """
    if spec.scale <= 0 or not math.isfinite(spec.scale):
        raise ValueError(f"object scale must be a positive number, got {spec.scale}")
    if spec.shape in BLOCK_SHAPES:
        return _spawn_block(client, spec)
    if spec.shape.startswith("urdf:"):
        return _spawn_urdf(client, spec)
    if spec.shape.lower().endswith(".obj"):
        return _spawn_user_mesh(client, spec)
    raise ValueError(f"unknown object shape {spec.shape!r}: expected one of {', '.join(BLOCK_SHAPES)}, "
                     "'urdf:<path>' or a path to an .obj file")


def novel_object_paths() -> list[str]:
    """The held-out novel objects: pybullet_data/random_urdfs 000, 020, ..., 960 (49 URDFs).

    Why this subset: a fixed stride over the procedural generator's sequence gives an evenly spread,
    deterministic sample of the same size as EGAD's evaluation set (49), independent of any RNG.
    None of these objects is used by the training tasks (they use "blocks"/"cubes").
    Spawn them with scale NOVEL_OBJECT_SCALE.
    """
    return list(_novel_object_paths())


@cache
def _novel_object_paths() -> tuple[str, ...]:
    root = Path(pybullet_data.getDataPath()) / "random_urdfs"
    paths = [root / f"{i:03d}" / f"{i:03d}.urdf" for i in range(0, NOVEL_STRIDE * NOVEL_COUNT, NOVEL_STRIDE)]
    missing = [str(x) for x in paths if not x.is_file()]
    if missing:
        raise FileNotFoundError(f"pybullet_data lacks novel objects: {missing[:3]}...")
    return tuple(str(x) for x in paths)


def random_quaternion(rng: np.random.Generator) -> tuple[float, float, float, float]:
    """A uniformly random rotation (x, y, z, w) (Shoemake's method)."""
    u1, u2, u3 = rng.random(3)
    a, b = math.sqrt(1 - u1), math.sqrt(u1)
    return (a * math.sin(2 * math.pi * u2), a * math.cos(2 * math.pi * u2),
            b * math.sin(2 * math.pi * u3), b * math.cos(2 * math.pi * u3))


def random_xy(rng: np.random.Generator, ws: WorkspaceConfig, margin_m: float) -> tuple[float, float]:
    """x then y (metres, world frame) uniform in the workspace shrunk by margin_m on every side."""
    x = float(rng.uniform(ws.x_min_m + margin_m, ws.x_max_m - margin_m))
    y = float(rng.uniform(ws.y_min_m + margin_m, ws.y_max_m - margin_m))
    return x, y


def random_object_specs(rng: np.random.Generator, object_set: str, n: int, ws: WorkspaceConfig,
                        drop_height_m: float = 0.15, margin_m: float = 0.05) -> list[ObjectSpec]:
    """n objects of `object_set` above the workspace, to be dropped one after another.

    x, y uniform in the workspace shrunk by margin_m on every side (metres, world frame); z =
    ws.z_min_m + drop_height_m; random orientation (cubes: random yaw only, so they land flat and
    stack). Colours cycle through PALETTE_RGBA from a random start. Deterministic for a given rng state.
    """
    if object_set not in OBJECT_SETS:
        raise ValueError(f"object_set must be one of {OBJECT_SETS}, got {object_set!r}")
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    if 2 * margin_m >= min(ws.x_max_m - ws.x_min_m, ws.y_max_m - ws.y_min_m):
        raise ValueError(f"margin_m={margin_m} leaves no room in the workspace")
    novel = novel_object_paths() if object_set == "novel" else []
    first_color = int(rng.integers(len(PALETTE_RGBA)))
    specs = []
    for k in range(n):
        scale = 1.0
        if object_set == "blocks":
            shape = BLOCK_SHAPES[int(rng.integers(len(BLOCK_SHAPES)))]
        elif object_set == "cubes":
            shape = "cube"
        else:
            shape, scale = "urdf:" + novel[int(rng.integers(len(novel)))], NOVEL_OBJECT_SCALE
        x, y = random_xy(rng, ws, margin_m)
        if object_set == "cubes":
            yaw = float(rng.uniform(0.0, 2 * math.pi))
            quat = (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2))
        else:
            quat = random_quaternion(rng)
        color = PALETTE_RGBA[(first_color + k) % len(PALETTE_RGBA)]
        specs.append(ObjectSpec(shape, color, (x, y, ws.z_min_m + drop_height_m), quat, scale))
    return specs
