"""What `romannet bench fleet` makes of its processes' files: pure functions, no processes.

Times are CLOCK_MONOTONIC ns (bench/fleet_actor.py, bench/fleet_learner.py); a window is (start_ns, end_ns).
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np


@dataclass
class ActorReport:
    """One light actor's report file: versions taken (version, t_ns) and acks (episode, step, t_ns, insert_us)."""

    weights: list[tuple[int, int]] = field(default_factory=list)
    acks: list[tuple[str, int, int, int]] = field(default_factory=list)


def read_actor_report(path: Path) -> ActorReport:
    """Parse a report file; a line not yet complete (the writer is mid-line) is skipped."""
    out = ActorReport()
    try:
        lines = path.read_text().splitlines()
    except OSError:
        return out
    for line in lines:
        parts = line.split()
        try:
            if parts[:1] == ["w"] and len(parts) == 3:
                out.weights.append((int(parts[1]), int(parts[2])))
            elif parts[:1] == ["a"] and len(parts) == 5:
                out.acks.append((parts[1], int(parts[2]), int(parts[3]), int(parts[4])))
        except ValueError:
            continue
    return out


def read_probe(path: Path) -> list[tuple[int, int, int, int]]:
    """The learner's publishes: (version, call_ns, return_ns, size_bytes)."""
    out = []
    try:
        lines = path.read_text().splitlines()
    except OSError:
        return out
    for line in lines:
        parts = line.split()
        if len(parts) == 4 and all(p.isdigit() for p in parts):
            out.append((int(parts[0]), int(parts[1]), int(parts[2]), int(parts[3])))
    return out


def _ms(values_ns: list[float], q: float) -> float | None:
    return round(float(np.percentile(np.asarray(values_ns) / 1e6, q)), 1) if values_ns else None


def _held_at(weights: list[tuple[int, int]], version: int) -> int | None:
    """When the actor first held `version` or a newer one (a newer one that came first replaces it)."""
    times = [t for v, t in weights if v >= version]
    return min(times) if times else None


def weights_latency(probe: list[tuple[int, int, int, int]], actors: list[ActorReport],
                    window: tuple[int, int]) -> dict[str, Any]:
    """Per version published in the window: from the publish call to the last actor holding it (or newer)."""
    published = [p for p in probe if window[0] <= p[1] < window[1]]
    every, each, missed = [], [], 0
    for version, t0, _, _ in published:
        held = [_held_at(a.weights, version) for a in actors]
        if any(t is None for t in held):
            missed += 1
            continue
        lat = [t - t0 for t in held if t is not None]
        every.append(max(lat))
        each.extend(lat)
    skipped = sum(len({v for v, _, _, _ in published} - {v for v, _ in a.weights}) for a in actors)
    return {"versions": len(published), "versions_not_at_every_actor": missed,
            "all_actors_ms_median": _ms(every, 50), "all_actors_ms_p99": _ms(every, 99),
            "per_actor_ms_median": _ms(each, 50), "per_actor_ms_p99": _ms(each, 99),
            "skipped_by_a_newer_version": skipped,
            "weights_bytes": int(np.median([p[3] for p in published])) if published else None,
            "publish_call_ms_median": _ms([p[2] - p[1] for p in published], 50)}


def inserts(actors: list[ActorReport], window: tuple[int, int]) -> dict[str, Any]:
    """Acknowledged inserts in the window: per second, and their latency (request to ack)."""
    lat_us = [us for a in actors for _, _, t, us in a.acks if window[0] <= t < window[1]]
    span_s = (window[1] - window[0]) / 1e9
    return {"acked_in_window": len(lat_us), "inserts_per_s": round(len(lat_us) / span_s, 2) if span_s > 0 else None,
            "insert_ms_p50": _ms([u * 1000 for u in lat_us], 50), "insert_ms_p99": _ms([u * 1000 for u in lat_us], 99)}


def learner_rows(metrics_csv: Path) -> list[dict[str, str]]:
    """The learner's metrics.csv rows, one per update (none before the first update)."""
    try:
        with metrics_csv.open(newline="") as fh:
            return list(csv.DictReader(fh))
    except OSError:
        return []


def learner_window(rows: list[dict[str, str]], window_s: float) -> dict[str, Any]:
    """Updates/s and the learner's sample round trips (request, the server's work, reply, decoding) over
    the rows of the updates made in the window."""
    sample_ns = [float(r["sample_latency_s"]) * 1e9 for r in rows if r.get("sample_latency_s")]
    return {"updates": len(rows), "updates_per_s": round(len(rows) / window_s, 3) if window_s > 0 else None,
            "sample_ms_p50": _ms(sample_ns, 50), "sample_ms_p99": _ms(sample_ns, 99)}


def acked_not_stored(actor_ids: list[str], actors: list[ActorReport], stored: set[tuple[str, str, int]]) -> int:
    """Acknowledged transitions (by actor, episode, step) that the replay's durable log does not hold."""
    return sum((actor_id, episode, step) not in stored
               for actor_id, a in zip(actor_ids, actors, strict=True) for episode, step, _, _ in a.acks)
