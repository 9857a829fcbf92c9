"""Checkpoints: atomic, complete, and a resume (also after SIGKILL) continues bit-identically."""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import _learner_helpers as H
import numpy as np
import pytest
import torch

from romannet.common.config_learner import LearnerConfig
from romannet.learner.checkpoint import (
    latest_checkpoint,
    load_checkpoint,
    save_checkpoint,
    start_from_weights,
)

TESTS = Path(__file__).resolve().parent


def _batches(n: int) -> list:
    return [H.batch(2, seed=10 + k) for k in range(n)]


def _assert_same_state(a, b):
    for k, v in a.model.state_dict().items():
        assert torch.equal(v, b.model.state_dict()[k]), k
    for (name, pa), pb in zip(a.model.named_parameters(), b.model.parameters(), strict=True):
        ma = a.optimizer.state.get(pa, {}).get("momentum_buffer")
        mb = b.optimizer.state.get(pb, {}).get("momentum_buffer")
        assert (ma is None) == (mb is None), name
        if ma is not None:
            assert torch.equal(ma, mb), name
    assert a.updates == b.updates
    assert a.exploration.state_dict() == b.exploration.state_dict()


def test_save_load_then_step_is_bit_identical(tmp_path):
    batches = _batches(5)
    a = H.trainer(seed=1, target_network=True, target_sync_every_updates=2)
    for b in batches[:3]:
        a.train_step(b)
    path = save_checkpoint(a, tmp_path)
    assert latest_checkpoint(tmp_path) == path
    torch.manual_seed(123)  # the checkpoint restores the RNGs, whatever happened in between
    np.random.seed(5)
    random.seed(7)
    for b in batches[3:]:
        a.train_step(b)
    expected_rng = (torch.rand(3), np.random.rand(), random.random())

    c = H.trainer(seed=2, target_network=True, target_sync_every_updates=2)  # other init: load overrides it
    load_checkpoint(c, tmp_path)
    assert c.updates == 3
    for b in batches[3:]:
        c.train_step(b)
    _assert_same_state(a, c)
    for k, v in a.target.state_dict().items():
        assert torch.equal(v, c.target.state_dict()[k]), k
    # The RNG streams continue from the checkpoint (the reseeding above came after the save).
    torch.manual_seed(123)
    np.random.seed(5)
    random.seed(7)
    got = (torch.rand(3), np.random.rand(), random.random())
    assert torch.equal(got[0], expected_rng[0]) and got[1:] == expected_rng[1:]


def test_checkpoint_files_are_safetensors_and_json_and_pruned(tmp_path):
    t = H.trainer(keep_checkpoints=2)
    for b in _batches(3):
        t.train_step(b)
        save_checkpoint(t, tmp_path)
    root = tmp_path / "checkpoints"
    assert sorted(p.name for p in root.glob("ckpt-*")) == ["ckpt-000000002", "ckpt-000000003"]
    assert sorted(p.name for p in (root / "ckpt-000000003").iterdir()) == ["manifest.json", "state.json",
                                                                        "tensors.safetensors"]
    state = json.loads((root / "ckpt-000000003" / "state.json").read_text())
    assert state["updates"] == 3 and state["config"]["learner"]["lr"] == 1e-4
    # A half-written checkpoint (a crash before the rename) is ignored.
    (root / ".ckpt-000000004.tmp-1").mkdir()
    assert latest_checkpoint(tmp_path).name == "ckpt-000000003"
    save_checkpoint(t, tmp_path)  # the same update again (a shutdown right after a periodic checkpoint)
    assert latest_checkpoint(tmp_path).name == "ckpt-000000003"


def test_default_cadence_is_every_100_updates_keeping_3(tmp_path):
    """Frequent enough to evaluate a run while it trains; three kept, so an evaluation that started on one has
    200 updates before it is pruned."""
    assert (LearnerConfig().checkpoint_every_updates, LearnerConfig().keep_checkpoints) == (100, 3)
    t = H.trainer()
    for updates in (100, 200, 300, 400):
        t.updates = updates
        save_checkpoint(t, tmp_path)
    assert sorted(p.name for p in (tmp_path / "checkpoints").glob("ckpt-*")) == [
        "ckpt-000000200", "ckpt-000000300", "ckpt-000000400"]


def test_start_from_weights_is_a_new_run_on_those_weights():
    source = H.trainer(seed=1)
    for b in _batches(2):
        source.train_step(b)
    used = H.trainer(seed=2, target_network=True)  # momentum, an update count and a moved exploration rate
    used.train_step(_batches(3)[2])
    start_from_weights(used, source.state_tensors())
    fresh = H.trainer(seed=3, target_network=True)
    start_from_weights(fresh, source.state_tensors())
    for t in (used, fresh):
        assert t.updates == 0 and not t.optimizer.state
        assert t.exploration.state_dict() == H.trainer().exploration.state_dict()
        for k, v in source.state_tensors().items():
            assert torch.equal(t.model.state_dict()[k], v) and torch.equal(t.target.state_dict()[k], v), k
    batch = _batches(4)[3]
    used.train_step(batch)
    fresh.train_step(batch)
    _assert_same_state(used, fresh)


def test_resume_refuses_another_model(tmp_path):
    save_checkpoint(H.trainer(), tmp_path)
    other = H.trainer(model=H.SMALL_MODEL.__class__(channels=4, residual_blocks=1))
    with pytest.raises(ValueError, match="model config"):
        load_checkpoint(other, tmp_path)
    with pytest.raises(FileNotFoundError):
        load_checkpoint(H.trainer(), tmp_path / "nothing")


CHILD = textwrap.dedent("""
    import sys, time, torch
    sys.path.insert(0, {tests!r})
    torch.set_num_threads({threads})
    import test_checkpoint as tc, _learner_helpers as H
    from romannet.learner.checkpoint import save_checkpoint
    t = H.trainer(seed=3)
    batches = tc._batches(5)
    for b in batches[:3]:
        t.train_step(b)
    save_checkpoint(t, {run_dir!r})
    print("saved", flush=True)
    while True:  # keep training (never checkpointing) until killed
        t.train_step(batches[3])
        time.sleep(0.01)
""")


def test_sigkill_after_checkpoint_then_resume_is_bit_identical(tmp_path):
    run_dir = str(tmp_path / "run")
    code = CHILD.format(tests=str(TESTS), threads=torch.get_num_threads(), run_dir=run_dir)
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONHASHSEED": "0"})
    try:
        line = proc.stdout.readline()
        assert line.strip() == "saved", line
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    assert proc.returncode == -signal.SIGKILL

    uninterrupted = H.trainer(seed=3)
    batches = _batches(5)
    for b in batches:
        uninterrupted.train_step(b)
    resumed = H.trainer(seed=3)
    load_checkpoint(resumed, run_dir)
    for b in batches[3:]:
        resumed.train_step(b)
    _assert_same_state(uninterrupted, resumed)


def test_a_latest_file_naming_a_path_outside_the_run_is_refused(tmp_path: Path) -> None:
    root = tmp_path / "checkpoints"
    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "elsewhere" / "state.json").write_text("{}")
    root.mkdir()
    (root / "ckpt-x").mkdir()
    (root / "LATEST").write_text("ckpt-x/../../elsewhere")
    with pytest.raises(FileNotFoundError, match="not a complete checkpoint"):
        latest_checkpoint(tmp_path)
