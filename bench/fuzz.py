"""`romannet bench fuzz`: malformed, random and oversized messages at a live replay server, and its memory.

A real `romannet replay` process (loopback Zenoh, its own port, multicast off) takes `valid` good inserts,
settles, and its resident memory then is the baseline. Then `messages` bad ones, in a fixed random order:
random bytes, valid transitions with flipped bits or cut short, transitions under another actor's key,
garbage sample requests and priority updates, transitions just over replay.max_item_bytes (refused in the
server's callback, before they are queued or copied) and `big_mb` messages of 100 MB-1 GB (dropped by
Zenoh on arrival at the server's message cap, common/zenoh_limits.py: no reply, the link stays up).
A thread samples the server's RSS every 20 ms meanwhile. At the end the server must still answer (a
valid insert is acknowledged, stats reply), hold every good item and nothing bad, and stop cleanly.

tests/test_replay_fuzz.py runs it with one 100 MB message; the 1 GB ones are for this command only (they
cost seconds of loopback traffic and 2 GB in this process).
"""

from __future__ import annotations

import dataclasses
import logging
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from romannet.common import wire
from romannet.common.action import Action
from romannet.common.replay_client import ZenohReplayClient
from romannet.common.wire_messages import TransitionMsg
from romannet.common.zenoh_session import free_port, make_config, open_session, parse_error

from .replay_workloads import synthetic_heightmaps

log = logging.getLogger(__name__)

_RUN_ID = "fuzz"
_SIDE_PX = 32
_MAX_ITEM_BYTES = 1 << 20  # the server's replay.max_item_bytes here: small, so "just over" is cheap to send
_CONFIG = f"""run_id = "{_RUN_ID}"
[workspace]
resolution_m = 0.014
[replay]
min_size_to_sample = 1
max_item_bytes = {_MAX_ITEM_BYTES}
snapshot_every_s = 0.0
snapshot_every_inserts = 0
samples_per_insert = 0.0  # unpaced: nothing samples while the fuzz inserts
"""
_MB = 1_000_000


@dataclasses.dataclass(frozen=True)
class FuzzPlan:
    """What one fuzz run sends. big_mb: sizes in MB of the messages far over every limit."""

    messages: int = 2000
    big_mb: tuple[int, ...] = (100, 250, 500, 1000)
    valid: int = 50
    seed: int = 0
    big_timeout_s: float = 2.0  # how long a big message's query waits for the reply that must not come


def rss_kib(pid: int, field: str = "VmRSS") -> int:
    """A process's resident set (or VmHWM, its peak) in KiB, from /proc."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise ValueError(f"no {field} for pid {pid}")


class _RssWatch(threading.Thread):
    """Samples a process's RSS until stopped; peak_kib is the largest seen."""

    def __init__(self, pid: int):
        super().__init__(daemon=True, name="rss-watch")
        self.pid, self.peak_kib, self._done = pid, 0, threading.Event()

    def run(self) -> None:
        while not self._done.wait(0.02):
            try:
                self.peak_kib = max(self.peak_kib, rss_kib(self.pid))
            except (OSError, ValueError):
                return

    def stop(self) -> int:
        self._done.set()
        self.join(2)
        return self.peak_kib


def fuzz_transition(step: int, actor: str = "fuzz-0") -> TransitionMsg:
    """A valid 32x32 transition of actor `actor` (the server here expects that size)."""
    cb, db = synthetic_heightmaps(step % 7, _SIDE_PX)
    ca, da = synthetic_heightmaps(step % 7 + 1, _SIDE_PX)
    return TransitionMsg(
        actor_id=actor, episode_id="ep-0", step=step, start_ns=1, end_ns=2, task="clutter",
        color_before=cb, depth_before=db, color_after=ca, depth_after=da,
        action=Action("pick", 10, 12, 0.5, 0.7, explored=False), success=True, progress_before=0.1,
        progress_after=0.2, reward=1.0, done=False, done_reason="", holding_before=False, holding_after=True,
        policy_version=3, explore_rate=0.2)


def _bad_messages(plan: FuzzPlan, valid: bytes) -> list[tuple[str, bytes | int]]:
    """(kind, payload or size) for every bad message, in a random order fixed by plan.seed."""
    rng = np.random.default_rng(plan.seed)
    kinds = ("random", "flipped", "truncated", "wrong_actor", "sample", "priorities")
    out: list[tuple[str, bytes | int]] = []
    for i in range(plan.messages - len(plan.big_mb)):
        kind = "over_item" if i % 100 == 99 else kinds[i % len(kinds)]  # a few just over the item limit
        if kind in ("random", "sample", "priorities"):
            out.append((kind, rng.bytes(int(rng.integers(0, 4096)))))
        elif kind == "flipped":
            raw = bytearray(valid)
            for j in rng.integers(0, len(raw), int(rng.integers(1, 16))):
                raw[j] ^= 1 << int(rng.integers(8))
            out.append((kind, bytes(raw)))
        elif kind == "truncated":
            out.append((kind, valid[: int(rng.integers(0, len(valid)))]))
        elif kind == "wrong_actor":
            out.append((kind, valid))
        else:
            out.append((kind, _MAX_ITEM_BYTES + 1 + int(rng.integers(0, 4096))))
    for size_mb in plan.big_mb:  # spread through the run
        out.insert(int(rng.integers(0, len(out) + 1)), ("big", size_mb * _MB))
    return out


def _send_big(session: zenoh.Session, key: str, size: int, timeout_s: float) -> bool:
    """Send `size` bytes as an insert; True if anything replied (it must not: Zenoh drops it)."""
    block = np.random.default_rng(size).bytes(_MB)
    payload = block * (size // _MB)
    replies = session.get(key, payload=payload, timeout=timeout_s, congestion_control=zenoh.CongestionControl.BLOCK)
    del payload
    return any(r.ok is not None or r.err.payload.to_bytes() != b"Timeout" for r in replies)


def run_fuzz(plan: FuzzPlan = FuzzPlan(), work_dir: str | Path | None = None) -> dict[str, Any]:
    """Run the plan against a fresh server; the result's "ok" says whether every check held."""
    with tempfile.TemporaryDirectory(prefix="romannet-fuzz-") as tmp:
        work = Path(work_dir) if work_dir else Path(tmp)
        work.mkdir(parents=True, exist_ok=True)
        (work / "replay.toml").write_text(_CONFIG)
        port = free_port()
        cmd = [sys.executable, "-m", "romannet.cli", "replay", "--config", str(work / "replay.toml"),
               "--dir", str(work / "store"), "--listen", f"tcp/127.0.0.1:{port}"]
        with open(work / "server.log", "ab") as server_log:
            proc = subprocess.Popen(cmd, stdout=server_log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
            try:
                out = _drive(plan, proc, port)
            finally:
                if proc.poll() is None:
                    proc.send_signal(signal.SIGTERM)
                try:
                    out_rc = proc.wait(60)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    out_rc = proc.wait()
        out["server_exit_code"] = out_rc
        text = (work / "server.log").read_text(errors="replace")
        out["server_tracebacks"] = text.count("Traceback")
        out["server_log_lines"] = len(text.splitlines())
    out["ok"] = bool(out["still_answering"] and out["peak_ratio"] <= 2.0 and out["server_exit_code"] == 0
                     and out["server_tracebacks"] == 0 and out["stored"] == out["expected_stored"])
    return out


def _drive(plan: FuzzPlan, proc: subprocess.Popen, port: int) -> dict[str, Any]:
    with open_session(make_config(listen=[], connect=[f"tcp/127.0.0.1:{port}"])) as session:
        client = ZenohReplayClient(session, _RUN_ID, expected_shape=(_SIDE_PX, _SIDE_PX))
        if not client.wait_until_ready(120):
            raise RuntimeError("the replay server did not come up")
        for step in range(plan.valid):
            client.insert(fuzz_transition(step))
        client.stats()
        time.sleep(1.0)  # let the allocator settle after the first inserts
        baseline_kib = rss_kib(proc.pid)
        valid = wire.encode_transition(fuzz_transition(10**6))
        messages = _bad_messages(plan, valid)
        watch = _RssWatch(proc.pid)
        watch.start()
        refused: dict[str, int] = {}
        accepted, big_replied = 0, 0
        started = time.monotonic()
        for kind, data in messages:
            if kind == "big":
                big_replied += _send_big(session, client.keys.replay_insert("fuzz-0"), int(data), plan.big_timeout_s)
                continue
            if kind == "priorities":
                session.put(client.keys.replay_priorities, data)
                continue
            payload = bytes(int(data)) if isinstance(data, int) else data
            key = {"sample": client.keys.replay_sample,
                   "wrong_actor": client.keys.replay_insert("fuzz-1")}.get(kind, client.keys.replay_insert("fuzz-0"))
            try:
                reply = next(iter(session.get(key, payload=payload, timeout=10.0)))
            except StopIteration:
                refused["no_reply"] = refused.get("no_reply", 0) + 1
                continue
            if reply.ok is not None:
                accepted += kind != "sample"  # a flip in a harmless spot is a valid transition
                continue
            reason = parse_error(reply.err.payload.to_bytes())[0]
            refused[reason] = refused.get(reason, 0) + 1
        fuzz_s = time.monotonic() - started
        # The kernel's high-water mark catches a spike between two samples (it covers start-up too).
        peak_kib = max(watch.stop(), rss_kib(proc.pid, "VmHWM"))
        last = client.insert(fuzz_transition(plan.valid))
        stats = client.stats()
        return {
            "messages": len(messages), "big_mb": list(plan.big_mb), "fuzz_s": round(fuzz_s, 1),
            "refused_by_reason": dict(sorted(refused.items())), "fuzzed_accepted": accepted,
            "big_replied": big_replied,
            "server_rejected": stats["server"]["rejected"],
            "baseline_rss_mb": round(baseline_kib / 1024, 1), "peak_rss_mb": round(peak_kib / 1024, 1),
            "after_rss_mb": round(rss_kib(proc.pid) / 1024, 1),
            "peak_ratio": round(peak_kib / baseline_kib, 2),
            "still_answering": last.status == "accepted",
            "stored": stats["size"], "expected_stored": plan.valid + 1 + accepted,
        }
