"""Learning curves from run directories, like the paper's ablation figure: action success rate and action
efficiency over training steps, one line per run (`romannet plot RUN_DIR...`); runs given the same label are
seeds of one variant: their mean is drawn, with the band between the lowest and highest run.

Source: the /step records of every episode file under RUN_DIR/episodes/ (what the actors did, in order of
their end time across actors). A file cut short (an actor killed mid-episode) is read up to its last whole
chunk; an unreadable file is skipped with a warning.

Over a sliding window of the last `window` training actions:
  action success rate  successful actions / actions (X of every primitive, as the paper's figure);
  action efficiency    ideal actions of the episodes that completed inside the window / actions in the
                       window (ideal: 2 (h - 1) for stacking, the objects of the scene for removal), so
                       actions spent on failed episodes count against it, as in VPG's and SPOT's plots.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from romannet.common.episode_file import STEP_TOPIC, EpisodeFileError, EpisodeReader
from romannet.common.episode_rules import ideal_actions

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainingAction:
    """One action of a training run, as the curves need it."""

    t_ns: int
    success: bool
    episode_end: str  # done reason if this action ended its episode, else ""
    ideal: int  # the episode's ideal action count (set on the ending action of a completed episode)


def read_step_records(path: Path) -> list[dict]:
    """The /step JSON records of one episode file, up to its last whole chunk (common.episode_file reads
    front to back, so an episode being written or cut short by a crash still counts)."""
    reader = EpisodeReader(path)
    out = []
    for message in reader.messages([STEP_TOPIC]):
        step = json.loads(message.data)
        step["_t_ns"] = message.log_time_ns
        out.append(step)
    return out


def _ideal(task: str, goal_height: int, records: Sequence[dict]) -> int:
    first = records[0]
    info = first.get("info") or {}
    # Objects at the start: those left after the first action, plus the one it removed (a clutter pick).
    removed = first.get("primitive") == "pick" and bool(first.get("success"))
    objects = int(info.get("objects_in_workspace", 0)) + int(removed)
    return ideal_actions(task, objects, goal_height)


def episode_actions(task: str, goal_stack_height: int, records: Sequence[dict]) -> list[TrainingAction]:
    """The training actions of one episode file's /step records (read_step_records), in order."""
    if not records:
        return []
    ideal = _ideal(task, goal_stack_height, records)
    out = []
    for i, r in enumerate(records):
        last = i == len(records) - 1
        end = str(r.get("done_reason") or "") if last and r.get("done") else ""
        out.append(TrainingAction(int(r["_t_ns"]), bool(r.get("success")), end, ideal if end == "done" else 0))
    return out


def run_actions(run_dir: Path) -> tuple[list[TrainingAction], dict]:
    """Every training action of a run (all actors), in time order, and the run's task settings."""
    from romannet.common.config import load_config

    cfg = load_config(run_dir / "config.toml")
    task, goal = cfg.task.kind, cfg.task.goal_stack_height
    actions: list[TrainingAction] = []
    files = sorted((run_dir / "episodes").glob("*/*.mcap"))
    for path in files:
        try:
            records = read_step_records(path)
        except (EpisodeFileError, ValueError) as err:  # not an episode, or a broken record: one line, go on
            log.warning("%s skipped: %s", path, err)
            continue
        actions.extend(episode_actions(task, goal, records))
    actions.sort(key=lambda a: a.t_ns)
    return actions, {"task": task, "goal_stack_height": goal, "episode_files": len(files)}


def windowed(actions: Sequence[TrainingAction], window: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(action index, success rate, efficiency) at every action from the `window`-th on (or all, if fewer)."""
    if window < 1:
        raise ValueError(f"window {window}: must be at least 1")
    n = len(actions)
    if n == 0:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    success = np.cumsum([a.success for a in actions], dtype=float)
    ideal = np.cumsum([a.ideal for a in actions], dtype=float)
    idx = np.arange(1, n + 1)
    lo = np.maximum(idx - window, 0)
    count = idx - lo
    s_lo = np.where(lo > 0, success[lo - 1], 0.0)
    i_lo = np.where(lo > 0, ideal[lo - 1], 0.0)
    rate = (success - s_lo) / count
    eff = np.minimum(1.0, (ideal - i_lo) / count)
    start = min(window, n) - 1
    return idx[start:], rate[start:], eff[start:]


def mean_curve(curves: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> dict[str, np.ndarray]:
    """Mean, lowest and highest of several runs' windowed curves (x, rate, eff) at the action indices all of
    them reach (a run stopped early shortens the whole group's curve rather than biasing its tail)."""
    if not curves:
        raise ValueError("no curves to average")
    common = curves[0][0]
    for x, _, _ in curves[1:]:
        common = np.intersect1d(common, x)
    rates = np.stack([rate[np.isin(x, common)] for x, rate, _ in curves])
    effs = np.stack([eff[np.isin(x, common)] for x, _, eff in curves])
    return {"x": common, "rate": rates.mean(axis=0), "rate_lo": rates.min(axis=0), "rate_hi": rates.max(axis=0),
            "eff": effs.mean(axis=0), "eff_lo": effs.min(axis=0), "eff_hi": effs.max(axis=0)}


def group_by_label(run_dirs: Sequence[Path], labels: Sequence[str] | None) -> dict[str, list[Path]]:
    """Runs per label, in the order labels first appear (runs sharing a label are seeds of one variant)."""
    if not labels:  # directory names, or whole paths where two runs share a name
        names = [p.name for p in run_dirs]
        labels = [n if names.count(n) == 1 else str(p) for n, p in zip(names, run_dirs, strict=True)]
    labels = list(labels)
    if len(labels) != len(run_dirs):
        raise ValueError(f"{len(labels)} labels for {len(run_dirs)} runs")
    groups: dict[str, list[Path]] = {}
    for run_dir, label in zip(run_dirs, labels, strict=True):
        groups.setdefault(label, []).append(run_dir)
    return groups


def _run_summary(run_dir: Path, actions: Sequence[TrainingAction], rate: np.ndarray, eff: np.ndarray,
                 meta: dict) -> dict:
    return {"run_dir": str(run_dir), "actions": len(actions),
            "episodes": sum(1 for a in actions if a.episode_end),
            "completed": sum(1 for a in actions if a.episode_end == "done"),
            "final_success_rate": float(rate[-1]) if len(rate) else None,
            "final_efficiency": float(eff[-1]) if len(eff) else None, **meta}


def _group_summary(runs: list[dict]) -> dict:
    """A variant's summary over its seeds: each run's own summary, and the mean and range of their final
    values (each run's last window, so a run cut short still counts with what it reached)."""
    out: dict = {"runs": runs}
    for key in ("final_success_rate", "final_efficiency"):
        values = [r[key] for r in runs if r[key] is not None]
        out[key] = float(np.mean(values)) if values else None
        out[f"{key}_range"] = [float(min(values)), float(max(values))] if values else None
    for key in ("task", "goal_stack_height"):
        if len({r[key] for r in runs}) == 1:
            out[key] = runs[0][key]
    return out


def plot_runs(run_dirs: Sequence[Path], out: Path, window: int = 200, labels: Sequence[str] | None = None) -> dict:
    """Draw the curves of every run, or of every group of runs sharing a label (mean line, min-max band),
    into `out` (PNG); returns per-label final values and counts (per run, and over the seeds of a group)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = group_by_label(run_dirs, labels)
    fig, ax = plt.subplots(figsize=(8, 4.5))
    summary: dict[str, dict] = {}
    for k, (label, dirs) in enumerate(groups.items()):
        runs, curves = [], []
        for run_dir in dirs:
            actions, meta = run_actions(run_dir)
            x, rate, eff = windowed(actions, window)
            runs.append(_run_summary(run_dir, actions, rate, eff, meta))
            curves.append((x, rate, eff))
        color, m = f"C{k}", mean_curve(curves)  # one run: its own curve
        name = label if len(dirs) == 1 else f"{label} (mean of {len(dirs)})"
        ax.plot(m["x"], 100 * m["rate"], color=color, label=f"{name}: action success")
        ax.plot(m["x"], 100 * m["eff"], color=color, linestyle=":", label=f"{name}: action efficiency")
        if len(dirs) > 1:
            ax.fill_between(m["x"], 100 * m["rate_lo"], 100 * m["rate_hi"], color=color, alpha=0.15, linewidth=0)
            ax.fill_between(m["x"], 100 * m["eff_lo"], 100 * m["eff_hi"], color=color, alpha=0.07, linewidth=0)
        summary[label] = runs[0] if len(dirs) == 1 else _group_summary(runs)
    ax.set_xlabel("training actions")
    ax.set_ylabel(f"% over the last {window} actions")
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return summary
