"""Why a simulated run's picks failed, per training phase, from the simulator's ground truth.

    romannet analyse grasp-failures runs/clutter --split 100 --json

Each simulated pick's `/step` record carries the grasp as the fingers closed (actor/sim/grasp_check.py, in its
info): held or the failure's cause, and for an object both fingers touched its tilt and its centre of mass's
offset from the pick's point across the closing axis (the lever it turns about the fingers with). Per phase:
picks and failures by cause, greedy and explored together, and the share failed by tilt and by that offset.
Picks recorded without a grasp (refused, unreachable, or recorded before the field existed) are counted apart.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path

from .repeated_failures import episode_steps

TILT_EDGES_DEG = (0.0, 5.0, 15.0, 90.0)
ACROSS_EDGES_CM = (0.0, 0.5, 1.5, 3.0, 100.0)


def _bins(values: list[tuple[float, bool]], edges: tuple[float, ...], unit: str) -> dict[str, dict]:
    """{"[lo, hi) unit": {"picks", "failed", "failed_share"}} of (value, failed) pairs; empty bins left out."""
    out = {}
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        group = [failed for v, failed in values if lo <= v < hi]
        if group:
            label = f"[{lo:g}, {hi:g}) {unit}" if hi < edges[-1] else f">= {lo:g} {unit}"
            out[label] = {"picks": len(group), "failed": sum(group), "failed_share": sum(group) / len(group)}
    return out


def summarize_picks(records: list[dict]) -> dict:
    """The counts over `/step` records (see the module docstring)."""
    picks = [r for r in records if r["primitive"] == "pick"]
    graded = [r for r in picks if isinstance(r.get("info"), dict) and "grasp" in r["info"]]
    causes = Counter(r["info"]["grasp"] for r in graded if r["info"]["grasp"] != "held")
    on_body = [r for r in graded if "grasp_tilt_deg" in r["info"]]
    tilt = [(float(r["info"]["grasp_tilt_deg"]), r["info"]["grasp"] != "held") for r in on_body]
    across = [(100 * abs(float(r["info"]["grasp_offset_across_m"])), r["info"]["grasp"] != "held") for r in on_body]
    return {"picks": len(picks), "picks_without_grasp": len(picks) - len(graded),
            "failed": sum(not r["success"] for r in picks), "failed_by_cause": dict(causes.most_common()),
            "by_tilt": _bins(tilt, TILT_EDGES_DEG, "deg"), "by_offset_across": _bins(across, ACROSS_EDGES_CM, "cm")}


def phase_summary(files: list[Path]) -> dict:
    """summarize_picks over every `/step` record of the episodes in `files`."""
    return summarize_picks([r for path in files for r in episode_steps(path)])
