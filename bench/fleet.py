"""`romannet bench fleet`: one learner, one replay server and 8, 32, 64 light actors through one router.

    result = run_fleet_benchmark(FleetPlan(sizes=(8, 32, 64), duration_s=180))
    romannet bench fleet --json --sizes 8,32,64 --duration 180

Per fleet size, a fresh fleet of real processes on Zenoh (bench/fleet_hosts.py: one network namespace per
process where root can build them, else loopback; a `romannet router`, every other process its client):
`romannet replay`, the learner (`romannet learner` with a clock on its publisher, bench/fleet_learner.py)
and N light actors (bench/fleet_actor.py: the actor's weights source, spool and sender, one synthetic
transition every 1-2 s, no physics, no model). Once every actor holds weights and has an acknowledged insert
and the learner has trained, it measures for duration_s seconds:
- weights: per version published in the window, from the publish call to the last actor holding it (or a
  newer one), median and p99; the learner's TCP egress over the window per version published, and that in
  copies of one version's bytes (goal: about one, whatever N);
- replay: acknowledged inserts/s and their request-to-ack p50/p99 at the actors; the learner's sample round
  trip p50/p99 (its metrics.csv: request, the server's work, the reply and its decoding);
- learner: updates/s, and its ratio to the 1-actor run made first (goal: >= 0.9). learner.max_updates_per_insert
  is 0 here, so the learner trains as fast as it can in every run and the ratio is the fleet's cost to it;
- ledger (bench/fault_ledger.py, after every process stopped): produced, acknowledged and stored per actor,
  lost and duplicated, and acknowledged keys the durable log does not hold, by (actor, episode, step).
- memory (RSS) of a light actor, the learner and the replay server; the CPU the actors used, in cores.
On one machine the actors share the CPUs with the learner: a fall in updates/s there may be the actors'
decoding, not the network. The load average is printed for that reason; read ratios, not absolute times.
"""

from __future__ import annotations

import dataclasses
import logging
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from . import fleet_report as fr
from .fault_ledger import Ledger, actor_status, logged_keys
from .fleet_hosts import client_config, open_hosts, resolve_topology, wait_router
from .fuzz import rss_kib
from .replay import _process_cpu_s
from .weights_latency import router_argv

log = logging.getLogger(__name__)

RUN_ID = "fleet"
# The learner trains flat out (no replay-ratio cap), from a small buffer, so its pace is its own; the replay
# does not pace the actors and a deep spool never stops them: their pace is period_s.
BENCH_SETTINGS = (f'run_id="{RUN_ID}"', "learner.max_updates_per_insert=0", "learner.min_replay_size=8",
                  "replay.min_size_to_sample=1", "replay.samples_per_insert=0", "actor.spool_max_items=2000")
# The tiny fleet of the tests (the faults and chaos benches' model and 64x64 heightmaps).
TINY_SETTINGS = ("model.channels=4", "model.residual_blocks=1", "model.num_threads=1", "learner.num_threads=1",
                 'learner.precision="fp32"', "learner.batch_size=2", "workspace.resolution_m=0.007")
GOAL_MS = {8: 500.0, 64: 1000.0}  # weights to every actor, median (issue 34)
_GRACE_S = 5.0  # after the window: versions published at its end reach the actors before they stop


@dataclasses.dataclass(frozen=True)
class FleetPlan:
    """sizes: light actors per fleet; duration_s: measured seconds per size; period_s: (low, high) seconds
    between an actor's transitions; topology: auto, netns or loopback; settings: config overrides."""

    sizes: tuple[int, ...] = (8, 32, 64)
    duration_s: float = 180.0
    period_s: tuple[float, float] = (1.0, 2.0)
    topology: str = "auto"
    settings: tuple[str, ...] = ()
    baseline: bool = True  # a 1-actor run first, for the learner's updates/s ratio
    seed: int = 0


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "romannet.cli", "--log-level", "INFO", *args]


class _Fleet:
    """One fleet's processes and files."""

    def __init__(self, hosts: Any, work: Path, config: Path, n: int, plan: FleetPlan):
        self.hosts, self.work, self.config, self.plan = hosts, work, config, plan
        self.run_dir, self.logs = work / "run", work / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        self.zenoh = client_config(work, hosts.router_endpoint)
        self.actor_ids = [f"actor-{i}" for i in range(n)]
        self.reports = [work / f"{a}.txt" for a in self.actor_ids]
        self.probe, self.stop_file = work / "publishes.txt", work / "stop"
        self.procs: dict[str, subprocess.Popen] = {}

    def spawn(self, name: str, host: str, argv: list[str]) -> None:
        env = {"OMP_NUM_THREADS": "1"} if name.startswith("actor") else None
        self.procs[name] = self.hosts.spawn(host, argv, self.logs / f"{name}.log", env)

    def start(self) -> None:
        self.spawn("router", "router", router_argv(self.work, self.hosts.router_listen))
        wait_router(self.hosts, self.procs["router"])
        zc = ["--config", str(self.config), "--zenoh-config", str(self.zenoh)]
        self.spawn("replay", "replay", _cli("replay", *zc, "--dir", str(self.run_dir / "replay")))
        self.spawn("learner", "learner", [sys.executable, "-m", "romannet.bench.fleet_learner", str(self.probe),
                                          *zc, "--run-dir", str(self.run_dir)])
        low, high = self.plan.period_s
        for i, (actor_id, report) in enumerate(zip(self.actor_ids, self.reports, strict=True)):
            self.spawn(actor_id, f"actor{i}", [
                sys.executable, "-m", "romannet.bench.fleet_actor", *zc, "--run-dir", str(self.run_dir),
                "--actor-id", actor_id, "--report", str(report), "--stop", str(self.stop_file),
                "--seed", str(self.plan.seed * 1000 + i), "--period-s", str(low), str(high)])

    def check_alive(self) -> None:
        dead = {n: p.returncode for n, p in self.procs.items() if p.poll() is not None}
        if dead:
            name = next(iter(dead))
            tail = (self.logs / f"{name}.log").read_text(errors="replace")[-2000:]
            raise RuntimeError(f"{sorted(dead)} exited early (codes {dead}); {name}.log ends:\n{tail}")

    def wait_up(self, timeout_s: float) -> None:
        """Every actor holds weights and has an acknowledged insert; the learner has trained."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            self.check_alive()
            reports = [fr.read_actor_report(p) for p in self.reports]
            if all(r.weights and r.acks for r in reports) and fr.learner_rows(self.run_dir / "metrics.csv"):
                return
            time.sleep(1.0)
        raise RuntimeError(f"the fleet of {len(self.actor_ids)} was not up within {timeout_s:.0f} s; logs in "
                           f"{self.logs}")

    def stop(self) -> dict[str, int | None]:
        """Actors first (they flush their spools), then the learner and the replay (SIGINT), the router."""
        self.stop_file.touch()
        codes = {a: _wait(self.procs[a], 120.0) for a in self.actor_ids}
        for name in ("learner", "replay", "router"):
            if self.procs[name].poll() is None:
                self.procs[name].send_signal(signal.SIGINT)
            codes[name] = _wait(self.procs[name], 120.0)
        return codes

    def kill_all(self) -> None:
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.kill()
                proc.wait(30)


def _wait(proc: subprocess.Popen, timeout_s: float) -> int | None:
    try:
        return proc.wait(timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(30)
        return None


def _rss_mb(pid: int) -> float | None:
    try:
        return round(rss_kib(pid) / 1024, 1)
    except (OSError, ValueError):
        return None


def _private_mb(pid: int) -> float | None:
    """Memory only this process holds (RSS less the shared pages: torch's libraries are mapped once for
    every process of the machine, so N actors need N times this, plus the shared part once)."""
    try:
        fields = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines()
                      if ":" in line)
        return round((int(fields["Private_Clean"].split()[0]) + int(fields["Private_Dirty"].split()[0])) / 1024, 1)
    except (OSError, ValueError, KeyError):
        return None


def _cpu_s(pids: list[int]) -> float:
    return sum(_process_cpu_s(p) or 0.0 for p in pids)


def _measure(fleet: _Fleet, duration_s: float) -> dict[str, Any]:
    """The window: egress, learner rows, the actors' CPU, memory at its end."""
    actor_pids = [fleet.procs[a].pid for a in fleet.actor_ids]
    learner_pid = fleet.procs["learner"].pid
    rows0 = len(fr.learner_rows(fleet.run_dir / "metrics.csv"))
    bytes0, cpu0 = fleet.hosts.learner_bytes_out(learner_pid), _cpu_s(actor_pids)
    t0 = time.monotonic_ns()
    end = time.monotonic() + duration_s
    while time.monotonic() < end:
        fleet.check_alive()
        time.sleep(min(1.0, max(0.0, end - time.monotonic())))
    t1 = time.monotonic_ns()
    rows1 = len(fr.learner_rows(fleet.run_dir / "metrics.csv"))
    bytes1, cpu1 = fleet.hosts.learner_bytes_out(learner_pid), _cpu_s(actor_pids)
    window_s = (t1 - t0) / 1e9
    actor_rss = [m for m in (_rss_mb(p) for p in actor_pids) if m is not None]
    actor_private = [m for m in (_private_mb(p) for p in actor_pids) if m is not None]
    return {"window": (t0, t1), "window_s": window_s, "rows0": rows0, "rows1": rows1,
            "egress": None if bytes0 is None or bytes1 is None else bytes1 - bytes0,
            "actors_cpu_cores": round((cpu1 - cpu0) / window_s, 2),
            "memory_mb": {"light_actor_median": round(statistics.median(actor_rss), 1) if actor_rss else None,
                          "light_actor_max": max(actor_rss, default=None),
                          "light_actor_private_median": round(statistics.median(actor_private), 1) if actor_private else None,
                          "learner": _rss_mb(learner_pid), "replay": _rss_mb(fleet.procs["replay"].pid)}}


def _run_size(plan: FleetPlan, n: int, topology: str, config: Path, work: Path) -> dict[str, Any]:
    hosts = ["router", "replay", "learner", *(f"actor{i}" for i in range(n))]
    started = time.monotonic()
    with open_hosts(topology, hosts) as h:
        fleet = _Fleet(h, work, config, n, plan)
        try:
            fleet.start()
            fleet.wait_up(120.0 + 5.0 * n)
            log.info("fleet of %d up after %.0f s; measuring for %.0f s", n, time.monotonic() - started,
                     plan.duration_s)
            window = _measure(fleet, plan.duration_s)
            time.sleep(_GRACE_S)
            codes = fleet.stop()
        finally:
            fleet.kill_all()
    return _size_result(fleet, n, window, codes, time.monotonic() - started)


def _size_result(fleet: _Fleet, n: int, m: dict[str, Any], codes: dict[str, int | None],
                 wall_s: float) -> dict[str, Any]:
    reports = [fr.read_actor_report(p) for p in fleet.reports]
    weights = fr.weights_latency(fr.read_probe(fleet.probe), reports, m["window"])
    versions, size = weights["versions"], weights["weights_bytes"]
    per_version = round(m["egress"] / versions) if m["egress"] is not None and versions else None
    weights["learner_bytes_out_per_version"] = per_version
    weights["copies_per_version"] = round(per_version / size, 2) if per_version is not None and size else None
    ledger = Ledger(fleet.run_dir, tuple(fleet.actor_ids))
    for actor_id in fleet.actor_ids:
        ledger.final(actor_id, actor_status(fleet.run_dir, actor_id))
    counts = ledger.reconcile(fleet.config)
    stored = set(logged_keys(fleet.config, fleet.run_dir / "replay"))
    rows = fr.learner_rows(fleet.run_dir / "metrics.csv")[m["rows0"]:m["rows1"]]  # the window's updates
    learner = fr.learner_window(rows, m["window_s"])
    return {
        "actors": n, "window_s": round(m["window_s"], 1), "wall_s": round(wall_s, 1),
        "every_actor_got_weights": all(r.weights for r in reports) and weights["versions_not_at_every_actor"] == 0,
        "weights": weights, "replay": {**fr.inserts(reports, m["window"]),
                                       "sample_ms_p50": learner.pop("sample_ms_p50"),
                                       "sample_ms_p99": learner.pop("sample_ms_p99")},
        "learner": learner,
        "ledger": {"produced": counts["sent"], "acknowledged": counts["acknowledged"], "stored": counts["stored"],
                   "lost": counts["lost"], "duplicated": counts["duplicates"],
                   "acked_not_stored": fr.acked_not_stored(fleet.actor_ids, reports, stored),
                   "counts_agree": counts["counts_agree"], "problems": counts["problems"][:10]},
        "actors_cpu_cores": m["actors_cpu_cores"], "memory_mb": m["memory_mb"], "exit_codes": codes,
        "load_average": os.getloadavg(),
    }


def _goals(size: dict[str, Any]) -> dict[str, bool | None]:
    """Issue 34's goals for one fleet size (None: not measured, or no goal for this size)."""
    n, w, ledger = size["actors"], size["weights"], size["ledger"]
    goal_ms = GOAL_MS[8] if n <= 8 else GOAL_MS[64]
    median, copies, ratio = w["all_actors_ms_median"], w["copies_per_version"], size["learner"].get("vs_1_actor")
    return {"weights_median_ms_within": goal_ms,
            "weights_latency": None if median is None else median <= goal_ms,
            "one_copy_per_version": None if copies is None else copies <= 1.5,
            "no_loss_no_duplicates": ledger["lost"] == 0 and ledger["duplicated"] == 0
            and ledger["acked_not_stored"] == 0 and ledger["counts_agree"],
            "learner_within_10_percent": None if ratio is None else ratio >= 0.9}


def run_fleet_benchmark(plan: FleetPlan = FleetPlan(), work_dir: str | Path | None = None) -> dict[str, Any]:
    """Every fleet size of the plan, the 1-actor baseline first (module docstring). "ok": no transition
    lost or duplicated, every actor got the weights and every process stopped cleanly, in every size."""
    from romannet.common.config import load_config
    from romannet.common.configbase import write_toml

    topology = resolve_topology(plan.topology)
    if not plan.sizes or min(plan.sizes) < 1 or plan.duration_s <= 0 or not 0 < plan.period_s[0] <= plan.period_s[1]:
        raise ValueError("sizes must be >= 1, duration > 0 and 0 < period low <= high")
    sizes = ((1,) if plan.baseline and 1 not in plan.sizes else ()) + tuple(plan.sizes)
    results: dict[str, Any] = {"benchmark": "fleet", "topology": topology, "cpu_count": os.cpu_count(),
                               "load_average_at_start": os.getloadavg(), "plan": dataclasses.asdict(plan),
                               "sizes": []}
    with tempfile.TemporaryDirectory(prefix="romannet-bench-fleet-") as tmp:
        root = Path(work_dir) if work_dir is not None else Path(tmp)
        config = root / "run.toml"
        root.mkdir(parents=True, exist_ok=True)
        write_toml(load_config(None, [*BENCH_SETTINGS, *plan.settings]), config)
        for n in sizes:
            log.info("fleet of %d light actor(s)", n)
            size = _run_size(plan, n, topology, config, root / f"fleet-{n}")
            results["sizes"].append(size)
            log.info("%d actor(s): %s", n, size)  # kept in the log if a later size fails
    base = next((s for s in results["sizes"] if s["actors"] == 1), None)
    base_ups = base["learner"]["updates_per_s"] if base else None
    for size in results["sizes"]:
        ups = size["learner"]["updates_per_s"]
        size["learner"]["vs_1_actor"] = round(ups / base_ups, 3) if ups is not None and base_ups else None
        size["goals"] = _goals(size)
    results["load_average_at_end"] = os.getloadavg()
    results["ok"] = all(s["goals"]["no_loss_no_duplicates"] and s["every_actor_got_weights"]
                        and all(c == 0 for c in s["exit_codes"].values()) for s in results["sizes"])
    return results
