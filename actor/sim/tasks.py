"""The paper's three tasks as small declarative definitions, plus the scene builders and measurements.

clutter     N objects of `sim.object_set` dropped at random (again, where one lands outside the workspace);
            a picked object is removed; done when no object is left in the workspace. Progress: share of
            the initial clutter footprint cleared.
arrangement a test-case file (VPG's format) placed as written, the whole case shifted and turned a little per
            seed (sim.case_jitter_m, sim.case_jitter_deg); otherwise like clutter.
stacking    `sim.num_stacking_cubes` cubes of edge `task.cube_size_m` (5 cm by default) placed flat at
            random, apart from each other; a picked cube stays in the hand until placed; done when the
            ground-truth stack reaches `task.goal_stack_height`. Progress: stack height from the depth
            heightmap / goal.
Positions in the world (= robot base) frame, metres; table top z = 0.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from romannet.common.config import TaskConfig, WorkspaceConfig
from romannet.common.config_sim import SimConfig
from romannet.common.configbase import require

from .arrangements import default_cases, jitter_case, load_case
from .objects import CUBE_SIZE_M, ObjectSpec, random_object_specs, random_xy, spawn_object
from .robot import FINGER_OPEN_M
from .scene import Scene

log = logging.getLogger(__name__)

DROP_STEPS = 60  # physics steps between two dropped objects, so they land one after another
DROP_MARGIN_M = 0.05  # dropped objects start this far inside the workspace edges
REDROP_ROUNDS = 3  # objects that landed outside the workspace are dropped again, at most this often
SPREAD_MIN_DISTANCE_M = 0.09  # stacking cubes start this far apart (centre to centre): none touches another
SPREAD_TRIES = 100


@dataclass(frozen=True)
class TaskDef:
    """What distinguishes the tasks, declaratively."""

    kind: str
    object_set: str  # the set objects are drawn from
    num_objects: int  # 0: given by the case file
    drop: bool  # True: objects fall one by one from drop_height_m; False: placed as specified
    remove_picked: bool  # clutter removal: a successful pick takes the object out of the scene
    progress: str  # "clutter" (occupied footprint) or "stacking" (stack height / goal)
    object_scale: float = 1.0  # every drawn object's size times this (stacking: task.cube_size_m / CUBE_SIZE_M)


def task_def(task: TaskConfig, sim: SimConfig) -> TaskDef:
    """The definition of task.kind under the simulator settings."""
    if task.kind == "clutter":
        return TaskDef("clutter", sim.object_set, sim.num_objects, True, True, "clutter")
    if task.kind == "arrangement":
        return TaskDef("arrangement", sim.object_set, 0, False, True, "clutter")
    if task.kind == "stacking":
        # Placed flat and apart (not dropped): dropped cubes often land on each other, and an episode
        # that starts with a 2-stack would make the stacking efficiency (ideal 2(h-1) actions) meaningless.
        # The cubes are task.cube_size_m, the edge the stack height is measured in (common.stack), so the
        # two can never disagree.
        require(task.cube_size_m < 2 * FINGER_OPEN_M, "task.cube_size_m", task.cube_size_m,
                f"the simulated hand opens {2 * FINGER_OPEN_M:.2f} m, so it could never pick such a cube")
        return TaskDef("stacking", "cubes", sim.num_stacking_cubes, False, False, "stacking",
                       object_scale=task.cube_size_m / CUBE_SIZE_M)
    raise ValueError(f"unknown task kind {task.kind!r}: expected clutter, arrangement or stacking")


def case_path(sim: SimConfig, rng: np.random.Generator) -> Path:
    """The arrangement to load: sim.case_file if set, else one of the shipped cases chosen by the rng."""
    if sim.case_file:
        return Path(sim.case_file)
    cases = default_cases()
    if not cases:
        raise FileNotFoundError("no arrangement case files are shipped (actor/sim/cases/*.txt)")
    return cases[int(rng.integers(len(cases)))]


def object_specs(td: TaskDef, sim: SimConfig, ws: WorkspaceConfig, rng: np.random.Generator) -> list[ObjectSpec]:
    """The episode's objects, drawn from rng (deterministic for a given seed)."""
    if td.kind == "arrangement":
        return jitter_case(load_case(case_path(sim, rng), ws), rng, ws, sim.case_jitter_m,
                           math.radians(sim.case_jitter_deg))
    specs = random_object_specs(rng, td.object_set, td.num_objects, ws, drop_height_m=sim.drop_height_m,
                                margin_m=DROP_MARGIN_M)
    if td.object_scale != 1.0:
        specs = [dataclasses.replace(spec, scale=spec.scale * td.object_scale) for spec in specs]
    return specs if td.drop else _spread_on_table(specs, rng, ws)


def _spread_on_table(specs: list[ObjectSpec], rng: np.random.Generator, ws: WorkspaceConfig,
                     margin_m: float = 0.05) -> list[ObjectSpec]:
    """The same objects resting on the table, centres at least SPREAD_MIN_DISTANCE_M apart (rejection
    sampling from rng; after SPREAD_TRIES misses an object keeps its drawn x, y)."""
    placed: list[np.ndarray] = []
    out = []
    for spec in specs:
        xy = np.array(spec.position_m[:2])
        for _ in range(SPREAD_TRIES):
            if all(np.linalg.norm(xy - q) >= SPREAD_MIN_DISTANCE_M for q in placed):
                break
            xy = np.array(random_xy(rng, ws, margin_m))
        placed.append(xy)
        z = ws.z_min_m + CUBE_SIZE_M * spec.scale / 2.0 + 0.001
        out.append(dataclasses.replace(spec, position_m=(float(xy[0]), float(xy[1]), z)))
    return out


def build_scene(scene: Scene, td: TaskDef, specs: list[ObjectSpec], rng: np.random.Generator) -> None:
    """Spawn the objects into an emptied scene (dropping them one by one if the task says so) and settle.

    Dropped objects that bounced or rolled out of the workspace are dropped again at a new place drawn from
    rng (up to REDROP_ROUNDS times), so an episode starts with its objects where the camera and the arm
    reach them (a stray left near the table edge fell off at the first push and ended the episode).
    """
    spawned: dict[int, ObjectSpec] = {}
    for spec in specs:
        body = spawn_object(scene.client, spec)
        scene.add_object(body)
        spawned[body] = spec
        if td.drop:
            scene.step(DROP_STEPS)
    scene.settle(scene.sim.settle_steps)
    if td.drop:
        redrop_strays(scene, spawned, rng)


def redrop_strays(scene: Scene, spawned: dict[int, ObjectSpec], rng: np.random.Generator,
                  rounds: int = REDROP_ROUNDS) -> int:
    """Drop every object whose centre is outside the workspace again from a new random place above it (the
    same object, x, y drawn from rng as for the first drop), then settle; repeat up to `rounds` times.

    spawned maps body id -> the spec it was spawned from (updated for the new bodies). Returns how many
    objects are still outside the workspace (logged; 0 nearly always).
    """
    ws = scene.ws
    strays = [b for b in scene.objects if not scene.in_workspace(b)]
    for round_ in range(rounds):
        if not strays:
            break
        log.debug("re-dropping %d object(s) that landed outside the workspace (round %d)", len(strays), round_ + 1)
        for body in strays:
            spec = spawned.pop(body)
            scene.discard_object(body)
            x, y = random_xy(rng, ws, DROP_MARGIN_M)
            spec = dataclasses.replace(spec, position_m=(x, y, ws.z_min_m + scene.sim.drop_height_m))
            new = spawn_object(scene.client, spec)
            scene.add_object(new)
            spawned[new] = spec
            scene.step(DROP_STEPS)
        scene.settle(scene.sim.settle_steps)
        strays = [b for b in scene.objects if not scene.in_workspace(b)]
    if strays:
        log.warning("%d object(s) still outside the workspace after %d re-drops", len(strays), rounds)
    return len(strays)


def objects_in_workspace(scene: Scene) -> int:
    """Objects whose centre is over the workspace (clutter is done when this is 0)."""
    return sum(scene.in_workspace(b) for b in scene.objects)


def stack_height_from_poses(scene: Scene, cube_size_m: float, exclude: int | None = None) -> int:
    """Ground-truth height of the tallest stack, in cubes, built from the table up.

    A cube counts at level 1 if it stands on the table (bottom within half a cube of it), at level k + 1 if
    it stands on a level-k cube (bottom within half a cube of that cube's top, centres less than a cube apart
    horizontally). Anything else, a cube in the hand, one lifted with it or one resting on it, is not part of
    a stack: counting the highest top instead read a cube carried at 0.5 m as a stack of 10 and ended two
    training episodes as "done" (docs/journal.md). exclude: a body to ignore (the cube the env knows is held).
    A cube counts while any of it is over the workspace (its centre within half a cube of the square), where
    the heightmap sees it: the reward measures stacks there (common.stack), and counting centres only left
    stacks built at the square's edge rewarded by every place but never "done" (docs/journal.md).
    """
    half, z0 = 0.5 * cube_size_m, scene.ws.z_min_m
    # (bottom, top, xy) of each body, read once; sorted from the lowest up, so a supporting cube has its
    # level before what it carries is looked at.
    bodies = sorted(((scene.bottom_z(b) - z0, scene.top_z(b) - z0, scene.pose(b)[0][:2]) for b in scene.objects
                     if b != exclude and scene.in_workspace(b, half)), key=lambda body: body[0])
    counted: list[tuple[float, np.ndarray, int]] = []  # (top, xy, level) of the cubes in a stack
    for bottom, top, xy in bodies:
        if bottom < half:
            counted.append((top, xy, 1))
            continue
        below = [lvl for t, q, lvl in counted
                 if abs(bottom - t) < half and float(np.linalg.norm(q - xy)) < cube_size_m]
        if below:
            counted.append((top, xy, max(below) + 1))
    return max((lvl for _, _, lvl in counted), default=0)
