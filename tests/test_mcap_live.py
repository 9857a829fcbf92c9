"""Episode files meet live components: `romannet mcap feed` into a real `romannet replay` process, `play` on
Zenoh and to a real Foxglove WebSocket server, and `romannet learner --offline` training from recordings.

Loopback only, free ports, multicast scouting off, every session closed, every wait bounded. Episodes come
from the real recorder (tests/_episodes.py, 32x32 heightmaps, resolution 0.014 m); the learner runs a tiny
model on one thread.
"""

from __future__ import annotations

import base64
import csv
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from _episodes import record_episode
from mcap.reader import make_reader

from romannet.actor.recorder import count_steps
from romannet.cli import main
from romannet.common.episode_file import EpisodeReader, read_episode
from romannet.common.keys import RunKeys
from romannet.common.replay_client import ZenohReplayClient
from romannet.common.zenoh_session import free_port, make_config, open_session
from romannet.mcaptools.play import PlayOptions, play, scan
from romannet.mcaptools.sinks import FoxgloveSink
from romannet.mcaptools.steps import parse_transition
from romannet.replay.recordcheck import CHECK_BYTES, record_problem

pytestmark = pytest.mark.timeout(120)

RUN = "mcap-live"
CONFIG = f"""run_id = "{RUN}"
[workspace]
resolution_m = 0.014
[model]
channels = 4
residual_blocks = 1
num_threads = 1
[replay]
min_size_to_sample = 1
samples_per_insert = 0.0  # unpaced: recordings are fed before (or without) a learner sampling
snapshot_every_s = 0.0
snapshot_every_inserts = 0
[learner]
batch_size = 2
precision = "fp32"
max_grad_norm = 10.0
num_threads = 1
min_replay_size = 4
publish_every_updates = 1
checkpoint_every_updates = 100
"""


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory):
    """a0: 6 steps, finished; a1: 4 steps, writer died after its last step; a2: cut in the middle."""
    root = tmp_path_factory.mktemp("recordings")
    full = record_episode(root / "a0" / "ep000000.mcap", 6, run_id=RUN)
    crashed = record_episode(root / "a1" / "ep000001.mcap", 4, actor_id="a1", episode_id="ep000001", seed=3,
                             run_id=RUN, finish=False)
    source = record_episode(root.parent / "whole-a2.mcap", 5, actor_id="a2", episode_id="ep000002", seed=5,
                            run_id=RUN)
    data = source.path.read_bytes()
    (root / "a2").mkdir()
    (root / "a2" / "ep000002.mcap").write_bytes(data[: len(data) // 2])
    whole = count_steps(root / "a2" / "ep000002.mcap")
    assert 1 <= whole < 5
    expected = full.transitions + crashed.transitions + source.transitions[:whole]
    return root, expected


class Proc:
    """A `romannet <verb>` subprocess with its output in <tmp>/<name>.log."""

    def __init__(self, tmp: Path, name: str, *argv: str):
        self.log_path = tmp / f"{name}.log"
        self._log = open(self.log_path, "ab")  # noqa: SIM115 - closed in stop()
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        self.proc = subprocess.Popen([sys.executable, "-m", "romannet.cli", *argv], stdout=self._log,
                                     stderr=subprocess.STDOUT, env=env)

    def output(self) -> str:
        return self.log_path.read_text(errors="replace")

    def wait(self, timeout_s: float) -> int:
        try:
            return self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"{self.proc.args} did not finish in {timeout_s} s:\n{self.output()}") from None

    def stop(self, sig: int = signal.SIGTERM, timeout_s: float = 30) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        try:
            return self.wait(timeout_s)
        finally:
            self._log.close()

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)
        self._log.close()


@pytest.fixture
def procs() -> Iterator[list[Proc]]:
    started: list[Proc] = []
    yield started
    for p in started:
        p.kill()


def _replay(tmp: Path, procs: list[Proc]) -> tuple[Proc, str]:
    (tmp / "run.toml").write_text(CONFIG)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = Proc(tmp, "replay", "replay", "--config", str(tmp / "run.toml"), "--dir", str(tmp / "replay"),
                  "--listen", endpoint)
    procs.append(server)
    return server, endpoint


def _feed(capsys: pytest.CaptureFixture[str], endpoint: str, *inputs: Path) -> tuple[int, dict, str]:
    code = main(["mcap", "feed", *map(str, inputs), "--connect", endpoint, "--json", "--wait", "60"])
    out, err = capsys.readouterr()
    return code, json.loads(out.strip().splitlines()[-1]), err


# ------------------------------------------------------------------------------------------------------ feed
def test_feed_round_trip_exactly_once_bit_equal_and_idempotent(recordings, tmp_path: Path, procs, capsys) -> None:
    root, expected = recordings
    server, endpoint = _replay(tmp_path, procs)
    (tmp_path / "notes.mcap").write_text("not a recording")
    code, first, err = _feed(capsys, endpoint, root, tmp_path / "notes.mcap")
    assert code == 1 and f"{tmp_path / 'notes.mcap'}: not an MCAP file" in err  # the bad file, named
    assert (first["files"], first["transitions"], first["accepted"]) == (3, len(expected), len(expected))
    assert (first["duplicates"], first["rejected"], first["replay_size"]) == (0, 0, len(expected))
    assert len(first["truncated_files"]) == 2
    code, again, _ = _feed(capsys, endpoint, root)  # the same files again: nothing is added
    assert code == 0
    assert (again["accepted"], again["duplicates"], again["replay_size"]) == (0, len(expected), len(expected))
    # Rescored experience is new experience (new episode ids) and feeding it twice adds it once.
    for new in (len(expected), 0):
        code = main(["mcap", "rescore", str(root), "--set", "reward.push_weight=0.5", "--feed", "--connect",
                     endpoint, "--json"])
        feed = json.loads(capsys.readouterr().out)["feed"]
        assert code == 0 and (feed["accepted"], feed["duplicates"]) == (new, len(expected) - new)
    assert server.stop() == 0, server.output()
    stored = []
    for segment in sorted((tmp_path / "replay").glob("segment-*.mcap")):
        with open(segment, "rb") as f:
            stored += [m.data for _, _, m in make_reader(f).iter_messages()]
    # The log keeps each transition as received, plus the priority it was inserted with (protobuf field 23,
    # appended: replay/recovery.py priority_suffix) and the record's checksum (replay/recordcheck.py), so the
    # recorded bytes are a prefix of every record.
    assert all(record_problem(item_id, r) is None for item_id, r in enumerate(stored))
    stored = [r[:-CHECK_BYTES] for r in stored]
    assert all(len(r) > 10 and r[-10:-8] == b"\xb9\x01" for r in stored)
    rescored = [r for r in stored if ".rs-" in parse_transition(r).episode_id]
    assert len(rescored) == len(expected)
    originals = sorted(r[:-10] for r in stored if r not in rescored)
    assert originals == sorted(expected)  # every recorded transition exactly once, bit-equal


# ------------------------------------------------------------------------------------------------------ play
def test_play_on_zenoh_delivers_every_message_in_recorded_order(recordings, capsys) -> None:
    root, _ = recordings
    path = root / "a0" / "ep000000.mcap"
    recorded = list(EpisodeReader(path).messages())
    got: list[tuple[str, bytes, dict]] = []
    done = threading.Event()
    port = free_port()
    keys = RunKeys(RUN)
    prefix = keys.actor_live("a0", "x")[:-1]

    def on_sample(sample) -> None:
        got.append((str(sample.key_expr).removeprefix(prefix), sample.payload.to_bytes(),
                    json.loads(sample.attachment.to_bytes())))
        if len(got) == len(recorded):
            done.set()

    with open_session(make_config(listen=[f"tcp/127.0.0.1:{port}"], connect=[])) as session:
        sub = session.declare_subscriber(keys.actors_live, on_sample)
        try:
            started = time.monotonic()
            code = main(["mcap", "play", str(path), "--zenoh", "--speed", "20", "--zenoh-wait", "10",
                         "--connect", f"tcp/127.0.0.1:{port}"])
            elapsed = time.monotonic() - started
            assert code == 0, capsys.readouterr().err
            assert done.wait(30), f"{len(got)} of {len(recorded)} messages arrived"
        finally:
            sub.undeclare()
    assert [topic for topic, _, _ in got] == [m.topic.lstrip("/") for m in recorded]
    assert [data for _, data, _ in got] == [m.data for m in recorded]
    assert [a["log_time_ns"] for _, _, a in got] == [m.log_time_ns for m in recorded]
    span_s = (recorded[-1].log_time_ns - recorded[0].log_time_ns) / 1e9
    assert elapsed >= 0.9 * span_s / 20  # it waited the recorded time, at 20x
    assert f"played {len(recorded)} of {len(recorded)} messages" in capsys.readouterr().out


class WebSocket:
    """Just enough of a WebSocket client (RFC 6455) to talk to the Foxglove server as the app does."""

    def __init__(self, port: int, protocols: str = "foxglove.sdk.v1, foxglove.websocket.v1"):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade"
                           f"\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: "
                           f"{protocols}\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            head += self.sock.recv(1)
        assert head.startswith(b"HTTP/1.1 101"), head

    def _read(self, n: int) -> bytes:
        out = b""
        while len(out) < n:
            chunk = self.sock.recv(n - len(out))
            if not chunk:
                raise ConnectionError("the server closed the connection")
            out += chunk
        return out

    def recv(self) -> tuple[int, bytes]:
        """(opcode, payload) of the next whole message (fragments joined)."""
        data, opcode = b"", None
        while True:
            b0, b1 = self._read(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._read(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._read(8))[0]
            mask = self._read(4) if b1 & 0x80 else b""
            payload = self._read(n)
            if mask:
                payload = bytes(c ^ mask[i % 4] for i, c in enumerate(payload))
            opcode = opcode if (b0 & 0x0F) == 0 else b0 & 0x0F
            data += payload
            if b0 & 0x80:
                return opcode, data

    def send_json(self, obj: dict) -> None:
        payload = json.dumps(obj).encode()
        mask = os.urandom(4)
        header = bytes([0x81]) + (bytes([0x80 | len(payload)]) if len(payload) < 126
                                  else bytes([0x80 | 126]) + struct.pack(">H", len(payload)))
        self.sock.sendall(header + mask + bytes(c ^ mask[i % 4] for i, c in enumerate(payload)))

    def close(self) -> None:
        try:
            self.sock.sendall(bytes([0x88, 0x80]) + os.urandom(4))  # a masked close frame, no payload
        finally:
            self.sock.close()


def test_play_to_foxglove_serves_every_message_with_its_schema(recordings) -> None:
    root, _ = recordings
    path = str(root / "a0" / "ep000000.mcap")
    reader, total = scan(path)
    recorded = list(EpisodeReader(path).messages())
    sink = FoxgloveSink(reader.channels.values(), port=0)
    ws = WebSocket(sink.port)
    try:
        advertised: dict[int, dict] = {}
        while len(advertised) < len(reader.channels):
            opcode, data = ws.recv()
            if opcode == 1 and json.loads(data).get("op") == "advertise":
                advertised.update({c["id"]: c for c in json.loads(data)["channels"]})
        by_topic = {c.topic: c for c in reader.channels.values()}
        for c in advertised.values():
            assert c["schemaName"] == by_topic[c["topic"]].schema_name
            binary = c["schemaEncoding"] == "protobuf"  # the protocol sends binary schemas in base64
            schema = base64.b64decode(c["schema"]) if binary else c["schema"].encode()
            assert schema == by_topic[c["topic"]].schema_data
        ws.send_json({"op": "subscribe", "subscriptions": [{"id": cid, "channelId": cid} for cid in advertised]})
        stop = threading.Event()
        assert sink.wait_for_client(10, stop, grace_s=0.5)
        assert play(path, [sink], PlayOptions(speed=0), stop, total) == total
        got = []
        while len(got) < total:
            opcode, data = ws.recv()
            if opcode == 2 and data[0] == 0x01:  # binary messageData: op, subscription id, log time, payload
                sub_id, log_time = struct.unpack_from("<IQ", data, 1)
                got.append((advertised[sub_id]["topic"], log_time, data[13:]))
    finally:
        ws.close()
        sink.close()
    assert got == [(m.topic, m.log_time_ns, m.data) for m in recorded]


# --------------------------------------------------------------------------------------------------- offline
def test_learner_trains_offline_from_recordings_mixed_with_live_experience(recordings, tmp_path: Path,
                                                                           procs) -> None:
    root, expected = recordings
    server, replay_ep = _replay(tmp_path, procs)
    live = parse_transition(read_episode(root.parent / "whole-a2.mcap").of("/transition")[-1].data)
    live.actor_id = "live-0"  # stands in for a live actor's experience
    with open_session(make_config(listen=[], connect=[replay_ep])) as session:
        client = ZenohReplayClient(session, RUN)
        assert client.wait_until_ready(60), server.output()
        assert client.insert_encoded(live.SerializeToString()).status == "accepted"

        def learner(*extra: str) -> Proc:
            p = Proc(tmp_path, "learner", "learner", "--config", str(tmp_path / "run.toml"), "--run-dir",
                     str(tmp_path / "learner"), "--connect", replay_ep, "--offline", str(root), *extra)
            procs.append(p)
            return p

        first = learner("--max-updates", "3")
        assert first.wait(90) == 0, first.output()
        stats = client.stats()
        assert stats["size"] == len(expected) + 1
        assert set(stats["per_actor"]) == {"a0", "a1", "a2", "live-0"}
        assert f"{len(expected)} transitions: {len(expected)} new" in first.output()
        with open(tmp_path / "learner" / "metrics.csv") as f:
            rows = list(csv.DictReader(f))
        assert [int(r["update"]) for r in rows] == [1, 2, 3]
        assert stats["samples"] >= 3 * 2  # batch_size 2 per update
        # A restarted learner feeds the same files again: all duplicates, nothing added; training goes on.
        second = learner("--max-updates", "4", "--resume")
        assert second.wait(90) == 0, second.output()
        assert f"0 new, {len(expected)} already in the replay" in second.output()
        assert client.stats()["size"] == len(expected) + 1
