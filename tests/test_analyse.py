"""`romannet analyse`: the run diagnostics (romannet/analyse/) on hand-made heightmaps and outcomes, and each
sub-command end to end on episode files written by the actor's recorder (tests/_episodes.py)."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from _episodes import SIDE_PX, config

from romannet.actor.recorder import EpisodeRecorder, step_record
from romannet.analyse.cli import DIAGNOSTICS
from romannet.cli import main
from romannet.common.action import Action
from romannet.common.configbase import dumps_toml
from romannet.common.wire import TransitionMsg, encode_transition


def analyse(*args: str) -> int:
    """`romannet analyse ARGS` in this process; its exit code."""
    return main(["analyse", *args])


def test_every_diagnostic_has_help_with_an_example(capsys):
    assert set(DIAGNOSTICS) == {"pick-offsets", "stack-actions", "repeated-failures", "training-counts",
                                "angle-probe", "grasp-failures"}
    for what in DIAGNOSTICS:
        with pytest.raises(SystemExit) as done:
            analyse(what, "--help")
        out = capsys.readouterr().out
        assert done.value.code == 0 and "RUN" in out and "--json" in out
        assert f"example:\n  romannet analyse {what} " in out


@pytest.mark.parametrize("what", sorted(DIAGNOSTICS))
def test_a_missing_run_is_one_line_and_exit_2(tmp_path, capsys, what):
    assert analyse(what, str(tmp_path / "no-such-run")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"romannet analyse {what}: error: ")
    assert "no-such-run" in err[0]


def test_the_installed_command_names_a_missing_run_without_a_traceback(tmp_path):
    done = subprocess.run([sys.executable, "-m", "romannet.cli", "analyse", "training-counts",
                           str(tmp_path / "gone")], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert done.stderr.strip() == f"romannet analyse training-counts: error: {tmp_path / 'gone'}: no such file or directory"


def test_repeated_failure_count_on_hand_made_step_records():
    from romannet.analyse.repeated_failures import count_repeats

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



# (primitive, row, col, success, explored, weights version) of each step of an episode on a still scene.
REPEATS_SCRIPT = [("pick", 5, 5, False, False, 1), ("pick", 5, 5, False, False, 1),  # greedy repeat, same weights
                  ("pick", 5, 5, False, False, 2),  # greedy repeat on new weights
                  ("pick", 5, 5, False, True, 2),  # explored: not a greedy choice
                  ("pick", 7, 5, True, False, 2),  # greedy after a failure, another pixel
                  ("pick", 7, 5, False, False, 2)]  # after a success: not counted


def record_script(path: Path, script: list[tuple[str, int, int, bool, bool, int]],
                  infos: list[dict] | None = None) -> None:
    """An episode of the script's actions on an empty scene, recorded as the actor records one: each /step
    record is recorder.step_record of its transition (with infos[i] as the environment's info)."""
    color, depth = np.full((SIDE_PX, SIDE_PX, 3), 90, np.uint8), np.zeros((SIDE_PX, SIDE_PX), np.float32)
    rec = EpisodeRecorder(path, {"run_id": "repeats", "actor_id": "a0", "episode_id": path.stem, "task": "clutter",
                                 "seed": 0, "weights_version_start": 0}, dumps_toml(config("repeats")),
                          chunk_bytes=64 * 1024)
    try:
        for step, (primitive, row, col, success, explored, version) in enumerate(script):
            start_ns = 1_700_000_000_000_000_000 + step * 10**9
            last = step == len(script) - 1
            msg = TransitionMsg(
                actor_id="a0", episode_id=path.stem, step=step, start_ns=start_ns, end_ns=start_ns + 10**8,
                task="clutter", color_before=color, depth_before=depth, color_after=color, depth_after=depth,
                action=Action(primitive, row, col, 0.0, 0.5, explored=explored), success=success,
                progress_before=0.0, progress_after=0.0, reward=0.0, done=last,
                done_reason="step_limit" if last else "", holding_before=False, holding_after=False,
                policy_version=version, explore_rate=0.1, initial_priority=None, sim_seed=0)
            info = infos[step] if infos else None
            rec.write_step(encode_transition(msg), step_record(msg, [0.0, 0.0, 0.0], info=info), start_ns + 10**8)
    finally:
        rec.close({"done_reason": "step_limit", "steps": len(script), "efficiency": None,
                   "weights_version_end": 2})


def test_repeated_failures_reads_a_run_from_its_recorded_steps(tmp_path, capsys):
    """End to end on two recorder-written episodes, split into phases by episode number; a /step record
    without the fields the count reads names its file (exit 2)."""
    episodes = tmp_path / "run" / "episodes" / "a0"
    record_script(episodes / "ep000000.mcap", REPEATS_SCRIPT)
    record_script(episodes / "ep000001.mcap", [("push", 1, 1, False, False, 3), ("push", 1, 1, False, False, 3)])
    assert analyse("repeated-failures", str(tmp_path / "run"), "--json") == 0
    both = json.loads(capsys.readouterr().out)["all"]
    assert (both["episodes"], both["actions"], both["pick_success"]) == (2, 8, 1 / 6)
    assert (both["greedy_after_failure"], both["repeats"], both["repeats_on_same_weights"]) == (4, 3, 2)
    assert analyse("repeated-failures", str(tmp_path / "run"), "--split", "1", "--json") == 0
    phases = json.loads(capsys.readouterr().out)
    assert phases["episodes < 1"]["repeats"] == 2 and phases["episodes >= 1"]["repeats"] == 1
    assert analyse("repeated-failures", str(tmp_path / "run"), "--split", "1") == 0
    assert capsys.readouterr().out.startswith("episodes < 1: {'episodes': 1, 'actions': 6,")

    from _episodes import record_episode  # its hand-written /step records lack the pixel and weights version

    record_episode(tmp_path / "old" / "ep000000.mcap", steps=3)
    assert analyse("repeated-failures", str(tmp_path / "old")) == 2
    assert "a /step record lacks row, col, explored, weights_version" in capsys.readouterr().err


def _grasp(cause: str, tilt: float | None = None, across_m: float = 0.0) -> dict:
    """A simulated pick's step info (actor/sim/grasp_check.py)."""
    info: dict = {"grasp": cause}
    if tilt is not None:
        info.update(grasp_tilt_deg=tilt, grasp_offset_along_m=0.0, grasp_offset_across_m=across_m)
    return info


def test_grasp_failures_reads_causes_tilt_and_offset_from_recorded_steps(tmp_path, capsys):
    script = [("pick", 5, 5, True, False, 1), ("pick", 5, 6, False, False, 1), ("pick", 5, 7, False, True, 1),
              ("pick", 5, 8, False, False, 1), ("push", 1, 1, True, False, 1), ("pick", 5, 9, False, False, 1)]
    infos = [_grasp("held", 2.0, 0.001), _grasp("lost_in_lift", 20.0, -0.02), _grasp("closed_on_nothing"),
             _grasp("lost_in_lift", 3.0, 0.04), {"seed": 0}, {"seed": 0}]  # the last: a pick refused, no grasp
    record_script(tmp_path / "run" / "episodes" / "a0" / "ep000000.mcap", script, infos)
    assert analyse("grasp-failures", str(tmp_path / "run"), "--json") == 0
    out = json.loads(capsys.readouterr().out)["all"]
    assert (out["picks"], out["picks_without_grasp"], out["failed"]) == (5, 1, 4)
    assert out["failed_by_cause"] == {"lost_in_lift": 2, "closed_on_nothing": 1}
    assert out["by_tilt"] == {"[0, 5) deg": {"picks": 2, "failed": 1, "failed_share": 0.5},
                              ">= 15 deg": {"picks": 1, "failed": 1, "failed_share": 1.0}}
    assert out["by_offset_across"] == {"[0, 0.5) cm": {"picks": 1, "failed": 0, "failed_share": 0.0},
                                       "[1.5, 3) cm": {"picks": 1, "failed": 1, "failed_share": 1.0},
                                       ">= 3 cm": {"picks": 1, "failed": 1, "failed_share": 1.0}}


def _cube_heightmap(centre_rc: tuple[float, float], yaw_deg: float, side_px: int = 25) -> np.ndarray:
    """A 224 x 224 heightmap with one 5 cm-high square of `side_px` pixels, turned by yaw_deg."""
    depth = np.zeros((224, 224), np.float32)
    box = cv2.boxPoints(((centre_rc[1], centre_rc[0]), (side_px, side_px), yaw_deg))
    cv2.fillPoly(depth, [np.round(box).astype(np.int32)], 0.05)
    return depth


def test_pick_offset_measures_along_and_across_the_closing_axis():
    from romannet.analyse.pick_offsets import pick_offset

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
    from romannet.analyse.pick_offsets import MAX_GAP_PX, pick_offset

    depth = _cube_heightmap((100, 120), 0.0)
    beside = pick_offset(depth, 100, 120 + 12 + 4, 0.0, 0.002)  # 4 px off the cube's right face
    assert not beside["on_object"] and beside["along_m"] == pytest.approx(0.032, abs=0.0015)
    assert pick_offset(depth, 100, 120 + 12 + MAX_GAP_PX + 3, 0.0, 0.002) is None
    assert pick_offset(np.zeros((224, 224), np.float32), 5, 5, 0.0, 0.002) is None
    with pytest.raises(ValueError, match="outside the heightmap"):
        pick_offset(depth, 224, 0, 0.0, 0.002)


def test_pick_offset_summary_splits_greedy_explored_and_leaves_stacks_out_of_the_medians():
    from romannet.analyse.pick_offsets import summarize

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

    from romannet.analyse.pick_offsets import episode_picks

    runs = tmp_path / "run" / "episodes" / "a0"
    runs.mkdir(parents=True)
    record_episode(runs / "ep000000.mcap", steps=6)
    picks = episode_picks(runs / "ep000000.mcap", min_height_m=0.02)
    assert [p["success"] for p in picks] == [True, False, True, False]
    on_block = [p for p in picks if p["success"]]
    assert all(p["on_object"] and abs(p["along_m"]) < 0.014 and p["area_cm2"] > 0 for p in on_block)
    assert all(p["along_m"] is None for p in picks if not p["success"])
    assert analyse("pick-offsets", str(tmp_path / "run"), "--json") == 0
    (tmp_path / "junk.mcap").write_bytes(b"not an episode")
    assert analyse("pick-offsets", str(tmp_path / "junk.mcap")) == 2


def test_phases_split_runs_by_the_number_in_the_episode_file_name(tmp_path):
    from romannet.analyse.phases import episode_index, split_phases

    files = [tmp_path / n for n in ("ep000003.mcap", "ep000020.mcap", "ep000100.mcap", "notes.mcap")]
    assert [episode_index(f) for f in files] == [3, 20, 100, -1]
    assert split_phases(files, 0) == {"all": files}
    assert split_phases(files, 20) == {"episodes < 20": [files[0], files[3]], "episodes >= 20": files[1:3]}


def test_cubes_under_an_action_counts_levels_of_the_tallest_point_near_its_pixel():
    from romannet.analyse.stack_actions import cubes_under

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


def test_place_geometry_measures_the_offset_from_a_top_and_the_distance_to_a_taller_stack():
    from romannet.analyse.stack_actions import distance_to_height_px, top_offset_px

    hm = np.zeros((60, 60), np.float32)
    hm[10:20, 10:20] = 0.05  # a lone cube, centre (14.5, 14.5)
    hm[40:50, 40:50] = 0.10  # a stack of two, centre (44.5, 44.5)
    assert top_offset_px(hm, 14, 14, 1, 0.05) == pytest.approx(np.hypot(0.5, 0.5))
    assert top_offset_px(hm, 44, 47, 2, 0.05) == pytest.approx(np.hypot(0.5, 2.5))
    assert top_offset_px(hm, 5, 5, 1, 0.05) == pytest.approx(np.hypot(9.5, 9.5))  # beside the lone cube
    assert top_offset_px(hm, 14, 14, 3, 0.05) is None and top_offset_px(hm, 14, 14, 0, 0.05) is None
    # as stack_height reads it: the median filter rounds the stack's corner, so its nearest pixel is (41, 41)
    assert distance_to_height_px(hm, 14, 14, 2, 0.05) == pytest.approx(np.hypot(27, 27))
    assert distance_to_height_px(hm, 45, 45, 2, 0.05) == 0.0
    assert distance_to_height_px(hm, 14, 14, 3, 0.05) is None


def test_stack_actions_summary_gives_place_offsets_and_places_onto_a_lower_cube():
    from romannet.analyse.stack_actions import summarize

    def place(stack, under, success, off, far=None):
        return {"primitive": "place", "stack": stack, "under": under, "success": success, "explored": False,
                "top_offset_cm": off, "to_stack_cm": far}

    out = summarize([place(2, 2, True, 1.0), place(2, 2, True, 3.0), place(2, 2, False, 4.0),
                     place(2, 1, False, 0.5, far=12.0), place(3, 1, False, 0.7, far=6.0), place(1, 0, False, None)])
    assert out["greedy places: offset from the centre of the top under them (cm)"]["stack 2, on 2"] == {
        "succeeded": {"places": 2, "median cm": 2.0}, "failed": {"places": 1, "median cm": 4.0}}
    assert out["greedy places onto a lower cube while a stack of 2+ stood"] == {
        "places": 2, "median distance to the stack (cm)": 9.0, "share beyond 10 cm": 0.5}


def test_stack_actions_summary_counts_picks_off_and_places_on_a_stack_top():
    from romannet.analyse.stack_actions import summarize

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

    from romannet.analyse.stack_actions import episode_actions

    episodes = tmp_path / "run" / "episodes" / "a0"
    episodes.mkdir(parents=True)
    record_stacking_episode(episodes / "ep000000.mcap")
    actions = episode_actions(episodes / "ep000000.mcap", radius_m=0.005)
    assert [(x["primitive"], x["stack"], x["under"], x["success"], x["explored"]) for x in actions] == [
        ("pick", 1, 1, True, False), ("place", 1, 1, True, False), ("pick", 2, 2, True, False),
        ("place", 1, 1, True, False), ("pick", 2, 1, False, False), ("pick", 2, 0, False, True)]
    assert len(actions) == len(STACK_SCRIPT)
    places = [x for x in actions if x["primitive"] == "place"]
    assert all(x["top_offset_cm"] is not None and 0 <= x["top_offset_cm"] < 5 for x in places)  # onto a cube
    assert all(x["to_stack_cm"] is None for x in places)  # none went onto a lower cube beside a taller stack
    assert analyse("stack-actions", str(tmp_path / "run"), "--json") == 0
    headline = json.loads(capsys.readouterr().out)["all"]["while a stack of 2+ stood (greedy)"]
    assert (headline["picks at a stack top"], headline["cubes taken off a stack"], headline["picks elsewhere"]) == (1, 1, 1)
    (tmp_path / "junk.mcap").write_bytes(b"not an episode")
    assert analyse("stack-actions", str(tmp_path / "junk.mcap")) == 2
    with pytest.raises(SystemExit):
        analyse("stack-actions", str(tmp_path / "run"), "--radius-m", "-1")


def test_training_counts_blocks_and_last_window_on_hand_made_outcomes():
    from romannet.analyse.training_counts import last_rate, per_block

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
    from romannet.analyse.training_counts import Recorded, summarize

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

    episodes = tmp_path / "run" / "episodes" / "a0"
    episodes.mkdir(parents=True)
    record_stacking_episode(episodes / "ep000000.mcap")
    assert analyse("training-counts", str(tmp_path / "run"), "--json", "--block", "4") == 0
    out = json.loads(capsys.readouterr().out)["all"]
    assert out["actions"] == len(STACK_SCRIPT) == 6
    assert out["successful actions per 4"] == [4, 0]  # picked, placed, took off, placed; two misses
    assert (out["pick"]["attempts"], out["pick"]["succeeded"], out["place"]["succeeded"]) == (4, 2, 2)
    assert out["episodes by highest stack"] == {"2": 1}
    assert out["episode ends"] == {"step_limit": 1} and out["completed"] == 0
    (tmp_path / "junk.mcap").write_bytes(b"not an episode")
    assert analyse("training-counts", str(tmp_path / "junk.mcap")) == 2
    with pytest.raises(SystemExit):
        analyse("training-counts", str(tmp_path / "run"), "--block", "0")


def test_lone_cube_centres_and_spread():
    from romannet.analyse.angle_probe import lone_cube_centres, spread

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

    from romannet.common.config import load_config
    from romannet.common.configbase import dumps_toml
    from romannet.common.model import encode_angle
    from romannet.learner.checkpoint import save_checkpoint
    from romannet.learner.trainer import Trainer

    run = tmp_path / "run"
    (run / "episodes" / "a0").mkdir(parents=True)
    record_stacking_episode(run / "episodes" / "a0" / "ep000000.mcap")
    assert analyse("angle-probe", str(run)) == 2 and "no checkpoint" in capsys.readouterr().err
    cfg = load_config(None, [*OVERRIDES, 'task.kind="stacking"', "model.rotation_harmonics=2"])
    (run / "config.toml").write_text(dumps_toml(cfg))
    trainer = Trainer(cfg.model, cfg.learner, cfg.reward, cfg.task, seed=0)
    head = trainer.model.nets["pick"].rot_head
    with torch.no_grad():
        head.weight.zero_()
        head.bias.copy_(torch.tensor(encode_angle(math.radians(head_deg), "pick", 2)))
    save_checkpoint(trainer, run)
    assert analyse("angle-probe", str(run), "--json") == 0
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
