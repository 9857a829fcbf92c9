"""Supervise child processes: start, restart crashed ones with backoff, stop them in order.

    sup = Supervisor([ChildSpec("replay", argv, stop_rank=2), ...], RestartPolicy())
    sup.start_all()
    while not done:
        sup.poll()          # reap exits, log crashes, restart what is due (call from the main thread)
        time.sleep(0.5)
    sup.stop_all()          # lowest stop_rank first: SIGTERM, wait stop_timeout_s, then SIGKILL

Process groups and signals (why it is done this way):
- Each child leads its own process group. Ctrl-C in a terminal sends SIGINT to the whole foreground group;
  if the children shared the launcher's group they would all stop at once, in no order, and the replay
  server could be gone before the actors flushed their spools. In their own groups only the launcher gets
  the Ctrl-C, and it stops the children itself: actors first, then the learner, then the replay server.
- A launcher that is killed outright (SIGKILL, OOM) cannot stop anyone, so each child asks the kernel for
  PR_SET_PDEATHSIG = SIGTERM (a tiny exec shim, `shim_command`): when the launcher dies, every child gets
  SIGTERM and shuts down cleanly on its own (no orphans). The kernel sends it when the *thread* that
  forked the child exits, so children must be started from a thread that lives as long as the launcher:
  the main thread (`poll` restarts run there too). A launcher that died before the prctl is caught by
  comparing the parent pid. Each child is in its own session (setsid), so closing the terminal reaches
  only the launcher, which stops them (SIGHUP is handled like SIGTERM).
- Signals go to the child's whole group (os.killpg), so anything a child started goes with it.
"""

from __future__ import annotations

import logging
import os
import signal
import subprocess
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

log = logging.getLogger(__name__)

# Runs in the child before it becomes the real command: ask for SIGTERM when the launcher dies (Linux;
# the setting survives execv), exit if the launcher already died (then getppid() is no longer it).
# An exec shim instead of Popen's preexec_fn: Python code between fork and exec is unsafe in a launcher
# whose Zenoh session has threads of its own.
_EXEC_SHIM = (
    "import os, signal, sys\n"
    "if sys.platform.startswith('linux'):\n"
    "    import ctypes\n"
    "    ctypes.CDLL(None, use_errno=True).prctl(1, int(signal.SIGTERM), 0, 0, 0)  # 1: PR_SET_PDEATHSIG\n"
    "if os.getppid() != int(sys.argv[1]):\n"
    "    sys.exit(143)\n"
    "os.execv(sys.argv[2], sys.argv[2:])\n"
)


def shim_command(argv: Sequence[str], parent_pid: int | None = None) -> list[str]:
    """argv wrapped so that the process gets SIGTERM when parent_pid (default: this process) dies."""
    pid = os.getpid() if parent_pid is None else parent_pid
    return [sys.executable, "-c", _EXEC_SHIM, str(pid), *argv]


@dataclass(frozen=True)
class RestartPolicy:
    """Exponential backoff between restarts, and a bound on how many restarts a window may hold.

    The n-th restart within window_s waits initial_backoff_s * factor**(n-1), at most max_backoff_s; a
    child that needs more than max_restarts restarts within window_s is given up on (a crash loop).
    """

    initial_backoff_s: float = 1.0
    factor: float = 2.0
    max_backoff_s: float = 30.0
    max_restarts: int = 5
    window_s: float = 300.0

    def backoff_s(self, recent_restarts: int) -> float:
        """Seconds to wait before the next restart, given how many happened within the window."""
        return min(self.max_backoff_s, self.initial_backoff_s * self.factor ** max(0, recent_restarts))


@dataclass(frozen=True)
class ChildSpec:
    """One supervised process.

    argv: the command, or a function returning it (re-evaluated at every start, e.g. to add --resume
    once a checkpoint exists). stop_rank: lower ranks are stopped first, children of one rank together.
    restart: "always" (a service: any exit it was not asked for is a crash) or "on-failure" (a job: exit
    code 0 means done). stop_timeout_s: how long a SIGTERM may take before SIGKILL.
    """

    name: str
    argv: Sequence[str] | Callable[[], Sequence[str]]
    stop_rank: int = 0
    restart: Literal["always", "on-failure"] = "always"
    stop_timeout_s: float = 60.0
    log_path: Path | None = None
    env: dict[str, str] | None = None

    def command(self) -> list[str]:
        return list(self.argv() if callable(self.argv) else self.argv)


@dataclass
class Child:
    """Run-time state of one supervised process."""

    spec: ChildSpec
    proc: subprocess.Popen | None = None
    state: Literal["new", "running", "backoff", "done", "failed", "stopped"] = "new"
    starts: int = 0
    restarts: deque[float] = field(default_factory=deque)  # monotonic times of recent restarts
    restart_at: float = 0.0
    last_exit: int | None = None
    asked_to_stop: bool = False  # SIGTERM/SIGKILL sent by stop_rank or kill_all since the last start
    unclean: str | None = None  # how its last run ended, if not cleanly (None: clean, running or never ran)

    @property
    def pid(self) -> int | None:
        return self.proc.pid if self.proc is not None else None

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None


def unclean_end(code: int, asked: bool, restart: str) -> str | None:
    """Why an exit was not clean, or None when it was: any non-zero code (a crash, or SIGKILL after the
    stop timeout), and a service (restart "always") that exited 0 without being asked to stop."""
    if code != 0:
        return describe_exit(code) + ("" if asked else " before it was asked to stop")
    if not asked and restart == "always":
        return "exit code 0 before it was asked to stop"
    return None


def describe_exit(code: int) -> str:
    """'exit code 3' or 'killed by SIGKILL' for a Popen return code."""
    if code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit code {code}"


class Supervisor:
    """Starts, watches and stops a set of ChildSpecs. Not thread-safe: call it from the main thread."""

    def __init__(self, specs: Sequence[ChildSpec], policy: RestartPolicy | None = None,
                 clock: Callable[[], float] = time.monotonic,
                 on_exit: Callable[[str, int], None] | None = None,
                 on_start: Callable[[str, int], None] | None = None):
        names = [s.name for s in specs]
        if len(set(names)) != len(names):
            raise ValueError(f"child names must be unique: {names}")
        self.children = {s.name: Child(s) for s in specs}
        self.policy = policy or RestartPolicy()
        self._clock = clock
        self._on_exit = on_exit  # told of every exit it was not asked for, before any restart
        self._on_start = on_start  # told of every start, with the pid
        self.stopping = False
        self.gave_up: list[str] = []  # children that crashed too often
        self.crashes = 0  # restarts done, for the summary
        self.ends: list[tuple[str, str]] = []  # (child, how) of every unclean end, restarted or not, in order

    # ------------------------------------------------------------------------------------ starting
    def start(self, name: str) -> None:
        """Start one child (first start or a restart)."""
        child = self.children[name]
        spec = child.spec
        argv = spec.command()
        env = {**os.environ, "PYTHONUNBUFFERED": "1", **(spec.env or {})}
        out = None
        if spec.log_path is not None:
            spec.log_path.parent.mkdir(parents=True, exist_ok=True)
            out = spec.log_path.open("ab")
        try:
            # start_new_session: the child leads its own process group (see the module docstring).
            child.proc = subprocess.Popen(shim_command(argv), stdin=subprocess.DEVNULL, stdout=out,
                                          stderr=subprocess.STDOUT if out is not None else None, env=env,
                                          start_new_session=True, close_fds=True)
        finally:
            if out is not None:
                out.close()  # the child holds its own descriptor
        child.state = "running"
        child.starts += 1
        child.asked_to_stop, child.unclean = False, None
        log.info("started %s (pid %d)%s", name, child.proc.pid,
                 f", log {spec.log_path}" if spec.log_path else "")
        log.debug("%s: %s", name, " ".join(argv))
        if self._on_start is not None:
            self._on_start(name, child.proc.pid)

    def start_all(self, names: Sequence[str] | None = None) -> None:
        for name in names if names is not None else list(self.children):
            self.start(name)

    # ------------------------------------------------------------------------------------ watching
    def poll(self) -> None:
        """Reap exited children, decide restarts, and start those whose backoff is over."""
        self.reap()
        now = self._clock()
        for name, child in self.children.items():
            if child.state == "backoff" and not self.stopping and now >= child.restart_at:
                log.warning("restarting %s (restart %d within %.0f s)", name, len(child.restarts),
                            self.policy.window_s)
                self.start(name)

    def _ended(self, child: Child, code: int, asked: bool) -> None:
        """Record how a run ended; an unclean end stays in the history even after a clean restart."""
        child.last_exit = code
        child.unclean = unclean_end(code, asked, child.spec.restart)
        if child.unclean is not None:
            self.ends.append((child.spec.name, child.unclean))

    def _exited(self, name: str, child: Child, code: int, now: float) -> None:
        self._ended(child, code, child.asked_to_stop)
        if self.stopping:
            # Not restarted any more, but still reported: a child that dies while another rank is being
            # stopped is found here (or by stop_rank's reaping), not lost because no one polled it.
            child.state = "stopped"
            if child.unclean is not None and not child.asked_to_stop:
                log.warning("%s ended while the fleet was stopping (%s; see %s)", name, child.unclean,
                            child.spec.log_path or "its output")
            return
        if self._on_exit is not None:
            self._on_exit(name, code)
        if code == 0 and child.spec.restart == "on-failure":
            child.state = "done"
            log.info("%s finished (exit code 0)", name)
            return
        while child.restarts and now - child.restarts[0] > self.policy.window_s:
            child.restarts.popleft()
        if len(child.restarts) >= self.policy.max_restarts:
            child.state = "failed"
            self.gave_up.append(name)
            log.error("%s crashed (%s) and was restarted %d times within %.0f s: giving up (see %s)", name,
                      describe_exit(code), len(child.restarts), self.policy.window_s,
                      child.spec.log_path or "its output")
            return
        delay_s = self.policy.backoff_s(len(child.restarts))
        child.restarts.append(now)
        child.restart_at = now + delay_s
        child.state = "backoff"
        self.crashes += 1
        what = "exited unexpectedly" if code == 0 else "crashed"
        log.warning("%s %s (%s); restarting in %.1f s (see %s)", name, what, describe_exit(code), delay_s,
                    child.spec.log_path or "its output")

    def states(self) -> dict[str, str]:
        return {name: child.state for name, child in self.children.items()}

    def unclean(self) -> dict[str, str]:
        """Each child whose last run ended unclean, with how (see unclean_end); a crash that was followed
        by a clean restart is not here (self.ends lists it, self.crashes counts it)."""
        return {name: c.unclean for name, c in self.children.items() if c.unclean is not None}

    def reap(self) -> None:
        """Record the exit of every child that died since the last look, without restarting any."""
        now = self._clock()
        for name, child in self.children.items():
            if child.state == "running" and child.proc is not None:
                code = child.proc.poll()
                if code is not None:
                    self._exited(name, child, code, now)

    # ------------------------------------------------------------------------------------ stopping
    def signal(self, name: str, sig: int) -> bool:
        """Send sig to a running child's process group; False if it is not running."""
        child = self.children[name]
        if not child.alive():
            return False
        assert child.proc is not None
        if sig in (signal.SIGTERM, signal.SIGKILL, signal.SIGINT):
            child.asked_to_stop = True
        try:
            os.killpg(child.proc.pid, sig)
        except ProcessLookupError:  # exited between poll and kill
            return False
        return True

    def stop_all(self, hurry: Callable[[], bool] = lambda: False) -> dict[str, int | None]:
        """Stop every child, lowest stop_rank first; returns the exit code per child (None: never ran).

        Each rank gets SIGTERM, then up to its stop_timeout_s to exit, then SIGKILL. hurry() is asked
        while waiting; once it says True (e.g. a second Ctrl-C) the rest are killed at once.
        """
        for rank in sorted({c.spec.stop_rank for c in self.children.values()}):
            self.stop_rank(rank, hurry)
        return {n: c.last_exit for n, c in self.children.items()}

    def stop_rank(self, rank: int, hurry: Callable[[], bool] = lambda: False) -> None:
        """Stop the children of one stop_rank (SIGTERM, wait, SIGKILL); none of them is restarted after."""
        self.stopping = True  # from now on no child is restarted
        self.reap()  # deaths since the last poll, e.g. while the previous rank was being stopped
        names = [n for n, c in self.children.items() if c.spec.stop_rank == rank]
        self._stop_group(names, hurry)
        self.reap()
        for name in names:
            if self.children[name].state in ("running", "backoff"):
                self.children[name].state = "stopped"

    def _stop_group(self, names: list[str], hurry: Callable[[], bool]) -> None:
        running = [n for n in names if self.children[n].alive()]
        if not running:
            return
        log.info("stopping %s", ", ".join(running))
        for name in running:
            self.signal(name, signal.SIGTERM)
        sent_at = self._clock()
        pending = set(running)
        while pending:
            for name in list(pending):
                child = self.children[name]
                assert child.proc is not None
                code = child.proc.poll()
                if code is not None:
                    pending.discard(name)
                    level = logging.INFO if code == 0 else logging.WARNING
                    log.log(level, "%s stopped (%s)", name, describe_exit(code))
                elif self._clock() - sent_at >= child.spec.stop_timeout_s or hurry():
                    log.warning("%s did not stop in time: SIGKILL", name)
                    self.signal(name, signal.SIGKILL)
                    code = child.proc.wait()
                    pending.discard(name)
                if code is not None:
                    self._ended(child, code, True)
                    child.state = "stopped"
            if pending:
                time.sleep(0.05)

    def kill_all(self) -> None:
        """SIGKILL whatever still runs (last resort, e.g. the launcher itself is failing)."""
        self.stopping = True
        self.reap()
        for name, child in self.children.items():
            if self.signal(name, signal.SIGKILL) and child.proc is not None:
                self._ended(child, child.proc.wait(), True)
                child.state = "stopped"
