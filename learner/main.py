"""`romannet learner`: train in the foreground until SIGTERM or SIGINT.

    romannet learner --config run.toml --run-dir runs/run-1 --connect tcp/127.0.0.1:7447
    romannet learner --run-dir runs/run-1 --resume --connect tcp/127.0.0.1:7447
    romannet learner --config run.toml --run-dir runs/off-1 --offline recordings/ --max-updates 2000 ...
    romannet learner --config run.toml --run-dir runs/ft-1 --init-from models/clutter --connect ...

The TOML file is the fleet config (configs/default.toml): run_id picks the keys, [workspace] the heightmap
size every sampled transition must have, [learner] the training (common/config_learner.py). With --resume
and no --config, the run directory's saved config.toml is used (plus any --set overrides), so a resumed run
trains what the interrupted one did. --offline DIR feeds MCAP episode recordings to the replay server
first (learner/offline.py); --max-updates N stops at update N as a signal would. --init-from DIR starts a
new run from a model package's, a run's or a checkpoint's weights (learner/checkpoint.py), checked before
the session opens. A signal sets a stop event; the learner finishes the step under way, publishes its
weights, writes a checkpoint, closes the session, and the process exits 0.
"""

from __future__ import annotations

import argparse
import logging
import threading
from pathlib import Path

from romannet.common.config import Config, load_config
from romannet.common.config_pacing import check_prefill
from romannet.common.errors import RomannetError
from romannet.common.signals import stop_on_signals
from romannet.common.zenoh_limits import learner_receive_limit, limit_messages
from romannet.common.zenoh_session import make_config, open_session

from .batches import TolerantReplayClient
from .checkpoint import read_init_weights
from .ckpt_integrity import checkpoint_candidates
from .offline import prefill
from .service import ServiceOptions, run_learner

log = logging.getLogger(__name__)


def resolve_config(config_path: str | None, overrides: list[str], run_dir: Path, resume: bool) -> Config:
    """The run's config: --config, else (on --resume) the run directory's config.toml, else defaults."""
    saved = run_dir / "config.toml"
    if config_path is None and resume:
        if not saved.is_file():
            raise RomannetError(f"--resume: {saved} does not exist: is {run_dir} a learner run directory? "
                                "(pass --config to resume with another config)")
        config_path = str(saved)
    return load_config(config_path, overrides)


def check_run_dir(run_dir: Path, resume: bool) -> None:
    """Refuse what would silently go wrong: --resume without a checkpoint, or a fresh start over one (intact
    or damaged: its names would be reused). A resume whose checkpoints are all damaged starts fresh, saying so."""
    existing = checkpoint_candidates(run_dir)
    if resume and not existing:
        raise RomannetError(f"--resume: {run_dir} holds no checkpoint to resume from")
    if not resume and existing:
        raise RomannetError(f"--run-dir {run_dir} already holds checkpoint {existing[0].name}: pass --resume to "
                            "continue that run, or choose a new --run-dir")


def run(args: argparse.Namespace) -> int:
    """Run the learner for parsed CLI arguments (see romannet/cli.py); returns the exit code."""
    run_dir = Path(args.run_dir)
    init_from = getattr(args, "init_from", None)
    if init_from and args.resume:
        raise RomannetError("--init-from starts a new run from other weights, --resume continues this run's "
                            "checkpoint: pass one of them")
    check_run_dir(run_dir, args.resume)
    config = resolve_config(args.config, args.overrides, run_dir, args.resume)
    if getattr(args, "offline", None):
        check_prefill(config.replay)
    init_weights = None
    if init_from:
        init_weights, what = read_init_weights(init_from, config.model)
        log.info("starting from the weights of %s", what)
    zenoh_config = make_config(args.zenoh_config, listen=args.listen or None, connect=args.connect or None)
    # A sample batch is the largest thing a learner receives; Zenoh drops anything larger on arrival.
    limit_messages(zenoh_config, learner_receive_limit(config.learner.batch_size, config.replay.max_item_bytes),
                   "learner")
    ws = config.workspace
    stop = threading.Event()

    with stop_on_signals(stop, "finishing the current step, then checkpoint and exit"):
        with open_session(zenoh_config) as session:
            client = TolerantReplayClient(session, config.run_id, expected_shape=(ws.height_px, ws.width_px),
                                          max_insert_bytes=config.replay.max_item_bytes)
            if getattr(args, "offline", None):
                prefill(client, args.offline, stop)
            options = ServiceOptions(max_updates=max(0, getattr(args, "max_updates", 0) or 0))
            run_learner(config, run_dir, client, session, stop, resume=args.resume, options=options,
                        init_weights=init_weights,
                        ready=lambda trainer: log.info("learner ready (run %s, dir %s, update %d)",
                                                       config.run_id, run_dir, trainer.updates))
    return 0
