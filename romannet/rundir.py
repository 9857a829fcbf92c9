"""The run directory of `romannet up`: validate the arguments, resolve the config, guard a resume.

`prepare_run(args)` creates `<runs-dir>/<name>/` and writes its config.toml before any child starts (every
child reads that file). A fresh run refuses a directory that holds anything; `--resume` reuses the saved
config.toml (plus --set and flag overrides) and, unless they are given again, the last launch's --actors
and --max-actions (launch.json); it refuses to change the workspace (the replay holds transitions of that
size) or to share the directory with a launcher that is still running, and warns about actors' spools
that the requested --actors would leave unsent.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from pathlib import Path
from typing import TYPE_CHECKING

from romannet.common.dirlock import check_not_locked
from romannet.common.errors import RomannetError
from romannet.common.fsutil import write_json_atomic

if TYPE_CHECKING:
    from romannet.common.config import Config

log = logging.getLogger("romannet.up")

LAUNCH_FILE = "launch.json"  # the last launch's --actors and --max-actions, the defaults of a --resume


def _flag_overrides(args: argparse.Namespace) -> list[str]:
    out = []
    if args.task is not None:
        out.append(f'task.kind="{args.task}"')
    if args.goal_height is not None:
        out.append(f"task.goal_stack_height={args.goal_height}")
    if args.resolution is not None:
        out.append(f"workspace.resolution_m={args.resolution!r}")
    if args.robot is not None:
        out.append(f'sim.robot="{args.robot}"')
    return out


def prepare_run(args: argparse.Namespace) -> tuple[Path, Config]:
    """Validate the arguments, create the run directory and write its config.toml (before any child)."""
    from romannet.common.config import load_config, load_saved_config
    from romannet.common.config_pacing import check_prefill
    from romannet.common.configbase import write_toml

    name = args.name or time.strftime("run-%Y%m%d-%H%M%S")
    if not all(c.isalnum() or c in "-_" for c in name) or not name:
        raise RomannetError(f"--name {name!r}: use letters, digits, '-' and '_' (it is the run id in Zenoh keys)")
    run_dir = Path(args.runs_dir) / name
    _fill_launch_defaults(args, run_dir)
    recordings = getattr(args, "from_recordings", [])
    if args.actors < (0 if recordings else 1):
        raise RomannetError(f"--actors {args.actors}: at least one actor is needed (or 0 with --from-recordings)")
    if args.actors == 0 and args.max_actions:
        raise RomannetError("--max-actions counts actors' actions: with --actors 0 the run goes until Ctrl-C")
    for path in recordings:
        if not Path(path).exists():
            raise RomannetError(f"--from-recordings {path}: no such file or directory")
    if args.max_actions < 0 or (0 < args.max_actions < args.actors):
        raise RomannetError(f"--max-actions {args.max_actions}: use 0 (no limit) or at least one action per "
                            f"actor (>= {args.actors})")
    saved = run_dir / "config.toml"
    overrides = [*args.overrides, *_flag_overrides(args), f'run_id="{name}"']
    if args.resume:
        if not saved.is_file():
            raise RomannetError(f"--resume: {saved} does not exist (is --name {name} a run in {args.runs_dir}?)")
        if args.config is not None:
            raise RomannetError("--resume uses the run's saved config.toml; change it with --set, not --config")
        _check_not_running(run_dir)
        _check_replay_free(run_dir)
        _check_actor_states(run_dir, args.actors)
        _warn_left_spools(run_dir, args.actors)
        before = load_saved_config(saved)
        cfg = load_saved_config(saved, overrides)
        if cfg.workspace != before.workspace:
            raise RomannetError("--resume cannot change the workspace or --resolution: the replay holds "
                                f"{before.workspace.height_px}x{before.workspace.width_px} transitions")
    else:
        if run_dir.exists() and any(run_dir.iterdir()):
            raise RomannetError(f"{run_dir} already exists: pass --resume to continue that run, or another --name")
        cfg = load_config(args.config, overrides)
    if recordings:
        check_prefill(cfg.replay)
    run_dir.mkdir(parents=True, exist_ok=True)
    write_toml(cfg, saved)
    write_json_atomic(run_dir / LAUNCH_FILE, {"actors": args.actors, "max_actions": args.max_actions})
    return run_dir, cfg


def _fill_launch_defaults(args: argparse.Namespace, run_dir: Path) -> None:
    """--actors / --max-actions not given: the run's last launch's (launch.json) with --resume, else 2 / 0."""
    last: dict[str, object] = {}
    if args.resume and (run_dir / LAUNCH_FILE).is_file():
        try:
            last = json.loads((run_dir / LAUNCH_FILE).read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise RomannetError(f"{run_dir / LAUNCH_FILE} cannot be read ({exc}): pass --actors and --max-actions "
                                "(the file only holds their last values)") from None
    taken = []
    for flag, attr, default in (("--actors", "actors", 2), ("--max-actions", "max_actions", 0)):
        if getattr(args, attr, None) is not None:
            continue
        value = last.get(attr) if isinstance(last, dict) else None
        if isinstance(value, int) and not isinstance(value, bool):
            setattr(args, attr, value)
            taken.append(f"{flag} {value}")
        else:
            setattr(args, attr, default)
    if taken:
        log.info("resuming with %s, as the run's last launch (%s); pass them to change", " ".join(taken),
                 run_dir / LAUNCH_FILE)


def _check_not_running(run_dir: Path) -> None:
    """Refuse to resume a run whose launcher is still alive (two fleets would share one directory)."""
    try:
        pid = int(json.loads((run_dir / "pids.json").read_text())["launcher"])
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
    except (OSError, ValueError, KeyError, TypeError):
        return
    if pid != os.getpid() and b"romannet" in cmdline:
        raise RomannetError(f"{run_dir} is in use by a running `romannet up` (pid {pid}); stop it first")


def _check_replay_free(run_dir: Path) -> None:
    """Refuse a run whose replay directory a replay server holds (started by hand, or left by a launcher
    that died): the fleet's own replay server would stop at its lock and crash-loop."""
    check_not_locked(run_dir / "replay", "replay directory")


def _check_actor_states(run_dir: Path, actors: int) -> None:
    """Refuse a resume where an actor's state.json is damaged (EpisodeStateError, one line naming it):
    that actor would exit at once and crash-loop until the launcher gave up on it."""
    from romannet.actor.episode_state import read_next_episode

    for i in range(actors):
        read_next_episode(run_dir / "actors" / f"actor-{i}" / "state.json", run_dir / "episodes" / f"actor-{i}")


def _warn_left_spools(run_dir: Path, actors: int) -> None:
    """Actors beyond --actors are not started: say so if their spools still hold unsent transitions."""
    for spool in sorted((run_dir / "actors").glob("*/spool")):
        actor_id = spool.parent.name
        index = actor_id.removeprefix("actor-")
        pending = sum(1 for p in spool.iterdir() if p.is_file()) if spool.is_dir() else 0
        if index.isdigit() and int(index) >= actors and pending:
            log.warning("%s is not started (--actors %d) but its spool holds %d file(s) not yet acknowledged: "
                        "resume with --actors %d to send them", actor_id, actors, pending, int(index) + 1)
