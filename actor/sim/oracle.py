"""Scripted oracle policies that read the simulator state (object poses), one per task.

Used by tests and as a sanity baseline; they return the same `Action` a learned policy would (a heightmap
pixel and an angle), so everything downstream is exercised. Frames as in common.action: angle from the
x (column) axis toward the y (row) axis; for pick/place the finger-closing axis.
"""

from __future__ import annotations

import math

import numpy as np
import pybullet as p

from romannet.common.action import Action, position_to_pixel

from .env import SimEnv
from .scene import wrap_half_pi

MAX_GRASP_WIDTH_M = 0.07  # the Panda opens 8 cm; leave a margin
CROWDED_GAP_M = 0.025  # a neighbour closer than this (surface to surface, roughly) blocks the fingers


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


def clutter_action(env: SimEnv) -> Action:
    """Pick the most isolated graspable object; if every object is crowded, push one out of the crowd."""
    bodies = [b for b in env.scene.objects if env.scene.in_workspace(b)]
    if not bodies:
        return _action(env, "pick", np.array([0.5, 0.0]), 0.0)
    # Highest first (it cannot be buried), then the most isolated.
    ranked = sorted(bodies, key=lambda b: (-round(env.scene.top_z(b), 2), -_nearest_gap(env, b, bodies)[0]))
    for body in ranked:
        narrow, angle, _, _ = _footprint(env, body)
        gap, _ = _nearest_gap(env, body, bodies)
        clear = gap - max(env.scene.local_half_extents_m[body]) > CROWDED_GAP_M + 0.03
        if narrow <= MAX_GRASP_WIDTH_M and (clear or "push" not in env.primitives):
            return _action(env, "pick", env.scene.pose(body)[0][:2], wrap_half_pi(angle))
    # Every object is crowded: push the top-ranked one sideways, across the line to its nearest neighbour,
    # starting from free floor beside it (a push starting over the neighbour would slide over its top).
    body = ranked[0]
    pos = env.scene.pose(body)[0]
    _, neighbour = _nearest_gap(env, body, bodies)
    away = pos[:2] - neighbour[:2]
    across = math.atan2(away[1], away[0]) + math.pi / 2 if np.linalg.norm(away) > 1e-6 else 0.0
    centre = np.array([(env.ws.x_min_m + env.ws.x_max_m) / 2, (env.ws.y_min_m + env.ws.y_max_m) / 2])
    if np.dot(centre - pos[:2], [math.cos(across), math.sin(across)]) < 0:
        across += math.pi  # push toward the middle of the workspace, not out of it
    start = pos[:2] - (max(env.scene.local_half_extents_m[body][:2]) + 0.03) * np.array(
        [math.cos(across), math.sin(across)])
    return _action(env, "push", start, across)


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
    return _action(env, "pick", scene.pose(body)[0][:2], wrap_half_pi(angle))


def oracle_action(env: SimEnv) -> Action:
    """The scripted action for env's task in its current state."""
    if env.task_def.progress == "stacking":
        return stacking_action(env)
    return clutter_action(env)
