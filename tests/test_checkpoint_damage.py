"""Damaged checkpoints are named in one line and skipped; weights versions never repeat across a crash.

Real files throughout: checkpoints written by save_checkpoint, then truncated, bit-flipped, deleted or
rewritten with bad contents; the learner's resume, `romannet eval`'s resolution, `romannet models check
--init` and --init-from all read them through learner/ckpt_integrity.py. The version test kills a real
learner process (run_learner on a real Zenoh session, fed by a synthetic replay) with SIGKILL after its
newest checkpoint and resumes it.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import _learner_helpers as H
import pytest
import safetensors.torch
import torch

from romannet.cli import main
from romannet.common.config import Config, load_config
from romannet.common.wire_messages import SampleBatchMsg, SampleItem
from romannet.common.zenoh_session import free_port, make_config, open_session
from romannet.evaluate.cli import resolve_checkpoint
from romannet.learner.checkpoint import load_checkpoint, read_init_weights, save_checkpoint
from romannet.learner.ckpt_integrity import (
    TENSORS,
    CheckpointDamaged,
    NoIntactCheckpoint,
    read_verified,
    write_checkpoint_files,
)
from romannet.learner.publisher import WeightsPublisher
from romannet.learner.service import ServiceOptions, _start_state, run_learner
from romannet.learner.versions import VersionClock, read_reservation

TESTS = Path(__file__).resolve().parent
PUBLISH = WeightsPublisher.publish_weights  # unpatched, whatever a test wraps it with
pytestmark = pytest.mark.timeout(240)


def _run_with_two_checkpoints(run_dir: Path) -> dict[str, torch.Tensor]:
    """ckpt-000000001 and ckpt-000000002 of a small trainer; returns the weights at update 1."""
    t = H.trainer(seed=1)
    t.train_step(H.batch(2, seed=1))
    save_checkpoint(t, run_dir)
    first = {k: v.clone() for k, v in t.state_tensors().items()}
    t.train_step(H.batch(2, seed=2))
    save_checkpoint(t, run_dir)
    return first


def _flip_weight_bytes(path: Path, count: int = 50) -> None:
    data = bytearray(path.read_bytes())
    start = 8 + int.from_bytes(data[:8], "little")  # after the safetensors header: tensor bytes
    for i in range(count):
        data[start + 97 * i] ^= 0xFF
    path.write_bytes(bytes(data))


def _truncate(path: Path) -> None:
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])


def _rewrite(ckpt: Path, change: Callable[[dict[str, torch.Tensor]], None]) -> None:
    """Rewrite a checkpoint consistently (a matching manifest) with changed tensors: only the content checks
    can tell."""
    tensors = safetensors.torch.load_file(str(ckpt / TENSORS))
    state = json.loads((ckpt / "state.json").read_text())
    change(tensors)
    write_checkpoint_files(ckpt, tensors, state)


def _nan(t: dict[str, torch.Tensor]) -> None:
    key = next(k for k in t if k.startswith("model/") and t[k].is_floating_point())
    t[key] = t[key].clone()
    t[key].view(-1)[0] = float("nan")


def _rename(t: dict[str, torch.Tensor]) -> None:
    key = next(k for k in t if k.startswith("model/"))
    t["model/not_a_layer"] = t.pop(key)


def _reshape(t: dict[str, torch.Tensor]) -> None:
    key = next(k for k in t if k.startswith("model/") and t[k].dim() == 4)
    t[key] = t[key][:1].contiguous()


DAMAGE: dict[str, tuple[Callable[[Path], None], str]] = {
    "truncated weights": (lambda c: _truncate(c / TENSORS), "truncated"),
    "50 flipped bytes in the weights": (lambda c: _flip_weight_bytes(c / TENSORS), "sha256"),
    "weights deleted": (lambda c: (c / TENSORS).unlink(), "tensors.safetensors is missing"),
    "state deleted": (lambda c: (c / "state.json").unlink(), "state.json is missing"),
    "manifest deleted": (lambda c: (c / "manifest.json").unlink(), "manifest.json is missing"),
    "garbage state JSON": (lambda c: (c / "state.json").write_text("{not json"), "state.json"),
    "garbage manifest JSON": (lambda c: (c / "manifest.json").write_text("]]"), "manifest.json is not valid JSON"),
    "NaN weights, checksums matching": (lambda c: _rewrite(c, _nan), "NaN"),
    "unknown tensor name, checksums matching": (lambda c: _rewrite(c, _rename), "not_a_layer"),
    "wrong shape, checksums matching": (lambda c: _rewrite(c, _reshape), "shape"),
}


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_resume_skips_a_damaged_newest_checkpoint_in_one_line(tmp_path: Path, caplog: Any, damage: str) -> None:
    first = _run_with_two_checkpoints(tmp_path)
    newest = tmp_path / "checkpoints" / "ckpt-000000002"
    do, problem = DAMAGE[damage]
    do(newest)
    with pytest.raises(CheckpointDamaged, match=problem):
        read_verified(newest)
    half_written = tmp_path / "checkpoints" / ".ckpt-000000003.tmp-1"  # a crash before the rename: never read
    half_written.mkdir()
    (half_written / TENSORS).write_bytes(b"\0" * 10)
    resumed = H.trainer(seed=9)
    with caplog.at_level(logging.WARNING):
        ckpt = load_checkpoint(resumed, tmp_path)
    assert ckpt.path.name == "ckpt-000000001" and resumed.updates == 1
    assert all(torch.equal(resumed.state_tensors()[k], v) for k, v in first.items())
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and str(newest) in warnings[0] and problem in warnings[0], warnings
    assert "\n" not in warnings[0]


def test_no_intact_checkpoint_starts_fresh_saying_so(tmp_path: Path, caplog: Any) -> None:
    _run_with_two_checkpoints(tmp_path)
    for ckpt in (tmp_path / "checkpoints").glob("ckpt-*"):
        _truncate(ckpt / TENSORS)
    trainer = H.trainer(seed=3)
    with pytest.raises(NoIntactCheckpoint, match="none of the 2 checkpoints"):
        load_checkpoint(trainer, tmp_path)
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        assert _start_state(trainer, tmp_path, resume=True, init_weights=None) == (0, None)
    lines = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(lines) == 3 and "starting fresh at update 0" in lines[-1], lines  # 2 damaged, then the fresh start
    assert trainer.updates == 0


def _one_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def test_eval_models_and_init_from_use_the_verified_loader(tmp_path: Path, capsys: Any) -> None:
    run_dir = tmp_path / "run"
    _run_with_two_checkpoints(run_dir)
    newest, older = (run_dir / "checkpoints" / f"ckpt-00000000{n}" for n in (2, 1))
    _flip_weight_bytes(newest / TENSORS)
    code = main(["eval", str(newest)])
    line = _one_line(capsys.readouterr().err)
    assert code == 2 and f"checkpoint {newest} is damaged" in line and "sha256" in line
    assert resolve_checkpoint(run_dir) == (older, run_dir)  # a run directory: its newest intact checkpoint
    code = main(["models", "check", "--init", str(newest), "--set", "model.channels=8",
                 "--set", "model.residual_blocks=1"])
    assert code == 2 and "is damaged" in _one_line(capsys.readouterr().err)
    _, what = read_init_weights(run_dir, H.SMALL_MODEL)
    assert f"checkpoint {older} (update 1)" in what


# ------------------------------------------------------------------------------------------------ versions
def test_version_clock_offsets_only_when_a_version_may_name_other_weights(tmp_path: Path) -> None:
    fresh = VersionClock.start(tmp_path, updates=0, saved_offset=0, resumed_from=None, block=10)
    assert fresh.offset == 0 and [fresh.claim(u) for u in (0, 5, 12)] == [0, 5, 12]
    assert read_reservation(tmp_path)["reserved"] == 21  # 12 and the 9 after it
    # A crash, then a resume from update 8: its versions start above everything reserved.
    after_crash = VersionClock.start(tmp_path, updates=8, saved_offset=0, resumed_from="ckpt-000000008", block=10)
    assert after_crash.claim(8) == 22 and after_crash.offset == 14
    # A clean stop at update 30 (checkpointed): the same weights resume under the same version.
    after_crash.release(30, "ckpt-000000030")
    clean = VersionClock.start(tmp_path, updates=30, saved_offset=14, resumed_from="ckpt-000000030", block=10)
    assert clean.claim(30) == 44
    # A resume from an older checkpoint of that run after the clean stop: above 44 again.
    assert VersionClock.start(tmp_path, 20, 14, "ckpt-000000020", 10).version(20) == 45
    # A restart without any checkpoint: above the reservation too.
    assert VersionClock.start(tmp_path, 0, 0, None, 10).version(0) > read_reservation(tmp_path)["reserved"]


class SyntheticReplay:
    """A replay client with 100 transitions that serves `serve` batches, then blocks (printing 'stuck')."""

    def __init__(self, serve: int = 10**9):
        self.served, self.serve = 0, serve

    def stats(self, timeout_s: float = 10.0) -> dict[str, Any]:
        return {"size": 100, "inserts": 100}

    def sample(self, batch_size: int, timeout_s: float = 10.0) -> SampleBatchMsg:
        if self.served >= self.serve:
            print("stuck", flush=True)
            time.sleep(3600)
        self.served += 1
        items = tuple(SampleItem(i, 0.5, 1.0, t) for t, _, i in H.batch(batch_size, seed=self.served))
        return SampleBatchMsg(f"r{self.served}", items, 100)

    def update_priorities(self, update: Any) -> None:
        pass


SETS = ["model.channels=8", "model.residual_blocks=1", "learner.num_threads=1", 'learner.precision="fp32"',
        "learner.batch_size=2", "learner.min_replay_size=1", "learner.max_updates_per_insert=0",
        "learner.publish_every_updates=2", "learner.checkpoint_every_updates=4", 'run_id="versions-test"']
OPTIONS = dict(idle_wait_s=0.01, stats_every_s=0.05, image_every_updates=0, plot_every_s=3600, log_every_s=3600)

CHILD = textwrap.dedent("""
    import sys
    sys.path.insert(0, {tests!r})
    import threading, torch
    torch.set_num_threads(1)
    import test_checkpoint_damage as td
    from romannet.common.config import load_config
    from romannet.common.zenoh_session import make_config, open_session
    from romannet.learner.publisher import WeightsPublisher
    from romannet.learner.service import ServiceOptions, run_learner
    publish = WeightsPublisher.publish_weights
    def logged(self, version, tensors):
        out = publish(self, version, tensors)
        print("published", version, flush=True)
        return out
    WeightsPublisher.publish_weights = logged
    with open_session(make_config(listen=["tcp/127.0.0.1:{port}"], connect=[])) as session:
        run_learner(load_config(None, td.SETS), {run_dir!r}, td.SyntheticReplay(serve=7), session,
                    threading.Event(), options=ServiceOptions(**td.OPTIONS))
""")


def _kill_after_update_7(run_dir: Path) -> list[int]:
    """A learner process that made 7 updates (checkpoint at 4, weights 0, 2, 4, 6), killed with SIGKILL;
    returns the versions it published."""
    code = CHILD.format(tests=str(TESTS), port=free_port(), run_dir=str(run_dir))
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
                            text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    published: list[int] = []
    try:
        for line in proc.stdout:  # type: ignore[union-attr]
            if line.startswith("published"):
                published.append(int(line.split()[1]))
            if line.strip() == "stuck":
                break
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL
    return published


def _resume(cfg: Config, run_dir: Path, session: Any, max_updates: int, monkeypatch: Any) -> list[int]:
    """Resume the run in this process up to update max_updates; returns the weights versions it published."""
    published: list[int] = []

    def logged(self: WeightsPublisher, version: int, tensors: Any) -> Any:
        published.append(version)
        return PUBLISH(self, version, tensors)

    monkeypatch.setattr(WeightsPublisher, "publish_weights", logged)
    thread = threading.Thread(target=run_learner, args=(cfg, run_dir, SyntheticReplay(), session, threading.Event()),
                              kwargs=dict(resume=True, options=ServiceOptions(max_updates=max_updates, **OPTIONS)))
    thread.start()
    thread.join(120)
    assert not thread.is_alive()
    return published


def test_kill9_then_resume_from_an_older_checkpoint_never_reuses_a_version(tmp_path: Path, monkeypatch: Any,
                                                                          caplog: Any) -> None:
    run_dir = tmp_path / "learner"
    killed = _kill_after_update_7(run_dir)
    assert killed == [0, 2, 4, 6], killed
    assert [p.name for p in (run_dir / "checkpoints").glob("ckpt-*")] == ["ckpt-000000004"]
    reserved = read_reservation(run_dir)["reserved"]
    assert reserved >= 7  # every version the killed process used (exploration rates up to update 7)

    cfg = load_config(None, SETS)
    with open_session(make_config(listen=[f"tcp/127.0.0.1:{free_port()}"], connect=[])) as session:
        with caplog.at_level(logging.INFO):
            resumed = _resume(cfg, run_dir, session, max_updates=6, monkeypatch=monkeypatch)
        assert "resumed from" in caplog.text and "ckpt-000000004 (update 4)" in caplog.text
        assert resumed and min(resumed) > reserved >= max(killed), (resumed, reserved)
        assert resumed == sorted(set(resumed))
        state = json.loads((run_dir / "checkpoints" / "ckpt-000000006" / "state.json").read_text())
        assert state["version_offset"] == resumed[0] - 4
        # A clean stop and resume keeps its numbering: the same weights under the same last version.
        again = _resume(cfg, run_dir, session, max_updates=8, monkeypatch=monkeypatch)
        assert again[0] == resumed[-1] and again[-1] == 8 + state["version_offset"], (resumed, again)


def test_the_trainer_ages_actor_values_in_weights_versions() -> None:
    """After a resume with a version offset, an actor's V(s_{t+1}) from the current weights is fresh, and one
    stamped with the same number as an update count (another learner's numbering) is not."""
    items = [(H.transition(seed=i, next_value=0.4, next_value_version=version), 1.0, i)
             for i, version in enumerate((13, 12, 3))]
    t = H.trainer(actor_value_max_age=2)
    t.updates, t.version_offset = 4, 10  # weights version 14
    t.train_step(items)
    assert (t.actor_values_used, t.values_computed) == (2, 1)
