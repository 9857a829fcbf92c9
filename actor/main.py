"""`romannet actor`: act in the foreground until SIGTERM / SIGINT or a limit, then exit 0.

    romannet actor --config run.toml --run-dir runs/run-1 --actor-id actor-0 --connect tcp/127.0.0.1:7447

The TOML file is the fleet config (configs/default.toml): run_id picks the keys, [task] [sim] [workspace]
the simulated scene, [model] [exploration] the policy, [actor] this process (common/config_actor.py).
--actor-id / --max-actions / --episodes override the [actor] values, so one file serves a whole fleet.

The environment sits behind common.interfaces.Env: the simulator (`--robot sim`, the default) or a UR arm
with a RealSense camera (`--robot ur --camera realsense`, actor/real/; the [robot] and [realsense] sections
and a calibration file from `romannet calibrate`). A robot stop pauses the actor until an operator resumes
it (actor/service.py). A signal
sets the stop event; the actor finishes the primitive under way, spools and records it, finishes the MCAP
file, gives the sender actor.shutdown_flush_s to empty the spool, drops its liveliness token and closes the
session.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import threading
from collections.abc import Callable
from pathlib import Path

from romannet.common.action import Action
from romannet.common.config import Config, load_config
from romannet.common.config_actor import ActorConfig
from romannet.common.configbase import write_toml
from romannet.common.errors import ConfigError
from romannet.common.interfaces import Env
from romannet.common.keys import RunKeys
from romannet.common.model import RoManNet, validate_tensors
from romannet.common.policy import InferenceEngine
from romannet.common.replay_client import ZenohReplayClient
from romannet.common.signals import stop_on_signals
from romannet.common.weights_client import ZenohWeightsSource
from romannet.common.zenoh_limits import FLEET_MAX_MESSAGE_BYTES, limit_messages
from romannet.common.zenoh_session import make_config, open_session

from .episode_state import read_next_episode
from .service import ActorPaths, run_actor

log = logging.getLogger(__name__)


def resolve_actor_config(cfg: Config, args: argparse.Namespace) -> ActorConfig:
    """The [actor] section with the command line's --actor-id / --max-actions / --episodes applied."""
    changes = {name: value for name, value in (("actor_id", args.actor_id), ("max_actions", args.max_actions),
                                               ("episodes", args.episodes)) if value is not None}
    acfg = dataclasses.replace(cfg.actor, **changes)  # validated again by __post_init__
    if acfg.demo_episodes and getattr(args, "robot", "sim") != "sim":
        raise ConfigError("actor.demo_episodes", acfg.demo_episodes,
                          "demonstrations come from the simulator's scripted oracle: 0 on a real robot")
    return acfg


def demonstrator_for(env: Env, acfg: ActorConfig) -> Callable[[], Action] | None:
    """The scripted oracle acting in the simulated `env` for the first actor.demo_episodes episodes (None when
    there are none; resolve_actor_config refuses them on a real robot)."""
    if acfg.demo_episodes == 0:
        return None
    from .sim.oracle import oracle_action

    return lambda: oracle_action(env)


def build_env(cfg: Config, robot: str = "sim", camera: str | None = None) -> Env:
    """The environment behind the actor: the simulator, or a real robot + camera (connected and checked)."""
    if robot == "sim":
        if camera not in (None, "sim"):
            raise ConfigError("--camera", camera, "a simulated robot sees through the simulator's camera: "
                              "leave --camera out (or use --robot ur)")
        from .sim.env import SimEnv  # imported here: pybullet is heavy

        return SimEnv.from_config(cfg)
    if camera not in (None, "realsense"):
        raise ConfigError("--camera", camera, "a real robot needs a real camera: --camera realsense")
    if not cfg.robot.calibration_file:
        raise ConfigError("robot.calibration_file", "", "a real robot needs the camera-to-robot calibration: "
                          "run `romannet calibrate --config robot.toml --out calibration.json` and set "
                          "[robot] calibration_file")
    from .real.calibration import load_calibration
    from .real.env import RealEnv
    from .real.realsense import RealSenseCamera
    from .real.ur import URRobot

    calibration = load_calibration(cfg.robot.calibration_file)
    env = RealEnv(cfg, URRobot(cfg.robot), RealSenseCamera(cfg.realsense), calibration.T_base_cam,
                  calibration.depth_scale)
    env.connect()
    return env


def for_robot(cfg: Config, robot: str) -> Config:
    """cfg as this robot runs it: the pick clearance rule models the simulated hand's fingers (the real tools
    have no footprint model yet), so a real robot picks without it, and says so."""
    if robot == "sim" or not cfg.exploration.pick_clearance:
        return cfg
    log.warning("exploration.pick_clearance is off on a real robot: the rule models the simulated hand's fingers")
    return dataclasses.replace(cfg, exploration=dataclasses.replace(cfg.exploration, pick_clearance=False))


def run(args: argparse.Namespace) -> int:
    """Run one actor for parsed CLI arguments (see romannet/cli.py); returns the exit code."""
    robot = getattr(args, "robot", "sim")
    cfg = for_robot(load_config(args.config, args.overrides), robot)
    acfg = resolve_actor_config(cfg, args)
    run_dir = Path(args.run_dir)
    paths = ActorPaths.of(run_dir, acfg)
    paths.root.mkdir(parents=True, exist_ok=True)  # a file in the way is named now, not as an unreadable state
    read_next_episode(paths.state, paths.episodes)  # a damaged state.json: one line now, before any start-up
    write_toml(cfg, paths.root / "config.toml")  # what this actor ran with (also in every MCAP file)
    zenoh_config = make_config(args.zenoh_config, listen=args.listen or None, connect=args.connect or None)
    limit_messages(zenoh_config, FLEET_MAX_MESSAGE_BYTES, "actor")  # weights are the largest it receives
    ws = cfg.workspace
    stop = threading.Event()

    with stop_on_signals(stop, "finishing the current action, then flush and exit"):
        engine = InferenceEngine(RoManNet(cfg.model, seed=cfg.learner.seed), cfg.model,
                                 primitives=cfg.task.primitives)
        env = build_env(cfg, robot, getattr(args, "camera", None))
        try:
            demonstrator = demonstrator_for(env, acfg)
            with open_session(zenoh_config) as session:
                token = session.liveliness().declare_token(RunKeys(cfg.run_id).actor_alive(acfg.actor_id))
                try:
                    client = ZenohReplayClient(session, cfg.run_id, expected_shape=(ws.height_px, ws.width_px),
                                               actor_id=acfg.actor_id, max_insert_bytes=cfg.replay.max_item_bytes)
                    with ZenohWeightsSource(session, cfg.run_id, fetch_timeout_s=acfg.weights_fetch_timeout_s,
                                            validate=lambda t: validate_tensors(engine.model, t)) as source:
                        log.info("actor %s ready (run %s, dir %s)", acfg.actor_id, cfg.run_id, run_dir)
                        run_actor(cfg, run_dir, env, client, source, stop, actor_cfg=acfg, engine=engine,
                                  demonstrator=demonstrator)
                finally:
                    token.undeclare()
        finally:
            env.close()
    return 0
