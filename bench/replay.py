"""`romannet bench replay`: the replay server over loopback Zenoh, measured end to end.

Per workload of 224x224 RGB-D transitions (bench/replay_workloads.py: "sim", real simulator transitions;
"camera_noise", synthetic scenes with camera noise, ~4x larger), a real `romannet replay` process (fsync
on) serves a fresh directory and this process plays actors and a learner. Reported per workload (medians
and ratios from this one run; a shared machine drifts):
- durable insert throughput of `clients` concurrent actors (each waits for its ack): transitions/s, MB/s,
  insert latency p50/p99, CPU ms per insert in the server and in this (client) process, inserts per
  fsync (the group commit), and other_load_cores: CPU time the machine spent on anything else meanwhile
  (other processes, hypervisor steal), in cores: on a shared machine throughput falls as it rises;
- sample round trip p50/p99 for batch 1 and 8 (ZenohReplayClient.sample_encoded: query to checked reply
  bytes; the learner's PNG decode, which runs on the learner, is reported separately);
- bytes on disk per stored transition (log segments + snapshot);
- recovery time per 10,000 transitions: opening the store from a log with no snapshot (the kill -9 worst
  case) in this process, after the server was killed;
- the server's CPU time per batch-1 sample request as a share of one learner step, where a learner step
  is forward + backward of one RoManNet net (GRConvNet) at batch 1, 224x224, measured here once;
- the cost of decoding every PNG at insert (replay/validate.py): the same inserts into a second fresh
  server started with --skip-pixel-decode (`without_pixel_decode`, run first), and the ratio of the two
  throughputs; plus the insert check alone in this process, one thread, with and without the decode.
Targets (issue 4): >= 500 inserts/s, p99 <= 20 ms, <= 5 s per 10k, < 10 %.
"""

from __future__ import annotations

import logging
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from romannet.common import wire
from romannet.common.replay_client import ZenohReplayClient
from romannet.common.zenoh_session import free_port, make_config, open_session

from .replay_workloads import WORKLOADS, distinct_payloads

log = logging.getLogger(__name__)

TARGETS = {"inserts_per_s": 500.0, "sample_p99_ms": 20.0, "recovery_s_per_10k": 5.0, "server_cpu_share": 0.10}
_RUN_ID = "bench"


def _process_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of a process (Linux /proc), or None elsewhere."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def _box_busy_s() -> float | None:
    """CPU seconds all processes on this machine have used (non-idle time, /proc/stat), or None."""
    try:
        fields = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
        return (sum(fields[:8]) - fields[3] - fields[4]) / os.sysconf("SC_CLK_TCK")  # minus idle, iowait
    except (OSError, ValueError, IndexError):
        return None


def _start_server(directory: Path, config_path: Path, port: int, decode_pixels: bool = True) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "romannet.cli", "--log-level", "WARNING", "replay", "--config",
           str(config_path), "--dir", str(directory), "--listen", f"tcp/127.0.0.1:{port}"]
    return subprocess.Popen(cmd + ([] if decode_pixels else ["--skip-pixel-decode"]), stdin=subprocess.DEVNULL)


def _percentiles_ms(samples_s: list[float]) -> dict[str, float]:
    a = np.asarray(samples_s) * 1000
    return {"p50_ms": round(float(np.percentile(a, 50)), 3), "p99_ms": round(float(np.percentile(a, 99)), 3)}


def _insert_phase(client: ZenohReplayClient, payloads: list[bytes], clients: int, pid: int) -> dict:
    latencies: list[float] = []
    lock = threading.Lock()
    errors: list[BaseException] = []

    def actor(part: list[bytes]) -> None:
        try:
            for data in part:
                t0 = time.perf_counter()
                ack = client.insert_encoded(data, timeout_s=30)
                dt = time.perf_counter() - t0
                if ack.status != "accepted":
                    raise RuntimeError(f"insert not accepted: {ack}")
                with lock:
                    latencies.append(dt)
        except BaseException as exc:  # reported after the join, not lost in a thread
            errors.append(exc)

    threads = [threading.Thread(target=actor, args=(payloads[i::clients],)) for i in range(clients)]
    cpu0, client_cpu0, box0 = _process_cpu_s(pid), time.process_time(), _box_busy_s()
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall_s = time.perf_counter() - t0
    cpu1, client_cpu1, box1 = _process_cpu_s(pid), time.process_time(), _box_busy_s()
    if errors:
        raise errors[0]
    n = len(payloads)
    mb = sum(len(p) for p in payloads) / 1e6
    out = {"inserts_per_s": round(n / wall_s, 1), "mb_per_s": round(mb / wall_s, 2),
           "insert_latency": _percentiles_ms(latencies),
           "payload_kb": round(mb * 1000 / n, 1),
           "client_cpu_ms_per_insert": round((client_cpu1 - client_cpu0) / n * 1000, 3)}
    if cpu0 is not None and cpu1 is not None:
        out["server_cpu_ms_per_insert"] = round((cpu1 - cpu0) / n * 1000, 3)
        if box0 is not None and box1 is not None:
            # CPU spent on anything else meanwhile, in cores (2 = both cores busy elsewhere).
            others_s = (box1 - box0) - (cpu1 - cpu0) - (client_cpu1 - client_cpu0)
            out["other_load_cores"] = round(max(0.0, others_s) / wall_s, 2)
    return out


def _sample_phase(client: ZenohReplayClient, batch_size: int, repeats: int, pid: int) -> dict:
    times, decode_s = [], []
    cpu0 = _process_cpu_s(pid)
    for i in range(repeats):
        t0 = time.perf_counter()
        reply = client.sample_encoded(batch_size, timeout_s=10)  # the learner's call, before its PNG decode
        times.append(time.perf_counter() - t0)
        if i < 5:  # the learner-side decode, a few times: it is the learner's cost, not the server's
            t1 = time.perf_counter()
            wire.decode_sample_batch(reply)
            decode_s.append(time.perf_counter() - t1)
    cpu1 = _process_cpu_s(pid)
    out = _percentiles_ms(times)
    out["learner_decode_ms"] = round(statistics.median(decode_s) * 1000, 2)
    if cpu0 is not None and cpu1 is not None:
        out["server_cpu_ms_per_request"] = round((cpu1 - cpu0) / repeats * 1000, 3)
    return out


def learner_step_s(repeats: int = 3) -> float | None:
    """Median seconds of forward + backward of one GRConvNet at batch 1, 224x224 (None without the model)."""
    try:
        import torch

        from romannet.common.model import GRConvNet
    except ImportError:
        return None
    net = GRConvNet()
    x = torch.randn(1, 4, 224, 224)
    times = []
    for i in range(repeats + 1):
        t0 = time.perf_counter()
        q, rot = net(x)
        (q.square().mean() + rot.square().mean()).backward()
        net.zero_grad(set_to_none=True)
        if i:  # the first call warms up allocators and kernels
            times.append(time.perf_counter() - t0)
    return statistics.median(times)


def run_replay_benchmark(inserts: int = 2000, repeats: int = 200, seed: int = 0, clients: int = 16,
                         directory: str | Path | None = None,
                         workloads: tuple[str, ...] = tuple(WORKLOADS)) -> dict:
    """Run every measurement once per workload; returns one JSON-able dict (see the module docstring)."""
    started = time.perf_counter()
    result: dict = {"inserts": inserts, "repeats": repeats, "clients": clients, "workloads": {}}
    step_s = learner_step_s()
    result["learner_step_ms"] = round(step_s * 1000, 1) if step_s else None
    for name in workloads:
        t0 = time.perf_counter()
        scenes = WORKLOADS[name](seed)
        payloads = distinct_payloads(scenes, inserts)
        build_s = time.perf_counter() - t0
        with tempfile.TemporaryDirectory(prefix=f"romannet-bench-replay-{name}-") as tmp:
            work = Path(directory) / name if directory is not None else Path(tmp)
            without = _insert_only(work / "without-pixel-decode", payloads, clients)
            out = _measure_workload(work, payloads, repeats, clients, step_s)
        out = {"scenes": len(scenes), "build_s": round(build_s, 2), **out, "without_pixel_decode": without,
               "pixel_decode": _pixel_decode_cost(out, without, payloads)}
        out["meets_targets"] = _meets_targets(out)
        result["workloads"][name] = out
        log.info("bench replay %s: %s", name, out)
    result["targets"] = TARGETS
    result["benchmark_s"] = round(time.perf_counter() - started, 1)
    return result


def _write_config(work: Path) -> Path:
    config_path = work / "bench.toml"
    work.mkdir(parents=True, exist_ok=True)
    # No time- or count-based snapshots: the recovery measurement then replays the whole log. Unpaced: the
    # insert phases sample nothing.
    config_path.write_text(f'run_id = "{_RUN_ID}"\n[replay]\nmin_size_to_sample = 8\n'
                           "snapshot_every_s = 0.0\nsnapshot_every_inserts = 0\nsamples_per_insert = 0.0\n")
    return config_path


def _insert_only(work: Path, payloads: list[bytes], clients: int) -> dict:
    """The insert phase alone, into a fresh server that checks PNG headers and CRCs but decodes no pixels."""
    port = free_port()
    proc = _start_server(work / "replay", _write_config(work), port, decode_pixels=False)
    try:
        with open_session(make_config(listen=[], connect=[f"tcp/127.0.0.1:{port}"])) as session:
            client = ZenohReplayClient(session, _RUN_ID)
            if not client.wait_until_ready(60):
                raise TimeoutError("the replay server did not come up within 60 s")
            return _insert_phase(client, payloads, clients, proc.pid)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(30)


def check_ms(payloads: list[bytes], decode_pixels: bool, count: int = 200) -> float:
    """Median ms of the server's insert check (replay/validate.py) on up to `count` payloads, one thread."""
    from romannet.replay.validate import check_transition

    times = []
    for data in payloads[:count]:
        t0 = time.perf_counter()
        check_transition(data, decode_pixels=decode_pixels)
        times.append(time.perf_counter() - t0)
    return round(statistics.median(times) * 1000, 3)


def _pixel_decode_cost(with_decode: dict, without: dict, payloads: list[bytes]) -> dict:
    """What decoding every PNG at insert costs: throughput ratio (with / without) and ms per insert."""
    out = {"inserts_per_s_ratio": round(with_decode["inserts_per_s"] / without["inserts_per_s"], 3),
           "check_ms": check_ms(payloads, True), "check_ms_without": check_ms(payloads, False)}
    if "server_cpu_ms_per_insert" in with_decode and "server_cpu_ms_per_insert" in without:
        out["server_cpu_ms_per_insert_added"] = round(with_decode["server_cpu_ms_per_insert"]
                                                      - without["server_cpu_ms_per_insert"], 3)
    return out


def _measure_workload(work: Path, payloads: list[bytes], repeats: int, clients: int,
                      step_s: float | None) -> dict:
    """A fresh server in work/replay: inserts, samples (batch 1 and 8), kill -9, disk bytes, recovery."""
    store_dir = work / "replay"
    port = free_port()
    proc = _start_server(store_dir, _write_config(work), port)
    out: dict = {}
    try:
        with open_session(make_config(listen=[], connect=[f"tcp/127.0.0.1:{port}"])) as session:
            client = ZenohReplayClient(session, _RUN_ID)
            if not client.wait_until_ready(60):
                raise TimeoutError("the replay server did not come up within 60 s")
            out.update(_insert_phase(client, payloads, clients, proc.pid))
            fsyncs = client.stats().get("log_fsyncs")
            out["inserts_per_fsync"] = round(len(payloads) / fsyncs, 2) if fsyncs else None
            out["sample_b1"] = _sample_phase(client, 1, repeats, proc.pid)
            out["sample_b8"] = _sample_phase(client, 8, repeats, proc.pid)
    finally:
        proc.send_signal(signal.SIGKILL)  # the crash case: recovery below has no shutdown snapshot
        proc.wait(30)
    disk_bytes = sum(p.stat().st_size for p in store_dir.rglob("*") if p.is_file())
    out["bytes_per_transition"] = round(disk_bytes / len(payloads))
    out["recovery_s_per_10k"] = round(_recovery_s(store_dir) / len(payloads) * 10_000, 3)
    cpu_ms = out["sample_b1"].get("server_cpu_ms_per_request")
    out["server_cpu_share_of_learner_step"] = (round(cpu_ms / 1000 / step_s, 4)
                                               if step_s and cpu_ms is not None else None)
    return out


def _meets_targets(out: dict) -> dict[str, bool | None]:
    share = out.get("server_cpu_share_of_learner_step")
    return {
        "inserts_per_s": out["inserts_per_s"] >= TARGETS["inserts_per_s"],
        "sample_p99_ms": max(out["sample_b1"]["p99_ms"], out["sample_b8"]["p99_ms"]) <= TARGETS["sample_p99_ms"],
        "recovery_s_per_10k": out["recovery_s_per_10k"] <= TARGETS["recovery_s_per_10k"],
        "server_cpu_share": None if share is None else share < TARGETS["server_cpu_share"],
    }


def _recovery_s(store_dir: Path) -> float:
    """Seconds to open the store (scan + replay the whole log) in this process, then close it."""
    from romannet.common.config_replay import ReplayConfig
    from romannet.replay.store import ReplayStore

    t0 = time.perf_counter()
    store = ReplayStore(ReplayConfig(min_size_to_sample=8, snapshot_every_s=0.0, snapshot_every_inserts=0),
                        store_dir)
    elapsed = time.perf_counter() - t0
    store.close()
    return elapsed
