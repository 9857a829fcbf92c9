"""What a sweep does, resolved and checked before anything starts: the variants (one recipe each), the runs,
the evaluation settings, the manifest and the command lines of the child processes.

Every check here raises RomannetError with one line; nothing is written until all of them passed.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from romannet.common.errors import RomannetError

MANIFEST = "sweep.json"
POLICIES = ("oracle", "random")  # the scripted rows beside the variants: the simulator's ceiling and the floor
TASKS = ("clutter", "arrangement", "stacking")
# What makes two sweeps the same one (a rerun resumes it); the policies and the worker count may change.
IDENTITY = ("variants", "seeds", "max_actions", "overrides", "runs_dir", "eval")


@dataclass(frozen=True)
class Variant:
    """One recipe of the sweep; its name is the file's stem."""

    name: str
    recipe: Path


@dataclass(frozen=True)
class RunJob:
    """One training run: a variant with one seed, in <runs_dir>/<variant>-s<seed>."""

    variant: str
    recipe: Path
    seed: int
    run_dir: Path

    @property
    def name(self) -> str:
        return self.run_dir.name


@dataclass(frozen=True)
class EvalSettings:
    """The frozen evaluation every row gets: the same task, scenes and seeds. Fields the task does not use
    are None, so they do not make two sweeps differ."""

    task: str
    runs: int
    seed: int
    max_steps: int
    goal_heights: tuple[int, ...] | None = None  # stacking
    objects: int | None = None  # clutter
    object_set: str | None = None  # clutter
    cases: str | None = None  # arrangement: a case directory (None: the built-in cases)

    def argv(self) -> list[str]:
        """The `romannet eval` flags of these settings."""
        out = ["--protocol", "frozen", "--task", self.task, "--runs", str(self.runs), "--seed", str(self.seed),
               "--max-steps", str(self.max_steps)]
        if self.goal_heights:
            out += ["--goal-height", *(str(h) for h in self.goal_heights)]
        if self.objects is not None:
            out += ["--objects", str(self.objects)]
        if self.object_set is not None:
            out += ["--object-set", self.object_set]
        if self.cases is not None:
            out += ["--cases", self.cases]
        return out

    def as_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["goal_heights"] = list(self.goal_heights) if self.goal_heights else None
        return out


@dataclass(frozen=True)
class SweepPlan:
    out: Path
    runs_dir: Path
    runs_dir_given: str | None
    variants: tuple[Variant, ...]
    seeds: tuple[int, ...]
    max_actions: int
    overrides: tuple[str, ...]
    eval: EvalSettings
    policies: tuple[str, ...]
    eval_workers: int
    log_level: str | None = None

    @property
    def jobs(self) -> list[RunJob]:
        """Every run, variant by variant, seed by seed (the order they are trained and tabulated in)."""
        return [RunJob(v.name, v.recipe, s, self.runs_dir / f"{v.name}-s{s}") for v in self.variants
                for s in self.seeds]

    def manifest(self) -> dict[str, Any]:
        return {"variants": [v.name for v in self.variants],
                "recipes": {v.name: str(v.recipe) for v in self.variants},
                "seeds": list(self.seeds), "max_actions": self.max_actions, "overrides": list(self.overrides),
                "runs_dir": self.runs_dir_given, "eval": self.eval.as_dict(), "policies": list(self.policies)}

    def run_overrides(self, job: RunJob) -> list[str]:
        """The --set values of a run: the sweep's, then its seed (romannet up adds the run id)."""
        return [*self.overrides, f"seed={job.seed}"]

    def up_argv(self, job: RunJob, resume: bool) -> list[str]:
        """`romannet up` for a run: fresh from its recipe, or --resume (the run's saved config.toml)."""
        argv = [*_romannet(self.log_level), "up", "--runs-dir", str(self.runs_dir), "--name", job.name,
                "--actors", "1", "--max-actions", str(self.max_actions)]
        if resume:
            return [*argv, "--resume"]
        return [*argv, "--config", str(job.recipe), *_sets(self.run_overrides(job))]

    def eval_argv(self, job: RunJob, out_dir: Path) -> list[str]:
        """`romannet eval` of a run's newest checkpoint, frozen, on the sweep's test scenes (--force: a task
        other than the run's own is the sweep's choice, --eval-task)."""
        return [*_romannet(self.log_level), "eval", str(job.run_dir), *self.eval.argv(), *self._workers(),
                "--force", "--out", str(out_dir)]

    def policy_argv(self, policy: str, out_dir: Path) -> list[str]:
        """`romannet eval --policy oracle|random` under the first recipe and the sweep's --set values."""
        first = self.variants[0]
        return [*_romannet(self.log_level), "eval", "--policy", policy, "--config", str(first.recipe),
                *_sets(self.overrides), *self.eval.argv(), *self._workers(), "--out", str(out_dir)]

    def _workers(self) -> list[str]:
        return ["--workers", str(self.eval_workers)] if self.eval_workers else []


def _romannet(log_level: str | None) -> list[str]:
    return [sys.executable, "-m", "romannet.cli", *(["--log-level", log_level] if log_level else [])]


def _sets(overrides: Sequence[str]) -> list[str]:
    return [arg for o in overrides for arg in ("--set", o)]


def _override_key(override: str) -> str:
    return override.split("=", 1)[0].strip()


def _valid_name(name: str) -> bool:
    return bool(name) and all(c.isalnum() or c in "-_" for c in name)


def variants_of(recipes: Sequence[str]) -> tuple[Variant, ...]:
    """One variant per --config, named by the file's stem; names must be unique, usable as run names and
    not those of the scripted rows."""
    if not recipes:
        raise RomannetError("no --config: pass one recipe per variant, e.g. --config configs/experiments/stacking.toml")
    variants = tuple(Variant(Path(r).stem, Path(r)) for r in recipes)
    seen: dict[str, Path] = {}
    for v in variants:
        if not _valid_name(v.name):
            raise RomannetError(f"--config {v.recipe}: its name {v.name!r} names the runs; use a file name of "
                                "letters, digits, '-' and '_'")
        if v.name in POLICIES:
            raise RomannetError(f"--config {v.recipe}: the name {v.name!r} is the {v.name} policy's row; rename the file")
        if v.name in seen:
            raise RomannetError(f"--config {seen[v.name]} and --config {v.recipe} are both variant {v.name!r} (the "
                                "file's stem names it): rename one")
        seen[v.name] = v.recipe
    return variants


def check_seeds(seeds: Sequence[int] | None) -> tuple[int, ...]:
    if not seeds:
        raise RomannetError("--seeds is empty: pass at least one seed, e.g. --seeds 1 2 3")
    repeated = sorted({s for s in seeds if list(seeds).count(s) > 1})
    if repeated:
        raise RomannetError(f"--seeds {' '.join(map(str, seeds))}: seed {repeated[0]} is given twice")
    if any(s < 0 for s in seeds):
        raise RomannetError(f"--seeds {' '.join(map(str, seeds))}: seeds are non-negative integers")
    return tuple(seeds)


def check_overrides(overrides: Sequence[str]) -> tuple[str, ...]:
    for o in overrides:
        source = {"seed": "--seeds", "run_id": "the run's name"}.get(_override_key(o))
        if source is not None:
            raise RomannetError(f"--set {o}: the sweep sets each run's {_override_key(o)} itself (from {source})")
    return tuple(overrides)


def resolve_eval(args: argparse.Namespace, tasks: Mapping[str, str], heights: Mapping[str, int],
                 defaults: Mapping[str, Any]) -> EvalSettings:
    """The evaluation settings: the --eval-* flags, else `romannet eval`'s defaults; the task and the goal
    heights default to the recipes' own, which must then agree (every row is tested on the same scenes).

    tasks, heights: each variant's task and goal stack height; defaults: `romannet eval`'s flag defaults."""
    task = args.eval_task
    if task is None:
        if len(set(tasks.values())) > 1:
            raise RomannetError(f"the variants train different tasks ({_listing(tasks)}): pass --eval-task (and its "
                                "flags) so that every row is tested on the same scenes")
        task = next(iter(tasks.values()))
    runs = _pick(args.eval_runs, defaults["runs"])
    seed = _pick(args.eval_seed, defaults["seed"])
    max_steps = _pick(args.eval_max_steps, defaults["max_steps"])
    if runs < 1:
        raise RomannetError(f"--eval-runs {runs}: at least one run per test case")
    if max_steps < 0:
        raise RomannetError(f"--eval-max-steps {max_steps}: 0 (the default limit) or more")
    out = EvalSettings(task=task, runs=runs, seed=seed, max_steps=max_steps)
    if task == "stacking":
        goal = args.eval_goal_height
        if not goal:
            if len(set(heights.values())) > 1:
                raise RomannetError(f"the variants stack to different heights ({_listing(heights)}): pass "
                                    "--eval-goal-height")
            goal = [next(iter(heights.values()))]
        if any(not 2 <= h <= 5 for h in goal):
            raise RomannetError(f"--eval-goal-height {' '.join(map(str, goal))}: goal heights are 2..5")
        return EvalSettings(**{**asdict(out), "goal_heights": tuple(goal)})
    if task == "clutter":
        objects = _pick(args.eval_objects, defaults["objects"])
        if objects < 1:
            raise RomannetError(f"--eval-objects {objects}: at least one object")
        return EvalSettings(**{**asdict(out), "objects": objects,
                               "object_set": _pick(args.eval_object_set, defaults["object_set"])})
    if args.eval_cases is not None:
        from romannet.actor.sim.arrangements import cases_dir

        cases = cases_dir(args.eval_cases)
        if not cases.is_dir() or not any(cases.glob("*.txt")):
            raise RomannetError(f"--eval-cases {cases}: not a directory of case files (*.txt)")
        return EvalSettings(**{**asdict(out), "cases": str(cases.resolve())})
    return out


def _pick(given: Any, default: Any) -> Any:
    return default if given is None else given


def _listing(values: Mapping[str, Any]) -> str:
    return ", ".join(f"{k}: {v}" for k, v in values.items())


def first_difference(a: Any, b: Any, prefix: str = "") -> tuple[str, Any, Any] | None:
    """(dotted key, a's value, b's value) of the first place two nested dicts differ (in a's key order, then
    b's), or None if equal."""
    if isinstance(a, Mapping) and isinstance(b, Mapping):
        for key in dict.fromkeys([*a, *b]):
            diff = first_difference(a.get(key), b.get(key), f"{prefix}.{key}" if prefix else str(key))
            if diff is not None:
                return diff
        return None
    return None if a == b else (prefix or "(whole)", a, b)


def check_manifest(existing: Mapping[str, Any], plan: SweepPlan) -> None:
    """Refuse an --out whose manifest describes another sweep (one line naming what differs)."""
    mine = plan.manifest()
    diff = first_difference({k: existing.get(k) for k in IDENTITY}, {k: mine[k] for k in IDENTITY})
    if diff is not None:
        key, there, here = diff
        raise RomannetError(f"{plan.out} holds another sweep ({key}: {json.dumps(there)} there, {json.dumps(here)} "
                            "here): choose another --out, or repeat that sweep's command to resume it")


def read_manifest(out: Path) -> dict[str, Any] | None:
    """The manifest in --out, None for a new or empty directory; RomannetError for a directory that holds
    other files or an unreadable manifest."""
    path = out / MANIFEST
    if not path.is_file():
        if out.exists() and (not out.is_dir() or any(out.iterdir())):
            raise RomannetError(f"--out {out} holds files but no {MANIFEST}: choose a new or empty directory")
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise RomannetError(f"{path} cannot be read ({exc}): move it away, or choose another --out") from None
    if not isinstance(data, dict):
        raise RomannetError(f"{path} is not a sweep manifest: move it away, or choose another --out")
    return data
