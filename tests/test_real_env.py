"""RealEnv (a UR arm + a RealSense camera behind the Env interface) on the fake drivers: the paper's real
tasks (bin picking with bin swapping, stacking), the actor loop pausing on a robot stop until an operator
resumes it, `romannet actor --robot ur --camera realsense` as a process against a real replay server, and
`romannet calibrate` through the same drivers."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from _fake_drivers import fake_driver_env, fake_drivers, fakeworld

from romannet import cli
from romannet.actor.real.calibration import load_calibration
from romannet.actor.real.env import RealEnv
from romannet.actor.real.realsense import RealSenseCamera
from romannet.actor.real.ur import URRobot
from romannet.actor.recorder import count_steps
from romannet.actor.service import ActorPaths, run_actor
from romannet.actor.stats import read_status
from romannet.common.action import Action, position_to_pixel
from romannet.common.config import Config, load_config
from romannet.common.config_replay import ReplayConfig
from romannet.common.configbase import write_toml
from romannet.common.errors import RobotError
from romannet.common.interfaces import Env
from romannet.common.zenoh_session import free_port
from romannet.replay.inprocess import InProcessReplayClient
from romannet.replay.store import ReplayStore

pytestmark = pytest.mark.timeout(120)

HOME = [0.5, 0.0, 0.45, math.pi, 0.0, 0.0]
BINS = [[0.276, -0.5], [0.276, 0.05]]
# Small and fast: 64x64 heightmaps (0.448 m at 7 mm/px), tiny nets.
BASE = ["workspace.resolution_m=0.007", "model.channels=8", "model.residual_blocks=1", 'robot.host="ur-fake"',
        f"robot.home_pose={HOME}", "robot.limits_y_m=[-0.55, 0.55]", "robot.vacuum_settle_s=0.0",
        "realsense.warmup_frames=1", "sim.max_steps=6"]


def make_world(boxes=(), **kw):
    fw = fakeworld()
    w = fw.World(host="ur-fake", home_pose=list(HOME), **kw)
    w.camera.T_base_cam = fw.look_at((0.5, 0.0, 1.2), (0.5, 0.0, 0.0))
    for name, xy in boxes:
        w.add_box(name, (*xy, 0.025), (0.05, 0.05, 0.05))
    return w


def make_env(cfg: Config, w) -> RealEnv:
    env = RealEnv(cfg, URRobot(cfg.robot), RealSenseCamera(cfg.realsense), np.array(w.camera.T_base_cam))
    env.connect()
    return env


def pick_at(env: RealEnv, x: float, y: float, primitive: str = "pick") -> Action:
    row, col = position_to_pixel(x, y, env.ws)
    return Action(primitive, row, col, 0.0, 0.0)


def test_bin_picking_drops_into_the_other_bin_and_swaps_when_empty():
    cfg = load_config(None, BASE + [f"robot.bins_xy_m={BINS}"])
    w = make_world([("a", (0.45, -0.3)), ("b", (0.6, -0.2))])
    with fake_drivers(w):
        env = make_env(cfg, w)
        try:
            obs = env.reset(7)
            assert env.source == 0 and obs.depth_hm.shape == (64, 64) and obs.depth_hm.max() == pytest.approx(0.05, abs=0.003)
            miss = env.step(pick_at(env, 0.35, -0.45))
            assert (miss.success, miss.detail, miss.reward, miss.done) == (False, "nothing_grasped", 0.0, False)
            first = env.step(pick_at(env, 0.45, -0.3))
            assert first.success and not first.done and first.reward > 0
            assert 0.3 < first.progress_after < 0.7  # one of two objects cleared from the footprint
            assert 0.05 < w.box("a").center_m[1] < 0.5  # dropped into bin 1
            last = env.step(pick_at(env, 0.6, -0.2))
            assert last.success and last.done and last.done_reason == "done" and last.progress_after == 1.0
            assert last.info["bin"] == 0 and not last.info["clamped"]
            env.reset(8)
            assert env.source == 1  # bin 0 is empty: the bins swapped
            assert env.ws.y_min_m == pytest.approx(0.05)
        finally:
            env.close()


def test_stacking_measures_the_stack_on_depth_and_waits_for_the_operator_to_unstack():
    cfg = load_config(None, BASE + ['task.kind="stacking"', "task.use_push=false", "task.goal_stack_height=2",
                                    "robot.reset_wait_s=0.1"])
    w = make_world([("a", (0.4, -0.1)), ("b", (0.6, 0.1))])
    with fake_drivers(w):
        env = make_env(cfg, w)
        try:
            env.reset(0)
            assert env.step(pick_at(env, 0.4, -0.1, "place")).detail == "not_holding"
            picked = env.step(pick_at(env, 0.4, -0.1))
            assert picked.success and picked.observation.holding and picked.progress_after == 0.5
            placed = env.step(pick_at(env, 0.6, 0.1, "place"))
            assert placed.success and placed.done and placed.done_reason == "done"
            assert placed.info["stack_height_hm"] == 2 and placed.reward > 0
            with pytest.raises(RobotError, match="un-stack"):
                env.reset(1)
        finally:
            env.close()


def test_a_stop_while_moving_home_at_reset_pauses_the_environment():
    cfg = load_config(None, BASE)
    w = make_world([("a", (0.45, -0.1))])
    w.tcp_pose = [0.5, 0.1, 0.3, math.pi, 0.0, 0.0]  # not at home: reset moves
    w.inject_protective_stop(after_moves=0)
    with fake_drivers(w):
        env = make_env(cfg, w)
        try:
            assert isinstance(env, Env) and env.paused == ""
            with pytest.raises(RobotError, match="stopped .protective_stop. moving home"):
                env.reset(0)
            assert "protective_stop" in env.paused and not env.try_resume()
            w.clear_stop()
            assert env.try_resume() and env.paused == ""
            assert env.reset(1).depth_hm.max() > 0.04
        finally:
            env.close()


class RecordingClient(InProcessReplayClient):
    def __init__(self, store: ReplayStore):
        super().__init__(store)
        self.sent: list = []

    def insert(self, transition, timeout_s: float = 10.0):
        self.sent.append(transition)
        return super().insert(transition, timeout_s)


class NoWeights:
    def poll_weights(self):
        return None

    def poll_exploration(self):
        return None


def _wait_for(predicate, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def test_actor_pauses_on_a_protective_stop_and_moves_only_after_the_operator_resumes(tmp_path: Path):
    cfg = load_config(None, BASE + [f"robot.bins_xy_m={BINS}", "actor.spool_fsync=false", 'actor.actor_id="ur-0"',
                                    "actor.max_actions=3"])
    w = make_world([("a", (0.45, -0.3)), ("b", (0.6, -0.2)), ("c", (0.35, -0.15))])
    w.inject_protective_stop(when_z_below=0.04)  # the first primitive's descent
    store = ReplayStore(ReplayConfig(fsync=False, min_size_to_sample=1, snapshot_every_s=0.0,
                                     snapshot_every_inserts=0), tmp_path / "replay")
    stop = threading.Event()
    paths = ActorPaths.of(tmp_path, cfg.actor)
    with fake_drivers(w):
        env = make_env(cfg, w)
        out: dict = {}
        client = RecordingClient(store)
        thread = threading.Thread(target=lambda: out.update(stats=run_actor(
            cfg, tmp_path, env, client, NoWeights(), stop)))
        thread.start()
        try:
            def paused() -> bool:
                status = read_status(paths.status)
                return bool(status and status["state"] == "paused")

            _wait_for(paused)
            status = read_status(paths.status)
            assert "protective_stop" in status["pause_reason"] and str(paths.resume) in status["pause_reason"]
            moves_at_stop = len(w.moves())
            paths.resume.touch()  # the operator asks too early: the stop is still set on the pendant
            _wait_for(lambda: not paths.resume.exists())
            time.sleep(0.3)
            assert paused() and len(w.moves()) == moves_at_stop
            w.clear_stop()
            paths.resume.touch()
            thread.join(60)
            assert not thread.is_alive()
        finally:
            stop.set()
            thread.join(10)
            env.close()
    assert out["stats"].actions == 3
    keys = sorted(store._by_key, key=lambda k: (k[1], k[2]))
    assert [k[1:] for k in keys] == [("ep000000", 0), ("ep000001", 0), ("ep000001", 1)]
    first = client.sent[0]
    assert (first.done, first.done_reason, first.success, first.reward) == (True, "robot_stopped", False, 0.0)
    assert all(t.sim_seed is None for t in client.sent)  # a real scene cannot be re-simulated from a seed
    cleared = [c["call"] for c in w.calls].index("clear_stop")
    # Nothing moved between the stop and the operator clearing it; the next episode moved after that.
    assert sum(c["call"] == "moveL" for c in w.calls[:cleared]) == moves_at_stop
    assert sum(c["call"] == "moveL" for c in w.calls[cleared:]) > 0
    files = sorted(paths.episodes.glob("*.mcap"))
    assert [f.stem for f in files] == ["ep000000", "ep000001"] and count_steps(files[0]) == 1
    assert read_status(paths.status)["last_done_reason"] in ("max_actions", "robot_stopped")
    store.close()


def test_romannet_actor_runs_a_real_robot_process_against_a_replay_server(tmp_path: Path):
    calibration = tmp_path / "camera_pose.txt"  # VPG's format, as a user coming from VPG would have it
    w = make_world([("a", (0.45, -0.3)), ("b", (0.6, -0.2))], state_path=str(tmp_path / "state.json"))
    np.savetxt(calibration, np.array(w.camera.T_base_cam))
    w.save(tmp_path / "world.json")
    config = write_toml(load_config(None, [*BASE, f"robot.bins_xy_m={BINS}", 'run_id="real"',
                                           f'robot.calibration_file="{calibration}"', "replay.fsync=false",
                                           "replay.min_size_to_sample=1", "replay.samples_per_insert=0",
                                           "actor.spool_fsync=false"]),  # no learner samples: unpaced
                        tmp_path / "robot.toml")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = {**fake_driver_env(tmp_path / "world.json"), "OMP_NUM_THREADS": "1"}
    replay = subprocess.Popen([sys.executable, "-m", "romannet.cli", "replay", "--config", str(config), "--dir",
                               str(tmp_path / "replay"), "--listen", endpoint], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        actor = subprocess.run([sys.executable, "-m", "romannet.cli", "actor", "--robot", "ur", "--camera",
                                "realsense", "--config", str(config), "--run-dir", str(tmp_path / "run"),
                                "--actor-id", "ur-0", "--max-actions", "3", "--connect", endpoint],
                               env=env, capture_output=True, text=True, timeout=90)
    finally:
        replay.terminate()
        replay.wait(30)
    assert actor.returncode == 0, actor.stderr[-3000:]
    status = json.loads((tmp_path / "run" / "actors" / "ur-0" / "status.json").read_text())
    assert status["actions"] == 3 and status["acked"] == 3 and status["spool_items"] == 0
    episodes = sorted((tmp_path / "run" / "episodes" / "ur-0").glob("*.mcap"))
    assert episodes and sum(count_steps(f) for f in episodes) == 3
    final = fakeworld().World.load(tmp_path / "state.json")
    assert len(final.moves()) >= 3 and all(-0.55 <= m["pose"][1] <= 0.55 for m in final.moves())


def test_romannet_calibrate_through_the_drivers_recovers_the_camera(tmp_path: Path, caplog):
    w = make_world()
    T = np.array(fakeworld().look_at((0.95, 0.1, 0.7), (0.5, 0.0, 0.1)))
    w.camera.T_base_cam = T.tolist()
    w.camera.depth_error_scale = 1.02
    w.board = {"board_offset_m": [0.0, 0.0, 0.0], "pattern_corners": [5, 4], "square_m": 0.02}
    sets = ['robot.host="ur-fake"', f"robot.home_pose={HOME}", "robot.vacuum_settle_s=0.0",
            "realsense.warmup_frames=1", "calibration.grid_x_m=[0.42, 0.58, 3]", "calibration.grid_y_m=[-0.08, 0.08, 3]",
            "calibration.grid_z_m=[0.12, 0.24, 2]", "calibration.settle_s=0", "calibration.min_poses=10",
            "calibration.tool_rotvec=[2.2, 0.0, -1.0]"]
    out = tmp_path / "cal.json"
    with fake_drivers(w):
        code = cli.main(["calibrate", "--out", str(out), *[a for s in sets for a in ("--set", s)]])
    assert code == 0, caplog.text[-2000:]
    cal = load_calibration(out)
    assert np.linalg.norm(cal.T_base_cam[:3, 3] - T[:3, 3]) < 0.002
    cos = (np.trace(cal.T_base_cam[:3, :3].T @ T[:3, :3]) - 1) / 2
    assert math.degrees(math.acos(min(1.0, cos))) < 0.5
    assert cal.depth_scale == pytest.approx(1.02, rel=0.005)
    assert out.with_suffix(".md").exists()
    assert np.allclose(w.tcp_pose, HOME)  # home at the end
    with fake_drivers(w):  # the same views against a residual bound nothing real meets: exit status 2
        strict = ["--set", "calibration.max_rms_error_m=1e-7", "--set", "calibration.grid_z_m=[0.12, 0.24, 1]"]
        assert cli.main(["calibrate", "--out", str(tmp_path / "strict.json"), *[a for s in sets for a in
                                                                                   ("--set", s)], *strict]) == 2
