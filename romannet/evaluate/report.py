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
    policy = report.get("policy", "net")  # reports written before the oracle/random policies: a net
    if policy == "net":
        who = f"Checkpoint `{report['checkpoint']}` (update {report.get('updates', '?')}), greedy policy"
        if report.get("precision"):
            who += f" in {report['precision']}"
    else:
        who = f"Policy: {report.get('policy_description', policy)}; {report.get('protocol_note', 'frozen')}"
    lines = [f"### {report['task']} — policy `{policy}` — protocol `{report['protocol']}`", "",
             f"{who}; {report['runs_per_case']} runs per case, seeds from {report['base_seed']}, "
             f"{report['workers']} worker process(es), {report['wall_s']:.0f} s on {report['machine']}."]
    for warning in report.get("warnings") or ():
        lines += ["", f"**Warning**: {warning}."]
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
    failed = report["overall"].get("failed_picks") or {}
    if failed:
        causes = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in failed.items())
        lines += ["", f"Failed picks by cause (all runs): {causes}."]
    lines += ["", "Completion: done without 10 consecutive failed attempts. Pick success and action efficiency "
                  "(ideal / actual actions) are averaged over completed runs, as the paper does. Not the paper's: "
                  "pick success pooled over all runs, and the median share of a scene's objects a run picked "
                  "(removal tasks)."]
    return "\n".join(lines) + "\n"


def bar_chart(path: Path, groups: Sequence[str], series: dict[str, Sequence[float]], *, ylabel: str, title: str,
              legend_loc: str = "lower right", marks: Sequence[float | None] = (), mark_label: str = "") -> Path:
    """Grouped bars (percent, 0-100): one group per x label, one bar per series; `marks` (one per group, or
    None) are drawn as a black line across their group."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    x = np.arange(len(groups))
    width = 0.8 / max(1, len(series))
    fig, ax = plt.subplots(figsize=(max(6.0, 0.3 * len(groups) * len(series) + 3), 4.0))
    for k, (label, values) in enumerate(series.items()):
        ax.bar(x - 0.4 + (k + 0.5) * width, values, width, label=label)
    first = True
    for i, mark in enumerate(marks):
        if mark is not None:
            ax.hlines(mark, i - 0.45, i + 0.45, colors="black", linewidth=2, label=mark_label if first else None)
            first = False
    many = len(groups) > 4
    ax.set_xticks(x, groups, rotation=30 if many else 0, ha="right" if many else "center")
    ax.set_ylim(0, 105)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.legend(loc=legend_loc, fontsize=8 if len(series) <= 3 else 7)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot(report: dict[str, Any], path: Path) -> Path | None:
    """Bars per case: completion, pick success, action efficiency (percent). None if nothing to plot."""
    if not report["cases"]:
        return None
    names = list(report["cases"])
    metrics = [("completion_rate", "completion"), ("pick_success_rate", "pick success"),
               ("action_efficiency", "action efficiency")]
    series = {label: [100 * (report["cases"][n][key] or 0.0) for n in names] for key, label in metrics}
    return bar_chart(path, names, series, ylabel="%",
                     title=f"{report['task']}, policy {report.get('policy', 'net')} ({report['protocol']} protocol, "
                           f"{report['runs_per_case']} runs per case)")


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
