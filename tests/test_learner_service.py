"""Integration: a real `romannet replay` and a real `romannet learner` process on loopback Zenoh.

The test feeds synthetic 64x64 transitions ([workspace] resolution_m = 0.007) through ZenohReplayClient,
watches weights and exploration rates arrive at a ZenohWeightsSource, stops the learner with SIGTERM and
resumes it. Free ports, multicast scouting off, every session closed, every wait bounded. A tiny model
(4 channels, 1 residual block) and one torch thread keep it light on a shared 2-core box.
"""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
import time
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from _learner_helpers import transition

from romannet.common import romannet_pb2 as pb
from romannet.common import wire
from romannet.common.config import ModelConfig
from romannet.common.errors import DecodeError
from romannet.common.keys import RunKeys
from romannet.common.model import RoManNet, load_tensors, validate_tensors
from romannet.common.replay_client import ZenohReplayClient
from romannet.common.weights_client import ZenohWeightsSource
from romannet.common.zenoh_session import free_port, make_config, open_session, wait_for_liveliness
from romannet.learner.batches import decode_batch_tolerant
from romannet.learner.checkpoint import latest_checkpoint
from romannet.learner.gate import ReplayGate

RUN = "learner-test"
SIDE_PX = 64
MODEL = ModelConfig(channels=4, residual_blocks=1)
CAP = 1.0  # learner.max_updates_per_insert
CONFIG_TOML = f"""run_id = "{RUN}"
[workspace]
resolution_m = 0.007
[model]
channels = {MODEL.channels}
residual_blocks = {MODEL.residual_blocks}
[replay]
min_size_to_sample = 1
samples_per_insert = 0.0  # unpaced: the learner's own cap (max_updates_per_insert) is what is tested
snapshot_every_s = 0.0
snapshot_every_inserts = 0
[learner]
batch_size = 2
precision = "fp32"
max_grad_norm = 10.0
num_threads = 1
min_replay_size = 16
max_updates_per_insert = {CAP}
publish_every_updates = 5
checkpoint_every_updates = 20
"""


class Proc:
    """A `romannet <verb>` subprocess with its output in <tmp>/<name>.log."""

    def __init__(self, tmp: Path, name: str, args: list[str]):
        self.log_path = tmp / f"{name}.log"
        self._log = self.log_path.open("ab")
        self.proc = subprocess.Popen([sys.executable, "-m", "romannet.cli", *args], stdout=self._log,
                                     stderr=subprocess.STDOUT)

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 60) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            return self.proc.wait(timeout_s)
        finally:
            self._log.close()

    def kill(self) -> None:
        """Cleanup after a failed test: no process outlives its test."""
        if self.proc.poll() is None:
            self.stop(signal.SIGKILL)
        self._log.close()

    def output(self) -> str:
        return self.log_path.read_text(errors="replace")[-4000:]

    def alive(self) -> bool:
        return self.proc.poll() is None


def wait_for(fn: Callable[[], Any], timeout_s: float, what: str, proc: Proc) -> Any:
    """Poll fn until it returns something truthy; fail after timeout_s seconds, or at once if proc exits."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and proc.alive():
        value = fn()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"no {what} within {timeout_s} s (process alive: {proc.alive()})\n{proc.output()}")


def synthetic(i: int, **kw: Any) -> wire.TransitionMsg:
    """Pick transitions at varied pixels; every third one succeeds; episodes of 5 steps."""
    rng = np.random.default_rng(i)
    success = i % 3 == 0
    return transition(SIDE_PX, seed=i, row=int(rng.integers(0, SIDE_PX)), col=int(rng.integers(0, SIDE_PX)),
                      angle_rad=float(rng.uniform(-1.5, 1.5)), success=success, reward=1.0 if success else 0.0,
                      episode_id=f"ep-{i // 5}", step=i % 5, done=i % 5 == 4, **kw)


def corrupt_encoded(i: int) -> bytes:
    """An encoded transition whose color PNG has valid headers and CRCs but an IDAT that is not zlib:
    the replay server (header checks only) stores it; only the learner's full decode finds it. Its top
    priority makes the learner draw it early (rank-based: ~9 % per draw among 100 items)."""
    msg = pb.Transition()
    msg.ParseFromString(wire.encode_transition(synthetic(i, initial_priority=1e6)))
    png = msg.color_before_png
    ihdr_end = 8 + 8 + 13 + 4  # signature, then IHDR: length, type, 13 data bytes, CRC
    idat = b"not a zlib stream"
    chunk = (len(idat).to_bytes(4, "big") + b"IDAT" + idat
             + zlib.crc32(b"IDAT" + idat).to_bytes(4, "big"))
    iend = (0).to_bytes(4, "big") + b"IEND" + zlib.crc32(b"IEND").to_bytes(4, "big")
    msg.color_before_png = png[:ihdr_end] + chunk + iend
    return msg.SerializeToString()


def csv_rows(run_dir: Path) -> list[dict[str, str]]:
    path = run_dir / "metrics.csv"
    if not path.exists():
        return []
    with path.open(newline="") as f:
        return [row for row in csv.DictReader(f) if row.get("update")]


def csv_updates(run_dir: Path) -> list[int]:
    return [int(float(row["update"])) for row in csv_rows(run_dir)]


def skipped_items(run_dir: Path) -> float:
    """Corrupt items the learner skipped, by its CSV."""
    return max((float(row["skipped_items"] or 0) for row in csv_rows(run_dir)), default=0.0)


def test_tolerant_batch_decoding_skips_only_the_corrupt_item() -> None:
    good = [wire.SampleItem(i, 0.5, 1.0, wire.encode_transition(synthetic(i))) for i in range(2)]
    bad = wire.SampleItem(7, 0.5, 1.0, corrupt_encoded(7))
    data = wire.encode_sample_batch(wire.SampleBatchMsg("req-1", (good[0], bad, good[1]), 10))
    with pytest.raises(DecodeError):
        wire.decode_sample_batch(data)  # the plain decoder loses the whole batch
    batch, corrupt = decode_batch_tolerant(data, (SIDE_PX, SIDE_PX))
    assert [it.item_id for it in batch.items] == [0, 1] and batch.buffer_size == 10
    assert [c.item_id for c in corrupt] == [7]
    with pytest.raises(DecodeError):
        decode_batch_tolerant(b"\xff\xff garbage")


class FakeStats:
    """Just the stats() of a replay client, with counts the test sets."""

    def __init__(self) -> None:
        self.size = self.inserts = 0

    def stats(self, timeout_s: float = 10.0) -> dict:
        return {"size": self.size, "inserts": self.inserts}


def test_replay_gate_min_size_and_ratio_cap() -> None:
    replay = FakeStats()
    replay.size = replay.inserts = 5
    gate = ReplayGate(replay, min_size=8, max_updates_per_insert=2.0, stats_every_s=0.0)  # type: ignore[arg-type]
    gate.start(updates=100)  # e.g. resumed at update 100
    assert not gate.ready(100) and "5 of the 8" in gate.waiting_reason
    replay.size = replay.inserts = 10
    assert gate.ready(100) and gate.ready(119)  # 2 updates per transition: 10 transitions (5 held + 5 new)
    assert not gate.ready(120) and "ratio cap" in gate.waiting_reason
    replay.size = replay.inserts = 11
    assert gate.ready(121) and not gate.ready(122)


@pytest.fixture
def procs() -> Iterator[list[Proc]]:
    started: list[Proc] = []
    yield started
    for p in started:
        p.kill()


def test_replay_learner_actor_round_trip_sigterm_and_resume(tmp_path: Path, procs: list[Proc]) -> None:
    config = tmp_path / "fleet.toml"
    config.write_text(CONFIG_TOML)
    run_dir = tmp_path / "learner"
    rport, lport = free_port(), free_port()
    learner_args = ["learner", "--run-dir", str(run_dir), "--listen", f"tcp/127.0.0.1:{lport}",
                    "--connect", f"tcp/127.0.0.1:{rport}"]
    # --skip-pixel-decode: a server that checks PNG headers and CRCs only (the default decodes every PNG and
    # refuses the corrupt one below), so the learner's own skip of an undecodable item is what is tested.
    procs.append(Proc(tmp_path, "replay", ["replay", "--config", str(config), "--dir", str(tmp_path / "replay"),
                                           "--listen", f"tcp/127.0.0.1:{rport}", "--skip-pixel-decode"]))
    learner = Proc(tmp_path, "learner", [*learner_args, "--config", str(config)])
    procs.append(learner)
    keys = RunKeys(RUN)
    fresh = RoManNet(MODEL, seed=123)
    versions: list[int] = []
    rates: list[wire.ExplorationRateMsg] = []
    last: dict[str, Any] = {}

    def poll(src: ZenohWeightsSource) -> None:
        got = src.poll_weights()
        if got is not None:
            versions.append(got[0])
            last["tensors"] = got[1]
        rate = src.poll_exploration()
        if rate is not None:
            rates.append(rate)

    session_cfg = make_config(listen=[], connect=[f"tcp/127.0.0.1:{rport}", f"tcp/127.0.0.1:{lport}"])
    with open_session(session_cfg) as session:
        client = ZenohReplayClient(session, RUN, expected_shape=(SIDE_PX, SIDE_PX))
        wait_for(lambda: client.wait_until_ready(0.5), 90, "replay server", procs[0])
        with ZenohWeightsSource(session, RUN, fetch_timeout_s=10,
                                validate=lambda t: validate_tensors(fresh, t)) as src:
            wait_for(lambda: wait_for_liveliness(session, keys.learner_alive, 0.5), 90, "learner", learner)
            for i in range(100):
                assert client.insert(synthetic(i)).status == "accepted"
                if i == 50:
                    assert client.insert_encoded(corrupt_encoded(1000)).status == "accepted"
                poll(src)

            def trained() -> bool:
                poll(src)
                return (bool(versions) and versions[-1] >= 20 and len(csv_updates(run_dir)) >= 20
                        and skipped_items(run_dir) >= 1)
            wait_for(trained, 120, "20 updates, weights v20 at the actor and a skipped corrupt item", learner)
            stats = client.stats()
            assert stats["priority_updates"] > 0, stats
            assert learner.stop() == 0, learner.output()
            inserted = client.stats()["inserts"]

            assert versions == sorted(set(versions)) and len(versions) >= 3, versions
            load_tensors(fresh, last["tensors"])
            rate_versions = [r.version for r in rates]
            assert rate_versions == sorted(set(rate_versions)) and len(rates) >= 2, rate_versions
            assert all(0.0 <= r.value <= 1.0 and r.policy == "lae" for r in rates)

            ckpt = latest_checkpoint(run_dir)
            assert ckpt is not None, learner.output()
            saved_updates = json.loads((ckpt / "state.json").read_text())["updates"]
            rows = csv_updates(run_dir)
            assert rows[-1] == saved_updates and rows == sorted(rows)
            assert saved_updates <= CAP * inserted + 1, (saved_updates, inserted)  # the replay-ratio cap
            assert (run_dir / "config.toml").is_file() and (run_dir / "learning_curves.png").is_file()
            assert any((run_dir / "tensorboard").iterdir())

            # Resume: no --config (the run's config.toml), and training continues from saved_updates.
            learner = Proc(tmp_path, "learner2", [*learner_args, "--resume"])
            procs.append(learner)
            for i in range(100, 110):
                client.insert(synthetic(i))

            def continued() -> bool:
                poll(src)
                return len(csv_updates(run_dir)) > len(rows) + 5 and versions[-1] > saved_updates
            wait_for(continued, 120, "updates after the resume", learner)
            assert csv_updates(run_dir)[len(rows)] == saved_updates + 1
            assert learner.stop() == 0, learner.output()
    assert f"(update {saved_updates})" in learner.output()
    final = json.loads((latest_checkpoint(run_dir) / "state.json").read_text())["updates"]  # type: ignore[operator]
    assert final > saved_updates
    assert procs[0].stop() == 0
