"""Frame transforms and the camera calibration in Foxglove's schemas: the simulator's real camera pose and
intrinsics, recorded with every observation, read back from the file, and consistent with the heightmaps
(a workspace point projected through /tf and /camera/calibration lands where the simulator's camera sees it).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms

from romannet.actor.recorder import EpisodeRecorder
from romannet.actor.scene_frames import SceneFrames, quaternion, scene_frames_of
from romannet.common.config import Config, WorkspaceConfig
from romannet.common.episode_file import read_episode
from romannet.common.heightmap import look_at
from romannet.common.interfaces import Observation

pytestmark = pytest.mark.timeout(120)


def rotation(q: tuple[float, float, float, float]) -> np.ndarray:
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


@pytest.mark.parametrize("eye,up", [((0.5, 0.0, 0.75), (-1.0, 0.0, 0.0)), ((0.1, -0.4, 0.9), (0.0, 0.0, 1.0)),
                                    ((0.5, 0.0, 0.75), (1.0, 0.0, 0.0)), ((0.9, 0.3, 0.5), (0.0, 1.0, 0.0))])
def test_quaternion_is_the_rotation(eye, up) -> None:
    T = look_at(np.array(eye), np.array((0.5, 0.0, 0.0)), np.array(up))
    q = quaternion(T[:3, :3])
    assert abs(np.linalg.norm(q) - 1.0) < 1e-9
    assert np.allclose(rotation(q), T[:3, :3], atol=1e-9)


def test_the_simulators_frames_are_recorded_with_every_observation(tmp_path: Path) -> None:
    from romannet.actor.sim.env import SimEnv

    ws = WorkspaceConfig(resolution_m=0.014)
    cfg = Config(workspace=ws)
    env = SimEnv.from_config(cfg)
    try:
        obs = env.reset(0)
        scene = scene_frames_of(env, cfg)
        T_true, K_true = env.scene.T_world_cam, env.scene.intrinsics
    finally:
        env.close()
    assert scene.T_world_cam is not None and scene.K is not None
    assert np.allclose(scene.T_world_cam[:3, 3], cfg.sim.camera_eye_m)
    rec = EpisodeRecorder(tmp_path / "ep.mcap", {"run_id": "r", "actor_id": "a", "episode_id": "e"}, scene=scene)
    try:
        rec.write_observation(obs, 1_000)
        rec.write_observation(obs, 2_000)
    finally:
        rec.close()
    episode = read_episode(tmp_path / "ep.mcap")
    tfs, calibs = episode.of("/tf"), episode.of("/camera/calibration")
    assert [m.log_time_ns for m in tfs] == [m.log_time_ns for m in calibs] == [1_000, 2_000]
    tf = FrameTransforms.FromString(tfs[0].data)
    by_child = {t.child_frame_id: t for t in tf.transforms}
    assert set(by_child) == {"camera", "heightmap"} and {t.parent_frame_id for t in tf.transforms} == {"world"}
    cam = by_child["camera"]
    R = rotation((cam.rotation.x, cam.rotation.y, cam.rotation.z, cam.rotation.w))
    t = np.array([cam.translation.x, cam.translation.y, cam.translation.z])
    assert np.allclose(R, T_true[:3, :3], atol=1e-6) and np.allclose(t, T_true[:3, 3])
    hm = by_child["heightmap"].translation
    assert (hm.x, hm.y, hm.z) == pytest.approx((ws.x_min_m, ws.y_min_m, ws.z_min_m))
    calib = CameraCalibration.FromString(calibs[0].data)
    assert (calib.frame_id, calib.width, calib.height) == ("camera", cfg.camera.width_px, cfg.camera.height_px)
    K = np.array(calib.K).reshape(3, 3)
    assert np.allclose(K, K_true)
    # The workspace centre, through the recorded frames, projects inside the image near its centre (the
    # default camera looks straight down at it), as the simulator renders it.
    centre = np.array([(ws.x_min_m + ws.x_max_m) / 2, (ws.y_min_m + ws.y_max_m) / 2, ws.z_min_m])
    p_cam = R.T @ (centre - t)
    u, v = (K @ p_cam)[:2] / p_cam[2]
    assert p_cam[2] > 0 and abs(u - calib.width / 2) < 5 and abs(v - calib.height / 2) < 5


def test_no_camera_pose_records_the_heightmap_frame_only(tmp_path: Path) -> None:
    obs = Observation(np.zeros((8, 8, 3), np.uint8), np.zeros((8, 8), np.float32), False)
    rec = EpisodeRecorder(tmp_path / "ep.mcap", {"run_id": "r", "actor_id": "a", "episode_id": "e"},
                          scene=SceneFrames((0.1, -0.2, 0.0)))
    try:
        rec.write_observation(obs, 5)
    finally:
        rec.close()
    episode = read_episode(tmp_path / "ep.mcap")
    assert episode.of("/camera/calibration") == []
    [tf] = [FrameTransforms.FromString(m.data) for m in episode.of("/tf")]
    assert [t.child_frame_id for t in tf.transforms] == ["heightmap"]
