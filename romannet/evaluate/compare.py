"""Several checkpoints on the same test scenes: one row per case and checkpoint, and their mean and range.

`romannet eval A B C --out DIR` evaluates each checkpoint with the same seeds (protocol.py: the same base
seed gives the same scenes), writes each one's report to DIR/<name>/ and this comparison to
DIR/comparison.{json,md,png}. Typical use: the seeds of one training recipe, or the variants of an ablation.

The mean of a metric over checkpoints is taken over the checkpoints that have it: pick success and action
efficiency are averages over completed runs, so a checkpoint that completed no run has neither (it is
counted in `n` of completion only).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from statistics import mean
from typing import Any

from romannet.common.fsutil import write_json_atomic, write_text_atomic

from .report import bar_chart

METRICS = ("completion_rate", "pick_success_rate", "action_efficiency")


def unique_names(names: Sequence[str]) -> list[str]:
    """The names with repeats made unique by a suffix: ["a", "a", "b"] -> ["a", "a-2", "b"]."""
    taken: set[str] = set()
    out = []
    for name in names:
        unique, k = name, 1
        while unique in taken:
            k += 1
            unique = f"{name}-{k}"
        taken.add(unique)
        out.append(unique)
    return out


def spread(values: Sequence[float | None]) -> dict[str, float | int | None]:
    """Mean, min, max and count of the values that are not None (all None: mean/min/max None, n 0)."""
    kept = [v for v in values if v is not None]
    if not kept:
        return {"mean": None, "min": None, "max": None, "n": 0}
    return {"mean": mean(kept), "min": min(kept), "max": max(kept), "n": len(kept)}


def compare(reports: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """The comparison of several eval reports (name -> report.json content) that share their test plan.

    Per case (in the first report's order): each checkpoint's completion, pick success and efficiency, and
    their spread over checkpoints; the same for the overall row. Raises ValueError when the reports were
    not made on the same cases, protocol and seeds (a comparison of different tests would mislead).
    """
    if not reports:
        raise ValueError("no reports to compare")
    names = list(reports)
    first = reports[names[0]]
    for name in names[1:]:
        r = reports[name]
        for key in ("task", "protocol", "base_seed", "runs_per_case"):
            if r.get(key) != first.get(key):
                raise ValueError(f"{name}: {key} {r.get(key)!r} differs from {names[0]}'s {first.get(key)!r}")
        if list(r["cases"]) and list(first["cases"]) and set(r["cases"]) != set(first["cases"]):
            raise ValueError(f"{name}: cases {list(r['cases'])} differ from {names[0]}'s {list(first['cases'])}")
    cases = list(dict.fromkeys(c for r in reports.values() for c in r["cases"]))
    rows: dict[str, Any] = {}
    for case in [*cases, "all"] if len(cases) > 1 else cases:
        per = {n: (reports[n]["overall"] if case == "all" else reports[n]["cases"].get(case)) for n in names}
        rows[case] = {
            "checkpoints": {n: None if s is None else {m: s[m] for m in (*METRICS, "runs", "completed")}
                            for n, s in per.items()},
            **{m: spread([None if s is None else s[m] for s in per.values()]) for m in METRICS},
        }
    return {"task": first["task"], "protocol": first["protocol"], "base_seed": first["base_seed"],
            "runs_per_case": first["runs_per_case"],
            "interrupted": any(r.get("interrupted") for r in reports.values()),
            "checkpoints": {n: _checkpoint_header(reports[n]) for n in names},
            "cases": rows}


def _checkpoint_header(report: Mapping[str, Any]) -> dict[str, Any]:
    return {"checkpoint": report["checkpoint"], "updates": report.get("updates"), "wall_s": report.get("wall_s"),
            "interrupted": bool(report.get("interrupted"))}


def _pct(value: float | None) -> str:
    return "–" if value is None else f"{100 * value:.1f} %"


def _spread_cell(s: Mapping[str, Any]) -> str:
    if s["mean"] is None:
        return "–"
    return f"{_pct(s['mean'])} ({100 * s['min']:.1f}–{100 * s['max']:.1f}, n {s['n']})"


def markdown(comparison: Mapping[str, Any]) -> str:
    """The comparison as Markdown: one row per case and checkpoint, then the mean (min–max) row."""
    lines = [f"### {comparison['task']}: {len(comparison['checkpoints'])} checkpoints, protocol "
             f"`{comparison['protocol']}`", "",
             f"The same test scenes for every checkpoint: {comparison['runs_per_case']} runs per case, seeds "
             f"from {comparison['base_seed']}."]
    if comparison["interrupted"]:
        lines.append("**Interrupted**: at least one checkpoint's evaluation did not finish (see its report).")
    lines += ["", "| case | checkpoint | updates | runs | completion | pick success | action efficiency |",
              "|---|---|---:|---:|---:|---:|---:|"]
    for case, row in comparison["cases"].items():
        for name, s in row["checkpoints"].items():
            updates = comparison["checkpoints"][name]["updates"]
            if s is None:
                lines.append(f"| {case} | {name} | {updates} | 0 | – | – | – |")
                continue
            lines.append(f"| {case} | {name} | {updates} | {s['runs']} | {_pct(s['completion_rate'])} | "
                         f"{_pct(s['pick_success_rate'])} | {_pct(s['action_efficiency'])} |")
        lines.append(f"| {case} | **mean (min–max)** | | | {_spread_cell(row['completion_rate'])} | "
                     f"{_spread_cell(row['pick_success_rate'])} | {_spread_cell(row['action_efficiency'])} |")
    lines += ["", "Pick success and action efficiency are averaged over a checkpoint's completed runs (the "
                  "paper's metrics); a checkpoint that completed no run has neither and is left out of their "
                  "mean (n counts the checkpoints that have the metric)."]
    return "\n".join(lines) + "\n"


def plot(comparison: Mapping[str, Any], path: Path) -> Path:
    """Completion per case: one bar per checkpoint, the mean over checkpoints as a line across each case."""
    cases = list(comparison["cases"])
    series = {name: [100 * ((comparison["cases"][c]["checkpoints"][name] or {}).get("completion_rate") or 0.0)
                     for c in cases] for name in comparison["checkpoints"]}
    means = [comparison["cases"][c]["completion_rate"]["mean"] for c in cases]
    return bar_chart(path, cases, series, ylabel="completion (%)", legend_loc="upper right",
                     title=f"{comparison['task']} ({comparison['protocol']} protocol, "
                           f"{comparison['runs_per_case']} runs per case and checkpoint)",
                     marks=[None if m is None else 100 * m for m in means], mark_label="mean over checkpoints")


def write_comparison(comparison: Mapping[str, Any], out_dir: Path) -> dict[str, Path]:
    """comparison.json and comparison.md in out_dir (each replaced all at once), and comparison.png."""
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {"json": out_dir / "comparison.json", "markdown": out_dir / "comparison.md"}
    write_json_atomic(paths["json"], comparison)
    write_text_atomic(paths["markdown"], markdown(comparison))
    paths["plot"] = plot(comparison, out_dir / "comparison.png")
    return paths
