"""`romannet bench system`: the fleet as a whole on this machine.

    run_system_benchmark(actions_per_actor=30, actor_counts=(1, 2), latency_actors=(1, 8))

Five measurements, and a sixth when named, one JSON object:
- throughput: `romannet up` (replay server, learner, N simulated actors as separate processes, everything
  over loopback Zenoh, the learner training alongside) runs N * actions_per_actor actions; per-actor
  actions/s come from the actor's MCAP episodes (first to last transition's log time, so start-up is not
  counted), the fleet's total is all actions over the span from the first to the last transition.
- weights latency: from the learner publishing a version to every actor holding it, loaded into its model,
  for 1 and 8 light actors (processes without physics; bench/weights_latency.py).
- actor time shares: one actor loop in-process with timers on its seams (bench/actor_timing.py).
- recipe paths (from a source checkout): the clutter recipe trained as `romannet up` runs it, 200 actions,
  today's path against the whole-map learner step with one thread per core in every process; actions/s
  after the first 60 actions, and their ratio.
- recipe precisions (from a source checkout): the same recipe with the actor's decisions in the precision
  "auto" picks here (bf16 or int8) against fp32.
- late pace (only when named, with late_from): a finished run resumed for 250 more actions, the learner's
  defaults against staler V(s_t+1) and weights every other update (STALE_VALUES_PATH).
`parts` picks some of them (SYSTEM_PARTS, OPTIONAL_PARTS), e.g. ("precisions",).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from .actor_timing import measure_actor_time_shares
from .weights_latency import measure_weights_latency

log = logging.getLogger(__name__)


def _transition_times(run_dir: Path) -> dict[str, list[int]]:
    """{actor_id: sorted log times (ns) of its /transition messages} over its MCAP episodes."""
    from mcap.reader import make_reader

    out: dict[str, list[int]] = {}
    for actor_dir in sorted((run_dir / "episodes").iterdir()):
        times: list[int] = []
        for path in sorted(actor_dir.glob("*.mcap")):
            with path.open("rb") as fh:
                times += [m.log_time for _, _, m in make_reader(fh).iter_messages(topics=["/transition"])]
        out[actor_dir.name] = sorted(times)
    return out


def measure_fleet_throughput(actors: int, actions_per_actor: int, robot: str = "gripper",
                             resolution_m: float = 0.002, timeout_s: float = 900.0) -> dict[str, Any]:
    """Run `romannet up` with `actors` actors to actors * actions_per_actor actions; actions/s."""
    with tempfile.TemporaryDirectory(prefix="romannet-bench-system-") as tmp:
        cmd = [sys.executable, "-m", "romannet.cli", "--log-level", "WARNING", "up", "--runs-dir", tmp,
               "--name", "bench", "--actors", str(actors), "--max-actions", str(actors * actions_per_actor),
               "--robot", robot, "--resolution", repr(resolution_m), "--set", "learner.min_replay_size=8"]
        t0 = time.monotonic()
        proc = subprocess.run(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                              stderr=subprocess.PIPE, timeout=timeout_s)
        wall_s = time.monotonic() - t0
        if proc.returncode != 0:
            raise RuntimeError(f"romannet up exited {proc.returncode}: {proc.stderr.decode()[-2000:]}")
        times = _transition_times(Path(tmp) / "bench")
    per_actor = {}
    for actor_id, ts in times.items():
        span_s = (ts[-1] - ts[0]) / 1e9 if len(ts) > 1 else 0.0
        per_actor[actor_id] = round((len(ts) - 1) / span_s, 3) if span_s > 0 else None
    every = sorted(t for ts in times.values() for t in ts)
    span_s = (every[-1] - every[0]) / 1e9 if len(every) > 1 else 0.0
    return {"actors": actors, "actions": len(every), "robot": robot,
            "total_actions_per_s": round((len(every) - 1) / span_s, 3) if span_s > 0 else None,
            "per_actor_actions_per_s": per_actor,
            "per_actor_median": statistics.median([v for v in per_actor.values() if v is not None] or [0.0]),
            "launcher_wall_s": round(wall_s, 1)}


# The learner step before window training and the actors' V(s_t+1), with each process on torch's default of
# one thread per core (as before `romannet up` shared the cores out): the path the recipes' times compare to.
WHOLE_MAP_PATH = ("learner.train_crop_px=0", "learner.actor_value_max_age=0")


def _rate_after(times: list[int], skip: int) -> float | None:
    """Actions/s from the skip-th transition to the last (start-up and the learner's first fill left out)."""
    ts = times[skip:]
    span_s = (ts[-1] - ts[0]) / 1e9 if len(ts) > 1 else 0.0
    return (len(ts) - 1) / span_s if span_s > 0 else None


def measure_recipe_variants(recipe: Path, variants: dict[str, list[str]], actions: int = 200, pairs: int = 1,
                            skip: int = 60, timeout_s: float = 1800.0) -> dict[str, float | None]:
    """A recipe's training pace (`romannet up`, 1 actor, paced as the recipe says) with each variant's --set
    overrides, alternating run by run; median actions/s after the first `skip` per variant."""
    rates: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(pairs):
        for name, sets in variants.items():
            with tempfile.TemporaryDirectory(prefix="romannet-bench-recipe-") as tmp:
                cmd = [sys.executable, "-m", "romannet.cli", "--log-level", "WARNING", "up", "--config", str(recipe),
                       "--runs-dir", tmp, "--name", "bench", "--actors", "1", "--max-actions", str(actions)]
                for kv in sets:
                    cmd += ["--set", kv]
                proc = subprocess.run(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.PIPE, timeout=timeout_s)
                if proc.returncode != 0:
                    raise RuntimeError(f"romannet up exited {proc.returncode}: {proc.stderr.decode()[-2000:]}")
                times = sorted(t for ts in _transition_times(Path(tmp) / "bench").values() for t in ts)
            rate = _rate_after(times, skip)
            if rate is not None:
                rates[name].append(rate)
    return {k: round(statistics.median(v), 3) if v else None for k, v in rates.items()}


def _ratio(a: float | None, b: float | None) -> float | None:
    return round(a / b, 2) if a and b else None


def measure_recipe_paths(recipe: Path, actions: int = 200, pairs: int = 1, skip: int = 60) -> dict[str, Any]:
    """Today's learner and thread plan against the whole-map path with one thread per core in every process."""
    cores = os.cpu_count() or 1
    whole_map = [*WHOLE_MAP_PATH, f"learner.num_threads={cores}", f"model.num_threads={cores}"]
    med = measure_recipe_variants(recipe, {"current": [], "whole_map": whole_map}, actions, pairs, skip)
    return {"recipe": str(recipe), "actions": actions, "after_action": skip, "pairs": pairs,
            "actions_per_s": med, "current_vs_whole_map": _ratio(med["current"], med["whole_map"]),
            "whole_map_sets": whole_map}


def measure_recipe_precisions(recipe: Path, actions: int = 200, pairs: int = 1, skip: int = 60) -> dict[str, Any]:
    """The actor's decisions in the precision "auto" picks here against fp32, the learner as the recipe has it:
    what the faster decision nets in an actor that swaps weights after every learner update (int8's swap
    costs more: it is prepared while the action executes). Nothing to compare where "auto" is fp32."""
    from romannet.common.policy import resolve_inference_precision

    auto = resolve_inference_precision("auto")
    if auto == "fp32":
        return {"recipe": str(recipe), "auto": auto, "left_out": "precision \"auto\" is fp32 on this machine"}
    med = measure_recipe_variants(recipe, {auto: [], "fp32": ['model.precision="fp32"']}, actions, pairs, skip)
    return {"recipe": str(recipe), "actions": actions, "after_action": skip, "pairs": pairs, "auto": auto,
            "actions_per_s": med, f"{auto}_vs_fp32": _ratio(med[auto], med["fp32"])}


# Staler bootstrap values and fewer weight swaps: clutter runs of 11.5-12 minutes on AMD-bf16 against the
# defaults' 14.6-14.9, and about 3 points less pick success (docs/journal.md, "Staler V(s') and weights every
# other update"); what this part prices.
STALE_VALUES_PATH = ("learner.actor_value_max_age=400", "learner.publish_every_updates=2")


def measure_late_pace(run_dir: Path, actions: int = 250, pairs: int = 1, skip: int = 60,
                      timeout_s: float = 1800.0) -> dict[str, Any]:
    """A finished run's pace late in training, where a full replay makes the learner's V(s_t+1) passes the
    cost: copies of `run_dir` resumed (`romannet up --resume`) for `actions` more actions, the learner's
    defaults against STALE_VALUES_PATH, alternating; median actions/s after the first `skip` new actions."""
    from romannet.common.config_learner import LearnerConfig

    done = int(json.loads((run_dir / "summary.json").read_text())["actions"])
    d = LearnerConfig()
    current = [f"learner.actor_value_max_age={d.actor_value_max_age}",
               f"learner.publish_every_updates={d.publish_every_updates}"]
    variants = {"current": current, "stale_values": list(STALE_VALUES_PATH)}
    before = max((t for ts in _transition_times(run_dir).values() for t in ts), default=0)  # the run's last one
    rates: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(pairs):
        for name, sets in variants.items():
            with tempfile.TemporaryDirectory(prefix="romannet-bench-late-") as tmp:
                copy = Path(tmp) / run_dir.name
                shutil.copytree(run_dir, copy, symlinks=True)
                cmd = [sys.executable, "-m", "romannet.cli", "--log-level", "WARNING", "up", "--resume",
                       "--runs-dir", tmp, "--name", run_dir.name, "--max-actions", str(done + actions)]
                for kv in sets:
                    cmd += ["--set", kv]
                proc = subprocess.run(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.PIPE, timeout=timeout_s)
                if proc.returncode != 0:
                    raise RuntimeError(f"romannet up --resume exited {proc.returncode}: "
                                       f"{proc.stderr.decode()[-2000:]}")
                times = sorted(t for ts in _transition_times(copy).values() for t in ts if t > before)
            rate = _rate_after(times, skip)
            if rate is not None:
                rates[name].append(rate)
    med = {k: round(statistics.median(v), 3) if v else None for k, v in rates.items()}
    return {"run": str(run_dir), "resumed_at_action": done, "actions": actions, "after_action": skip,
            "pairs": pairs, "actions_per_s": med, "stale_vs_current": _ratio(med["stale_values"], med["current"]),
            "current_sets": current, "stale_values_sets": list(STALE_VALUES_PATH)}


SYSTEM_PARTS = ("throughput", "latency", "recipe", "precisions", "time")
OPTIONAL_PARTS = ("late",)  # needs a finished run to resume: run only when named


def run_system_benchmark(actions_per_actor: int = 30, actor_counts: tuple[int, ...] = (1, 2),
                         latency_actors: tuple[int, ...] = (1, 8), repeats: int = 5, robot: str = "gripper",
                         resolution_m: float = 0.002, seed: int = 0,
                         parts: tuple[str, ...] = SYSTEM_PARTS, late_from: Path | None = None) -> dict[str, Any]:
    """The measurements named in parts (SYSTEM_PARTS, OPTIONAL_PARTS; see the module docstring)."""
    unknown = sorted(set(parts) - set(SYSTEM_PARTS) - set(OPTIONAL_PARTS))
    if unknown:
        raise ValueError(f"unknown part(s) {', '.join(unknown)}: choose from "
                         f"{', '.join(SYSTEM_PARTS + OPTIONAL_PARTS)}")
    if "late" in parts and (late_from is None or not (late_from / "summary.json").is_file()):
        raise ValueError("part 'late' resumes a finished `romannet up` run: name one (a directory with a "
                         f"summary.json) with --late-from RUN_DIR{f'; {late_from} is not one' if late_from else ''}")
    result: dict[str, Any] = {
        "benchmark": "system", "cpu_count": os.cpu_count(), "load_average_at_start": os.getloadavg(),
        "robot": robot, "resolution_m": resolution_m, "parts": list(parts),
        "actions_per_actor": actions_per_actor, "throughput": [], "weights_latency": [],
    }
    if "throughput" in parts:
        for n in actor_counts:
            log.info("throughput with %d actor(s)", n)
            result["throughput"].append(measure_fleet_throughput(n, actions_per_actor, robot, resolution_m))
    if "latency" in parts:
        for n in latency_actors:
            log.info("weights latency with %d light actor(s)", n)
            result["weights_latency"].append(measure_weights_latency(n, repeats))
    recipe = Path(__file__).resolve().parent.parent / "configs" / "experiments" / "clutter.toml"
    if recipe.is_file() and "recipe" in parts:  # a source checkout: the clutter recipe's pace
        log.info("recipe pace: %s, current vs whole-map path", recipe.name)
        result["recipe_paths"] = measure_recipe_paths(recipe)
    if recipe.is_file() and "precisions" in parts:
        log.info("recipe pace: %s, the actor's precision \"auto\" vs fp32", recipe.name)
        result["recipe_precisions"] = measure_recipe_precisions(recipe)
    if "late" in parts and late_from is not None:
        log.info("late pace: %s resumed, the learner's defaults vs staler V(s_t+1) and fewer weight swaps",
                 late_from)
        result["late_pace"] = measure_late_pace(late_from)
    if "time" in parts:
        log.info("actor time shares")
        result["actor_time"] = measure_actor_time_shares(actions_per_actor, robot, resolution_m, seed)
    result["load_average_at_end"] = os.getloadavg()  # other work on the box skews every number above
    return result
