"""Watch a run's liveliness tokens and write each change with its time, for the fault scenario.

    python -m romannet.bench.fleet_watch --zenoh-config operator.json5 --run-id r1 --out events.jsonl

One JSON object per line: {"t": CLOCK_MONOTONIC seconds, "kind": "put" | "delete", "key": "<token key>"}
for liveliness changes, {"t", "kind": "weights", "version": N} for each weights announcement.
CLOCK_MONOTONIC is one clock for every process of the machine (network namespaces share it), so the
scenario compares these times with the moment it killed a process. Runs until SIGTERM / SIGINT.
"""

from __future__ import annotations

import argparse
import json
import logging
import threading
import time
from pathlib import Path

import zenoh

from romannet.common import wire
from romannet.common.errors import DecodeError
from romannet.common.keys import RunKeys
from romannet.common.signals import stop_on_signals
from romannet.common.zenoh_session import make_config, open_session


def watch(config_file: str, run_id: str, out: Path, stop: threading.Event) -> None:
    lock = threading.Lock()
    with out.open("a", encoding="utf-8") as fh, open_session(make_config(config_file)) as session:
        def on_change(sample: zenoh.Sample) -> None:
            line = json.dumps({"t": time.monotonic(), "key": str(sample.key_expr),
                               "kind": "put" if sample.kind == zenoh.SampleKind.PUT else "delete"})
            with lock:
                fh.write(line + "\n")
                fh.flush()

        def on_weights(sample: zenoh.Sample) -> None:
            try:
                version = wire.decode_weights_announcement(sample.payload.to_bytes()).version
            except DecodeError:
                return
            with lock:
                fh.write(json.dumps({"t": time.monotonic(), "kind": "weights", "version": version}) + "\n")
                fh.flush()

        keys = RunKeys(run_id)
        subs = [session.liveliness().declare_subscriber(f"{keys.root}/**", on_change, history=True),
                session.declare_subscriber(keys.weights_announce, on_weights)]
        try:
            stop.wait()
        finally:
            for sub in subs:
                sub.undeclare()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--zenoh-config", required=True)
    p.add_argument("--run-id", required=True)
    p.add_argument("--out", required=True, type=Path)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    stop = threading.Event()
    with stop_on_signals(stop, "stopping the watch"):
        watch(args.zenoh_config, args.run_id, args.out, stop)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
