"""`romannet eval --policy oracle|random`: the simulator's ceiling and floor through the same protocol and
report as a checkpoint, without one; and the one-line answers for a run with no checkpoint yet.

Through the CLI entry point in this process (--workers 1), on real PyBullet scenes kept small (64x64
heightmaps, the floating gripper, three cubes) so each evaluation takes seconds."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np
import pytest

from romannet.cli import main
from romannet.common.config import load_config
from romannet.common.configbase import write_toml
from romannet.common.episode_rules import refusal
from romannet.common.exploration import ANGLE_RANGE_RAD
from romannet.evaluate.policies import random_action
from romannet.learner.checkpoint import save_checkpoint
from romannet.learner.trainer import Trainer

pytestmark = pytest.mark.timeout(120)

SMALL = ["model.channels=4", "model.residual_blocks=1", "model.num_threads=1", "learner.num_threads=1",
         'learner.precision="fp32"', "workspace.resolution_m=0.007", 'sim.robot="gripper"', "task.use_push=false",
         "sim.num_stacking_cubes=3", "camera.width_px=160", "camera.height_px=120", "camera.fx_px=154.655",
         "camera.fy_px=154.655", "camera.cx_px=80.0", "camera.cy_px=60.0"]
SETS = [arg for s in SMALL for arg in ("--set", s)]


def _eval(tmp_path: Path, policy: str, *extra: str) -> dict:
    out = tmp_path / policy
    code = main(["eval", "--policy", policy, "--task", "stacking", "--goal-height", "2", "--runs", "2",
                 "--workers", "1", "--out", str(out), *SETS, *extra])
    assert code == 0
    report = json.loads((out / "report.json").read_text())
    assert (out / "runs.jsonl").read_text().count("\n") == 2 and (out / "report.png").stat().st_size > 1000
    assert f"policy `{policy}`" in (out / "report.md").read_text()
    return report


def test_random_actions_are_always_valid_and_seeded() -> None:
    for holding, primitives in ((False, ("push", "pick", "place")), (False, ("pick", "place")),
                                (True, ("push", "pick", "place"))):
        rng = np.random.default_rng(7)
        actions = [random_action(holding, primitives, (64, 48), rng) for _ in range(200)]
        assert all(refusal(a, primitives, holding, (64, 48)) == "" for a in actions)
        assert all(ANGLE_RANGE_RAD[a.primitive][0] <= a.angle_rad <= ANGLE_RANGE_RAD[a.primitive][1]
                   for a in actions)
        assert {a.primitive for a in actions} == ({"place"} if holding else set(primitives) - {"place"})
        assert max(a.row for a in actions) > 50 and max(a.col for a in actions) > 38  # the whole heightmap
    again = np.random.default_rng(7)
    assert random_action(False, ("push", "pick", "place"), (64, 48), again) == \
        random_action(False, ("push", "pick", "place"), (64, 48), np.random.default_rng(7))


def test_random_picks_under_the_clearance_rule_are_drawn_among_the_clear_pairs() -> None:
    clear = np.zeros((4, 64, 48), bool)
    clear[1, 10, 20] = clear[3, 40, 5] = True
    rng = np.random.default_rng(3)
    picks = [a for a in (random_action(False, ("push", "pick"), (64, 48), rng, clear) for _ in range(200))
             if a.primitive == "pick"]
    assert {(a.row, a.col, round(a.angle_rad, 6)) for a in picks} == {(10, 20, round(np.pi / 4, 6)),
                                                                     (40, 5, round(3 * np.pi / 4, 6))}
    nothing = np.zeros_like(clear)  # no clear pick anywhere: anywhere, as without the rule
    anywhere = [random_action(False, ("pick",), (64, 48), rng, nothing) for _ in range(50)]
    assert len({(a.row, a.col) for a in anywhere}) > 40


def test_oracle_and_random_policies_run_the_protocol_without_a_checkpoint(tmp_path: Path) -> None:
    oracle = _eval(tmp_path, "oracle")
    random = _eval(tmp_path, "random", "--protocol", "paper")
    for report, policy in ((oracle, "oracle"), (random, "random")):
        assert report["policy"] == policy and report["checkpoint"] is None and report["protocol"] == "frozen"
        assert report["task"] == "stacking" and list(report["cases"]) == ["h2"] and not report["interrupted"]
        assert [r["seed"] for r in report["runs"]] == [100000, 100001]  # the seeds a checkpoint meets
    assert "paper applies to a net only" in random["protocol_note"]
    assert oracle["overall"]["completion_rate"] == 1.0 and oracle["overall"]["pick_success_rate"] == 1.0
    assert oracle["overall"]["action_efficiency"] == 1.0  # pick, place: the ideal two actions
    assert random["overall"]["completion_rate"] <= oracle["overall"]["completion_rate"]
    assert random["overall"]["pick_success_all_runs"] < oracle["overall"]["pick_success_all_runs"]


def test_a_scripted_policy_without_a_config_needs_the_task(tmp_path: Path, capsys) -> None:
    code = main(["eval", "--policy", "oracle", "--runs", "1", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "pass --task" in err[0]
    assert main(["eval", "--runs", "1"]) == 2  # a net needs a checkpoint
    assert "--policy oracle|random" in capsys.readouterr().err


def test_a_run_without_a_checkpoint_yet_says_so_in_one_line(tmp_path: Path, capsys) -> None:
    run_dir = tmp_path / "fresh"
    write_toml(load_config(None, [*SMALL, "learner.checkpoint_every_updates=250"]), run_dir / "config.toml")
    (run_dir / "checkpoints").mkdir()
    assert main(["eval", str(run_dir), "--runs", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in err[0]
    assert f"{run_dir} has no checkpoint yet: the learner writes one every 250 updates" in err[0]


def test_a_checkpoint_at_update_0_is_evaluated_with_a_warning(tmp_path: Path, caplog) -> None:
    run_dir = tmp_path / "untrained"
    cfg = load_config(None, [*SMALL, 'task.kind="stacking"', "task.goal_stack_height=2"])
    write_toml(cfg, run_dir / "config.toml")
    save_checkpoint(Trainer(cfg.model, cfg.learner, cfg.reward, cfg.task, exploration_cfg=cfg.exploration), run_dir)
    with caplog.at_level(logging.WARNING, logger="romannet.eval"):
        code = main(["eval", str(run_dir), "--runs", "1", "--workers", "1", "--max-steps", "2", "--protocol",
                     "frozen", "--out", str(tmp_path / "out")])
    assert code == 0
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert len(warnings) == 1 and "update 0: an untrained net" in warnings[0]
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["policy"] == "net" and report["updates"] == 0 and len(report["runs"]) == 1
