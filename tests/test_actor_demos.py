"""actor.demo_actions: the first N actions of an actor are the scripted oracle's (planner demonstrations in
replay before the policy acts), then the policy's; real SimEnv, in-process replay store."""

from __future__ import annotations

import threading
from pathlib import Path

import pytest
from test_actor_service import OVERRIDES, NoWeights, RecordingClient

from romannet.actor.main import demonstrator_for
from romannet.actor.service import run_actor
from romannet.actor.sim.env import SimEnv
from romannet.common.config import load_config
from romannet.common.config_actor import ActorConfig
from romannet.common.config_replay import ReplayConfig
from romannet.common.configbase import ConfigError
from romannet.replay.store import ReplayStore

pytestmark = pytest.mark.timeout(120)


def test_the_first_demo_actions_are_the_oracles_then_the_policys(tmp_path: Path) -> None:
    cfg = load_config(None, [*OVERRIDES, "sim.max_steps=20"])
    acfg = ActorConfig(actor_id="a0", spool_fsync=False, max_actions=7, demo_actions=4)
    store = ReplayStore(ReplayConfig(fsync=False, min_size_to_sample=1, snapshot_every_s=0.0,
                                     snapshot_every_inserts=0), tmp_path / "replay")
    env = SimEnv.from_config(cfg)
    oracle = demonstrator_for(env, acfg)
    assert oracle is not None
    chosen = []

    def recording_oracle():
        chosen.append(oracle())
        return chosen[-1]

    client = RecordingClient(store)
    try:
        run_actor(cfg, tmp_path, env, client, NoWeights(), threading.Event(), actor_cfg=acfg,
                  demonstrator=recording_oracle)
    finally:
        env.close()
        store.close()
    sent = [t.action for t in client.accepted]
    assert len(sent) == 7 and len(chosen) == 4  # asked once per demonstration, never after
    assert sent[:4] == chosen and all(a.explored for a in chosen)
    # The oracle picks where an object is: the first demonstration in a 3-block scene is a successful pick.
    assert chosen[0].primitive == "pick" and client.accepted[0].success
    # V(s_t+1) still comes from the policy's own maps during demonstrations.
    assert all(t.next_value is not None for t in client.accepted[:3] if not t.done)


def test_demonstrations_need_the_simulator() -> None:
    class RobotEnv:  # anything that is not the simulator
        primitives = ("push", "pick")

    assert demonstrator_for(RobotEnv(), ActorConfig(demo_actions=0)) is None  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="actor.demo_actions"):
        demonstrator_for(RobotEnv(), ActorConfig(demo_actions=10))  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="actor.demo_actions"):
        ActorConfig(demo_actions=-1)


