"""The actor loop in-process (real SimEnv, floating gripper, 64x64 heightmaps, in-process replay store) and
`romannet actor` as a process against a real `romannet replay` process (SIGTERM -> exit 0, nothing lost)."""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader

from romannet.actor.recorder import count_steps
from romannet.actor.service import ActorPaths, run_actor
from romannet.actor.sim.env import SimEnv
from romannet.actor.stats import read_status
from romannet.common.config import Config, load_config
from romannet.common.config_actor import ActorConfig
from romannet.common.config_replay import ReplayConfig
from romannet.common.int8net import int8_ops_available
from romannet.common.model import RoManNet, state_dict_to_tensors
from romannet.common.policy import InferenceEngine
from romannet.common.replay_client import RateLimitedError
from romannet.common.wire import ExplorationRateMsg
from romannet.common.zenoh_session import NoReplyError, free_port, make_config, open_session
from romannet.replay.inprocess import InProcessReplayClient
from romannet.replay.store import ReplayStore

pytestmark = pytest.mark.timeout(120)

# Small and fast: 64x64 heightmaps, a 160x120 camera (same field of view), tiny nets, short episodes.
# fp32 decisions, whatever the CPU ("auto" is int8 on AVX2 without bf16, whose weights swap on its own schedule).
OVERRIDES = ["workspace.resolution_m=0.007", 'sim.robot="gripper"', "sim.num_objects=3", "sim.max_steps=3",
             "model.channels=8", "model.residual_blocks=1", "camera.width_px=160", "camera.height_px=120",
             "camera.fx_px=154.655", "camera.fy_px=154.655", "camera.cx_px=80.0", "camera.cy_px=60.0",
             'model.precision="fp32"']


@pytest.fixture(scope="module")
def cfg() -> Config:
    return load_config(None, OVERRIDES)


@pytest.fixture
def store(tmp_path: Path):
    # Unpaced: no learner samples here.
    s = ReplayStore(ReplayConfig(fsync=False, min_size_to_sample=1, snapshot_every_s=0.0,
                                 snapshot_every_inserts=0, samples_per_insert=0.0), tmp_path / "replay")
    yield s
    s.close()


class FakeWeights:
    """Delivers weights `version` on the (after+1)-th poll (polls happen right before each decision) and an
    exploration rate on the second poll."""

    def __init__(self, cfg: Config, version: int, after: int):
        self.tensors = state_dict_to_tensors(RoManNet(cfg.model, seed=123))
        self.version, self.after, self.polls, self.rate_polls = version, after, 0, 0

    def poll_weights(self):
        self.polls += 1
        return (self.version, self.tensors) if self.polls == self.after + 1 else None

    def poll_exploration(self):
        self.rate_polls += 1
        return ExplorationRateMsg(1, 0.25, "lae") if self.rate_polls == 2 else None


class NoWeights:
    def poll_weights(self):
        return None

    def poll_exploration(self):
        return None


def _acfg(**kw) -> ActorConfig:
    return ActorConfig(**{"actor_id": "a0", "spool_fsync": False, "insert_timeout_s": 1.0,
                          "resend_backoff_initial_s": 0.05, "resend_backoff_max_s": 0.2, **kw})


class RecordingClient(InProcessReplayClient):
    """The in-process client, keeping every transition the store accepted (in insert order)."""

    def __init__(self, store: ReplayStore):
        super().__init__(store)
        self.accepted: list = []

    def insert(self, transition, timeout_s: float = 10.0):
        ack = super().insert(transition, timeout_s)
        if ack.status == "accepted":
            self.accepted.append(transition)
        return ack


@pytest.mark.skipif(not int8_ops_available(), reason="this PyTorch build has no oneDNN int8 convolutions")
def test_an_int8_actor_prepares_new_weights_while_the_action_executes(tmp_path: Path, cfg: Config,
                                                                       store: ReplayStore, monkeypatch) -> None:
    # int8's weight swap measures each net's int8 error (about a decision's time): it is built on a background
    # thread during the action's physics (or a robot's motion) and in force for the next decision.
    cfg = dataclasses.replace(cfg, model=dataclasses.replace(cfg.model, precision="int8"))
    prepared_on: list[str] = []
    prepare = InferenceEngine.prepare

    def spy(self: InferenceEngine, tensors):
        prepared_on.append(threading.current_thread().name)
        return prepare(self, tensors)

    monkeypatch.setattr(InferenceEngine, "prepare", spy)
    env = SimEnv.from_config(cfg)
    weights = FakeWeights(cfg, version=7, after=1)  # polls: the episode's start, then before each action's physics
    client = RecordingClient(store)
    try:
        stats = run_actor(cfg, tmp_path, env, client, weights, threading.Event(), actor_cfg=_acfg(max_actions=5))
    finally:
        env.close()
    assert stats.actions == 5 and stats.weights_version == 7
    assert prepared_on == ["romannet-weights_0"]
    assert [t.policy_version for t in client.accepted] == [0, 7, 7, 7, 7]
    assert client.accepted[0].next_value_version == 7  # the decision after the action used them


@pytest.mark.parametrize("clearance", [False, True])
def test_loop_sends_stamps_versions_and_records(tmp_path: Path, cfg: Config, store: ReplayStore,
                                                clearance: bool) -> None:
    cfg = dataclasses.replace(cfg, exploration=dataclasses.replace(cfg.exploration, pick_clearance=clearance))
    env = SimEnv.from_config(cfg)
    weights = FakeWeights(cfg, version=7, after=4)
    client = RecordingClient(store)
    try:
        stats = run_actor(cfg, tmp_path, env, client, weights, threading.Event(),
                          actor_cfg=_acfg(max_actions=8))
    finally:
        env.close()
    assert stats.actions == 8
    keys = sorted(store._by_key, key=lambda k: (k[1], k[2]))
    assert len(keys) == 8 and {k[0] for k in keys} == {"a0"}
    per_episode: dict[str, list[int]] = {}
    for _, episode, step in keys:
        per_episode.setdefault(episode, []).append(step)
    for steps in per_episode.values():
        assert steps == list(range(len(steps)))  # steps from 0, none missing
    transitions = client.accepted
    assert [(t.episode_id, t.step) for t in transitions] == [k[1:] for k in keys]  # sent in order
    # Swapped only between actions: the first 4 actions used v0, the rest v7 (an action boundary).
    assert [t.policy_version for t in transitions] == [0] * 4 + [7] * 4
    # The initial rate until the learner's first rate (second poll), then the learner's.
    assert [t.explore_rate for t in transitions] == [0.5] + [0.25] * 7
    assert all(t.task == "clutter" and t.sim_seed is not None for t in transitions)
    # V(s_t+1) travels with each transition a decision followed (not at an episode's end, nor the last
    # action): the next decision's largest Q over every pixel, taken with the weights that then chose the next
    # action, unclear picks included; a greedy choice that avoided no failure (exploration.failure_memory_px) and
    # no unclear pick (exploration.pick_clearance) is that largest Q.
    for t, nxt in zip(transitions, transitions[1:], strict=False):
        avoiding = not t.success  # a failure is remembered until a success clears the memory
        if t.done:
            assert t.next_value is None
            continue
        assert nxt.episode_id == t.episode_id and t.next_value_version == nxt.policy_version
        assert t.next_value >= nxt.action.q_value - 1e-6
        if not nxt.action.explored and not avoiding and not clearance:
            assert t.next_value == pytest.approx(nxt.action.q_value, abs=1e-6)
    assert transitions[-1].next_value is None
    # One MCAP file per episode with that episode's step count, finished (summary present).
    paths = ActorPaths.of(tmp_path, _acfg())
    files = sorted(paths.episodes.glob("*.mcap"))
    assert [f.stem for f in files] == sorted(per_episode)
    for f in files:
        assert count_steps(f) == len(per_episode[f.stem])
        with open(f, "rb") as fh:
            reader = make_reader(fh)
            assert reader.get_summary() is not None
            meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert meta["romannet"]["actor_id"] == "a0" and "toml" in meta["config"]
    status = read_status(paths.status)
    assert status is not None and status["state"] == "stopped"
    assert status["actions"] == 8 and status["acked"] == 8 and status["spool_items"] == 0
    assert status["weights_version"] == 7 and status["weights_versions_used"] == 2
    assert status["explore_rate"] == 0.25 and status["explore_rate_received"] and not status["paused"]
    for field in ("episodes", "picks", "successful_picks", "completed_episodes", "efficiency_mean", "sent",
                  "last_done_reason"):
        assert field in status
    # A restart continues the episode numbering: ids are never reused.
    assert json.loads(paths.state.read_text())["next_episode"] == len(per_episode)


class DownClient:
    def insert(self, transition, timeout_s: float = 10.0):
        raise TimeoutError("no reply (server down)")

    def insert_encoded(self, data: bytes, timeout_s: float = 10.0):
        raise TimeoutError("no reply (server down)")


def _wait_until_paused(status_path: Path, timeout_s: float = 60.0) -> dict:
    """The actor's status once it says paused (fails the test after timeout_s)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not (read_status(status_path) or {}).get("paused"):
        time.sleep(0.05)
    status = read_status(status_path)
    assert status is not None and status["paused"], f"not paused after {timeout_s} s: {status}"
    return status


class LaggingLearnerClient(InProcessReplayClient):
    """A live replay server whose rate limiter holds inserts back (RateLimitedError) until `release` is set:
    the learner lags behind the actor."""

    def __init__(self, store: ReplayStore):
        super().__init__(store)
        self.release = threading.Event()

    def insert(self, transition, timeout_s: float = 10.0):
        if not self.release.is_set():
            time.sleep(0.02)  # the server holds the request for its wait before it answers
            raise RateLimitedError("romannet/@v1/x/replay/insert/a0", "rate_limited", "held for 0.02 s")
        return super().insert(transition, timeout_s)


def test_a_greedy_actor_does_not_repeat_a_failed_action_in_its_episode(tmp_path: Path, store: ReplayStore) -> None:
    """exploration.failure_memory_px: untrained weights, no exploration, the same scene after each failed
    pick; each decision keeps out of the discs of the episode's failures since its last success."""
    cfg = load_config(None, [*OVERRIDES, "sim.max_steps=6", "exploration.initial_rate=0.0",
                             "exploration.failure_memory_px=6", "task.use_push=false",
                             'exploration.pick_angle="net"', "exploration.pick_centre=false"])  # failures to avoid
    env = SimEnv.from_config(cfg)
    client = RecordingClient(store)
    try:
        run_actor(cfg, tmp_path, env, client, NoWeights(), threading.Event(), actor_cfg=_acfg(max_actions=12))
    finally:
        env.close()
    failed: dict[str, list[tuple[int, int]]] = {}
    checked = 0
    for t in client.accepted:
        a = t.action
        assert not a.explored
        earlier = failed.setdefault(t.episode_id, [])
        if a.primitive == "pick":
            assert all((a.row - r) ** 2 + (a.col - c) ** 2 > 6 ** 2 for r, c in earlier), (t.episode_id, t.step)
            checked += len(earlier)
        if t.success:
            earlier.clear()
        elif a.primitive == "pick":
            earlier.append((a.row, a.col))
    assert checked >= 5  # decisions were taken with failures to avoid


def test_waiting_for_a_lagging_learner_is_pacing_not_a_pause(tmp_path: Path, cfg: Config, store: ReplayStore,
                                                             caplog: pytest.LogCaptureFixture,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """A full spool behind a rate-limited (live) server: the status says paced, the server reachable, and no
    warning is logged; the transitions go once the learner catches up."""
    import romannet.actor.service as service

    monkeypatch.setattr(service, "_QUIET_PAUSE_S", 0.1)  # report the wait at once, not after 5 s
    env = SimEnv.from_config(cfg)
    client = LaggingLearnerClient(store)
    acfg = _acfg(max_actions=3, spool_max_items=2, shutdown_flush_s=5.0, record_mcap=False)
    status_path = ActorPaths.of(tmp_path, acfg).status
    result: list = []
    try:
        with caplog.at_level(logging.INFO, logger="romannet.actor"):
            thread = threading.Thread(target=lambda: result.append(
                run_actor(cfg, tmp_path, env, client, NoWeights(), threading.Event(), actor_cfg=acfg)))
            thread.start()
            status = _wait_until_paused(status_path)
            assert status["actions"] == 2
            assert status["pause_kind"] == "paced" and status["pause_reason"].startswith("paced by the learner")
            assert status["server_reachable"] is True and status["send_failures"] == 0
            client.release.set()
            thread.join(60)
            assert not thread.is_alive()
    finally:
        env.close()
    assert result and result[0].actions == 3 and len(store._by_key) == 3
    status = read_status(status_path)
    assert status["paced_inserts"] >= 1 and not status["paused"] and status["acked"] == 3
    assert not [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]


class HangingThenDownClient:
    """A server that takes the first insert and never answers: the request hangs until `give_up` is set, then
    ends without a reply (NoReplyError), as a request to a server that died meanwhile does."""

    def __init__(self) -> None:
        self.give_up = threading.Event()

    def insert(self, transition, timeout_s: float = 10.0):
        self.give_up.wait(60)
        raise NoReplyError("no reply (server died)")

    def insert_encoded(self, data: bytes, timeout_s: float = 10.0):
        self.give_up.wait(60)
        raise NoReplyError("no reply (server died)")


def test_a_wait_on_an_insert_in_flight_turns_into_an_outage(tmp_path: Path, cfg: Config,
                                                            caplog: pytest.LogCaptureFixture,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """While the insert is in flight the actor is only waiting (no warning); when it fails the pause is an
    outage: a warning and the status say so."""
    import romannet.actor.service as service

    monkeypatch.setattr(service, "_QUIET_PAUSE_S", 0.1)
    env = SimEnv.from_config(cfg)
    client, stop = HangingThenDownClient(), threading.Event()
    acfg = _acfg(max_actions=20, spool_max_items=2, shutdown_flush_s=0.2, record_mcap=False)
    status_path = ActorPaths.of(tmp_path, acfg).status
    try:
        with caplog.at_level(logging.INFO, logger="romannet.actor"):
            thread = threading.Thread(target=run_actor, args=(cfg, tmp_path, env, client, NoWeights(), stop),
                                      kwargs={"actor_cfg": acfg})
            thread.start()
            status = _wait_until_paused(status_path)
            assert status["pause_kind"] == "waiting" and status["server_reachable"] is True
            assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
            client.give_up.set()
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and (read_status(status_path) or {}).get("pause_kind") != "outage":
                time.sleep(0.05)
            status = read_status(status_path)
            assert status["paused"] and status["pause_kind"] == "outage" and status["actions"] == 2
            warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
            assert any(m.startswith("actor paused: spool full") for m in warnings)
            stop.set()
            thread.join(30)
            assert not thread.is_alive()
    finally:
        client.give_up.set()
        env.close()


def test_pauses_when_spool_full_and_resends_after_restart(tmp_path: Path, cfg: Config,
                                                         store: ReplayStore) -> None:
    env = SimEnv.from_config(cfg)
    stop = threading.Event()
    acfg = _acfg(max_actions=20, spool_max_items=2, shutdown_flush_s=0.2, record_mcap=False)
    status_path = ActorPaths.of(tmp_path, acfg).status
    try:
        thread = threading.Thread(target=run_actor, args=(cfg, tmp_path, env, DownClient(), NoWeights(), stop),
                                  kwargs={"actor_cfg": acfg})
        thread.start()
        status = _wait_until_paused(status_path)
        assert status["actions"] == 2
        assert "spool full" in status["pause_reason"] and status["server_reachable"] is False
        assert status["pause_kind"] == "outage"
        stop.set()
        thread.join(30)
        assert not thread.is_alive()
        # Restart against a reachable server: the two spooled transitions go first, then new ones.
        stats = run_actor(cfg, tmp_path, env, InProcessReplayClient(store), NoWeights(), threading.Event(),
                          actor_cfg=_acfg(max_actions=2, spool_max_items=2, record_mcap=False))
    finally:
        env.close()
    assert stats.actions == 2
    status = read_status(status_path)
    assert status["spool_recovered"] == 2 and status["acked"] == 4 and status["spool_items"] == 0
    assert len(store._by_key) == 4 and store.stats()["duplicates"] == 0
    assert {k[1] for k in store._by_key} == {"ep000000", "ep000001"}  # the restart started a new episode


def _wait_for(predicate, timeout_s: float, what: str, procs=()) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return
        for p in procs:
            assert p.poll() is None, f"{what}: a process exited early with {p.returncode}"
        time.sleep(0.1)
    raise AssertionError(f"timed out waiting for {what}")


def test_cli_actor_against_replay_process(tmp_path: Path) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    sets = [a for o in OVERRIDES + ["replay.fsync=false", "run_id=\"cli-test\""] for a in ("--set", o)]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    cli = [sys.executable, "-m", "romannet.cli"]
    run_dir = tmp_path / "run"
    replay = subprocess.Popen(cli + ["replay", "--dir", str(run_dir / "replay"), "--listen", endpoint] + sets,
                              env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    actor = None
    try:
        actor = subprocess.Popen(cli + ["actor", "--run-dir", str(run_dir), "--actor-id", "sim-1", "--connect",
                                        endpoint] + sets, env=env, stdout=subprocess.PIPE,
                                 stderr=subprocess.STDOUT)
        status_path = run_dir / "actors" / "sim-1" / "status.json"
        _wait_for(lambda: ((read_status(status_path) or {}).get("acked") or 0) >= 3, 90,
                  "3 acknowledged transitions", (replay, actor))
        actor.send_signal(signal.SIGTERM)
        out, _ = actor.communicate(timeout=60)
        assert actor.returncode == 0, out.decode()[-3000:]
        status = read_status(status_path)
        assert status["state"] == "stopped" and status["spool_items"] == 0
        assert status["acked"] == status["actions"]
        files = sorted((run_dir / "episodes" / "sim-1").glob("*.mcap"))
        assert files and sum(count_steps(f) for f in files) == status["actions"]
        for f in files:
            with open(f, "rb") as fh:
                assert make_reader(fh).get_summary() is not None  # finished, also the interrupted one
        with open_session(make_config(connect=[endpoint], listen=[])) as session:
            from romannet.common.replay_client import ZenohReplayClient

            server = ZenohReplayClient(session, "cli-test").stats(timeout_s=10)
        assert server["size"] == status["actions"] and server["duplicates"] == 0
        assert server["per_actor"]["sim-1"]["inserted"] == status["actions"]
    finally:
        for p in (actor, replay):
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGTERM)
                try:
                    p.communicate(timeout=30)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.communicate()
    assert replay.returncode == 0


class DivergingWeights:
    """Good weights v3 on the 2nd poll, then v5 (finite numbers whose Q maps overflow: a diverged learner's)
    on the 4th, then good v6 on the 7th."""

    def __init__(self, cfg: Config):
        good = state_dict_to_tensors(RoManNet(cfg.model, seed=123))
        blown = {k: (v * 1e30 if k.endswith(("conv6.weight", "q_head.weight")) else v) for k, v in good.items()}
        assert all(bool(v.isfinite().all()) for v in blown.values() if v.is_floating_point())
        self.deliveries = {2: (3, good), 4: (5, blown), 7: (6, good)}
        self.polls = 0

    def poll_weights(self):
        self.polls += 1
        return self.deliveries.get(self.polls)

    def poll_exploration(self):
        return None


def test_weights_with_non_finite_q_maps_are_dropped_for_the_last_good_ones(
        tmp_path: Path, cfg: Config, store: ReplayStore, caplog: pytest.LogCaptureFixture) -> None:
    env = SimEnv.from_config(cfg)
    client = RecordingClient(store)
    try:
        stats = run_actor(cfg, tmp_path, env, client, DivergingWeights(cfg), threading.Event(),
                          actor_cfg=_acfg(max_actions=8))
    finally:
        env.close()
    assert stats.actions == 8  # the actor kept acting
    # v0 for the first action, v3 from the 2nd; v5 is loaded before the 4th decision, gives NaN/inf Q maps
    # and is replaced by v3 for that very decision; v6 from the 7th.
    assert [t.policy_version for t in client.accepted] == [0, 3, 3, 3, 3, 3, 6, 6]
    assert "weights v5 give non-finite Q maps" in caplog.text and "back to v3" in caplog.text
