"""Scripted oracle policies that read the simulator state (object poses), one per task.

Used by tests and as a sanity baseline; they return the same `Action` a learned policy would (a heightmap
pixel and an angle), so everything downstream is exercised. Frames as in common.action: angle from the
x (column) axis toward the y (row) axis; for pick/place the finger-closing axis.
"""

from __future__ import annotations

import math

import numpy as np
import pybullet as p

from romannet.common.action import Action, patch_max, position_to_pixel

from .env import SimEnv
from .scene import wrap_half_pi

GRASP_WIDTH_MARGIN_M = 0.01  # an object this much narrower than the full opening still fits between the fingers
CROWDED_GAP_M = 0.025  # a neighbour closer than this (surface to surface, roughly) blocks the fingers
# The Panda's fingers squeeze with their lowest centimetre: there must be material at these heights above
# the fingertips (an arch grasped over its hole has material only higher up, and slips: measured).
PAD_HEIGHTS_M = (0.003, 0.008)
FREE_FLOOR_M = 0.01  # a push starts where the heightmap is below this (else it rides over an object)


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


def _solid_between_fingers(env: SimEnv, body: int, angle_rad: float) -> bool:
    """Would fingers closing along angle_rad over the body's centre squeeze material of the body?

    Rays along the closing axis, from just outside the body toward its centre, at the pads' height when the
    fingertips are pick_depth_m below the top: an arch grasped across its thickness over the middle closes
    on its hole (both rays miss), across its span on its legs (both hit).
    """
    pos = env.scene.pose(body)[0]
    z_tip = max(env.scene.top_z(body) - env.sim.pick_depth_m, env.sim.fingertip_clearance_m)
    reach = float(np.linalg.norm(env.scene.local_half_extents_m[body])) + 0.01
    d = np.array([math.cos(angle_rad), math.sin(angle_rad), 0.0])
    starts, ends = [], []
    for dz in PAD_HEIGHTS_M:
        centre = np.array([pos[0], pos[1], z_tip + dz])
        starts += [(centre - reach * d).tolist(), (centre + reach * d).tolist()]
        ends += [centre.tolist(), centre.tolist()]
    hits = p.rayTestBatch(starts, ends, physicsClientId=env.scene.client)
    return all(h[0] == body for h in hits)


def _grasp_angle(env: SimEnv, body: int) -> float | None:
    """Closing angle for a top-down grasp of body: across its narrow side, else across its wide side when
    that fits the gripper and the narrow one would close on nothing; None if neither does."""
    narrow, angle, wide, wide_angle = _footprint(env, body)
    max_width = 2 * env.sim.finger_travel_m - GRASP_WIDTH_MARGIN_M
    for width, a in ((narrow, angle), (wide, wide_angle)):
        if width <= max_width and _solid_between_fingers(env, body, a):
            return wrap_half_pi(a)
    return wrap_half_pi(angle) if narrow <= max_width else None


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
    """Pick the most isolated graspable object; if every object is crowded, push one out of the crowd."""
    bodies = [b for b in env.scene.objects if env.scene.in_workspace(b)]
    if not bodies:
        return _action(env, "pick", np.array([0.5, 0.0]), 0.0)
    # Highest first (it cannot be buried), then the most isolated.
    ranked = sorted(bodies, key=lambda b: (-round(env.scene.top_z(b), 2), -_nearest_gap(env, b, bodies)[0]))
    for body in ranked:
        angle = _grasp_angle(env, body)
        gap, _ = _nearest_gap(env, body, bodies)
        clear = gap - max(env.scene.local_half_extents_m[body]) > CROWDED_GAP_M + 0.03
        if angle is not None and (clear or "push" not in env.primitives):
            return _action(env, "pick", env.scene.pose(body)[0][:2], angle)
    # Every object is crowded: push one out of its crowd. After failures, the next candidate: the same push
    # would fail again (e.g. a start the arm cannot reach).
    pushes = [a for body in ranked for a in _push_actions(env, body, bodies)]
    if pushes:
        return pushes[env.consecutive_failures % len(pushes)]
    body = ranked[0]
    return _action(env, "pick", env.scene.pose(body)[0][:2], _grasp_angle(env, body) or 0.0)


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
