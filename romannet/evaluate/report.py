"""The evaluation's outputs: report.json (everything), report.md (the table people read), report.png."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from romannet.common.fsutil import write_json_atomic, write_text_atomic

from .metrics import RunLog, Summary, by_case, cases_solved_in_all_runs, summarize


def _pct(value: float | None) -> str:
    return "–" if value is None else f"{100 * value:.1f} %"


def build_report(runs: Sequence[RunLog], header: dict[str, Any]) -> dict[str, Any]:
    """The JSON report: header (what was evaluated, how), overall and per-case metrics, every run."""
    if not runs:
        return {**header, "overall": None, "cases": {}, "cases_solved_in_all_runs": 0, "runs": []}
    from .protocol import run_to_json

    removal = header.get("task") != "stacking"
    per_case = by_case(runs, removal=removal)
    return {**header, "overall": summarize(runs, removal=removal).as_dict(),
            "cases": {name: s.as_dict() for name, s in per_case.items()},
            "cases_solved_in_all_runs": cases_solved_in_all_runs(per_case),
            "runs": [run_to_json(r) for r in runs]}


def _row(name: str, s: Summary) -> str:
    reasons = ", ".join(f"{k} {v}" for k, v in s.end_reasons.items())
    mean_actions = "–" if s.mean_actions is None else f"{s.mean_actions:.1f}"
    return (f"| {name} | {s.runs} | {_pct(s.completion_rate)} | {_pct(s.pick_success_rate)} | "
            f"{_pct(s.action_efficiency)} | {_pct(s.pick_success_all_runs)} | {_pct(s.median_share_picked)} | "
            f"{mean_actions} | {reasons} |")


def markdown(report: dict[str, Any]) -> str:
    """The report as a Markdown section: what was evaluated, then one row per case and the total."""
    lines = [f"### {report['task']} — protocol `{report['protocol']}`", "",
             f"Checkpoint `{report['checkpoint']}` (update {report.get('updates', '?')}), "
             f"{report['runs_per_case']} runs per case, seeds from {report['base_seed']}, greedy policy, "
             f"{report['workers']} worker process(es), {report['wall_s']:.0f} s on {report['machine']}."]
    if report.get("interrupted"):
        lines.append(f"**Interrupted**: {len(report['runs'])} of {report['planned_runs']} planned runs finished.")
    lines += ["", "| case | runs | completion | pick success | action efficiency | pick success, all runs | "
                  "objects picked (median) | mean actions | end reasons |",
              "|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    if report["overall"] is None:
        return "\n".join(lines + ["| (no run finished) | 0 | | | | | | | |"]) + "\n"
    for name, case in report["cases"].items():
        lines.append(_row(name, Summary(**case)))
    if len(report["cases"]) > 1:
        lines.append(_row("**all**", Summary(**report["overall"])))
        lines += ["", f"Cases completed in all runs: **{report['cases_solved_in_all_runs']} / "
                      f"{len(report['cases'])}**."]
    lines += ["", "Completion: done without 10 consecutive failed attempts. Pick success and action efficiency "
                  "(ideal / actual actions) are averaged over completed runs, as the paper does. Not the paper's: "
                  "pick success pooled over all runs, and the median share of a scene's objects a run picked "
                  "(removal tasks)."]
    return "\n".join(lines) + "\n"


def plot(report: dict[str, Any], path: Path) -> Path | None:
    """Bars per case: completion, pick success, action efficiency (percent). None if nothing to plot."""
    if not report["cases"]:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    names = list(report["cases"])
    metrics = [("completion_rate", "completion"), ("pick_success_rate", "pick success"),
               ("action_efficiency", "action efficiency")]
    x = np.arange(len(names))
    width = 0.27
    fig, ax = plt.subplots(figsize=(max(6.0, 0.9 * len(names) + 3), 4.0))
    for k, (key, label) in enumerate(metrics):
        values = [100 * (report["cases"][n][key] or 0.0) for n in names]
        ax.bar(x + (k - 1) * width, values, width, label=label)
    ax.set_xticks(x, names, rotation=30 if len(names) > 4 else 0, ha="right" if len(names) > 4 else "center")
    ax.set_ylim(0, 105)
    ax.set_ylabel("%")
    ax.set_title(f"{report['task']} ({report['protocol']} protocol, {report['runs_per_case']} runs per case)")
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_outputs(report: dict[str, Any], out_dir: Path) -> dict[str, Path]:
    """report.json and report.md (each replaced all at once) and report.png."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"json": out_dir / "report.json", "markdown": out_dir / "report.md"}
    write_json_atomic(paths["json"], report)
    write_text_atomic(paths["markdown"], markdown(report))
    png = plot(report, out_dir / "report.png")
    if png is not None:
        paths["plot"] = png
    return paths
