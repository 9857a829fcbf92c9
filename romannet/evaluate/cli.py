"""`romannet eval`: the paper's evaluation protocol on a checkpoint, as a command.

    romannet eval runs/stack-h4 --task stacking --goal-height 2 3 4 5
    romannet eval runs/clutter --task clutter --objects 30 --object-set novel --protocol frozen
    romannet eval runs/clutter/checkpoints/ckpt-000002000 --task arrangement --cases my_cases/

CHECKPOINT is a run directory (its newest checkpoint is used) or one checkpoint directory. The run's
config.toml gives the model, workspace, camera, reward and simulator; --task and the task flags say what
to test on; --set changes any other field (e.g. --set sim.robot=gripper). Outputs go to
<run>/eval/<task>-<protocol>-<time>/ (or --out): report.md, report.json, report.png and runs.jsonl.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import os
import platform
import time
from pathlib import Path

from romannet.common.errors import RomannetError

log = logging.getLogger("romannet.eval")

EXAMPLE = "romannet eval runs/stack-h4 --task stacking --goal-height 2 3 4 5 --runs 30"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("checkpoint", metavar="CHECKPOINT", help="a run directory (newest checkpoint) or a ckpt-* directory")
    p.add_argument("--task", choices=["clutter", "arrangement", "stacking"], help="default: the run's task")
    p.add_argument("--protocol", choices=["paper", "frozen"], default="paper",
                   help="paper: weights reset to the checkpoint every run, learning within the run (default); "
                        "frozen: no learning")
    p.add_argument("--runs", type=int, default=30, metavar="N", help="runs per test case, each a new seed (30)")
    p.add_argument("--seed", type=int, default=100000, metavar="S", help="base seed of the test scenes")
    p.add_argument("--objects", type=int, default=30, metavar="N", help="clutter: objects per scene (30)")
    p.add_argument("--object-set", choices=["blocks", "novel"], default="blocks", help="clutter: object set")
    p.add_argument("--cases", metavar="DIR", help="arrangement: a directory of case files (default: ours)")
    p.add_argument("--goal-height", type=int, nargs="+", metavar="H", help="stacking: goal heights (default: "
                   "the run's)")
    p.add_argument("--max-steps", type=int, default=0, metavar="N",
                   help="actions per run before it ends as step_limit (0: 5x the ideal count, at least 30)")
    p.add_argument("--workers", type=int, default=0, metavar="N", help="processes (0: one per CPU core)")
    p.add_argument("--out", metavar="DIR", help="output directory (default: <run>/eval/<task>-<protocol>-<time>)")
    p.add_argument("--config", metavar="FILE.toml", help="use this config instead of the run's config.toml")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="override a config field (repeatable)")


def resolve_checkpoint(path: Path) -> tuple[Path, Path]:
    """(checkpoint directory, run directory) for a run directory or a checkpoint directory."""
    if (path / "tensors.safetensors").is_file():
        return path, path.parent.parent
    from romannet.learner.checkpoint import latest_checkpoint

    try:
        ckpt = latest_checkpoint(path)
    except FileNotFoundError as err:
        raise RomannetError(str(err)) from None
    if ckpt is None:
        raise RomannetError(f"{path} is neither a checkpoint directory nor a run directory with checkpoints/LATEST")
    return ckpt, path


def _machine() -> str:
    import torch

    from romannet.common.info import cpu_model

    return f"{platform.machine()} {cpu_model() or 'CPU'}, {os.cpu_count()} cores, torch {torch.__version__}"


def run(args: argparse.Namespace) -> int:
    from romannet.actor.sim.arrangements import default_cases_dir, load_case
    from romannet.common.config import load_config
    from romannet.common.configbase import dumps_toml

    from .metrics import completed
    from .protocol import Progress, execute, plan_runs
    from .report import build_report, markdown, write_outputs
    from .runner import EvalSetup

    ckpt, run_dir = resolve_checkpoint(Path(args.checkpoint))
    config_path = Path(args.config) if args.config else run_dir / "config.toml"
    if not config_path.is_file():
        raise RomannetError(f"{config_path} does not exist: pass --config with the config the checkpoint was "
                            "trained with")
    cfg = load_config(config_path, args.overrides)
    state = json.loads((ckpt / "state.json").read_text())
    trained_model = state.get("config", {}).get("model")
    if trained_model is not None and trained_model != json.loads(json.dumps(_as_dict(cfg.model))):
        raise RomannetError(f"{ckpt} was trained with model config {trained_model}; the config says "
                            f"{_as_dict(cfg.model)}")
    task = args.task or cfg.task.kind
    case_files: list[Path] = []
    case_objects: list[int] = []
    if task == "arrangement":
        cases_dir = Path(args.cases) if args.cases else default_cases_dir()
        case_files = sorted(p for p in cases_dir.glob("*.txt"))
        if not case_files:
            raise RomannetError(f"no case files (*.txt) in {cases_dir}")
        case_objects = [len(load_case(p, cfg.workspace)) for p in case_files]
    heights = args.goal_height or [cfg.task.goal_stack_height]
    if any(not 2 <= h <= 5 for h in heights):
        raise RomannetError(f"--goal-height {heights}: goal heights are 2..5")
    specs = plan_runs(task, args.runs, args.seed, goal_heights=heights, num_objects=args.objects,
                      object_set=args.object_set, case_files=case_files, case_objects=case_objects,
                      max_steps=args.max_steps)
    cores = os.cpu_count() or 1
    workers = min(args.workers or cores, len(specs))
    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    out_dir = Path(args.out) if args.out else run_dir / "eval" / f"{task}-{args.protocol}-{stamp}"
    out_dir.mkdir(parents=True, exist_ok=True)
    journal = out_dir / "runs.jsonl"
    if journal.exists() and journal.stat().st_size:
        raise RomannetError(f"{journal} already holds runs: choose another --out")
    (out_dir / "config.toml").write_text(dumps_toml(cfg), encoding="utf-8")
    setup = EvalSetup(config_toml=dumps_toml(cfg), checkpoint=str(ckpt), protocol=args.protocol,
                      threads=max(1, cores // workers))

    progress = Progress(len(specs))
    log.info("evaluating %s on %s (%s protocol): %d runs on %d worker(s), output in %s", ckpt, task,
             args.protocol, len(specs), workers, out_dir)
    start = time.monotonic()
    runs = execute(setup, specs, workers, journal, on_run=lambda r: progress.update(r, completed(r)))
    header = {"checkpoint": str(ckpt), "updates": state.get("updates"), "task": task, "protocol": args.protocol,
              "runs_per_case": args.runs, "base_seed": args.seed, "planned_runs": len(specs),
              "interrupted": len(runs) < len(specs), "workers": workers, "machine": _machine(),
              "date": dt.datetime.now().isoformat(timespec="seconds"), "wall_s": time.monotonic() - start,
              "object_set": args.object_set if task == "clutter" else None,
              "num_objects": args.objects if task == "clutter" else None,
              "goal_heights": heights if task == "stacking" else None,
              "cases_dir": str(case_files[0].parent) if case_files else None,
              "overrides": list(args.overrides), "config": str(config_path)}
    report = build_report(runs, header)
    paths = write_outputs(report, out_dir)
    print(markdown(report))
    print(f"written: {', '.join(str(p) for p in paths.values())}")
    return 130 if report["interrupted"] else 0


def _as_dict(cfg: object) -> dict:
    from romannet.common.configbase import to_dict

    return to_dict(cfg)
