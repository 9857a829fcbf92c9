"""The fault scenario's counting (bench/fault_ledger.py) on hand-made runs: a real ReplayStore log, spool files
and status files as the actors write them. It must agree exactly when nothing is lost, and name every way a
transition can go missing (a gap inside an episode, a spooled transition never stored, a clean process that
reported more than was stored)."""

from __future__ import annotations

import json
from pathlib import Path

from _replay_helpers import tr

from romannet.bench.fault_ledger import Ledger, next_episode, spool_keys
from romannet.common import wire
from romannet.common.config import load_config
from romannet.common.configbase import write_toml
from romannet.replay.store import ReplayStore

ACTORS = ("actor-0", "actor-1")


def _run(tmp_path: Path, stored: list[tuple[str, str, int]]) -> Path:
    config = tmp_path / "run.toml"
    write_toml(load_config(None, ["replay.snapshot_every_s=0.0", "replay.snapshot_every_inserts=0"]), config)
    with ReplayStore(load_config(config).replay, tmp_path / "run" / "replay") as store:
        for actor, episode, step in stored:
            assert store.insert(tr(step, episode=episode, actor=actor)).status == "accepted"
    return config


def _status(**kw: object) -> dict:
    return {"state": "stopped", "actions": 0, **kw}


def _spool(tmp_path: Path, actor: str, keys: list[tuple[str, int]]) -> None:
    spool = tmp_path / "run" / "actors" / actor / "spool"
    spool.mkdir(parents=True, exist_ok=True)
    for seq, (episode, step) in enumerate(keys):
        (spool / f"{seq:012d}.pb").write_bytes(wire.encode_transition(tr(step, episode=episode, actor=actor)))


def _state(tmp_path: Path, actor: str, next_index: int) -> None:
    path = tmp_path / "run" / "actors" / actor / "state.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"next_episode": next_index}))


def test_counts_agree_through_a_killed_and_restarted_actor(tmp_path: Path) -> None:
    # actor-0: process 1 did ep000000 (3 steps) and ep000001 (2 steps, the 2nd spooled in the instant
    # before the kill: its status says 4 actions); process 2 resent it and did ep000002 (2 steps).
    stored = [("actor-0", "ep000000", s) for s in range(3)] + [("actor-0", "ep000001", s) for s in range(2)] \
        + [("actor-0", "ep000002", s) for s in range(2)] + [("actor-1", "ep000000", s) for s in range(4)]
    config = _run(tmp_path, stored)
    _spool(tmp_path, "actor-0", [("ep000001", 1)])
    _state(tmp_path, "actor-0", 2)
    ledger = Ledger(tmp_path / "run", ACTORS)
    assert spool_keys(tmp_path / "run", "actor-0") == {("actor-0", "ep000001", 1)}
    ledger.killed("actor-0", _status(state="running", actions=4), spool_keys(tmp_path / "run", "actor-0"),
                  next_episode(tmp_path / "run", "actor-0"))
    for f in (tmp_path / "run" / "actors" / "actor-0" / "spool").glob("*.pb"):
        f.unlink()  # the restarted process resent and acknowledged it
    ledger.final("actor-0", _status(actions=2))
    ledger.final("actor-1", _status(actions=4))
    counts = ledger.reconcile(config)
    assert counts["problems"] == [], counts
    assert (counts["sent"], counts["acknowledged"], counts["stored"]) == (11, 11, 11)
    assert counts["lost"] == counts["duplicates"] == counts["left_in_spools"] == 0 and counts["counts_agree"]
    assert counts["per_actor"]["actor-0"]["processes"] == 2


def test_every_kind_of_loss_is_named(tmp_path: Path) -> None:
    # actor-0: step 1 of ep000000 missing (a gap); a transition spooled at the kill that never got stored.
    # actor-1: its clean process says 3 actions, 2 are stored, and 1 is still in its spool.
    stored = [("actor-0", "ep000000", 0), ("actor-0", "ep000000", 2), ("actor-1", "ep000000", 0),
              ("actor-1", "ep000000", 1)]
    config = _run(tmp_path, stored)
    _spool(tmp_path, "actor-0", [("ep000000", 3)])
    ledger = Ledger(tmp_path / "run", ACTORS)
    ledger.killed("actor-0", _status(state="running", actions=4), spool_keys(tmp_path / "run", "actor-0"), 1)
    ledger.final("actor-1", _status(actions=3))
    _spool(tmp_path, "actor-1", [("ep000000", 2)])
    counts = ledger.reconcile(config)
    problems = "\n".join(counts["problems"])
    assert "actor-0: steps missing inside episodes {'ep000000': [1]}" in problems
    assert "actor-0: 1 transition(s) spooled at the kill never stored" in problems
    assert counts["lost"] >= 2 and not counts["counts_agree"]
    assert counts["per_actor"]["actor-1"]["refused"] == 0
    assert counts["left_in_spools"] == 2  # actor-0's unsent one and actor-1's
    assert counts["acknowledged"] < counts["sent"]


def test_a_refused_transition_is_a_problem_with_its_reason(tmp_path: Path) -> None:
    config = _run(tmp_path, [("actor-0", "ep000000", 0), ("actor-1", "ep000000", 0)])
    rejected = tmp_path / "run" / "actors" / "actor-1" / "spool" / "rejected"
    rejected.mkdir(parents=True)
    (rejected / "1-000000000001.pb").write_bytes(wire.encode_transition(tr(1, episode="ep000000", actor="actor-1")))
    (rejected / "1-000000000001.json").write_text(json.dumps({"reason": "error: Timeout"}))
    ledger = Ledger(tmp_path / "run", ACTORS)
    ledger.final("actor-0", _status(actions=1))
    ledger.final("actor-1", _status(actions=2))
    counts = ledger.reconcile(config)
    assert "actor-1: 1 transition(s) refused by the replay server and set aside in its spool's rejected/ " \
           "(first: error: Timeout)" in counts["problems"]
    assert counts["per_actor"]["actor-1"]["refused"] == 1 and not counts["counts_agree"]
