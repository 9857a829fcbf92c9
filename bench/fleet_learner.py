"""The learner of `romannet bench fleet`: `romannet learner` itself, with a clock on its weights publisher.

    python -m romannet.bench.fleet_learner PROBE_FILE [romannet learner arguments...]

Everything is the real learner (learner/main.py, its config, training, checkpoints and metrics); only its
WeightsPublisher is replaced by a subclass that appends `<version> <call_ns> <return_ns> <size_bytes>` to
PROBE_FILE per publish (CLOCK_MONOTONIC, comparable with the light actors' times). The latency the issue asks
for starts at the publish call, encoding and hashing included, which no message on the wire carries.
"""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any


def install_probe(probe: Path) -> None:
    """Make learner/service.py publish through a publisher that writes each publish's times to probe."""
    from romannet.learner import service

    lock = threading.Lock()

    class TimedPublisher(service.WeightsPublisher):  # type: ignore[misc,valid-type]
        def publish_weights(self, version: int, tensors: Mapping[str, Any]) -> Any:
            t0 = time.monotonic_ns()
            announcement = super().publish_weights(version, tensors)
            t1 = time.monotonic_ns()
            with lock, probe.open("a") as out:
                out.write(f"{version} {t0} {t1} {announcement.size_bytes}\n")
            return announcement

    service.WeightsPublisher = TimedPublisher  # type: ignore[misc]


def main(argv: list[str] | None = None) -> int:
    args = list(sys.argv[1:] if argv is None else argv)
    if not args:
        sys.stderr.write("usage: python -m romannet.bench.fleet_learner PROBE_FILE [learner arguments]\n")
        return 2
    install_probe(Path(args[0]))
    from romannet.cli import main as cli_main

    return cli_main(["--log-level", "INFO", "learner", *args[1:]])


if __name__ == "__main__":
    sys.exit(main())
