"""`romannet bench system`: the fleet as a whole on this machine.

    run_system_benchmark(actions_per_actor=30, actor_counts=(1, 2), latency_actors=(1, 8))

Three measurements, one JSON object:
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
"""

from __future__ import annotations

import logging
import os
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


def measure_recipe_paths(recipe: Path, actions: int = 200, pairs: int = 1, skip: int = 60,
                         timeout_s: float = 1800.0) -> dict[str, Any]:
    """A recipe's training pace (`romannet up`, 1 actor, paced as the recipe says) with today's learner and
    thread plan against the whole-map path, alternating run by run; actions/s after the first `skip`."""
    cores = os.cpu_count() or 1
    whole_map = [*WHOLE_MAP_PATH, f"learner.num_threads={cores}", f"model.num_threads={cores}"]
    rates: dict[str, list[float]] = {"current": [], "whole_map": []}
    for _ in range(pairs):
        for name, sets in (("current", []), ("whole_map", whole_map)):
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
    med = {k: round(statistics.median(v), 3) if v else None for k, v in rates.items()}
    ratio = round(med["current"] / med["whole_map"], 2) if med["current"] and med["whole_map"] else None
    return {"recipe": str(recipe), "actions": actions, "after_action": skip, "pairs": pairs,
            "actions_per_s": med, "current_vs_whole_map": ratio,
            "whole_map_sets": whole_map}


def run_system_benchmark(actions_per_actor: int = 30, actor_counts: tuple[int, ...] = (1, 2),
                         latency_actors: tuple[int, ...] = (1, 8), repeats: int = 5, robot: str = "gripper",
                         resolution_m: float = 0.002, seed: int = 0) -> dict[str, Any]:
    """All three measurements; see the module docstring."""
    result: dict[str, Any] = {
        "benchmark": "system", "cpu_count": os.cpu_count(), "load_average_at_start": os.getloadavg(),
        "robot": robot, "resolution_m": resolution_m,
        "actions_per_actor": actions_per_actor, "throughput": [], "weights_latency": [],
    }
    for n in actor_counts:
        log.info("throughput with %d actor(s)", n)
        result["throughput"].append(measure_fleet_throughput(n, actions_per_actor, robot, resolution_m))
    for n in latency_actors:
        log.info("weights latency with %d light actor(s)", n)
        result["weights_latency"].append(measure_weights_latency(n, repeats))
    recipe = Path(__file__).resolve().parent.parent / "configs" / "experiments" / "clutter.toml"
    if recipe.is_file():  # a source checkout: the clutter recipe's pace, today's path against the whole map
        log.info("recipe pace: %s, current vs whole-map path", recipe.name)
        result["recipe_paths"] = measure_recipe_paths(recipe)
    log.info("actor time shares")
    result["actor_time"] = measure_actor_time_shares(actions_per_actor, robot, resolution_m, seed)
    result["load_average_at_end"] = os.getloadavg()  # other work on the box skews every number above
    return result
