"""Where a sweep stands, read from disk only, so a rerun after Ctrl-C, a crash or a reboot picks up there.

A run's actions are the actors' ledger (`actors/ledger.json`: the totals of earlier launches and restarted
processes) plus what each actor's status.json says beyond it, as `romannet up` counts them for
--max-actions; unlike summary.json this is right even after the launcher was killed outright.
"""

from __future__ import annotations

import json
import logging
from enum import Enum
from pathlib import Path
from typing import Any

from romannet.fleet import ActorLedger, read_actor_statuses
from romannet.up import LEDGER_FILE

log = logging.getLogger("romannet.sweep")


class RunState(Enum):
    NEW = "new"  # nothing trained yet: `romannet up` from the recipe
    PARTIAL = "partial"  # started, short of --max-actions: `romannet up --resume`
    DONE = "done"  # reached --max-actions: never trained again


def run_actions(run_dir: Path) -> int:
    """Actions the run's actors made over all its launches and restarts."""
    ledger = ActorLedger.load(run_dir / "actors" / LEDGER_FILE)
    statuses = read_actor_statuses(run_dir)
    counted = {aid: int(ledger.merged(aid, status).get("actions") or 0) for aid, status in statuses.items()}
    # An actor whose status file is gone still has its banked actions.
    return sum(counted.values()) + sum(ledger.actions(aid) for aid in ledger.carried if aid not in counted)


def run_state(run_dir: Path, max_actions: int) -> RunState:
    if not (run_dir / "config.toml").is_file():
        return RunState.NEW
    return RunState.DONE if run_actions(run_dir) >= max_actions else RunState.PARTIAL


def finished_report(out_dir: Path) -> dict[str, Any] | None:
    """An evaluation's report.json if it finished (present, readable, not interrupted), else None."""
    try:
        report = json.loads((out_dir / "report.json").read_text(encoding="utf-8"))
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        log.warning("%s cannot be read (%s): evaluating again", out_dir / "report.json", exc)
        return None
    if not isinstance(report, dict) or report.get("interrupted") or report.get("overall") is None:
        return None
    return report
