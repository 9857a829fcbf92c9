"""Exact, atomic, checksummed learner checkpoints as safetensors + JSON (no pickle, no torch.load).

Layout of a run directory:

    RUN_DIR/checkpoints/ckpt-000001000/tensors.safetensors   model/…, target/…, momentum/…, rng/torch, rng/numpy
    RUN_DIR/checkpoints/ckpt-000001000/state.json            updates, LAE state, numpy/python RNG, configs
    RUN_DIR/checkpoints/ckpt-000001000/manifest.json         sha256 and size of the two files above
    RUN_DIR/checkpoints/LATEST                               name of the newest complete checkpoint
    RUN_DIR/checkpoints/versions.json                        bound on the weights versions published (versions.py)

A checkpoint is written into a temporary directory, fsync'ed, renamed into place, and only then named in
LATEST (itself replaced atomically), so a crash at any moment leaves the previous checkpoint loadable.
Everything the next update depends on is saved: weights and BN statistics, the SGD momentum buffers, the
target net, the update counter, the exploration rate, and the torch / numpy / python RNG states. On a CPU
with the same thread count the update after a resume is bit-identical to the uninterrupted run's
(tests/test_checkpoint.py).

Every read goes through ckpt_integrity.py: a checkpoint is used only when its files match their manifest
and hold what the saved model config says. A resume takes the newest intact checkpoint, naming each newer
damaged one in one warning line (tests/test_checkpoint_damage.py).

Starting a run from trained weights (`--init-from`) reads the online net out of a checkpoint, a run
directory (its newest intact checkpoint) or a model package (models/<experiment>/, packed by
romannet/models.py: weights.safetensors in bf16, its config.toml and model.json with the weights' sha256);
the update counter, the optimiser and the exploration rate start fresh.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import random
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import safetensors.torch
import torch

from romannet.common.config import Config, ModelConfig, as_saved, load_saved_config
from romannet.common.errors import RomannetError
from romannet.common.exploration import ExplorationRate
from romannet.common.fsutil import fsync_directory
from romannet.common.model import RoManNet, load_tensors, state_dict_to_tensors, validate_tensors
from romannet.common.safe_names import is_safe_name

from .ckpt_integrity import (
    FORMAT_VERSION,
    VerifiedCheckpoint,
    checkpoint_candidates,
    checkpoint_dir,
    is_checkpoint_dir,
    newest_intact,
    read_verified,
    write_checkpoint_files,
)

if TYPE_CHECKING:  # only for annotations: reading weights (romannet models, --init-from checks) stays light
    from .trainer import Trainer

logger = logging.getLogger(__name__)

LATEST = "LATEST"


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


def _training_tensors(trainer: Trainer) -> dict[str, torch.Tensor]:
    """Online and target nets and SGD momentum buffers, as checkpoint tensors."""
    tensors = {f"model/{k}": v for k, v in state_dict_to_tensors(trainer.model).items()}
    if trainer.target is not None:
        tensors.update({f"target/{k}": v for k, v in state_dict_to_tensors(trainer.target).items()})
    for pname, param in trainer.model.named_parameters():
        buf = trainer.optimizer.state.get(param, {}).get("momentum_buffer")
        if buf is not None:
            tensors[f"momentum/{pname}"] = buf.detach().cpu().contiguous()
    return tensors


def save_checkpoint(trainer: Trainer, run_dir: str | Path, version_offset: int = 0) -> Path:
    """Write the trainer's complete state as RUN_DIR/checkpoints/ckpt-<updates>; returns that directory.
    version_offset: weights version minus update count of this learner (versions.py), kept for a resume."""
    root = checkpoint_dir(run_dir)
    root.mkdir(parents=True, exist_ok=True)
    name = f"ckpt-{trainer.updates:09d}"
    final, tmp = root / name, root / f".{name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    rng_tensors, rng_meta = _rng_state()
    state = {"format": FORMAT_VERSION, "updates": trainer.updates, "seed": trainer.seed,
             "version_offset": version_offset, "exploration": trainer.exploration.state_dict(), "rng": rng_meta,
             "config": _configs(trainer)}
    write_checkpoint_files(tmp, {**_training_tensors(trainer), **rng_tensors}, state)
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
    # The name comes from a file: one path component only, never a way out of the checkpoint directory.
    if not (is_safe_name(name) and name.startswith("ckpt-") and (path / "state.json").is_file()):
        raise FileNotFoundError(f"{root / LATEST} names {name!r}, which is not a complete checkpoint")
    return path


def has_checkpoints(run_dir: str | Path) -> bool:
    """Whether the run holds any ckpt-* directory, intact or not (a fresh start there would reuse its names)."""
    return bool(checkpoint_candidates(run_dir))


def load_checkpoint(trainer: Trainer, run_dir: str | Path, path: str | Path | None = None) -> VerifiedCheckpoint:
    """Restore the trainer (and the global RNGs) from `path`, else from the run's newest intact checkpoint
    (each newer damaged one is named in a warning line and skipped). CheckpointDamaged when `path` does not
    verify; NoIntactCheckpoint (a FileNotFoundError) when the run has no intact checkpoint; ValueError when
    it was trained with another model or task config."""
    ckpt = (read_verified(path, training_state=True) if path is not None
            else newest_intact(run_dir, training_state=True))
    _check_configs(trainer, ckpt)
    _restore(trainer, ckpt.tensors, ckpt.state)
    logger.info("resumed from %s (update %d)", ckpt.path, trainer.updates)
    return ckpt


def _check_configs(trainer: Trainer, ckpt: VerifiedCheckpoint) -> None:
    saved_cfg, now_cfg = as_saved(ckpt.state["config"]), _configs(trainer)
    for section in ("model", "task"):
        if saved_cfg.get(section) != now_cfg[section]:
            raise ValueError(f"{ckpt.path} was trained with {section} config {saved_cfg.get(section)}, "
                             f"but this learner has {now_cfg[section]}: resume with the run's config")
    changed = [s for s in now_cfg if saved_cfg.get(s) != now_cfg[s]]
    if changed:
        logger.warning("resuming %s with changed config sections %s", ckpt.path, changed)


def _restore(trainer: Trainer, tensors: Mapping[str, torch.Tensor], state: Mapping[str, Any]) -> None:
    """Put verified checkpoint contents into the trainer and the global RNGs."""
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
        if buf is not None:  # shape checked by read_verified
            trainer.optimizer.state[param]["momentum_buffer"] = torch.empty_like(param).copy_(buf)
    trainer.updates = int(state["updates"])
    trainer.exploration.load_state_dict(state["exploration"])
    _set_rng_state(dict(tensors), state["rng"])


# ----------------------------------------------------------------------------------------------------------
# Model packages and --init-from

PACKAGE_META = "model.json"
PACKAGE_WEIGHTS = "weights.safetensors"
PACKAGE_CONFIG = "config.toml"
PACKAGE_FORMAT = 1
# BN running statistics stay fp32 in a package: they are 0.3 % of the bytes, and a running variance rounded
# to bf16's 8 bits moves every normalised activation after it (docs/journal.md, "Measurements behind code
# comments").
FP32_IN_PACKAGE = ("running_mean", "running_var")
# The fields that make the same weights the same function: precision, channels_last and num_threads say how
# a process computes it, q_head_init only how a fresh net starts, so a run may differ from its source there.
ARCHITECTURE_FIELDS = ("channels", "residual_blocks", "rotation_harmonics")


def to_package_dtypes(tensors: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """A state dict as a package stores it: floating tensors in bf16 but BN running statistics, integers as is."""
    return {k: v.to(torch.bfloat16).contiguous() if v.is_floating_point() and not k.endswith(FP32_IN_PACKAGE)
            else v.contiguous() for k, v in tensors.items()}


def from_package_dtypes(tensors: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Every floating tensor back to fp32, what RoManNet, the learner and the actors hold (exact: bf16 ⊂ fp32)."""
    return {k: v.float() if v.is_floating_point() else v for k, v in tensors.items()}


def sha256_file(path: str | Path) -> str:
    """Hex sha256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def is_model_package(path: str | Path) -> bool:
    """A packaged model directory is recognised by its model.json."""
    return (Path(path) / PACKAGE_META).is_file()


def architecture(model: ModelConfig | Mapping[str, Any]) -> dict[str, Any]:
    """The ARCHITECTURE_FIELDS of a model config (a dataclass or its saved dict)."""
    data = dataclasses.asdict(model) if isinstance(model, ModelConfig) else dict(model)
    return {k: data.get(k) for k in ARCHITECTURE_FIELDS}


def _load_safetensors(path: Path) -> dict[str, torch.Tensor]:
    if not path.is_file():
        raise RomannetError(f"{path} does not exist")
    try:
        return safetensors.torch.load_file(str(path))
    except Exception as err:  # safetensors has its own error type for every kind of malformed file
        raise RomannetError(f"{path} is not a readable safetensors file ({err})") from None


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise RomannetError(f"{path} does not exist") from None
    except (OSError, ValueError) as err:
        raise RomannetError(f"{path} is not readable JSON ({err})") from None
    if not isinstance(data, dict):
        raise RomannetError(f"{path} holds {type(data).__name__}, not a JSON object")
    return data


def check_tensors(tensors: Mapping[str, torch.Tensor], model_cfg: ModelConfig,
                  where: Path) -> dict[str, torch.Tensor]:
    """`tensors` if they are exactly a RoManNet(model_cfg)'s names, shapes and dtypes, all finite."""
    try:
        validate_tensors(RoManNet(model_cfg), tensors)
    except RomannetError as err:
        raise RomannetError(f"{where}: {err}") from None
    return dict(tensors)


def read_package(path: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, Any], Config]:
    """(fp32 tensors, model.json, Config) of a model package, checked: every file there, the weights' sha256
    as model.json says, a valid config, and tensors that fit that config's model. RomannetError otherwise."""
    path = Path(path)
    missing = [n for n in (PACKAGE_META, PACKAGE_WEIGHTS, PACKAGE_CONFIG) if not (path / n).is_file()]
    if missing:
        raise RomannetError(f"{path} is not a complete model package: {', '.join(missing)} missing")
    meta = _read_json(path / PACKAGE_META)
    if meta.get("format") != PACKAGE_FORMAT:
        raise RomannetError(f"{path / PACKAGE_META} has format {meta.get('format')!r}; this version reads "
                            f"{PACKAGE_FORMAT}")
    expected = (meta.get("weights") or {}).get("sha256")
    actual = sha256_file(path / PACKAGE_WEIGHTS)
    if actual != expected:
        raise RomannetError(f"{path / PACKAGE_WEIGHTS} has sha256 {actual[:12]}…, model.json says "
                            f"{str(expected)[:12]}…: the file is corrupt or was replaced")
    cfg = load_saved_config(path / PACKAGE_CONFIG)
    tensors = from_package_dtypes(_load_safetensors(path / PACKAGE_WEIGHTS))
    return check_tensors(tensors, cfg.model, path / PACKAGE_WEIGHTS), meta, cfg


def read_checkpoint_model(ckpt: str | Path) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """(online net's tensors, state.json) of one checkpoint directory, verified (CheckpointDamaged otherwise)."""
    verified = read_verified(ckpt)
    return verified.model_tensors(), verified.state


def weights_source(path: str | Path) -> tuple[str, Path]:
    """("package" | "checkpoint", directory) for a model package, a checkpoint or a run directory (its newest
    intact checkpoint); RomannetError naming what was expected, or what is damaged, otherwise."""
    path = Path(path)
    if not path.is_dir():
        raise RomannetError(f"{path} is not a directory (a model package, a checkpoint or a run directory)")
    if is_model_package(path):
        return "package", path
    if is_checkpoint_dir(path):
        return "checkpoint", path
    if not has_checkpoints(path):
        raise RomannetError(f"{path} is neither a model package (model.json), a checkpoint (tensors.safetensors) "
                            "nor a run directory with checkpoints/ckpt-*")
    return "checkpoint", newest_intact(path).path


def read_init_weights(path: str | Path, model_cfg: ModelConfig) -> tuple[dict[str, torch.Tensor], str]:
    """The online net's fp32 tensors of a package, checkpoint or run directory, checked to fit a run whose model
    config is model_cfg (same architecture, then names, shapes, finite values); also a description for logs."""
    kind, where = weights_source(path)
    if kind == "package":
        tensors, meta, cfg = read_package(where)
        source_model: Mapping[str, Any] = dataclasses.asdict(cfg.model)
        what = (f"model package {where} (update {meta.get('updates')}, sha256 "
                f"{str((meta.get('weights') or {}).get('sha256'))[:12]})")
    else:
        tensors, state = read_checkpoint_model(where)
        source_model = as_saved(state.get("config") or {}).get("model") or {}
        what = f"checkpoint {where} (update {state.get('updates')})"
    theirs, ours = architecture(source_model), architecture(model_cfg)
    if theirs != ours:
        diff = [k for k in ARCHITECTURE_FIELDS if theirs[k] != ours[k]]
        raise RomannetError(f"{path} was trained with model {', '.join(f'{k}={theirs[k]}' for k in diff)}, this run "
                            f"has {', '.join(f'{k}={ours[k]}' for k in diff)}: give the run the same [model] section")
    return check_tensors(tensors, model_cfg, where), what


def start_from_weights(trainer: Trainer, tensors: Mapping[str, torch.Tensor]) -> None:
    """Put `tensors` (validated) in the online and target nets of a new run: update counter 0, no momentum,
    the exploration rate at its start."""
    load_tensors(trainer.model, tensors)
    trainer.sync_target()
    trainer.optimizer.state.clear()
    trainer.updates = 0
    trainer.exploration = ExplorationRate(trainer.exploration_cfg)
