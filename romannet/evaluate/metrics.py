"""The paper's evaluation metrics ("Evaluation Metrics") as pure functions of episode logs.

A run is one episode of the evaluation protocol: a fresh scene from a new seed, the greedy policy, until
the task is done or it fails. Its log is the sequence of executed primitives with their success (X).

completion rate    share of runs that completed the task without `max_consecutive_failures` (the paper:
                   10) failed attempts in a row. A run whose log holds such a streak before the task was
                   done is not complete, whatever the simulator said afterwards; a run cut by a step limit
                   or an unstable simulation is not complete either.
pick success rate  successful picks / pick attempts of one completed run, averaged over completed runs
                   (a completed run without any pick attempt has no pick rate and is left out of the mean).
action efficiency  ideal / actual actions of one completed run, averaged over completed runs. Ideal: the
                   number of objects for the removal tasks (clutter, arrangements), 2 (h - 1) for stacking
                   to height h (one pick and one place per cube added to the first). Capped at 1: in
                   clutter a push can clear an object out of the workspace without a pick, which would
                   otherwise read as better than ideal.

Two more numbers that are not the paper's, because averages over completed runs hide the runs that failed:
pick success over all runs (successful picks / pick attempts, pooled over every run) and, for the removal
tasks, the median share of the scene's objects a run picked (successful picks / objects at the start).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from statistics import mean, median

MAX_CONSECUTIVE_FAILURES = 10  # the paper's completion criterion


@dataclass(frozen=True)
class StepLog:
    """One executed action: its primitive and whether it succeeded (the sub-task indicator X); for a failed
    pick, why (the simulator's grasp cause, actor/sim/grasp_check.py, else the environment's reason)."""

    primitive: str
    success: bool
    cause: str = ""


@dataclass(frozen=True)
class RunLog:
    """One evaluation run: what was asked, what happened, and how the environment ended it.

    end_reason: the environment's (done, consecutive_failures, step_limit, unstable) or "error: …".
    ideal_actions: common.episode_rules.ideal_actions at the run's start (objects present, or the goal).
    """

    case: str  # "clutter", "stacking-h4" or an arrangement case name
    seed: int
    ideal_actions: int
    end_reason: str
    steps: tuple[StepLog, ...] = field(default_factory=tuple)
    duration_s: float = 0.0

    @property
    def actions(self) -> int:
        return len(self.steps)


def failure_streak_at(successes: Sequence[bool], limit: int = MAX_CONSECUTIVE_FAILURES) -> int | None:
    """Index of the action that completed the first streak of `limit` failures in a row, or None."""
    if limit < 1:
        raise ValueError(f"limit {limit}: must be at least 1")
    streak = 0
    for i, ok in enumerate(successes):
        streak = 0 if ok else streak + 1
        if streak >= limit:
            return i
    return None


def completed(run: RunLog, limit: int = MAX_CONSECUTIVE_FAILURES) -> bool:
    """Done, and no `limit` consecutive failures before the task was done (the paper's completion)."""
    return run.end_reason == "done" and failure_streak_at([s.success for s in run.steps], limit) is None


def pick_success_rate(run: RunLog) -> float | None:
    """Successful picks / pick attempts of one run; None when it attempted no pick."""
    picks = [s.success for s in run.steps if s.primitive == "pick"]
    return sum(picks) / len(picks) if picks else None


def action_efficiency(run: RunLog) -> float | None:
    """ideal / actual actions of one run, capped at 1; None for a run without actions."""
    return min(1.0, run.ideal_actions / run.actions) if run.actions else None


def pooled_pick_success(runs: Sequence[RunLog]) -> float | None:
    """Successful picks / pick attempts over every run, completed or not; None without any pick."""
    picks = [s.success for r in runs for s in r.steps if s.primitive == "pick"]
    return sum(picks) / len(picks) if picks else None


def share_picked(run: RunLog) -> float:
    """Removal tasks: the share of the scene's objects (its ideal count) the run picked, capped at 1."""
    return min(1.0, sum(s.success for s in run.steps if s.primitive == "pick") / max(1, run.ideal_actions))


def failed_picks(runs: Sequence[RunLog]) -> dict[str, int]:
    """Failed picks over every run by cause, most frequent first ("unknown": logged without a cause)."""
    causes = Counter(s.cause or "unknown" for r in runs for s in r.steps if s.primitive == "pick" and not s.success)
    return dict(causes.most_common())


def _mean_or_none(values: Sequence[float | None]) -> float | None:
    kept = [v for v in values if v is not None]
    return mean(kept) if kept else None


@dataclass(frozen=True)
class Summary:
    """The metrics of a set of runs (one test case, or all of them)."""

    runs: int
    completed: int
    completion_rate: float
    pick_success_rate: float | None  # mean over completed runs that attempted a pick
    action_efficiency: float | None  # mean over completed runs
    mean_actions: float | None  # over all runs
    end_reasons: dict[str, int]
    solved_all: bool  # every run completed
    pick_success_all_runs: float | None = None  # pooled over every run (not the paper's metric)
    median_share_picked: float | None = None  # removal tasks: median share of the objects a run picked
    failed_picks: dict[str, int] = field(default_factory=dict)  # over every run, by cause (failed_picks)

    def as_dict(self) -> dict:
        return {"runs": self.runs, "completed": self.completed, "completion_rate": self.completion_rate,
                "pick_success_rate": self.pick_success_rate, "action_efficiency": self.action_efficiency,
                "mean_actions": self.mean_actions, "end_reasons": dict(self.end_reasons),
                "solved_all": self.solved_all, "pick_success_all_runs": self.pick_success_all_runs,
                "median_share_picked": self.median_share_picked, "failed_picks": dict(self.failed_picks)}


def summarize(runs: Sequence[RunLog], limit: int = MAX_CONSECUTIVE_FAILURES, removal: bool = True) -> Summary:
    """Completion rate, pick success and efficiency (over completed runs), end reasons of `runs`, and the
    pooled pick success and (removal tasks: `removal`) the median share of objects picked."""
    if not runs:
        raise ValueError("no runs to summarize")
    done = [r for r in runs if completed(r, limit)]
    return Summary(
        runs=len(runs), completed=len(done), completion_rate=len(done) / len(runs),
        pick_success_rate=_mean_or_none([pick_success_rate(r) for r in done]),
        action_efficiency=_mean_or_none([action_efficiency(r) for r in done]),
        mean_actions=mean(r.actions for r in runs),
        end_reasons=dict(sorted(Counter(_reason_key(r, limit) for r in runs).items())),
        solved_all=len(done) == len(runs), pick_success_all_runs=pooled_pick_success(runs),
        median_share_picked=median(share_picked(r) for r in runs) if removal else None,
        failed_picks=failed_picks(runs))


def _reason_key(run: RunLog, limit: int) -> str:
    """The end reason to count: a 'done' preceded by a failure streak counts as consecutive_failures."""
    if run.end_reason == "done" and not completed(run, limit):
        return "consecutive_failures"
    return run.end_reason


def by_case(runs: Sequence[RunLog], limit: int = MAX_CONSECUTIVE_FAILURES, removal: bool = True
            ) -> dict[str, Summary]:
    """One Summary per case name, in the order cases first appear."""
    cases: dict[str, list[RunLog]] = {}
    for r in runs:
        cases.setdefault(r.case, []).append(r)
    return {case: summarize(rs, limit, removal) for case, rs in cases.items()}


def cases_solved_in_all_runs(per_case: dict[str, Summary]) -> int:
    """How many cases completed in every one of their runs (the paper's "10/11 cases at 100 %")."""
    return sum(s.solved_all for s in per_case.values())
