"""`romannet eval` refuses a task or flags that do not fit the checkpoint (one line; --force for the task) and
says so, in its log and its report, when the net is untrained or forced onto a task it did not learn."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from test_eval import SETS, make_run

from romannet.evaluate.cli import foreign_task_flags, task_misfit

pytestmark = pytest.mark.timeout(240)

ROMANNET = str(Path(sys.executable).parent / "romannet")
CLUTTER = [*SETS[:7], *SETS[-6:], 'task.kind="clutter"', "task.use_push=true", "sim.num_objects=3"]
QUICK = ["--runs", "1", "--max-steps", "2", "--workers", "1", "--protocol", "frozen"]


def romannet(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["nice", "-n", "19", ROMANNET, *args], capture_output=True, text=True, timeout=200)


def error_lines(stderr: str) -> list[str]:
    return [ln for ln in stderr.splitlines() if not ln.startswith("pybullet build time")]


def test_flags_of_another_task_are_named() -> None:
    assert foreign_task_flags("clutter", {"--objects", "--object-set"}) is None
    assert foreign_task_flags("stacking", set()) is None
    assert foreign_task_flags("stacking", {"--objects"}) == (
        "--objects is a clutter flag: stacking scenes would ignore it (stacking takes --goal-height; or pass "
        "--task clutter)")
    assert foreign_task_flags("clutter", {"--goal-height", "--cases"}) == (
        "--goal-height (stacking), --cases (arrangement) are flags of other tasks: clutter scenes would ignore "
        "them (clutter takes --objects and --object-set)")


def test_a_task_fits_a_net_trained_for_it_or_its_family() -> None:
    clutter = {"kind": "clutter", "use_push": True}
    assert task_misfit(clutter, "clutter", True) is None
    assert task_misfit(clutter, "arrangement", True) is None  # the paper tests clutter nets on arrangements
    assert task_misfit(clutter, "stacking", True) == "trained on clutter, tested on stacking"
    assert task_misfit({"kind": "stacking", "use_push": False}, "clutter", True) == \
        "trained on stacking, tested on clutter"
    assert task_misfit(clutter, "clutter", False) == \
        "trained with pushes, tested without (task.use_push = false)"
    assert task_misfit(None, "stacking", True) is None  # a checkpoint that does not say: nothing to hold to


def test_eval_refuses_what_does_not_fit_in_one_line(tmp_path: Path) -> None:
    run_dir = make_run(tmp_path, CLUTTER, name="clutter")
    cases = [
        (["--task", "stacking", "--objects", "3"], "--objects is a clutter flag: stacking scenes would ignore it"),
        (["--task", "stacking"], "does not fit this evaluation: trained on clutter, tested on stacking (pass --force"),
        (["--task", "stacking", "--force", "--objects", "3"], "--objects is a clutter flag"),
        (["--goal-height", "3"], "--goal-height is a stacking flag: clutter scenes would ignore it"),
        (["--set", "task.use_push=false"], "trained with pushes, tested without (task.use_push = false)"),
    ]
    for args, expected in cases:
        proc = romannet("eval", str(run_dir), *args, *QUICK, "--out", str(tmp_path / "never"))
        lines = error_lines(proc.stderr)
        assert proc.returncode == 2 and len(lines) == 1, (args, proc.stderr)
        assert lines[0].startswith("romannet eval: error: ") and expected in lines[0], (args, lines[0])
    assert not (tmp_path / "never").exists()


def test_forced_and_untrained_evaluations_say_so_in_the_log_and_the_report(tmp_path: Path) -> None:
    run_dir = make_run(tmp_path, CLUTTER, name="clutter")  # an update-0 checkpoint
    out = tmp_path / "forced"
    proc = romannet("eval", str(run_dir), "--task", "stacking", "--goal-height", "2", "--force", *QUICK,
                    "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    assert "WARNING romannet.eval: " in proc.stderr and "trained on clutter, tested on stacking (--force)" in proc.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["task"] == "stacking" and report["warnings"] == [
        "the net was trained on clutter, tested on stacking (--force)",
        "update 0: an untrained net, so these numbers say nothing about learning"]
    md = (out / "report.md").read_text()
    assert "**Warning**: update 0: an untrained net" in md and "**Warning**: update 0" in proc.stdout


def test_the_sweep_still_reads_evals_defaults() -> None:
    from romannet.sweep.cli import _eval_parser_facts

    defaults, offered = _eval_parser_facts()
    assert (defaults["objects"], defaults["object_set"]) == (30, "blocks") and {"oracle", "random"} <= offered
