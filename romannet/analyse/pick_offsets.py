"""Where a run's picks land on the objects: offset from the object's centre along and across the closing axis.

    romannet analyse pick-offsets runs/stack-h4 --split 20 --json

A parallel-jaw pick of a box-like object (the stacking cubes, the toy blocks) succeeds when the fingers
straddle it: the pick pixel must be near the object's centre ALONG the finger-closing axis (a 5 cm cube in
the 8 cm hand leaves 1.5 cm on each side), while ACROSS it the finger pads tolerate more. This reads the
recorded episodes (each `/transition`: the action and the depth heightmap it acted on), finds the object under (or within
MAX_GAP_PX of) every pick pixel as the connected blob of heightmap pixels above `--min-height`, fits its
minimum-area rectangle, and reports per training phase and for greedy and explored picks apart: how many
picks hit an object, how many succeeded, and the median |offset| along and across the closing axis and the
median angle between the closing axis and the object's faces (0-45 degrees), for successful and failed
picks, and the mean cos 4(angle to the faces) of all and of the successful picks (1 = square to the faces,
-1 = on the diagonal, 0 = no preference). Blobs larger than `--max-area-cm2` (a stack, touching objects)
are counted but left out of the medians, since their centre is not one object's. Prints one JSON object
(or a line per phase).
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Iterable, Sequence
from pathlib import Path

import cv2
import numpy as np

from .phases import recorded_number, recorded_transitions

MAX_GAP_PX = 8  # a pick pixel this close to an object (but off it) is still measured against that object
ANGLE_BINS_DEG = ((0, 10), (10, 20), (20, 30), (30, 45.01))


def pick_offset(depth_hm: np.ndarray, row: int, col: int, angle_rad: float, resolution_m: float,
                min_height_m: float = 0.02) -> dict | None:
    """The pick at (row, col, angle) measured against the object under it; None if no object is near.

    Returns {"on_object": the pixel itself is on it, "along_m"/"across_m": signed offset of the pixel from
    the object's centre along / across the closing axis (cos, sin) = (d_col, d_row), "face_angle_deg": angle
    between the closing axis and the nearest face normal of its minimum-area rectangle (0-45),
    "area_cm2": the blob's footprint}.
    """
    depth = np.nan_to_num(np.asarray(depth_hm, dtype=np.float32), nan=0.0)
    if depth.ndim != 2 or not (0 <= row < depth.shape[0] and 0 <= col < depth.shape[1]):
        raise ValueError(f"pixel ({row}, {col}) is outside the heightmap of shape {depth.shape}")
    _, labels = cv2.connectedComponents((depth > min_height_m).astype(np.uint8), connectivity=8)
    label = int(labels[row, col])
    on_object = label != 0
    if not on_object:
        rows, cols = np.nonzero(labels)
        if rows.size == 0:
            return None
        nearest = int(np.argmin((rows - row) ** 2 + (cols - col) ** 2))
        if math.hypot(rows[nearest] - row, cols[nearest] - col) > MAX_GAP_PX:
            return None
        label = int(labels[rows[nearest], cols[nearest]])
    rows, cols = np.nonzero(labels == label)
    (cx, cy), _, rect_deg = cv2.minAreaRect(np.stack([cols, rows], axis=1).astype(np.float32))
    # minAreaRect works on pixel corners' centres; pixel (row, col) is the point (col, row) here as well.
    closing = np.array([math.cos(angle_rad), math.sin(angle_rad)])
    offset = np.array([col - cx, row - cy]) * resolution_m
    face = (math.degrees(angle_rad) - rect_deg) % 90.0
    return {"on_object": on_object, "along_m": float(offset @ closing),
            "across_m": float(offset @ np.array([-closing[1], closing[0]])),
            "face_angle_deg": float(min(face, 90.0 - face)), "area_cm2": float(rows.size * resolution_m ** 2 * 1e4)}


def _median(values: Sequence[float], digits: int) -> float | None:
    return round(statistics.median(values), digits) if values else None


def mean_cos4(face_angles_deg: Sequence[float]) -> float | None:
    """Mean cos 4a of the angles a to the faces: 1 = every closing axis square to the faces, -1 = all on the
    diagonal (45 deg), 0 = no preference (uniform angles)."""
    if not face_angles_deg:
        return None
    return round(float(np.mean(np.cos(np.radians(4 * np.asarray(face_angles_deg, dtype=float))))), 3)


def summarize(picks: Iterable[dict], max_area_cm2: float) -> dict:
    """Counts and medians over pick records ({explored, success} + pick_offset's fields, or no object)."""
    picks = list(picks)
    near = [p for p in picks if p.get("along_m") is not None]
    single = [p for p in near if p["area_cm2"] <= max_area_cm2]
    out: dict = {"picks": len(picks), "succeeded": sum(bool(p["success"]) for p in picks),
                 "near_an_object": len(near), "on_an_object": sum(bool(p["on_object"]) for p in near),
                 "single_object": len(single)}
    for kind, explored in (("greedy", False), ("explored", True)):
        group = [p for p in single if bool(p["explored"]) == explored]
        row: dict = {"picks": len(group), "succeeded": sum(bool(p["success"]) for p in group)}
        for outcome, ok in (("succeeded", True), ("failed", False)):
            sel = [p for p in group if bool(p["success"]) == ok]
            row[f"median_abs_along_cm_{outcome}"] = _median([abs(p["along_m"]) * 100 for p in sel], 2)
            row[f"median_abs_across_cm_{outcome}"] = _median([abs(p["across_m"]) * 100 for p in sel], 2)
            row[f"median_face_angle_deg_{outcome}"] = _median([p["face_angle_deg"] for p in sel], 1)
        row["within_1cm_along"] = sum(abs(p["along_m"]) < 0.01 for p in group)
        for outcome, sel in (("picks", group), ("succeeded", [p for p in group if p["success"]])):
            row[f"mean_cos4_face_angle_{outcome}"] = mean_cos4([p["face_angle_deg"] for p in sel])
        row["by_face_angle"] = {f"{lo}-{min(hi, 45):g}": {
            "picks": sum(lo <= p["face_angle_deg"] < hi for p in group),
            "succeeded": sum(lo <= p["face_angle_deg"] < hi and bool(p["success"]) for p in group)}
            for lo, hi in ANGLE_BINS_DEG}
        out[kind] = row
    return out


def episode_picks(path: Path, min_height_m: float) -> list[dict]:
    """pick_offset of every recorded pick of one episode file, against the heightmap it acted on."""
    config_toml, transitions = recorded_transitions(path)
    resolution_m = recorded_number(path, config_toml, "workspace", "resolution_m")
    out = []
    for t in transitions:
        if t.action.primitive != "pick":
            continue
        where = pick_offset(t.depth_before, t.action.row, t.action.col, t.action.angle_rad, resolution_m,
                            min_height_m)
        out.append({"explored": t.action.explored, "success": t.success, **(where or {"along_m": None})})
    return out


def phase_summary(files: list[Path], min_height_m: float, max_area_cm2: float) -> dict:
    """summarize() over every recorded pick of the given episode files."""
    return summarize((pick for f in files for pick in episode_picks(f, min_height_m)), max_area_cm2)
