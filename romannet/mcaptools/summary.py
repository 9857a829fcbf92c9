"""`romannet mcap inspect`: what an episode file holds, as a dict (for --json) and as text for people.

Per episode: run, actor, episode id, task, seed, steps, actions and successes by primitive, explored
actions, rewards, progress at the end, end reason, weights versions and exploration rates, duration,
heightmap size, messages per topic, and the file's health: complete, truncated (it ends early: read up to
its last whole chunk) or damaged (each damaged part named and skipped, the rest read), with the steps read
of those the file's summary counts.
Transitions are parsed as protobuf without decoding their pixels; --verify decodes and validates each one
with the same decoder the replay server and the learner use.
"""

from __future__ import annotations

import datetime as dt
import json
from collections import Counter
from pathlib import Path
from typing import Any

from romannet.common.episode_file import END_METADATA, STEP_TOPIC, TRANSITION_TOPIC, EpisodeReader
from romannet.common.errors import DecodeError
from romannet.common.imagecodec import read_png_header
from romannet.common.wire import decode_transition

from .steps import parse_transition, primitive_of

PRIMITIVES = ("push", "pick", "place")


def _number(text: str | None) -> float | int | None:
    """A metadata value (metadata values are strings) as a number, if it is one."""
    if text is None or text in ("", "None"):
        return None
    try:
        value = float(text)
    except ValueError:
        return None
    return int(value) if value.is_integer() and "." not in text else value


class _Tally:
    """Running totals over an episode's transitions."""

    def __init__(self, verify: bool):
        self.verify = verify
        self.actions: Counter[str] = Counter()
        self.successes: Counter[str] = Counter()
        self.rewards: list[float] = []
        self.versions: list[int] = []
        self.explored = self.invalid = 0
        self.first_error = ""
        self.first_start_ns: int | None = None
        self.last: Any = None  # the last parsed transition
        self.shape: tuple[int, int] | None = None

    def add(self, data: bytes) -> None:
        try:
            t = parse_transition(data)
            if self.verify:
                decode_transition(data, self.shape)
            if self.shape is None:
                self.shape = read_png_header(t.color_before_png)[:2]
        except DecodeError as err:
            self.invalid += 1
            self.first_error = self.first_error or str(err)
            return
        primitive = primitive_of(t)
        self.actions[primitive] += 1
        self.successes[primitive] += int(t.success)
        self.explored += int(t.action.explored)
        self.rewards.append(float(t.reward))
        self.versions.append(int(t.policy_version))
        if self.first_start_ns is None:
            self.first_start_ns = int(t.start_ns)
        self.last = t


def summarize(path: str | Path, verify: bool = False) -> dict[str, Any]:
    """The summary dict of one episode file; raises EpisodeFileError for a file that is not one."""
    reader = EpisodeReader(path)
    tally = _Tally(verify)
    topics: Counter[str] = Counter()
    for msg in reader.messages():
        topics[msg.topic] += 1
        if msg.topic == TRANSITION_TOPIC:
            tally.add(msg.data)
    health = reader.health
    assert health is not None
    meta, end = reader.episode, reader.metadata.get(END_METADATA, {})
    last = tally.last
    steps = sum(tally.actions.values())
    if end.get("done_reason"):
        end_reason = end["done_reason"]
    elif last is not None and last.done:
        end_reason = last.done_reason or "done"
    else:
        end_reason = "unfinished" if not health.complete else "unknown"
    duration_s = None
    if last is not None and tally.first_start_ns is not None:
        duration_s = round((int(last.end_ns) - tally.first_start_ns) / 1e9, 3)
    return {
        "path": str(path), "health": health.state, "health_detail": health.describe(),
        "damage": list(health.damage), "file_bytes": health.file_bytes, "read_bytes": health.read_bytes,
        "skipped_bytes": health.skipped_bytes, "steps_recorded": health.expected.get(TRANSITION_TOPIC),
        "run_id": meta.get("run_id"), "actor_id": meta.get("actor_id"), "episode_id": meta.get("episode_id"),
        "task": meta.get("task"), "seed": _number(meta.get("seed")),
        "demonstration": meta.get("demonstration") == "True",  # the scripted oracle acted it (actor.demo_episodes)
        "steps": steps, "step_records": topics[STEP_TOPIC], "invalid_transitions": tally.invalid,
        "first_invalid": tally.first_error or None,
        "actions": {p: tally.actions[p] for p in PRIMITIVES if tally.actions[p]},
        "successes": {p: tally.successes[p] for p in PRIMITIVES if tally.actions[p]},
        "explored": tally.explored,
        "reward_sum": round(sum(tally.rewards), 6), "reward_mean": round(sum(tally.rewards) / steps, 6) if steps else None,
        "reward_max": max(tally.rewards) if tally.rewards else None,
        "progress_end": float(last.progress_after) if last is not None else None,
        "end_reason": end_reason, "efficiency": _number(end.get("efficiency")),
        "weights_versions": {"start": _number(meta.get("weights_version_start")),
                             "end": _number(end.get("weights_version_end")),
                             "min": min(tally.versions) if tally.versions else None,
                             "max": max(tally.versions) if tally.versions else None,
                             "distinct": len(set(tally.versions))},
        "explore_rate_start": _number(meta.get("explore_rate_start")),
        "explore_rate_end": float(last.explore_rate) if last is not None else None,
        "started_utc": (dt.datetime.fromtimestamp(tally.first_start_ns / 1e9, dt.timezone.utc).isoformat(
            timespec="seconds") if tally.first_start_ns else None),
        "duration_s": duration_s, "heightmap_px": list(tally.shape) if tally.shape else None,
        "camera": topics["/camera/color"] > 0, "messages": dict(sorted(topics.items())),
        "rescored": "rescore" in reader.metadata,
    }


def totals(episodes: list[dict[str, Any]]) -> dict[str, Any]:
    """Fleet-level totals over episode summaries."""
    actions: Counter[str] = Counter()
    successes: Counter[str] = Counter()
    for e in episodes:
        actions.update(e["actions"])
        successes.update(e["successes"])
    steps = sum(e["steps"] for e in episodes)
    return {"episodes": len(episodes), "steps": steps, "truncated": sum(e["health"] == "truncated" for e in episodes),
            "damaged": sum(e["health"] == "damaged" for e in episodes),
            "completed": sum(e["end_reason"] == "done" for e in episodes),
            "demonstrations": sum(e["demonstration"] for e in episodes),
            "actions": dict(actions), "successes": dict(successes),
            "pick_success": successes["pick"] / actions["pick"] if actions["pick"] else None,
            "reward_sum": round(sum(e["reward_sum"] for e in episodes), 6)}


def _kb(n: int) -> str:
    return f"{n / 1e6:.2f} MB" if n >= 1e6 else f"{n / 1e3:.1f} kB"


def format_episode(e: dict[str, Any]) -> str:
    """A few lines for people."""
    acts = ", ".join(f"{p} {e['successes'][p]}/{n}" for p, n in e["actions"].items()) or "none"
    wv = e["weights_versions"]
    versions = "-" if wv["min"] is None else (f"v{wv['min']}" if wv["min"] == wv["max"] else f"v{wv['min']}..v{wv['max']}")
    health = e["health_detail"].replace("truncated", "TRUNCATED", 1).replace("damaged", "DAMAGED", 1)
    if e["steps_recorded"] is not None and e["steps_recorded"] != e["steps"]:
        health += f"; {e['steps']} of {e['steps_recorded']} steps read"
    lines = [f"{e['path']}  [{health}, {_kb(e['file_bytes'])}]",
             f"  run {e['run_id']} | actor {e['actor_id']} | episode {e['episode_id']} | task {e['task']} | "
             f"seed {e['seed']}" + (" | rescored" if e["rescored"] else "")
             + (" | demonstration (the oracle's actions)" if e["demonstration"] else ""),
             f"  {e['steps']} steps, successes {acts}; explored {e['explored']}; reward sum {e['reward_sum']:.3f}"
             + (f", mean {e['reward_mean']:.3f}" if e["reward_mean"] is not None else ""),
             f"  end: {e['end_reason']}" + (f" (efficiency {e['efficiency']:.2f})" if e["efficiency"] is not None else "")
             + f" | weights {versions} | duration {e['duration_s'] if e['duration_s'] is not None else '-'} s"
             + (f" | heightmaps {e['heightmap_px'][0]}x{e['heightmap_px'][1]}" if e["heightmap_px"] else "")
             + (" | camera" if e["camera"] else " | no camera")]
    if e["invalid_transitions"]:
        lines.append(f"  {e['invalid_transitions']} invalid transition(s), e.g. {e['first_invalid']}")
    return "\n".join(lines)


def format_totals(t: dict[str, Any]) -> str:
    pick = "-" if t["pick_success"] is None else f"{100 * t['pick_success']:.1f} %"
    return (f"{t['episodes']} episode(s), {t['steps']} steps, {t['completed']} completed, {t['truncated']} "
            f"truncated, {t['damaged']} damaged"
            + (f", {t['demonstrations']} demonstration(s)" if t["demonstrations"] else "")
            + f"; pick success {pick}; reward sum {t['reward_sum']:.3f}")


def to_json(episodes: list[dict[str, Any]], errors: list[str]) -> str:
    return json.dumps({"episodes": episodes, "totals": totals(episodes), "errors": errors}, indent=2)
