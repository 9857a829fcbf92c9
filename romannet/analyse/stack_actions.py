"""Where a stacking run's picks and places land: on the table, on a lone cube or on top of the stack.

    romannet analyse stack-actions runs/stack-h4 --split 5 --json

The paper's TPG reward gives 0 to an action that reverses progress, so a policy should learn not to pick
cubes off the stack it is building, and to place on the stack's top. This reads a run's recorded episodes
(each `/transition`: the action and the depth heightmap it acted on) and, for every pick and place, measures
the stack height before it (common.stack.stack_height, as the simulator's reward does) and the number of
cubes under the action pixel (the tallest point within `--radius-m` of it, in cube heights of the recorded
task.cube_size_m). It reports per training phase, for greedy and explored actions apart, attempts and
successes by (stack height, cubes under the pixel), and the headline counts: while a stack of 2 or more
stood, how many greedy picks went to a stack top (and how many of them took a cube off it) and how many
greedy places went to a stack top (and raised it), how far greedy places land from the centre of the top
under them, and how far the taller stack stood from those that went onto a lower cube. Prints one JSON
object (or a line per phase).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np

from romannet.common.stack import filtered_heightmap, stack_height

from .phases import recorded_number, recorded_transitions


def cubes_under(depth_hm: np.ndarray, row: int, col: int, cube_size_m: float, radius_px: int) -> int:
    """Cubes under an action pixel: the tallest height within radius_px of it, in whole cube heights."""
    if not cube_size_m > 0 or radius_px < 0:
        raise ValueError(f"cube_size_m must be > 0 and radius_px >= 0; got {cube_size_m}, {radius_px}")
    h, w = depth_hm.shape
    if not (0 <= row < h and 0 <= col < w):
        raise ValueError(f"pixel ({row}, {col}) is outside the {h}x{w} heightmap")
    patch = depth_hm[max(row - radius_px, 0):row + radius_px + 1, max(col - radius_px, 0):col + radius_px + 1]
    tallest = float(np.nan_to_num(patch, nan=0.0, posinf=0.0, neginf=0.0).max())
    return max(0, int(np.rint(tallest / cube_size_m)))


def top_offset_px(depth_hm: np.ndarray, row: int, col: int, level: int, cube_size_m: float) -> float | None:
    """Distance (px) from a pixel to the centre of the cube top at `level` cubes nearest it: the connected
    pixels of the stack-height reading (common.stack.filtered_heightmap) within a quarter cube of that height;
    None when no top stands at that level."""
    if level < 1:
        return None
    depth = filtered_heightmap(depth_hm)
    count, labels = cv2.connectedComponents((np.abs(depth - level * cube_size_m) < cube_size_m / 4).astype(np.uint8))
    if count < 2:
        return None
    pixels = np.argwhere(labels > 0)
    nearest = pixels[np.hypot(pixels[:, 0] - row, pixels[:, 1] - col).argmin()]
    top = np.argwhere(labels == labels[tuple(nearest)])
    return float(np.hypot(*(top.mean(0) - (row, col))))


def distance_to_height_px(depth_hm: np.ndarray, row: int, col: int, cubes: int, cube_size_m: float) -> float | None:
    """Distance (px) from a pixel to the nearest pixel that stack_height reads as at least `cubes` cubes high;
    None when there is none."""
    tall = np.argwhere(filtered_heightmap(depth_hm) >= (cubes - 0.5) * cube_size_m)
    return float(np.hypot(tall[:, 0] - row, tall[:, 1] - col).min()) if len(tall) else None


def episode_actions(path: Path, radius_m: float) -> list[dict]:
    """{primitive, explored, success, stack, under} of every recorded pick and place of one episode file; a
    place also has top_offset_cm (from the centre of the top under it) and to_stack_cm (to the tallest stack,
    when it went onto a lower cube), None where not measured."""
    config_toml, transitions = recorded_transitions(path)
    cube_m = recorded_number(path, config_toml, "task", "cube_size_m")
    radius_px = int(round(radius_m / recorded_number(path, config_toml, "workspace", "resolution_m")))
    cm_per_px = 100 * recorded_number(path, config_toml, "workspace", "resolution_m")
    out = []
    for t in transitions:
        a = t.action
        if a.primitive not in ("pick", "place"):
            continue
        stack, under = stack_height(t.depth_before, cube_m), cubes_under(t.depth_before, a.row, a.col, cube_m, radius_px)
        item = {"primitive": a.primitive, "explored": bool(a.explored), "success": bool(t.success),
                "stack": stack, "under": under}
        if a.primitive == "place":
            off = top_offset_px(t.depth_before, a.row, a.col, under, cube_m)
            far = distance_to_height_px(t.depth_before, a.row, a.col, stack, cube_m) if 0 < under < stack else None
            item["top_offset_cm"] = None if off is None else off * cm_per_px
            item["to_stack_cm"] = None if far is None else far * cm_per_px
        out.append(item)
    return out


def _count(actions: list[dict]) -> dict:
    return {"attempts": len(actions), "succeeded": sum(a["success"] for a in actions)}


def summarize(actions: Iterable[dict]) -> dict:
    """Attempts / successes by primitive, greedy vs explored and (stack, cubes under the pixel); headlines."""
    actions = list(actions)
    out: dict = {}
    for primitive in ("pick", "place"):
        mine = [a for a in actions if a["primitive"] == primitive]
        rows: dict = {}
        for kind, explored in (("greedy", False), ("explored", True)):
            group = [a for a in mine if a["explored"] == explored]
            keys = sorted({(a["stack"], a["under"]) for a in group})
            rows[kind] = {f"stack {s}, on {u}": _count([a for a in group if (a["stack"], a["under"]) == (s, u)])
                          for s, u in keys}
        out[primitive] = rows
    greedy_tall = [a for a in actions if not a["explored"] and a["stack"] >= 2]
    picks = [a for a in greedy_tall if a["primitive"] == "pick"]
    places = [a for a in greedy_tall if a["primitive"] == "place"]
    # At a stack's top: as many cubes under the pixel as the tallest stack has (>=: the unfiltered patch
    # maximum may read a speckle higher than the median-filtered stack height).
    off_top = [a for a in picks if a["under"] >= a["stack"]]
    on_top = [a for a in places if a["under"] >= a["stack"]]
    out["while a stack of 2+ stood (greedy)"] = {
        "picks": len(picks), "picks at a stack top": len(off_top),
        "cubes taken off a stack": sum(a["success"] for a in off_top),
        "picks elsewhere": len(picks) - len(off_top),
        "picks elsewhere succeeded": sum(a["success"] for a in picks if a["under"] < a["stack"]),
        "places": len(places), "places on a stack top": len(on_top),
        "places that raised the stack": sum(a["success"] for a in places)}
    out["greedy places: offset from the centre of the top under them (cm)"] = place_offsets(
        [a for a in actions if a["primitive"] == "place" and not a["explored"]])
    lower = [a["to_stack_cm"] for a in places if a.get("to_stack_cm") is not None]
    out["greedy places onto a lower cube while a stack of 2+ stood"] = {
        "places": len(lower), "median distance to the stack (cm)": _median(lower),
        "share beyond 10 cm": round(float(np.mean(np.array(lower) > 10)), 3) if lower else None}
    return out


def _median(values: list[float]) -> float | None:
    return round(float(np.median(values)), 2) if values else None


def place_offsets(places: list[dict]) -> dict:
    """{'stack S, on U': {succeeded/failed: count and median top_offset_cm}} of places with a measured offset."""
    out: dict = {}
    for s, u in sorted({(a["stack"], a["under"]) for a in places if a.get("top_offset_cm") is not None}):
        group = [a for a in places if (a["stack"], a["under"]) == (s, u) and a.get("top_offset_cm") is not None]
        out[f"stack {s}, on {u}"] = {
            kind: {"places": len(g), "median cm": _median([a["top_offset_cm"] for a in g])}
            for kind, g in (("succeeded", [a for a in group if a["success"]]),
                            ("failed", [a for a in group if not a["success"]]))}
    return out


def phase_summary(files: list[Path], radius_m: float) -> dict:
    """summarize() over every recorded pick and place of the given episode files."""
    return summarize(a for f in files for a in episode_actions(f, radius_m))
