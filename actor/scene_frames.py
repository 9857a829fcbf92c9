"""Where the camera and the heightmaps sit, in Foxglove's schemas, so the app's 3D panel can place them.

Frames: "world" is the robot base frame (the workspace bounds and /step's position_m are in it);
"camera" is the camera's optical frame (OpenCV: x right, y down, z forward, what foxglove.CameraCalibration
assumes); "heightmap" has its origin at the workspace corner (x_min, y_min, z_min), x along the heightmap's
columns and y along its rows (common/action.pixel_to_position), z up.

Recorded with every observation (actor/recorder.py): /tf (foxglove.FrameTransforms: world->camera,
world->heightmap) and /camera/calibration (foxglove.CameraCalibration), so a player or a live client that
joins mid-episode has them with the next step.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms

from romannet.common.config import Config
from romannet.common.interfaces import Env

TF_TOPIC, CALIBRATION_TOPIC = "/tf", "/camera/calibration"
WORLD, CAMERA, HEIGHTMAP = "world", "camera", "heightmap"


@dataclass(frozen=True, eq=False)
class SceneFrames:
    """T_world_cam: 4x4 camera pose (None: unknown); K: 3x3 intrinsics (None: unknown, no calibration
    recorded); width, height: the camera image in pixels; heightmap_origin: the workspace corner, metres."""

    heightmap_origin: tuple[float, float, float]
    T_world_cam: np.ndarray | None = None
    K: np.ndarray | None = None
    width: int = 0
    height: int = 0


def scene_frames_of(env: Env, cfg: Config) -> SceneFrames:
    """The frames of an actor's environment: the simulator's camera pose and intrinsics, or a real robot's
    camera-to-base calibration (its intrinsics come from the device with each frame: not recorded here)."""
    ws = cfg.workspace
    origin = (ws.x_min_m, ws.y_min_m, ws.z_min_m)
    T, K = env.camera_pose()
    if T is not None and K is not None:
        return SceneFrames(origin, np.asarray(T, float), np.asarray(K, float), cfg.camera.width_px,
                           cfg.camera.height_px)
    return SceneFrames(origin, None if T is None else np.asarray(T, float))


def quaternion(R: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix (Shepperd's method: stable for every rotation)."""
    m = np.asarray(R, float)
    t = np.trace(m)
    if t > 0:
        s = 2.0 * np.sqrt(t + 1.0)
        return ((m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s)
    i = int(np.argmax(np.diag(m)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = 2.0 * np.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
    q = [0.0, 0.0, 0.0]
    q[i], q[j], q[k] = 0.25 * s, (m[j, i] + m[i, j]) / s, (m[k, i] + m[i, k]) / s
    return q[0], q[1], q[2], (m[k, j] - m[j, k]) / s


def _transform(t_ns: int, child: str, translation: Any, R: np.ndarray) -> FrameTransform:
    msg = FrameTransform(parent_frame_id=WORLD, child_frame_id=child)
    msg.timestamp.FromNanoseconds(int(t_ns))
    msg.translation.x, msg.translation.y, msg.translation.z = (float(v) for v in translation)
    msg.rotation.x, msg.rotation.y, msg.rotation.z, msg.rotation.w = quaternion(R)
    return msg


def frame_messages(scene: SceneFrames, t_ns: int) -> list[tuple[str, Any]]:
    """(topic, message) of /tf and, with intrinsics, /camera/calibration at time t_ns."""
    transforms = [_transform(t_ns, HEIGHTMAP, scene.heightmap_origin, np.eye(3))]
    if scene.T_world_cam is not None:
        transforms.append(_transform(t_ns, CAMERA, scene.T_world_cam[:3, 3], scene.T_world_cam[:3, :3]))
    out: list[tuple[str, Any]] = [(TF_TOPIC, FrameTransforms(transforms=transforms))]
    if scene.K is not None:
        K = [float(v) for v in scene.K.reshape(-1)]
        calib = CameraCalibration(frame_id=CAMERA, width=scene.width, height=scene.height,
                                  distortion_model="plumb_bob", D=[0.0] * 5, K=K,
                                  R=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
                                  P=[K[0], K[1], K[2], 0.0, K[3], K[4], K[5], 0.0, 0.0, 0.0, 1.0, 0.0])
        calib.timestamp.FromNanoseconds(int(t_ns))
        out.append((CALIBRATION_TOPIC, calib))
    return out
