"""Why a simulated pick failed (actor/sim/grasp_check.py): ground truth in each pick's step info, counted by
`romannet eval`."""

from __future__ import annotations

import dataclasses
import math

import pybullet as p
import pytest

from romannet.actor.sim.env import SimEnv
from romannet.actor.sim.grasp_check import CAUSES, ClosedGrasp, tilt_deg
from romannet.actor.sim.objects import ObjectSpec, spawn_object
from romannet.common.action import Action, position_to_pixel
from romannet.common.config import load_config
from romannet.evaluate.metrics import RunLog, StepLog, failed_picks, summarize
from romannet.evaluate.protocol import run_from_json, run_to_json
from romannet.evaluate.report import build_report, markdown

pytestmark = pytest.mark.timeout(120)

SMALL = ["workspace.resolution_m=0.007", "camera.width_px=160", "camera.height_px=120", "camera.fx_px=154.655",
         "camera.fy_px=154.655", "camera.cx_px=80.0", "camera.cy_px=60.0", 'task.kind="clutter"',
         'sim.robot="gripper"']


def test_the_cause_follows_the_gap_and_the_fingers_contacts() -> None:
    assert ClosedGrasp(0.03, body=7, tilt_deg=0.0, offset_along_m=0.0, offset_across_m=0.0).cause(True, 0.002) == "held"
    assert ClosedGrasp(0.001).cause(False, 0.002) == "closed_on_nothing"
    assert ClosedGrasp(0.03).cause(False, 0.002) == "fingers_on_two_objects"  # no one body between both
    lost = ClosedGrasp(0.03, body=7, tilt_deg=20.0, offset_along_m=0.001, offset_across_m=-0.02)
    assert lost.cause(False, 0.002) == "lost_in_lift"
    assert lost.info(False, 0.002) == {"grasp": "lost_in_lift", "grasp_tilt_deg": 20.0,
                                       "grasp_offset_along_m": 0.001, "grasp_offset_across_m": -0.02}
    assert ClosedGrasp(0.001).info(False, 0.002) == {"grasp": "closed_on_nothing"}  # no NaN in a step record
    assert set(CAUSES) == {"closed_on_nothing", "fingers_on_two_objects", "lost_in_lift"}


def test_tilt_is_zero_on_any_face_and_the_angle_off_it_otherwise() -> None:
    assert tilt_deg((0.0, 0.0, 0.0, 1.0)) == pytest.approx(0.0, abs=1e-6)
    assert tilt_deg(p.getQuaternionFromEuler([0.0, 0.0, 1.0])) == pytest.approx(0.0, abs=1e-4)  # a yaw only
    assert tilt_deg(p.getQuaternionFromEuler([math.radians(30), 0.0, 0.0])) == pytest.approx(30.0, abs=1e-4)
    assert tilt_deg(p.getQuaternionFromEuler([math.pi / 2, 0.0, 0.0])) == pytest.approx(0.0, abs=1e-4)  # on its side


def _lone_block_pick(shape: str, offset_across_m: float, pick_over_table: bool = False) -> dict:
    """A lone block at the workspace centre, picked across its x axis (its long side for the pillar lying
    down) offset_across_m off its centre along that side; the pick's step info."""
    env = SimEnv.from_config(load_config(None, SMALL))
    with env:
        env.task_def = dataclasses.replace(env.task_def, num_objects=0)
        env.reset(0)
        x, y = (env.ws.x_min_m + env.ws.x_max_m) / 2, (env.ws.y_min_m + env.ws.y_max_m) / 2
        body = spawn_object(env.scene.client, ObjectSpec(shape, (0.8, 0.2, 0.2, 1.0), (x, y, 0.03)))
        env.scene.add_object(body)
        env.scene.settle(240)
        env.observe_start()
        px, py = (x + 0.12, y) if pick_over_table else (x + offset_across_m, y)
        row, col = position_to_pixel(px, py, env.ws)
        return env.step(Action("pick", row, col, math.pi / 2, 1.0)).info  # closing along y, across x


def test_a_centred_pick_of_a_lone_block_is_held_with_its_offsets_and_tilt_recorded() -> None:
    info = _lone_block_pick("cube", 0.0)
    assert info["grasp"] == "held"
    assert abs(info["grasp_offset_across_m"]) < 0.008 and abs(info["grasp_offset_along_m"]) < 0.008
    assert info["grasp_tilt_deg"] < 5.0


def test_a_pick_over_the_bare_table_closes_on_nothing() -> None:
    info = _lone_block_pick("cube", 0.0, pick_over_table=True)
    assert info["grasp"] == "closed_on_nothing" and "grasp_tilt_deg" not in info


def test_eval_counts_failed_picks_by_cause_and_keeps_them_through_its_journal() -> None:
    runs = [RunLog("blocks-30", 1, 3, "done", (StepLog("pick", False, "lost_in_lift"), StepLog("push", False),
                                               StepLog("pick", True), StepLog("pick", False, "closed_on_nothing"),
                                               StepLog("pick", False, "lost_in_lift"))),
            RunLog("blocks-30", 2, 3, "done", (StepLog("pick", False, "unreachable"), StepLog("pick", False)))]
    assert failed_picks(runs) == {"lost_in_lift": 2, "closed_on_nothing": 1, "unreachable": 1, "unknown": 1}
    assert [run_from_json(run_to_json(r)) for r in runs] == runs
    old = run_to_json(runs[0]) | {"steps": ["pick:0", "push:1"]}  # a journal written before causes existed
    assert run_from_json(old).steps == (StepLog("pick", False), StepLog("push", True))
    assert summarize(runs).failed_picks == failed_picks(runs)
    header = {"task": "clutter", "protocol": "frozen", "policy": "oracle", "runs_per_case": 2, "base_seed": 1,
              "workers": 1, "wall_s": 1.0, "machine": "test"}
    assert "Failed picks by cause (all runs): lost in lift 2, closed on nothing 1, unreachable 1, unknown 1." \
        in markdown(build_report(runs, header))
