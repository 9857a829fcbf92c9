"""`romannet bench fleet`: a real tiny fleet (router, replay server, learner, 2 light actors, a few seconds),
and the report's arithmetic on hand-made files.

The fleet runs in network namespaces when this process can build them (root), else on loopback: either way
real processes over real Zenoh sessions, multicast scouting off. Speed is not asserted (tests never time
things); the report must be complete, the ledger exact, and every actor must have got the weights.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from romannet.bench import fleet_report as fr
from romannet.bench.fleet import TINY_SETTINGS, FleetPlan, run_fleet_benchmark


def test_report_latency_counts_a_newer_version_as_holding_the_older() -> None:
    probe = [(5, 1_000_000, 1_100_000, 400), (6, 2_000_000, 2_100_000, 400), (7, 9_000_000, 9_100_000, 400)]
    a = fr.ActorReport(weights=[(5, 1_500_000), (7, 9_300_000)])  # v6 skipped: v7 replaced it
    b = fr.ActorReport(weights=[(5, 3_000_000), (6, 4_000_000), (7, 9_900_000)])
    got = fr.weights_latency(probe, [a, b], window=(0, 5_000_000))  # v7 is outside the window
    assert got["versions"] == 2 and got["versions_not_at_every_actor"] == 0
    assert got["skipped_by_a_newer_version"] == 1
    # v5: the slowest actor (b) 2.0 ms after the call; v6: a held it only through v7, 7.3 ms after.
    assert got["all_actors_ms_median"] == pytest.approx((2.0 + 7.3) / 2, abs=0.1)
    missing = fr.weights_latency(probe, [a, fr.ActorReport()], window=(0, 5_000_000))
    assert missing["versions_not_at_every_actor"] == 2 and missing["all_actors_ms_median"] is None


def test_report_inserts_and_acked_not_stored(tmp_path: Path) -> None:
    path = tmp_path / "a.txt"
    path.write_text("w 3 100\na ep0 0 2000000000 5000\na ep0 1 3000000000 7000\na ep0 2 9000000000 10\nw 4")
    report = fr.read_actor_report(path)  # the cut last line is skipped
    assert report.weights == [(3, 100)] and len(report.acks) == 3
    got = fr.inserts([report], window=(1_000_000_000, 5_000_000_000))
    assert got["acked_in_window"] == 2 and got["inserts_per_s"] == 0.5 and got["insert_ms_p99"] <= 7.0
    stored = {("actor-0", "ep0", 0), ("actor-0", "ep0", 1)}
    assert fr.acked_not_stored(["actor-0"], [report], stored) == 1


@pytest.mark.timeout(600)
def test_tiny_fleet_reports_every_field_without_loss(tmp_path: Path) -> None:
    plan = FleetPlan(sizes=(2,), duration_s=5.0, settings=TINY_SETTINGS)
    result = run_fleet_benchmark(plan, work_dir=tmp_path)
    context = f"result: {result}\nlogs under {tmp_path}"
    assert result["ok"], context
    assert [s["actors"] for s in result["sizes"]] == [1, 2], context  # the 1-actor run comes first
    for size in result["sizes"]:
        assert size["every_actor_got_weights"], context
        w = size["weights"]
        assert w["versions"] > 0 and w["versions_not_at_every_actor"] == 0, context
        assert 0 < w["all_actors_ms_median"] <= w["all_actors_ms_p99"], context
        assert w["weights_bytes"] > 0 and w["copies_per_version"] is not None, context
        assert w["copies_per_version"] < 2.0, context  # one put per version, not one copy per actor
        replay = size["replay"]
        assert replay["acked_in_window"] >= 0 and replay["insert_ms_p99"] is not None, context
        assert replay["sample_ms_p99"] is not None and size["learner"]["updates_per_s"] > 0, context
        assert size["learner"]["vs_1_actor"] > 0, context
        ledger = size["ledger"]
        assert ledger["lost"] == ledger["duplicated"] == ledger["acked_not_stored"] == 0, context
        assert ledger["produced"] == ledger["acknowledged"] == ledger["stored"] > 0, context
        assert all(code == 0 for code in size["exit_codes"].values()), context
        assert set(size["goals"]) >= {"weights_latency", "one_copy_per_version", "no_loss_no_duplicates",
                                      "learner_within_10_percent"}, context
        assert size["memory_mb"]["light_actor_median"] > 0, context
