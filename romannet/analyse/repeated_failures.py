"""How often the greedy policy repeats the action that just failed, per training phase of a run.

    romannet analyse repeated-failures runs/clutter --split 52 --json

A failed pick or push leaves the scene as it was, so a greedy policy whose weights have not changed since
picks the same pixel again. This reads the recorded episodes (`/step` records: primitive, pixel, explored,
success, weights version) and counts, for the episodes before and from episode index `--split` on, how many
greedy actions repeat the previous action exactly (same primitive and pixel) right after it failed, and how
many of those repeats ran on the same weights version. Prints one JSON object (or a line per phase).
"""

from __future__ import annotations

import json
from pathlib import Path

from romannet.common.episode_file import STEP_TOPIC, EpisodeFileError, read_episode

STEP_FIELDS = ("primitive", "row", "col", "explored", "success", "weights_version")  # what the count reads


def episode_steps(path: Path) -> list[dict]:
    """The `/step` records of one episode file; EpisodeFileError for a record that is not a JSON object or
    lacks a field the count reads, so a foreign or older recording is named instead of failing mid-count."""
    out = []
    for message in read_episode(path, topics=[STEP_TOPIC]).of(STEP_TOPIC):
        try:
            record = json.loads(message.data)
        except ValueError as err:  # not JSON, or not UTF-8
            raise EpisodeFileError(path, f"a /step record is not JSON ({err})") from err
        missing = [k for k in STEP_FIELDS if not isinstance(record, dict) or k not in record]
        if missing:
            raise EpisodeFileError(path, f"a /step record lacks {', '.join(missing)}")
        out.append(record)
    return out


def phase_counts(files: list[Path]) -> dict:
    """Counts over the episodes in `files` (see the module docstring)."""
    return count_repeats([episode_steps(path) for path in files])


def count_repeats(episodes: list[list[dict]]) -> dict:
    """Counts over episodes given as their `/step` records, in order (see the module docstring)."""
    actions = greedy_after_failure = repeats = repeats_same_weights = picks = picked = 0
    for steps in episodes:
        prev = None
        for s in steps:
            actions += 1
            if s["primitive"] == "pick":
                picks += 1
                picked += int(bool(s["success"]))
            if prev is not None and not prev["success"] and not s["explored"]:
                greedy_after_failure += 1
                if (s["primitive"], s["row"], s["col"]) == (prev["primitive"], prev["row"], prev["col"]):
                    repeats += 1
                    repeats_same_weights += int(s["weights_version"] == prev["weights_version"])
            prev = s
    return {"episodes": len(episodes), "actions": actions, "pick_success": picked / picks if picks else None,
            "greedy_after_failure": greedy_after_failure, "repeats": repeats,
            "repeat_rate": repeats / greedy_after_failure if greedy_after_failure else None,
            "repeats_on_same_weights": repeats_same_weights}

