"""The paper's evaluation metrics on hand-made episode logs (romannet/evaluate/metrics.py)."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
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


def test_repeated_failure_count_on_hand_made_step_records():
    from romannet.bench.repeated_failures import count_repeats

    def step(prim, row, col, ok, explored=False, version=1):
        return {"primitive": prim, "row": row, "col": col, "success": ok, "explored": explored,
                "weights_version": version}

    episode = [step("pick", 5, 5, False), step("pick", 5, 5, False),  # greedy repeat, same weights
               step("pick", 5, 5, False, version=2),  # greedy repeat on new weights
               step("pick", 5, 5, False, explored=True),  # explored: not a greedy choice
               step("pick", 7, 5, True),  # greedy after a failure, another pixel
               step("pick", 7, 5, False)]  # after a success: not counted
    out = count_repeats([episode, [step("push", 1, 1, False)]])
    assert out["episodes"] == 2 and out["actions"] == 7
    assert (out["greedy_after_failure"], out["repeats"], out["repeats_on_same_weights"]) == (3, 2, 1)
    assert out["repeat_rate"] == 2 / 3 and out["pick_success"] == 1 / 6


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


def _cube_heightmap(centre_rc: tuple[float, float], yaw_deg: float, side_px: int = 25) -> np.ndarray:
    """A 224 x 224 heightmap with one 5 cm-high square of `side_px` pixels, turned by yaw_deg."""
    depth = np.zeros((224, 224), np.float32)
    box = cv2.boxPoints(((centre_rc[1], centre_rc[0]), (side_px, side_px), yaw_deg))
    cv2.fillPoly(depth, [np.round(box).astype(np.int32)], 0.05)
    return depth


def test_pick_offset_measures_along_and_across_the_closing_axis():
    from romannet.bench.pick_offsets import pick_offset

    depth = _cube_heightmap((100, 120), 0.0)
    centre = pick_offset(depth, 100, 120, 0.0, 0.002)
    assert centre["on_object"] and abs(centre["along_m"]) < 0.0015 and abs(centre["across_m"]) < 0.0015
    assert centre["face_angle_deg"] < 1.0 and 20 < centre["area_cm2"] < 30
    # 10 px to the right of the centre (+col) with the closing axis along +col: 2 cm along, nothing across;
    # the same pixel with the closing axis turned 90 degrees: 2 cm across, nothing along.
    right = pick_offset(depth, 100, 130, 0.0, 0.002)
    assert right["along_m"] == pytest.approx(0.02, abs=0.0015) and abs(right["across_m"]) < 0.0015
    turned = pick_offset(depth, 100, 130, math.pi / 2, 0.002)
    assert abs(turned["along_m"]) < 0.0015 and abs(turned["across_m"]) == pytest.approx(0.02, abs=0.0015)
    # An angle between the closing axis and the faces folds into 0-45 degrees, whichever face pair.
    assert pick_offset(depth, 100, 120, math.radians(30), 0.002)["face_angle_deg"] == pytest.approx(30, abs=1)
    assert pick_offset(depth, 100, 120, math.radians(120), 0.002)["face_angle_deg"] == pytest.approx(30, abs=1)
    assert pick_offset(_cube_heightmap((100, 120), 20.0), 100, 120, math.radians(65), 0.002)[
        "face_angle_deg"] == pytest.approx(45, abs=1.5)


def test_pick_offset_beside_an_object_and_far_from_any():
    from romannet.bench.pick_offsets import MAX_GAP_PX, pick_offset

    depth = _cube_heightmap((100, 120), 0.0)
    beside = pick_offset(depth, 100, 120 + 12 + 4, 0.0, 0.002)  # 4 px off the cube's right face
    assert not beside["on_object"] and beside["along_m"] == pytest.approx(0.032, abs=0.0015)
    assert pick_offset(depth, 100, 120 + 12 + MAX_GAP_PX + 3, 0.0, 0.002) is None
    assert pick_offset(np.zeros((224, 224), np.float32), 5, 5, 0.0, 0.002) is None
    with pytest.raises(ValueError, match="outside the heightmap"):
        pick_offset(depth, 224, 0, 0.0, 0.002)


def test_pick_offset_summary_splits_greedy_explored_and_leaves_stacks_out_of_the_medians():
    from romannet.bench.pick_offsets import summarize

    def pick(explored, ok, along, area=25.0, angle=5.0):
        return {"explored": explored, "success": ok, "on_object": True, "along_m": along, "across_m": 0.0,
                "face_angle_deg": angle, "area_cm2": area}

    picks = [pick(False, False, 0.022), pick(False, False, -0.024), pick(False, True, 0.004, angle=35.0),
             pick(True, True, 0.002), pick(False, False, 0.0, area=50.0),  # on a two-cube blob
             {"explored": False, "success": False, "along_m": None}]  # on the empty table
    out = summarize(picks, max_area_cm2=35.0)
    assert (out["picks"], out["succeeded"], out["near_an_object"], out["single_object"]) == (6, 2, 5, 4)
    greedy, explored = out["greedy"], out["explored"]
    assert (greedy["picks"], greedy["succeeded"], greedy["within_1cm_along"]) == (3, 1, 1)
    assert greedy["median_abs_along_cm_failed"] == 2.3 and greedy["median_abs_along_cm_succeeded"] == 0.4
    assert greedy["by_face_angle"]["0-10"] == {"picks": 2, "succeeded": 0}
    assert greedy["by_face_angle"]["30-45"] == {"picks": 1, "succeeded": 1}
    assert greedy["mean_cos4_face_angle_picks"] == pytest.approx(
        (2 * math.cos(math.radians(20)) + math.cos(math.radians(140))) / 3, abs=1e-3)
    assert greedy["mean_cos4_face_angle_succeeded"] == pytest.approx(math.cos(math.radians(140)), abs=1e-3)
    assert explored["mean_cos4_face_angle_picks"] == pytest.approx(math.cos(math.radians(20)), abs=1e-3)
    assert (explored["picks"], explored["succeeded"], explored["median_abs_along_cm_failed"]) == (1, 1, None)


def test_pick_offsets_reads_a_run_from_its_recorded_transitions(tmp_path):
    """End to end on episode files written by the actor's recorder: every pick found, measured against the
    block under it (the scripted successful picks sit on a block, the failed ones far from any)."""
    from _episodes import record_episode

    from romannet.bench.pick_offsets import episode_picks, main

    runs = tmp_path / "run" / "episodes" / "a0"
    runs.mkdir(parents=True)
    record_episode(runs / "ep000000.mcap", steps=6)
    picks = episode_picks(runs / "ep000000.mcap", min_height_m=0.02)
    assert [p["success"] for p in picks] == [True, False, True, False]
    on_block = [p for p in picks if p["success"]]
    assert all(p["on_object"] and abs(p["along_m"]) < 0.014 and p["area_cm2"] > 0 for p in on_block)
    assert all(p["along_m"] is None for p in picks if not p["success"])
    assert main([str(tmp_path / "run"), "--json"]) == 0
    (tmp_path / "junk.mcap").write_bytes(b"not an episode")
    assert main([str(tmp_path / "junk.mcap")]) == 2


def test_phases_split_runs_by_the_number_in_the_episode_file_name(tmp_path):
    from romannet.bench.episode_phases import episode_index, split_phases

    files = [tmp_path / n for n in ("ep000003.mcap", "ep000020.mcap", "ep000100.mcap", "notes.mcap")]
    assert [episode_index(f) for f in files] == [3, 20, 100, -1]
    assert split_phases(files, 0) == {"all": files}
    assert split_phases(files, 20) == {"episodes < 20": [files[0], files[3]], "episodes >= 20": files[1:3]}


def test_cubes_under_an_action_counts_levels_of_the_tallest_point_near_its_pixel():
    from romannet.bench.stack_actions import cubes_under

    hm = np.zeros((40, 40), np.float32)
    hm[5:15, 5:15] = 0.05  # a lone cube
    hm[20:30, 20:30] = 0.101  # a stack of two (a little depth noise)
    assert cubes_under(hm, 10, 10, 0.05, 2) == 1
    assert cubes_under(hm, 25, 25, 0.05, 2) == 2
    assert cubes_under(hm, 35, 35, 0.05, 2) == 0  # bare table
    assert cubes_under(hm, 17, 10, 0.05, 2) == 0 and cubes_under(hm, 17, 10, 0.05, 3) == 1  # beside the cube
    hm[0, 0] = np.nan  # an unknown height reads as the table, not as a tower
    assert cubes_under(hm, 0, 0, 0.05, 1) == 0
    with pytest.raises(ValueError, match="outside"):
        cubes_under(hm, 40, 0, 0.05, 2)
    with pytest.raises(ValueError, match="cube_size_m"):
        cubes_under(hm, 0, 0, 0.0, 2)


def test_stack_actions_summary_counts_picks_off_and_places_on_a_stack_top():
    from romannet.bench.stack_actions import summarize

    def a(primitive, stack, under, success, explored=False):
        return {"primitive": primitive, "stack": stack, "under": under, "success": success, "explored": explored}

    out = summarize([a("pick", 1, 1, True), a("place", 1, 1, True),
                     a("pick", 2, 2, True), a("pick", 2, 2, False), a("pick", 2, 1, True), a("pick", 2, 0, False),
                     a("pick", 2, 2, True, explored=True),  # explored: not in the greedy headline
                     a("place", 2, 2, True), a("place", 2, 1, False), a("place", 3, 1, False)])
    assert out["while a stack of 2+ stood (greedy)"] == {
        "picks": 4, "picks at a stack top": 2, "cubes taken off a stack": 1, "picks elsewhere": 2,
        "picks elsewhere succeeded": 1, "places": 3, "places on a stack top": 1, "places that raised the stack": 1}
    assert out["pick"]["greedy"]["stack 2, on 2"] == {"attempts": 2, "succeeded": 1}
    assert out["pick"]["explored"] == {"stack 2, on 2": {"attempts": 1, "succeeded": 1}}
    assert out["place"]["greedy"]["stack 3, on 1"] == {"attempts": 1, "succeeded": 0}
    # a patch maximum a speckle above the median-filtered stack height is still the stack's top
    speckle = summarize([a("pick", 2, 3, True)])["while a stack of 2+ stood (greedy)"]
    assert (speckle["picks at a stack top"], speckle["cubes taken off a stack"], speckle["picks elsewhere"]) == (1, 1, 0)


def test_stack_actions_reads_a_stacking_run_from_its_recorded_transitions(tmp_path, capsys):
    """End to end on an episode file written by the actor's recorder: a cube stacked, taken off the stack
    and stacked again, a lone cube missed, the table explored."""
    import json

    from _episodes import STACK_SCRIPT, record_stacking_episode

    from romannet.bench.stack_actions import episode_actions, main

    episodes = tmp_path / "run" / "episodes" / "a0"
    episodes.mkdir(parents=True)
    record_stacking_episode(episodes / "ep000000.mcap")
    actions = episode_actions(episodes / "ep000000.mcap", radius_m=0.005)
    assert [(x["primitive"], x["stack"], x["under"], x["success"], x["explored"]) for x in actions] == [
        ("pick", 1, 1, True, False), ("place", 1, 1, True, False), ("pick", 2, 2, True, False),
        ("place", 1, 1, True, False), ("pick", 2, 1, False, False), ("pick", 2, 0, False, True)]
    assert len(actions) == len(STACK_SCRIPT)
    assert main([str(tmp_path / "run"), "--json"]) == 0
    headline = json.loads(capsys.readouterr().out)["all"]["while a stack of 2+ stood (greedy)"]
    assert (headline["picks at a stack top"], headline["cubes taken off a stack"], headline["picks elsewhere"]) == (1, 1, 1)
    (tmp_path / "junk.mcap").write_bytes(b"not an episode")
    assert main([str(tmp_path / "junk.mcap")]) == 2
    with pytest.raises(SystemExit):
        main([str(tmp_path / "run"), "--radius-m", "-1"])


def test_training_counts_blocks_and_last_window_on_hand_made_outcomes():
    from romannet.bench.training_counts import last_rate, per_block

    outcomes = [True, False, True, True, False, False, True]
    assert per_block(outcomes, 3) == [2, 1, 1]  # the last, partial block counts what it has
    assert per_block(outcomes, 50) == [4]
    assert last_rate(outcomes, 4) == 0.5 and last_rate(outcomes, 500) == 4 / 7
    assert per_block([], 50) == [] and last_rate([], 500) is None
    with pytest.raises(ValueError, match="block 0"):
        per_block(outcomes, 0)
    with pytest.raises(ValueError, match="last 0"):
        last_rate(outcomes, 0)


def test_training_counts_order_actors_by_time_and_count_episodes_and_stacks():
    from romannet.bench.training_counts import Recorded, summarize

    a = [Recorded(10, "a0/ep0", "pick", False, True, "", 1), Recorded(30, "a0/ep0", "place", False, True, "done", 4),
         Recorded(50, "a0/ep1", "pick", True, False, "", 1)]
    b = [Recorded(20, "a1/ep0", "pick", False, False, "", 2), Recorded(40, "a1/ep0", "pick", False, True,
                                                                       "consecutive_failures", 3)]
    out = summarize(a + b, block=2, last=3)
    assert out["successful actions per 2"] == [1, 2, 0]  # in end-time order: T F | T T | F
    assert out["action success, last 3"] == 2 / 3
    assert out["pick"] == {"attempts": 4, "succeeded": 2, "rate": 0.5}
    assert out["place"] == {"attempts": 1, "succeeded": 1, "rate": 1.0}
    assert (out["explored actions"], out["episodes"], out["completed"]) == (1, 3, 1)
    assert out["episode ends"] == {"consecutive_failures": 1, "done": 1, "not ended": 1}
    assert out["episodes by highest stack"] == {"1": 1, "3": 1, "4": 1}


def test_training_counts_read_a_stacking_run_from_its_recorded_transitions(tmp_path, capsys):
    import json

    from _episodes import STACK_SCRIPT, record_stacking_episode

    from romannet.bench.training_counts import main

    episodes = tmp_path / "run" / "episodes" / "a0"
    episodes.mkdir(parents=True)
    record_stacking_episode(episodes / "ep000000.mcap")
    assert main([str(tmp_path / "run"), "--json", "--block", "4"]) == 0
    out = json.loads(capsys.readouterr().out)["all"]
    assert out["actions"] == len(STACK_SCRIPT) == 6
    assert out["successful actions per 4"] == [4, 0]  # picked, placed, took off, placed; two misses
    assert (out["pick"]["attempts"], out["pick"]["succeeded"], out["place"]["succeeded"]) == (4, 2, 2)
    assert out["episodes by highest stack"] == {"2": 1}
    assert out["episode ends"] == {"step_limit": 1} and out["completed"] == 0
    (tmp_path / "junk.mcap").write_bytes(b"not an episode")
    assert main([str(tmp_path / "junk.mcap")]) == 2
    with pytest.raises(SystemExit):
        main([str(tmp_path / "run"), "--block", "0"])


def test_lone_cube_centres_and_spread():
    from romannet.bench.angle_probe import lone_cube_centres, spread

    depth = np.zeros((40, 40), np.float32)
    depth[2:7, 2:7] = 0.05  # a lone cube (5 x 5 px of 1 cm: 25 cm^2)
    depth[20:25, 2:7] = 0.10  # a stack of two: the same footprint
    depth[20:25, 20:30] = 0.05  # two touching cubes: twice the footprint, left out
    depth[32, 32] = 0.05  # a speck
    depth[10, 10] = np.nan
    assert lone_cube_centres(depth, 0.01, 0.05) == [(4, 4), (22, 4)]
    files = [Path(f"ep{i:06d}.mcap") for i in range(10)]
    assert spread(files, 3) == [files[0], files[4], files[9]]  # round(4.5) = 4
    assert spread(files, 20) == files and spread(files, 1) == [files[0]]


@pytest.mark.parametrize("head_deg, faces_ok", [(0.0, True), (45.0, False)])
def test_angle_probe_reads_the_heads_angle_at_cubes_and_at_trained_picks(tmp_path, capsys, head_deg, faces_ok):
    """End to end on a recorder-written stacking episode and a learner checkpoint whose pick rotation head
    answers one angle everywhere: square to the (axis-aligned) cubes and equal to the executed picks' 0 deg,
    or on their diagonals; no checkpoint: exit 2."""
    import json

    import torch
    from _episodes import OVERRIDES, STACK_CUBES, record_stacking_episode

    from romannet.bench.angle_probe import main
    from romannet.common.config import load_config
    from romannet.common.configbase import dumps_toml
    from romannet.common.model import encode_angle
    from romannet.learner.checkpoint import save_checkpoint
    from romannet.learner.trainer import Trainer

    run = tmp_path / "run"
    (run / "episodes" / "a0").mkdir(parents=True)
    record_stacking_episode(run / "episodes" / "a0" / "ep000000.mcap")
    assert main([str(run)]) == 2 and "no checkpoint" in capsys.readouterr().err
    cfg = load_config(None, [*OVERRIDES, 'task.kind="stacking"', "model.rotation_harmonics=2"])
    (run / "config.toml").write_text(dumps_toml(cfg))
    trainer = Trainer(cfg.model, cfg.learner, cfg.reward, cfg.task, seed=0)
    head = trainer.model.nets["pick"].rot_head
    with torch.no_grad():
        head.weight.zero_()
        head.bias.copy_(torch.tensor(encode_angle(math.radians(head_deg), "pick", 2)))
    save_checkpoint(trainer, run)
    assert main([str(run), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    cubes = out["lone cubes, first states: head angle to the faces"]
    picks = out["successful greedy picks: head angle to the executed angle (mod 90 deg)"]
    assert out["successful explored picks: head angle to the executed angle (mod 90 deg)"]["count"] == 0
    assert out["episodes"] == 1 and cubes["count"] == len(STACK_CUBES) and picks["count"] == 2
    if faces_ok:
        assert cubes["mean_cos4"] == pytest.approx(1.0) and cubes["within_10deg"] == len(STACK_CUBES)
        assert picks["median_deg"] == pytest.approx(0.0, abs=0.1) and picks["within_10deg"] == 2
    else:
        assert cubes["mean_cos4"] == pytest.approx(-1.0) and cubes["beyond_30deg"] == len(STACK_CUBES)
        assert picks["median_deg"] == pytest.approx(45.0, abs=0.1) and picks["beyond_30deg"] == 2
