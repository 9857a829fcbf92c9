"""The sweep's table: per variant the mean, min and max over seeds of the frozen evaluation's completion,
pick success and action efficiency, and of the action success rate over the last training actions; the
oracle and random rows beside them; and the learning curves (mean and min-max band over seeds).

Pure functions build the table from the reports and each run's successes; `collect` reads them from disk.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from romannet.common.fsutil import write_json_atomic, write_text_atomic
from romannet.evaluate.compare import spread
from romannet.evaluate.run_curves import curve_window

EVAL_METRICS = ("completion_rate", "pick_success_rate", "action_efficiency")
LAST_ACTIONS = 500  # the training success rate is over this many last actions, as docs/results.md reports it
TRAINING = "training_success_last"
COLUMNS = (*EVAL_METRICS, TRAINING)


def run_entry(report: Mapping[str, Any], successes: Sequence[bool] | None) -> dict[str, Any]:
    """One run's (or scripted policy's) numbers: the evaluation's overall metrics, and the success rate over
    the last LAST_ACTIONS training actions (None without training)."""
    from romannet.analyse.training_counts import last_rate

    overall = report["overall"]
    return {**{m: overall.get(m) for m in EVAL_METRICS},
            TRAINING: last_rate(list(successes), LAST_ACTIONS) if successes is not None else None,
            "training_actions": None if successes is None else len(successes),
            "eval_runs": overall.get("runs"), "eval_completed": overall.get("completed"),
            "updates": report.get("updates")}


def row(entries: Mapping[str, Mapping[str, Any]], kind: str) -> dict[str, Any]:
    """A table row: each run's entry and every column's spread (mean, min, max, n) over them."""
    return {"kind": kind, "runs": {name: dict(e) for name, e in entries.items()},
            **{c: spread([e[c] for e in entries.values()]) for c in COLUMNS}}


def build_results(manifest: Mapping[str, Any], variants: Mapping[str, Mapping[str, Mapping[str, Any]]],
                  policies: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """The whole table: variants (name -> run name -> entry) in the sweep's order, then the policy rows."""
    rows = {name: row(entries, "variant") for name, entries in variants.items()}
    rows.update({name: row({name: entry}, "policy") for name, entry in policies.items()})
    return {"sweep": dict(manifest), "last_actions": LAST_ACTIONS, "rows": rows}


def _pct(value: float | None) -> str:
    return "–" if value is None else f"{100 * value:.1f} %"


def _cell(s: Mapping[str, Any]) -> str:
    if s["mean"] is None:
        return "–"
    if s["n"] == 1:
        return _pct(s["mean"])
    return f"{_pct(s['mean'])} ({100 * s['min']:.1f}–{100 * s['max']:.1f})"


def markdown(results: Mapping[str, Any]) -> str:
    sweep = results["sweep"]
    ev = sweep["eval"]
    test = {"stacking": f"goal height {', '.join(map(str, ev.get('goal_heights') or []))}",
            "clutter": f"{ev.get('objects')} {ev.get('object_set')} objects",
            "arrangement": "arrangement cases"}.get(ev["task"], ev["task"])
    lines = [f"### Sweep: {len(sweep['variants'])} variant(s) x {len(sweep['seeds'])} seed(s), "
             f"{sweep['max_actions']} training actions each", "",
             f"Frozen evaluation on {ev['task']} ({test}): {ev['runs']} runs per case, seeds from {ev['seed']}, the "
             f"same scenes for every row. Training seeds {', '.join(map(str, sweep['seeds']))}; each cell is the "
             "mean (min–max) over seeds.", "",
             f"| row | seeds | completion | pick success | action efficiency | training success, last "
             f"{results['last_actions']} actions |", "|---|---:|---:|---:|---:|---:|"]
    for name, r in results["rows"].items():
        seeds = str(len(r["runs"])) if r["kind"] == "variant" else "–"
        lines.append(f"| {name} | {seeds} | " + " | ".join(_cell(r[c]) for c in COLUMNS) + " |")
    lines += ["", "Pick success and action efficiency are averaged over a run's completed evaluation runs (the "
                  "paper's metrics); a seed that completed none has neither and is left out of their mean."]
    if any(r["kind"] == "policy" for r in results["rows"].values()):
        lines[-1] += (" The oracle and random rows are scripted policies (the simulator's ceiling and the floor) "
                      "and do not train.")
    lines.append("")
    return "\n".join(lines)


def write_results(results: Mapping[str, Any], out: Path) -> dict[str, Path]:
    paths = {"json": out / "results.json", "markdown": out / "results.md"}
    write_json_atomic(paths["json"], results)
    write_text_atomic(paths["markdown"], markdown(results))
    return paths


def collect(manifest: Mapping[str, Any], jobs: Sequence[Any], eval_dirs: Mapping[str, Path],
            policy_dirs: Mapping[str, Path]) -> dict[str, Any]:
    """Read every finished evaluation and each run's recorded training actions into the table.

    jobs: the sweep's RunJobs; eval_dirs: run name -> its evaluation's directory; policy_dirs likewise."""
    from romannet.evaluate.curves import run_actions

    from .state import finished_report

    variants: dict[str, dict[str, dict[str, Any]]] = {}
    for job in jobs:
        report = finished_report(eval_dirs[job.name])
        if report is None:
            raise ValueError(f"{eval_dirs[job.name]} holds no finished evaluation")
        actions, _ = run_actions(job.run_dir)
        variants.setdefault(job.variant, {})[job.name] = run_entry(report, [a.success for a in actions])
    policies = {}
    for name, out_dir in policy_dirs.items():
        report = finished_report(out_dir)
        if report is not None:
            policies[name] = run_entry(report, None)
    return build_results(manifest, variants, policies)


def plot_curves(jobs: Sequence[Any], out: Path, max_actions: int) -> Path:
    """curves.png: action success and efficiency over training actions, per variant the mean over its seeds
    with their min-max band (romannet plot's drawing)."""
    from romannet.evaluate.curves import plot_runs

    plot_runs([job.run_dir for job in jobs], out, curve_window(max_actions), labels=[job.variant for job in jobs])
    return out
