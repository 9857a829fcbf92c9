"""The evaluation plan (which runs) and its execution over worker processes, with progress and a journal.

Seeds: run i of case c gets seed `base_seed + 1000 * c + i`: a new scene per run, the same scenes for
every checkpoint evaluated with the same base seed (so two policies meet the same test set).

Every finished run is appended to `runs.jsonl` in the output directory and flushed at once, so an
evaluation stopped by Ctrl-C or a crash keeps every run it finished; the report is written from whatever
is there, marked as interrupted.
"""

from __future__ import annotations

import json
import logging
import multiprocessing
import os
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import asdict
from pathlib import Path

from .metrics import RunLog, StepLog
from .runner import EvalSetup, RunSpec, Worker, init_worker, run_in_worker

log = logging.getLogger(__name__)

SEED_STRIDE = 1000  # seeds of consecutive cases are this far apart


def auto_max_steps(task: str, num_objects: int, goal_height: int) -> int:
    """A run's action limit when none is given: 5x the ideal count, at least 30 (the paper has none but
    the 10-failures rule; a policy that keeps 'succeeding' at useless pushes must still end)."""
    ideal = 2 * (goal_height - 1) if task == "stacking" else num_objects
    return max(30, 5 * ideal)


def plan_runs(task: str, runs: int, base_seed: int, *, goal_heights: Sequence[int] = (4,), num_objects: int = 30,
              object_set: str = "blocks", case_files: Sequence[Path] = (), case_objects: Sequence[int] = (),
              max_steps: int = 0) -> list[RunSpec]:
    """Every run of an evaluation, case by case."""
    if runs < 1:
        raise ValueError(f"--runs {runs}: at least one run per case")
    specs: list[RunSpec] = []
    if task == "stacking":
        cases = [(f"h{h}", dict(goal_height=h), auto_max_steps(task, 0, h)) for h in goal_heights]
    elif task == "clutter":
        cases = [(f"{object_set}-{num_objects}", dict(num_objects=num_objects, object_set=object_set),
                  auto_max_steps(task, num_objects, 0))]
    elif task == "arrangement":
        if not case_files:
            raise ValueError("no arrangement case files to evaluate")
        n_objects = list(case_objects) or [10] * len(case_files)
        cases = [(p.stem, dict(case_file=str(p)), auto_max_steps(task, n, 0)) for p, n in zip(case_files, n_objects,
                                                                                                strict=True)]
    else:
        raise ValueError(f"unknown task {task!r}: expected clutter, arrangement or stacking")
    for c, (name, fields, limit) in enumerate(cases):
        for i in range(runs):
            specs.append(RunSpec(case=name, seed=base_seed + SEED_STRIDE * c + i, task=task,
                                 max_steps=max_steps or limit, **fields))
    return specs


def run_to_json(run: RunLog) -> dict:
    d = asdict(run)
    d["steps"] = [f"{s.primitive}:{int(s.success)}" + (f":{s.cause}" if s.cause else "") for s in run.steps]
    return d


def run_from_json(d: dict) -> RunLog:
    steps = tuple(StepLog(p, bool(int(ok)), cause[0] if cause else "")
                  for p, ok, *cause in (s.split(":", 2) for s in d["steps"]))
    return RunLog(d["case"], int(d["seed"]), int(d["ideal_actions"]), d["end_reason"], steps,
                  float(d.get("duration_s", 0.0)))


def read_journal(path: Path) -> list[RunLog]:
    """The runs of a runs.jsonl; a torn last line (the writer was killed) is skipped with a warning."""
    runs = []
    for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        try:
            runs.append(run_from_json(json.loads(line)))
        except (ValueError, KeyError, TypeError) as err:
            log.warning("%s line %d is not a whole run record (%s); skipped", path, n, err)
    return runs


def run_fields(completed: int, last: RunLog) -> list[str]:
    """The evaluation's progress fields, most important first."""
    return [f"{completed} completed", f"last {last.case} seed {last.seed}: {last.end_reason} in {last.actions} actions"]


def execute(setup: EvalSetup, specs: Sequence[RunSpec], workers: int, journal: Path,
            on_run: Callable[[RunLog], None] | None = None) -> list[RunLog]:
    """Run every spec on `workers` processes (1: in this process), journaling each finished run.

    KeyboardInterrupt stops handing out runs; the ones finished so far are returned (and journaled).
    """
    results: list[RunLog] = []
    with open(journal, "a", encoding="utf-8") as out:
        def record(run: RunLog) -> None:
            out.write(json.dumps(run_to_json(run)) + "\n")
            out.flush()
            os.fsync(out.fileno())
            results.append(run)
            if on_run is not None:
                on_run(run)

        try:
            if workers <= 1:
                worker = Worker(setup)
                try:
                    for spec in specs:
                        record(worker.run(spec))
                finally:
                    worker.close()
            else:
                _execute_pool(setup, specs, workers, record)
        except KeyboardInterrupt:
            log.warning("interrupted: %d of %d runs finished (kept in %s)", len(results), len(specs), journal)
    return results


def _execute_pool(setup: EvalSetup, specs: Sequence[RunSpec], workers: int,
                  record: Callable[[RunLog], None]) -> None:
    ctx = multiprocessing.get_context("spawn")  # PyBullet and torch do not survive fork well
    pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=init_worker, initargs=(setup,))
    pending: set[Future] = set()
    queue = list(specs)[::-1]
    try:
        while queue or pending:
            while queue and len(pending) < 2 * workers:  # a short queue, so Ctrl-C has little to cancel
                pending.add(pool.submit(run_in_worker, queue.pop()))
            finished, pending = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                record(fut.result())
    except KeyboardInterrupt:  # workers ignore SIGINT: the runs under way finish and are kept
        running = {f for f in pending if not f.cancel()}
        log.warning("interrupted: finishing the %d run(s) under way", len(running))
        for fut in running:
            record(fut.result())
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
