"""The paper's evaluation metrics on hand-made episode logs (romannet/evaluate/metrics.py)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from romannet.common.episode_rules import ideal_actions
from romannet.evaluate.curves import TrainingAction, group_by_label, mean_curve, windowed
from romannet.evaluate.metrics import (
    RunLog,
    StepLog,
    action_efficiency,
    by_case,
    cases_solved_in_all_runs,
    completed,
    failure_streak_at,
    pick_success_rate,
    summarize,
)
from romannet.evaluate.protocol import auto_max_steps, plan_runs, run_from_json, run_to_json


def steps(text: str) -> tuple[StepLog, ...]:
    """'P1 p0 L1' -> push success, pick failure, place success (P push, p pick, L place)."""
    names = {"P": "push", "p": "pick", "L": "place"}
    return tuple(StepLog(names[t[0]], t[1] == "1") for t in text.split())


def run(text: str, end: str = "done", ideal: int = 3, case: str = "c") -> RunLog:
    return RunLog(case, 0, ideal, end, steps(text))


def test_ten_consecutive_failures_rule_counts_only_unbroken_streaks():
    nine = [False] * 9
    assert failure_streak_at(nine) is None
    assert failure_streak_at(nine + [False]) == 9
    assert failure_streak_at(nine + [True] + nine) is None  # a success in between resets the streak
    assert failure_streak_at([True] * 3 + [False] * 10 + [True]) == 12
    assert failure_streak_at([False, False], limit=2) == 1
    with pytest.raises(ValueError):
        failure_streak_at([True], limit=0)


def test_a_run_is_complete_only_if_done_without_a_prior_failure_streak():
    ok = run("p0 " * 9 + "p1 p1 p1")
    assert completed(ok)
    streak_then_done = run("p0 " * 10 + "p1 p1 p1")  # the simulator went on, the paper's rule does not
    assert not completed(streak_then_done)
    assert not completed(run("p1 p1", end="step_limit"))
    assert not completed(run("p1", end="unstable"))
    assert not completed(run("p0 " * 10, end="consecutive_failures"))


def test_pick_success_rate_counts_picks_only():
    r = run("P1 p0 p1 P0 p1 L1")
    assert pick_success_rate(r) == pytest.approx(2 / 3)
    assert pick_success_rate(run("P1 P1")) is None


def test_action_efficiency_is_ideal_over_actual_capped_at_one():
    assert action_efficiency(run("p1 p1 p1", ideal=3)) == 1.0
    assert action_efficiency(run("p0 p1 p1 p1", ideal=3)) == 0.75
    # clutter: a push swept two objects out of the workspace, fewer actions than objects
    assert action_efficiency(run("P1 p1", ideal=3)) == 1.0
    assert action_efficiency(RunLog("c", 0, 3, "error: x", ())) is None


def test_stacking_efficiency_uses_two_actions_per_added_cube():
    h4 = ideal_actions("stacking", 0, 4)
    perfect = run("p1 L1 p1 L1 p1 L1", ideal=h4)
    sloppy = run("p1 L0 p1 L1 p0 p1 L1 p1 L1", ideal=h4)  # 9 actions for an ideal of 6
    assert action_efficiency(perfect) == 1.0
    assert action_efficiency(sloppy) == pytest.approx(6 / 9)


def test_summary_averages_over_completed_runs_and_reports_end_reasons():
    runs = [run("p1 p1 p1", ideal=3),  # complete: pick 1.0, eff 1.0
            run("p0 p1 p1 p1", ideal=3),  # complete: pick 0.75, eff 0.75
            run("p1 " + "p0 " * 10, end="consecutive_failures"),  # incomplete: partial progress ignored
            run("p0 " * 10 + "p1 p1 p1"),  # "done" after a streak: incomplete
            run("p1 p1", end="step_limit")]
    s = summarize(runs)
    assert (s.runs, s.completed) == (5, 2)
    assert s.completion_rate == pytest.approx(0.4)
    assert s.pick_success_rate == pytest.approx((1.0 + 0.75) / 2)
    assert s.action_efficiency == pytest.approx((1.0 + 0.75) / 2)
    assert s.end_reasons == {"consecutive_failures": 2, "done": 2, "step_limit": 1}
    assert not s.solved_all
    assert s.mean_actions == pytest.approx((3 + 4 + 11 + 13 + 2) / 5)


def test_pooled_pick_success_and_share_picked_count_every_run():
    runs = [run("p1 p1 p1", ideal=3),  # complete: 3 of 3 objects picked
            run("p1 " + "p0 " * 10, ideal=4, end="consecutive_failures"),  # 1 of 4 picked, 1 of 11 picks
            run("P1 p1 p0", ideal=2, end="step_limit")]  # 1 of 2; the push is no pick attempt
    s = summarize(runs)
    assert s.pick_success_rate == pytest.approx(1.0)  # the paper's: completed runs only
    assert s.pick_success_all_runs == pytest.approx((3 + 1 + 1) / (3 + 11 + 2))
    assert s.median_share_picked == pytest.approx(0.5)  # of 1.0, 0.25, 0.5
    assert summarize(runs, removal=False).median_share_picked is None  # stacking: no objects to remove
    assert summarize([run("P1 P0", ideal=2)]).pick_success_all_runs is None


def test_summary_of_runs_without_any_completion_has_no_rates():
    s = summarize([run("p0 " * 10, end="consecutive_failures")])
    assert s.completion_rate == 0.0 and s.pick_success_rate is None and s.action_efficiency is None
    with pytest.raises(ValueError):
        summarize([])


def test_completed_run_without_picks_is_left_out_of_the_pick_mean():
    s = summarize([run("P1", ideal=1), run("p1 p0 p1", ideal=2)])
    assert s.completed == 2
    assert s.pick_success_rate == pytest.approx(2 / 3)


def test_per_case_rows_and_cases_solved_in_all_runs():
    runs = [run("p1 p1", ideal=2, case="a"), run("p1 p1", ideal=2, case="a"),
            run("p1 p1", ideal=2, case="b"), run("p0 " * 10, end="consecutive_failures", case="b")]
    per = by_case(runs)
    assert list(per) == ["a", "b"]
    assert per["a"].completion_rate == 1.0 and per["b"].completion_rate == 0.5
    assert cases_solved_in_all_runs(per) == 1


def test_plan_gives_each_run_a_new_seed_and_cases_distinct_seed_ranges():
    specs = plan_runs("stacking", 30, 100, goal_heights=(2, 3, 4, 5))
    assert len(specs) == 120
    assert len({s.seed for s in specs}) == 120
    assert [s.case for s in specs[::30]] == ["h2", "h3", "h4", "h5"]
    assert specs[30].goal_height == 3 and specs[30].max_steps == auto_max_steps("stacking", 0, 3) == 30
    clutter = plan_runs("clutter", 3, 0, num_objects=30, object_set="novel")
    assert [s.seed for s in clutter] == [0, 1, 2] and clutter[0].case == "novel-30"
    assert clutter[0].max_steps == 150
    with pytest.raises(ValueError, match="no arrangement case files"):
        plan_runs("arrangement", 3, 0)


def test_run_records_round_trip_through_the_journal_format():
    r = RunLog("case_01", 7, 4, "done", steps("P1 p0 p1"), 1.5)
    assert run_from_json(run_to_json(r)) == r


def test_windowed_curves_count_failed_episodes_against_efficiency():
    def act(i: int, ok: bool, end: str = "", ideal: int = 0) -> TrainingAction:
        return TrainingAction(i, ok, end, ideal)

    # episode 1: 4 actions, done, ideal 2; episode 2: 3 failures, ended by the failure rule
    actions = [act(0, True), act(1, False), act(2, True), act(3, True, "done", 2),
               act(4, False), act(5, False), act(6, False, "consecutive_failures")]
    x, rate, eff = windowed(actions, window=4)
    assert list(x) == [4, 5, 6, 7]
    assert rate[0] == pytest.approx(3 / 4) and eff[0] == pytest.approx(2 / 4)
    assert rate[-1] == pytest.approx(1 / 4) and eff[-1] == pytest.approx(2 / 4)  # episode 1 ended in the window
    _, rate3, eff3 = windowed(actions, window=3)
    assert rate3[-1] == 0.0 and eff3[-1] == 0.0  # only the failed episode's actions
    x, rate, eff = windowed(actions[:2], window=10)  # fewer actions than the window: one point
    assert list(x) == [2] and math.isclose(rate[0], 0.5)
    assert windowed([], 5)[0].size == 0
    assert np.all((rate >= 0) & (rate <= 1))


def test_seeds_of_a_variant_average_over_the_actions_all_of_them_reach():
    a = (np.array([3, 4, 5, 6]), np.array([0.2, 0.4, 0.6, 0.8]), np.array([0.0, 0.0, 0.5, 0.5]))
    b = (np.array([3, 4, 5]), np.array([0.4, 0.0, 0.2]), np.array([0.0, 0.25, 0.25]))  # stopped one action early
    m = mean_curve([a, b])
    assert list(m["x"]) == [3, 4, 5]
    assert np.allclose(m["rate"], [0.3, 0.2, 0.4]) and np.allclose(m["rate_lo"], [0.2, 0.0, 0.2])
    assert np.allclose(m["rate_hi"], [0.4, 0.4, 0.6])
    assert np.allclose(m["eff"], [0.0, 0.125, 0.375]) and np.allclose(m["eff_hi"], [0.0, 0.25, 0.5])
    one = mean_curve([a])
    assert np.array_equal(one["rate"], a[1]) and np.array_equal(one["rate_lo"], one["rate_hi"])
    with pytest.raises(ValueError, match="no curves"):
        mean_curve([])


def test_runs_sharing_a_label_are_grouped_in_the_order_labels_first_appear():
    runs = [Path("r/base-s1"), Path("r/full-s1"), Path("r/base-s2"), Path("r/full-s2")]
    groups = group_by_label(runs, ["baseline", "full", "baseline", "full"])
    assert list(groups) == ["baseline", "full"]
    assert groups["baseline"] == [runs[0], runs[2]] and groups["full"] == [runs[1], runs[3]]
    assert list(group_by_label(runs[:2], None)) == ["base-s1", "full-s1"]  # default: one line per run
    same_name = [Path("a/run"), Path("b/run")]
    assert list(group_by_label(same_name, None)) == ["a/run", "b/run"]  # not silently merged
    with pytest.raises(ValueError, match="3 labels for 4 runs"):
        group_by_label(runs, ["a", "b", "c"])


def test_report_table_shows_the_papers_metrics_and_the_pooled_ones():
    from romannet.evaluate.report import build_report, markdown

    header = {"task": "clutter", "protocol": "frozen", "checkpoint": "ckpt-000000001", "updates": 1,
              "runs_per_case": 2, "base_seed": 100000, "workers": 1, "wall_s": 3.0, "machine": "test box"}
    report = build_report([run("p1 p1 p1", ideal=3), run("p1 " + "p0 " * 10, ideal=4, end="consecutive_failures")],
                          header)
    table = markdown(report)
    assert "| c | 2 | 50.0 % | 100.0 % | 100.0 % | 28.6 % | 62.5 % | 7.0 | consecutive_failures 1, done 1 |" in table
    # A report written before the pooled columns existed still renders (they show as "–").
    for key in ("pick_success_all_runs", "median_share_picked"):
        del report["cases"]["c"][key]
    assert "| c | 2 | 50.0 % | 100.0 % | 100.0 % | – | – | 7.0 |" in markdown(report)
    stacking = build_report([run("p1 L1", ideal=2)], {**header, "task": "stacking"})
    assert stacking["overall"]["median_share_picked"] is None


def _stacking_report(runs: list[RunLog], **header: object) -> dict:
    from romannet.evaluate.report import build_report

    base = {"task": "stacking", "protocol": "frozen", "checkpoint": "ckpt", "updates": 5, "runs_per_case": 2,
            "base_seed": 100000, "workers": 1, "wall_s": 1.0, "machine": "test box"}
    return build_report(runs, {**base, **header})


def test_comparison_gives_each_checkpoints_metrics_and_their_spread():
    from romannet.evaluate.compare import compare, markdown

    ten_failures = "p0 " * 10
    a = _stacking_report([run("p1 L1", ideal=2, case="h2"), run("p1 L1 p0 p1 L1 p1 L1", ideal=6, case="h4"),
                          run("p1 L1", ideal=2, case="h2"), run(ten_failures, end="consecutive_failures", case="h4")])
    b = _stacking_report([run("p0 p1 L1", ideal=2, case="h2"), run(ten_failures, end="consecutive_failures", case="h4"),
                          run("p1 L0", end="unstable", ideal=2, case="h2"),
                          run(ten_failures, end="consecutive_failures", case="h4")], updates=9)
    c = compare({"s1": a, "s2": b})
    assert list(c["cases"]) == ["h2", "h4", "all"]
    h2 = c["cases"]["h2"]
    assert h2["checkpoints"]["s1"]["completion_rate"] == 1.0 and h2["checkpoints"]["s2"]["completion_rate"] == 0.5
    assert h2["completion_rate"] == {"mean": 0.75, "min": 0.5, "max": 1.0, "n": 2}
    assert h2["pick_success_rate"] == {"mean": 0.75, "min": 0.5, "max": 1.0, "n": 2}  # s2: its one completed run
    assert h2["action_efficiency"]["max"] == 1.0 and h2["action_efficiency"]["min"] == pytest.approx(2 / 3)
    h4 = c["cases"]["h4"]  # s2 completed no h4 run: no pick success or efficiency, left out of their mean
    assert h4["completion_rate"] == {"mean": 0.25, "min": 0.0, "max": 0.5, "n": 2}
    assert h4["pick_success_rate"] == {"mean": 0.75, "min": 0.75, "max": 0.75, "n": 1}
    assert c["cases"]["all"]["completion_rate"]["mean"] == pytest.approx((0.75 + 0.25) / 2)
    assert c["checkpoints"]["s2"]["updates"] == 9 and not c["interrupted"]
    table = markdown(c)
    assert "| h4 | s2 | 9 | 2 | 0.0 % | – | – |" in table
    assert "| h4 | **mean (min–max)** | | | 25.0 % (0.0–50.0, n 2) | 75.0 % (75.0–75.0, n 1) |" in table


def test_comparison_refuses_reports_of_different_tests():
    from romannet.evaluate.compare import compare, unique_names

    a = _stacking_report([run("p1 L1", ideal=2, case="h2")])
    with pytest.raises(ValueError, match="protocol 'paper' differs"):
        compare({"a": a, "b": {**a, "protocol": "paper"}})
    with pytest.raises(ValueError, match="base_seed"):
        compare({"a": a, "b": {**a, "base_seed": 7}})
    with pytest.raises(ValueError, match="cases"):
        compare({"a": a, "b": _stacking_report([run("p1 L1", ideal=2, case="h3")])})
    with pytest.raises(ValueError, match="no reports"):
        compare({})
    assert unique_names(["a", "a", "b", "a"]) == ["a", "a-2", "b", "a-3"]
    assert unique_names(["a", "a-2", "a"]) == ["a", "a-2", "a-3"]  # a suffix never repeats a given name
