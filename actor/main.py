"""`romannet actor`: act in the foreground until SIGTERM / SIGINT or a limit, then exit 0.

    romannet actor --config run.toml --run-dir runs/run-1 --actor-id actor-0 --connect tcp/127.0.0.1:7447

The TOML file is the fleet config (configs/default.toml): run_id picks the keys, [task] [sim] [workspace]
the simulated scene, [model] [exploration] the policy, [actor] this process (common/config_actor.py).
--actor-id / --max-actions / --episodes override the [actor] values, so one file serves a whole fleet.

The environment sits behind common.interfaces.Env (SimEnv now; a real robot later plugs in here). A signal
sets the stop event; the actor finishes the primitive under way, spools and records it, finishes the MCAP
file, gives the sender actor.shutdown_flush_s to empty the spool, drops its liveliness token and closes the
session.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import threading
from pathlib import Path

from romannet.common.config import Config, load_config
from romannet.common.config_actor import ActorConfig
from romannet.common.configbase import write_toml
from romannet.common.keys import RunKeys
from romannet.common.model import RoManNet, validate_tensors
from romannet.common.policy import InferenceEngine
from romannet.common.replay_client import ZenohReplayClient
from romannet.common.signals import stop_on_signals
from romannet.common.weights_client import ZenohWeightsSource
from romannet.common.zenoh_session import make_config, open_session

from .service import ActorPaths, actor_section, run_actor

log = logging.getLogger(__name__)


def resolve_actor_config(cfg: Config, args: argparse.Namespace) -> ActorConfig:
    """The [actor] section with the command line's --actor-id / --max-actions / --episodes applied."""
    changes = {name: value for name, value in (("actor_id", args.actor_id), ("max_actions", args.max_actions),
                                               ("episodes", args.episodes)) if value is not None}
    return dataclasses.replace(actor_section(cfg), **changes)  # validated again by __post_init__


def run(args: argparse.Namespace) -> int:
    """Run one actor for parsed CLI arguments (see romannet/cli.py); returns the exit code."""
    cfg = load_config(args.config, args.overrides)
    acfg = resolve_actor_config(cfg, args)
    run_dir = Path(args.run_dir)
    paths = ActorPaths.of(run_dir, acfg)
    write_toml(cfg, paths.root / "config.toml")  # what this actor ran with (also in every MCAP file)
    zenoh_config = make_config(args.zenoh_config, listen=args.listen or None, connect=args.connect or None)
    ws = cfg.workspace
    stop = threading.Event()

    with stop_on_signals(stop, "finishing the current action, then flush and exit"):
        # Imported here: pybullet is heavy and only this verb needs it.
        from .sim.env import SimEnv

        engine = InferenceEngine(RoManNet(cfg.model, seed=cfg.learner.seed), cfg.model)
        env = SimEnv.from_config(cfg)
        try:
            with open_session(zenoh_config) as session:
                token = session.liveliness().declare_token(RunKeys(cfg.run_id).actor_alive(acfg.actor_id))
                try:
                    client = ZenohReplayClient(session, cfg.run_id, expected_shape=(ws.height_px, ws.width_px),
                                               actor_id=acfg.actor_id)
                    with ZenohWeightsSource(session, cfg.run_id, fetch_timeout_s=acfg.weights_fetch_timeout_s,
                                            validate=lambda t: validate_tensors(engine.model, t)) as source:
                        log.info("actor %s ready (run %s, dir %s)", acfg.actor_id, cfg.run_id, run_dir)
                        run_actor(cfg, run_dir, env, client, source, stop, actor_cfg=acfg, engine=engine)
                finally:
                    token.undeclare()
        finally:
            env.close()
    return 0
