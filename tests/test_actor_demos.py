"""actor.demo_episodes: the scripted oracle acts the actor's first episodes (planner demonstrations in replay),
by episode index so a restarted actor does not repeat them; refused on a real robot."""

from __future__ import annotations

import argparse
import dataclasses
import threading
from pathlib import Path

import pytest
from test_actor_service import OVERRIDES, NoWeights, RecordingClient, _acfg

from romannet.actor.main import demonstrator_for, resolve_actor_config
from romannet.actor.service import ActorPaths, run_actor
from romannet.actor.sim.env import SimEnv
from romannet.common.config import Config, load_config
from romannet.common.config_actor import ActorConfig
from romannet.common.config_replay import ReplayConfig
from romannet.common.errors import ConfigError
from romannet.mcaptools.summary import format_episode, format_totals, summarize, totals
from romannet.replay.store import ReplayStore

pytestmark = pytest.mark.timeout(180)

# Stacking to 2 with the floating gripper: the oracle needs 2 actions, an untrained greedy policy does not stack.
STACKING = OVERRIDES + ['task.kind="stacking"', "task.goal_stack_height=2", "task.use_push=false",
                        "sim.num_objects=3", "sim.max_steps=4", "exploration.initial_rate=0.0",
                        "exploration.failure_memory_px=0"]


@pytest.fixture(scope="module")
def cfg() -> Config:
    return load_config(None, STACKING)


def _run(cfg: Config, run_dir: Path, store_dir: Path, acfg: ActorConfig) -> list:
    store = ReplayStore(ReplayConfig(fsync=False, min_size_to_sample=1, snapshot_every_s=0.0,
                                     snapshot_every_inserts=0, samples_per_insert=0.0), store_dir)
    env = SimEnv.from_config(cfg)
    client = RecordingClient(store)
    try:
        run_actor(cfg, run_dir, env, client, NoWeights(), threading.Event(), actor_cfg=acfg,
                  demonstrator=demonstrator_for(env, acfg))
    finally:
        env.close()
        store.close()
    return client.accepted


def _summaries(run_dir: Path) -> list[dict]:
    return [summarize(f) for f in sorted(ActorPaths.of(run_dir, _acfg()).episodes.glob("*.mcap"))]


def test_the_first_episodes_are_the_oracles_and_a_restart_does_not_repeat_them(tmp_path: Path,
                                                                                 cfg: Config) -> None:
    acfg = _acfg(episodes=1, demo_episodes=1)
    first = _run(cfg, tmp_path, tmp_path / "replay1", acfg)
    # The oracle stacks 2 in its 2 ideal actions (pick, place), each marked as not the policy's greedy choice.
    assert [(t.episode_id, t.action.primitive, t.success) for t in first] == \
        [("ep000000", "pick", True), ("ep000000", "place", True)]
    assert first[-1].done and first[-1].done_reason == "done"
    assert all(t.action.explored for t in first)
    assert first[0].next_value is not None  # the policy's V(s') still travels for the bootstrap

    # The same actor restarted: episode 1 is past demo_episodes, so the (untrained, greedy) policy acts.
    second = _run(cfg, tmp_path, tmp_path / "replay2", acfg)
    assert second and {t.episode_id for t in second} == {"ep000001"}
    assert not any(t.action.explored for t in second)
    # `romannet mcap summary` tells the recorded demonstration from the policy's episode.
    episodes = _summaries(tmp_path)
    assert [(e["episode_id"], e["demonstration"]) for e in episodes] == [("ep000000", True), ("ep000001", False)]
    assert "demonstration" in format_episode(episodes[0]) and "demonstration" not in format_episode(episodes[1])
    assert totals(episodes)["demonstrations"] == 1 and "1 demonstration(s)" in format_totals(totals(episodes))


def test_no_demonstrator_without_demo_episodes(cfg: Config) -> None:
    env = SimEnv.from_config(cfg)
    try:
        assert demonstrator_for(env, _acfg()) is None
    finally:
        env.close()


def test_demonstrations_are_refused_on_a_real_robot_and_bad_counts_are_named(cfg: Config) -> None:
    args = argparse.Namespace(actor_id=None, max_actions=None, episodes=None, robot="ur5e")
    with_demos = dataclasses.replace(cfg, actor=dataclasses.replace(cfg.actor, demo_episodes=5))
    with pytest.raises(ConfigError, match="actor.demo_episodes.*real robot"):
        resolve_actor_config(with_demos, args)
    assert resolve_actor_config(with_demos, argparse.Namespace(**{**vars(args), "robot": "sim"})).demo_episodes == 5
    with pytest.raises(ConfigError, match="actor.demo_episodes"):
        _acfg(demo_episodes=-1)
