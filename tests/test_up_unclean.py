"""The launcher reports every child that ended unclean, whenever it died: real child processes, a real
SIGKILL sent while an earlier stop group is being stopped, and the supervisor's report of it."""

from __future__ import annotations

import signal
import sys
import textwrap
import time
from pathlib import Path

import pytest

from romannet.supervisor import ChildSpec, RestartPolicy, Supervisor, unclean_end

PY = sys.executable
# Generous on purpose: on a loaded 2-core CI box a process can wait seconds for the CPU; the actor's own wait
# ends well before the supervisor's SIGKILL, so a slow victim shows in the trace rather than as a killed actor.
ACTOR_WAIT_S = 30
ACTOR_STOP_TIMEOUT_S = 45


def _service(name: str, tmp: Path) -> list[str]:
    """Writes its pid, then sleeps; SIGTERM ends it with exit 0."""
    code = textwrap.dedent(f"""
        import os, signal, sys, time
        signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
        open({str(tmp / (name + '.pid'))!r}, "w").write(str(os.getpid()))
        time.sleep(120)
    """)
    return [PY, "-c", code]


def _actor_that_kills(victim: str, sig: int, tmp: Path) -> list[str]:
    """An actor whose SIGTERM handler kills `victim` with `sig` and waits until it is dead (a zombie of
    the supervisor, or already reaped) before exiting 0: the victim dies while the actors are being stopped.
    It writes what it saw to actor-0.trace, which a failing test prints."""
    code = textwrap.dedent(f"""
        import os, signal, sys, time
        trace = open({str(tmp / 'actor-0.trace')!r}, "w", buffering=1)
        def on_term(*_):
            pid = int(open({str(tmp / (victim + '.pid'))!r}).read())
            os.kill(pid, {int(sig)})
            trace.write(f"sent signal {int(sig)} to pid {{pid}}\\n")
            start = time.monotonic()
            state = "?"
            while time.monotonic() - start < {ACTOR_WAIT_S}:
                try:
                    state = open(f"/proc/{{pid}}/stat").read().rsplit(")", 1)[1].split()[0]
                except FileNotFoundError:  # reaped by the supervisor already
                    state = "reaped"
                if state in ("Z", "X", "reaped"):
                    break
                time.sleep(0.01)
            trace.write(f"victim state {{state}} after {{time.monotonic() - start:.2f}} s\\n")
            sys.exit(0)
        signal.signal(signal.SIGTERM, on_term)
        open({str(tmp / 'actor-0.pid')!r}, "w").write(str(os.getpid()))
        time.sleep(120)
    """)
    return [PY, "-c", code]


def _fleet(tmp: Path, victim: str, sig: int) -> Supervisor:
    return Supervisor([ChildSpec("replay", _service("replay", tmp), stop_rank=2, stop_timeout_s=10),
                       ChildSpec("learner", _service("learner", tmp), stop_rank=1, stop_timeout_s=10),
                       ChildSpec("actor-0", _actor_that_kills(victim, sig, tmp), stop_rank=0, restart="on-failure",
                                 stop_timeout_s=ACTOR_STOP_TIMEOUT_S)])


def _trace(tmp: Path) -> str:
    path = tmp / "actor-0.trace"
    return "actor-0 saw: " + (path.read_text().strip().replace("\n", "; ") if path.exists() else "nothing")


def _wait_for_pids(tmp: Path, names: list[str], timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not all((tmp / f"{n}.pid").exists() and (tmp / f"{n}.pid").read_text() for n in names):
        assert time.monotonic() < deadline, "children did not start"
        time.sleep(0.02)


@pytest.mark.timeout(120)
def test_child_killed_while_the_actors_stop_is_reported(tmp_path: Path) -> None:
    sup = _fleet(tmp_path, "replay", signal.SIGKILL)
    sup.start_all()
    try:
        _wait_for_pids(tmp_path, ["replay", "learner", "actor-0"])
        sup.poll()
        # As `romannet up` stops: actors, then the learner, then the rest; the replay dies in the first step.
        sup.stop_rank(0)
        assert not sup.children["replay"].alive()
        sup.stop_rank(1)
        codes = sup.stop_all()
    finally:
        sup.kill_all()
    assert codes == {"replay": -signal.SIGKILL, "learner": 0, "actor-0": 0}, _trace(tmp_path)
    assert sup.unclean() == {"replay": "killed by SIGKILL before it was asked to stop"}
    assert sup.ends == [("replay", "killed by SIGKILL before it was asked to stop")]


@pytest.mark.timeout(120)
def test_service_that_exits_0_unasked_while_stopping_is_unclean(tmp_path: Path) -> None:
    # The learner's SIGTERM handler exits 0, but nobody asked it yet: a service leaving on its own is not clean.
    sup = _fleet(tmp_path, "learner", signal.SIGTERM)
    sup.start_all()
    try:
        _wait_for_pids(tmp_path, ["replay", "learner", "actor-0"])
        codes = sup.stop_all()
    finally:
        sup.kill_all()
    assert codes == {"replay": 0, "learner": 0, "actor-0": 0}, _trace(tmp_path)
    assert sup.unclean() == {"learner": "exit code 0 before it was asked to stop"}


@pytest.mark.timeout(60)
def test_clean_stop_reports_nothing_and_sigkill_after_timeout_is_unclean(tmp_path: Path) -> None:
    stubborn = [PY, "-c", "import signal, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
                f"open({str(tmp_path / 'stubborn.pid')!r}, 'w').write('1'); time.sleep(60)"]
    sup = Supervisor([ChildSpec("replay", _service("replay", tmp_path), stop_rank=1),
                      ChildSpec("stubborn", stubborn, stop_rank=0, stop_timeout_s=0.3)])
    sup.start_all()
    try:
        _wait_for_pids(tmp_path, ["replay", "stubborn"])
        codes = sup.stop_all()
    finally:
        sup.kill_all()
    assert codes == {"replay": 0, "stubborn": -signal.SIGKILL}
    assert sup.unclean() == {"stubborn": "killed by SIGKILL"} and sup.ends == [("stubborn", "killed by SIGKILL")]


@pytest.mark.timeout(60)
def test_a_crash_that_a_restart_recovered_from_stays_in_the_history(tmp_path: Path) -> None:
    # The first run exits 3 on its own; the restart runs until it is stopped and stops cleanly.
    code = textwrap.dedent(f"""
        import os, signal, sys, time
        marker = {str(tmp_path / 'crashed')!r}
        if not os.path.exists(marker):
            open(marker, "w").close()
            sys.exit(3)
        signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))
        open({str(tmp_path / 'flaky.pid')!r}, "w").write(str(os.getpid()))
        time.sleep(60)
    """)
    sup = Supervisor([ChildSpec("flaky", [PY, "-c", code], stop_timeout_s=10)],
                     RestartPolicy(initial_backoff_s=0.0))
    sup.start_all()
    try:
        deadline = time.monotonic() + 30
        while not (tmp_path / "flaky.pid").exists():
            assert time.monotonic() < deadline, "the restart did not come up"
            sup.poll()
            time.sleep(0.02)
        codes = sup.stop_all()
    finally:
        sup.kill_all()
    assert codes == {"flaky": 0} and sup.crashes == 1
    assert sup.unclean() == {}  # its last run ended cleanly: the launcher's exit code stays 0
    assert sup.ends == [("flaky", "exit code 3 before it was asked to stop")]  # summary.json's unclean_ends


def test_unclean_end_rules() -> None:
    assert unclean_end(0, asked=True, restart="always") is None
    assert unclean_end(0, asked=False, restart="on-failure") is None  # a job that finished
    assert unclean_end(0, asked=False, restart="always") == "exit code 0 before it was asked to stop"
    assert unclean_end(3, asked=True, restart="on-failure") == "exit code 3"
    assert unclean_end(-9, asked=False, restart="always") == "killed by SIGKILL before it was asked to stop"
