"""`romannet up`: the whole fleet on one machine (replay server, learner, N actors) until done or Ctrl-C.

    romannet up --config configs/experiments/clutter.toml --actors 2 --max-actions 2000
    romannet up --name run-1 --resume
    romannet up --name offline-1 --actors 0 --from-recordings runs/run-1/episodes \
        --set replay.samples_per_insert=0   (learner/offline.py)
    romannet up --name ft-1 --config models/clutter/config.toml --init-from models/clutter
    romannet up --foxglove 8765    (each actor live in the Foxglove app: romannet/mcaptools/live.py)

Each component runs as its own process (`python -m romannet.cli <verb> ...`: a fresh interpreter, so no
Zenoh session crosses a fork), with its own Zenoh session in peer mode on loopback and multicast
scouting off: the replay server and the learner listen on free loopback ports and every process connects
to those, so discovery needs no multicast. This module only starts processes and reads their outputs;
it never imports actor, learner or replay code (--init-from's weights are checked by a `romannet models
check --init` process before anything starts; the learner starts from them while the run has no checkpoint).

The run directory `<runs-dir>/<name>/` holds (config.toml is written first, before any child starts):

    config.toml           the resolved config every child reads (run_id = the run's name)
    launcher.log          this launcher's log; logs/<child>.log each child's output
    pids.json             the launcher's and each child's current pid
    replay/               the replay server's log segments and snapshots
    checkpoints/ metrics.csv tensorboard/ learning_curves.png    the learner's
    training_curves.png tensorboard/episodes/   success, completion, return, length, actions/s over actions
    actors/<id>/status.json  episodes/<id>/*.mcap                 each actor's
    actors/ledger.json    each actor's totals over the run's launches and restarts (what --max-actions counts)
    launch.json           this launch's --actors and --max-actions (a --resume's defaults)
    summary.json          the run's totals at exit

Stopping (Ctrl-C, SIGTERM, SIGHUP, or every actor reaching its share of --max-actions): actors first
(they finish the primitive under way, flush spool and MCAP), then the learner (checkpoint), then the
replay server (snapshot); each gets --stop-timeout seconds before SIGKILL. A second Ctrl-C kills the rest
at once. Children sit in their own process groups and get SIGTERM if the launcher dies
(romannet/supervisor.py), so none outlives it. Exit code 0 when every child stopped cleanly (exit 0),
1 if the supervisor gave up on a crash-looping child or a child's last run did not end cleanly (a crash,
also one while another group was being stopped; a service that exited before it was asked; SIGKILL after
the timeout): summary.json's "unclean" names each such child and how it ended; its "unclean_ends" lists
every unclean end in order, also a crash a restart recovered from (which alone leaves the exit code 0).
2 for bad arguments.
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from romannet.common.config_pacing import transitions_before_first_update
from romannet.common.fsutil import write_json_atomic

from .fleet import ActorLedger, FleetProgress, FleetSnapshot, fleet_fields, read_actor_statuses
from .progress import ClearLineFilter, Progress
from .rundir import prepare_run
from .supervisor import ChildSpec, RestartPolicy, Supervisor

if TYPE_CHECKING:
    from romannet.common.config import Config

log = logging.getLogger("romannet.up")

# Stop ranks: lower stops first.
ACTOR_RANK, LEARNER_RANK, REPLAY_RANK = 0, 1, 2
LEDGER_FILE = "ledger.json"  # <run>/actors/: each actor's totals over the run's launches (progress.ActorLedger)
STAGE_TIMEOUT_S = 180.0  # how long a stage of the start-up may take to come alive before the next starts


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The `up` verb's flags (romannet/cli.py adds --config/--set). This module imports only the standard
    library at the top, so building the CLI parser stays fast."""
    p.add_argument("--name", help="run name: the directory <runs-dir>/<name> and the run id of every Zenoh "
                   "key (default: run-<date>-<time>)")
    p.add_argument("--runs-dir", default="runs", metavar="DIR", help="where run directories live (default: runs)")
    p.add_argument("--task", choices=["clutter", "arrangement", "stacking"], help="task (default: the config's, "
                   "clutter)")
    p.add_argument("--goal-height", type=int, metavar="N", help="stacking: cubes in the goal stack (2..5)")
    p.add_argument("--actors", type=int, metavar="N", help="simulated actors (default: 2, or with --resume the "
                   "run's last launch's; 0 with --from-recordings: train on the recordings only)")
    p.add_argument("--from-recordings", action="append", default=[], metavar="FILE|DIR",
                   help="pre-fill the replay server with these MCAP episode recordings (the learner feeds them, "
                   "acknowledged and idempotent, before it trains); with actors, recorded and live experience "
                   "mix (repeatable). A damaged file costs only its damaged chunks and a file that is not an "
                   "episode is skipped, each named in one line of logs/learner.log; the run goes on. Needs "
                   "--set replay.samples_per_insert=0 (no ratio limit)")
    p.add_argument("--max-actions", type=int, metavar="N",
                   help="total actions of the run over the whole fleet, split evenly between the actors; the "
                   "launcher stops everything cleanly when every actor has done its share; with --resume "
                   "the actions of earlier launches count (default: 0 = until Ctrl-C, or with --resume the "
                   "run's last launch's)")
    p.add_argument("--resolution", type=float, metavar="M_PER_PX", help="heightmap resolution in metres per "
                   "pixel over the 0.448 m workspace: 0.002 -> 224x224 (default), 0.007 -> 64x64")
    p.add_argument("--robot", choices=["arm", "gripper"], help="simulated robot: the Panda arm (default) or "
                   "a floating gripper (faster)")
    p.add_argument("--resume", action="store_true", help="restart every component from the run directory: "
                   "the learner from its checkpoint, the replay from its log, actors resend their spools")
    p.add_argument("--init-from", metavar="DIR", help="start the learner from these weights: a model package "
                   "(models/<experiment>), a run or a checkpoint directory (update 0, fresh optimiser; the [model] "
                   "section must match; checked before anything starts)")
    p.add_argument("--stop-timeout", type=float, default=60.0, metavar="S",
                   help="seconds each stage may take to stop cleanly before SIGKILL (default: 60)")
    p.add_argument("--progress-every", type=float, default=30.0, metavar="S",
                   help="seconds between progress lines when stderr is not a terminal (default: 30)")
    p.add_argument("--foxglove", type=int, metavar="PORT", help="serve every actor's camera, heightmaps, Q maps "
                   "and chosen action live to the Foxglove app on PORT (topics /<actor-id>/...; 0: any free port)")
    p.add_argument("--foxglove-host", default="127.0.0.1", metavar="HOST",
                   help="address the live view binds (default 127.0.0.1; 0.0.0.0 for other machines)")


def split_actions(total: int, actors: int) -> list[int]:
    """total split into `actors` near-equal shares (the first ones take the remainder); 0 = unlimited."""
    if total <= 0 or actors <= 0:
        return [0] * max(actors, 0)
    base, extra = divmod(total, actors)
    return [base + (1 if i < extra else 0) for i in range(actors)]


def actor_shares(max_actions: int, done: int, actors: int) -> list[int]:
    """Each actor's --max-actions for this launch: what is left of the run's max_actions after the `done`
    actions of earlier launches, split evenly; at least 1 each (an actor started at all has to flush its
    spool, and 0 would mean no limit). All 0 (no limit) when max_actions is 0."""
    if max_actions <= 0:
        return [0] * max(actors, 0)
    return [max(1, share) for share in split_actions(max(0, max_actions - done), actors)]


def thread_plan(cores: int, actors: int) -> dict[str, int]:
    """Torch threads per child so that the fleet's compute threads add up to the machine's cores.

    The learner and the actors each default to one thread per core; on one machine they then oversubscribe
    it, and OpenMP's spinning threads wait on each other at every convolution's barrier: on 2 cores a
    learner step and an actor decision, side by side, took 10.8 s and 1.0 s with 2 threads each and 2.2 s
    and 0.64 s with 1 thread each (docs/benchmarks.md, "Sharing the cores"). Each actor gets an equal share,
    the learner the rest, every child at least 1; the replay server computes little and gets 1."""
    actor_threads = max(1, cores // (actors + 1))
    return {"replay": 1, "actor": actor_threads, "learner": max(1, cores - actors * actor_threads)}


def _threads_env(n: int) -> dict[str, str]:
    # torch reads OMP_NUM_THREADS for its default; a config's explicit num_threads still wins.
    return {"OMP_NUM_THREADS": str(n)}


def build_specs(run_dir: Path, cfg: Config, args: argparse.Namespace, replay_ep: str, learner_ep: str,
                ledger: ActorLedger) -> list[ChildSpec]:
    """The replay server, the learner and the actors as supervised children.

    An actor's --max-actions counts the actions of its process. The run's --max-actions less what earlier
    launches did (the ledger at its mark_start) is split between the actors; a restarted actor gets what is
    left of its share (ledger: what its earlier processes of this launch did), so the run's total stays
    --max-actions."""
    base = [sys.executable, "-m", "romannet.cli"]
    level = logging.getLevelName(logging.getLogger().getEffectiveLevel())
    if isinstance(level, str):
        base += ["--log-level", level]
    config = str(run_dir / "config.toml")
    logs = run_dir / "logs"
    stop_s = args.stop_timeout

    def learner_argv() -> list[str]:
        # A (re)start over a checkpoint must resume it: the learner refuses to start fresh over one (intact
        # or not; it resumes from the newest intact one, or starts fresh saying so when none is).
        ckpts = run_dir / "checkpoints"
        resume = ["--resume"] if (ckpts / "LATEST").is_file() or any(ckpts.glob("ckpt-*")) else []
        recordings = getattr(args, "from_recordings", [])
        offline = [arg for path in recordings for arg in ("--offline", str(Path(path).resolve()))]
        init_from = getattr(args, "init_from", None)
        init = ["--init-from", str(Path(init_from).resolve())] if init_from and not resume else []
        return [*base, "learner", "--config", config, "--run-dir", str(run_dir), "--listen", learner_ep,
                "--connect", replay_ep, *resume, *offline, *init]

    threads = thread_plan(os.cpu_count() or 1, args.actors)
    specs = [
        ChildSpec("replay", [*base, "replay", "--config", config, "--dir", str(run_dir / "replay"),
                             "--listen", replay_ep], stop_rank=REPLAY_RANK, restart="always",
                  stop_timeout_s=stop_s, log_path=logs / "replay.log", env=_threads_env(threads["replay"])),
        ChildSpec("learner", learner_argv, stop_rank=LEARNER_RANK, restart="always", stop_timeout_s=stop_s,
                  log_path=logs / "learner.log", env=_threads_env(threads["learner"])),
    ]
    for i, share in enumerate(actor_shares(args.max_actions, ledger.start_total(), args.actors)):
        actor_id = f"actor-{i}"

        def actor_argv(actor_id: str = actor_id, share: int = share) -> list[str]:
            argv = [*base, "actor", "--config", config, "--run-dir", str(run_dir), "--actor-id", actor_id,
                    "--connect", replay_ep, "--connect", learner_ep]
            if share:  # at least 1: a process that crashed after its last action still has to flush
                argv += ["--max-actions", str(max(1, share - ledger.this_start(actor_id)))]
            return argv

        specs.append(ChildSpec(actor_id, actor_argv, stop_rank=ACTOR_RANK, restart="on-failure",
                               stop_timeout_s=stop_s, log_path=logs / f"{actor_id}.log",
                               env=_threads_env(threads["actor"])))
    return specs


class _ReplayStatsPoller:
    """Asks the replay server for its stats every period_s on a thread of its own, so an unreachable
    server (a query waits out its timeout) never stalls supervision; `latest()` never blocks."""

    def __init__(self, client: Any, period_s: float = 2.0, timeout_s: float = 1.5):
        self._client, self._period_s, self._timeout_s = client, period_s, timeout_s
        self._latest: dict[str, Any] | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="replay-stats", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                self._latest = self._client.stats(timeout_s=self._timeout_s)
            except Exception as exc:  # a replay restarting or stopping: keep the last known numbers
                log.debug("replay stats: %s", exc)
            self._stop.wait(self._period_s)

    def latest(self) -> dict[str, Any] | None:
        return self._latest

    def close(self) -> None:
        self._stop.set()
        self._thread.join(self._timeout_s + 5.0)


class _Signals:
    """Counts SIGINT/SIGTERM/SIGHUP: the first asks for a clean stop, the second for SIGKILL of the rest."""

    def __init__(self) -> None:
        self.count = 0
        self._previous = {s: signal.signal(s, self._on) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}

    def _on(self, signum: int, _frame: object) -> None:
        self.count += 1
        if self.count == 1:
            log.info("received %s: stopping cleanly (actors, learner, replay; again to kill at once)",
                     signal.Signals(signum).name)
        else:
            log.warning("received %s again: killing what is left", signal.Signals(signum).name)

    def restore(self) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)


def _attach_log_file(path: Path) -> logging.Handler:
    handler = logging.FileHandler(path)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logging.getLogger().addHandler(handler)
    return handler


def init_check_argv(args: argparse.Namespace) -> list[str]:
    """The `romannet models check --init` command that checks --init-from against the run's [model] (which
    only --config and --set decide), so a bad source is one line here rather than a learner crash loop."""
    argv = [sys.executable, "-m", "romannet.cli", "--log-level", "WARNING", "models", "check", "--init",
            str(args.init_from)]
    if args.config is not None:
        argv += ["--config", str(args.config)]
    return argv + [arg for text in args.overrides for arg in ("--set", text)]


def check_init_from(args: argparse.Namespace) -> None:
    """RomannetError (the check's own line) unless --init-from can start this run; nothing without it."""
    import subprocess

    from romannet.common.errors import RomannetError

    if not getattr(args, "init_from", None):
        return
    if args.resume:
        raise RomannetError("--init-from starts a new run from other weights, --resume continues this run's "
                            "checkpoint: pass one of them")
    done = subprocess.run(init_check_argv(args), capture_output=True, text=True, timeout=300)
    if done.returncode != 0:
        lines = [ln for ln in done.stderr.splitlines() if ln.strip()] or [f"exit code {done.returncode}"]
        raise RomannetError(lines[-1].removeprefix("romannet models: error: "))
    log.info("%s", done.stdout.strip())


def run(args: argparse.Namespace) -> int:
    """Run the fleet for parsed CLI arguments (romannet/cli.py); returns the exit code."""
    from romannet.common.keys import RunKeys
    from romannet.common.replay_client import ZenohReplayClient
    from romannet.common.zenoh_session import free_port, make_config, open_session, wait_for_liveliness
    from romannet.evaluate.run_curves import curve_window
    from romannet.evaluate.run_report import LiveRunReport

    check_init_from(args)
    live = None
    if getattr(args, "foxglove", None) is not None:  # a thread of the launcher reading the files actors write
        from romannet.mcaptools.live import LiveView, announce_live_view, run_folders

        # Bound before the run directory exists: a port in use is one line and leaves no half-made run that
        # the corrected command would be refused for.
        live = LiveView(dict, args.foxglove, args.foxglove_host)
    try:
        run_dir, cfg = prepare_run(args)
        ledger = ActorLedger.load(run_dir / "actors" / LEDGER_FILE)  # a fresh run has none yet
        if args.resume:
            for name, status in read_actor_statuses(run_dir).items():  # the last launch's processes
                ledger.retire(name, status)
        ledger.mark_start()
    except BaseException:
        if live is not None:
            live.close()
        raise
    if args.max_actions and ledger.start_total() >= args.max_actions:
        log.info("run %s already has %d actions (--max-actions %d): nothing to do; raise --max-actions to "
                 "train on", run_dir.name, ledger.start_total(), args.max_actions)
        if live is not None:
            live.close()
        return 0
    if live is not None:
        live.follow(run_folders(run_dir / "episodes"))
        announce_live_view(live, args.foxglove_host, f"run {run_dir.name}")
    file_handler = _attach_log_file(run_dir / "launcher.log")
    display = Progress("up", total=args.max_actions or None, unit="actions", log_every_s=args.progress_every,
                       redraw_s=1.0)
    console = [h for h in logging.getLogger().handlers if isinstance(h, logging.StreamHandler)
               and not isinstance(h, logging.FileHandler)]
    clear = ClearLineFilter(display)
    for h in console:
        h.addFilter(clear)
    if os.environ.pop("ROMANNET_ZENOH_CONFIG", None):  # children inherit os.environ when they start
        log.info("ignoring $ROMANNET_ZENOH_CONFIG: `romannet up` runs the fleet on this machine (peer mode on "
                 "loopback); use the service verbs with a router for several machines (docs/deploy.md)")
    replay_ep, learner_ep = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    log.info("run %s in %s (%s task, %dx%d px, %s robot, %d actor(s), max actions %s%s); replay on %s, "
             "learner on %s", cfg.run_id, run_dir, cfg.task.kind, cfg.workspace.height_px, cfg.workspace.width_px,
             cfg.sim.robot, args.actors, args.max_actions or "unlimited", ", resumed" if args.resume else "",
             replay_ep, learner_ep)
    if ledger.start_total():
        log.info("the run's earlier launches made %d actions; --max-actions counts them", ledger.start_total())
    first_update = transitions_before_first_update(cfg.replay, cfg.learner)
    if args.max_actions and args.max_actions < first_update:
        log.warning("this run will not train: the learner's first update needs %d transitions in replay "
                    "(replay.min_size_to_sample, learner.min_replay_size) and --max-actions is %d; run longer or "
                    "lower both with --set", first_update, args.max_actions)

    def on_exit(name: str, _code: int) -> None:
        if sup.children[name].spec.stop_rank == ACTOR_RANK:  # bank its counts before a restart resets them
            ledger.retire(name, read_actor_statuses(run_dir).get(name))

    pids: dict[str, int] = {}

    def on_start(name: str, pid: int) -> None:  # pids.json: which process is which, for people and tests
        pids[name] = pid
        write_json_atomic(run_dir / "pids.json", {"launcher": os.getpid(), **pids})

    sup = Supervisor(build_specs(run_dir, cfg, args, replay_ep, learner_ep, ledger), RestartPolicy(),
                     on_exit=on_exit, on_start=on_start)
    signals = _Signals()
    started = time.monotonic()
    outcome = "stopped"
    final: dict[str, Any] | None = None
    progress = FleetProgress(run_dir, ledger=ledger)
    report = LiveRunReport(run_dir, curve_window(args.max_actions or 0))  # training_curves.png, tensorboard/episodes
    try:
        with open_session(make_config(listen=[], connect=[replay_ep, learner_ep])) as session:
            client = ZenohReplayClient(session, cfg.run_id)
            poller = _ReplayStatsPoller(client)
            try:
                progress = FleetProgress(run_dir, poller.latest, ledger=ledger)
                keys = RunKeys(cfg.run_id)
                ready = {"replay": lambda: client.wait_until_ready(0.5),
                         "learner": lambda: wait_for_liveliness(session, keys.learner_alive, 0.5)}
                outcome = _supervise(sup, ready, signals, progress, display)
                display.clear()
                sup.stop_rank(ACTOR_RANK, hurry=lambda: signals.count > 1)
                sup.stop_rank(LEARNER_RANK, hurry=lambda: signals.count > 1)
                final = _final_stats(client, sup)
            finally:
                poller.close()
                sup.stop_all(hurry=lambda: signals.count > 1)
    except BaseException:
        sup.kill_all()  # the launcher itself failed: leave no child behind
        raise
    finally:
        signals.restore()
        display.clear()
        for h in console:
            h.removeFilter(clear)
        report.close()  # after the actors stopped: the curves end with every recorded action
        if live is not None:
            live.close()
    _summary(run_dir, progress.snapshot(), final, sup, outcome, time.monotonic() - started, ledger.start_total(),
             first_update)
    log.info("curves of run %s: %s (what the robot did), %s (the learner); live: tensorboard --logdir %s",
             run_dir.name, run_dir / "training_curves.png", run_dir / "learning_curves.png", run_dir.parent)
    unclean = sup.unclean()
    if unclean:
        log.warning("not every child stopped cleanly: %s (see %s)",
                    "; ".join(f"{n}: {how}" for n, how in unclean.items()), run_dir / "logs")
    logging.getLogger().removeHandler(file_handler)
    file_handler.close()
    return 1 if sup.gave_up or unclean else 0


def _supervise(sup: Supervisor, ready: dict[str, Callable[[], bool]], signals: _Signals,
               progress: FleetProgress, display: Progress) -> str:
    """Start the fleet and watch it until it is done, asked to stop, or a child crash-loops."""
    # In stages, each waiting (bounded) for the previous one's liveliness token: the replay, the learner,
    # then the actors. All of them cope with a peer that is not there yet, but actors that start first
    # spend their first actions on the initial weights, and a 2-core box starts faster when the
    # interpreters do not all import torch at the same moment.
    for name in ("replay", "learner"):
        sup.start(name)
        deadline = time.monotonic() + STAGE_TIMEOUT_S
        while not ready[name]():
            sup.poll()
            if signals.count:
                return "stopped_by_signal"
            if sup.gave_up:
                return f"gave_up_on_{sup.gave_up[0]}"
            if time.monotonic() > deadline:
                log.warning("%s not ready after %.0f s: starting the rest anyway", name, STAGE_TIMEOUT_S)
                break
    sup.start_all([n for n, c in sup.children.items() if c.spec.stop_rank == ACTOR_RANK])
    actors = [n for n, c in sup.children.items() if c.spec.stop_rank == ACTOR_RANK]
    next_draw = 0.0
    while True:
        sup.poll()
        if signals.count:
            return "stopped_by_signal"
        if sup.gave_up:
            return f"gave_up_on_{sup.gave_up[0]}"
        if actors and all(sup.children[a].state == "done" for a in actors):
            log.info("every actor finished its share of --max-actions: stopping the learner and the replay")
            return "max_actions_reached"
        now = time.monotonic()
        if now >= next_draw:
            snap = progress.snapshot()
            display.update(snap.actions, fleet_fields(snap))
            next_draw = now + 1.0
        time.sleep(0.2)


def _final_stats(client: Any, sup: Supervisor) -> dict[str, Any] | None:
    """The replay's stats once actors and learner are stopped (nothing more will arrive)."""
    if not sup.children["replay"].alive():
        return None
    try:
        return client.stats(timeout_s=10.0)
    except Exception as exc:  # a replay that is restarting right now: the summary says so
        log.warning("could not read the replay's final stats: %s", exc)
        return None


def _summary(run_dir: Path, snap: FleetSnapshot, replay: dict[str, Any] | None, sup: Supervisor, outcome: str,
             elapsed_s: float, earlier_actions: int = 0, first_update: int = 0) -> dict[str, Any]:
    """Log the run's totals (all launches; actions also this launch's) and write them to summary.json.
    first_update: transitions the learner needs before its first update (named when it made none)."""
    summary = {
        "run_dir": str(run_dir), "outcome": outcome, "elapsed_s": round(elapsed_s, 1),
        "actions": snap.actions, "actions_this_launch": snap.actions - earlier_actions, "episodes": snap.episodes,
        "completed_episodes": snap.completed_episodes,
        "pick_success": snap.successful_picks / snap.picks if snap.picks else None,
        "efficiency": snap.efficiency, "learner_updates": snap.updates or 0, "trained": bool(snap.updates),
        "learner_explore_rate": snap.learner_explore_rate, "acked": snap.acked, "spooled": snap.spooled,
        "replay_size": replay.get("size") if replay else snap.replay_size,
        "replay_inserts": replay.get("inserts") if replay else snap.replay_inserts,
        "replay_duplicates": replay.get("duplicates") if replay else None,
        "restarts": sup.crashes, "gave_up": sup.gave_up,
        "exit_codes": {n: c.last_exit for n, c in sup.children.items()},
        "unclean": sup.unclean(),  # child -> how its last run ended, for each that did not stop cleanly
        # Every unclean end in order, also those a restart recovered from (the exit code stays 0 for them).
        "unclean_ends": [{"child": name, "how": how} for name, how in sup.ends],
        "actors": {aid: {k: s.get(k) for k in ("actions", "episodes", "completed_episodes", "picks",
                                                "successful_picks", "weights_version", "explore_rate",
                                                "sent", "acked", "spool_items", "last_done_reason")}
                   for aid, s in snap.actors.items()},
    }
    write_json_atomic(run_dir / "summary.json", summary, indent=2)
    pick = "-" if summary["pick_success"] is None else f"{100 * summary['pick_success']:.1f}%"
    log.info("run %s %s after %.0f s: %d actions (%d in this launch), %d episodes (%d completed), pick "
             "success %s, %s learner updates, replay holds %s (acked by actors: %d, still spooled: %d), "
             "%d restart(s); summary in %s",
             run_dir.name, outcome.replace("_", " "), elapsed_s, snap.actions, summary["actions_this_launch"],
             snap.episodes, snap.completed_episodes, pick, summary["learner_updates"],
             summary["replay_size"], snap.acked, snap.spooled, sup.crashes, run_dir / "summary.json")
    if not snap.updates:
        log.warning("run %s did not train: the learner made no update (its first needs %d transitions in replay, "
                    "replay.min_size_to_sample and learner.min_replay_size; the replay holds %s): its checkpoints "
                    "and curves are the untrained net's", run_dir.name, first_update, summary["replay_size"])
    return summary
