"""The Foxglove WebSocket servers as the app meets them: real `romannet mcap play` and `romannet mcap live`
processes, and a real WebSocket client (the `websockets` package) offering each subprotocol the Foxglove app
and its forks offer. Loopback only, free ports, every wait bounded.
"""

from __future__ import annotations

import base64
import json
import os
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _episodes import record_episode
from websockets.exceptions import InvalidStatus
from websockets.sync.client import ClientConnection, connect

from romannet.common.episode_file import EpisodeReader
from romannet.common.zenoh_session import free_port

pytestmark = pytest.mark.timeout(120)

CURRENT_APP = ["foxglove.sdk.v1", "foxglove.websocket.v1"]  # what the current Foxglove app offers
PROTOCOLS = [["foxglove.sdk.v1"], CURRENT_APP, ["foxglove.websocket.v1"]]  # the last: Studio, Lichtblick


class Served:
    """A `romannet mcap <tool>` process serving Foxglove on a free port, output in <tmp>/<name>.log."""

    def __init__(self, tmp: Path, name: str, *argv: str):
        self.port = free_port()
        self.log_path = tmp / f"{name}.log"
        self._log = open(self.log_path, "wb")  # noqa: SIM115 - closed in stop()
        self.proc = subprocess.Popen([sys.executable, "-X", "faulthandler", "-m", "romannet.cli", "mcap", *argv, "--foxglove",
                                      str(self.port)], stdout=self._log, stderr=subprocess.STDOUT,
                                     env={**os.environ, "OMP_NUM_THREADS": "1"})

    def output(self) -> str:
        return self.log_path.read_text(errors="replace")

    def connect(self, protocols: list[str]) -> ClientConnection:
        deadline = time.monotonic() + 60
        while True:
            try:
                return connect(f"ws://127.0.0.1:{self.port}", subprotocols=protocols, open_timeout=10,
                               max_size=None)
            except (ConnectionRefusedError, TimeoutError):
                assert self.proc.poll() is None, self.output()
                if time.monotonic() > deadline:
                    raise AssertionError(f"no server on port {self.port}:\n{self.output()}") from None
                time.sleep(0.2)

    def stop(self) -> tuple[int, str]:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        try:
            code = self.proc.wait(60)
        except subprocess.TimeoutExpired:
            self.proc.send_signal(signal.SIGABRT)  # faulthandler writes where each thread is stuck
            self.proc.wait(10)
            raise AssertionError(f"no exit 60 s after SIGINT:\n{self.output()}") from None
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
            self._log.close()
        return code, self.output()


def advertised(ws: ClientConnection, topics: int) -> dict[int, dict]:
    """The channels of the first `topics` advertisements, by id (serverInfo and the rest skipped)."""
    channels: dict[int, dict] = {}
    while len(channels) < topics:
        msg = ws.recv(timeout=30)
        if isinstance(msg, str) and json.loads(msg).get("op") == "advertise":
            channels.update({c["id"]: c for c in json.loads(msg)["channels"]})
    return channels


def subscribe(ws: ClientConnection, channels: dict[int, dict]) -> None:
    ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": cid, "channelId": cid} for cid in channels]}))


def message_data(ws: ClientConnection, channels: dict[int, dict], count: int) -> list[tuple[str, int, bytes]]:
    """(topic, log time, payload) of the next `count` messageData frames (op 1: sub id, log time, payload)."""
    got = []
    while len(got) < count:
        msg = ws.recv(timeout=30)
        if isinstance(msg, bytes) and msg[0] == 0x01:
            sub_id, log_time = struct.unpack_from("<IQ", msg, 1)
            got.append((channels[sub_id]["topic"], log_time, msg[13:]))
    return got


def chunk_ends(data: bytes) -> list[int]:
    """Where each chunk record of an MCAP file ends (records: opcode u8, length u64, body)."""
    ends, at = [], 8
    while at + 9 <= len(data):
        opcode, length = struct.unpack_from("<BQ", data, at)
        at += 9 + length
        if opcode == 0x06:
            ends.append(at)
    return ends


@pytest.fixture(scope="module")
def episode(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return record_episode(tmp_path_factory.mktemp("fox") / "a0" / "ep000000.mcap", 3, run_id="fox").path


@pytest.mark.parametrize("protocols", PROTOCOLS, ids=["sdk.v1", "current-app", "websocket.v1"])
def test_play_serves_each_protocol_every_message_and_keeps_serving(episode: Path, tmp_path: Path,
                                                                   protocols: list[str]) -> None:
    reader = EpisodeReader(episode)
    recorded = list(reader.messages())
    by_topic = {c.topic: c for c in reader.channels.values()}
    topics = {m.topic for m in recorded}
    server = Served(tmp_path, "play", "play", str(episode), "--speed", "0", "--wait-client", "60")
    try:
        with server.connect(protocols) as ws:
            assert ws.subprotocol == protocols[0]  # the newest offered name, answered as offered
            channels = advertised(ws, len(topics))
            for c in channels.values():
                schema = base64.b64decode(c["schema"]) if c["schemaEncoding"] == "protobuf" else c["schema"].encode()
                assert (c["schemaName"], schema) == (by_topic[c["topic"]].schema_name, by_topic[c["topic"]].schema_data)
            subscribe(ws, channels)
            got = message_data(ws, channels, len(recorded))
            assert got == [(m.topic, m.log_time_ns, m.data) for m in recorded]
            time.sleep(1.5)  # well past the last message: the server is still there
            assert server.proc.poll() is None, server.output()
            assert "still serving Foxglove" in server.output()
            ws.ping().wait(10)  # the connection is alive, not just the process
        with server.connect(protocols) as again:  # a second client after playback gets the channels too
            assert len(advertised(again, len(topics))) == len(topics)
    finally:
        code, out = server.stop()
    assert code == 0, out
    assert f"played {len(recorded)} of {len(recorded)} messages" in out and "(stopped)" in out


def test_a_client_offering_no_foxglove_protocol_is_refused(episode: Path, tmp_path: Path) -> None:
    server = Served(tmp_path, "play", "play", str(episode), "--wait-client", "0")
    try:
        with server.connect(["foxglove.sdk.v1"]):  # up
            pass
        with pytest.raises(InvalidStatus):
            connect(f"ws://127.0.0.1:{server.port}", subprotocols=["graphql-ws"], open_timeout=10)
    finally:
        server.stop()


@pytest.mark.parametrize("protocols", [CURRENT_APP, ["foxglove.websocket.v1"]], ids=["current-app", "websocket.v1"])
def test_live_serves_each_actors_steps_as_they_are_written(tmp_path: Path, protocols: list[str]) -> None:
    """An actor writing episodes while `mcap live` follows the run's episodes/: the messages of every step
    written after the client subscribed arrive on /<actor>/<topic>, and a new episode file is followed."""
    episodes = tmp_path / "run" / "episodes"
    first = record_episode(tmp_path / "src" / "ep000000.mcap", 4, actor_id="actor-0", run_id="fox").path
    second = record_episode(tmp_path / "src" / "ep000001.mcap", 3, actor_id="actor-0", episode_id="ep000001",
                            seed=2, run_id="fox").path
    folder = episodes / "actor-0"
    folder.mkdir(parents=True)
    data = first.read_bytes()
    cut = chunk_ends(data)[1] + 100  # as an actor is writing it: its first two steps' chunks, a torn third
    (folder / "ep000000.mcap").write_bytes(data[:cut])
    server = Served(tmp_path, "live", "live", str(episodes))
    try:
        with server.connect(protocols) as ws:
            assert ws.subprotocol == protocols[0]
            channels = advertised(ws, 1)
            assert all(c["topic"].startswith("/actor-0/") for c in channels.values())
            time.sleep(1.0)  # every channel of the first chunk advertised by now
            while True:
                try:
                    msg = ws.recv(timeout=0.5)
                except TimeoutError:
                    break
                if isinstance(msg, str) and json.loads(msg).get("op") == "advertise":
                    channels.update({c["id"]: c for c in json.loads(msg)["channels"]})
            subscribe(ws, channels)
            time.sleep(1.0)  # the subscription is in before the actor writes on
            (folder / "ep000000.mcap").write_bytes(data)  # the actor writes the rest and finishes the file
            (folder / "ep000001.mcap").write_bytes(second.read_bytes())  # and starts the next episode
            later = [m for m in EpisodeReader(folder / "ep000000.mcap").messages() if m.end_offset > cut]
            expected = later + list(EpisodeReader(second).messages())
            wanted = [m for m in expected if f"/actor-0{m.topic}" in {c["topic"] for c in channels.values()}]
            got = message_data(ws, channels, len(wanted))
    finally:
        code, out = server.stop()
    assert code == 0, out
    assert got == [(f"/actor-0{m.topic}", m.log_time_ns, m.data) for m in wanted]
    assert {"/actor-0/step", "/actor-0/transition", "/actor-0/heightmap/depth"} <= {t for t, _, _ in got}


def fleet_logs(tmp_path: Path, log_path: Path) -> str:
    """The launcher's output and the end of the actor's log, for a failure message."""
    actor_log = tmp_path / "runs" / "fox" / "logs" / "actor-0.log"
    tail = actor_log.read_text(errors="replace")[-2000:] if actor_log.exists() else "(no actor log)"
    return f"{log_path.read_text(errors='replace')[-3000:]}\n--- actor-0.log ---\n{tail}"


UP_SETS = ["model.channels=4", "model.residual_blocks=1", "model.num_threads=1", "learner.num_threads=1",
           'learner.precision="fp32"', "learner.batch_size=2", "learner.min_replay_size=4",
           "replay.min_size_to_sample=2", "sim.num_objects=3"]


@pytest.mark.timeout(300)  # a whole fleet (replay, learner, actor) starting beside another test worker
def test_up_foxglove_serves_the_actor_live(tmp_path: Path) -> None:
    """`romannet up --foxglove PORT`: while the actor acts, a client offering the current app's protocols
    gets its heightmaps, Q maps, camera, frames and each /step, the bytes the actor records. The run has no
    action limit: it is still running when Ctrl-C comes, however slowly the client was served."""
    port = free_port()
    argv = ["up", "--runs-dir", str(tmp_path / "runs"), "--name", "fox", "--actors", "1", "--max-actions", "0",
            "--robot", "gripper", "--resolution", "0.007", "--foxglove", str(port)]
    for s in UP_SETS:
        argv += ["--set", s]
    log_path = tmp_path / "up.out"
    with open(log_path, "wb") as out:
        proc = subprocess.Popen([sys.executable, "-m", "romannet.cli", *argv], stdout=out, stderr=subprocess.STDOUT,
                                env={**os.environ, "OMP_NUM_THREADS": "1"})
        try:
            deadline = time.monotonic() + 60
            while True:
                try:
                    ws = connect(f"ws://127.0.0.1:{port}", subprotocols=CURRENT_APP, open_timeout=10, max_size=None)
                    break
                except (ConnectionRefusedError, TimeoutError):
                    assert proc.poll() is None and time.monotonic() < deadline, fleet_logs(tmp_path, log_path)
                    time.sleep(0.3)
            with ws:
                channels: dict[int, dict] = {}
                got: dict[str, list[bytes]] = {}
                deadline = time.monotonic() + 150
                while len(got.get("/actor-0/step", [])) < 2:  # two steps after it subscribed
                    assert time.monotonic() < deadline, f"{sorted(got)}\n{fleet_logs(tmp_path, log_path)}"
                    try:
                        msg = ws.recv(timeout=5)
                    except TimeoutError:  # nothing yet: the deadline above says so with the fleet's logs
                        continue
                    if isinstance(msg, str) and json.loads(msg).get("op") == "advertise":
                        new = {c["id"]: c for c in json.loads(msg)["channels"]}
                        channels.update(new)
                        subscribe(ws, new)
                    elif isinstance(msg, bytes) and msg[0] == 0x01:
                        sub_id = struct.unpack_from("<I", msg, 1)[0]
                        got.setdefault(channels[sub_id]["topic"], []).append(msg[13:])
        finally:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)
            code = proc.wait(60)
    out = log_path.read_text()
    assert code == 0, out[-3000:]
    assert "live view of run fox on ws://127.0.0.1" in out and "run fox stopped by signal" in out, out[-3000:]
    assert {"/actor-0/heightmap/color", "/actor-0/heightmap/depth", "/actor-0/camera/color", "/actor-0/tf",
            "/actor-0/camera/calibration", "/actor-0/transition"} <= set(got), sorted(got)
    assert any(t.startswith("/actor-0/q/") for t in got), sorted(got)
    recorded = {m.data for path in (tmp_path / "runs" / "fox" / "episodes" / "actor-0").glob("*.mcap")
                for m in EpisodeReader(path).messages(["/step"])}
    assert set(got["/actor-0/step"]) <= recorded  # what the app saw is what the actor recorded
    steps = [json.loads(d) for d in got["/actor-0/step"]]
    assert all({"primitive", "row", "col", "angle_rad", "q_value", "reward"} <= s.keys() for s in steps)
