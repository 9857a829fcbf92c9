"""Object sets of the simulator: block geometry, spawning, random drops, novel objects, user meshes.

Each test uses its own PyBullet DIRECT client (never the global one) with a plane at z = 0 as the table.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pybullet as p
import pytest

from romannet.actor.sim.block_meshes import BLOCK_SHAPES, block_extents_m, block_obj_text
from romannet.actor.sim.objects import (
    CUBE_SIZE_M,
    LATERAL_FRICTION,
    NOVEL_OBJECT_SCALE,
    OBJECT_SETS,
    PALETTE_RGBA,
    ObjectSpec,
    block_mesh_path,
    novel_object_paths,
    random_object_specs,
    spawn_object,
    urdf_lateral_friction,
)
from romannet.common.config import WorkspaceConfig

WS = WorkspaceConfig()
GRIPPER_OPENING_M = 0.08  # Franka Panda
RED = PALETTE_RGBA[6]


@pytest.fixture
def client() -> Iterator[int]:
    cid = p.connect(p.DIRECT)
    try:
        p.setGravity(0, 0, -9.81, physicsClientId=cid)
        p.setTimeStep(1 / 240, physicsClientId=cid)
        plane = p.createCollisionShape(p.GEOM_PLANE, physicsClientId=cid)
        p.createMultiBody(0, plane, physicsClientId=cid)
        yield cid
    finally:
        p.disconnect(cid)


def _extent(cid: int, body: int) -> np.ndarray:
    lo, hi = p.getAABB(body, physicsClientId=cid)
    return np.subtract(hi, lo)


def _step(cid: int, steps: int) -> None:
    for _ in range(steps):
        p.stepSimulation(physicsClientId=cid)


def test_committed_block_meshes_match_their_generator() -> None:
    for shape in BLOCK_SHAPES:
        assert block_mesh_path(shape).read_text() == block_obj_text(shape), f"regenerate assets for {shape}"


def test_nine_distinct_block_shapes_of_toy_size() -> None:
    assert len(BLOCK_SHAPES) == len(set(BLOCK_SHAPES)) == 9
    assert block_extents_m("cube") == pytest.approx((CUBE_SIZE_M,) * 3)
    for shape in BLOCK_SHAPES:
        ext = np.array(block_extents_m(shape))
        assert 0.025 - 1e-9 <= ext.min() and ext.max() <= 0.05 + 1e-9, (shape, ext)
        assert np.sort(ext)[0] < GRIPPER_OPENING_M - 0.02, shape  # graspable across its thinnest side


def test_each_block_spawns_with_its_size_and_rests_on_the_table(client: int) -> None:
    bodies = {}
    for k, shape in enumerate(BLOCK_SHAPES):
        height = block_extents_m(shape)[2]
        pos = (0.35 + 0.08 * (k % 5), -0.1 + 0.1 * (k // 5), height / 2)
        bodies[shape] = spawn_object(client, ObjectSpec(shape, RED, pos))
    _step(client, 120)
    for shape, body in bodies.items():
        # Bullet pads AABBs by a collision margin of a few millimetres.
        assert _extent(client, body) == pytest.approx(block_extents_m(shape), abs=0.005), shape
        assert p.getDynamicsInfo(body, -1, physicsClientId=client)[0] > 0.01  # mass, kg
        z = p.getBasePositionAndOrientation(body, physicsClientId=client)[0][2]
        assert z == pytest.approx(block_extents_m(shape)[2] / 2, abs=0.003), shape


def test_arch_has_a_real_opening(client: int) -> None:
    """Rays along the arch's depth axis pass under its top through the opening, and hit its pillars."""
    sx, sy, sz = block_extents_m("arch")
    body = spawn_object(client, ObjectSpec("arch", RED, (0.5, 0.0, sz / 2)))

    def hit(x: float, z: float) -> bool:
        result = p.rayTest((x, -0.1, z), (x, 0.1, z), physicsClientId=client)[0]
        return result[0] == body

    assert not hit(0.5, 0.004) and not hit(0.5, 0.008) and not hit(0.505, 0.004)  # through the opening
    assert hit(0.5, sz - 0.004)  # the top above the opening
    assert hit(0.5 + sx / 2 - 0.005, 0.004) and hit(0.5 - sx / 2 + 0.005, 0.004)  # the pillars


def test_half_pipe_is_hollow(client: int) -> None:
    body = spawn_object(client, ObjectSpec("half_pipe", RED, (0.5, 0.0, block_extents_m("half_pipe")[2] / 2)))
    result = p.rayTest((0.5, 0.0, 0.2), (0.5, 0.0, -0.01), physicsClientId=client)[0]
    assert result[0] == body and result[3][2] < 0.012  # lands on the inner bottom, not on a filled top


@pytest.mark.parametrize("object_set", OBJECT_SETS)
def test_random_specs_deterministic_and_above_the_workspace(object_set: str) -> None:
    a = random_object_specs(np.random.default_rng(7), object_set, 12, WS, drop_height_m=0.2, margin_m=0.05)
    b = random_object_specs(np.random.default_rng(7), object_set, 12, WS, drop_height_m=0.2, margin_m=0.05)
    c = random_object_specs(np.random.default_rng(8), object_set, 12, WS, drop_height_m=0.2, margin_m=0.05)
    assert a == b and a != c and len(a) == 12
    for spec in a:
        x, y, z = spec.position_m
        assert WS.x_min_m + 0.05 <= x <= WS.x_max_m - 0.05 and WS.y_min_m + 0.05 <= y <= WS.y_max_m - 0.05
        assert z == pytest.approx(WS.z_min_m + 0.2)
        assert np.linalg.norm(spec.orientation_xyzw) == pytest.approx(1.0)
        assert spec.color_rgba in PALETTE_RGBA
    shapes = {s.shape for s in a}
    if object_set == "cubes":
        assert shapes == {"cube"}
    elif object_set == "blocks":
        assert shapes <= set(BLOCK_SHAPES) and len(shapes) > 3
    else:
        assert {s[len("urdf:"):] for s in shapes} <= set(novel_object_paths())
        assert {s.scale for s in a} == {NOVEL_OBJECT_SCALE}


def test_random_specs_reject_bad_arguments() -> None:
    rng = np.random.default_rng(0)
    with pytest.raises(ValueError, match="object_set"):
        random_object_specs(rng, "spheres", 3, WS)
    with pytest.raises(ValueError, match="margin"):
        random_object_specs(rng, "blocks", 3, WS, margin_m=0.3)


@pytest.mark.parametrize("object_set", ["blocks", "cubes"])
def test_dropped_objects_settle_in_the_workspace(client: int, object_set: str) -> None:
    specs = random_object_specs(np.random.default_rng(3), object_set, 8, WS)
    bodies = []
    for spec in specs:  # one after another, as the clutter task drops them
        bodies.append(spawn_object(client, spec))
        _step(client, 60)
    _step(client, 240)
    for body in bodies:
        (x, y, z), _ = p.getBasePositionAndOrientation(body, physicsClientId=client)
        assert WS.x_min_m <= x <= WS.x_max_m and WS.y_min_m <= y <= WS.y_max_m and -0.002 < z < 0.2
        assert np.linalg.norm(p.getBaseVelocity(body, physicsClientId=client)[0]) < 0.05


def test_novel_subset_is_fixed_loads_and_fits_the_gripper(client: int) -> None:
    paths = novel_object_paths()
    assert len(paths) == 49 == len(set(paths))
    assert [Path(x).stem for x in paths] == [f"{i:03d}" for i in range(0, 980, 20)]
    assert novel_object_paths() == paths  # deterministic, a fresh list each call
    for k, path in enumerate(paths):
        body = spawn_object(client, ObjectSpec("urdf:" + path, RED, (0.5, 0.0, 0.1 + 0.2 * k), scale=NOVEL_OBJECT_SCALE))
        ext = np.sort(_extent(client, body))
        assert ext[0] <= GRIPPER_OPENING_M - 0.025, (path, ext)  # a side the open gripper spans
        assert ext[2] <= 0.09, (path, ext)


def test_a_urdf_keeps_the_friction_it_declares_and_blocks_keep_ours(client: int, tmp_path: Path) -> None:
    novel = novel_object_paths()[0]
    assert urdf_lateral_friction(novel) == 1.0  # random_urdfs: <contact><lateral_friction value="1.0"/>
    body = spawn_object(client, ObjectSpec("urdf:" + novel, RED, (0.5, 0.0, 0.1), scale=NOVEL_OBJECT_SCALE))
    assert p.getDynamicsInfo(body, -1, physicsClientId=client)[1] == pytest.approx(1.0)
    block = spawn_object(client, ObjectSpec("cube", RED, (0.6, 0.0, 0.1)))
    assert p.getDynamicsInfo(block, -1, physicsClientId=client)[1] == pytest.approx(LATERAL_FRICTION)

    bare = tmp_path / "bare.urdf"  # no <contact>: our friction
    bare.write_text(Path(novel).read_text().split("<contact>")[0] + Path(novel).read_text().split("</contact>")[1])
    assert "<contact>" not in bare.read_text() and urdf_lateral_friction(str(bare)) is None
    mesh_dir = Path(novel).parent
    (tmp_path / Path(novel).name.replace(".urdf", ".obj")).symlink_to(mesh_dir / Path(novel).name.replace(".urdf", ".obj"))
    body = spawn_object(client, ObjectSpec("urdf:" + str(bare), RED, (0.4, 0.0, 0.1), scale=NOVEL_OBJECT_SCALE))
    assert p.getDynamicsInfo(body, -1, physicsClientId=client)[1] == pytest.approx(LATERAL_FRICTION)
    for text in ("<robot><link", '<robot><link name="a"><contact><lateral_friction value="grip"/></contact></link></robot>',
                 '<robot><link name="a"><contact><lateral_friction value="-1"/></contact></link></robot>'):
        bad = tmp_path / "bad.urdf"
        bad.write_text(text)
        urdf_lateral_friction.cache_clear()
        assert urdf_lateral_friction(str(bad)) is None, text


def _write_l_shape(path: Path) -> None:
    """A closed, concave L-shaped prism (4 x 4 x 2 cm, 2 cm arms) as an OBJ file (metres)."""
    outline = [(0, 0), (0.04, 0), (0.04, 0.02), (0.02, 0.02), (0.02, 0.04), (0, 0.04)]
    lines = [f"v {x - 0.02} {y - 0.02} {z}" for z in (-0.01, 0.01) for x, y in outline]
    lines += ["f 1 6 5 4 3 2", "f 7 8 9 10 11 12"]
    lines += [f"f {k + 1} {(k + 1) % 6 + 1} {(k + 1) % 6 + 7} {k + 7}" for k in range(6)]
    path.write_text("\n".join(lines) + "\n")


def test_user_obj_mesh_loads_with_concave_collision(client: int, tmp_path: Path,
                                                    monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("ROMANNET_CACHE_DIR", str(tmp_path / "cache"))
    mesh = tmp_path / "l_shape.obj"
    _write_l_shape(mesh)
    body = spawn_object(client, ObjectSpec(str(mesh), RED, (0.5, 0.0, 0.011)))
    assert _extent(client, body)[:2] == pytest.approx((0.04, 0.04), abs=0.006)
    assert len(list((tmp_path / "cache" / "vhacd").glob("*.obj"))) == 1  # decomposition cached by hash
    # The missing quadrant of the L is empty: a ray down through it reaches the table.
    result = p.rayTest((0.51, 0.01, 0.1), (0.51, 0.01, -0.01), physicsClientId=client)[0]
    assert result[0] != body
    _step(client, 120)
    assert p.getBasePositionAndOrientation(body, physicsClientId=client)[0][2] == pytest.approx(0.01, abs=0.004)
    spawn_object(client, ObjectSpec(str(mesh), RED, (0.6, 0.0, 0.011), scale=1.5))  # reuses the cache
    assert len(list((tmp_path / "cache" / "vhacd").glob("*.obj"))) == 1


def test_unknown_shapes_and_missing_files_raise(client: int, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unknown object shape"):
        spawn_object(client, ObjectSpec("sphere", RED, (0.5, 0.0, 0.1)))
    with pytest.raises(FileNotFoundError):
        spawn_object(client, ObjectSpec(str(tmp_path / "nope.obj"), RED, (0.5, 0.0, 0.1)))
    with pytest.raises(FileNotFoundError):
        spawn_object(client, ObjectSpec("urdf:" + str(tmp_path / "nope.urdf"), RED, (0.5, 0.0, 0.1)))
    with pytest.raises(ValueError, match="scale"):
        spawn_object(client, ObjectSpec("cube", RED, (0.5, 0.0, 0.1), scale=0.0))


def _rolled_distance_m(cid: int, shape: str, speed_mps: float) -> float:
    """Lay the block on its side on the plane, set it rolling along x at speed_mps, return how far it went."""
    quat = p.getQuaternionFromEuler((np.pi / 2, 0.0, 0.0))  # cylinder axis along y: it rolls along x
    body = spawn_object(client=cid, spec=ObjectSpec(shape, RED, (0.5, 0.0, 0.0205), quat))
    _step(cid, 30)
    start = np.array(p.getBasePositionAndOrientation(body, physicsClientId=cid)[0])
    p.resetBaseVelocity(body, (speed_mps, 0.0, 0.0), (0.0, speed_mps / 0.02, 0.0), physicsClientId=cid)
    _step(cid, 4 * 240)
    end = np.array(p.getBasePositionAndOrientation(body, physicsClientId=cid)[0])
    return float(np.linalg.norm((end - start)[:2]))


def test_a_rolling_cylinder_stops_within_the_workspace(client: int) -> None:
    # Lying on its side after a drop, set rolling at 0.3 m/s by a bounce or a push: with the default rolling
    # resistance it went 56 cm, out of the 45 cm workspace (and, in 30-block scenes, off the table).
    assert _rolled_distance_m(client, "cylinder", 0.3) < 0.08
    assert _rolled_distance_m(client, "cylinder", 1.0) < 0.4
