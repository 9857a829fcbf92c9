"""`romannet sweep` end to end: real `romannet up` and `romannet eval` subprocesses (PyBullet, Zenoh on
loopback), interrupted with SIGINT mid-run and resumed, then run again to check nothing is redone; and bad
input that stops at once with one line, before anything is written.

One tiny stacking variant (the floating gripper, 64x64 heightmaps, a 4-channel net, a small camera) and one
seed keep the end-to-end test near a minute on a shared 2-core box; every wait is bounded.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from romannet.cli import main
from romannet.sweep.execute import Pace, eta_s, format_duration
from romannet.sweep.plan import first_difference
from romannet.sweep.state import run_actions

REPO = Path(__file__).resolve().parent.parent
RECIPE = REPO / "configs" / "experiments" / "stacking.toml"
TINY = ["model.channels=4", "model.residual_blocks=1", "model.num_threads=1", "learner.num_threads=1",
        'learner.precision="fp32"', "learner.max_grad_norm=10", "learner.batch_size=2", "learner.min_replay_size=4",
        "replay.min_size_to_sample=2", 'sim.robot="gripper"', "workspace.resolution_m=0.007",
        "task.goal_stack_height=2", "sim.num_stacking_cubes=3", "camera.width_px=160", "camera.height_px=120",
        "camera.fx_px=154.655", "camera.fy_px=154.655", "camera.cx_px=80.0", "camera.cy_px=60.0"]
MAX_ACTIONS = 60  # the gripper makes ~10 actions/s here: room to interrupt the run before its end


def sweep_argv(out: Path, *extra: str) -> list[str]:
    sets = [arg for s in TINY for arg in ("--set", s)]
    return [sys.executable, "-m", "romannet.cli", "sweep", "--config", str(RECIPE), *sets, "--seeds", "1",
            "--max-actions", str(MAX_ACTIONS), "--eval-runs", "2", "--eval-max-steps", "4", "--eval-workers", "1",
            "--policies", "oracle", "random", "--progress-every", "5", "--out", str(out), *extra]


def romannet(*args: str, timeout_s: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "romannet.cli", *args], capture_output=True, text=True,
                          timeout=timeout_s, cwd=REPO)


def files_state(root: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(root)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(root.rglob("*"))
            if p.is_file()}


def test_eta_comes_from_the_rates_so_far() -> None:
    assert eta_s(Pace(actions_left=100, actions_gained=0, training_s=5.0, evals_left=0)) is None
    assert eta_s(Pace(actions_left=100, actions_gained=50, training_s=25.0, evals_left=0)) == pytest.approx(50.0)
    assert eta_s(Pace(100, 50, 25.0, evals_left=2)) is None  # no evaluation timed yet
    assert eta_s(Pace(100, 50, 25.0, evals_left=2, eval_s=(10.0, 30.0))) == pytest.approx(90.0)
    assert eta_s(Pace(0, 0, 0.0, evals_left=0)) == 0.0
    assert (format_duration(None), format_duration(20), format_duration(600), format_duration(7380)) == \
        ("-", "<1m", "10m", "2h03m")
    assert first_difference({"a": {"b": 1, "c": 2}}, {"a": {"b": 1, "c": 3}}) == ("a.c", 2, 3)
    assert first_difference({"a": [1]}, {"a": [1]}) is None


def test_bad_input_stops_with_one_line_before_anything_is_written(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    other = tmp_path / "other" / "stacking.toml"
    other.parent.mkdir()
    other.write_text(RECIPE.read_text())
    (other.parent / "clutter.toml").write_text((RECIPE.parent / "clutter.toml").read_text())  # its base
    broken = tmp_path / "broken.toml"
    broken.write_text("[task\nkind = 1\n")
    taken = tmp_path / "taken"
    taken.mkdir()
    manifest = {"variants": ["clutter"], "seeds": [1], "max_actions": 10, "overrides": [], "runs_dir": None,
                "eval": {}}
    (taken / "sweep.json").write_text(json.dumps(manifest))
    cluttered = tmp_path / "cluttered"
    cluttered.mkdir()
    (cluttered / "notes.txt").write_text("mine")
    out = tmp_path / "out"
    base = ["--max-actions", "10"]
    cases = [
        (["--config", str(tmp_path / "missing.toml"), "--seeds", "1", "--out", str(out)], "does not exist"),
        (["--config", str(broken), "--seeds", "1", "--out", str(out)], "not valid TOML"),
        (["--config", str(RECIPE), "--seeds", "--out", str(out)], "--seeds is empty"),
        (["--config", str(RECIPE), "--config", str(other), "--seeds", "1", "--out", str(out)],
         "are both variant 'stacking'"),
        (["--config", str(RECIPE), "--seeds", "1", "1", "--out", str(out)], "seed 1 is given twice"),
        (["--config", str(RECIPE), "--seeds", "1", "--set", "seed=4", "--out", str(out)], "sets each run's seed"),
        (["--config", str(RECIPE), "--seeds", "1", "--set", "task.goal_stack_height=9", "--out", str(out)],
         "task.goal_stack_height"),
        (["--config", str(RECIPE), "--config", str(REPO / "configs/experiments/clutter.toml"), "--seeds", "1",
          "--out", str(out)], "the variants train different tasks"),
        (["--config", str(RECIPE), "--seeds", "1", "--out", str(taken)], "holds another sweep (variants"),
        (["--config", str(RECIPE), "--seeds", "1", "--out", str(cluttered)], "holds files but no sweep.json"),
    ]
    for args, expected in cases:  # in this process (the CLI's own main), for speed
        code = main(["sweep", *args, *base])
        captured = capsys.readouterr()
        lines = captured.err.strip().splitlines()
        assert code == 2, (args, captured.err)
        assert len(lines) == 1 and lines[0].startswith("romannet sweep: error: "), (args, captured.err)
        assert expected in lines[0], (args, lines[0])
    proc = romannet("sweep", *cases[0][0], *base)  # and once as the real command
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert cases[0][1] in proc.stderr and "Traceback" not in proc.stderr + proc.stdout
    assert not out.exists()
    assert json.loads((taken / "sweep.json").read_text()) == manifest
    assert sorted(p.name for p in taken.iterdir()) == ["sweep.json"]
    assert sorted(p.name for p in cluttered.iterdir()) == ["notes.txt"]


@pytest.mark.timeout(420)
def test_sweep_interrupted_resumes_and_is_not_redone(tmp_path: Path) -> None:
    out = tmp_path / "sweep"
    run_dir = out / "runs" / "stacking-s1"
    log_path = tmp_path / "first.out"

    # First launch: SIGINT (what Ctrl-C delivers) as soon as the run has made an action.
    with log_path.open("wb") as fh:
        proc = subprocess.Popen(sweep_argv(out), stdout=fh, stderr=subprocess.STDOUT, cwd=REPO)
    try:
        deadline = time.monotonic() + 150
        while proc.poll() is None and time.monotonic() < deadline:
            if (run_dir / "actors").is_dir() and run_actions(run_dir) >= 1:
                break
            time.sleep(0.1)
        assert proc.poll() is None, log_path.read_text()
        proc.send_signal(signal.SIGINT)
        assert proc.wait(120) == 130, log_path.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    first = log_path.read_text()
    interrupted_at = run_actions(run_dir)
    assert 1 <= interrupted_at < MAX_ACTIONS, first
    assert json.loads((run_dir / "summary.json").read_text())["outcome"] == "stopped_by_signal"
    assert "the same command resumes it" in first
    assert not (out / "eval").exists() and not (out / "results.json").exists()
    manifest = json.loads((out / "sweep.json").read_text())
    assert (manifest["variants"], manifest["seeds"], manifest["max_actions"]) == (["stacking"], [1], MAX_ACTIONS)
    assert manifest["eval"]["task"] == "stacking" and manifest["eval"]["goal_heights"] == [2]
    assert "stacking-s1: actions" in (out / "sweep.log").read_text()  # the progress line
    up_log = (out / "logs" / "stacking-s1.log").read_text()
    assert "romannet.up" in up_log and "romannet.up" not in first  # the child's output went to its log file

    # The same command resumes the run with --resume, then evaluates it and the two policies.
    proc2 = subprocess.run(sweep_argv(out), capture_output=True, text=True, timeout=300, cwd=REPO)
    assert proc2.returncode == 0, proc2.stderr[-4000:]
    up_log = (out / "logs" / "stacking-s1.log").read_text()
    assert "--resume" in up_log and f"the run's earlier launches made {interrupted_at} actions" in up_log
    assert run_actions(run_dir) == MAX_ACTIONS
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["outcome"] == "max_actions_reached" and summary["actions"] == MAX_ACTIONS, summary
    for name in ("stacking-s1", "oracle", "random"):
        report = json.loads((out / "eval" / name / "report.json").read_text())
        assert not report["interrupted"] and report["protocol"] == "frozen" and report["base_seed"] == 100000
        assert report["task"] == "stacking" and report["goal_heights"] == [2] and report["overall"]["runs"] == 2
        assert report.get("policy", "net") == ("net" if name == "stacking-s1" else name)

    results = json.loads((out / "results.json").read_text())
    assert list(results["rows"]) == ["stacking", "oracle", "random"]
    variant = results["rows"]["stacking"]
    assert list(variant["runs"]) == ["stacking-s1"]
    entry = variant["runs"]["stacking-s1"]
    assert entry["training_actions"] == MAX_ACTIONS and entry["eval_runs"] == 2 and entry["updates"] > 0
    for column in ("completion_rate", "pick_success_rate", "action_efficiency", "training_success_last"):
        s = variant[column]
        if s["mean"] is not None:
            assert 0.0 <= s["min"] <= s["mean"] <= s["max"] <= 1.0, (column, s)
            assert s["n"] == 1 and s["mean"] == entry[column]
    assert variant["completion_rate"]["n"] == 1 and variant["training_success_last"]["n"] == 1
    for policy in ("oracle", "random"):
        row = results["rows"][policy]
        assert row["kind"] == "policy" and row["training_success_last"]["n"] == 0
        assert 0.0 <= row["completion_rate"]["mean"] <= 1.0
    assert results["rows"]["oracle"]["completion_rate"]["mean"] >= 0.5  # the scripted ceiling stacks two cubes
    md = (out / "results.md").read_text()
    assert "| stacking | 1 |" in md and "| oracle | – |" in md and "| random | – |" in md
    assert "| stacking | 1 |" in proc2.stdout
    assert (out / "curves.png").stat().st_size > 5000

    # Again: nothing trained or evaluated again; the run's and the evaluations' files are untouched.
    before = {**files_state(out / "runs"), **files_state(out / "eval"), **files_state(out / "logs")}
    proc3 = subprocess.run(sweep_argv(out), capture_output=True, text=True, timeout=120, cwd=REPO)
    assert proc3.returncode == 0, proc3.stderr[-4000:]
    assert f"already trained ({MAX_ACTIONS} actions)" in proc3.stderr
    assert {**files_state(out / "runs"), **files_state(out / "eval"), **files_state(out / "logs")} == before
    assert json.loads((out / "results.json").read_text()) == results
