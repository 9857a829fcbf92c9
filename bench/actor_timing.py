"""Where an actor's time goes: simulation, inference, encoding/recording, spool, transport.

    measure_actor_time_shares(actions=30, robot="gripper")

Runs the real actor loop (actor/service.py run_actor) in this process against a real `romannet replay`
subprocess over loopback Zenoh, with timers wrapped around the seams the loop calls:

    sim        env.reset / env.step (physics, camera render, heightmaps, reward)
    inference  InferenceEngine.infer (the nets that run for this decision)
    encoding   encode_transition (PNG heightmaps + protobuf) and the MCAP recorder (Q-map images,
               observations, steps, closing the file)
    spool      Spool.put (the fsync'ed write that makes a transition durable before it is sent)
    status     status.json rewrites
    transport  the replay insert requests, on the sender thread (they overlap acting)

Shares are of the loop's wall time; `other` is the rest of the acting thread (decision logic, weights
polling, bookkeeping). No weights arrive (a null source): the learner is not running, so the box's two
cores are the actor's and the replay server's. The wrappers patch attribute names of actor/ internals;
if the actor reports its own timings one day, read those instead.
"""

from __future__ import annotations

import contextlib
import dataclasses
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any


class _NullWeights:
    """A WeightsSource that never has anything new (the actor keeps its initial weights)."""

    def poll_weights(self) -> None:
        return None

    def poll_exploration(self) -> None:
        return None


class _Timers:
    def __init__(self) -> None:
        self.total_s: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)

    def wrap(self, name: str, fn: Callable[..., Any]) -> Callable[..., Any]:
        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.total_s[name] += time.perf_counter() - t0
                self.calls[name] += 1

        return timed


@contextlib.contextmanager
def _patched(obj: Any, attr: str, timers: _Timers, name: str) -> Iterator[None]:
    original = getattr(obj, attr)
    setattr(obj, attr, timers.wrap(name, original))
    try:
        yield
    finally:
        setattr(obj, attr, original)


def measure_actor_time_shares(actions: int = 30, robot: str = "gripper", resolution_m: float = 0.002,
                              seed: int = 0) -> dict[str, Any]:
    """Run one actor for `actions` actions; seconds and shares per part of its loop."""
    from romannet.actor import service
    from romannet.actor.recorder import EpisodeRecorder
    from romannet.actor.sim.env import SimEnv
    from romannet.actor.spool import Spool
    from romannet.common.config import load_config
    from romannet.common.configbase import write_toml
    from romannet.common.model import RoManNet
    from romannet.common.policy import InferenceEngine
    from romannet.common.replay_client import ZenohReplayClient
    from romannet.common.zenoh_session import free_port, make_config, open_session

    run_id = "bench-actor"
    # No learner samples here: unpaced, or the replay would hold the actor's inserts once it is ahead.
    cfg = load_config(None, [f'run_id="{run_id}"', f"seed={seed}", f'sim.robot="{robot}"',
                             f"workspace.resolution_m={resolution_m!r}", "replay.samples_per_insert=0"])
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    timers = _Timers()
    with tempfile.TemporaryDirectory(prefix="romannet-bench-actor-") as tmp:
        config = write_toml(cfg, Path(tmp) / "config.toml")
        replay = subprocess.Popen([sys.executable, "-m", "romannet.cli", "--log-level", "WARNING", "replay",
                                   "--config", str(config), "--dir", str(Path(tmp) / "replay"), "--listen",
                                   endpoint], stdin=subprocess.DEVNULL)
        env = None
        try:
            env = SimEnv.from_config(cfg)
            engine = InferenceEngine(RoManNet(cfg.model, seed=cfg.learner.seed), cfg.model)
            with open_session(make_config(listen=[], connect=[endpoint])) as session:
                ws = cfg.workspace
                client = ZenohReplayClient(session, run_id, expected_shape=(ws.height_px, ws.width_px))
                if not client.wait_until_ready(120.0):
                    raise RuntimeError("the replay server did not come up within 120 s")
                acfg = cfg.actor
                acfg = dataclasses.replace(acfg, max_actions=actions)
                with contextlib.ExitStack() as stack:
                    for obj, attr, name in (
                            (env, "reset", "sim"), (env, "step", "sim"), (engine, "infer", "inference"),
                            (service, "encode_transition", "encoding"),
                            (EpisodeRecorder, "write_q_maps", "encoding"),
                            (EpisodeRecorder, "write_observation", "encoding"),
                            (EpisodeRecorder, "write_step", "encoding"), (EpisodeRecorder, "close", "encoding"),
                            (Spool, "put", "spool"), (service.ActorLoop, "write_status", "status"),
                            (client, "insert_encoded", "transport")):
                        stack.enter_context(_patched(obj, attr, timers, name))
                    t0 = time.perf_counter()
                    stats = service.run_actor(cfg, Path(tmp) / "run", env, client, _NullWeights(),
                                              threading.Event(), actor_cfg=acfg, engine=engine)
                    wall_s = time.perf_counter() - t0
        finally:
            if env is not None:
                env.close()
            replay.terminate()
            try:
                replay.wait(60)
            except subprocess.TimeoutExpired:
                replay.kill()
                replay.wait()
    acting = {k: timers.total_s[k] for k in ("sim", "inference", "encoding", "spool", "status")}
    shares = {k: round(v / wall_s, 3) for k, v in acting.items()}
    shares["other"] = round(max(0.0, wall_s - sum(acting.values())) / wall_s, 3)
    return {"actions": stats.actions, "robot": robot, "heightmap_px": cfg.workspace.height_px,
            "wall_s": round(wall_s, 2), "actions_per_s": round(stats.actions / wall_s, 3),
            "seconds": {k: round(v, 3) for k, v in timers.total_s.items()},
            "calls": dict(timers.calls), "share_of_wall": shares,
            "transport_share_of_wall_on_sender_thread": round(timers.total_s["transport"] / wall_s, 3)}
