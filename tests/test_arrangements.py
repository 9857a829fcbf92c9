"""Arrangement test cases: VPG's text format, frame mapping, errors, our 11 committed cases and the 11
held-out ones (actor/sim/cases_heldout, never tuned on).

Our case files end with one isolated object (after a `# isolated` comment); the lines before it are the
tightly packed objects (3-6 per case, the paper's "challenging arrangements").
"""

from __future__ import annotations

import itertools
import logging
import math
from pathlib import Path

import numpy as np
import pybullet as p
import pytest

from romannet.actor.sim.arrangements import (
    CASE_SETS,
    CaseFormatError,
    cases_dir,
    coppeliasim_euler_to_quaternion,
    default_cases,
    default_cases_dir,
    jitter_case,
    load_case,
)
from romannet.actor.sim.block_meshes import BLOCK_SHAPES
from romannet.actor.sim.objects import spawn_object
from romannet.common.config import WorkspaceConfig

WS = WorkspaceConfig()
CASES = default_cases()
HELDOUT = sorted(CASE_SETS["heldout"].glob("*.txt"))
PACKED_GAP_MAX_M = 0.01  # every packed object has a neighbour at most this far away
ISOLATED_GAP_MIN_M = 0.08  # the sanity-check object is clear of the packed ones


def _write(tmp_path: Path, text: str, name: str = "case.txt") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def _rx(a: float) -> np.ndarray:
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


def _ry(a: float) -> np.ndarray:
    return np.array([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]])


def _rz(a: float) -> np.ndarray:
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


def test_eleven_cases_ship_with_the_package() -> None:
    assert [c.name for c in CASES] == [f"case_{k:02d}.txt" for k in range(1, 12)]
    assert all(c.parent == default_cases_dir() for c in CASES)


def test_eleven_heldout_cases_ship_and_resolve_by_name(tmp_path: Path) -> None:
    assert [c.name for c in HELDOUT] == [f"heldout_{k:02d}.txt" for k in range(1, 12)]
    # Names distinct from ours, so reports (rows named by file stem) of the two sets never read as one.
    assert not {c.stem for c in HELDOUT} & {c.stem for c in CASES}
    assert cases_dir(None) == cases_dir("ours") == default_cases_dir()
    assert cases_dir("heldout") == HELDOUT[0].parent and cases_dir("heldout") != default_cases_dir()
    assert cases_dir(str(tmp_path)) == tmp_path and cases_dir(tmp_path) == tmp_path
    for case in HELDOUT:  # one-line header naming the case, as ours have
        assert case.read_text().startswith(f"# RoManNet held-out arrangement case {case.stem[-2:]}: ")


@pytest.mark.parametrize("case", CASES + HELDOUT, ids=lambda c: c.stem)
def test_case_loads_packed_objects_plus_one_isolated_in_the_workspace(case: Path) -> None:
    specs = load_case(case, WS)
    assert 3 <= len(specs) - 1 <= 6  # packed objects; the last one is isolated
    assert "# isolated" in case.read_text()
    for spec in specs:
        x, y, z = spec.position_m
        assert WS.x_min_m < x < WS.x_max_m and WS.y_min_m < y < WS.y_max_m and 0 < z < 0.06
        assert spec.shape in BLOCK_SHAPES


@pytest.mark.parametrize("case", CASES + HELDOUT, ids=lambda c: c.stem)
def test_case_is_tightly_packed_and_settles_in_place(case: Path) -> None:
    specs = load_case(case, WS)
    cid = p.connect(p.DIRECT)
    try:
        p.setGravity(0, 0, -9.81, physicsClientId=cid)
        p.setTimeStep(1 / 240, physicsClientId=cid)
        p.createMultiBody(0, p.createCollisionShape(p.GEOM_PLANE, physicsClientId=cid), physicsClientId=cid)
        bodies = [spawn_object(cid, s) for s in specs]
        p.performCollisionDetection(physicsClientId=cid)
        packed, isolated = bodies[:-1], bodies[-1]

        def gap(a: int, b: int, reach: float) -> float:
            points = p.getClosestPoints(a, b, reach, physicsClientId=cid)
            return min((q[8] for q in points), default=math.inf)

        gaps = {(a, b): gap(a, b, 0.05) for a, b in itertools.permutations(packed, 2)}
        assert min(gaps.values()) > -0.001, "objects start interpenetrating"
        for a in packed:
            assert min(gaps[a, b] for b in packed if b != a) <= PACKED_GAP_MAX_M
        assert all(gap(isolated, b, 1.0) >= ISOLATED_GAP_MIN_M for b in packed)

        start = [p.getBasePositionAndOrientation(b, physicsClientId=cid)[0] for b in bodies]
        for _ in range(240):
            p.stepSimulation(physicsClientId=cid)
        for body, before in zip(bodies, start, strict=True):
            after = p.getBasePositionAndOrientation(body, physicsClientId=cid)[0]
            assert WS.x_min_m < after[0] < WS.x_max_m and WS.y_min_m < after[1] < WS.y_max_m
            assert np.linalg.norm(np.subtract(after, before)) < 0.005  # no explosion, no toppling
            linear, angular = p.getBaseVelocity(body, physicsClientId=cid)
            assert np.linalg.norm(linear) < 0.01 and np.linalg.norm(angular) < 0.1
    finally:
        p.disconnect(cid)


def test_vpg_frame_colours_and_mesh_names_map_to_ours(tmp_path: Path) -> None:
    path = _write(tmp_path, "\n".join([
        "# VPG-style lines: absolute and relative block mesh paths",
        "/home/someone/meshes/blocks/4.obj 0.3 0.4 0.5 -0.5 0.0 0.025 0 0 0",
        "",
        "blocks/1.obj 1 0 0 -0.724 -0.224 0.015 0 0 1.5708  # a trailing comment",
        "7.obj 0 1 0 -0.276 0.224 0.0125 0 0 0",
        "arch 0 0 1 -0.6 0.1 0.015 0 0 0",
    ]))
    specs = load_case(path, WS)
    assert [s.shape for s in specs] == ["cube", "arch", "half_cylinder", "arch"]
    assert specs[0].position_m == pytest.approx((0.5, 0.0, 0.025))
    assert specs[1].position_m == pytest.approx((WS.x_min_m, WS.y_min_m, 0.015))
    assert specs[2].position_m == pytest.approx((WS.x_max_m, WS.y_max_m, 0.0125))
    assert specs[0].color_rgba == (0.3, 0.4, 0.5, 1.0)
    assert specs[1].orientation_xyzw == pytest.approx((0, 0, math.sin(0.7854), math.cos(0.7854)), abs=1e-4)
    shifted = WorkspaceConfig(x_min_m=0.3, x_max_m=0.748, y_min_m=-0.1, y_max_m=0.348, z_min_m=0.02)
    assert load_case(path, shifted)[0].position_m == pytest.approx((0.524, 0.124, 0.045))


@pytest.mark.parametrize("angles", [(0.3, -0.7, 1.2), (-1.5757, -0.0467, -1.5626), (math.pi / 2, 0.8, 0.0)])
def test_euler_angles_follow_coppeliasim_rx_ry_rz(angles: tuple[float, float, float]) -> None:
    quat = coppeliasim_euler_to_quaternion(*angles)
    matrix = np.array(p.getMatrixFromQuaternion(quat)).reshape(3, 3)
    a, b, g = angles
    np.testing.assert_allclose(matrix, _rx(a) @ _ry(b) @ _rz(g), atol=1e-12)


def test_objects_outside_the_workspace_or_below_the_table_are_skipped(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = _write(tmp_path, "\n".join([
        "cube 1 0 0 -0.5 0.0 0.025 0 0 0",
        "cube 1 0 0 -0.80 0.0 0.025 0 0 0",  # beyond x_min
        "cube 1 0 0 -0.5 0.30 0.025 0 0 0",  # beyond y_max
        "6.obj 1 0 0 -0.69 -0.05 -726.58 -2.5 -0.7 0.13",  # fell off the table in VPG
    ]))
    with caplog.at_level(logging.WARNING, logger="romannet.actor.sim.arrangements"):
        specs = load_case(path, WS)
    assert len(specs) == 1 and specs[0].position_m == pytest.approx((0.5, 0.0, 0.025))
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 3
    assert all(str(path) in m for m in messages)
    assert sum("outside the workspace" in m for m in messages) == 2 and "below the table" in messages[2]
    assert ":4:" in messages[2]


@pytest.mark.parametrize(("line", "problem"), [
    ("cube 1 0 0 -0.5 0.0 0.025 0 0", "expected 10 fields"),
    ("cube 1 0 0 -0.5 0.0 0.025 0 0 0 0", "expected 10 fields"),
    ("cube 1 0 0 -0.5 zero 0.025 0 0 0", "field y is not a number"),
    ("cube 1 0 0 -0.5 0.0 nan 0 0 0", "field z is not finite"),
    ("cube 255 0 0 -0.5 0.0 0.025 0 0 0", "colour"),
    ("sphere 1 0 0 -0.5 0.0 0.025 0 0 0", "unknown mesh 'sphere'"),
    ("missing.obj 1 0 0 -0.5 0.0 0.025 0 0 0", "unknown mesh 'missing.obj'"),
    ("blocks/9.obj 1 0 0 -0.5 0.0 0.025 0 0 0", "unknown mesh"),
])
def test_malformed_line_names_file_and_line(tmp_path: Path, line: str, problem: str) -> None:
    path = _write(tmp_path, f"# header\n\ncube 1 0 0 -0.5 0.0 0.025 0 0 0\n{line}\n", name="bad_case.txt")
    with pytest.raises(CaseFormatError, match=problem) as info:
        load_case(path, WS)
    assert str(info.value).startswith(f"{path}:4: ")
    assert info.value.line_no == 4 and info.value.path == path


def test_relative_mesh_paths_resolve_next_to_the_case_file(tmp_path: Path) -> None:
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "thing.obj").write_text("v 0 0 0\nv 0.01 0 0\nv 0 0.01 0\nv 0 0 0.01\nf 1 2 3\n")
    (tmp_path / "thing.urdf").write_text("<robot name='x'/>")
    path = _write(tmp_path, "meshes/thing.obj 1 0 0 -0.5 0.0 0.02 0 0 0\n"
                            "urdf:thing.urdf 1 0 0 -0.5 0.1 0.02 0 0 0\n")
    specs = load_case(path, WS)
    assert specs[0].shape == str((tmp_path / "meshes" / "thing.obj").resolve())
    assert specs[1].shape == "urdf:" + str((tmp_path / "thing.urdf").resolve())


def _rotation(spec) -> np.ndarray:
    return np.array(p.getMatrixFromQuaternion(spec.orientation_xyzw)).reshape(3, 3)


def test_jitter_moves_a_case_as_one_rigid_body() -> None:
    specs = load_case(CASES[0], WS)
    moved = jitter_case(specs, np.random.default_rng(3), WS, shift_m=0.005, turn_rad=math.radians(3.0))
    before = np.array([s.position_m for s in specs])
    after = np.array([s.position_m for s in moved])
    assert not np.allclose(before, after)  # it did move
    # Distances between objects (packed stays packed) and heights are kept.
    for i, j in itertools.combinations(range(len(specs)), 2):
        assert np.linalg.norm(after[i] - after[j]) == pytest.approx(np.linalg.norm(before[i] - before[j]), abs=1e-9)
    assert np.allclose(before[:, 2], after[:, 2])
    # Every object turned by the same angle about world z, at most 3 degrees; the centre moved <= 5 mm per axis.
    turns = []
    for a, b in zip(specs, moved, strict=True):
        delta = _rotation(b) @ _rotation(a).T
        assert delta[2, 2] == pytest.approx(1.0, abs=1e-9)  # a rotation about the vertical
        turns.append(math.atan2(delta[1, 0], delta[0, 0]))
    assert np.ptp(turns) < 1e-9 and 0 < abs(turns[0]) <= math.radians(3.0)
    assert np.all(np.abs(after[:, :2].mean(axis=0) - before[:, :2].mean(axis=0)) <= 0.005 + 1e-12)
    assert [s.shape for s in moved] == [s.shape for s in specs]


def test_jitter_is_drawn_from_the_seed_and_zero_keeps_the_case_as_written() -> None:
    specs = load_case(CASES[1], WS)

    def jittered(seed: int, shift: float = 0.005, turn: float = 0.05) -> np.ndarray:
        return np.array([s.position_m for s in jitter_case(specs, np.random.default_rng(seed), WS, shift, turn)])

    assert np.array_equal(jittered(7), jittered(7))
    assert not np.allclose(jittered(7), jittered(8))
    assert jitter_case(specs, np.random.default_rng(7), WS, 0.0, 0.0) == specs
    # A shift that would push an object out of the workspace leaves the case as written.
    edge = [type(specs[0])(specs[0].shape, specs[0].color_rgba, (WS.x_max_m - 1e-4, 0.0, 0.02)), *specs[1:]]
    branches = set()
    for seed in range(8):
        dx = np.random.default_rng(seed).uniform(-1.0, 1.0, 2)[0] * 0.01  # the draw jitter_case makes first
        out = jitter_case(edge, np.random.default_rng(seed), WS, 0.01, 0.0)
        if dx > 1e-4:
            assert out == edge
        else:
            assert out != edge and all(WS.x_min_m <= s.position_m[0] <= WS.x_max_m for s in out)
        branches.add(dx > 1e-4)
    assert branches == {True, False}


@pytest.mark.parametrize("given", ["heldout", "ours", None])
def test_eval_plans_a_case_set_by_name(given: str | None) -> None:
    import argparse

    from romannet.evaluate.cli import add_arguments, plan_scripted

    parser = argparse.ArgumentParser()
    add_arguments(parser)
    argv = ["--policy", "oracle", "--task", "arrangement", "--runs", "2"]
    args = parser.parse_args(argv + (["--cases", given] if given else []))
    plan = plan_scripted(args)
    expected = HELDOUT if given == "heldout" else CASES
    assert plan.cases_dir == str(expected[0].parent)
    assert len(plan.specs) == 2 * len(expected)
    assert {s.case for s in plan.specs} == {c.stem for c in expected}
