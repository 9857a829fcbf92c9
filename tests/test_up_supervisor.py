"""The launcher's supervisor with tiny dummy children (`python -c ...`): restarts with backoff, stop order,
SIGKILL after the grace time, and no orphan when the launcher itself is killed."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from romannet.fleet import ActorLedger, FleetSnapshot, MovingRate, fleet_fields, read_last_metrics
from romannet.progress import Reading, plain_line
from romannet.supervisor import ChildSpec, RestartPolicy, Supervisor
from romannet.up import actor_shares, split_actions

PY = sys.executable


def _wait(fn: Callable[[], object], timeout_s: float = 20.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if fn():
            return
        time.sleep(0.05)
    raise AssertionError(f"no {what} within {timeout_s} s")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # A zombie still answers kill(0); it is dead for our purpose.
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def test_backoff_policy_doubles_up_to_the_cap() -> None:
    policy = RestartPolicy(initial_backoff_s=1.0, factor=2.0, max_backoff_s=5.0)
    assert [policy.backoff_s(n) for n in range(5)] == [1.0, 2.0, 4.0, 5.0, 5.0]


def test_crashing_child_is_restarted_with_backoff_then_given_up(caplog: pytest.LogCaptureFixture,
                                                                tmp_path: Path) -> None:
    policy = RestartPolicy(initial_backoff_s=0.2, factor=2.0, max_backoff_s=1.0, max_restarts=2, window_s=60)
    sup = Supervisor([ChildSpec("crasher", [PY, "-c", "import sys; sys.exit(3)"], log_path=tmp_path / "c.log")],
                     policy)
    caplog.set_level(logging.INFO, logger="romannet.supervisor")
    starts: list[float] = []
    sup.start("crasher")
    starts.append(time.monotonic())
    try:
        deadline = time.monotonic() + 30
        while not sup.gave_up and time.monotonic() < deadline:
            before = sup.children["crasher"].starts
            sup.poll()
            if sup.children["crasher"].starts > before:
                starts.append(time.monotonic())
            time.sleep(0.02)
    finally:
        sup.stop_all()
    assert sup.gave_up == ["crasher"]
    assert sup.children["crasher"].starts == 3 and sup.crashes == 2
    gaps = [b - a for a, b in zip(starts, starts[1:], strict=False)]
    assert gaps[0] >= 0.2 and gaps[1] >= 0.4, gaps  # 0.2 s, then 0.4 s (plus the child's own run time)
    text = caplog.text
    assert "crasher crashed (exit code 3); restarting in 0.2 s" in text
    assert "crasher crashed (exit code 3); restarting in 0.4 s" in text
    assert "restarting crasher" in text and "giving up" in text


def test_job_that_exits_0_is_done_not_restarted() -> None:
    sup = Supervisor([ChildSpec("job", [PY, "-c", "pass"], restart="on-failure")])
    sup.start_all()
    _wait(lambda: (sup.poll(), sup.children["job"].state == "done")[1], what="job done")
    assert sup.children["job"].starts == 1 and sup.crashes == 0


def _sleeper(name: str, out: Path, ignore_term: bool = False) -> list[str]:
    """A child that says it is ready, then on SIGTERM appends its name to `out` and exits 0 (or ignores it)."""
    code = textwrap.dedent(f"""
        import signal, sys, time
        from pathlib import Path
        def on_term(*_):
            with open({str(out)!r}, "a") as f:
                f.write({name!r} + "\\n")
            time.sleep(0.2)  # a little clean-up work: the next rank must wait for it
            sys.exit(0)
        signal.signal(signal.SIGTERM, signal.SIG_IGN if {ignore_term} else on_term)
        Path({str(out)!r} + ".{name}.ready").touch()
        time.sleep(120)
    """)
    return [PY, "-c", code]


def test_stop_order_ranks_and_sigkill_after_grace(tmp_path: Path) -> None:
    out = tmp_path / "order.txt"
    specs = [ChildSpec("replay", _sleeper("replay", out), stop_rank=2),
             ChildSpec("learner", _sleeper("learner", out), stop_rank=1),
             ChildSpec("actor-0", _sleeper("actor-0", out), stop_rank=0, restart="on-failure"),
             ChildSpec("actor-1", _sleeper("actor-1", out), stop_rank=0, restart="on-failure"),
             ChildSpec("stubborn", _sleeper("stubborn", out, ignore_term=True), stop_rank=3, stop_timeout_s=0.5)]
    sup = Supervisor(specs)
    sup.start_all()
    try:
        _wait(lambda: all(Path(f"{out}.{s.name}.ready").exists() for s in specs), what="children ready")
        codes = sup.stop_all()
    finally:
        sup.kill_all()
    lines = out.read_text().split()
    assert sorted(lines[:2]) == ["actor-0", "actor-1"] and lines[2:] == ["learner", "replay"], lines
    assert codes["stubborn"] == -signal.SIGKILL
    assert all(codes[n] == 0 for n in ("replay", "learner", "actor-0", "actor-1")), codes
    assert all(c.state == "stopped" for c in sup.children.values())


def test_killed_launcher_leaves_no_orphan(tmp_path: Path) -> None:
    """SIGKILL a process that supervises a child: the child gets SIGTERM (PR_SET_PDEATHSIG) and exits."""
    pid_file = tmp_path / "child.pid"
    launcher_code = textwrap.dedent(f"""
        import sys, time
        from romannet.supervisor import ChildSpec, Supervisor
        child = [sys.executable, "-c", "import os, time; open({str(pid_file)!r}, 'w').write(str(os.getpid())); "
                 "time.sleep(120)"]
        sup = Supervisor([ChildSpec("child", child)])
        sup.start_all()
        time.sleep(120)
    """)
    launcher = subprocess.Popen([PY, "-c", launcher_code])
    try:
        _wait(lambda: pid_file.exists() and pid_file.read_text().strip(), what="child pid")
        child_pid = int(pid_file.read_text())
        assert _pid_alive(child_pid)
        assert os.getpgid(child_pid) == child_pid  # its own process group: a terminal's Ctrl-C skips it
        launcher.kill()
        launcher.wait(10)
        _wait(lambda: not _pid_alive(child_pid), timeout_s=30, what="child exit after the launcher died")
    finally:
        if launcher.poll() is None:
            launcher.kill()
        if pid_file.exists() and _pid_alive(int(pid_file.read_text())):
            os.kill(int(pid_file.read_text()), signal.SIGKILL)


def test_split_actions_and_ledger_across_restarts() -> None:
    assert split_actions(41, 2) == [21, 20] and split_actions(0, 3) == [0, 0, 0]
    ledger = ActorLedger()
    ledger.retire("a", {"pid": 10, "actions": 7, "acked": 6})
    ledger.retire("a", {"pid": 10, "actions": 7, "acked": 6})  # the same dead process twice counts once
    assert ledger.merged("a", {"pid": 10, "actions": 7})["actions"] == 7  # its file, not yet replaced
    assert ledger.merged("a", {"pid": 11, "actions": 2, "acked": 1})["acked"] == 7
    assert ledger.actions("a") == 7


def test_actor_shares_count_the_runs_earlier_launches() -> None:
    assert actor_shares(0, 500, 2) == [0, 0]  # no limit
    assert actor_shares(2500, 0, 1) == [2500]
    assert actor_shares(2500, 1666, 1) == [834]
    assert actor_shares(2500, 1667, 2) == [417, 416]
    assert actor_shares(2500, 2499, 3) == [1, 1, 1]  # every started actor does one (0 would be no limit)


def test_ledger_saved_and_loaded_across_launches(tmp_path: Path) -> None:
    from romannet.common.errors import RomannetError

    path = tmp_path / "actors" / "ledger.json"
    first = ActorLedger.load(path)  # none yet: empty
    assert first.carried == {}
    first.retire("a", {"pid": 10, "started_ns": 1, "actions": 7, "picks": 5})
    second = ActorLedger.load(path)  # what the next launch reads
    second.retire("a", {"pid": 10, "started_ns": 1, "actions": 7, "picks": 5})  # that process again: nothing
    second.retire("a", {"pid": 10, "started_ns": 2, "actions": 3})  # the same pid after a reboot is another
    second.retire("b", {"pid": 12, "actions": 4})  # a status from before started_ns
    second.mark_start()
    assert (second.actions("a"), second.actions("b"), second.start_total()) == (10, 4, 14)
    assert second.merged("a", {"pid": 10, "started_ns": 2, "actions": 3})["actions"] == 10  # stale file
    assert second.merged("a", {"pid": 20, "started_ns": 9, "actions": 2, "picks": 1})["picks"] == 6
    second.retire("a", {"pid": 20, "started_ns": 9, "actions": 2})  # a crash in this launch
    assert second.this_start("a") == 2 and second.this_start("b") == 0
    assert ActorLedger.load(path).carried == second.carried
    path.write_text('{"carried": {"a": {"actions": 7}}, "ret')  # torn
    with pytest.raises(RomannetError, match="cannot be read .*move it away"):
        ActorLedger.load(path)
    path.write_text('{"carried": [1, 2], "retired": []}')
    with pytest.raises(RomannetError, match="is not a ledger"):
        ActorLedger.load(path)


def test_moving_pick_rate_and_metrics_tail(tmp_path: Path) -> None:
    rate = MovingRate(window=10)
    for attempts, successes in [(0, 0), (10, 2), (20, 10)]:
        rate.add(attempts, successes)
    assert rate.value() == pytest.approx(0.8)  # the last 10 attempts: 8 successes
    csv_path = tmp_path / "metrics.csv"
    csv_path.write_text("update,explore_rate\n1,0.5\n2,0.4\n3,0.")  # the last row is being written
    assert read_last_metrics(csv_path) == {"update": "2", "explore_rate": "0.4"}


def test_progress_line_tells_a_paced_actor_from_a_paused_one() -> None:
    """Waiting for a slow learner is routine ("paced"); a spool full because the server is gone is news."""
    snap = FleetSnapshot(actions=12, actors={
        "a0": {"weights_version": 3, "paused": True, "pause_kind": "paced"},
        "a1": {"weights_version": 3, "paused": True, "pause_kind": "outage"},
        "a2": {"weights_version": 2, "paused": False},
        "a3": {"weights_version": 3, "paused": True, "pause_kind": "waiting"},
        "a4": {"weights_version": 3, "paused": True, "pause_kind": "robot"},
        "a5": {"weights_version": 1, "paused": True}})  # a status from before pause_kind existed
    line = plain_line(Reading("up", snap.actions, 100, "actions", fields=tuple(fleet_fields(snap))))
    assert "actions 12/100" in line and "PAUSED a1 a4 a5" in line
    assert "a0:v3 paced a1:v3 PAUSED a2:v2 a3:v3 waiting a4:v3 PAUSED a5:v1 PAUSED" in line


def test_prepare_run_flags_fresh_and_resume(tmp_path: Path) -> None:
    from romannet.cli import build_parser
    from romannet.common.config import load_config
    from romannet.common.errors import RomannetError
    from romannet.rundir import prepare_run

    def args(*extra: str) -> object:
        return build_parser().parse_args(["up", "--runs-dir", str(tmp_path), "--name", "r1", *extra])

    run_dir, cfg = prepare_run(args("--task", "stacking", "--goal-height", "3", "--resolution", "0.007",
                                    "--robot", "gripper", "--set", "learner.batch_size=2"))
    saved = load_config(run_dir / "config.toml")
    assert saved == cfg and cfg.run_id == "r1" and cfg.task.kind == "stacking"
    assert (cfg.task.goal_stack_height, cfg.workspace.height_px, cfg.sim.robot, cfg.learner.batch_size) == \
        (3, 64, "gripper", 2)
    with pytest.raises(RomannetError, match="already exists"):
        prepare_run(args())
    with pytest.raises(RomannetError, match="cannot change the workspace"):
        prepare_run(args("--resume", "--resolution", "0.002"))
    _, resumed = prepare_run(args("--resume", "--set", "learner.batch_size=4"))
    assert resumed.task.kind == "stacking" and resumed.learner.batch_size == 4
    with pytest.raises(RomannetError, match="at least one action per actor"):
        prepare_run(args("--actors", "3", "--max-actions", "2"))


def test_resume_of_a_run_saved_before_a_default_changed_keeps_what_it_ran_with(tmp_path: Path) -> None:
    """A run's config.toml written while no ratio limit was an unwritten unset value, and before the rotation
    head had a second harmonic, resumes unpaced with one harmonic, not with today's defaults."""
    import tomli_w

    from romannet.cli import build_parser
    from romannet.common.config import Config, load_config
    from romannet.common.configbase import to_dict
    from romannet.rundir import prepare_run

    old = to_dict(Config(run_id="r1"))
    del old["model"]["rotation_harmonics"], old["replay"]["samples_per_insert"]
    (tmp_path / "r1").mkdir()
    (tmp_path / "r1" / "config.toml").write_text(tomli_w.dumps(old))
    ns = build_parser().parse_args(["up", "--runs-dir", str(tmp_path), "--name", "r1", "--resume", "--actors", "1"])
    _, cfg = prepare_run(ns)
    assert cfg.replay.spi_limit is None and cfg.model.rotation_harmonics == 1
    assert load_config(tmp_path / "r1" / "config.toml") == cfg  # written out in full, as it ran


def test_resume_takes_the_last_launchs_fleet_unless_given(tmp_path: Path) -> None:
    from romannet.cli import build_parser
    from romannet.common.errors import RomannetError
    from romannet.rundir import prepare_run

    def args(*extra: str) -> argparse.Namespace:
        ns = build_parser().parse_args(["up", "--runs-dir", str(tmp_path), "--name", "r1", *extra])
        prepare_run(ns)
        return ns

    fresh = args("--actors", "1", "--max-actions", "2500")
    assert (fresh.actors, fresh.max_actions) == (1, 2500)
    resumed = args("--resume")
    assert (resumed.actors, resumed.max_actions) == (1, 2500)
    changed = args("--resume", "--actors", "3")
    assert (changed.actors, changed.max_actions) == (3, 2500)
    assert (args("--resume").actors, args("--resume", "--max-actions", "0").max_actions) == (3, 0)
    other = build_parser().parse_args(["up", "--runs-dir", str(tmp_path), "--name", "r2"])
    prepare_run(other)
    assert (other.actors, other.max_actions) == (2, 0)  # a fresh run's defaults
    (tmp_path / "r2" / "launch.json").write_text("{not json")
    with pytest.raises(RomannetError, match="launch.json cannot be read .*pass --actors and --max-actions"):
        args_r2 = build_parser().parse_args(["up", "--runs-dir", str(tmp_path), "--name", "r2", "--resume"])
        prepare_run(args_r2)
