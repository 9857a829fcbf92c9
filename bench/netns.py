"""Hosts made of Linux network namespaces on one virtual switch, for multi-machine fault tests (needs root).

    with NetnsLab(["router", "server", "actor0"]) as lab:
        proc = lab.spawn("router", ["romannet", "router", ...], log_path)
        lab.cut("actor0"); ...; lab.restore("actor0")

Each host is a namespace with one interface, eth0 = 10.77.0.<n>/24 (n = 1, 2, ... in the order given),
plus its own loopback; a switch namespace holds a bridge with one veth port per host. Every name carries
this process's pid (`rnf<pid>-<host>`), so concurrent labs never meet, and a lab whose owner died is
removed by the next one (`remove_stale`). `cut(host)` takes the host's switch port down: the host's own
interface stays up, so its packets vanish as on an unplugged cable upstream (TCP notices nothing; Zenoh's
lease does). Processes start through `ip netns exec`, behind the supervisor's exec shim, so they get
SIGTERM if this process dies; close() kills whatever is left, then deletes the namespaces (which removes
their interfaces).
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import subprocess
import time
from collections.abc import Sequence
from pathlib import Path
from typing import IO

from romannet.supervisor import shim_command

log = logging.getLogger(__name__)

PREFIX = "rnf"
SUBNET = "10.77.0"
_IP_TIMEOUT_S = 20.0


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=_IP_TIMEOUT_S, check=check)


def netns_unavailable_reason() -> str | None:
    """None if this process can build a lab here; otherwise why not (for a test's skip message)."""
    if os.geteuid() != 0:
        return "network namespaces need root (CAP_SYS_ADMIN and CAP_NET_ADMIN); run as root or in CI"
    if shutil.which("ip") is None:
        return "the `ip` command (iproute2) is not installed"
    probe = f"{PREFIX}{os.getpid()}-probe"
    try:
        _ip("netns", "add", probe)
        try:
            _ip("-n", probe, "link", "add", "br0", "type", "bridge")
            _ip("-n", probe, "link", "add", "p0", "type", "veth", "peer", "name", "p1")
        finally:
            _ip("netns", "del", probe, check=False)
    except (subprocess.CalledProcessError, subprocess.TimeoutExpired, OSError) as exc:
        detail = getattr(exc, "stderr", "") or str(exc)
        return f"cannot create network namespaces, bridges or veth pairs here: {detail.strip()}"
    return None


def _pids_in(ns: str) -> list[int]:
    out = _ip("netns", "pids", ns, check=False).stdout
    return [int(p) for p in out.split() if p.isdigit()]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale() -> list[str]:
    """Delete labs left by processes that no longer exist (a test run killed before its cleanup)."""
    removed = []
    for line in _ip("netns", "list", check=False).stdout.splitlines():
        name = line.split()[0] if line.split() else ""
        if not name.startswith(PREFIX) or "-" not in name:
            continue
        owner = name[len(PREFIX):].split("-", 1)[0]
        if not owner.isdigit() or _alive(int(owner)):
            continue
        for pid in _pids_in(name):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        _ip("netns", "del", name, check=False)
        removed.append(name)
    if removed:
        log.info("removed stale network namespaces: %s", ", ".join(removed))
    return removed


class NetnsLab:
    """Hosts on a switch; see the module docstring. Use as a context manager."""

    def __init__(self, hosts: Sequence[str], subnet: str = SUBNET):
        if len(set(hosts)) != len(hosts) or not hosts:
            raise ValueError(f"host names must be unique and at least one: {list(hosts)}")
        if len(hosts) > 250:
            raise ValueError("at most 250 hosts on one /24")
        self.hosts = list(hosts)
        self.subnet = subnet
        self.tag = f"{PREFIX}{os.getpid()}"
        self.switch = f"{self.tag}-switch"
        self._procs: list[subprocess.Popen] = []
        self._logs: list[IO[bytes]] = []
        self._created: list[str] = []

    # ---------------------------------------------------------------------------------------- set-up
    def ns(self, host: str) -> str:
        return f"{self.tag}-{host}"

    def address(self, host: str) -> str:
        return f"{self.subnet}.{self.hosts.index(host) + 1}"

    def _port(self, host: str) -> str:
        return f"p{self.hosts.index(host)}"

    def __enter__(self) -> NetnsLab:
        remove_stale()
        try:
            self._add_ns(self.switch)
            _ip("-n", self.switch, "link", "add", "br0", "type", "bridge")
            _ip("-n", self.switch, "link", "set", "br0", "up")
            for host in self.hosts:
                ns = self.ns(host)
                self._add_ns(ns)
                _ip("-n", self.switch, "link", "add", self._port(host), "type", "veth", "peer", "name", "eth0",
                    "netns", ns)
                _ip("-n", self.switch, "link", "set", self._port(host), "master", "br0")
                _ip("-n", self.switch, "link", "set", self._port(host), "up")
                _ip("-n", ns, "addr", "add", f"{self.address(host)}/24", "dev", "eth0")
                _ip("-n", ns, "link", "set", "eth0", "up")
                _ip("-n", ns, "link", "set", "lo", "up")
        except BaseException:
            self.close()
            raise
        log.info("network lab %s: %s", self.tag, ", ".join(f"{h}={self.address(h)}" for h in self.hosts))
        return self

    def _add_ns(self, name: str) -> None:
        _ip("netns", "add", name)
        self._created.append(name)

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------------------------- processes
    def spawn(self, host: str, argv: Sequence[str], log_path: Path, env: dict[str, str] | None = None
              ) -> subprocess.Popen:
        """Start argv on host (stdout and stderr appended to log_path); killed by close() at the latest."""
        log_path.parent.mkdir(parents=True, exist_ok=True)
        out = log_path.open("ab")
        self._logs.append(out)
        ip = shutil.which("ip") or "ip"
        proc = subprocess.Popen(shim_command([ip, "netns", "exec", self.ns(host), *argv]), stdout=out,
                                stderr=subprocess.STDOUT, env={**os.environ, **(env or {})},
                                start_new_session=True)
        self._procs.append(proc)
        return proc

    def run(self, host: str, argv: Sequence[str], timeout_s: float) -> subprocess.CompletedProcess:
        """Run argv on host to the end; its output is returned (raises TimeoutExpired after timeout_s)."""
        return subprocess.run(["ip", "netns", "exec", self.ns(host), *argv], capture_output=True, text=True,
                              timeout=timeout_s)

    # ---------------------------------------------------------------------------------------- faults
    def cut(self, host: str) -> None:
        """Unplug host from the switch (its side stays up; packets vanish)."""
        _ip("-n", self.switch, "link", "set", self._port(host), "down")

    def restore(self, host: str) -> None:
        _ip("-n", self.switch, "link", "set", self._port(host), "up")

    # ------------------------------------------------------------------------------------- clean-up
    def close(self) -> None:
        """SIGTERM what is still running (2 s grace), SIGKILL the rest, delete the namespaces."""
        live = [p for p in self._procs if p.poll() is None]
        for p in live:
            _signal_group(p, signal.SIGTERM)
        deadline = time.monotonic() + 2.0
        for p in live:
            try:
                p.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                _signal_group(p, signal.SIGKILL)
                p.wait(10)
        for name in reversed(self._created):
            for pid in _pids_in(name):  # anything that got in by other means (it would keep the netns)
                try:
                    os.kill(pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            _ip("netns", "del", name, check=False)
        self._created.clear()
        for f in self._logs:
            f.close()
        self._logs.clear()


def _signal_group(proc: subprocess.Popen, sig: int) -> None:
    try:
        os.killpg(proc.pid, sig)
    except ProcessLookupError:
        pass
