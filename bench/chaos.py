"""`romannet bench chaos`: a fleet of 2 actors trained on loopback while random children are SIGKILLed.

    result = run_chaos(ChaosPlan(duration_s=600))
    romannet bench chaos --json --duration 600 --kill-every 30,90

The replay server, the learner and actor-0/actor-1 run as `romannet` processes on loopback Zenoh (the
tiny model and 64x64 heightmaps of `romannet bench faults`, no root needed). Every 30-90 s (uniform,
seeded) one of the four is killed with SIGKILL (each once per round, in a random order per round) and
restarted at once (the learner with --resume), as systemd's Restart=on-failure would. After each kill a copy of the replay directory gets `flips` flipped
bytes (bench/chaos_damage.py); after a kill of the replay server the copy is taken before the restart,
so it is exactly what the restarted server recovers. A thread samples each service's RSS every 0.5 s.

At the end every process is stopped with SIGINT (actors first) and the replay server's durable log is
read back (bench/fault_ledger.py): actions taken, acknowledged, stored, lost and duplicated. Also
printed: per replay kill, the items the server held just before it against those recovered after it; per
damaged copy, what it held and what was recovered, reported damaged, reported lost, and unreported; per
service its peak RSS and its peak in each half of the run. Goal: 0 lost, 0 duplicated, nothing
unreported, memory flat (second-half peak <= 1.5x the first-half peak).
"""

from __future__ import annotations

import dataclasses
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from romannet.common.replay_client import ZenohReplayClient
from romannet.common.zenoh_session import ZenohQueryError, free_port, make_config, open_session

from .chaos_damage import damage_copy
from .fault_ledger import Key, Ledger, _episode_index, actor_status, next_episode, spool_keys
from .faults import RUN_SETTINGS
from .fuzz import rss_kib

log = logging.getLogger(__name__)

RUN_ID = "chaos"
ACTORS = ("actor-0", "actor-1")
SERVICES = ("replay", "learner", *ACTORS)
SETTINGS = [s for s in RUN_SETTINGS if not s.startswith("run_id")] + [f'run_id="{RUN_ID}"']


@dataclasses.dataclass(frozen=True)
class ChaosPlan:
    """duration_s: chaos time after the fleet is up; kill_every_s: (low, high) of the uniform pause
    between kills; flips: bytes flipped per damaged copy."""

    duration_s: float = 600.0
    kill_every_s: tuple[float, float] = (30.0, 90.0)
    flips: int = 8
    seed: int = 0
    startup_timeout_s: float = 300.0
    stop_timeout_s: float = 120.0


class _Rss(threading.Thread):
    """Samples the RSS of each service's current process every 0.5 s: {service: [(t, MiB)]}."""

    def __init__(self, procs: dict[str, subprocess.Popen]):
        super().__init__(daemon=True, name="chaos-rss")
        self.procs, self.samples = procs, {name: [] for name in SERVICES}
        self._done = threading.Event()

    def run(self) -> None:
        while not self._done.wait(0.5):
            for name, proc in list(self.procs.items()):
                try:
                    self.samples[name].append((time.monotonic(), rss_kib(proc.pid) / 1024))
                except (OSError, ValueError):
                    pass  # between a kill and the restart

    def stop(self) -> None:
        self._done.set()
        self.join(5)

    def summary(self, t0: float, t1: float) -> dict[str, dict[str, float]]:
        """Per service: peak MiB overall and in each half of [t0, t1] (start-up excluded)."""
        mid, out = (t0 + t1) / 2, {}
        for name, samples in self.samples.items():
            first = [m for t, m in samples if t0 <= t < mid]
            second = [m for t, m in samples if t >= mid]
            peak1, peak2 = max(first, default=0.0), max(second, default=0.0)
            out[name] = {"peak_mb": round(max((m for _, m in samples), default=0.0), 1),
                         "first_half_peak_mb": round(peak1, 1), "second_half_peak_mb": round(peak2, 1),
                         "growth": round(peak2 / peak1, 2) if peak1 else None}
        return out


class _Fleet:
    """The four processes, their logs, and their start, kill and stop."""

    def __init__(self, work: Path):
        self.work, self.run_dir, self.logs = work, work / "run", work / "logs"
        self.config = work / "run.toml"
        self.replay_ep, self.learner_ep = (f"tcp/127.0.0.1:{free_port()}" for _ in range(2))
        self.procs: dict[str, subprocess.Popen] = {}
        self._log_start: dict[str, int] = {}  # where the current process's part of its log begins

    def argv(self, name: str) -> list[str]:
        base = [sys.executable, "-m", "romannet.cli", "--log-level", "INFO"]
        common = ["--config", str(self.config)]
        if name == "replay":
            return [*base, "replay", *common, "--dir", str(self.run_dir / "replay"), "--listen", self.replay_ep]
        if name == "learner":
            ckpts = self.run_dir / "checkpoints"
            resume = ["--resume"] if (ckpts / "LATEST").is_file() or any(ckpts.glob("ckpt-*")) else []
            return [*base, "learner", *common, "--run-dir", str(self.run_dir), "--listen", self.learner_ep,
                    "--connect", self.replay_ep, *resume]
        return [*base, "actor", *common, "--run-dir", str(self.run_dir), "--actor-id", name,
                "--connect", self.replay_ep, "--connect", self.learner_ep]

    def start(self, name: str) -> None:
        self.logs.mkdir(parents=True, exist_ok=True)
        with (self.logs / f"{name}.log").open("ab") as fh:
            self._log_start[name] = fh.tell()
            fh.write(f"==== start at t={time.monotonic():.3f}\n".encode())
            fh.flush()
            # One torch thread each: four processes share a small machine (romannet up's thread plan).
            self.procs[name] = subprocess.Popen(self.argv(name), stdout=fh, stderr=subprocess.STDOUT,
                                                stdin=subprocess.DEVNULL, env={**os.environ, "OMP_NUM_THREADS": "1"})

    def ready(self, name: str) -> bool:
        """Whether the current process of `name` is serving (and so handles SIGINT: a process still
        importing may have SIGINT ignored, as a background job of a non-interactive shell has)."""
        if name in ACTORS:
            return actor_status(self.run_dir, name).get("pid") == self.procs[name].pid
        with (self.logs / f"{name}.log").open("rb") as fh:
            fh.seek(self._log_start[name])
            return b"replay server ready" in fh.read() if name == "replay" else b"learner ready" in fh.read()

    def wait_ready(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not all(self.ready(n) or self.procs[n].poll() is not None
                                                      for n in SERVICES):
            time.sleep(0.5)

    def kill9(self, name: str) -> None:
        self.procs[name].send_signal(signal.SIGKILL)
        self.procs[name].wait(30)

    def stop(self, name: str, timeout_s: float) -> int | None:
        """SIGINT, then wait; the exit code (None: it had to be killed)."""
        proc = self.procs[name]
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            return proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(30)
            log.error("%s did not stop within %.0f s of SIGINT", name, timeout_s)
            return None

    def wait_up(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            dead = [n for n, p in self.procs.items() if p.poll() is not None]
            if dead:
                raise RuntimeError(f"{dead} exited during start-up; see {self.logs}")
            if all(int(actor_status(self.run_dir, a).get("acked", 0)) >= 3 for a in ACTORS):
                return
            time.sleep(0.5)
        raise RuntimeError(f"the fleet did not get 3 acknowledgements per actor within {timeout_s:.0f} s")


def run_chaos(plan: ChaosPlan = ChaosPlan(), work_dir: str | Path | None = None) -> dict[str, Any]:
    """Run the plan (module docstring); "ok" in the result says whether every goal was met."""
    with tempfile.TemporaryDirectory(prefix="romannet-chaos-") as tmp:
        work = Path(work_dir) if work_dir is not None else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        fleet = _Fleet(work)
        try:
            return _run(plan, fleet)
        finally:
            for proc in fleet.procs.values():
                if proc.poll() is None:
                    proc.kill()
                    proc.wait(30)


def _stored(client: ZenohReplayClient) -> int | None:
    """The replay server's item count now, or None while it does not answer (it is restarting)."""
    try:
        return int(client.stats(timeout_s=5.0)["size"])
    except (ZenohQueryError, KeyError, ValueError):
        return None


def _spooled_by(fleet: _Fleet, actor_id: str, first_episode: int) -> tuple[dict[str, Any], set[Key]]:
    """The killed process's status and the spooled transitions of its own episodes (from first_episode on):
    the rest of the spool is an earlier process's, not yet resent, and was counted at that one's kill.
    A process killed before it wrote a status of its own (still starting) acted at most once."""
    status = actor_status(fleet.run_dir, actor_id)
    if status.get("pid") != fleet.procs[actor_id].pid:
        status = {"actions": 0, "state": "killed while starting"}
    spooled = {k for k in spool_keys(fleet.run_dir, actor_id) if _episode_index(k[1]) >= first_episode}
    return status, spooled


def _run(plan: ChaosPlan, fleet: _Fleet) -> dict[str, Any]:
    from romannet.common.config import load_config
    from romannet.common.configbase import write_toml

    write_toml(load_config(None, SETTINGS), fleet.config)
    with open_session(make_config(listen=[], connect=[fleet.replay_ep])) as session:
        return _chaos(plan, fleet, ZenohReplayClient(session, RUN_ID))


def _chaos(plan: ChaosPlan, fleet: _Fleet, client: ZenohReplayClient) -> dict[str, Any]:
    rng = np.random.default_rng(plan.seed)
    ledger = Ledger(fleet.run_dir, ACTORS)
    first_episode = dict.fromkeys(ACTORS, 0)  # the first episode of each actor's current process
    started = time.monotonic()
    for name in SERVICES:
        fleet.start(name)
    rss = _Rss(fleet.procs)
    rss.start()
    fleet.wait_up(plan.startup_timeout_s)
    t0 = time.monotonic()
    end = t0 + plan.duration_s
    kills: list[dict[str, Any]] = []
    next_kill = t0 + float(rng.uniform(*plan.kill_every_s))
    order: list[str] = []  # victims: each service once per round, rounds in random order
    while True:
        time.sleep(max(0.0, min(next_kill, end) - time.monotonic()))
        if time.monotonic() >= end:
            break
        order = order or [str(s) for s in rng.permutation(SERVICES)]
        victim = order.pop()
        event: dict[str, Any] = {"t_s": round(time.monotonic() - t0, 1), "killed": victim}
        if victim == "replay":  # inserts go on until the kill, so it must recover at least this many
            event["stored_before"] = _stored(client)
        fleet.kill9(victim)
        if victim in ACTORS:  # what the dead process left, read before its restart touches it
            status, spooled = _spooled_by(fleet, victim, first_episode[victim])
            first_episode[victim] = next_episode(fleet.run_dir, victim)
            ledger.killed(victim, status, spooled, first_episode[victim])
        event["damaged_copy"] = damage_copy(fleet.run_dir / "replay", fleet.work / "copies" / f"kill-{len(kills):03d}",
                                            rng, plan.flips)
        if victim == "replay":  # the copy is exactly what the restart recovers
            event["recovered"] = event["damaged_copy"]["held_before"]
        fleet.start(victim)
        log.info("chaos: killed %s at %.0f s; copy %s", victim, event["t_s"], event["damaged_copy"])
        kills.append(event)
        next_kill = time.monotonic() + float(rng.uniform(*plan.kill_every_s))
    t1 = time.monotonic()
    fleet.wait_ready(plan.startup_timeout_s)  # the last restarted process must be able to take SIGINT
    exit_codes = {name: fleet.stop(name, plan.stop_timeout_s) for name in (*ACTORS, "learner", "replay")}
    rss.stop()
    for actor_id in ACTORS:
        ledger.final(actor_id, actor_status(fleet.run_dir, actor_id))
    counts = ledger.reconcile(fleet.config)
    return _result(plan, counts, kills, rss.summary(t0, t1), exit_codes, t1 - t0, time.monotonic() - started)


def _result(plan: ChaosPlan, counts: dict[str, Any], kills: list[dict[str, Any]], memory: dict[str, Any],
            exit_codes: dict[str, int | None], chaos_s: float, wall_s: float) -> dict[str, Any]:
    copies = [k["damaged_copy"] for k in kills]
    replay_kills = [{"stored_before": k["stored_before"], "recovered": k["recovered"]} for k in kills if "recovered" in k]
    out = {
        "benchmark": "chaos", "cpu_count": os.cpu_count(), "load_average_at_end": os.getloadavg(),
        "plan": dataclasses.asdict(plan), "chaos_s": round(chaos_s, 1), "wall_s": round(wall_s, 1),
        "actions": counts["sent"], "acknowledged": counts["acknowledged"], "stored": counts["stored"],
        "lost": counts["lost"], "duplicated": counts["duplicates"], "counts_agree": counts["counts_agree"],
        "problems": counts["problems"], "per_actor": counts["per_actor"],
        "kills": len(kills), "kills_by_service": {s: sum(k["killed"] == s for k in kills) for s in SERVICES},
        "replay_kills": replay_kills,
        "damaged_copies": {"copies": len(copies), "flipped_bytes": sum(c["flipped_bytes"] for c in copies),
                           "held": sum(c["held_before"] for c in copies),
                           "recovered": sum(c["recovered"] for c in copies),
                           "damaged_reported": sum(c["damaged_reported"] for c in copies),
                           "lost_reported": sum(c["lost_reported"] for c in copies),
                           "unreported": sum(c["unreported"] for c in copies)},
        "memory": memory, "exit_codes": exit_codes, "events": kills,
    }
    flat = all(m["growth"] is None or m["growth"] <= 1.5 for m in memory.values())
    out["memory_flat"] = flat
    out["ok"] = bool(counts["counts_agree"] and counts["lost"] == 0 and counts["duplicates"] == 0 and flat
                     and out["damaged_copies"]["unreported"] == 0
                     and all(k["recovered"] >= (k["stored_before"] or 0) for k in replay_kills)
                     and all(code == 0 for code in exit_codes.values()))
    return out
