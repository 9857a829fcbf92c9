"""Geometry of the nine toy blocks, written as OBJ meshes made of convex parts.

Every block is a union of convex prisms (a convex polygon extruded along one axis). Each part is one
`o` group in the OBJ file; PyBullet turns a multi-group OBJ given to `createCollisionShape(GEOM_MESH)`
into a compound of convex hulls, one per group, so concave blocks (arch, half-pipe) get exact concave
collision without VHACD, deterministically, and the visual mesh is the very same file (visual matches
collision).

Frames and units: metres; the block's frame origin is the centre of its axis-aligned bounding box, with
+z up in the block's natural resting pose (flat face down). The order of BLOCK_SHAPES follows the VPG
block meshes `objects/blocks/<i>.obj` (i = 0..8), so index i of VPG maps to BLOCK_SHAPES[i] (see
arrangements.py); VPG's blocks are up to 10 cm long, ours are scaled to 2.5-5 cm (the issue's range).

The committed files under assets/blocks/ are the output of `write_block_meshes`; a test regenerates
them and compares, so the code here stays the single source of truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# Order = VPG mesh index 0..8 (VPG's 5.obj was not available to compare; half_pipe takes its slot).
BLOCK_SHAPES: tuple[str, ...] = (
    "triangular_prism",  # VPG 0: roof-shaped prism
    "arch",  # VPG 1: box with a semicircular opening underneath (concave)
    "square_slab",  # VPG 2: flat square tile
    "cuboid",  # VPG 3: plank (ours a 5 x 2.5 x 2.5 cm bar)
    "cube",  # VPG 4: 5 cm cube (also the stacking cube)
    "half_pipe",  # VPG 5 (unavailable): half of a tube, opening up (concave)
    "pillar",  # VPG 6: tall square column
    "half_cylinder",  # VPG 7: half cylinder lying on its flat face
    "cylinder",  # VPG 8: upright cylinder
)

CUBE_SIZE_M = 0.05
ARCH_SIZE_M = (0.05, 0.025, 0.03)  # x (across the opening), y (depth), z (height)
ARCH_OPENING_RADIUS_M = 0.0125  # semicircular opening, centred at the bottom face
_ROUND_SEGMENTS = 24  # polygon segments of a full circle (half shapes use half of them)


@dataclass(frozen=True)
class ConvexPart:
    """A convex polygon `polygon` (in the two axes other than `axis`, in axis order) extruded along `axis`
    from `lo_m` to `hi_m` (metres, block frame)."""

    polygon: tuple[tuple[float, float], ...]
    axis: int  # 0 = x, 1 = y, 2 = z
    lo_m: float
    hi_m: float

    def vertices(self) -> np.ndarray:
        """(2n, 3) vertices: the polygon at lo_m, then at hi_m."""
        others = [a for a in range(3) if a != self.axis]
        out = np.zeros((2 * len(self.polygon), 3))
        for k, (u, v) in enumerate(self.polygon):
            for layer, w in enumerate((self.lo_m, self.hi_m)):
                row = out[layer * len(self.polygon) + k]
                row[others[0]], row[others[1]], row[self.axis] = u, v, w
        return out

    def volume_m3(self) -> float:
        pts = np.asarray(self.polygon)
        area = 0.5 * abs(float(np.dot(pts[:, 0], np.roll(pts[:, 1], -1)) - np.dot(pts[:, 1], np.roll(pts[:, 0], -1))))
        return area * (self.hi_m - self.lo_m)


def _rect(u0: float, u1: float, v0: float, v1: float) -> tuple[tuple[float, float], ...]:
    return ((u0, v0), (u1, v0), (u1, v1), (u0, v1))


def _box(sx: float, sy: float, sz: float) -> list[ConvexPart]:
    return [ConvexPart(_rect(-sx / 2, sx / 2, -sy / 2, sy / 2), 2, -sz / 2, sz / 2)]


def _arc(radius: float, start: float, stop: float, segments: int, cu: float = 0.0, cv: float = 0.0):
    angles = np.linspace(start, stop, segments + 1)
    return [(cu + radius * math.cos(a), cv + radius * math.sin(a)) for a in angles]


def _arch() -> list[ConvexPart]:
    sx, sy, sz = ARCH_SIZE_M
    r = ARCH_OPENING_RADIUS_M
    bottom, top = -sz / 2, sz / 2
    parts = [  # two pillars beside the opening
        ConvexPart(_rect(-sx / 2, -r, bottom, top), 1, -sy / 2, sy / 2),
        ConvexPart(_rect(r, sx / 2, bottom, top), 1, -sy / 2, sy / 2),
    ]
    # Above the opening: slabs whose bottom is a chord of the semicircle (convex; the chord lies at most
    # r(1 - cos(pi/12)) ~ 0.4 mm inside the opening).
    arc = _arc(r, math.pi, 0.0, _ROUND_SEGMENTS // 4, 0.0, bottom)
    for (u0, v0), (u1, v1) in zip(arc[:-1], arc[1:], strict=True):
        parts.append(ConvexPart(((u0, v0), (u1, v1), (u1, top), (u0, top)), 1, -sy / 2, sy / 2))
    return parts


def _half_pipe(outer_r: float = 0.025, inner_r: float = 0.0165, length: float = 0.04) -> list[ConvexPart]:
    # Tube axis along y at the top face; the bottom half of the annulus, cut into convex sectors.
    axis_z = outer_r / 2
    n = _ROUND_SEGMENTS // 3
    outer = _arc(outer_r, math.pi, 2 * math.pi, n, 0.0, axis_z)
    inner = _arc(inner_r, math.pi, 2 * math.pi, n, 0.0, axis_z)
    return [
        ConvexPart((outer[k], outer[k + 1], inner[k + 1], inner[k]), 1, -length / 2, length / 2) for k in range(n)
    ]


def _half_cylinder(radius: float = 0.025, length: float = 0.04) -> list[ConvexPart]:
    # Flat face down: the semicircle (x, z) with z from -radius/2 to +radius/2.
    arc = _arc(radius, 0.0, math.pi, _ROUND_SEGMENTS // 2, 0.0, -radius / 2)
    return [ConvexPart(tuple(arc), 1, -length / 2, length / 2)]


def _cylinder(radius: float = 0.02, height: float = 0.045) -> list[ConvexPart]:
    ring = _arc(radius, 0.0, 2 * math.pi, _ROUND_SEGMENTS)[:-1]
    return [ConvexPart(tuple(ring), 2, -height / 2, height / 2)]


def _triangular_prism(base: float = 0.05, height: float = 0.04, length: float = 0.04) -> list[ConvexPart]:
    tri = ((-base / 2, -height / 2), (base / 2, -height / 2), (0.0, height / 2))
    return [ConvexPart(tri, 1, -length / 2, length / 2)]


def block_parts(shape: str) -> list[ConvexPart]:
    """The convex parts of one of BLOCK_SHAPES (metres, block frame). Raises KeyError for other names."""
    builders = {
        "triangular_prism": _triangular_prism,
        "arch": _arch,
        "square_slab": lambda: _box(0.045, 0.045, 0.025),
        "cuboid": lambda: _box(0.05, 0.025, 0.025),
        "cube": lambda: _box(CUBE_SIZE_M, CUBE_SIZE_M, CUBE_SIZE_M),
        "half_pipe": _half_pipe,
        "pillar": lambda: _box(0.03, 0.03, 0.05),
        "half_cylinder": _half_cylinder,
        "cylinder": _cylinder,
    }
    if shape not in builders:
        raise KeyError(f"unknown block shape {shape!r}; known: {', '.join(BLOCK_SHAPES)}")
    return builders[shape]()


def block_extents_m(shape: str) -> tuple[float, float, float]:
    """Size of the block's bounding box along its own x, y, z (metres, unscaled)."""
    pts = np.concatenate([p.vertices() for p in block_parts(shape)])
    return tuple(float(v) for v in pts.max(axis=0) - pts.min(axis=0))  # type: ignore[return-value]


def block_volume_m3(shape: str) -> float:
    """Volume of the block (metres cubed, unscaled); parts do not overlap."""
    return sum(p.volume_m3() for p in block_parts(shape))


def _fmt(x: float) -> str:
    text = f"{x:.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text


def block_obj_text(shape: str) -> str:
    """OBJ text for the block: one `o` group per convex part, flat normals, outward faces."""
    lines = [f"# {shape}: generated by romannet actor/sim/block_meshes.py; units metres, frame = bbox centre"]
    v_base, n_base = 0, 0
    for index, part in enumerate(block_parts(shape)):
        verts = part.vertices()
        n = len(part.polygon)
        centroid = verts.mean(axis=0)
        faces = [list(range(n)), list(range(2 * n - 1, n - 1, -1))]  # caps
        faces += [[k, (k + 1) % n, n + (k + 1) % n, n + k] for k in range(n)]  # sides
        lines.append(f"o part_{index}")
        lines += ["v " + " ".join(_fmt(c) for c in row) for row in verts]
        normals = []
        for face in faces:
            pts = verts[face]
            normal = np.cross(pts[1] - pts[0], pts[2] - pts[0])
            if np.dot(normal, pts.mean(axis=0) - centroid) < 0:  # make every face point outwards
                face.reverse()
                normal = -normal
            normals.append(normal / np.linalg.norm(normal))
        lines += ["vn " + " ".join(_fmt(c) for c in nrm) for nrm in normals]
        for k, face in enumerate(faces):
            lines.append("f " + " ".join(f"{v_base + i + 1}//{n_base + k + 1}" for i in face))
        v_base += len(verts)
        n_base += len(faces)
    return "\n".join(lines) + "\n"


def write_block_meshes(out_dir: Path) -> list[Path]:
    """Write `<shape>.obj` for every block into out_dir (used to produce assets/blocks/)."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for shape in BLOCK_SHAPES:
        path = out_dir / f"{shape}.obj"
        path.write_text(block_obj_text(shape))
        paths.append(path)
    return paths
