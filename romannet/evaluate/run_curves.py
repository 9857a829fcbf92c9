"""One run's training curves, over training actions (all actors), from its recorded episodes.

The source is the same as `romannet plot`'s: the /step records of every episode file under
RUN_DIR/episodes/ (romannet.evaluate.curves reads them and turns them into TrainingActions). On top of the
action success rate and efficiency (curves.windowed), per finished episode: its return (the sum of its
step rewards), its length (actions), whether it completed the task, and the completion rate of the last
`episode_window` episodes; and the fleet's actions per second over the last `window` actions.

An episode's x is the number of training actions (every actor's) taken by its end. An episode file still
being written counts its actions but is not an episode yet; a cut-short file (a killed actor) never is.
`EpisodeFiles` keeps what it read per file (by size and modification time), so a live run is read
incrementally: a finished episode's file is parsed once.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from romannet.common.episode_file import EpisodeFileError

from .curves import TrainingAction, episode_actions, read_step_records, windowed

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EpisodeEnd:
    """A finished episode: when it ended, its length in actions, its return and how it ended."""

    t_ns: int
    length: int
    episode_return: float
    reason: str

    @property
    def completed(self) -> bool:
        return self.reason == "done"


@dataclass(frozen=True)
class EpisodeFile:
    """What one episode file holds for the curves: its actions, and its end once it has one."""

    actions: tuple[TrainingAction, ...]
    end: EpisodeEnd | None


def episode_file(task: str, goal_stack_height: int, records: Sequence[dict]) -> EpisodeFile:
    """The EpisodeFile of one file's /step records (read_step_records)."""
    actions = tuple(episode_actions(task, goal_stack_height, records))
    if not records or not records[-1].get("done"):
        return EpisodeFile(actions, None)
    ret = float(sum(float(r.get("reward") or 0.0) for r in records))
    reason = str(records[-1].get("done_reason") or "done")
    return EpisodeFile(actions, EpisodeEnd(int(records[-1]["_t_ns"]), len(records), ret, reason))


@dataclass
class EpisodeFiles:
    """The episode files of a run directory, read once each unless they change (size or mtime)."""

    run_dir: Path
    task: str
    goal_stack_height: int
    _seen: dict[Path, tuple[tuple[int, int], EpisodeFile]] = field(default_factory=dict)

    def read(self) -> list[EpisodeFile]:
        """Every readable episode file now under run_dir/episodes/*/ (a broken one: a warning, skipped)."""
        out = []
        for path in sorted((self.run_dir / "episodes").glob("*/*.mcap")):
            try:
                st = path.stat()
            except OSError:  # removed since the glob
                continue
            key = (st.st_size, st.st_mtime_ns)
            seen = self._seen.get(path)
            if seen is None or seen[0] != key:
                try:
                    parsed = episode_file(self.task, self.goal_stack_height, read_step_records(path))
                except (EpisodeFileError, ValueError, KeyError) as err:
                    log.warning("%s skipped: %s", path, err)
                    parsed = EpisodeFile((), None)
                seen = (key, parsed)
                self._seen[path] = seen
            out.append(seen[1])
        return out


@dataclass(frozen=True)
class RunCurves:
    """Curves of one run. Per-action arrays share `action_x`; per-episode arrays share `episode_x`."""

    action_x: np.ndarray  # training actions (1-based), from the window-th action on
    success_rate: np.ndarray  # fraction of the last `window` actions that succeeded
    efficiency: np.ndarray  # ideal / actual actions over the last `window` (curves.windowed)
    actions_per_s: np.ndarray  # the fleet's rate over the last `window` actions (nan where it spans 0 s)
    episode_x: np.ndarray  # training actions taken by each finished episode's end
    episode_return: np.ndarray
    episode_length: np.ndarray
    completion_rate: np.ndarray  # fraction of the last `episode_window` finished episodes that completed
    completed: int  # finished episodes that completed the task
    actions: int
    window: int
    episode_window: int

    @property
    def episodes(self) -> int:
        return len(self.episode_x)


def curve_window(max_actions: int) -> int:
    """The curves' sliding window: romannet plot's 200 actions, narrower for short runs so they draw a curve
    (0: no limit, 200)."""
    return max(1, min(200, max_actions // 5)) if max_actions > 0 else 200


def rolling_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Mean of the last `window` values (fewer at the start) at every index."""
    if len(values) == 0:
        return np.zeros(0)
    csum = np.cumsum(np.asarray(values, dtype=float))
    idx = np.arange(len(values))
    lo = idx - window
    prev = np.where(lo >= 0, csum[np.maximum(lo, 0)], 0.0)
    return (csum - prev) / np.minimum(idx + 1, window)


def actions_rate(t_ns: np.ndarray, window: int) -> np.ndarray:
    """Actions per second at every action: the actions since the one `window` back (or the first) over the
    time between them; nan at the first action or where no time passed."""
    n = len(t_ns)
    j = np.arange(n)
    lo = np.maximum(j - window, 0)
    span_s = (t_ns - t_ns[lo]) / 1e9
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(span_s > 0, (j - lo) / span_s, np.nan)


def compute(files: Sequence[EpisodeFile], window: int = 200, episode_window: int = 20) -> RunCurves:
    """The curves of a run's episode files (pure)."""
    if window < 1 or episode_window < 1:
        raise ValueError(f"window {window}, episode window {episode_window}: both must be at least 1")
    actions = sorted((a for f in files for a in f.actions), key=lambda a: a.t_ns)
    ends = sorted((f.end for f in files if f.end is not None), key=lambda e: e.t_ns)
    x, rate, eff = windowed(actions, window)
    t_ns = np.array([a.t_ns for a in actions], dtype=np.int64)
    per_s = actions_rate(t_ns, window)[min(window, len(actions)) - 1:] if actions else np.zeros(0)
    end_t = np.array([e.t_ns for e in ends], dtype=np.int64)
    completed = np.array([e.completed for e in ends], dtype=float)
    return RunCurves(
        action_x=x, success_rate=rate, efficiency=eff, actions_per_s=per_s,
        episode_x=np.searchsorted(t_ns, end_t, side="right").astype(np.int64),
        episode_return=np.array([e.episode_return for e in ends], dtype=float),
        episode_length=np.array([e.length for e in ends], dtype=float),
        completion_rate=rolling_mean(completed, episode_window), completed=int(completed.sum()),
        actions=len(actions), window=window, episode_window=episode_window)


def last(values: np.ndarray) -> float | None:
    """The last finite value of a curve, or None."""
    finite = np.asarray(values, dtype=float)
    finite = finite[np.isfinite(finite)]
    return float(finite[-1]) if len(finite) else None


def summary(curves: RunCurves) -> dict[str, float | int | None]:
    """The run's latest values (each curve's last point; return and length as their rolling mean), as
    `romannet plot RUN_DIR` prints them."""
    return {"actions": curves.actions, "episodes": curves.episodes,
            "completed": curves.completed,
            "final_success_rate": last(curves.success_rate), "final_efficiency": last(curves.efficiency),
            "final_completion_rate": last(curves.completion_rate),
            "final_episode_return": last(rolling_mean(curves.episode_return, curves.episode_window)),
            "final_episode_length": last(rolling_mean(curves.episode_length, curves.episode_window)),
            "actions_per_s": last(curves.actions_per_s)}
