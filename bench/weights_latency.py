"""Weights propagation latency: from the learner publishing version N to every actor holding it, loaded.

    measure_weights_latency(actors=8, repeats=5)

The "learner" is this process: a WeightsPublisher (learner/publisher.py) on a Zenoh session listening on a
free loopback port, with the learner's liveliness token. Each "light actor" is a separate process
(`python -m romannet.bench.weights_latency --light-actor ...`) without physics: a Zenoh session connected
to that port, a ZenohWeightsSource (common/weights_client.py, what real actors use), a RoManNet of the
same config; it polls every 2 ms and, when a new version arrives, validates and loads it into its model
(what an actor does before its next action), then appends `<version> <monotonic_ns>` to its report
file. CLOCK_MONOTONIC is system-wide on Linux, so the times compare across processes.

Latency per version = the slowest actor's load time - the time publish_weights() was called (so the
learner's own encoding, SHA-256 and announcement are included). A real actor also waits for the action
under way to end before it swaps weights; that wait is the action time and is not measured here.
"""

from __future__ import annotations

import argparse
import logging
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

log = logging.getLogger(__name__)

RUN_ID = "bench-weights"
_POLL_S = 0.002


def _light_actor(connect: str, report: Path, stop: Path, channels: int, blocks: int, timeout_s: float) -> None:
    """Hold the newest weights until `stop` exists; report each version when it is loaded."""
    import torch

    from romannet.common.config import ModelConfig
    from romannet.common.model import RoManNet, load_tensors, validate_tensors
    from romannet.common.weights_client import ZenohWeightsSource
    from romannet.common.zenoh_session import make_config, open_session

    torch.set_num_threads(1)
    model = RoManNet(ModelConfig(channels=channels, residual_blocks=blocks))
    deadline = time.monotonic() + timeout_s
    with open_session(make_config(listen=[], connect=[connect])) as session, \
            ZenohWeightsSource(session, RUN_ID, validate=lambda t: validate_tensors(model, t)) as source, \
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


def measure_weights_latency(actors: int, repeats: int = 5, channels: int = 32, blocks: int = 5,
                            start_timeout_s: float = 180.0) -> dict[str, Any]:
    """Publish `repeats` new versions to `actors` light actors; latencies in milliseconds (medians)."""
    from romannet.common.config import ModelConfig
    from romannet.common.keys import RunKeys
    from romannet.common.model import RoManNet, state_dict_to_tensors
    from romannet.common.zenoh_session import free_port, make_config, open_session
    from romannet.learner.publisher import WeightsPublisher

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    tensors = state_dict_to_tensors(RoManNet(ModelConfig(channels=channels, residual_blocks=blocks)))
    with tempfile.TemporaryDirectory(prefix="romannet-bench-weights-") as tmp:
        stop = Path(tmp) / "stop"
        paths = [Path(tmp) / f"actor-{i}.txt" for i in range(actors)]
        procs: list[subprocess.Popen] = []
        with open_session(make_config(listen=[endpoint], connect=[])) as session, \
                WeightsPublisher(session, RUN_ID) as publisher:
            first = publisher.publish_weights(0, tensors)
            token = session.liveliness().declare_token(RunKeys(RUN_ID).learner_alive)
            try:
                for path in paths:
                    procs.append(subprocess.Popen(
                        [sys.executable, "-m", "romannet.bench.weights_latency", "--light-actor", "--connect",
                         endpoint, "--report", str(path), "--stop", str(stop), "--channels", str(channels),
                         "--blocks", str(blocks)], stdin=subprocess.DEVNULL))
                _wait_all(paths, 0, start_timeout_s)  # connected, fetched the current version, loaded it
                all_ms, each_ms, publish_ms = [], [], []
                for version in range(1, repeats + 1):
                    time.sleep(0.5)  # let the previous round's work settle
                    t0 = time.monotonic_ns()
                    publisher.publish_weights(version, tensors)
                    publish_ms.append((time.monotonic_ns() - t0) / 1e6)
                    reports = _wait_all(paths, version, 60.0)
                    lat = [(r[version] - t0) / 1e6 for r in reports]
                    all_ms.append(max(lat))
                    each_ms.extend(lat)
            finally:
                stop.touch()
                for p in procs:
                    try:
                        p.wait(30)
                    except subprocess.TimeoutExpired:
                        p.kill()
                        p.wait()
                token.undeclare()
    return {"actors": actors, "repeats": repeats, "weights_bytes": first.size_bytes,
            "all_actors_ms_median": round(statistics.median(all_ms), 1),
            "all_actors_ms": [round(v, 1) for v in all_ms],
            "per_actor_ms_median": round(statistics.median(each_ms), 1),
            "publish_call_ms_median": round(statistics.median(publish_ms), 1)}


def main(argv: list[str] | None = None) -> int:
    """Entry point of a light actor process."""
    p = argparse.ArgumentParser(description="light actor for the weights-latency benchmark (internal)")
    p.add_argument("--light-actor", action="store_true", required=True)
    p.add_argument("--connect", required=True)
    p.add_argument("--report", required=True, type=Path)
    p.add_argument("--stop", required=True, type=Path)
    p.add_argument("--channels", type=int, default=32)
    p.add_argument("--blocks", type=int, default=5)
    p.add_argument("--timeout-s", type=float, default=900.0)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING)
    _light_actor(args.connect, args.report, args.stop, args.channels, args.blocks, args.timeout_s)
    return 0


if __name__ == "__main__":
    sys.exit(main())
