"""Exact, atomic learner checkpoints as safetensors + JSON (no pickle, no torch.load).

Layout of a run directory:

    RUN_DIR/checkpoints/ckpt-000001000/tensors.safetensors   model/…, target/…, momentum/…, rng/torch, rng/numpy
    RUN_DIR/checkpoints/ckpt-000001000/state.json            updates, LAE state, numpy/python RNG, configs
    RUN_DIR/checkpoints/LATEST                               name of the newest complete checkpoint

A checkpoint is written into a temporary directory, fsync'ed, renamed into place, and only then named in
LATEST (itself replaced atomically), so a crash at any moment leaves the previous checkpoint loadable.
Everything the next update depends on is saved: weights and BN statistics, the SGD momentum buffers, the
target net, the update counter, the exploration rate, and the torch / numpy / python RNG states. On a CPU
with the same thread count the update after a resume is bit-identical to the uninterrupted run's
(tests/test_checkpoint.py).
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import random
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import safetensors.torch
import torch

from romannet.common.fsutil import fsync_directory
from romannet.common.model import load_tensors, state_dict_to_tensors

from .trainer import Trainer

logger = logging.getLogger(__name__)

FORMAT_VERSION = 1
LATEST = "LATEST"


def checkpoint_dir(run_dir: str | Path) -> Path:
    """Where a run's checkpoints live."""
    return Path(run_dir) / "checkpoints"


def _fsync_write(path: Path, data: bytes) -> None:
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())



def _rng_state() -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """The global torch / numpy / python RNG states as tensors and JSON-able values."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    version, internal, gauss_next = random.getstate()
    tensors = {"rng/torch": torch.get_rng_state().clone(),
               "rng/numpy": torch.from_numpy(np.asarray(keys, dtype=np.uint32).astype(np.int64))}
    meta = {"numpy": {"kind": kind, "pos": int(pos), "has_gauss": int(has_gauss), "cached_gaussian": float(cached)},
            "python": {"version": version, "internal": list(internal), "gauss_next": gauss_next}}
    return tensors, meta


def _set_rng_state(tensors: dict[str, torch.Tensor], meta: dict[str, Any]) -> None:
    torch.set_rng_state(tensors["rng/torch"])
    n = meta["numpy"]
    np.random.set_state((n["kind"], tensors["rng/numpy"].numpy().astype(np.uint32), n["pos"], n["has_gauss"],
                         n["cached_gaussian"]))
    p = meta["python"]
    random.setstate((p["version"], tuple(p["internal"]), p["gauss_next"]))


def _configs(trainer: Trainer) -> dict[str, Any]:
    return {name: dataclasses.asdict(cfg) for name, cfg in (
        ("model", trainer.model_cfg), ("learner", trainer.cfg), ("reward", trainer.reward_cfg),
        ("task", trainer.task_cfg), ("exploration", trainer.exploration_cfg))}


def save_checkpoint(trainer: Trainer, run_dir: str | Path) -> Path:
    """Write the trainer's complete state as RUN_DIR/checkpoints/ckpt-<updates>; returns that directory."""
    root = checkpoint_dir(run_dir)
    root.mkdir(parents=True, exist_ok=True)
    name = f"ckpt-{trainer.updates:09d}"
    final, tmp = root / name, root / f".{name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()

    tensors = {f"model/{k}": v for k, v in state_dict_to_tensors(trainer.model).items()}
    if trainer.target is not None:
        tensors.update({f"target/{k}": v for k, v in state_dict_to_tensors(trainer.target).items()})
    for pname, param in trainer.model.named_parameters():
        buf = trainer.optimizer.state.get(param, {}).get("momentum_buffer")
        if buf is not None:
            tensors[f"momentum/{pname}"] = buf.detach().cpu().contiguous()
    rng_tensors, rng_meta = _rng_state()
    tensors.update(rng_tensors)
    state = {"format": FORMAT_VERSION, "updates": trainer.updates, "seed": trainer.seed,
             "exploration": trainer.exploration.state_dict(), "rng": rng_meta, "config": _configs(trainer)}
    _fsync_write(tmp / "tensors.safetensors", safetensors.torch.save(tensors, metadata={"format": "pt"}))
    _fsync_write(tmp / "state.json", json.dumps(state, indent=1).encode())
    fsync_directory(tmp)
    if final.exists():  # e.g. the shutdown checkpoint right after a periodic one at the same update
        old = root / f".{name}.old-{os.getpid()}"
        final.rename(old)
        tmp.rename(final)
        shutil.rmtree(old, ignore_errors=True)
    else:
        tmp.rename(final)
    fsync_directory(root)
    _fsync_write(root / f".{LATEST}.tmp", name.encode())
    os.replace(root / f".{LATEST}.tmp", root / LATEST)
    fsync_directory(root)
    _prune(root, trainer.cfg.keep_checkpoints, keep=name)
    logger.info("checkpoint %s written (update %d)", final, trainer.updates)
    return final


def _prune(root: Path, keep_count: int, keep: str) -> None:
    """Delete all but the newest `keep_count` complete checkpoints (never `keep`)."""
    done = sorted(p for p in root.glob("ckpt-*") if p.is_dir())
    for p in done[:-keep_count]:
        if p.name != keep:
            shutil.rmtree(p, ignore_errors=True)


def latest_checkpoint(run_dir: str | Path) -> Path | None:
    """The newest complete checkpoint of a run (named by LATEST), or None if there is none."""
    root = checkpoint_dir(run_dir)
    try:
        name = (root / LATEST).read_text().strip()
    except FileNotFoundError:
        return None
    path = root / name
    if not (name.startswith("ckpt-") and (path / "state.json").is_file()):
        raise FileNotFoundError(f"{root / LATEST} names {name!r}, which is not a complete checkpoint")
    return path


def load_checkpoint(trainer: Trainer, run_dir: str | Path, path: str | Path | None = None) -> Path:
    """Restore the trainer (and the global RNGs) from the run's latest checkpoint, or from `path`."""
    ckpt = Path(path) if path is not None else latest_checkpoint(run_dir)
    if ckpt is None:
        raise FileNotFoundError(f"no checkpoint in {checkpoint_dir(run_dir)}")
    state = json.loads((ckpt / "state.json").read_text())
    if state.get("format") != FORMAT_VERSION:
        raise ValueError(f"{ckpt} has checkpoint format {state.get('format')!r}; this learner reads "
                         f"{FORMAT_VERSION}")
    saved_cfg, now_cfg = state["config"], _configs(trainer)
    for section in ("model", "task"):
        if saved_cfg[section] != now_cfg[section]:
            raise ValueError(f"{ckpt} was trained with {section} config {saved_cfg[section]}, "
                             f"but this learner has {now_cfg[section]}: resume with the run's config")
    changed = [s for s in now_cfg if saved_cfg.get(s) != now_cfg[s]]
    if changed:
        logger.warning("resuming %s with changed config sections %s", ckpt, changed)
    tensors = safetensors.torch.load_file(str(ckpt / "tensors.safetensors"))
    load_tensors(trainer.model, {k[6:]: v for k, v in tensors.items() if k.startswith("model/")})
    if trainer.target is not None:
        target = {k[7:]: v for k, v in tensors.items() if k.startswith("target/")}
        if target:
            load_tensors(trainer.target, target)
        else:  # the run had no target net: start it from the online weights
            trainer.sync_target()
    trainer.optimizer.state.clear()
    for pname, param in trainer.model.named_parameters():
        buf = tensors.get(f"momentum/{pname}")
        if buf is not None:
            if buf.shape != param.shape:
                raise ValueError(f"{ckpt}: momentum/{pname} has shape {tuple(buf.shape)}, "
                                 f"expected {tuple(param.shape)}")
            trainer.optimizer.state[param]["momentum_buffer"] = torch.empty_like(param).copy_(buf)
    trainer.updates = int(state["updates"])
    trainer.exploration.load_state_dict(state["exploration"])
    _set_rng_state(tensors, state["rng"])
    logger.info("resumed from %s (update %d)", ckpt, trainer.updates)
    return ckpt
