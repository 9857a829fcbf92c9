"""A training run's counts, as docs/journal.md tabulates them: actions, pick and place success, explored
actions, successful actions per block of 50 in order, action success over the last 500, episodes (completed)
and, for stacking, the highest stack each episode reached.

    romannet analyse training-counts runs/stack-h4 --json

Reads every recorded `/transition` of the run's episodes (what each actor sent: action, success, heightmaps,
how the episode ended), all actors together in order of their end time. The highest stack of an episode is
the tallest common.stack.stack_height (as the simulator's reward measures it) of the heightmaps after its
actions, counted for every episode, with the one the budget cut short.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

from romannet.common.stack import stack_height

from .phases import recorded_number, recorded_transitions


@dataclass(frozen=True)
class Recorded:
    """One recorded action: when it ended, what it was, and how its episode stood after it."""

    end_ns: int
    episode: str
    primitive: str
    explored: bool
    success: bool
    done_reason: str  # set on the action that ended its episode, else ""
    stack: int  # stack height after the action, in cubes (0 for tasks without cubes)


def episode_records(path: Path) -> list[Recorded]:
    """Every action of one episode file; stacks measured for stacking episodes only."""
    config_toml, transitions = recorded_transitions(path)
    cube_m = None
    if any(t.task == "stacking" for t in transitions):
        cube_m = recorded_number(path, config_toml, "task", "cube_size_m")
    out = []
    for t in transitions:
        stack = 0 if cube_m is None else stack_height(t.depth_after, cube_m)
        out.append(Recorded(int(t.end_ns), f"{path.parent.name}/{t.episode_id}", t.action.primitive,
                            bool(t.action.explored), bool(t.success), t.done_reason if t.done else "", stack))
    return out


def per_block(successes: Sequence[bool], block: int) -> list[int]:
    """Successful actions in each block of `block` consecutive actions; a last partial block counts too."""
    if block < 1:
        raise ValueError(f"block {block}: must be at least 1")
    return [sum(successes[i:i + block]) for i in range(0, len(successes), block)]


def last_rate(successes: Sequence[bool], last: int) -> float | None:
    """Share of successful actions among the last `last` (all of them if fewer); None without actions."""
    if last < 1:
        raise ValueError(f"last {last}: must be at least 1")
    tail = successes[-last:]
    return sum(tail) / len(tail) if tail else None


def _rate(group: list[Recorded]) -> dict:
    ok = sum(r.success for r in group)
    return {"attempts": len(group), "succeeded": ok, "rate": ok / len(group) if group else None}


def summarize(records: Iterable[Recorded], block: int = 50, last: int = 500) -> dict:
    """The run's counts (see the module docstring) from its recorded actions, in any order."""
    records = sorted(records, key=lambda r: r.end_ns)
    successes = [r.success for r in records]
    episodes: dict[str, list[Recorded]] = {}
    for r in records:
        episodes.setdefault(r.episode, []).append(r)
    ends = Counter(next((r.done_reason for r in rs if r.done_reason), "not ended") for rs in episodes.values())
    out = {"actions": len(records),
           **{primitive: _rate([r for r in records if r.primitive == primitive])
              for primitive in sorted({r.primitive for r in records})},
           "explored actions": sum(r.explored for r in records),
           f"successful actions per {block}": per_block(successes, block),
           f"action success, last {last}": last_rate(successes, last),
           "episodes": len(episodes), "completed": ends.get("done", 0), "episode ends": dict(sorted(ends.items()))}
    if any(r.stack for r in records):
        highest = Counter(max(r.stack for r in rs) for rs in episodes.values())
        out["episodes by highest stack"] = {str(h): highest[h] for h in sorted(highest)}
    return out


def phase_summary(files: list[Path], block: int, last: int) -> dict:
    """summarize() over every recorded action of the given episode files."""
    return summarize((r for f in files for r in episode_records(f)), block, last)
