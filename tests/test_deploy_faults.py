"""Multi-host fault test: a secure fleet on five network-namespace hosts, trained through injected faults.

The scenario is `romannet bench faults` (bench/faults.py): a router host, a replay+learner host, two actor
hosts and an operator host on a virtual switch; every process uses the secure deploy configs (mutual TLS,
deny-by-default access control). It kills the replay server and the learner with SIGKILL and restarts
them (the learner with --resume), cuts an actor's link for 10 s, kills an actor, and sends an intruder
and certificate-less clients at the router. This test holds it to the issue's bar: nothing acknowledged
lost, nothing duplicated, sent == acknowledged == stored exactly, every recovery observed, every denial
observed. It needs root (network namespaces); elsewhere it is skipped with the reason.
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from romannet.bench.faults import run_fault_scenario_checked
from romannet.bench.netns import PREFIX, netns_unavailable_reason

_REASON = netns_unavailable_reason()


@pytest.mark.skipif(_REASON is not None, reason=f"multi-host fault test skipped: {_REASON}")
@pytest.mark.timeout(900)
def test_secure_fleet_survives_every_fault_without_losing_a_transition(tmp_path: Path) -> None:
    result = run_fault_scenario_checked(work_dir=tmp_path, link_cut_s=10.0)
    logs = tmp_path / "logs"
    context = f"result: {result}\nlogs in {logs}"

    # Counts: every transition the actors produced was acknowledged and stored exactly once.
    assert result["problems"] == [], context
    assert result["lost"] == 0 and result["duplicates"] == 0 and result["left_in_spools"] == 0, context
    assert result["sent"] == result["acknowledged"] == result["stored"] > 0, context
    assert all(a["stored"] > 0 for a in result["per_actor"].values()), context
    assert result["per_actor"]["actor-0"]["processes"] == 2  # killed once, restarted
    assert all(code == 0 for code in result["exit_codes"].values()), context  # clean SIGINT stops

    faults = {f["fault"].split(",")[0]: f for f in result["faults"]}
    assert result["faults_injected"] == 5, context

    intruder = next(f for f in result["faults"] if f["fault"].startswith("intruder"))
    assert intruder["as_expected"] == intruder["checks"] >= 20 and intruder["denials"] >= 14, context
    assert result["access_control_ok"], [c for c in result["access_control"] if not c["ok"]]

    replay = faults["kill -9 replay server"]
    assert replay["back_up_after_s"] < replay["recovery_s"] < 90, replay

    learner = faults["kill -9 learner"]
    assert learner["resumed_from_checkpoint"], (learner, (logs / "learner.log").read_text()[-3000:])
    assert learner["newest_before_kill"] >= 1, learner

    cut = faults["actor-1 link cut for 10 s"]
    # The actor kept acting on its spool while cut off, and the router noticed within its 3 s lease.
    assert cut["actions_during_cut"] > 0 and cut["spooled_at_restore"] > 0, cut
    assert cut["liveliness_gone_after_s"] is not None and 1.0 < cut["liveliness_gone_after_s"] < 8.0, cut

    killed = faults["kill -9 actor-0"]
    assert killed["liveliness_gone_after_s"] < 5.0, killed
    assert killed["others_acked_after_s"] < 30.0, killed

    left = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True, check=True).stdout
    assert f"{PREFIX}{os.getpid()}-" not in left, left  # the lab cleaned up after itself
