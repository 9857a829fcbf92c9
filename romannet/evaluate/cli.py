"""`romannet eval`: the paper's evaluation protocol on a checkpoint, as a command.

    romannet eval runs/stack-h4 --task stacking --goal-height 2 3 4 5
    romannet eval runs/clutter --task clutter --objects 30 --object-set novel --protocol frozen
    romannet eval runs/clutter/checkpoints/ckpt-000002000 --task arrangement --cases my_cases/
    romannet eval runs/clutter --task arrangement --cases heldout --protocol frozen

CHECKPOINT is a run directory (its newest checkpoint is used) or one checkpoint directory. The run's
config.toml gives the model, workspace, camera, reward and simulator; --task and the task flags say what
to test on; --set changes any other field (e.g. --set sim.robot=gripper). Outputs go to
<run>/eval/<task>-<protocol>-<time>/ (or --out): report.md, report.json, report.png and runs.jsonl.

Several checkpoints (the seeds of one recipe, the variants of an ablation) are tested one after another on
the same scenes; --out DIR is then required: each checkpoint's outputs go to DIR/<name>/ (name: its run
directory's name, or run-ckpt for a checkpoint directory) and their comparison, with the mean and range of
every metric over the checkpoints, to DIR/comparison.md, .json and .png:

    romannet eval runs/stack-s1 runs/stack-s2 runs/stack-s3 --goal-height 4 --protocol frozen --out cmp/

--policy oracle (the scripted oracle: the simulator's ceiling) or --policy random (random valid actions: the
floor) runs through the same protocol, seeds and report without a checkpoint. CHECKPOINT is then optional:
given, its run's config.toml is used; else --config or the defaults, and --task unless the config names
one. Neither learns, so both run frozen. Outputs: <run>/eval/<policy>-<task>-frozen-<time>/, or
eval/<policy>-<task>-frozen-<time>/ without a run (or --out):

    romannet eval --policy oracle --config configs/experiments/clutter.toml --objects 30 --runs 10
    romannet eval --policy random --task stacking --goal-height 4 --runs 10 --out eval/random-h4
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

from .policy_names import DESCRIPTION, POLICIES, SCRIPTED

log = logging.getLogger("romannet.eval")

EXAMPLE = "romannet eval runs/stack-h4 --task stacking --goal-height 2 3 4 5 --runs 30"

# The flags of one task's scenes; any other task would ignore them.
TASK_FLAGS = {"--objects": "clutter", "--object-set": "clutter", "--goal-height": "stacking", "--cases": "arrangement"}
# Tasks a net carries over to: arrangements are the clutter-trained policy's test cases (the paper trains on
# clutter and tests on them); stacking places what the removal tasks push and pick away.
TASK_FAMILY = {"clutter": "removal", "arrangement": "removal", "stacking": "stacking"}


class _Given(argparse.Action):
    """Stores the value and notes the flag in namespace.given: a default is not a choice the user made."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        setattr(namespace, self.dest, values)
        namespace.given = {*getattr(namespace, "given", ()), self.option_strings[0]}


def foreign_task_flags(task: str, given: set[str]) -> str | None:
    """One line on the flags given that `task`'s scenes would ignore, or None when every one applies."""
    wrong = [flag for flag in TASK_FLAGS if flag in given and TASK_FLAGS[flag] != task]
    if not wrong:
        return None
    own = " and ".join(flag for flag, t in TASK_FLAGS.items() if t == task)
    if len(wrong) == 1:
        return (f"{wrong[0]} is a {TASK_FLAGS[wrong[0]]} flag: {task} scenes would ignore it ({task} takes {own}; "
                f"or pass --task {TASK_FLAGS[wrong[0]]})")
    listing = ", ".join(f"{flag} ({TASK_FLAGS[flag]})" for flag in wrong)
    return f"{listing} are flags of other tasks: {task} scenes would ignore them ({task} takes {own})"


def task_misfit(trained: dict[str, Any] | None, task: str, use_push: bool) -> str | None:
    """How evaluating on `task` (use_push: whether its runs may push) does not fit the task config a net was
    trained with (the checkpoint's state.json), or None when it fits or the checkpoint does not say."""
    if not trained:
        return None
    kind = trained.get("kind")
    if kind in TASK_FAMILY and TASK_FAMILY.get(task) != TASK_FAMILY[kind]:
        return f"trained on {kind}, tested on {task}"
    if "use_push" in trained and bool(trained["use_push"]) != use_push:
        return (f"trained {'with' if trained['use_push'] else 'without'} pushes, tested "
                f"{'with' if use_push else 'without'} (task.use_push = {str(use_push).lower()})")
    return None


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("checkpoints", nargs="*", metavar="CHECKPOINT",
                   help="a run directory (newest checkpoint) or a ckpt-* directory; several: compared on the "
                        "same scenes (needs --out); optional with --policy oracle|random (then its run's config)")
    p.add_argument("--policy", choices=POLICIES, default="net",
                   help="net: the checkpoint's greedy policy (default); oracle: the scripted oracle (the "
                        "simulator's ceiling); random: random valid actions (the floor); both need no "
                        "checkpoint and run frozen")
    p.add_argument("--task", choices=["clutter", "arrangement", "stacking"],
                   help="default: the run's (or --config's) task; one the net was not trained for (stacking "
                        "for a clutter net, or the other way) is refused without --force")
    p.add_argument("--protocol", choices=["paper", "frozen"], default="paper",
                   help="paper: weights reset to the checkpoint every run, learning within the run (default); "
                        "frozen: no learning")
    p.add_argument("--runs", type=int, default=30, metavar="N", help="runs per test case, each a new seed (30)")
    p.add_argument("--seed", type=int, default=100000, metavar="S", help="base seed of the test scenes")
    p.add_argument("--objects", type=int, default=30, metavar="N", action=_Given,
                   help="clutter: objects per scene (30)")
    p.add_argument("--object-set", choices=["blocks", "novel"], default="blocks", action=_Given,
                   help="clutter: object set")
    p.add_argument("--cases", metavar="SET|DIR", action=_Given,
                   help="arrangement: a shipped case set, 'ours' (default) or 'heldout' (11 harder cases "
                        "nothing is tuned on), or a directory of case files")
    p.add_argument("--goal-height", type=int, nargs="+", metavar="H", action=_Given,
                   help="stacking: goal heights (default: the run's)")
    p.add_argument("--max-steps", type=int, default=0, metavar="N",
                   help="actions per run before it ends as step_limit (0: 5x the ideal count, at least 30)")
    p.add_argument("--workers", type=int, default=0, metavar="N", help="processes (0: one per CPU core)")
    p.add_argument("--out", metavar="DIR",
                   help="output directory (default: <run>/eval/<task>-<protocol>-<time>); with several "
                        "checkpoints DIR/<name>/ for each and DIR/comparison.md")
    p.add_argument("--config", metavar="FILE.toml", help="use this config instead of the run's config.toml")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="override a config field (repeatable)")
    p.add_argument("--force", action="store_true",
                   help="evaluate a net on a task it was not trained for (a warning, not an error)")


def _checkpoint_interval(run_dir: Path) -> str:
    """How often the run's learner writes a checkpoint, in words, from its config.toml."""
    from romannet.common.config import load_config

    try:
        every = load_config(run_dir / "config.toml").learner.checkpoint_every_updates
    except Exception:  # an unreadable config must not hide the message it is part of
        return "every learner.checkpoint_every_updates updates"
    return f"every {every} updates"


def resolve_checkpoint(path: Path) -> tuple[Path, Path]:
    """(checkpoint directory, run directory) for a run directory (its newest intact checkpoint), a checkpoint
    directory (verified) or a model package (models/<experiment>/: a checkpoint-like fp32 copy of its weights,
    the package standing for the run); RomannetError (one line) when none is usable."""
    if (path / "model.json").is_file():
        from romannet.models import resolve_model_dir

        return resolve_model_dir(path)[0], path
    from romannet.learner.ckpt_integrity import (
        checkpoint_candidates,
        is_checkpoint_dir,
        newest_intact,
        read_verified,
    )

    if is_checkpoint_dir(path):
        read_verified(path)  # a damaged one: CheckpointDamaged, one line naming it and what is wrong
        return path, path.parent.parent
    if checkpoint_candidates(path):
        return newest_intact(path).path, path  # the newest intact one, each newer damaged one named in a warning
    if (path / "config.toml").is_file() or (path / "checkpoints").is_dir():
        raise RomannetError(f"{path} has no checkpoint yet: the learner writes one "
                            f"{_checkpoint_interval(path)} and when it stops")
    raise RomannetError(f"{path} is neither a checkpoint directory nor a run directory with checkpoints/ckpt-*")


def _machine() -> str:
    import torch

    from romannet.info import cpu_model

    return f"{platform.machine()} {cpu_model() or 'CPU'}, {os.cpu_count()} cores, torch {torch.__version__}"


@dataclass(frozen=True)
class CheckpointPlan:
    """One checkpoint's (or scripted policy's) evaluation, resolved and validated before any run starts."""

    path: Path | None  # as given (None: a scripted policy without a run)
    ckpt: Path | None  # None for the oracle and random policies
    run_dir: Path | None
    config_path: Path | None  # None: the defaults
    config_toml: str
    state: dict
    task: str
    heights: list[int]
    cases_dir: str | None
    specs: list  # of runner.RunSpec
    policy: str = "net"
    warnings: tuple[str, ...] = ()  # what the report must say about the net (untrained, forced onto a task)

    @property
    def name(self) -> str:
        """The run directory's name, plus the checkpoint's when a ckpt-* directory was given."""
        if self.ckpt is None or self.path is None or self.run_dir is None:
            return self.policy
        if self.path.resolve() == self.ckpt.resolve():
            return f"{self.run_dir.name}-{self.ckpt.name}"
        return self.run_dir.name


def plan_checkpoint(args: argparse.Namespace, path: Path) -> CheckpointPlan:
    """Resolve a checkpoint, load and check its config, and plan its runs; RomannetError on bad input."""
    from romannet.common.config import as_saved, load_config, load_saved_config

    ckpt, run_dir = resolve_checkpoint(path)
    config_path = Path(args.config) if args.config else run_dir / "config.toml"
    if not config_path.is_file():
        raise RomannetError(f"{config_path} does not exist: pass --config with the config the checkpoint was "
                            "trained with")
    cfg = (load_config if args.config else load_saved_config)(config_path, args.overrides)
    state = json.loads((ckpt / "state.json").read_text())
    trained_model = as_saved(state.get("config", {})).get("model")
    if trained_model is not None and trained_model != json.loads(json.dumps(_as_dict(cfg.model))):
        raise RomannetError(f"{ckpt} was trained with model config {trained_model}; the config says "
                            f"{_as_dict(cfg.model)}")
    task = args.task or cfg.task.kind
    foreign = foreign_task_flags(task, getattr(args, "given", set()))
    if foreign is not None:
        raise RomannetError(foreign)
    warnings: list[str] = []
    misfit = task_misfit(state.get("config", {}).get("task"), task, cfg.task.use_push)
    if misfit is not None:
        if not args.force:
            raise RomannetError(f"{path} does not fit this evaluation: {misfit} (pass --force to evaluate it "
                                "anyway)")
        warnings.append(f"the net was {misfit} (--force)")
    if state.get("updates") == 0:
        warnings.append("update 0: an untrained net, so these numbers say nothing about learning")
    plan = _plan_tests(args, cfg, path=path, ckpt=ckpt, run_dir=run_dir, config_path=config_path, state=state,
                       task=task, warnings=warnings)
    for warning in warnings:
        log.warning("%s: %s", path, warning)
    return plan


def plan_scripted(args: argparse.Namespace) -> CheckpointPlan:
    """The plan of --policy oracle|random: the config of the run given (if any), of --config or the defaults."""
    from romannet.common.config import load_config

    if len(args.checkpoints) > 1:
        raise RomannetError(f"--policy {args.policy} takes at most one CHECKPOINT (whose run's config it uses), "
                            f"got {len(args.checkpoints)}")
    path = Path(args.checkpoints[0]) if args.checkpoints else None
    run_dir = None
    if path is not None:
        run_dir = path.parent.parent if (path / "tensors.safetensors").is_file() else path
    config_path = Path(args.config) if args.config else (run_dir / "config.toml" if run_dir else None)
    if config_path is not None and not config_path.is_file():
        raise RomannetError(f"{config_path} does not exist: pass --config with a recipe (e.g. "
                            "configs/experiments/clutter.toml)")
    cfg = load_config(config_path, args.overrides)
    names_task = config_path is not None or any(o.split("=", 1)[0].strip() == "task.kind" for o in args.overrides)
    if not args.task and not names_task:
        raise RomannetError(f"--policy {args.policy} without a run or --config: pass --task (clutter, arrangement "
                            "or stacking)")
    return _plan_tests(args, cfg, path=path, ckpt=None, run_dir=run_dir, config_path=config_path, state={},
                       task=args.task or cfg.task.kind)


def _plan_tests(args: argparse.Namespace, cfg: Any, *, path: Path | None, ckpt: Path | None,
                run_dir: Path | None, config_path: Path | None, state: dict, task: str,
                warnings: list[str] | None = None) -> CheckpointPlan:
    """The runs of an evaluation (cases, heights, seeds) under cfg; RomannetError on bad task flags."""
    from romannet.actor.sim.arrangements import cases_dir as resolve_cases_dir
    from romannet.actor.sim.arrangements import load_case
    from romannet.common.configbase import dumps_toml

    from .protocol import plan_runs

    foreign = foreign_task_flags(task, getattr(args, "given", set()))
    if foreign is not None:
        raise RomannetError(foreign)

    case_files: list[Path] = []
    case_objects: list[int] = []
    if task == "arrangement":
        cases_dir = resolve_cases_dir(args.cases)
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
                          cases_dir=str(case_files[0].parent) if case_files else None, specs=specs,
                          policy=args.policy, warnings=tuple(warnings or ()))


def effective_protocol(args: argparse.Namespace) -> str:
    """The protocol runs follow: the one asked for on a net; frozen for the oracle and random (they never learn)."""
    return "frozen" if args.policy in SCRIPTED else args.protocol


def _header_policy(args: argparse.Namespace, plan: CheckpointPlan) -> dict[str, Any]:
    """What acted, for the report's header; for a scripted policy a note that it ran frozen."""
    fields: dict[str, Any] = {"policy": plan.policy, "policy_description": DESCRIPTION[plan.policy]}
    if plan.policy == "net":  # "auto" differs by CPU (bf16, int8 or fp32), and so may a near-tied decision
        from romannet.common.config import load_config_text
        from romannet.common.policy import resolve_inference_precision

        fields["precision"] = resolve_inference_precision(load_config_text(plan.config_toml).model.precision)
    if plan.policy in SCRIPTED:
        fields["protocol_note"] = f"the {plan.policy} policy does not learn: evaluated frozen"
        if args.protocol == "paper":
            fields["protocol_note"] += " (--protocol paper applies to a net only)"
    return fields


def evaluate(args: argparse.Namespace, plan: CheckpointPlan, out_dir: Path) -> dict[str, Any]:
    """Run one checkpoint's plan into out_dir; write and print its report; return it."""
    from romannet.progress import Progress

    from .metrics import RunLog, completed
    from .protocol import execute, run_fields
    from .report import build_report, markdown, write_outputs
    from .runner import EvalSetup

    cores = os.cpu_count() or 1
    workers = min(args.workers or cores, len(plan.specs))
    out_dir.mkdir(parents=True, exist_ok=True)
    journal = out_dir / "runs.jsonl"
    (out_dir / "config.toml").write_text(plan.config_toml, encoding="utf-8")
    protocol = effective_protocol(args)
    setup = EvalSetup(config_toml=plan.config_toml, checkpoint=str(plan.ckpt or ""), protocol=protocol,
                      threads=max(1, cores // workers), policy=plan.policy)
    log.info("evaluating %s on %s (%s protocol): %d runs on %d worker(s), output in %s", plan.ckpt or plan.policy,
             plan.task, protocol, len(plan.specs), workers, out_dir)
    start = time.monotonic()
    done = {"runs": 0, "completed": 0}

    def on_run(run: RunLog) -> None:
        done["runs"] += 1
        done["completed"] += int(completed(run))
        progress.update(done["runs"], run_fields(done["completed"], run),
                        force=done["runs"] == len(plan.specs))

    with Progress("eval", total=len(plan.specs), unit="runs", initial=0, window_s=600.0) as progress:
        runs = execute(setup, plan.specs, workers, journal, on_run=on_run)
    header = {"checkpoint": str(plan.ckpt) if plan.ckpt else None, "updates": plan.state.get("updates"),
              **_header_policy(args, plan), "task": plan.task, "protocol": protocol, "runs_per_case": args.runs,
              "base_seed": args.seed,
              "planned_runs": len(plan.specs), "interrupted": len(runs) < len(plan.specs), "workers": workers,
              "machine": _machine(), "date": dt.datetime.now().isoformat(timespec="seconds"),
              "wall_s": time.monotonic() - start,
              "object_set": args.object_set if plan.task == "clutter" else None,
              "num_objects": args.objects if plan.task == "clutter" else None,
              "goal_heights": plan.heights if plan.task == "stacking" else None,
              "cases_dir": plan.cases_dir, "overrides": list(args.overrides),
              "config": str(plan.config_path) if plan.config_path else "defaults", "warnings": list(plan.warnings)}
    report = build_report(runs, header)
    paths = write_outputs(report, out_dir)
    print(markdown(report))
    print(f"written: {', '.join(str(p) for p in paths.values())}")
    return report


def default_out_dir(args: argparse.Namespace, plan: CheckpointPlan, stamp: str) -> Path:
    """<run>/eval/<task>-<protocol>-<time> for a net; [<run>/]eval/<policy>-<task>-frozen-<time> otherwise."""
    prefix = f"{plan.policy}-" if plan.policy in SCRIPTED else ""
    return (plan.run_dir or Path()) / "eval" / f"{prefix}{plan.task}-{effective_protocol(args)}-{stamp}"


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
    if args.policy in SCRIPTED:
        plans = [plan_scripted(args)]
    else:
        if not paths:
            raise RomannetError("no CHECKPOINT: pass a run directory or a ckpt-* directory, or --policy oracle|random")
        if len(paths) > 1 and not args.out:
            raise RomannetError(f"{len(paths)} checkpoints: pass --out DIR (each checkpoint's report goes to "
                                "DIR/<name>/, their comparison to DIR/comparison.md)")
        plans = [plan_checkpoint(args, p) for p in paths]  # every input checked before the first run
    _same_tests(plans)
    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    names = unique_names([p.name for p in plans])
    if len(plans) == 1:
        out_dirs = [Path(args.out) if args.out else default_out_dir(args, plans[0], stamp)]
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
