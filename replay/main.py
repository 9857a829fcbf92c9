"""`romannet replay`: run the replay server in the foreground until SIGTERM or SIGINT.

    romannet replay --config run.toml --dir runs/run-1/replay --listen tcp/127.0.0.1:7447
    romannet replay --check runs/run-1/replay     # read and check every held item; exit 1 on damage

If recovery finds acknowledged items it cannot get back, the server refuses to start (one line with the
count and ids) until started with --accept-loss, which records the loss in DIR/losses.json (losses.py).

The TOML file is the fleet config (configs/default.toml): run_id picks the keys, [workspace] the
heightmap size every transition must have, [replay] the buffer (common/config_replay.py). A signal
sets a stop event; the server then stops taking queries, finishes queued work, snapshots, closes the
store and the session, and the process exits 0.
"""

from __future__ import annotations

import argparse
import logging
import threading
from pathlib import Path

from romannet.common.config import Config, load_config
from romannet.common.config_replay import ReplayConfig
from romannet.common.signals import stop_on_signals
from romannet.common.zenoh_limits import limit_messages, replay_receive_limit
from romannet.common.zenoh_session import make_config

from .check import run_check
from .server import ServerLimits, run_replay_server

log = logging.getLogger(__name__)


def load_replay_config(path: str | Path | None, overrides: list[str]) -> tuple[Config, ReplayConfig]:
    """(fleet config, its replay section) from the TOML file and `section.field=value` overrides."""
    config = load_config(path, overrides)
    return config, config.replay


def run(args: argparse.Namespace) -> int:
    """Run the server (or --check) for parsed CLI arguments (see romannet/cli.py); returns the exit code."""
    if args.check:
        return run_check(Path(args.check))
    if not args.dir:
        raise ValueError("--dir DIR is required (or --check DIR to check a replay directory)")
    config, replay_cfg = load_replay_config(args.config, args.overrides)
    zenoh_config = make_config(args.zenoh_config, listen=args.listen or None, connect=args.connect or None)
    # Zenoh drops a larger message on arrival, before it holds more than this of it.
    limit_messages(zenoh_config, replay_receive_limit(replay_cfg.max_item_bytes), "replay server")
    ws = config.workspace
    limits = ServerLimits(max_insert_bytes=replay_cfg.max_item_bytes,
                          expected_shape=(ws.height_px, ws.width_px),
                          decode_pixels=not args.skip_pixel_decode)
    stop = threading.Event()

    with stop_on_signals(stop, "shutting down"):
        Path(args.dir).mkdir(parents=True, exist_ok=True)
        run_replay_server(replay_cfg, args.dir, zenoh_config, stop, run_id=config.run_id, limits=limits,
                          accept_loss=args.accept_loss,
                          ready=lambda server: log.info("replay server ready (run %s, dir %s)",
                                                        config.run_id, args.dir))
    return 0
