"""A light actor of `romannet bench fleet`: an actor's network life without physics or a model.

    python -m romannet.bench.fleet_actor --config run.toml --zenoh-config actor.json5 --run-dir RUN \
        --actor-id actor-3 --report actor-3.txt --stop STOP

What it keeps of a real actor (actor/service.py) is what the fleet benchmark measures:
- weights: the actor's own ZenohWeightsSource (common/weights_client.py) with the same checks (SHA-256,
  size, safetensors, finite values, the model's names, shapes and dtypes), so reception and decoding cost
  what they cost a real actor. The names and shapes come from a RoManNet built on torch's "meta" device:
  no parameter memory, and no model to load into, since no decision is made. A light actor therefore holds
  one decoded copy of the weights, not a model plus a copy: 64 of them fit on one machine.
- transitions: one every 1-2 s (uniform, seeded per actor; a real action's duration), spooled on disk with
  fsync and sent by the actor's own Sender (actor/sender.py) through ZenohReplayClient, so inserts, acks,
  resends and the spool behave as in a real actor. The transitions are synthetic tabletop heightmaps with
  camera noise (bench/replay_workloads.py) of the config's size: valid, and PNG-sized like a real camera's.
  Episodes are "ep<k>" of 10 steps, the actor's own numbering, so bench/fault_ledger.py can find gaps.

Report file lines (CLOCK_MONOTONIC ns, one clock for every process of the machine, network namespaces
included): `w <version> <t_ns>` when a version is taken, `a <episode> <step> <t_ns> <insert_us>` when an
insert is acknowledged (insert_us: request to ack). On the stop file it flushes its spool (up to 60 s) and
writes status.json (actions, acked, state) as a real actor does, for the ledger.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

STEPS_PER_EPISODE = 10
_POLL_S = 0.005  # the weights' arrival is seen within 5 ms: 1 % of the 0.5 s goal
_FLUSH_S = 60.0


class _TimedClient:
    """The actor's replay client, timing each insert and writing a line per acknowledgement."""

    def __init__(self, client: Any, out: Any, lock: threading.Lock):
        self._client, self._out, self._lock = client, out, lock

    def insert_encoded(self, data: bytes, timeout_s: float = 10.0) -> Any:
        t0 = time.monotonic_ns()
        ack = self._client.insert_encoded(data, timeout_s=timeout_s)
        t1 = time.monotonic_ns()
        if ack.status in ("accepted", "duplicate"):
            with self._lock:
                self._out.write(f"a {ack.episode_id} {ack.step} {t1} {(t1 - t0) // 1000}\n")
                self._out.flush()
        return ack


def _template(actor_id: str, side_px: int, seed: int) -> Any:
    """One valid encoded transition (protobuf) of this actor; the caller sets episode, step and version."""
    from romannet.common import romannet_pb2 as pb
    from romannet.common import wire
    from romannet.common.action import Action
    from romannet.common.interfaces import Observation, StepResult

    from .replay_workloads import synthetic_heightmaps

    before = Observation(*synthetic_heightmaps(seed, side_px), holding=False)
    result = StepResult(Observation(*synthetic_heightmaps(seed + 1, side_px), holding=False), success=True,
                        progress_before=0.1, progress_after=0.2, reward=0.2, done=False)
    msg = wire.TransitionMsg.from_step(
        before, Action("push", side_px // 2, side_px // 3, 0.5, 0.7, explored=False), result, actor_id=actor_id,
        episode_id="ep0", step=0, start_ns=1, end_ns=2, task="clutter", explore_rate=0.2)
    proto = pb.Transition()
    proto.ParseFromString(wire.encode_transition(msg))
    return proto


def run_light_actor(args: argparse.Namespace) -> int:
    import torch

    from romannet.actor.sender import Sender
    from romannet.actor.spool import Spool
    from romannet.common.config import load_config
    from romannet.common.fsutil import write_json_atomic
    from romannet.common.model import RoManNet, validate_tensors
    from romannet.common.replay_client import ZenohReplayClient
    from romannet.common.weights_client import ZenohWeightsSource
    from romannet.common.zenoh_session import make_config, open_session

    torch.set_num_threads(1)
    cfg = load_config(args.config)
    ws = cfg.workspace
    if ws.height_px != ws.width_px:
        log.error("the light actor needs a square workspace (heightmaps %dx%d)", ws.height_px, ws.width_px)
        return 2
    with torch.device("meta"):
        shapes = RoManNet(cfg.model)  # names, shapes and dtypes only
    rng = np.random.default_rng(args.seed)
    proto = _template(args.actor_id, ws.height_px, args.seed)
    actor_dir = Path(args.run_dir) / "actors" / args.actor_id
    spool = Spool(actor_dir / "spool", cfg.actor.spool_max_items, cfg.actor.spool_max_bytes)
    lock = threading.Lock()
    produced, version = 0, 0
    with open_session(make_config(args.zenoh_config)) as session, \
            ZenohWeightsSource(session, cfg.run_id, fetch_timeout_s=cfg.actor.weights_fetch_timeout_s,
                               validate=lambda t: validate_tensors(shapes, t)) as source, \
            Path(args.report).open("a") as out:
        client = ZenohReplayClient(session, cfg.run_id, actor_id=args.actor_id,
                                   max_insert_bytes=cfg.replay.max_item_bytes)
        sender = Sender(spool, _TimedClient(client, out, lock), cfg.actor.insert_timeout_s,
                        cfg.actor.resend_backoff_initial_s, cfg.actor.resend_backoff_max_s).start()
        next_action = time.monotonic() + rng.uniform(0, args.period_s[1])  # no fleet-wide lockstep
        while not Path(args.stop).exists():
            got = source.poll_weights()
            if got is not None:
                version = got[0]
                with lock:
                    out.write(f"w {version} {time.monotonic_ns()}\n")
                    out.flush()
            now = time.monotonic()
            if now >= next_action and not spool.full():
                proto.episode_id = f"ep{produced // STEPS_PER_EPISODE}"
                proto.step, proto.policy_version = produced % STEPS_PER_EPISODE, max(0, version)
                proto.start_ns, proto.end_ns = time.time_ns() - 1_000_000_000, time.time_ns()
                spool.put(proto.SerializeToString())
                produced += 1
                next_action = max(next_action + rng.uniform(*args.period_s), now)
            time.sleep(_POLL_S)
        sender.stop(flush_s=_FLUSH_S)
        acked = sender.stats().acked
    write_json_atomic(actor_dir / "status.json", {"actor_id": args.actor_id, "pid": os.getpid(),
                                                  "state": "stopped", "actions": produced, "acked": acked})
    return 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", required=True)
    p.add_argument("--zenoh-config", required=True)
    p.add_argument("--run-dir", required=True)
    p.add_argument("--actor-id", required=True)
    p.add_argument("--report", required=True)
    p.add_argument("--stop", required=True)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--period-s", type=float, nargs=2, default=(1.0, 2.0), metavar=("LOW", "HIGH"))
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return run_light_actor(args)


if __name__ == "__main__":
    sys.exit(main())
