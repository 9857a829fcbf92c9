"""`romannet models`: shipped pretrained policies, one directory per experiment under models/.

    romannet models pack runs/clutter --eval runs/clutter/eval/clutter-frozen-20260101-120000 --out models/clutter
    romannet models check models/clutter
    romannet models check models/clutter --init --config configs/experiments/clutter.toml

A package, models/<experiment>/ (at most MAX_PACKAGE_BYTES in all):

    weights.safetensors   the online net's state dict in bf16; BN running statistics fp32, counters int64
    config.toml           the resolved config the run trained with
    report.json report.md the evaluation report of these weights (copied from a `romannet eval` output)
    model.json            source run and checkpoint, updates, training actions, sha256 of the weights, date

Reading casts every tensor back to fp32 (exact), so what an actor or a learner loads is the bf16 rounding of
the trained weights: bf16 halves a package and moves Q maps by under 1 % of their range, no greedy action
changed (docs/journal.md, "Measurements behind code comments"); the BN statistics stay fp32 for 77 kB.

`pack` refuses to replace a package unless the new report's main metric (overall completion rate) is
better than the old one's on the same tests; --force replaces anyway. A package is used wherever a run or
a checkpoint is: `romannet up --init-from` / `romannet learner --init-from` (learner/checkpoint.py reads
it), and `romannet eval` through `resolve_model_dir`, which writes its fp32 weights once as a
checkpoint-like directory in a cache (ROMANNET_CACHE_DIR, else $XDG_CACHE_HOME/romannet or
~/.cache/romannet).
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import hashlib
import json
import logging
import os
import shutil
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import safetensors.torch

from romannet.common.config import as_saved, load_config, load_saved_config
from romannet.common.configbase import dumps_toml, to_dict
from romannet.common.errors import RomannetError
from romannet.learner.checkpoint import (
    PACKAGE_CONFIG,
    PACKAGE_FORMAT,
    PACKAGE_META,
    PACKAGE_WEIGHTS,
    architecture,
    check_tensors,
    from_package_dtypes,
    is_model_package,
    read_checkpoint_model,
    read_init_weights,
    read_package,
    sha256_file,
    to_package_dtypes,
    weights_source,
)
from romannet.learner.ckpt_integrity import read_verified, write_checkpoint_files

log = logging.getLogger("romannet.models")

MAX_PACKAGE_BYTES = 15_000_000
REPORT_FILES = ("report.json", "report.md")
MAIN_METRIC = "completion_rate"  # the paper's first metric, of report.json's "overall" row
# What makes two reports' numbers comparable: the same tests (runs per case only changes their noise).
SETTINGS_KEYS = ("task", "protocol", "object_set", "num_objects", "goal_heights")


def main_metric(report: Mapping[str, Any]) -> float | None:
    """The report's overall completion rate, None when no run finished."""
    overall = report.get("overall")
    return None if not isinstance(overall, Mapping) else overall.get(MAIN_METRIC)


def eval_settings(report: Mapping[str, Any]) -> dict[str, Any]:
    """The tests a report ran: task, protocol, task settings and its case names."""
    return {**{k: report.get(k) for k in SETTINGS_KEYS}, "cases": sorted(report.get("cases") or {})}


def replace_refusal(out: Path, old: Mapping[str, Any], new: Mapping[str, Any]) -> str | None:
    """Why the package in `out` (report `old`) must not be replaced by one with report `new`; None if it may."""
    if eval_settings(old) != eval_settings(new):
        return (f"{out} holds a model evaluated on {eval_settings(old)}, the new report is of "
                f"{eval_settings(new)}: not comparable (pass --force to replace it anyway)")
    before, after = main_metric(old), main_metric(new)
    if before is not None and (after is None or after <= before):
        return (f"{out} holds a model with {MAIN_METRIC} {before:.1%}; the new one has "
                f"{'none' if after is None else f'{after:.1%}'}, not better (pass --force to replace it anyway)")
    return None


def check_report(report: Mapping[str, Any], updates: int, eval_dir: Path) -> None:
    """A report fit to ship with a checkpoint: finished runs, not interrupted, of that checkpoint's update."""
    if report.get("policy", "net") != "net":
        raise RomannetError(f"{eval_dir / 'report.json'} evaluated the {report.get('policy')} policy, not a checkpoint")
    if main_metric(report) is None:
        raise RomannetError(f"{eval_dir / 'report.json'} has no finished run: evaluate the checkpoint first")
    if report.get("interrupted"):
        raise RomannetError(f"{eval_dir / 'report.json'} is of an interrupted evaluation: run it to the end")
    if report.get("updates") != updates:
        raise RomannetError(f"{eval_dir / 'report.json'} evaluated update {report.get('updates')}, the checkpoint "
                            f"is at update {updates}: pack the checkpoint directory that was evaluated")


def training_actions(run_dir: Path, updates: int) -> int | None:
    """Transitions the replay held when the learner made update `updates` (metrics.csv's replay_inserts, the
    row of that update or the last one before it); None if the run has no such record."""
    best: tuple[int, int] | None = None
    try:
        with open(run_dir / "metrics.csv", newline="", encoding="utf-8") as f:
            for row in csv.DictReader(f):
                try:
                    update, inserts = int(float(row["update"])), int(float(row["replay_inserts"]))
                except (KeyError, TypeError, ValueError):
                    continue
                if update <= updates and (best is None or update >= best[0]):
                    best = (update, inserts)
    except OSError:
        return None
    return None if best is None else best[1]


def _read_report(eval_dir: Path) -> tuple[dict[str, Any], bytes, bytes]:
    missing = [n for n in REPORT_FILES if not (eval_dir / n).is_file()]
    if missing:
        raise RomannetError(f"--eval {eval_dir}: {', '.join(missing)} missing (a `romannet eval` output directory "
                            "has report.json and report.md)")
    raw = (eval_dir / "report.json").read_bytes()
    try:
        report = json.loads(raw)
    except ValueError as err:
        raise RomannetError(f"{eval_dir / 'report.json'} is not valid JSON ({err})") from None
    if not isinstance(report, dict):
        raise RomannetError(f"{eval_dir / 'report.json'} is not a report (a JSON object)")
    return report, raw, (eval_dir / "report.md").read_bytes()


def package_files(source: Path, eval_dir: Path, out: Path, now: dt.datetime | None = None) -> dict[str, bytes]:
    """The files of a package of the checkpoint `source` (or a run's newest) with the report in eval_dir."""
    kind, ckpt = weights_source(source)
    if kind == "package":
        raise RomannetError(f"{source} is already a model package: pack a run or a checkpoint directory")
    tensors, state = read_checkpoint_model(ckpt)
    run_dir = ckpt.parent.parent
    config_path = run_dir / "config.toml"
    if not config_path.is_file():
        raise RomannetError(f"{config_path} does not exist: {ckpt} is not inside a run directory")
    cfg = load_saved_config(config_path)
    trained = as_saved(state.get("config") or {}).get("model") or {}
    if architecture(trained) != architecture(cfg.model):
        raise RomannetError(f"{ckpt} was trained with model {architecture(trained)}, but {config_path} says "
                            f"{architecture(cfg.model)}")
    updates = int(state.get("updates", -1))
    report, report_json, report_md = _read_report(eval_dir)
    check_report(report, updates, eval_dir)
    packed = to_package_dtypes(tensors)
    check_tensors(from_package_dtypes(packed), cfg.model, ckpt)  # what a reader gets, e.g. no bf16 overflow
    # One metadata entry: safetensors writes several in no fixed order, and the same weights should give the
    # same bytes (and sha256) every time they are packed.
    weights = safetensors.torch.save(packed, metadata={"format": f"romannet-model-{PACKAGE_FORMAT}"})
    meta = {
        "format": PACKAGE_FORMAT, "experiment": out.name, "source_run": str(run_dir), "checkpoint": ckpt.name,
        "updates": updates, "training_actions": training_actions(run_dir, updates),
        "weights": {"file": PACKAGE_WEIGHTS, "sha256": hashlib.sha256(weights).hexdigest(), "bytes": len(weights),
                    "dtype": "bfloat16 (BN running statistics float32)"},
        "model": architecture(cfg.model), "task": cfg.task.kind,
        "main_metric": {"name": MAIN_METRIC, "value": main_metric(report), **eval_settings(report)},
        "date": (now or dt.datetime.now(dt.timezone.utc)).isoformat(timespec="seconds"),
    }
    # The resolved config, not the run's file: a run from an older version may still name removed options.
    files = {PACKAGE_WEIGHTS: weights, PACKAGE_CONFIG: dumps_toml(cfg).encode(), "report.json": report_json,
             "report.md": report_md, PACKAGE_META: (json.dumps(meta, indent=1) + "\n").encode()}
    total = sum(len(b) for b in files.values())
    if total > MAX_PACKAGE_BYTES:
        sizes = ", ".join(f"{n} {len(b) / 1e6:.1f} MB" for n, b in files.items())
        raise RomannetError(f"the package would take {total / 1e6:.1f} MB, more than {MAX_PACKAGE_BYTES / 1e6:.0f} MB "
                            f"({sizes})")
    return files


def pack(source: str | Path, eval_dir: str | Path, out: str | Path, force: bool = False) -> Path:
    """Write the package of `source` evaluated in eval_dir to `out`, replacing a package there only when
    the new report's main metric is better (or `force`); returns `out`."""
    source, eval_dir, out = Path(source), Path(eval_dir), Path(out)
    files = package_files(source, eval_dir, out)
    if out.exists() and not force:
        _refuse_replacing(out, json.loads(files["report.json"]))
    stage = out.parent / f".{out.name}.tmp-{os.getpid()}"
    shutil.rmtree(stage, ignore_errors=True)
    stage.mkdir(parents=True)
    for name, data in files.items():
        (stage / name).write_bytes(data)
    if out.exists():
        old = out.parent / f".{out.name}.old-{os.getpid()}"
        out.rename(old)
        stage.rename(out)
        shutil.rmtree(old, ignore_errors=True)
    else:
        stage.rename(out)
    meta = json.loads(files[PACKAGE_META])
    log.info("packed %s (update %d, %s %.1f %%, %.1f MB) into %s", source, meta["updates"], MAIN_METRIC,
             100 * meta["main_metric"]["value"], sum(len(b) for b in files.values()) / 1e6, out)
    return out


def _refuse_replacing(out: Path, new_report: Mapping[str, Any]) -> None:
    if not out.is_dir():
        raise RomannetError(f"--out {out} exists and is not a directory")
    if not any(out.iterdir()):
        return
    if not is_model_package(out):
        raise RomannetError(f"--out {out} holds files but no {PACKAGE_META}: not a model package, not replaced")
    try:
        old_report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        raise RomannetError(f"{out} holds a model without a readable report.json: pass --force to replace it") \
            from None
    reason = replace_refusal(out, old_report, new_report)
    if reason:
        raise RomannetError(reason)


def cache_root() -> Path:
    """Where checkpoint-like copies of packages live (see the module docstring)."""
    if os.environ.get("ROMANNET_CACHE_DIR"):
        return Path(os.environ["ROMANNET_CACHE_DIR"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "romannet"


def _cache_intact(ckpt: Path) -> bool:
    try:
        read_verified(ckpt)
    except RomannetError as err:
        log.warning("%s; writing it again", err)
        return False
    return True


def resolve_model_dir(path: str | Path) -> tuple[Path, Path]:
    """(checkpoint-like directory, config.toml) of a model package: the directory holds tensors.safetensors
    (the package's weights in fp32 under model/) and state.json (updates, model config), as a learner
    checkpoint does, so tools that read checkpoints read it; the config is the package's own. Checked as
    read_package checks; the copy is written once per weights and config (atomically) and reused."""
    path = Path(path)
    tensors, meta, cfg = read_package(path)
    config_path = path / PACKAGE_CONFIG
    key = hashlib.sha256((meta["weights"]["sha256"] + sha256_file(config_path)).encode()).hexdigest()[:16]
    updates = int(meta.get("updates") or 0)
    ckpt = cache_root() / "models" / f"{path.resolve().name}-{key}" / f"ckpt-{updates:09d}"
    if (ckpt / "state.json").is_file() and not _cache_intact(ckpt):
        shutil.rmtree(ckpt, ignore_errors=True)  # a damaged copy is written again from the (checked) package
    if not (ckpt / "state.json").is_file():
        stage = ckpt.parent / f".{ckpt.name}.tmp-{os.getpid()}"
        shutil.rmtree(stage, ignore_errors=True)
        stage.mkdir(parents=True)
        state = {"updates": updates, "package": str(path.resolve()), "weights_sha256": meta["weights"]["sha256"],
                 "config": {name: to_dict(getattr(cfg, name)) for name in
                            ("model", "learner", "reward", "task", "exploration")}}
        write_checkpoint_files(stage, {f"model/{k}": v for k, v in tensors.items()}, state)
        try:
            stage.rename(ckpt)
        except OSError:  # another process wrote the same copy first
            shutil.rmtree(stage, ignore_errors=True)
    return ckpt, config_path


def check(path: str | Path, init_config: Any | None = None) -> str:
    """One line on a package (integrity), or with init_config (a Config) on any weights source as a start
    for a run with that config (--init-from); RomannetError otherwise."""
    path = Path(path)
    if init_config is not None:
        _, what = read_init_weights(path, init_config.model)
        return f"{path}: usable by --init-from for this config: {what}"
    if not is_model_package(path):
        raise RomannetError(f"{path} has no {PACKAGE_META}: not a model package (add --init to check a run or a "
                            "checkpoint as an --init-from source)")
    tensors, meta, cfg = read_package(path)
    size = sum((path / n).stat().st_size for n in (PACKAGE_WEIGHTS, PACKAGE_CONFIG, PACKAGE_META, *REPORT_FILES)
               if (path / n).is_file())
    metric = (meta.get("main_metric") or {}).get("value")
    return (f"{path}: {cfg.task.kind} model from {meta.get('source_run')} update {meta.get('updates')}, "
            f"{len(tensors)} tensors, {size / 1e6:.1f} MB, {MAIN_METRIC} "
            f"{'-' if metric is None else f'{metric:.1%}'}, sha256 ok")


def run(args: argparse.Namespace) -> int:
    """`romannet models pack|check` for parsed CLI arguments (romannet/cli.py); returns the exit code."""
    if args.models_cmd == "pack":
        out = pack(args.source, args.eval_dir, args.out, force=args.force)
        sys.stdout.write(check(out) + "\n")
        return 0
    init_config = load_config(args.config, args.overrides) if args.init else None
    sys.stdout.write(check(args.path, init_config) + "\n")
    return 0
