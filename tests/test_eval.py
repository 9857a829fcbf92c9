"""`romannet eval` and `romannet plot` end to end: a real learner checkpoint, real PyBullet runs in real
worker processes, the report files a user reads; and the learning curves from real recorded episodes.

Small everything (64x64 heightmaps, a 4-channel net, the floating gripper) so a run takes seconds."""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from romannet.actor.service import run_actor
from romannet.actor.sim.arrangements import default_cases
from romannet.actor.sim.env import SimEnv
from romannet.common.config import load_config
from romannet.common.config_replay import ReplayConfig
from romannet.common.configbase import write_toml
from romannet.evaluate.curves import run_actions
from romannet.evaluate.protocol import read_journal
from romannet.learner.checkpoint import save_checkpoint
from romannet.learner.trainer import Trainer
from romannet.replay.inprocess import InProcessReplayClient
from romannet.replay.store import ReplayStore

pytestmark = pytest.mark.timeout(240)

SETS = ["model.channels=4", "model.residual_blocks=1", "model.num_threads=1", "learner.num_threads=1",
        'learner.precision="fp32"', "learner.max_grad_norm=10", "workspace.resolution_m=0.007", 'sim.robot="gripper"',
        'task.kind="stacking"', "task.goal_stack_height=2", "task.use_push=false", "sim.num_stacking_cubes=3",
        "camera.width_px=160", "camera.height_px=120", "camera.fx_px=154.655", "camera.fy_px=154.655",
        "camera.cx_px=80.0", "camera.cy_px=60.0"]


def make_run(tmp_path: Path, sets: list[str] = SETS, name: str = "run") -> Path:
    """A run directory with config.toml and one learner checkpoint (an untrained, seeded net)."""
    run_dir = tmp_path / name
    cfg = load_config(None, sets)
    write_toml(cfg, run_dir / "config.toml")
    trainer = Trainer(cfg.model, cfg.learner, cfg.reward, cfg.task, exploration_cfg=cfg.exploration)
    save_checkpoint(trainer, run_dir)
    return run_dir


def romannet(*args: str, timeout_s: float = 200) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "romannet.cli", *args], capture_output=True, text=True,
                          timeout=timeout_s)


def test_eval_stacking_paper_protocol_on_two_processes(tmp_path: Path) -> None:
    run_dir = make_run(tmp_path)
    out = tmp_path / "eval"
    proc = romannet("eval", str(run_dir), "--goal-height", "2", "3", "--runs", "2", "--workers", "2",
                    "--max-steps", "6", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    report = json.loads((out / "report.json").read_text())
    assert report["protocol"] == "paper" and report["task"] == "stacking" and not report["interrupted"]
    assert report["updates"] == 0 and report["workers"] == 2 and report["goal_heights"] == [2, 3]
    assert list(report["cases"]) == ["h2", "h3"]
    runs = report["runs"]
    assert len(runs) == 4 and len({r["seed"] for r in runs}) == 4
    for r in runs:
        assert 1 <= len(r["steps"]) <= 6
        assert r["end_reason"] in ("done", "consecutive_failures", "step_limit", "unstable")
        assert r["ideal_actions"] == (2 if r["case"] == "h2" else 4)
        assert all(s.split(":")[0] in ("pick", "place") for s in r["steps"])  # no push in this task
    total = sum(c["runs"] for c in report["cases"].values())
    assert total == report["overall"]["runs"] == 4
    assert read_journal(out / "runs.jsonl")  # the journal holds the same runs
    assert len(read_journal(out / "runs.jsonl")) == 4
    md = (out / "report.md").read_text()
    assert "| h2 | 2 |" in md and "| h3 | 2 |" in md and "protocol `paper`" in md
    assert (out / "report.png").stat().st_size > 1000
    assert "| h2 | 2 |" in proc.stdout  # the table is printed too


def test_eval_frozen_protocol_is_deterministic_and_arrangement_cases_get_rows(tmp_path: Path) -> None:
    run_dir = make_run(tmp_path, [*SETS[:7], *SETS[-6:], 'task.kind="clutter"', "task.use_push=true"])
    cases = tmp_path / "cases"
    cases.mkdir()
    for p in default_cases()[:2]:
        shutil.copy(p, cases / p.name)
    outs = []
    for k in range(2):
        out = tmp_path / f"eval{k}"
        proc = romannet("eval", str(run_dir), "--task", "arrangement", "--cases", str(cases), "--runs", "1",
                        "--workers", "1", "--protocol", "frozen", "--max-steps", "4", "--out", str(out))
        assert proc.returncode == 0, proc.stderr
        outs.append(json.loads((out / "report.json").read_text()))
    a, b = outs
    assert list(a["cases"]) == sorted(p.stem for p in cases.iterdir())
    assert a["protocol"] == "frozen" and a["cases_dir"] == str(cases)
    assert [r["steps"] for r in a["runs"]] == [r["steps"] for r in b["runs"]]  # no learning: same actions
    assert all(r["ideal_actions"] >= 3 for r in a["runs"])  # the case's objects
    assert "Cases completed in all runs" in (tmp_path / "eval0" / "report.md").read_text()
    # the decisions' numerics, which "auto" picks per CPU: bf16, int8 or fp32
    from romannet.common.policy import resolve_inference_precision

    assert a["precision"] == resolve_inference_precision("auto")
    assert f"greedy policy in {a['precision']};" in (tmp_path / "eval0" / "report.md").read_text()


def test_eval_bad_inputs_give_one_line_errors(tmp_path: Path) -> None:
    proc = romannet("eval", str(tmp_path), "--runs", "1")
    assert proc.returncode == 2 and "error:" in proc.stderr and "Traceback" not in proc.stderr
    run_dir = make_run(tmp_path)
    proc = romannet("eval", str(run_dir), "--goal-height", "7", "--runs", "1")
    assert proc.returncode == 2 and "goal heights are 2..5" in proc.stderr
    proc = romannet("eval", str(run_dir), "--runs", "1", "--set", "model.channels=8")
    assert proc.returncode == 2 and "trained with model config" in proc.stderr
    out = tmp_path / "busy"
    out.mkdir()
    (out / "runs.jsonl").write_text('{"case": "h2"}\n')
    proc = romannet("eval", str(run_dir), "--runs", "1", "--out", str(out))
    assert proc.returncode == 2 and "already holds runs" in proc.stderr


def test_eval_takes_a_checkpoint_saved_before_a_model_field_existed(tmp_path: Path) -> None:
    """A run trained before model.pick_angle_bins existed (its checkpoint's config lacks it) ran without it, and
    evaluates as it ran: models trained then are what users evaluate."""
    from romannet.cli import main
    from romannet.learner.ckpt_integrity import read_verified, write_checkpoint_files

    run_dir = make_run(tmp_path)
    ckpt = next((run_dir / "checkpoints").glob("ckpt-*"))
    saved = read_verified(ckpt)
    state = json.loads((ckpt / "state.json").read_text())
    del state["config"]["model"]["pick_angle_bins"]
    write_checkpoint_files(ckpt, saved.tensors, state)
    code = main(["eval", str(run_dir), "--runs", "1", "--workers", "1", "--protocol", "frozen", "--max-steps", "2",
                 "--out", str(tmp_path / "out")])
    assert code == 0
    assert json.loads((tmp_path / "out" / "report.json").read_text())["runs"]


def test_eval_compares_checkpoints_on_the_same_scenes(tmp_path: Path) -> None:
    """Two seeds of a recipe: each gets its own report under --out, both meet the same seeds, and
    comparison.json holds each one's metrics and their mean and range."""
    a = make_run(tmp_path, [*SETS, "seed=1"], name="stack-s1")
    b = make_run(tmp_path, [*SETS, "seed=2"], name="stack-s2")
    b_ckpt = next((b / "checkpoints").glob("ckpt-*"))
    out = tmp_path / "cmp"
    proc = romannet("eval", str(a), str(b_ckpt), "--goal-height", "2", "--runs", "2", "--workers", "1",
                    "--protocol", "frozen", "--max-steps", "4", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    names = ["stack-s1", f"stack-s2-{b_ckpt.name}"]
    reports = {n: json.loads((out / n / "report.json").read_text()) for n in names}
    assert [r["seed"] for r in reports[names[0]]["runs"]] == [r["seed"] for r in reports[names[1]]["runs"]]
    assert reports[names[1]]["checkpoint"] == str(b_ckpt)
    cmp = json.loads((out / "comparison.json").read_text())
    assert list(cmp["checkpoints"]) == names and list(cmp["cases"]) == ["h2"] and not cmp["interrupted"]
    row = cmp["cases"]["h2"]
    rates = [reports[n]["cases"]["h2"]["completion_rate"] for n in names]
    assert [row["checkpoints"][n]["completion_rate"] for n in names] == rates
    assert row["completion_rate"]["mean"] == pytest.approx(sum(rates) / 2)
    assert row["completion_rate"]["min"] == min(rates) and row["completion_rate"]["n"] == 2
    md = (out / "comparison.md").read_text()
    assert "| h2 | stack-s1 |" in md and "**mean (min–max)**" in md and "| h2 | stack-s1 |" in proc.stdout
    assert (out / "comparison.png").stat().st_size > 1000


def test_eval_of_several_checkpoints_checks_every_input_before_running(tmp_path: Path) -> None:
    a = make_run(tmp_path, name="a")
    proc = romannet("eval", str(a), str(a), "--runs", "1")
    assert proc.returncode == 2 and "pass --out DIR" in proc.stderr
    proc = romannet("eval", str(a), str(tmp_path / "missing"), "--runs", "1", "--out", str(tmp_path / "o1"))
    assert proc.returncode == 2 and "missing" in proc.stderr and not (tmp_path / "o1").exists()
    c = make_run(tmp_path, [*SETS[:7], *SETS[-6:], 'task.kind="clutter"', "task.use_push=true"], name="c")
    proc = romannet("eval", str(a), str(c), "--runs", "1", "--out", str(tmp_path / "o2"))
    assert proc.returncode == 2 and "need the same tests" in proc.stderr and not (tmp_path / "o2").exists()


class _NoWeights:
    def poll_weights(self):
        return None

    def poll_exploration(self):
        return None


def test_plot_draws_curves_from_recorded_episodes(tmp_path: Path) -> None:
    """A real actor records stacking episodes; `romannet plot` reads every action back in order."""
    cfg = load_config(None, [*SETS, "task.goal_stack_height=2", "sim.max_consecutive_failures=3",
                             "actor.spool_fsync=false", "actor.record_camera=false"])
    run_dir = tmp_path / "train"
    write_toml(cfg, run_dir / "config.toml")
    env = SimEnv.from_config(cfg)
    store = ReplayStore(ReplayConfig(fsync=False, snapshot_every_s=0.0, snapshot_every_inserts=0), tmp_path / "rp")
    try:
        acfg = dataclasses.replace(cfg.actor, max_actions=12, shutdown_flush_s=0.5)
        stats = run_actor(cfg, run_dir, env, InProcessReplayClient(store), _NoWeights(), threading.Event(),
                          actor_cfg=acfg)
    finally:
        env.close()
        store.close()
    actions, meta = run_actions(run_dir)
    assert len(actions) == stats.actions == 12
    assert [a.t_ns for a in actions] == sorted(a.t_ns for a in actions)
    assert sum(1 for a in actions if a.episode_end) == stats.episodes
    assert meta["task"] == "stacking" and meta["goal_stack_height"] == 2
    out = tmp_path / "curves.png"
    proc = romannet("plot", str(run_dir), str(run_dir), "--labels", "a", "b", "--window", "5", "--out", str(out))
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert summary["a"]["actions"] == 12 and summary["b"]["episodes"] == stats.episodes
    assert out.stat().st_size > 1000
    # Runs sharing a label are seeds of one variant: one mean line, each run's numbers kept.
    seeds = tmp_path / "seeds.png"
    proc = romannet("plot", str(run_dir), str(run_dir), str(run_dir), "--labels", "v", "v", "w", "--window", "5",
                    "--out", str(seeds))
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout)
    assert list(summary) == ["v", "w"] and len(summary["v"]["runs"]) == 2
    assert all(r["actions"] == 12 for r in summary["v"]["runs"])
    assert summary["v"]["final_success_rate"] == pytest.approx(summary["w"]["final_success_rate"])
    lo, hi = summary["v"]["final_success_rate_range"]
    assert lo == hi == pytest.approx(summary["w"]["final_success_rate"])
    assert summary["v"]["task"] == "stacking" and seeds.stat().st_size > 1000


def test_paper_protocol_learns_within_a_run_and_resets_to_the_checkpoint(tmp_path: Path) -> None:
    import torch

    from romannet.common.configbase import dumps_toml
    from romannet.common.model import state_dict_to_tensors
    from romannet.evaluate.runner import EvalSetup, RunSpec, Worker, load_model_tensors

    run_dir = make_run(tmp_path)
    ckpt = run_dir / "checkpoints" / (run_dir / "checkpoints" / "LATEST").read_text().strip()
    saved = load_model_tensors(ckpt)
    cfg = load_config(run_dir / "config.toml")
    worker = Worker(EvalSetup(dumps_toml(cfg), str(ckpt), "paper"))
    try:
        spec = RunSpec(case="h2", seed=5, task="stacking", goal_height=2, max_steps=3)
        first = worker.run(spec)
        trainer = worker._trainer
        assert trainer is not None and trainer.updates == first.actions == 3  # one SGD step per action
        learned = state_dict_to_tensors(worker.engine.model)
        assert any(not torch.equal(learned[k], saved[k]) for k in saved)  # the run changed the weights
        second = worker.run(spec)  # same seed, weights reset to the checkpoint: the same run again
        assert second.steps == first.steps
        assert trainer.updates == 6
    finally:
        worker.close()
    frozen = Worker(EvalSetup(dumps_toml(cfg), str(ckpt), "frozen"))
    try:
        frozen.run(spec)
        now = state_dict_to_tensors(frozen.engine.model)
        assert all(torch.equal(now[k], saved[k]) for k in saved) and frozen._trainer is None
    finally:
        frozen.close()


def test_curves_read_an_episode_cut_short_up_to_its_last_whole_chunk(tmp_path: Path) -> None:
    """An actor killed mid-episode leaves a file without a summary: its whole chunks still count."""
    from romannet.actor.recorder import EpisodeRecorder
    from romannet.evaluate.curves import read_step_records

    cfg = load_config(None, SETS)
    run_dir = tmp_path / "cut"
    write_toml(cfg, run_dir / "config.toml")
    path = run_dir / "episodes" / "actor-0" / "ep000000.mcap"
    path.parent.mkdir(parents=True)

    def record(target: Path, steps: int) -> bytes:
        rec = EpisodeRecorder(target, {"run_id": "r", "actor_id": "actor-0", "task": "stacking"}, chunk_bytes=1024)
        for step in range(steps):
            rec.write_step(b"\x00" * 10, {"step": step, "success": step % 2 == 0, "done": step == 5,
                                          "done_reason": "done" if step == 5 else ""}, 1_000 + step)
        rec.close()
        return target.read_bytes()

    five, six = record(tmp_path / "five.mcap", 5), record(path, 6)
    assert [r["step"] for r in read_step_records(path)] == list(range(6))
    chunk6 = next(i for i, (a, b) in enumerate(zip(five, six, strict=False)) if a != b)  # 6th chunk starts here
    path.write_bytes(six[: chunk6 + 30])  # the writer died inside the 6th chunk: no summary either
    cut = read_step_records(path)
    assert [r["step"] for r in cut] == list(range(5))
    actions, _ = run_actions(run_dir)
    assert len(actions) == len(cut) and not any(a.episode_end for a in actions)  # it never ended
