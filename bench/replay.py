"""`romannet bench replay`: the replay server over loopback Zenoh, measured end to end.

A real `romannet replay` process (fsync on) serves a fresh directory; this process plays actors and a
learner. Reported (medians and ratios from this one run; the 2-core box drifts):
- durable insert throughput of `clients` concurrent actors (each waits for its ack): transitions/s, MB/s;
- sample round trip p50/p99 for batch 1 and 8 (query to reply bytes; the learner's PNG decode, which
  runs on the learner, is reported separately);
- bytes on disk per stored transition (log segments + snapshot);
- recovery time per 10,000 transitions: opening the store from a log with no snapshot (the kill -9 worst
  case) in this process, after the server was killed;
- the server's CPU time per batch-1 sample request as a share of one learner step, where a learner step
  is forward + backward of one RoManNet net (GRConvNet) at batch 1, 224x224, measured here.
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

from romannet.common import romannet_pb2 as pb
from romannet.common import wire
from romannet.common.action import Action
from romannet.common.imagecodec import units_to_depth_m
from romannet.common.replay_client import ZenohReplayClient
from romannet.common.zenoh_session import free_port, make_config, open_session, query_one

log = logging.getLogger(__name__)

TARGETS = {"inserts_per_s": 500.0, "sample_p99_ms": 20.0, "recovery_s_per_10k": 5.0, "server_cpu_share": 0.10}
_RUN_ID = "bench"


def synthetic_heightmaps(seed: int, side_px: int = 224) -> tuple[np.ndarray, np.ndarray]:
    """A tabletop-like scene: grey floor, 8 coloured boxes 2-10 cm tall, camera-like noise (sigma 3 levels
    of colour, 0.5 mm of depth), so PNG sizes are realistic (random pixels would not compress at all)."""
    rng = np.random.default_rng(seed)
    color = np.full((side_px, side_px, 3), (90, 90, 95), np.float32)
    depth = np.zeros((side_px, side_px), np.float32)
    for _ in range(8):
        y, x = rng.integers(0, side_px - 30, 2)
        s = int(rng.integers(10, 30))
        color[y:y + s, x:x + s] = rng.integers(0, 256, 3)
        depth[y:y + s, x:x + s] = rng.uniform(0.02, 0.10)
    color = np.clip(color + rng.normal(0, 3, color.shape), 0, 255).astype(np.uint8)
    depth = np.clip(depth + rng.normal(0, 5e-4, depth.shape), 0, 0.6)
    return color, units_to_depth_m(np.round(depth / 1e-5).astype(np.uint16))


def encoded_transitions(count: int, scenes: int = 8, seed: int = 0) -> list[bytes]:
    """`count` distinct encoded transitions (unique actor/episode/step) built from `scenes` scenes; only
    the scalar fields are re-serialised per item, so this takes seconds, not count x 25 ms of PNG coding."""
    protos = []
    for k in range(scenes):
        cb, db = synthetic_heightmaps(seed + 2 * k)
        ca, da = synthetic_heightmaps(seed + 2 * k + 1)
        msg = wire.TransitionMsg(
            actor_id=f"bench-{k}", episode_id="ep-0", step=0, start_ns=1, end_ns=2, task="clutter",
            color_before=cb, depth_before=db, color_after=ca, depth_after=da,
            action=Action("pick", 100, 120, 0.5, 0.7, explored=False), success=True, progress_before=0.1,
            progress_after=0.2, reward=1.0, done=False, done_reason="", holding_before=False,
            holding_after=True, policy_version=3, explore_rate=0.2)
        proto = pb.Transition()
        proto.ParseFromString(wire.encode_transition(msg))
        protos.append(proto)
    out = []
    for i in range(count):
        proto = protos[i % scenes]
        proto.episode_id, proto.step = f"ep-{i // 100}", i % 100
        out.append(proto.SerializeToString())
    return out


def _process_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of a process (Linux /proc), or None elsewhere."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def _start_server(directory: Path, config_path: Path, port: int) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "romannet.cli", "--log-level", "WARNING", "replay", "--config",
           str(config_path), "--dir", str(directory), "--listen", f"tcp/127.0.0.1:{port}"]
    return subprocess.Popen(cmd, stdin=subprocess.DEVNULL)


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
    cpu0, client_cpu0 = _process_cpu_s(pid), time.process_time()
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall_s = time.perf_counter() - t0
    cpu1, client_cpu1 = _process_cpu_s(pid), time.process_time()
    if errors:
        raise errors[0]
    n = len(payloads)
    mb = sum(len(p) for p in payloads) / 1e6
    out = {"inserts_per_s": round(n / wall_s, 1), "mb_per_s": round(mb / wall_s, 2),
           "clients": clients, "insert_latency": _percentiles_ms(latencies),
           "payload_kb": round(mb * 1000 / n, 1),
           "client_cpu_ms_per_insert": round((client_cpu1 - client_cpu0) / n * 1000, 3)}
    if cpu0 is not None and cpu1 is not None:
        out["server_cpu_ms_per_insert"] = round((cpu1 - cpu0) / n * 1000, 3)
    return out


def _sample_phase(session, client: ZenohReplayClient, batch_size: int, repeats: int, pid: int) -> dict:
    request_key = client.keys.replay_sample
    times, decode_s = [], []
    cpu0 = _process_cpu_s(pid)
    for i in range(repeats):
        payload = wire.encode_sample_request(wire.SampleRequestMsg(f"b{batch_size}-{i}", batch_size))
        t0 = time.perf_counter()
        reply = query_one(session, request_key, payload, timeout_s=10, parameters="wait_ms=5000")
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
                         directory: str | Path | None = None) -> dict:
    """Run every measurement once; returns one JSON-able dict (see the module docstring)."""
    with tempfile.TemporaryDirectory(prefix="romannet-bench-replay-") as tmp:
        work = Path(directory) if directory is not None else Path(tmp)
        store_dir = work / "replay"
        config_path = work / "bench.toml"
        # No time- or count-based snapshots: the recovery measurement then replays the whole log.
        config_path.write_text(f'run_id = "{_RUN_ID}"\n[replay]\nmin_size_to_sample = 8\n'
                               "snapshot_every_s = 0.0\nsnapshot_every_inserts = 0\n")
        payloads = encoded_transitions(inserts, seed=seed)
        port = free_port()
        proc = _start_server(store_dir, config_path, port)
        result: dict = {"inserts": inserts, "repeats": repeats}
        try:
            with open_session(make_config(listen=[], connect=[f"tcp/127.0.0.1:{port}"])) as session:
                client = ZenohReplayClient(session, _RUN_ID)
                if not client.wait_until_ready(60):
                    raise TimeoutError("the replay server did not come up within 60 s")
                result["insert"] = _insert_phase(client, payloads, clients, proc.pid)
                result["sample_b1"] = _sample_phase(session, client, 1, repeats, proc.pid)
                result["sample_b8"] = _sample_phase(session, client, 8, repeats, proc.pid)
        finally:
            proc.send_signal(signal.SIGKILL)  # the crash case: recovery below has no shutdown snapshot
            proc.wait(30)
        disk_bytes = sum(p.stat().st_size for p in store_dir.rglob("*") if p.is_file())
        result["bytes_per_transition"] = round(disk_bytes / inserts)
        result["recovery_s_per_10k"] = round(_recovery_s(store_dir) / inserts * 10_000, 3)
    step_s = learner_step_s()
    result["learner_step_ms"] = round(step_s * 1000, 1) if step_s else None
    cpu_ms = result["sample_b1"].get("server_cpu_ms_per_request")
    result["server_cpu_share_of_learner_step"] = (round(cpu_ms / 1000 / step_s, 4)
                                                  if step_s and cpu_ms is not None else None)
    result["targets"] = TARGETS
    return result


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
