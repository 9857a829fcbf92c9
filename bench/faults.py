"""`romannet bench faults`: a secure multi-host fleet in network namespaces, trained through injected faults.

    result = run_fault_scenario()          # needs root; see bench/netns.py
    romannet bench faults --json

Hosts (bench/netns.py): `router` (romannet router), `server` (replay server and learner), `actor0` and
`actor1` (one gripper actor each, 64x64 heightmaps, a tiny RoManNet), `operator` (a liveliness watcher, the
access-control probe). Every process uses the configs `romannet deploy certs` writes: mutual TLS, access
control denying by default. During one short training run, in this order:

1. the access-control probe (bench/acl_probe.py) runs from the operator host while the fleet starts;
2. `kill -9` of the replay server, restarted at once: recovered when every actor has new acknowledgements;
3. `kill -9` of the learner, restarted with --resume: recovered when every actor holds weights newer than
   the newest before the kill;
4. actor1's link cut for link_cut_s (its switch port down), then restored: recovered when actor1's
   acknowledgements have caught up with every action it took up to the restore;
5. `kill -9` of actor0: its liveliness token must vanish at the operator within a few seconds and actor1
   must keep getting acknowledgements; actor0 is then restarted and resends its spool.
Then every process is stopped with SIGINT (actors first) and the replay server's durable log is read
back: the transitions sent, acknowledged and stored must agree exactly (bench/fault_ledger.py).

Times are CLOCK_MONOTONIC seconds, comparable across the namespaces. On a shared 2-core box the recovery
times include the restarted process's start-up (importing torch takes seconds there).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from romannet.common.errors import RomannetError

from .fault_ledger import Ledger, actor_status, next_episode, spool_keys
from .netns import NetnsLab, netns_unavailable_reason

log = logging.getLogger(__name__)

RUN_ID = "faults"
ACTORS = ("actor-0", "actor-1")
HOSTS = ("router", "server", "actor0", "actor1", "operator")
ROUTER_PORT = 7447
# A light run: the tiny RoManNet of the integration tests, 64x64 heightmaps, the floating gripper.
RUN_SETTINGS = [
    f'run_id="{RUN_ID}"', "model.channels=4", "model.residual_blocks=1", "model.num_threads=1",
    "learner.num_threads=1", 'learner.precision="fp32"', "learner.max_grad_norm=10", "learner.batch_size=2",
    "learner.min_replay_size=4",
    "learner.publish_every_updates=2", "learner.checkpoint_every_updates=4", "replay.min_size_to_sample=1",
    "sim.num_objects=3", 'sim.robot="gripper"', "workspace.resolution_m=0.007", "actor.record_camera=false",
    "actor.insert_timeout_s=3.0", "actor.resend_backoff_max_s=1.0", "actor.weights_fetch_timeout_s=5.0",
    # Unpaced, with a deep spool: the actors act through the outages measured.
    "replay.samples_per_insert=0", "actor.spool_max_items=2000",
]


class FaultScenarioError(RomannetError):
    """The scenario could not go on (a process did not come up, a recovery did not happen in time)."""


class Fleet:
    """The scenario's processes in their namespaces, their files, and waits with readable failures."""

    def __init__(self, lab: NetnsLab, work: Path):
        self.lab, self.work = lab, work
        self.run_dir, self.logs, self.configs = work / "run", work / "logs", work / "site" / "zenoh"
        self.config = work / "run.toml"
        self.procs: dict[str, subprocess.Popen] = {}
        self._starts: dict[str, int] = {}

    def _cli(self, *args: str) -> list[str]:
        return [sys.executable, "-m", "romannet.cli", "--log-level", "INFO", *args]

    def start(self, name: str, host: str, argv: list[str]) -> subprocess.Popen:
        self._starts[name] = self._starts.get(name, 0) + 1
        log_path = self.logs / f"{name}.log"
        log_path.parent.mkdir(parents=True, exist_ok=True)
        with log_path.open("a", encoding="utf-8") as fh:
            fh.write(f"==== start {self._starts[name]} at t={time.monotonic():.3f}\n")
        self.procs[name] = self.lab.spawn(host, argv, log_path)
        return self.procs[name]

    def start_router(self) -> None:
        self.start("router", "router", self._cli("router", "--zenoh-config", str(self.configs / "router.json5")))

    def start_replay(self) -> None:
        self.start("replay", "server", self._cli("replay", "--config", str(self.config), "--dir",
                                                 str(self.run_dir / "replay"), "--zenoh-config",
                                                 str(self.configs / "replay.json5")))

    def start_learner(self, resume: bool) -> None:
        self.start("learner", "server", self._cli("learner", "--config", str(self.config), "--run-dir",
                                                  str(self.run_dir), "--zenoh-config",
                                                  str(self.configs / "learner.json5"),
                                                  *(["--resume"] if resume else [])))

    def start_actor(self, actor_id: str) -> None:
        host = "actor" + actor_id.rsplit("-", 1)[-1]
        self.start(actor_id, host, self._cli("actor", "--config", str(self.config), "--run-dir", str(self.run_dir),
                                             "--actor-id", actor_id, "--zenoh-config",
                                             str(self.configs / f"{actor_id}.json5")))

    def start_watch(self) -> None:
        self.start("watch", "operator", [sys.executable, "-m", "romannet.bench.fleet_watch", "--zenoh-config",
                                         str(self.configs / "operator.json5"), "--run-id", RUN_ID,
                                         "--out", str(self.work / "liveliness.jsonl")])

    def kill9(self, name: str) -> float:
        proc = self.procs[name]
        t = time.monotonic()
        proc.kill()
        proc.wait(30)
        log.info("kill -9 %s (pid %d)", name, proc.pid)
        return t

    def stop(self, name: str, timeout_s: float = 60.0) -> int:
        """SIGINT (what Ctrl-C and systemd's KillSignal=SIGINT send), then wait; returns the exit code."""
        proc = self.procs[name]
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            return proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(10)
            raise FaultScenarioError(f"{name} did not stop within {timeout_s} s of SIGINT\n{self.tail(name)}") \
                from None

    def status(self, actor_id: str) -> dict[str, Any]:
        return actor_status(self.run_dir, actor_id)

    def liveliness_events(self) -> list[dict[str, Any]]:
        path = self.work / "liveliness.jsonl"
        if not path.is_file():
            return []
        return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]

    def tail(self, name: str, chars: int = 3000) -> str:
        path = self.logs / f"{name}.log"
        return f"--- {path} (end) ---\n" + (path.read_text(errors="replace")[-chars:] if path.is_file() else "")

    def wait_for(self, what: str, fn: Callable[[], Any], timeout_s: float, watch: tuple[str, ...] = ()) -> Any:
        """Poll fn every 0.1 s until it returns something true; fail naming `what` with the logs of watch."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for name in watch:
                if self.procs[name].poll() is not None:
                    raise FaultScenarioError(f"{name} exited ({self.procs[name].returncode}) while waiting for "
                                             f"{what}\n{self.tail(name)}")
            value = fn()
            if value:
                return value
            time.sleep(0.1)
        raise FaultScenarioError(f"no {what} within {timeout_s} s\n" + "\n".join(self.tail(n) for n in watch))


def _write_site(work: Path, router_ip: str) -> None:
    from romannet.common.config import load_config
    from romannet.common.configbase import write_toml
    from romannet.deploy.pki import generate_site
    from romannet.deploy.zenoh_configs import SiteLayout, write_site_configs

    generate_site(work / "site" / "pki", ACTORS, [router_ip])
    endpoint = f"tls/{router_ip}:{ROUTER_PORT}"
    write_site_configs(work / "site" / "zenoh", SiteLayout(
        actor_ids=ACTORS, router_endpoints=(endpoint,), listen=(f"tls/0.0.0.0:{ROUTER_PORT}",),
        pki_dir=str(work / "site" / "pki")))
    write_toml(load_config(None, RUN_SETTINGS), work / "run.toml")


def _acked(fleet: Fleet) -> dict[str, int]:
    return {a: int(fleet.status(a).get("acked", 0)) for a in ACTORS}


def _token_event(fleet: Fleet, who: str, kind: str, after_t: float) -> float | None:
    """When the watcher saw who's liveliness token appear ("put") or vanish ("delete") after after_t;
    who is "replay", "learner" or an actor id."""
    key_end = f"/{who}/alive" if who in ("replay", "learner") else f"/actor/{who}/alive"
    for ev in fleet.liveliness_events():
        if ev["kind"] == kind and ev["key"].endswith(key_end) and ev["t"] >= after_t:
            return float(ev["t"])
    return None


def _announced(fleet: Fleet, before_t: float) -> list[int]:
    """Versions of the weights announcements the watcher saw before before_t."""
    return [int(ev["version"]) for ev in fleet.liveliness_events() if ev["kind"] == "weights" and ev["t"] < before_t]


def _probe_results(fleet: Fleet, proc: subprocess.Popen) -> list[dict[str, Any]]:
    try:
        proc.wait(120)
    except subprocess.TimeoutExpired:
        raise FaultScenarioError(f"the access-control probe did not finish\n{fleet.tail('acl_probe')}") from None
    for line in reversed((fleet.logs / "acl_probe.log").read_text().splitlines()):
        if line.startswith("["):
            return json.loads(line)
    raise FaultScenarioError(f"the access-control probe printed no result\n{fleet.tail('acl_probe')}")


def run_fault_scenario_checked(**kwargs: Any) -> dict[str, Any]:
    """run_fault_scenario with its verdict: "ok" is true when nothing was lost or duplicated, the counts
    agree, every access-control check came out as expected and every process exited 0. Raises
    RomannetError where network namespaces cannot be made (not root)."""
    reason = netns_unavailable_reason()
    if reason is not None:
        raise RomannetError(f"bench faults: {reason}")
    result = run_fault_scenario(**kwargs)
    result["ok"] = bool(result["counts_agree"] and result["lost"] == 0 and result["duplicates"] == 0
                        and result["access_control_ok"] and not any(result["exit_codes"].values()))
    return result


def run_fault_scenario(work_dir: str | Path | None = None, link_cut_s: float = 10.0,
                       startup_timeout_s: float = 180.0, recovery_timeout_s: float = 90.0) -> dict[str, Any]:
    """Run the scenario (module docstring) and return faults, recovery times, counts and probe results."""
    with tempfile.TemporaryDirectory(prefix="romannet-faults-") as tmp:
        work = Path(work_dir) if work_dir is not None else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        with NetnsLab(HOSTS) as lab:
            return _scenario(Fleet(lab, work), link_cut_s, startup_timeout_s, recovery_timeout_s)


def _scenario(fleet: Fleet, link_cut_s: float, startup_timeout_s: float, recovery_s: float) -> dict[str, Any]:
    started = time.monotonic()
    lab = fleet.lab
    _write_site(fleet.work, lab.address("router"))
    ledger = Ledger(fleet.run_dir, ACTORS)
    faults: list[dict[str, Any]] = []
    fleet.start_router()
    fleet.start_watch()
    fleet.start_replay()
    fleet.start_learner(resume=False)
    for actor_id in ACTORS:
        fleet.start_actor(actor_id)
    probe = fleet.start("acl_probe", "operator", [sys.executable, "-m", "romannet.bench.acl_probe", "--configs",
                                                  str(fleet.configs), "--actors", ",".join(ACTORS), "--json"])
    everyone = ("router", "replay", "learner", *ACTORS)
    fleet.wait_for("acknowledged transitions and learner weights at every actor",
                   lambda: all(s.get("acked", 0) >= 3 and not s.get("initial_weights", True)
                               for s in map(fleet.status, ACTORS)), startup_timeout_s, everyone)
    fleet_up_s = time.monotonic() - started
    acl = _probe_results(fleet, probe)
    faults.append({"fault": f"intruder with {ACTORS[0]}'s certificate (publishes weights and rates, serves "
                   f"weights, reads {ACTORS[1]}'s transitions, inserts under its id, ...); clients without a "
                   "certificate or with one from another CA",
                   "checks": len(acl), "as_expected": sum(c["ok"] for c in acl),
                   "denials": sum(c["expected"] in ("denied", "refused") for c in acl)})

    # 1. kill -9 the replay server, restart it at once (as systemd's Restart= would, without the delay).
    t_kill = fleet.kill9("replay")
    fleet.start_replay()
    t_up = fleet.wait_for("the restarted replay server's liveliness token",
                          lambda: _token_event(fleet, "replay", "put", t_kill), recovery_s, everyone)
    # Status files lag acknowledgements by at most one action; none arrived while the server was down, so
    # the counts read now are all from before the kill.
    before = _acked(fleet)
    fleet.wait_for("acknowledgements from the restarted replay server",
                   lambda: all(_acked(fleet)[a] > before[a] for a in ACTORS), recovery_s, everyone)
    faults.append({"fault": "kill -9 replay server, restarted", "recovery_s": time.monotonic() - t_kill,
                   "back_up_after_s": t_up - t_kill, "recovered_when": "every actor got new acknowledgements"})

    # 2. kill -9 the learner once it has a checkpoint, restart it with --resume.
    fleet.wait_for("a learner checkpoint", lambda: (fleet.run_dir / "checkpoints" / "LATEST").is_file(),
                   recovery_s, everyone)
    t_kill = fleet.kill9("learner")
    # The killed learner's newest weights: announced (the watcher's record) or already held by an actor.
    newest = max([*_announced(fleet, before_t=t_kill), *(int(fleet.status(a).get("weights_version", 0))
                                                         for a in ACTORS)])
    fleet.start_learner(resume=True)
    t_up = fleet.wait_for("the restarted learner's liveliness token",
                          lambda: _token_event(fleet, "learner", "put", t_kill), recovery_s, everyone)
    fleet.wait_for(f"weights newer than v{newest} at every actor from the resumed learner",
                   lambda: all(int(fleet.status(a).get("weights_version", 0)) > newest for a in ACTORS),
                   recovery_s, everyone)
    resumed = "resumed from" in (fleet.logs / "learner.log").read_text(errors="replace").rsplit("==== start", 1)[-1]
    faults.append({"fault": "kill -9 learner, restarted with --resume", "recovery_s": time.monotonic() - t_kill,
                   "back_up_after_s": t_up - t_kill, "newest_before_kill": newest,
                   "recovered_when": f"every actor holds weights newer than v{newest}",
                   "resumed_from_checkpoint": resumed})

    # 3. Cut actor-1's link, keep it cut, restore it.
    victim, host = ACTORS[1], "actor1"
    at_cut = fleet.status(victim)
    t_cut = time.monotonic()
    lab.cut(host)
    time.sleep(link_cut_s)
    at_restore = fleet.status(victim)
    lab.restore(host)
    t_restore = time.monotonic()
    target = int(at_restore.get("actions", 0))
    fleet.wait_for(f"{victim} acknowledged up to its action {target} after the link came back",
                   lambda: int(fleet.status(victim).get("acked", 0)) >= target, recovery_s, everyone)
    gone = _token_event(fleet, victim, "delete", t_cut)
    faults.append({
        "fault": f"{victim} link cut for {link_cut_s:g} s, restored", "recovery_s": time.monotonic() - t_restore,
        "recovered_when": "its acknowledgements caught up with every action taken up to the restore",
        "actions_during_cut": int(at_restore.get("actions", 0)) - int(at_cut.get("actions", 0)),
        "spooled_at_restore": int(at_restore.get("spool_items", 0)),
        "liveliness_gone_after_s": None if gone is None else gone - t_cut,
    })

    # 4. kill -9 actor-0: its liveliness must vanish, the rest must go on; then it restarts and resends.
    victim = ACTORS[0]
    other_acked = int(fleet.status(ACTORS[1]).get("acked", 0))
    t_kill = fleet.kill9(victim)
    # What the dead process left: its last status file and its spool (nobody touches them until restart).
    ledger.killed(victim, fleet.status(victim), spool_keys(fleet.run_dir, victim),
                  next_episode(fleet.run_dir, victim))
    gone = fleet.wait_for(f"{victim}'s liveliness token to vanish",
                          lambda: _token_event(fleet, victim, "delete", t_kill), recovery_s, ("router", "watch"))
    fleet.wait_for(f"{ACTORS[1]} to keep getting acknowledgements",
                   lambda: int(fleet.status(ACTORS[1]).get("acked", 0)) > other_acked, recovery_s,
                   ("router", "replay", "learner", ACTORS[1]))
    t_other = time.monotonic()
    fleet.start_actor(victim)
    fleet.wait_for(f"the restarted {victim} to resend its spool and act",
                   lambda: fleet.status(victim).get("pid") == fleet.procs[victim].pid
                   and int(fleet.status(victim).get("acked", 0)) > int(fleet.status(victim).get("spool_recovered", 0)),
                   recovery_s, everyone)
    faults.append({"fault": f"kill -9 {victim}", "liveliness_gone_after_s": gone - t_kill,
                   "others_acked_after_s": t_other - t_kill, "recovery_s": time.monotonic() - t_kill,
                   "recovered_when": "restarted, its spool resent and new transitions acknowledged"})

    # Stop: actors first (they flush their spools), then the learner, the replay server, the rest.
    exit_codes = {name: fleet.stop(name) for name in (*ACTORS, "learner", "replay", "watch", "router")}
    for actor_id in ACTORS:
        ledger.final(actor_id, fleet.status(actor_id))
    counts = ledger.reconcile(fleet.config)
    return {
        "benchmark": "faults", "cpu_count": os.cpu_count(), "load_average_at_end": os.getloadavg(),
        "hosts": {h: lab.address(h) for h in lab.hosts}, "profile": "mutual TLS + access control (deny by default)",
        "fleet_up_s": fleet_up_s, "faults": faults, "faults_injected": len(faults),
        "access_control": acl, "access_control_ok": all(c["ok"] for c in acl),
        "exit_codes": exit_codes, **counts, "wall_s": time.monotonic() - started,
    }
