"""Where `romannet bench fleet` runs its processes: one loopback host, or one network namespace per process.

    with open_hosts("auto", ["router", "replay", "learner", "actor0", ...], work) as hosts:
        hosts.spawn("router", argv, log_path); hosts.wait_router(); hosts.learner_bytes_out(pid)

"netns" (root, bench/netns.py): every process is a host of its own on one virtual switch, with its own
address and link, as on a fleet network; the router listens on its host's address, and the learner's egress
is every byte its namespace's TCP sockets sent. "loopback": every process on 127.0.0.1, the router on a free
port, and the learner's egress is that of its own sockets (`ss`, by pid). "auto" picks netns where it can
be built. Either way shared memory is off in every Zenoh session, so the sockets carry every byte.
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import time
from collections.abc import Iterator, Sequence
from pathlib import Path

from romannet.common.zenoh_session import free_port

from .netns import NetnsLab, netns_unavailable_reason
from .weights_latency import bytes_out

_NETNS_ROUTER_PORT = 7447


def client_config(folder: Path, endpoint: str) -> Path:
    """A Zenoh client config to the router (multicast scouting and shared memory off), written once."""
    path = folder / "client.json5"
    path.write_text(f'{{mode: "client", connect: {{endpoints: ["{endpoint}"]}}, '
                    'scouting: {multicast: {enabled: false}}, transport: {shared_memory: {enabled: false}}}')
    return path


class LoopbackHosts:
    """Every process on this machine's loopback."""

    topology = "loopback"

    def __init__(self) -> None:
        self.port = free_port()
        self.router_listen = self.router_endpoint = f"tcp/127.0.0.1:{self.port}"
        self._logs: list = []

    def spawn(self, host: str, argv: Sequence[str], log_path: Path, env: dict[str, str] | None = None
              ) -> subprocess.Popen:
        out = log_path.open("ab")
        self._logs.append(out)
        return subprocess.Popen(list(argv), stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
                                env={**os.environ, **(env or {})})

    def router_listening(self) -> bool:
        with socket.socket() as s:
            return s.connect_ex(("127.0.0.1", self.port)) == 0

    def learner_bytes_out(self, pid: int) -> int | None:
        return bytes_out(pid)

    def close(self) -> None:
        for f in self._logs:
            f.close()


class NetnsHosts:
    """One network namespace per process (bench/netns.py); close() ends what is left and removes them."""

    topology = "netns"

    def __init__(self, lab: NetnsLab):
        self.lab = lab
        self.router_listen = f"tcp/{lab.address('router')}:{_NETNS_ROUTER_PORT}"
        self.router_endpoint = self.router_listen

    def spawn(self, host: str, argv: Sequence[str], log_path: Path, env: dict[str, str] | None = None
              ) -> subprocess.Popen:
        return self.lab.spawn(host, argv, log_path, env)

    def router_listening(self) -> bool:
        try:
            listening = self.lab.run("router", ["ss", "-ltnH"], timeout_s=10).stdout
        except subprocess.TimeoutExpired:
            return False
        return f":{_NETNS_ROUTER_PORT}" in listening

    def learner_bytes_out(self, pid: int) -> int | None:
        return bytes_out(None, self.lab.ns("learner"))  # the learner is its namespace's only process

    def close(self) -> None:
        self.lab.close()


def resolve_topology(topology: str) -> str:
    """"netns" or "loopback" for "auto" (netns where this process can build it); ValueError for others."""
    if topology not in ("auto", "netns", "loopback"):
        raise ValueError(f"topology must be auto, netns or loopback, not {topology!r}")
    reason = netns_unavailable_reason() if topology != "loopback" else "asked for loopback"
    if topology == "netns" and reason is not None:
        raise ValueError(f"topology netns is not available here: {reason}")
    return "netns" if reason is None else "loopback"


@contextlib.contextmanager
def open_hosts(topology: str, hosts: list[str]) -> Iterator[LoopbackHosts | NetnsHosts]:
    """The hosts of one fleet (topology already resolved); every process is ended on exit."""
    if topology == "netns":
        with NetnsLab(hosts) as lab:
            yield NetnsHosts(lab)
        return
    h = LoopbackHosts()
    try:
        yield h
    finally:
        h.close()


def wait_router(hosts: LoopbackHosts | NetnsHosts, proc: subprocess.Popen, timeout_s: float = 60.0) -> None:
    """Return once the router accepts TCP; RuntimeError if it exits or does not listen in time."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the router exited with {proc.returncode}")
        if hosts.router_listening():
            return
        time.sleep(0.2)
    raise RuntimeError(f"the router did not listen within {timeout_s:.0f} s")
