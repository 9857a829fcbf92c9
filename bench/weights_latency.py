"""Weights propagation: latency from the learner publishing version N to every actor holding it, and the
bytes that leave the learner per version.

    measure_weights_latency(actors=8, repeats=5)                  # through a router, three protocols
    python -m romannet.bench.weights_latency --actors 1 8 --json  # the same for several fleet sizes

The "learner" is this process: a WeightsPublisher (learner/publisher.py) on a Zenoh session, with the
learner's liveliness token. With topology "router" a `romannet router` process listens on a free loopback
port and the learner and the actors are its clients, as on a fleet network; with "peer" the actors connect
to the learner's session directly. Each "light actor" is a separate process (`--light-actor`) without
physics: a ZenohWeightsSource (common/weights_client.py, what real actors use) and a RoManNet of the same
config; it polls every 2 ms and, when a new version arrives, validates and loads it into its model (what an
actor does before its next action), then appends `<version> <monotonic_ns>` to its report file.
CLOCK_MONOTONIC is system-wide on Linux, so the times compare across processes.

The same actors are served by three protocols, `repeats` versions each (ratios within one run):
"fetch-fp32" announces only, so every actor fetches its own copy with a query (the protocol before the
put); "push-fp32" puts each version once on weights/data; "push-bf16" does so with the body's convolutions
in bf16 (common/weights_wire.py). Fetch runs first, as a block: actors that have seen a push wait a moment
for the data before fetching an announced version. The push modes then take turns version by version.

Latency per version = the slowest actor's load time - the time publish_weights() was called (the learner's
encoding, SHA-256 and puts included). Bytes per version = the growth of `bytes_acked` of this process's TCP
sockets (`ss -ti`) from just before the publish until every actor holds the version: what went out of the
learner's machine. Zenoh's shared memory between local processes is off in every session here, so the
sockets carry what a network between machines would. A real actor also waits for the action under way to end before it swaps weights; that
wait is the action time and is not measured here.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

RUN_ID = "bench-weights"
MODES = ("fetch-fp32", "push-fp32", "push-bf16")
_POLL_S = 0.002
# Longer than an actor's default 10 s: eight 23 MB fetches through one router on a busy 2-core box can
# take more, and a failed fetch would leave the fetch-only protocol's version undelivered.
_FETCH_TIMEOUT_S = 120.0
_SOCKET = re.compile(r"pid=(\d+),")
_ACKED = re.compile(r"bytes_acked:(\d+)")


def _light_actor(connect: str, mode: str, report: Path, stop: Path, channels: int, blocks: int,
                 timeout_s: float) -> None:
    """Hold the newest weights until `stop` exists; report each version when it is loaded."""
    import torch

    from romannet.common.config import ModelConfig
    from romannet.common.model import RoManNet, load_tensors, validate_tensors
    from romannet.common.weights_client import ZenohWeightsSource
    from romannet.common.zenoh_session import make_config, open_session

    torch.set_num_threads(1)
    model = RoManNet(ModelConfig(channels=channels, residual_blocks=blocks))
    config = _no_shm(make_config(listen=[], connect=[connect]))
    config.insert_json5("mode", json.dumps(mode))
    deadline = time.monotonic() + timeout_s
    with open_session(config) as session, \
            ZenohWeightsSource(session, RUN_ID, fetch_timeout_s=_FETCH_TIMEOUT_S,
                               validate=lambda t: validate_tensors(model, t)) as source, \
            report.open("a") as out:
        while not stop.exists() and time.monotonic() < deadline:
            got = source.poll_weights()
            if got is None:
                time.sleep(_POLL_S)
                continue
            version, tensors = got
            load_tensors(model, tensors)
            out.write(f"{version} {time.monotonic_ns()}\n")
            out.flush()


def _reports(paths: list[Path]) -> list[dict[int, int]]:
    """{version: monotonic_ns} per light actor (lines not yet complete are skipped)."""
    out = []
    for path in paths:
        seen: dict[int, int] = {}
        try:
            for line in path.read_text().splitlines():
                parts = line.split()
                if len(parts) == 2:
                    seen[int(parts[0])] = int(parts[1])
        except (OSError, ValueError):
            pass
        out.append(seen)
    return out


def _wait_all(paths: list[Path], version: int, timeout_s: float) -> list[dict[int, int]]:
    deadline = time.monotonic() + timeout_s
    while True:
        reports = _reports(paths)
        if all(version in r for r in reports):
            return reports
        if time.monotonic() > deadline:
            missing = sum(version not in r for r in reports)
            raise TimeoutError(f"{missing} of {len(paths)} light actors did not load weights v{version} in "
                               f"{timeout_s:.0f} s")
        time.sleep(0.005)


def bytes_out(pid: int | None, netns: str | None = None) -> int | None:
    """Bytes acknowledged by the peers of pid's established TCP sockets (None without a working `ss`).
    netns: count in that network namespace (`ip netns exec`); pid None there counts every socket of it,
    which is one process's egress when the namespace is a host of its own (bench/netns.py)."""
    argv = ["ss", "-tinpH", "state", "established"]
    try:
        text = subprocess.run(["ip", "netns", "exec", netns, *argv] if netns else argv, capture_output=True,
                              text=True, timeout=10, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    total, mine = 0, False
    for line in text.splitlines():  # a socket's line (with its process) then its indented info line
        if not line[:1].isspace():
            owner = _SOCKET.search(line)
            mine = pid is None or (owner is not None and int(owner.group(1)) == pid)
        elif mine and (acked := _ACKED.search(line)):
            total += int(acked.group(1))
            mine = False
    return total


def _no_shm(config: Any) -> Any:
    """Zenoh moves large payloads between processes of one host through shared memory and sends only a
    reference on the socket: off, so the bytes on the sockets are those a network between machines carries."""
    config.insert_json5("transport/shared_memory/enabled", "false")
    return config


def router_argv(folder: Path, listen: str) -> list[str]:
    """`romannet router` on endpoint `listen`, multicast scouting and shared memory off (its config goes in
    folder)."""
    config = folder / "router.json5"
    config.write_text('{mode: "router", scouting: {multicast: {enabled: false}}, '
                      'transport: {shared_memory: {enabled: false}}}')
    return [sys.executable, "-m", "romannet.cli", "router", "--zenoh-config", str(config), "--listen", listen]


def start_router(port: int, folder: Path) -> subprocess.Popen:
    """A `romannet router` process on 127.0.0.1:port, once it accepts TCP."""
    log_path = folder / "router.log"
    with log_path.open("ab") as log_file:
        proc = subprocess.Popen(router_argv(folder, f"tcp/127.0.0.1:{port}"), stdin=subprocess.DEVNULL,
                                stdout=log_file, stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the router exited with {proc.returncode}: {log_path.read_text()[-2000:]}")
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return proc
        time.sleep(0.1)
    proc.kill()
    raise TimeoutError("the router did not listen within 60 s")


def stop_process(proc: subprocess.Popen, signal_first: bool = False) -> None:
    if signal_first and proc.poll() is None:
        proc.terminate()
    try:
        proc.wait(30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()


def _median(values: list[float]) -> float | None:
    return round(statistics.median(values), 1) if values else None


def measure_weights_latency(actors: int, repeats: int = 5, channels: int = 32, blocks: int = 5,
                            topology: str = "router", modes: tuple[str, ...] = MODES,
                            start_timeout_s: float = 180.0) -> dict[str, Any]:
    """Publish `repeats` new versions per mode to `actors` light actors; milliseconds and bytes (medians).
    The top-level latency fields are the last mode's (the learner's default protocol)."""
    from romannet.common.config import ModelConfig
    from romannet.common.keys import RunKeys
    from romannet.common.model import RoManNet, state_dict_to_tensors
    from romannet.common.zenoh_session import free_port, make_config, open_session
    from romannet.learner.publisher import WeightsPublisher

    if topology not in ("router", "peer") or not modes or any(m not in MODES for m in modes):
        raise ValueError(f"topology must be 'router' or 'peer' and modes some of {MODES}")
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    tensors = state_dict_to_tensors(RoManNet(ModelConfig(channels=channels, residual_blocks=blocks)))
    results: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory(prefix="romannet-bench-weights-") as tmp:
        stop = Path(tmp) / "stop"
        paths = [Path(tmp) / f"actor-{i}.txt" for i in range(actors)]
        procs: list[subprocess.Popen] = []
        router = start_router(port, Path(tmp)) if topology == "router" else None
        config = _no_shm(make_config(listen=[] if router else [endpoint], connect=[endpoint] if router else []))
        if router:
            config.insert_json5("mode", '"client"')
        try:
            with open_session(config) as session:
                publisher = WeightsPublisher(session, RUN_ID, *_publisher_args(modes[0]))
                publisher.publish_weights(0, tensors)
                token = session.liveliness().declare_token(RunKeys(RUN_ID).learner_alive)
                try:
                    for path in paths:
                        procs.append(subprocess.Popen(
                            [sys.executable, "-m", "romannet.bench.weights_latency", "--light-actor",
                             "--connect", endpoint, "--mode", "client" if router else "peer", "--report",
                             str(path), "--stop", str(stop), "--channels", str(channels), "--blocks", str(blocks)],
                            stdin=subprocess.DEVNULL))
                    _wait_all(paths, 0, start_timeout_s)  # connected, fetched the current version, loaded it
                    version = 0
                    for block in _blocks(modes):
                        publisher.close()
                        publisher = WeightsPublisher(session, RUN_ID, *_publisher_args(block[0]))
                        measured, version = _measure_block(publisher, block, tensors, paths, version, repeats)
                        results.update(measured)
                finally:
                    stop.touch()
                    for p in procs:
                        stop_process(p)
                    token.undeclare()
                    publisher.close()
        finally:
            if router is not None:
                stop_process(router, signal_first=True)
    last = results[modes[-1]]
    fp32_bytes = sum(t.numel() * 4 if t.is_floating_point() else t.numel() * t.element_size()
                     for t in tensors.values())
    return {"actors": actors, "repeats": repeats, "topology": topology, "fp32_tensor_bytes": fp32_bytes,
            "all_actors_ms_median": last["all_actors_ms_median"],
            "per_actor_ms_median": last["per_actor_ms_median"],
            "publish_call_ms_median": last["publish_call_ms_median"], "modes": results}


def _blocks(modes: tuple[str, ...]) -> list[tuple[str, ...]]:
    """The fetch modes, then the push modes: each group is served by one publisher, its modes in turns."""
    groups = [tuple(m for m in modes if not _publisher_args(m)[1]), tuple(m for m in modes if _publisher_args(m)[1])]
    return [g for g in groups if g]


def _publisher_args(mode: str) -> tuple[str, bool]:
    """(wire dtype, push) of a mode name."""
    protocol, dtype = mode.split("-")
    return dtype, protocol == "push"


def _measure_block(publisher: Any, modes: tuple[str, ...], tensors: dict, paths: list[Path], version: int,
                   repeats: int) -> tuple[dict[str, dict[str, Any]], int]:
    """`repeats` versions per mode through one publisher, the modes (same push, their own wire dtype) taking
    turns version by version, so that a drift of the machine's load falls on each alike. Returns each mode's
    medians and the last version published."""
    samples: dict[str, dict[str, list]] = {m: {"all": [], "each": [], "call": [], "sent": [], "size": []}
                                           for m in modes}
    if publisher.push:
        # Unmeasured: an actor's first pushed version may race its announcement (no push seen yet, so no
        # wait for the data) and be fetched too, once in the actor's life; the rounds below are the steady state.
        version += 1
        publisher.publish_weights(version, tensors)
        _wait_all(paths, version, 120.0)
    served_before = publisher.served
    for _ in range(repeats):
        for mode in modes:
            publisher.wire_dtype = _publisher_args(mode)[0]
            version += 1
            time.sleep(0.5)  # let the previous round's work settle
            before = bytes_out(os.getpid())
            t0 = time.monotonic_ns()
            announcement = publisher.publish_weights(version, tensors)
            call_ms = (time.monotonic_ns() - t0) / 1e6
            reports = _wait_all(paths, version, 120.0)
            after = bytes_out(os.getpid())
            lat = [(r[version] - t0) / 1e6 for r in reports]
            got = samples[mode]
            got["all"].append(max(lat))
            got["each"].extend(lat)
            got["call"].append(call_ms)
            got["size"].append(announcement.size_bytes)
            if before is not None and after is not None:
                got["sent"].append(after - before)
    fetches = round((publisher.served - served_before) / (repeats * len(modes)), 2)
    return {m: _summary(got, fetches) for m, got in samples.items()}, version


def _summary(got: dict[str, list], fetches_per_version: float) -> dict[str, Any]:
    size, sent = got["size"][-1], got["sent"]
    return {"weights_bytes": size,
            "learner_bytes_out_per_version_median": int(statistics.median(sent)) if sent else None,
            "copies_per_version": round(statistics.median(sent) / size, 2) if sent else None,
            "fetches_per_version": fetches_per_version,
            "all_actors_ms_median": _median(got["all"]), "all_actors_ms": [round(v, 1) for v in got["all"]],
            "per_actor_ms_median": _median(got["each"]), "publish_call_ms_median": _median(got["call"])}


def main(argv: list[str] | None = None) -> int:
    """The benchmark (one JSON object per fleet size, or one list with --json), or a light actor process."""
    p = argparse.ArgumentParser(description="weights latency and learner egress per version, 1..N light actors")
    p.add_argument("--actors", type=int, nargs="+", default=[1, 8])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--topology", choices=("router", "peer"), default="router")
    p.add_argument("--modes", nargs="+", choices=MODES, default=list(MODES))
    p.add_argument("--json", action="store_true", help="one JSON list on stdout")
    # A light actor (started by the benchmark itself).
    p.add_argument("--light-actor", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--connect", help=argparse.SUPPRESS)
    p.add_argument("--mode", default="peer", help=argparse.SUPPRESS)
    p.add_argument("--report", type=Path, help=argparse.SUPPRESS)
    p.add_argument("--stop", type=Path, help=argparse.SUPPRESS)
    p.add_argument("--channels", type=int, default=32)
    p.add_argument("--blocks", type=int, default=5)
    p.add_argument("--timeout-s", type=float, default=900.0, help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.light_actor:
        logging.basicConfig(level=logging.WARNING)
        _light_actor(args.connect, args.mode, args.report, args.stop, args.channels, args.blocks, args.timeout_s)
        return 0
    logging.basicConfig(level=logging.INFO, stream=sys.stderr)
    results = []
    for n in args.actors:
        results.append(measure_weights_latency(n, args.repeats, args.channels, args.blocks, args.topology,
                                               tuple(args.modes)))
        log.info("%d actor(s): %s", n, json.dumps(results[-1]))  # kept if a later size fails
    sys.stdout.write(json.dumps(results if args.json else results[-1]) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
