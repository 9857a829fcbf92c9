"""`romannet sweep`: the command (flags, checks, then training, evaluations and the table, each resumable).

    romannet sweep --config configs/experiments/stacking.toml --config configs/experiments/stacking-baseline.toml \\
        --seeds 1 2 3 --max-actions 2500 --out sweeps/stack-abl

This module imports only the standard library at the top, so building the CLI parser stays fast.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from romannet.common.errors import RomannetError

if TYPE_CHECKING:
    from romannet.progress import Progress

    from .execute import Pace, StopRequests
    from .plan import RunJob, SweepPlan

log = logging.getLogger("romannet.sweep")

INTERRUPTED = 130  # the exit status of a sweep stopped by a signal (as `romannet eval`'s)
LOCK = "sweep.pid"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", dest="configs", action="append", default=[], metavar="FILE.toml", required=True,
                   help="a recipe: one variant, named by the file's stem (repeatable)")
    p.add_argument("--seeds", type=int, nargs="*", required=True, metavar="S",
                   help="training seeds: every variant is trained once per seed (config field `seed`)")
    p.add_argument("--max-actions", type=int, required=True, metavar="N", help="training actions of each run")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="the sweep's directory: manifest, runs, logs, evaluations, results.md/.json, curves.png; "
                   "the same command again resumes the sweep there")
    p.add_argument("--runs-dir", metavar="DIR", help="where the training runs go (default: <out>/runs)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="override a config value of every variant (repeatable; not seed, which --seeds sets)")
    p.add_argument("--policies", nargs="*", choices=["oracle", "random"], metavar="POLICY",
                   help="scripted rows evaluated beside the variants: oracle, random (default: both; none "
                   "when given empty)")
    e = p.add_argument_group("evaluation (frozen, the same scenes for every row; defaults: romannet eval's, on "
                             "the recipes' own task)")
    e.add_argument("--eval-task", choices=["clutter", "arrangement", "stacking"],
                   help="default: the recipes' task (they must agree)")
    e.add_argument("--eval-runs", type=int, metavar="N", help="runs per test case (30)")
    e.add_argument("--eval-seed", type=int, metavar="S", help="base seed of the test scenes (100000)")
    e.add_argument("--eval-objects", type=int, metavar="N", help="clutter: objects per scene (30)")
    e.add_argument("--eval-object-set", choices=["blocks", "novel"], help="clutter: object set (blocks)")
    e.add_argument("--eval-goal-height", type=int, nargs="+", metavar="H",
                   help="stacking: goal heights (default: the recipes')")
    e.add_argument("--eval-cases", metavar="SET|DIR",
                   help="arrangement: 'ours' (default), 'heldout' or a directory of case files")
    e.add_argument("--eval-max-steps", type=int, metavar="N",
                   help="actions per run before it ends as step_limit (0: 5x the ideal count, at least 30)")
    e.add_argument("--eval-workers", type=int, default=0, metavar="N",
                   help="evaluation processes (0: one per CPU core)")
    p.add_argument("--progress-every", type=float, default=30.0, metavar="S",
                   help="seconds between logged progress lines (default: 30; a terminal's line is redrawn "
                   "every second)")


def _eval_parser_facts() -> tuple[dict[str, Any], set[str]]:
    """`romannet eval`'s flag defaults, and the scripted policies its --policy offers (none if it has none)."""
    from romannet.evaluate.cli import add_arguments as add_eval_arguments

    p = argparse.ArgumentParser(add_help=False)
    add_eval_arguments(p)
    defaults = {k: p.get_default(k) for k in ("runs", "seed", "max_steps", "objects", "object_set")}
    action = p._option_string_actions.get("--policy")
    return defaults, set(action.choices or ()) if action is not None else set()


def _policies(asked: list[str] | None, offered: set[str]) -> tuple[str, ...]:
    from .plan import POLICIES

    if asked is None:
        available = tuple(p for p in POLICIES if p in offered)
        if len(available) < len(POLICIES):
            log.warning("this romannet eval has no --policy %s: the table gets no such row",
                        "|".join(p for p in POLICIES if p not in offered))
        return available
    missing = [p for p in asked if p not in offered]
    if missing:
        raise RomannetError(f"--policies {' '.join(asked)}: this romannet eval has no --policy {missing[0]}; drop it "
                            "from --policies")
    return tuple(dict.fromkeys(asked))


def build_plan(args: argparse.Namespace) -> SweepPlan:
    """Every input checked (recipes loaded, names, seeds, evaluation settings, --out, existing runs) before
    anything is written or started."""
    from romannet.common.config import load_config

    from .plan import SweepPlan, check_overrides, check_seeds, read_manifest, resolve_eval, variants_of

    variants = variants_of(args.configs)
    seeds = check_seeds(args.seeds)
    if args.max_actions < 1:
        raise RomannetError(f"--max-actions {args.max_actions}: each run needs at least one action")
    if args.eval_workers < 0:
        raise RomannetError(f"--eval-workers {args.eval_workers}: 0 (one per CPU core) or more")
    if args.progress_every <= 0:
        raise RomannetError(f"--progress-every {args.progress_every}: a positive number of seconds")
    overrides = check_overrides(args.overrides)
    tasks, heights = {}, {}
    for v in variants:
        try:
            cfg = load_config(v.recipe, [*overrides, f"seed={seeds[0]}"])
        except RomannetError as err:
            raise RomannetError(f"--config {v.recipe}: {err}") from None
        tasks[v.name], heights[v.name] = cfg.task.kind, cfg.task.goal_stack_height
    defaults, offered = _eval_parser_facts()
    out = Path(args.out)
    plan = SweepPlan(out=out, runs_dir=Path(args.runs_dir) if args.runs_dir else out / "runs",
                     runs_dir_given=args.runs_dir, variants=variants, seeds=seeds, max_actions=args.max_actions,
                     overrides=overrides, eval=resolve_eval(args, tasks, heights, defaults),
                     policies=_policies(args.policies, offered), eval_workers=args.eval_workers,
                     log_level=args.log_level)
    existing = read_manifest(out)
    if existing is not None:
        from .plan import check_manifest

        check_manifest(existing, plan)
        _check_not_running(out)
    for job in plan.jobs:
        _check_existing_run(plan, job)
    return plan


def _check_existing_run(plan: SweepPlan, job: RunJob) -> None:
    """A run directory already there must be this sweep's run: the config its recipe gives now."""
    from romannet.common.config import load_config, load_saved_config
    from romannet.common.configbase import to_dict

    from .plan import first_difference

    saved = job.run_dir / "config.toml"
    if not saved.is_file():
        if job.run_dir.exists() and any(job.run_dir.iterdir()):
            raise RomannetError(f"{job.run_dir} holds files but no config.toml: move it away, or pass another "
                                "--runs-dir")
        return
    try:
        there = to_dict(load_saved_config(saved))
    except RomannetError as err:
        raise RomannetError(f"{saved}: {err}") from None
    here = to_dict(load_config(job.recipe, [*plan.run_overrides(job), f'run_id="{job.name}"']))
    diff = first_difference(there, here)
    if diff is not None:
        key, a, b = diff
        raise RomannetError(f"{job.run_dir} holds a run with another config ({key} = {a!r} there, {b!r} from "
                            f"{job.recipe} now): move it away, or pass another --runs-dir")


def _check_not_running(out: Path) -> None:
    """Refuse an --out whose sweep is still running in another process (they would train the same runs)."""
    try:
        pid = int((out / LOCK).read_text().strip())
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
    except (OSError, ValueError):
        return
    if pid != os.getpid() and b"sweep" in cmdline:
        raise RomannetError(f"{out} is in use by a running `romannet sweep` (pid {pid}); stop it first")


class Sweep:
    """Trains, evaluates and tabulates a checked plan, skipping what is already on disk."""

    def __init__(self, plan: SweepPlan, stops: StopRequests, display: Progress):
        from .state import finished_report, run_actions

        self.plan, self.stops, self.display = plan, stops, display
        self.jobs = plan.jobs
        self.done = {job.name: run_actions(job.run_dir) if job.run_dir.is_dir() else 0 for job in self.jobs}
        self.at_start = dict(self.done)
        self.training_s = 0.0
        reports = {name: finished_report(d) for name, d in self.eval_dirs().items()}
        self.evaluated = {name for name, r in reports.items() if r is not None}
        self.eval_s = [float(r["wall_s"]) for r in reports.values()
                       if r is not None and isinstance(r.get("wall_s"), int | float)]

    def eval_dirs(self) -> dict[str, Path]:
        return {**{job.name: self.plan.out / "eval" / job.name for job in self.jobs},
                **{p: self.plan.out / "eval" / p for p in self.plan.policies}}

    def pace(self, extra_training_s: float = 0.0) -> Pace:
        from .execute import Pace

        total = self.plan.max_actions * len(self.jobs)
        done = sum(min(n, self.plan.max_actions) for n in self.done.values())
        evals_left = len(self.eval_dirs()) - len(self.evaluated)
        return Pace(actions_left=total - done, actions_gained=sum(self.done.values()) - sum(self.at_start.values()),
                    training_s=self.training_s + extra_training_s, evals_left=evals_left, eval_s=tuple(self.eval_s))

    def train(self, only: str | None = None) -> int | None:
        """Every run (or the one named `only`) to --max-actions, one after another; an exit code to stop with,
        or None when all are done."""
        from .execute import run_child, training_eta
        from .state import RunState, run_actions, run_state

        for i, job in enumerate(self.jobs, 1):
            if only is not None and job.name != only:
                continue
            if self.stops.count:
                return INTERRUPTED
            state = run_state(job.run_dir, self.plan.max_actions)
            if state is RunState.DONE:
                log.info("run %d of %d %s: already trained (%d actions)", i, len(self.jobs), job.name,
                         self.done[job.name])
                continue
            log_path = self.plan.out / "logs" / f"{job.name}.log"
            log.info("run %d of %d %s: %s (romannet up's output in %s)", i, len(self.jobs), job.name,
                     "resuming it" if state is RunState.PARTIAL else "training it", log_path)
            started = time.monotonic()
            self.display.restart(f"sweep: run {i} of {len(self.jobs)} {job.name}", self.plan.max_actions,
                                 "actions", short_label=f"run {i}/{len(self.jobs)} {job.name}")

            def tick(job: RunJob = job, started: float = started) -> None:
                try:
                    self.done[job.name] = run_actions(job.run_dir)
                except RomannetError:  # a ledger being replaced right now: the next tick reads it
                    pass
                eta, note = training_eta(self.pace(time.monotonic() - started))
                self.display.update(self.done[job.name], note, eta=eta)

            code = run_child(self.plan.up_argv(job, resume=state is RunState.PARTIAL), log_path, self.stops, tick)
            self.training_s += time.monotonic() - started
            self.display.clear()
            self.done[job.name] = run_actions(job.run_dir)
            if self.stops.count:
                log.info("stopped during run %s at %d/%d actions: the same command resumes it", job.name,
                         self.done[job.name], self.plan.max_actions)
                return INTERRUPTED
            if self.done[job.name] < self.plan.max_actions:
                log.error("romannet up for %s exited %d at %d/%d actions: %s (all of it in %s); the same command "
                          "resumes it", job.name, code, self.done[job.name], self.plan.max_actions,
                          _last_line(log_path), log_path)
                return 1
            if code != 0:
                log.warning("romannet up for %s reached its %d actions but exited %d (see %s)", job.name,
                            self.plan.max_actions, code, log_path)
        return None

    def evaluate(self, only: str | None = None) -> int | None:
        """Each run's newest checkpoint and each scripted policy (or the one named `only`), frozen on the same
        scenes; an exit code to stop with, or None when every evaluation is finished."""
        from .execute import eval_eta, format_duration, run_child
        from .state import finished_report

        argvs = {**{job.name: self.plan.eval_argv(job, self.plan.out / "eval" / job.name) for job in self.jobs},
                 **{p: self.plan.policy_argv(p, self.plan.out / "eval" / p) for p in self.plan.policies}}
        dirs = self.eval_dirs()
        for k, (name, argv) in enumerate(argvs.items(), 1):
            if only is not None and name != only:
                continue
            if self.stops.count:
                return INTERRUPTED
            if finished_report(dirs[name]) is not None:
                self.evaluated.add(name)
                continue
            if dirs[name].exists():  # an interrupted one: romannet eval refuses a journal that holds runs
                log.info("evaluation of %s did not finish: starting it again", name)
                shutil.rmtree(dirs[name])
            log_path = self.plan.out / "logs" / f"eval-{name}.log"
            log.info("evaluation %d of %d: %s (romannet eval's output in %s)", k, len(argvs), name, log_path)
            started = time.monotonic()
            self.display.restart(f"sweep: evaluation {k} of {len(argvs)} {name}", None, "runs",
                                 short_label=f"evaluation {k}/{len(argvs)} {name}")

            def tick(journal: Path = dirs[name] / "runs.jsonl", started: float = started) -> None:
                elapsed = time.monotonic() - started
                self.display.update(_lines(journal), [f"{format_duration(elapsed)} so far"],
                                    eta=eval_eta(elapsed, self.pace()))

            code = run_child(argv, log_path, self.stops, tick)
            self.display.clear()
            if self.stops.count:
                log.info("stopped during the evaluation of %s: the same command runs it again", name)
                return INTERRUPTED
            if code != 0 or finished_report(dirs[name]) is None:
                log.error("romannet eval of %s exited %d: %s (all of it in %s)", name, code, _last_line(log_path),
                          log_path)
                return 1
            self.eval_s.append(time.monotonic() - started)
            self.evaluated.add(name)
        return None

    def tabulate(self) -> dict[str, Path]:
        from .results import collect, markdown, plot_curves, write_results

        dirs = self.eval_dirs()
        results = collect(self.plan.manifest(), self.jobs, dirs, {p: dirs[p] for p in self.plan.policies})
        paths = write_results(results, self.plan.out)
        paths["curves"] = plot_curves(self.jobs, self.plan.out / "curves.png", self.plan.max_actions)
        print(markdown(results))
        return paths


def _lines(path: Path) -> int:
    """Lines in a file so far (the runs an evaluation has journaled); 0 before it exists."""
    try:
        return path.read_bytes().count(b"\n")
    except OSError:
        return 0


def _last_line(path: Path, tail_bytes: int = 4096) -> str:
    """The last non-empty line of a log file (what a failed child said last)."""
    try:
        with path.open("rb") as fh:
            fh.seek(max(0, path.stat().st_size - tail_bytes))
            lines = [ln.strip() for ln in fh.read().decode("utf-8", "replace").splitlines() if ln.strip()]
    except OSError:
        return "(no output)"
    return lines[-1] if lines else "(no output)"


def run(args: argparse.Namespace) -> int:
    from romannet.common.fsutil import write_json_atomic, write_text_atomic
    from romannet.progress import ClearLineFilter, Progress

    from .execute import StopRequests
    from .plan import MANIFEST

    plan = build_plan(args)
    plan.out.mkdir(parents=True, exist_ok=True)
    manifest_path = plan.out / MANIFEST
    if not manifest_path.is_file():
        write_json_atomic(manifest_path, plan.manifest(), indent=2)
    write_text_atomic(plan.out / LOCK, f"{os.getpid()}\n")
    handler = logging.FileHandler(plan.out / "sweep.log")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.addHandler(handler)
    display = Progress("sweep", log_every_s=args.progress_every, redraw_s=1.0)
    console = [h for h in root.handlers if isinstance(h, logging.StreamHandler)
               and not isinstance(h, logging.FileHandler)]
    clear = ClearLineFilter(display)
    for h in console:
        h.addFilter(clear)
    stops = StopRequests()
    try:
        log.info("sweep in %s: %d variant(s) x %d seed(s) = %d runs of %d actions, each evaluated once "
                 "trained, then %d scripted row(s) (%s)", plan.out, len(plan.variants), len(plan.seeds),
                 len(plan.jobs), plan.max_actions, len(plan.policies), json.dumps(plan.eval.as_dict()))
        sweep = Sweep(plan, stops, display)
        code = None
        for job in plan.jobs:  # each run evaluated as soon as it is trained: results arrive run by run
            code = sweep.train(only=job.name)
            if code is None:
                code = sweep.evaluate(only=job.name)
            if code is not None:
                break
        if code is None:
            code = sweep.evaluate()  # the scripted rows
        if code is None:
            paths = sweep.tabulate()
            log.info("sweep done: %s", ", ".join(str(p) for p in paths.values()))
            code = 0
        return code
    finally:
        stops.restore()
        display.clear()
        for h in console:
            h.removeFilter(clear)
        (plan.out / LOCK).unlink(missing_ok=True)
        root.removeHandler(handler)
        handler.close()
