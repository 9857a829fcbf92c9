"""A learner checkpoint's files, written whole and read back only when verified.

    RUN_DIR/checkpoints/ckpt-000001000/tensors.safetensors   weights, target net, momentum, RNG tensors
    RUN_DIR/checkpoints/ckpt-000001000/state.json            updates, LAE state, RNG states, configs
    RUN_DIR/checkpoints/ckpt-000001000/manifest.json         sha256 and size of the two files above

`write_checkpoint_files` writes the three (each fsync'ed, the manifest last, then the directory) into a
directory the caller renames into place. `read_verified` reads one back and checks everything a damaged or
half-copied checkpoint could get wrong: a file missing, a size or sha256 that is not the manifest's, JSON
that does not parse, a safetensors file that does not, tensor names, shapes or dtypes that are not the
saved model config's RoManNet, NaN or infinite values. Any of these raises CheckpointDamaged, whose
message is one line naming the directory and the problem. Format 1 checkpoints (written before manifests)
are read with every check but the checksums.

`newest_intact` is what every reader of a run directory uses (learner resume, `romannet eval`, `romannet
models`, --init-from): the newest ckpt-* directory that verifies, one warning line for each newer one that
does not; NoIntactCheckpoint when none does.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import safetensors.torch
import torch

from romannet.common.config import ModelConfig
from romannet.common.configbase import from_dict
from romannet.common.errors import RomannetError
from romannet.common.fsutil import fsync_directory
from romannet.common.model import RoManNet, validate_tensors
from romannet.common.tensor_checks import all_finite

logger = logging.getLogger(__name__)

FORMAT_VERSION = 2  # 2: with manifest.json; 1: without (still readable, no checksums)
READABLE_FORMATS = (1, 2)
TENSORS = "tensors.safetensors"
STATE = "state.json"
MANIFEST = "manifest.json"
CKPT_NAME = re.compile(r"ckpt-\d+")
TRAINING_TENSORS = ("rng/torch", "rng/numpy")  # what a resume needs beyond the weights
TRAINING_STATE = ("exploration", "rng", "config")


class CheckpointDamaged(RomannetError):
    """A checkpoint directory that is not whole; str() is one line naming it and what is wrong."""

    def __init__(self, ckpt: Path, problem: str):
        self.ckpt, self.problem = ckpt, problem
        super().__init__(f"checkpoint {ckpt} is damaged: {problem}")


class NoIntactCheckpoint(RomannetError, FileNotFoundError):
    """A run directory without a checkpoint that verifies (none at all, or all damaged)."""


@dataclass(frozen=True)
class VerifiedCheckpoint:
    """A checkpoint read back whole: its directory, every tensor and state.json."""

    path: Path
    tensors: dict[str, torch.Tensor]
    state: dict[str, Any]

    def model_tensors(self) -> dict[str, torch.Tensor]:
        """The online net's state dict."""
        return {k[len("model/"):]: v for k, v in self.tensors.items() if k.startswith("model/")}


def checkpoint_dir(run_dir: str | Path) -> Path:
    """Where a run's checkpoints live."""
    return Path(run_dir) / "checkpoints"


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _fsync_write(path: Path, data: bytes) -> None:
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())


def write_checkpoint_files(directory: Path, tensors: Mapping[str, torch.Tensor], state: Mapping[str, Any]) -> None:
    """Write tensors, state (its "format" set to FORMAT_VERSION) and their manifest into `directory`, fsync'ed."""
    blobs = {TENSORS: safetensors.torch.save(dict(tensors), metadata={"format": "pt"}),
             STATE: json.dumps({**state, "format": FORMAT_VERSION}, indent=1).encode()}
    manifest = {"format": FORMAT_VERSION,
                "files": {name: {"sha256": _sha256(data), "bytes": len(data)} for name, data in blobs.items()}}
    for name, data in blobs.items():
        _fsync_write(directory / name, data)
    _fsync_write(directory / MANIFEST, json.dumps(manifest, indent=1).encode())
    fsync_directory(directory)


def _read_bytes(ckpt: Path, name: str) -> bytes:
    try:
        return (ckpt / name).read_bytes()
    except FileNotFoundError:
        raise CheckpointDamaged(ckpt, f"{name} is missing") from None
    except OSError as err:
        raise CheckpointDamaged(ckpt, f"{name} is unreadable ({err.strerror or err})") from None


def _parse_json(ckpt: Path, name: str, data: bytes) -> dict[str, Any]:
    try:
        value = json.loads(data)
    except ValueError as err:
        raise CheckpointDamaged(ckpt, f"{name} is not valid JSON ({err})") from None
    if not isinstance(value, dict):
        raise CheckpointDamaged(ckpt, f"{name} holds {type(value).__name__}, not a JSON object")
    return value


def _check_manifest(ckpt: Path, blobs: Mapping[str, bytes]) -> None:
    """Each file's size and sha256 as manifest.json says."""
    manifest = _parse_json(ckpt, MANIFEST, _read_bytes(ckpt, MANIFEST))
    files = manifest.get("files")
    if not isinstance(files, dict):
        raise CheckpointDamaged(ckpt, f"{MANIFEST} lists no files")
    for name, data in blobs.items():
        entry = files.get(name)
        if not isinstance(entry, dict):
            raise CheckpointDamaged(ckpt, f"{MANIFEST} has no checksum for {name}")
        if entry.get("bytes") != len(data):
            raise CheckpointDamaged(ckpt, f"{name} is {len(data)} bytes, {MANIFEST} says {entry.get('bytes')} "
                                    "(truncated or half-written)")
        if entry.get("sha256") != _sha256(data):
            raise CheckpointDamaged(ckpt, f"{name} has sha256 {_sha256(data)[:12]}…, {MANIFEST} says "
                                    f"{str(entry.get('sha256'))[:12]}… (its bytes changed)")


def _check_state(ckpt: Path, state: Mapping[str, Any], training_state: bool) -> ModelConfig:
    """The state's format, update count and saved model config (returned)."""
    if state.get("format") not in READABLE_FORMATS:
        raise CheckpointDamaged(ckpt, f"{STATE} has format {state.get('format')!r}; this version reads "
                                f"{', '.join(map(str, READABLE_FORMATS))}")
    updates = state.get("updates")
    if not isinstance(updates, int) or isinstance(updates, bool) or updates < 0:
        raise CheckpointDamaged(ckpt, f"{STATE} has updates {updates!r}, not a count")
    offset = state.get("version_offset", 0)
    if not isinstance(offset, int) or isinstance(offset, bool) or offset < 0:
        raise CheckpointDamaged(ckpt, f"{STATE} has version_offset {offset!r}, not a count")
    missing = [k for k in TRAINING_STATE if k not in state] if training_state else []
    if missing:
        raise CheckpointDamaged(ckpt, f"{STATE} lacks {', '.join(missing)}")
    model = (state.get("config") or {}).get("model") if isinstance(state.get("config"), dict) else None
    if not isinstance(model, dict):
        raise CheckpointDamaged(ckpt, f"{STATE} has no config.model section")
    known = {f.name for f in dataclasses.fields(ModelConfig)}  # a field since removed does not change shapes
    try:
        return from_dict(ModelConfig, {k: v for k, v in model.items() if k in known}, "model")
    except RomannetError as err:
        raise CheckpointDamaged(ckpt, f"{STATE}: {err}") from None


def _check_tensors(ckpt: Path, tensors: Mapping[str, torch.Tensor], model_cfg: ModelConfig,
                   training_state: bool) -> None:
    """Names, shapes, dtypes and finiteness of the online net, the target net and the momentum buffers."""
    with torch.device("meta"):  # shapes and dtypes only: no memory, no initialisation
        reference = RoManNet(model_cfg)
    shapes = {k: tuple(p.shape) for k, p in reference.named_parameters()}
    groups: dict[str, dict[str, torch.Tensor]] = {"model": {}, "target": {}, "momentum": {}, "rng": {}}
    for key, value in tensors.items():
        group, _, name = key.partition("/")
        if group not in groups or not name:
            raise CheckpointDamaged(ckpt, f"{TENSORS} holds an unexpected tensor {key!r}")
        groups[group][name] = value
    if not groups["model"]:
        raise CheckpointDamaged(ckpt, f"{TENSORS} holds no model/ tensors")
    for group in ("model", "target"):
        if groups[group]:
            try:
                validate_tensors(reference, groups[group])
            except RomannetError as err:
                raise CheckpointDamaged(ckpt, f"{group}/: {err}") from None
    for name, buf in groups["momentum"].items():
        if shapes.get(name) != tuple(buf.shape):
            raise CheckpointDamaged(ckpt, f"momentum/{name} has shape {tuple(buf.shape)}, the model "
                                    f"{'has no such parameter' if name not in shapes else shapes[name]}")
        if not all_finite(buf):
            raise CheckpointDamaged(ckpt, f"momentum/{name} contains NaN or infinite values")
    missing = [k for k in TRAINING_TENSORS if training_state and k not in tensors]
    if missing:
        raise CheckpointDamaged(ckpt, f"{TENSORS} lacks {', '.join(missing)}")


def read_verified(ckpt: str | Path, training_state: bool = False) -> VerifiedCheckpoint:
    """One checkpoint directory read back and verified (module docstring); CheckpointDamaged otherwise.
    training_state: also require what a resume needs (RNG states, exploration), not only the weights."""
    ckpt = Path(ckpt)
    if not ckpt.is_dir():
        raise CheckpointDamaged(ckpt, "no such directory")
    blobs = {TENSORS: _read_bytes(ckpt, TENSORS), STATE: _read_bytes(ckpt, STATE)}
    if (ckpt / MANIFEST).exists():
        _check_manifest(ckpt, blobs)
    state = _parse_json(ckpt, STATE, blobs[STATE])
    if state.get("format") != 1 and not (ckpt / MANIFEST).exists():
        raise CheckpointDamaged(ckpt, f"{MANIFEST} is missing")
    model_cfg = _check_state(ckpt, state, training_state)
    try:
        tensors = safetensors.torch.load(blobs[TENSORS])
    except Exception as err:  # safetensors has its own error type for every kind of malformed file
        raise CheckpointDamaged(ckpt, f"{TENSORS} is not a readable safetensors file ({err})") from None
    _check_tensors(ckpt, tensors, model_cfg, training_state)
    return VerifiedCheckpoint(ckpt, tensors, state)


def checkpoint_candidates(run_dir: str | Path) -> list[Path]:
    """A run's ckpt-* directories, newest (highest update) first; temporary and moved-aside ones excluded."""
    root = checkpoint_dir(run_dir)
    if not root.is_dir():
        return []
    return sorted((p for p in root.iterdir() if CKPT_NAME.fullmatch(p.name) and p.is_dir()), reverse=True)


def is_checkpoint_dir(path: Path) -> bool:
    """A ckpt-* directory, or one holding any of a checkpoint's files (whether or not they are intact)."""
    return CKPT_NAME.fullmatch(path.name) is not None or any((path / n).is_file() for n in (TENSORS, STATE, MANIFEST))


def newest_intact(run_dir: str | Path, training_state: bool = False) -> VerifiedCheckpoint:
    """The run's newest checkpoint that verifies; a warning line for each newer damaged one skipped.
    NoIntactCheckpoint (naming how many were damaged) when there is none."""
    candidates = checkpoint_candidates(run_dir)
    for ckpt in candidates:
        try:
            return read_verified(ckpt, training_state)
        except CheckpointDamaged as err:
            logger.warning("%s; skipped, trying an older one", err)
    root = checkpoint_dir(run_dir)
    if candidates:
        raise NoIntactCheckpoint(f"none of the {len(candidates)} checkpoints in {root} is intact")
    raise NoIntactCheckpoint(f"no checkpoint in {root}")
