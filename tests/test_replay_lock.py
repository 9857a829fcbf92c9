"""One replay server per directory (issue 31, point 6): <dir>/LOCK with the holder's pid.

Real processes: two `romannet replay` servers on loopback Zenoh (free ports, multicast scouting off) on
one directory, a lock holder killed with SIGKILL, and the stores and checks that open a replay directory.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from _replay_helpers import cfg, tr
from _wire_samples import transition

from romannet.common.dirlock import LOCK_FILE, DirectoryInUseError, DirectoryLock, check_not_locked
from romannet.common.replay_client import ZenohReplayClient
from romannet.common.zenoh_session import free_port, make_config, open_session
from romannet.replay.store import ReplayStore

pytestmark = pytest.mark.timeout(180)

RUN = "lock-run"
SIDE_PX = 32
CONFIG_TOML = f"""run_id = "{RUN}"
[workspace]
resolution_m = 0.014
[replay]
min_size_to_sample = 1
samples_per_insert = 0.0  # no learner samples here: unpaced
snapshot_every_s = 0.0
snapshot_every_inserts = 0
"""
HOLD = ("import sys, time\nfrom romannet.common.dirlock import DirectoryLock\n"
        "lock = DirectoryLock(sys.argv[1], 'replay directory')\nprint('locked', flush=True)\ntime.sleep(300)\n")


def _item(step: int):
    return transition(SIDE_PX, SIDE_PX, seed=step % 5, episode_id="ep-1", step=step, initial_priority=1.0,
                      done=False, done_reason="")


class Server:
    """A `romannet replay` process serving `directory` on 127.0.0.1:<free port>; its output in a log file."""

    def __init__(self, tmp: Path, directory: Path, name: str):
        self.port, self.dir, self.log_path = free_port(), directory, tmp / f"{name}.log"
        self.config = tmp / "replay.toml"
        self.config.write_text(CONFIG_TOML)
        cmd = [sys.executable, "-m", "romannet.cli", "replay", "--config", str(self.config), "--dir", str(directory),
               "--listen", f"tcp/127.0.0.1:{self.port}"]
        with open(self.log_path, "wb") as log:
            self.proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)

    def output(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self, sig: int = signal.SIGTERM) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
        return self.proc.wait(30)


@pytest.fixture
def servers() -> Iterator[list[Server]]:
    started: list[Server] = []
    yield started
    for srv in started:  # no server outlives its test
        if srv.proc.poll() is None:
            srv.stop(signal.SIGKILL)


def _client(session, srv: Server) -> ZenohReplayClient:
    c = ZenohReplayClient(session, RUN, expected_shape=(SIDE_PX, SIDE_PX))
    assert c.wait_until_ready(60), "server did not come up:\n" + srv.output()
    return c


def _session(*servers: Server):
    return open_session(make_config(listen=[], connect=[f"tcp/127.0.0.1:{s.port}" for s in servers]))


def test_second_server_on_a_directory_in_use_exits_with_the_holders_pid(tmp_path: Path, servers) -> None:
    directory = tmp_path / "replay"
    first = Server(tmp_path, directory, "first")
    servers.append(first)
    with _session(first) as session:
        client = _client(session, first)
        assert client.insert(_item(0)).status == "accepted"
        assert (directory / LOCK_FILE).read_text() == f"{first.proc.pid}\n"

        second = Server(tmp_path, directory, "second")
        servers.append(second)
        started = time.monotonic()
        code = second.proc.wait(60)
        out = second.output()
        assert code == 2, out
        assert time.monotonic() - started < 60
        lines = [line for line in out.splitlines() if line.strip()]
        assert lines[-1] == f"romannet replay: error: replay directory {directory} is in use by pid {first.proc.pid}"
        assert "Traceback" not in out and "ready" not in out  # it never served, never announced itself
        assert not [line for line in lines if "zenoh" in line.lower()]

        # The first server never noticed: it acknowledges, deduplicates and serves as before.
        assert client.insert(_item(1)).status == "accepted"
        assert client.insert(_item(0)).status == "duplicate"
        assert client.stats()["size"] == 2
        assert first.proc.poll() is None
        assert first.stop() == 0, first.output()
    assert (directory / LOCK_FILE).read_text() == ""  # released on a clean stop


def test_a_server_killed_with_sigkill_leaves_no_lock_behind(tmp_path: Path, servers) -> None:
    directory = tmp_path / "replay"
    first = Server(tmp_path, directory, "first")
    servers.append(first)
    with _session(first) as session:
        assert _client(session, first).insert(_item(0)).status == "accepted"
    first.stop(signal.SIGKILL)
    assert (directory / LOCK_FILE).read_text() == f"{first.proc.pid}\n"  # a dead pid stays in the file...
    again = Server(tmp_path, directory, "again")  # ...and blocks nothing: the kernel dropped the flock
    servers.append(again)
    with _session(again) as session:
        client = _client(session, again)
        assert client.insert(_item(0)).status == "duplicate"  # the acknowledged item survived
        assert (directory / LOCK_FILE).read_text() == f"{again.proc.pid}\n"
    assert again.stop() == 0, again.output()


def test_lock_of_a_process_killed_with_sigkill_is_free(tmp_path: Path) -> None:
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "locked"
        with pytest.raises(DirectoryInUseError) as err:
            DirectoryLock(tmp_path, "replay directory")
        assert str(err.value) == f"replay directory {tmp_path} is in use by pid {holder.pid}"
        with pytest.raises(DirectoryInUseError):  # a store refuses before it reads or repairs anything
            ReplayStore(cfg(), tmp_path)
        assert not list(tmp_path.glob("segment-*"))
        with pytest.raises(DirectoryInUseError):  # what `romannet up --resume` checks before any child starts
            check_not_locked(tmp_path, "replay directory")
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait(30)
        if holder.stdout is not None:
            holder.stdout.close()
    with ReplayStore(cfg(), tmp_path) as store:
        assert store.insert(tr(0)).status == "accepted"


def test_two_stores_in_one_process_and_the_lock_after_close(tmp_path: Path) -> None:
    store = ReplayStore(cfg(), tmp_path)
    try:
        with pytest.raises(DirectoryInUseError, match=r"is in use by pid \d+"):
            ReplayStore(cfg(), tmp_path)
        check_not_locked(tmp_path / "missing")  # nothing to check, nothing created
        assert not (tmp_path / "missing").exists()
    finally:
        store.close()
    check_not_locked(tmp_path)
    with ReplayStore(cfg(), tmp_path) as again:
        assert again.insert(tr(1)).status == "accepted"


def test_resume_refuses_a_run_whose_replay_directory_is_held(tmp_path: Path) -> None:
    from romannet.rundir import _check_replay_free

    replay = tmp_path / "run" / "replay"
    replay.mkdir(parents=True)
    with DirectoryLock(replay, "replay directory"):
        with pytest.raises(DirectoryInUseError, match=f"replay directory {replay} is in use by pid"):
            _check_replay_free(tmp_path / "run")
    _check_replay_free(tmp_path / "run")
