"""`romannet eval`: the paper's evaluation protocol on a checkpoint, as a command.

    romannet eval runs/stack-h4 --task stacking --goal-height 2 3 4 5
    romannet eval runs/clutter --task clutter --objects 30 --object-set novel --protocol frozen
    romannet eval runs/clutter/checkpoints/ckpt-000002000 --task arrangement --cases my_cases/

CHECKPOINT is a run directory (its newest checkpoint is used) or one checkpoint directory. The run's
config.toml gives the model, workspace, camera, reward and simulator; --task and the task flags say what
to test on; --set changes any other field (e.g. --set sim.robot=gripper). Outputs go to
<run>/eval/<task>-<protocol>-<time>/ (or --out): report.md, report.json, report.png and runs.jsonl.

Several checkpoints (the seeds of one recipe, the variants of an ablation) are tested one after another on
the same scenes; --out DIR is then required: each checkpoint's outputs go to DIR/<name>/ (name: its run
directory's name, or run-ckpt for a checkpoint directory) and their comparison, with the mean and range of
every metric over the checkpoints, to DIR/comparison.md, .json and .png:

    romannet eval runs/stack-s1 runs/stack-s2 runs/stack-s3 --goal-height 4 --protocol frozen --out cmp/
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import os
import platform
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from romannet.common.errors import RomannetError

log = logging.getLogger("romannet.eval")

EXAMPLE = "romannet eval runs/stack-h4 --task stacking --goal-height 2 3 4 5 --runs 30"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("checkpoints", nargs="+", metavar="CHECKPOINT",
                   help="a run directory (newest checkpoint) or a ckpt-* directory; several: compared on the "
                        "same scenes (needs --out)")
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
    p.add_argument("--out", metavar="DIR",
                   help="output directory (default: <run>/eval/<task>-<protocol>-<time>); with several "
                        "checkpoints DIR/<name>/ for each and DIR/comparison.md")
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


@dataclass(frozen=True)
class CheckpointPlan:
    """One checkpoint's evaluation, resolved and validated before any run starts."""

    path: Path  # as given
    ckpt: Path
    run_dir: Path
    config_path: Path
    config_toml: str
    state: dict
    task: str
    heights: list[int]
    cases_dir: str | None
    specs: list  # of runner.RunSpec

    @property
    def name(self) -> str:
        """The run directory's name, plus the checkpoint's when a ckpt-* directory was given."""
        if self.path.resolve() == self.ckpt.resolve():
            return f"{self.run_dir.name}-{self.ckpt.name}"
        return self.run_dir.name


def plan_checkpoint(args: argparse.Namespace, path: Path) -> CheckpointPlan:
    """Resolve a checkpoint, load and check its config, and plan its runs; RomannetError on bad input."""
    from romannet.actor.sim.arrangements import default_cases_dir, load_case
    from romannet.common.config import load_config
    from romannet.common.configbase import dumps_toml

    from .protocol import plan_runs

    ckpt, run_dir = resolve_checkpoint(path)
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
    return CheckpointPlan(path=path, ckpt=ckpt, run_dir=run_dir, config_path=config_path,
                          config_toml=dumps_toml(cfg), state=state, task=task, heights=list(heights),
                          cases_dir=str(case_files[0].parent) if case_files else None, specs=specs)


def evaluate(args: argparse.Namespace, plan: CheckpointPlan, out_dir: Path) -> dict[str, Any]:
    """Run one checkpoint's plan into out_dir; write and print its report; return it."""
    from .metrics import completed
    from .protocol import Progress, execute
    from .report import build_report, markdown, write_outputs
    from .runner import EvalSetup

    cores = os.cpu_count() or 1
    workers = min(args.workers or cores, len(plan.specs))
    out_dir.mkdir(parents=True, exist_ok=True)
    journal = out_dir / "runs.jsonl"
    (out_dir / "config.toml").write_text(plan.config_toml, encoding="utf-8")
    setup = EvalSetup(config_toml=plan.config_toml, checkpoint=str(plan.ckpt), protocol=args.protocol,
                      threads=max(1, cores // workers))
    progress = Progress(len(plan.specs))
    log.info("evaluating %s on %s (%s protocol): %d runs on %d worker(s), output in %s", plan.ckpt, plan.task,
             args.protocol, len(plan.specs), workers, out_dir)
    start = time.monotonic()
    runs = execute(setup, plan.specs, workers, journal, on_run=lambda r: progress.update(r, completed(r)))
    header = {"checkpoint": str(plan.ckpt), "updates": plan.state.get("updates"), "task": plan.task,
              "protocol": args.protocol, "runs_per_case": args.runs, "base_seed": args.seed,
              "planned_runs": len(plan.specs), "interrupted": len(runs) < len(plan.specs), "workers": workers,
              "machine": _machine(), "date": dt.datetime.now().isoformat(timespec="seconds"),
              "wall_s": time.monotonic() - start,
              "object_set": args.object_set if plan.task == "clutter" else None,
              "num_objects": args.objects if plan.task == "clutter" else None,
              "goal_heights": plan.heights if plan.task == "stacking" else None,
              "cases_dir": plan.cases_dir, "overrides": list(args.overrides), "config": str(plan.config_path)}
    report = build_report(runs, header)
    paths = write_outputs(report, out_dir)
    print(markdown(report))
    print(f"written: {', '.join(str(p) for p in paths.values())}")
    return report


def _same_tests(plans: list[CheckpointPlan]) -> None:
    """Checkpoints compared must meet the same scenes: same task, cases, seeds and step limits."""
    first = plans[0]
    for plan in plans[1:]:
        if plan.specs != first.specs:
            raise RomannetError(
                f"{plan.path} would be tested on {plan.task} {sorted({s.case for s in plan.specs})} and "
                f"{first.path} on {first.task} {sorted({s.case for s in first.specs})}: compared checkpoints need "
                "the same tests (pass --task and its flags, e.g. --goal-height)")


def run(args: argparse.Namespace) -> int:
    from .compare import compare, markdown, unique_names, write_comparison

    paths = [Path(p) for p in args.checkpoints]
    if len(paths) > 1 and not args.out:
        raise RomannetError(f"{len(paths)} checkpoints: pass --out DIR (each checkpoint's report goes to "
                            "DIR/<name>/, their comparison to DIR/comparison.md)")
    plans = [plan_checkpoint(args, p) for p in paths]  # every input checked before the first run
    _same_tests(plans)
    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    names = unique_names([p.name for p in plans])
    if len(plans) == 1:
        default = plans[0].run_dir / "eval" / f"{plans[0].task}-{args.protocol}-{stamp}"
        out_dirs = [Path(args.out) if args.out else default]
    else:
        out_dirs = [Path(args.out) / name for name in names]
    for out_dir in out_dirs:
        journal = out_dir / "runs.jsonl"
        if journal.exists() and journal.stat().st_size:
            raise RomannetError(f"{journal} already holds runs: choose another --out")
    reports: dict[str, dict[str, Any]] = {}
    for k, (plan, name, out_dir) in enumerate(zip(plans, names, out_dirs, strict=True)):
        if len(plans) > 1:
            log.info("checkpoint %d of %d: %s", k + 1, len(plans), name)
        reports[name] = evaluate(args, plan, out_dir)
        if reports[name]["interrupted"]:
            break
    if len(plans) > 1:
        comparison = compare(reports)
        comparison["interrupted"] = comparison["interrupted"] or len(reports) < len(plans)
        written = write_comparison(comparison, Path(args.out))
        print(markdown(comparison))
        print(f"written: {', '.join(str(p) for p in written.values())}")
    return 130 if any(r["interrupted"] for r in reports.values()) else 0


def _as_dict(cfg: object) -> dict:
    from romannet.common.configbase import to_dict

    return to_dict(cfg)
