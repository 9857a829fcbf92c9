"""Integration: `romannet up` runs the whole fleet (replay, learner, 2 gripper actors at 64x64) to the end.

Checked after each run: every transition an actor sent is in the replay server exactly once (its durable
log, opened with ReplayStore), the learner made updates, each actor used at least two weights versions
and received LAE rates, every MCAP file is finished and holds the steps the actor took, no process is
left. A second run SIGKILLs the replay server in the middle: the supervisor restarts it, actors keep
acting on their spools and resend, and the totals still match. A third is interrupted like Ctrl-C (SIGINT
to the launcher) and then resumed with --resume: nothing lost, nothing duplicated, the learner continues,
--max-actions counts the earlier launch's actions, and a resume without fleet flags keeps the last
launch's. A tiny model (4 channels, 1 residual block) and one torch thread per process keep it light on a
shared 2-core box; every wait is bounded.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from romannet.common.config import load_config
from romannet.replay.store import ReplayStore
from romannet.up import thread_plan

SETS = ["model.channels=4", "model.residual_blocks=1", "model.num_threads=1", "learner.num_threads=1",
        'learner.precision="fp32"', "learner.max_grad_norm=10", "learner.batch_size=2", "learner.min_replay_size=4",
        "learner.publish_every_updates=2", "replay.min_size_to_sample=2", "sim.num_objects=3"]
RUN_TIMEOUT_S = 180


class Up:
    """A `romannet up` subprocess with its output in <tmp>/<name>.out."""

    def __init__(self, tmp: Path, name: str, max_actions: int | None, *extra: str):
        """max_actions None: neither --actors nor --max-actions (a --resume takes the last launch's)."""
        self.run_dir = tmp / "runs" / name
        self.out_path = tmp / f"{name}.out"
        self._out = self.out_path.open("ab")
        fleet = [] if max_actions is None else ["--actors", "2", "--max-actions", str(max_actions)]
        args = ["up", "--runs-dir", str(tmp / "runs"), "--name", name, *fleet, "--robot", "gripper",
                "--resolution", "0.007", "--progress-every", "5"]
        for s in SETS:
            args += ["--set", s]
        args += extra  # after SETS, so a test's --set wins
        self.proc = subprocess.Popen([sys.executable, "-m", "romannet.cli", *args], stdout=self._out,
                                     stderr=subprocess.STDOUT)

    def wait(self, timeout_s: float = RUN_TIMEOUT_S) -> int:
        try:
            return self.proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"romannet up did not finish in {timeout_s} s\n{self.output()}") from None

    def kill(self) -> None:
        """Cleanup after a failed test: SIGTERM (the launcher stops its children), then SIGKILL."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._out.close()

    def output(self) -> str:
        return self.out_path.read_text(errors="replace")[-6000:]

    def pids(self) -> dict[str, int]:
        try:
            return json.loads((self.run_dir / "pids.json").read_text())
        except (OSError, ValueError):
            return {}


@pytest.fixture
def ups() -> Iterator[list[Up]]:
    started: list[Up] = []
    yield started
    for up in started:
        up.kill()


def _wait_for(fn: Callable[[], Any], timeout_s: float, what: str, up: Up) -> Any:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and up.proc.poll() is None:
        value = fn()
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"no {what} within {timeout_s} s\n{up.output()}")


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def _statuses(run_dir: Path) -> dict[str, dict[str, Any]]:
    return {p.parent.name: json.loads(p.read_text()) for p in sorted((run_dir / "actors").glob("*/status.json"))}


def _replay_items(run_dir: Path) -> tuple[list[tuple[str, str, int]], dict[str, set[int]]]:
    """(keys of every item in the replay's durable log, policy versions per actor), read with the store."""
    cfg = load_config(run_dir / "config.toml")
    with ReplayStore(cfg.replay, run_dir / "replay") as store:
        items = store.recovered.items
    keys = [tuple(meta.key) for _, _, meta in items]
    versions: dict[str, set[int]] = {}
    for _, _, meta in items:
        versions.setdefault(meta.key[0], set()).add(meta.policy_version)
    return keys, versions  # type: ignore[return-value]


def _mcap_episodes(run_dir: Path, actor_id: str) -> tuple[int, set[int], set[float]]:
    """(steps, weights versions, LAE rates) over an actor's MCAP files; each file must be finished."""
    steps, versions, rates = 0, set(), set()
    files = sorted((run_dir / "episodes" / actor_id).glob("*.mcap"))
    assert files, f"no MCAP file for {actor_id}"
    for path in files:
        with path.open("rb") as fh:
            reader = make_reader(fh)
            assert reader.get_summary() is not None, f"{path} is not finished"
            assert "romannet" in {m.name for m in reader.iter_metadata()}, path
            transitions = 0
            for _, channel, message in reader.iter_messages(topics=["/transition", "/step"]):
                if channel.topic == "/transition":
                    transitions += 1
                else:
                    step = json.loads(message.data)
                    versions.add(int(step["weights_version"]))
                    rates.add(float(step["explore_rate"]))
            steps += transitions
    return steps, versions, rates


def _each_actor_acked(up: Up, n: int) -> bool:
    """Both actors have n acknowledged transitions (so both have started an episode and its MCAP file)."""
    statuses = _statuses(up.run_dir)
    return len(statuses) == 2 and all(s.get("acked", 0) >= n for s in statuses.values())


def _check_run(up: Up, expected_actions: int, learning: bool = True) -> dict[str, Any]:
    """Everything a finished run must satisfy; returns the summary. learning: also require that each actor
    acted with at least two weights versions and received LAE rates (not when the test froze the replay,
    and with it the learner, for much of a short run)."""
    run_dir = up.run_dir
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["outcome"] == "max_actions_reached", summary
    assert summary["trained"] is True, summary
    assert all(code == 0 for code in summary["exit_codes"].values()), summary["exit_codes"]
    statuses = _statuses(run_dir)
    assert sorted(statuses) == ["actor-0", "actor-1"]
    assert sum(s["actions"] for s in statuses.values()) == expected_actions

    # Replay: every transition sent is there exactly once (keys are unique in the log; counts match).
    keys, replay_versions = _replay_items(run_dir)
    assert len(keys) == len(set(keys)), "duplicate keys in the replay log"
    per_actor = Counter(k[0] for k in keys)
    for aid, status in statuses.items():
        assert status["spool_items"] == 0, (aid, status)  # everything was acknowledged before exit
        assert per_actor[aid] == status["actions"] == status["acked"], (aid, per_actor, status)
        steps, versions, rates = _mcap_episodes(run_dir, aid)
        assert steps == status["actions"], (aid, steps, status["actions"])
        if learning:
            assert status["weights_versions_used"] >= 2, (aid, status)
            assert status["explore_rate_received"], (aid, status)
            assert len(replay_versions[aid]) >= 2, (aid, replay_versions)
            assert len(versions) >= 2, (aid, versions)
            assert any(r != 0.5 for r in rates), (aid, rates)  # 0.5 = exploration.initial_rate, before LAE
    assert summary["replay_size"] == len(keys), summary

    # Learner: updates in metrics.csv, a checkpoint, curves.
    with (run_dir / "metrics.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert rows and int(rows[-1]["update"]) >= 2, "the learner made no updates"
    assert (run_dir / "checkpoints" / "LATEST").is_file() and (run_dir / "learning_curves.png").is_file()
    assert (run_dir / "config.toml").is_file() and (run_dir / "launcher.log").is_file()
    # The launcher's own curves of what the actors did: the PNG and the TensorBoard events with the config.
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    assert (run_dir / "training_curves.png").is_file()
    board = EventAccumulator(str(run_dir / "tensorboard" / "episodes"))
    board.Reload()
    assert "config" in board.Tags()["tensors"] and "actions/success_rate" in board.Tags()["scalars"]
    assert board.Scalars("actions/success_rate")[-1].step <= expected_actions

    # No process outlives the launcher.
    pids = up.pids()
    assert pids and not any(_alive(pid) for pid in pids.values()), pids
    return summary


# The defaults' pacing (the clutter recipe's): the replay server holds an insert's acknowledgement while the
# learner is more than a few samples behind, and a 2-item spool makes the actor wait for it. Unpaced, a fast
# machine's actors finished all 40 actions before the learner's second weights version.
PACED = ["replay.samples_per_insert=2.0", "replay.max_batch_size=4", "replay.spi_tolerance=8.0",
         "actor.spool_max_items=2"]
# Unpaced, with a deep spool: the actors act on through a replay outage.
UNPACED = ["replay.samples_per_insert=0", "actor.spool_max_items=2000"]


def test_up_runs_the_fleet_to_max_actions(tmp_path: Path, ups: list[Up]) -> None:
    """Learner-paced as the recipes are, so each actor's share of the 40 actions spans several weights
    versions however fast the actors are compared with the learner."""
    up = Up(tmp_path, "fleet", 40, *[arg for s in PACED for arg in ("--set", s)])
    ups.append(up)
    assert up.wait() == 0, up.output()
    summary = _check_run(up, 40)
    assert summary["restarts"] == 0, summary
    assert "max actions reached" in up.output()


def test_a_run_too_short_to_train_says_so_first_and_in_its_summary(tmp_path: Path, ups: list[Up]) -> None:
    up = Up(tmp_path, "short", 4, "--set", "learner.min_replay_size=8", "--set", "replay.min_size_to_sample=8")
    ups.append(up)
    assert up.wait() == 0, up.output()
    out = up.output()
    assert "this run will not train: the learner's first update needs 8 transitions" in out, out
    assert "run short did not train: the learner made no update" in out, out
    summary = json.loads((up.run_dir / "summary.json").read_text())
    assert summary["trained"] is False and summary["learner_updates"] == 0, summary


def test_replay_outages_mid_run_lose_and_duplicate_nothing(tmp_path: Path, ups: list[Up]) -> None:
    """The replay server is frozen for 6 s (SIGSTOP: queries pile up unanswered, then time out and are
    resent while the originals are still queued), then killed (SIGKILL: the supervisor restarts it, it
    recovers from its log). Actors keep acting on their spools throughout. The run has no action limit, so
    the outages always fall mid-run however fast the machine; it ends with Ctrl-C once the restarted server
    has acknowledged more transitions."""
    up = Up(tmp_path, "outage", 0, *[arg for s in UNPACED for arg in ("--set", s)])
    ups.append(up)

    def acked() -> int:
        return sum(s.get("acked", 0) for s in _statuses(up.run_dir).values())

    _wait_for(lambda: _each_actor_acked(up, 5) and "replay" in up.pids(), 120,
              "5 acknowledged transitions from each actor", up)
    replay_pid = up.pids()["replay"]
    os.kill(replay_pid, signal.SIGSTOP)
    try:
        time.sleep(6.0)
    finally:
        os.kill(replay_pid, signal.SIGCONT)
    after_stop = acked()
    _wait_for(lambda: acked() > after_stop, 60, "acknowledgements after SIGCONT", up)
    os.kill(replay_pid, signal.SIGKILL)  # no snapshot, no clean close: recovery from the log
    at_kill = acked()
    _wait_for(lambda: up.pids().get("replay", replay_pid) != replay_pid, 60, "a restarted replay server", up)
    _wait_for(lambda: acked() > at_kill + 5, 90, "acknowledgements from the restarted server", up)
    up.proc.send_signal(signal.SIGINT)
    assert up.wait(120) == 0, up.output()

    summary = json.loads((up.run_dir / "summary.json").read_text())
    assert summary["outcome"] == "stopped_by_signal", summary
    assert summary["restarts"] == 1, summary
    assert "replay crashed (killed by SIGKILL); restarting" in up.output()
    assert summary["unclean_ends"] == [{"child": "replay", "how": "killed by SIGKILL before it was asked to stop"}]
    keys, _ = _replay_items(up.run_dir)
    assert len(keys) == len(set(keys)), "duplicate keys in the replay log"
    per_actor = Counter(k[0] for k in keys)
    for aid, status in _statuses(up.run_dir).items():
        # Nothing lost: every action is either acknowledged (so in the replay log) or still spooled on disk.
        assert status["acked"] + status["spool_items"] == status["actions"], (aid, status)
        assert status["acked"] <= per_actor[aid] <= status["actions"], (aid, per_actor, status)
        steps, _, _ = _mcap_episodes(up.run_dir, aid)
        assert steps == status["actions"], (aid, steps, status)
    pids = up.pids()
    assert not any(_alive(pid) for pid in pids.values()), pids


def test_ctrl_c_stops_cleanly_and_resume_continues(tmp_path: Path, ups: list[Up]) -> None:
    up = Up(tmp_path, "resumed", 0)  # no limit: runs until interrupted
    ups.append(up)
    _wait_for(lambda: _each_actor_acked(up, 5), 120, "5 acknowledged transitions from each actor", up)
    up.proc.send_signal(signal.SIGINT)  # what Ctrl-C delivers to the launcher (children have their own group)
    assert up.wait(120) == 0, up.output()
    summary = json.loads((up.run_dir / "summary.json").read_text())
    assert summary["outcome"] == "stopped_by_signal", summary
    assert all(code == 0 for code in summary["exit_codes"].values()), summary["exit_codes"]
    pids = up.pids()
    assert not any(_alive(pid) for pid in pids.values()), pids
    first = _statuses(up.run_dir)
    keys, _ = _replay_items(up.run_dir)
    per_actor = Counter(k[0] for k in keys)
    for aid, status in first.items():
        # Nothing lost: what the server did not acknowledge is still in the actor's spool on disk.
        assert status["acked"] + status["spool_items"] == status["actions"], (aid, status)
        assert per_actor[aid] >= status["acked"], (aid, per_actor, status)
        steps, _, _ = _mcap_episodes(up.run_dir, aid)  # every file finished despite the interruption
        assert steps == status["actions"], (aid, steps, status)
    updates_before = int(list(csv.DictReader((up.run_dir / "metrics.csv").open()))[-1]["update"])
    done = sum(status["actions"] for status in first.values())

    # --max-actions counts the run's actions over its launches: 20 more to reach done + 20.
    again = Up(tmp_path, "resumed", done + 20, "--resume")
    ups.append(again)
    assert again.wait() == 0, again.output()
    summary = json.loads((again.run_dir / "summary.json").read_text())
    assert summary["outcome"] == "max_actions_reached", summary
    assert (summary["actions"], summary["actions_this_launch"]) == (done + 20, 20), summary
    assert f"the run's earlier launches made {done} actions" in again.output()
    assert f"resumed from {up.run_dir / 'checkpoints'}" in (again.run_dir / "logs" / "learner.log").read_text()
    second = _statuses(again.run_dir)
    keys, _ = _replay_items(again.run_dir)
    assert len(keys) == len(set(keys)), "duplicate keys in the replay log"
    per_actor = Counter(k[0] for k in keys)
    for aid in first:
        assert second[aid]["spool_items"] == 0, second[aid]
        assert per_actor[aid] == first[aid]["actions"] + second[aid]["actions"], (aid, per_actor, first, second)
    rows = [int(r["update"]) for r in csv.DictReader((again.run_dir / "metrics.csv").open())]
    assert rows == sorted(rows) and rows[-1] > updates_before, (updates_before, rows[-5:])

    # Resumed without --actors / --max-actions: the last launch's (2, done + 20), which the run has reached.
    third = Up(tmp_path, "resumed", None, "--resume")
    ups.append(third)
    assert third.wait(60) == 0, third.output()
    assert "resuming with --actors 2 --max-actions" in third.output()
    assert f"already has {done + 20} actions (--max-actions {done + 20}): nothing to do" in third.output()
    assert third.pids() == again.pids(), "the third launch started processes"


def test_killed_actor_is_restarted_with_the_rest_of_its_share(tmp_path: Path, ups: list[Up]) -> None:
    up = Up(tmp_path, "actorcrash", 40)
    ups.append(up)
    _wait_for(lambda: _statuses(up.run_dir).get("actor-1", {}).get("actions", 0) >= 5, 120,
              "5 actions by actor-1", up)
    killed = up.pids()["actor-1"]
    os.kill(killed, signal.SIGKILL)  # mid-action: its MCAP file stays unfinished, its spool stays on disk
    _wait_for(lambda: up.pids().get("actor-1", killed) != killed, 60, "a restarted actor-1", up)
    assert up.wait() == 0, up.output()
    summary = json.loads((up.run_dir / "summary.json").read_text())
    assert summary["outcome"] == "max_actions_reached" and summary["restarts"] == 1, summary
    assert "actor-1 crashed (killed by SIGKILL); restarting" in up.output()
    assert summary["unclean"] == {} and summary["unclean_ends"] == [
        {"child": "actor-1", "how": "killed by SIGKILL before it was asked to stop"}], summary
    # The launcher adds up both processes of actor-1; together they did its share (20 of 40).
    assert summary["actions"] == 40 and summary["actors"]["actor-1"]["actions"] == 20, summary
    keys, _ = _replay_items(up.run_dir)
    assert len(keys) == len(set(keys)), "duplicate keys in the replay log"
    per_actor = Counter(k[0] for k in keys)
    assert per_actor["actor-0"] == 20
    # A transition spooled in the instant before the kill, not yet counted in status.json, is still sent.
    assert per_actor["actor-1"] in (20, 21), per_actor
    files = sorted((up.run_dir / "episodes" / "actor-1").glob("*.mcap"))
    unfinished = []
    for path in files:
        with path.open("rb") as fh:
            try:
                finished = make_reader(fh).get_summary() is not None
            except Exception:  # a file cut off mid-chunk by the kill
                finished = False
        if not finished:
            unfinished.append(path.name)
    assert len(unfinished) <= 1, unfinished  # only the episode under way at the kill


@pytest.mark.parametrize("cores,actors,expected", [
    (2, 1, {"replay": 1, "actor": 1, "learner": 1}),
    (2, 2, {"replay": 1, "actor": 1, "learner": 1}),
    (16, 1, {"replay": 1, "actor": 8, "learner": 8}),
    (16, 3, {"replay": 1, "actor": 4, "learner": 4}),
    (1, 1, {"replay": 1, "actor": 1, "learner": 1}),
])
def test_thread_plan_shares_the_cores_between_learner_and_actors(cores, actors, expected):
    plan = thread_plan(cores, actors)
    assert plan == expected
    if cores >= actors + 1:  # room for everyone: the compute threads never exceed the cores
        assert plan["learner"] + actors * plan["actor"] <= cores
