"""Scripted oracle policies that read the simulator state (object poses), one per task.

Used by tests and as the simulator's ceiling (`romannet eval --policy oracle`); they return the same
`Action` a learned policy would (a heightmap pixel and an angle), so everything downstream is exercised.
Frames as in common.action: angle from the x (column) axis toward the y (row) axis; for pick/place the
finger-closing axis.

A clutter grasp is judged as the hand would meet it: where the open fingers (sim.finger_travel_m from the
centre) and the hand come down on the depth heightmap, and whether the pads then close on the object's
material (rays through the simulator's geometry). Counting neighbours within a radius instead pushed in
dense scenes where a grasp along the free axis was there, and half of the 30-block runs ended on failures.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pybullet as p

from romannet.common.action import Action, patch_max, position_to_pixel
from romannet.common.grasp_clearance import CLEAR_M, PAD_HEIGHTS_M, GripperFootprint, footprint_height

from .env import SimEnv
from .scene import wrap_half_pi

GRASP_WIDTH_MARGIN_M = 0.01  # an object this much narrower than the full opening still fits between the fingers
FREE_FLOOR_M = 0.01  # a push starts where the heightmap is below this (else it rides over an object)
EXTRA_ANGLES_RAD = (math.pi / 4, -math.pi / 4)  # tried after the footprint's two axes (irregular or round objects)
TOP_RAY_STEP_M = 0.004  # spacing of the rays that find an object's top from above
POINT_MIN_DISTANCE_M = 0.005
CROWD_RADIUS_M = 0.12  # a body with no other body's centre this close gains nothing from a push


def _footprint(env: SimEnv, body: int) -> tuple[float, float, float, float]:
    """(narrow width m, angle of the narrow axis rad, wide width m, angle of the wide axis) seen from above.

    Uses the body's local half extents and orientation: of its three axes the two most horizontal span the
    footprint.
    """
    _, orn = env.scene.pose(body)
    rot = np.array(p.getMatrixFromQuaternion(orn.tolist())).reshape(3, 3)
    half = env.scene.local_half_extents_m[body]
    axes = sorted(range(3), key=lambda i: abs(rot[2, i]))[:2]
    spans = [(2.0 * half[i], math.atan2(rot[1, i], rot[0, i])) for i in axes]
    (w0, a0), (w1, a1) = sorted(spans)
    return w0, a0, w1, a1


def _pixel(env: SimEnv, xy: np.ndarray) -> tuple[int, int] | None:
    """Heightmap pixel whose position (its corner, as pixel_to_position returns it) is nearest xy."""
    ws = env.ws
    x = float(np.clip(xy[0] + ws.resolution_m / 2, ws.x_min_m, ws.x_max_m - 1e-6))
    y = float(np.clip(xy[1] + ws.resolution_m / 2, ws.y_min_m, ws.y_max_m - 1e-6))
    try:
        return position_to_pixel(x, y, ws)
    except ValueError:
        return None


def _action(env: SimEnv, primitive: str, xy: np.ndarray, angle_rad: float) -> Action:
    px = _pixel(env, xy)
    row, col = px if px is not None else (0, 0)
    return Action(primitive, row, col, float(angle_rad), 1.0)


def _nearest_gap(env: SimEnv, body: int, bodies: list[int]) -> tuple[float, np.ndarray]:
    """Centre distance to the nearest other body (m) and that body's position."""
    pos = env.scene.pose(body)[0]
    best, best_pos = math.inf, pos
    for other in bodies:
        if other != body:
            q = env.scene.pose(other)[0]
            d = float(np.linalg.norm(q[:2] - pos[:2]))
            if d < best:
                best, best_pos = d, q
    return best, best_pos


def _across_body(env: SimEnv, body: int, xy: np.ndarray, angle_rad: float, z_tip: float) -> float | None:
    """Width (m) of body along the closing axis at the pads' heights when the fingertips are at z_tip, if
    fingers closing there over xy would squeeze material of the body at every pad height; else None.

    Rays along the closing axis, from just outside the body toward xy: an arch grasped across its thickness
    over the middle closes on its hole (the rays miss), across its span on its legs (they hit); a neighbour
    in between is hit first (the finger would close on it).
    """
    reach = float(np.linalg.norm(env.scene.local_half_extents_m[body])) + 0.01
    d = np.array([math.cos(angle_rad), math.sin(angle_rad), 0.0])
    starts, ends = [], []
    for dz in PAD_HEIGHTS_M:
        centre = np.array([xy[0], xy[1], z_tip + dz])
        starts += [(centre - reach * d).tolist(), (centre + reach * d).tolist()]
        ends += [centre.tolist(), centre.tolist()]
    hits = p.rayTestBatch(starts, ends, physicsClientId=env.scene.client)
    if not all(h[0] == body for h in hits):
        return None
    points = np.array([h[3] for h in hits])
    return float(max(np.linalg.norm(points[0] - points[1]), np.linalg.norm(points[2] - points[3])))


def _footprint_height(env: SimEnv, xy: np.ndarray, angle_rad: float) -> float:
    """Where the open fingers or the hand of a pick over xy along angle_rad land first (m above the table)."""
    ws, sim = env.ws, env.sim
    g = GripperFootprint(sim.finger_travel_m, sim.pick_depth_m, sim.fingertip_clearance_m)
    xy_px = ((xy[0] - ws.x_min_m) / ws.resolution_m, (xy[1] - ws.y_min_m) / ws.resolution_m)
    return footprint_height(env.obs.depth_hm, ws.resolution_m, xy_px, angle_rad, g)


@dataclass(frozen=True)
class Grasp:
    """A top-down pick of one body: where, along which closing axis, and how the fingers get down."""

    body: int
    xy: np.ndarray
    angle_rad: float
    clear: bool  # the fingers and the hand reach the grasp height without landing on anything


def _grasp_points(env: SimEnv, body: int) -> list[np.ndarray]:
    """Where to centre a grasp of body (x, y), in order: the middle of its bounding box, its origin, the
    middle of its top as seen from above (a ring's or an L's box middle is a hole, a URDF's origin may lie
    off the object). Points closer than POINT_MIN_DISTANCE_M to an earlier one are dropped."""
    client = env.scene.client
    lo, hi = (np.array(v) for v in p.getAABB(body, physicsClientId=client))
    points = [(lo[:2] + hi[:2]) / 2, env.scene.pose(body)[0][:2]]
    xs = np.arange(lo[0], hi[0], TOP_RAY_STEP_M)
    ys = np.arange(lo[1], hi[1], TOP_RAY_STEP_M)
    grid = np.array([(x, y) for x in xs for y in ys])
    if len(grid):
        hits = p.rayTestBatch([(x, y, hi[2] + 0.05) for x, y in grid], [(x, y, lo[2] - 0.01) for x, y in grid],
                              physicsClientId=client)
        on_top = np.array([h[3] for h in hits if h[0] == body]).reshape(-1, 3)
        if len(on_top):
            points.append(on_top[:, :2].mean(axis=0))
    kept: list[np.ndarray] = []
    for pt in points:
        if all(np.linalg.norm(pt - q) >= POINT_MIN_DISTANCE_M for q in kept):
            kept.append(np.asarray(pt, dtype=np.float64))
    return kept


def _grasp_angles(env: SimEnv, body: int) -> list[float]:
    """Closing axes to try: across the narrow side of the footprint, the wide side, then the diagonals."""
    _, narrow_angle, _, wide_angle = _footprint(env, body)
    angles: list[float] = []
    for a in (narrow_angle, wide_angle, *(narrow_angle + e for e in EXTRA_ANGLES_RAD)):
        a = wrap_half_pi(a)
        if all(abs(wrap_half_pi(a - b)) > 0.1 for b in angles):
            angles.append(a)
    return angles


def _grasps(env: SimEnv, body: int) -> list[Grasp]:
    """The body's feasible grasps, clear ones first, each in the order of _grasp_points then _grasp_angles;
    feasible when the object fits the opening and the pads close on its material at the height where the
    fingers stop (their grasp height, or higher where they land on a neighbour)."""
    travel, ws = env.sim.finger_travel_m, env.ws
    grasps = []
    for xy in _grasp_points(env, body):
        px = _pixel(env, xy)
        if px is None:
            continue
        top = float(env.obs.depth_hm[px]) + ws.z_min_m  # the height the env reads at this pixel
        z_grasp = max(top - env.sim.pick_depth_m, env.sim.fingertip_clearance_m + ws.z_min_m)
        for a in _grasp_angles(env, body):
            z_tip = max(z_grasp, _footprint_height(env, xy, a) + ws.z_min_m)
            width = _across_body(env, body, xy, a, z_tip)
            if width is not None and width <= 2 * travel - GRASP_WIDTH_MARGIN_M:
                grasps.append(Grasp(body, xy, a, clear=z_tip <= z_grasp + CLEAR_M))
    return sorted(grasps, key=lambda g: not g.clear)  # a stable sort


def _push_actions(env: SimEnv, body: int, bodies: list[int]) -> list[Action]:
    """Pushes moving body sideways out of its crowd, best first, each from free floor (a push starting over
    a neighbour would slide over its top): across the line to its nearest neighbour, toward the workspace
    centre first, then into that neighbour from the far side."""
    pos = env.scene.pose(body)[0]
    _, neighbour = _nearest_gap(env, body, bodies)
    away = pos[:2] - neighbour[:2]
    away_angle = math.atan2(away[1], away[0]) if np.linalg.norm(away) > 1e-6 else 0.0
    centre = np.array([(env.ws.x_min_m + env.ws.x_max_m) / 2, (env.ws.y_min_m + env.ws.y_max_m) / 2])
    across = [away_angle + math.pi / 2, away_angle - math.pi / 2]
    across.sort(key=lambda a: -np.dot(centre - pos[:2], [math.cos(a), math.sin(a)]))
    pushes = []
    for angle in (*across, away_angle + math.pi):
        d = np.array([math.cos(angle), math.sin(angle)])
        start = pos[:2] - (max(env.scene.local_half_extents_m[body][:2]) + 0.03) * d
        px = _pixel(env, start)
        if px is None or not (env.ws.x_min_m <= start[0] <= env.ws.x_max_m
                              and env.ws.y_min_m <= start[1] <= env.ws.y_max_m):
            continue
        if patch_max(env.obs.depth_hm, px[0], px[1], 0.012, env.ws.resolution_m) < FREE_FLOOR_M:
            pushes.append(Action("push", px[0], px[1], float(angle), 1.0))
    return pushes


def clutter_action(env: SimEnv) -> Action:
    """Pick an object the fingers reach around unhindered, the highest first (nothing lies on it), then the
    most isolated; if there is none, push a crowded one out of its crowd; if no push starts on free floor,
    a grasp whose fingers land on a neighbour; if nothing is feasible, a grasp at the object's middle
    anyway. After failures, the next candidate: the same action would fail again (e.g. a wrist angle the
    arm cannot reach there, a push whose start it cannot reach)."""
    bodies = [b for b in env.scene.objects if env.scene.in_workspace(b)]
    if not bodies:
        return _action(env, "pick", np.array([0.5, 0.0]), 0.0)
    ranked = sorted(bodies, key=lambda b: (-round(env.scene.top_z(b), 2), -_nearest_gap(env, b, bodies)[0]))
    grasps = [g for body in ranked for g in _grasps(env, body)]
    clear = [g for g in grasps if g.clear]
    crowded = [b for b in ranked if _nearest_gap(env, b, bodies)[0] < CROWD_RADIUS_M]
    pushes = [a for body in crowded for a in _push_actions(env, body, bodies)] if "push" in env.primitives else []
    k = env.consecutive_failures
    if clear:  # after the clear grasps failed, the others (near its base the arm reaches some wrist angles only)
        g = (clear + [g for g in grasps if not g.clear])[k % len(grasps)]
    elif pushes:
        return pushes[k % len(pushes)]
    elif grasps:
        g = grasps[k % len(grasps)]
    else:
        blind = [Grasp(b, xy, a, clear=False) for b in ranked for xy in _grasp_points(env, b)
                 for a in _grasp_angles(env, b)]
        g = blind[k % len(blind)]
    return _action(env, "pick", g.xy, g.angle_rad)


def stacking_action(env: SimEnv) -> Action:
    """Holding: place on the top cube of the tallest stack. Otherwise pick the most isolated free cube."""
    scene = env.scene
    cubes = [b for b in scene.objects if b != env.held_body and scene.in_workspace(b)]
    base = max(cubes, key=lambda b: (round(scene.top_z(b), 3), -b))
    if env.holding:
        _, angle, _, _ = _footprint(env, base)
        return _action(env, "place", scene.pose(base)[0][:2], wrap_half_pi(angle))
    base_top = scene.top_z(base)
    free = [b for b in cubes if b != base and scene.top_z(b) < base_top - 0.5 * env.task.cube_size_m]
    free = free or [b for b in cubes if b != base] or cubes
    body = max(free, key=lambda b: _nearest_gap(env, b, cubes)[0])
    _, angle, _, _ = _footprint(env, body)
    # A cube is grasped across either pair of faces. The hand is 21 cm long along the closing axis and its
    # underside 4.6 cm above the fingertips: the closing axis goes across the line to the stack, else the
    # hand lands on the stack. After a failure, the other pair.
    to_base = scene.pose(base)[0][:2] - scene.pose(body)[0][:2]
    angles = sorted((angle, angle + math.pi / 2),
                    key=lambda a: abs(math.cos(a) * to_base[0] + math.sin(a) * to_base[1]))
    angle = angles[env.consecutive_failures % 2]
    return _action(env, "pick", scene.pose(body)[0][:2], wrap_half_pi(angle))


def oracle_action(env: SimEnv) -> Action:
    """The scripted action for env's task in its current state."""
    if env.task_def.progress == "stacking":
        return stacking_action(env)
    return clutter_action(env)
