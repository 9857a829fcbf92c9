"""MCAP episode recorder: one file per episode, images with Foxglove schemas, each step's Transition.

Channels (topic: schema, message encoding):

    /camera/color       foxglove.CompressedImage (jpeg or png)   raw camera frame, RGB
    /camera/depth       foxglove.RawImage 16UC1, millimetres     raw camera depth (the ROS convention)
    /heightmap/color    foxglove.CompressedImage png             orthographic color heightmap
    /heightmap/depth    foxglove.RawImage 16UC1, units of 1e-5 m heights above the workspace floor
    /q/<primitive>      foxglove.CompressedImage png             Q map of each net that ran, JET colormap,
                                                                 scaled min..max (the range is in /step)
    /tf                 foxglove.FrameTransforms                 world->camera, world->heightmap (scene_frames.py)
    /camera/calibration foxglove.CameraCalibration               the camera's intrinsics (simulated camera)
    /transition         romannet.v1.Transition (protobuf)        the executed step, as sent to replay
    /step               JSON (jsonschema)                        action, pose, X, P, reward, done reason,
                                                                 holding, weights version, LAE rate, ...

The first observation is logged at the episode's start; per step the Q maps at the decision time, then
at the action's end the observation after it, the Transition and the /step record (write_step flushes the
step's chunk). So a file of N steps holds N /transition messages and N + 1 observations.

Metadata records: "romannet" (run id, actor id, episode id, task, seed, weights version and exploration
rate at the start, units) and "config" (the resolved config as TOML). The writer flushes a chunk after
every step and the caller finishes the file in `finally`: a crash loses at most the step being written.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.RawImage_pb2 import RawImage
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_protobuf.schema import build_file_descriptor_set

from romannet.common.episode_file import STEP_SCHEMA, STEP_TOPIC, TRANSITION_TOPIC
from romannet.common.imagecodec import depth_m_to_units, encode_color_png
from romannet.common.interfaces import Observation
from romannet.common.wire import TransitionMsg, mcap_schema

from .scene_frames import SceneFrames, frame_messages

log = logging.getLogger(__name__)

__all__ = ["EpisodeRecorder", "colorize", "count_steps", "step_record", "STEP_TOPIC", "TRANSITION_TOPIC"]
_COMPRESSION = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
_STEP_SCHEMA = json.dumps({"type": "object", "title": STEP_SCHEMA,
                           "description": "One executed action of an actor, with its outcome and policy state"})


def colorize(q: np.ndarray) -> tuple[np.ndarray, float, float]:
    """(BGR uint8 JET image, q_min, q_max) of a Q map scaled min..max over its finite values."""
    finite = np.isfinite(q)
    lo = float(q[finite].min()) if finite.any() else 0.0
    hi = float(q[finite].max()) if finite.any() else 0.0
    scaled = np.zeros(q.shape, np.uint8)
    if hi > lo:
        scaled = np.clip((np.where(finite, q, lo) - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)
    return cv2.applyColorMap(scaled, cv2.COLORMAP_JET), lo, hi


def _png_bgr(img_bgr: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(".png", img_bgr, [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise ValueError(f"PNG encoding of a {img_bgr.shape} image failed")
    return buf.tobytes()


def _plain(value: Any) -> Any:
    """JSON for numpy scalars and arrays (actions and infos carry them)."""
    if isinstance(value, np.generic | np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


def step_record(msg: TransitionMsg, position_m: list[float], detail: str = "",
                q_ranges: dict[str, tuple[float, float]] | None = None,
                info: dict[str, Any] | None = None) -> dict[str, Any]:
    """The /step JSON record of a step: its transition's fields, plus what a transition does not carry
    (the action's robot-frame position, why it failed, the Q maps' colour scaling, the environment's info)."""
    a = msg.action
    return {"step": msg.step, "episode_id": msg.episode_id, "primitive": a.primitive, "row": a.row, "col": a.col,
            "angle_rad": a.angle_rad, "q_value": a.q_value, "explored": a.explored, "position_m": position_m,
            "success": msg.success, "progress_before": msg.progress_before, "progress_after": msg.progress_after,
            "reward": msg.reward, "done": msg.done, "done_reason": msg.done_reason, "detail": detail,
            "holding_before": msg.holding_before, "holding_after": msg.holding_after,
            "weights_version": msg.policy_version, "explore_rate": msg.explore_rate, "q_ranges": q_ranges or {},
            "info": info or {}}


def _stamp(msg: Any, t_ns: int, frame_id: str) -> Any:
    msg.timestamp.FromNanoseconds(int(t_ns))
    msg.frame_id = frame_id
    return msg


class EpisodeRecorder:
    """Writes one episode to `path` (created, parent folders too). Call close() in `finally`."""

    def __init__(self, path: str | Path, metadata: dict[str, str], config_toml: str = "",
                 chunk_bytes: int = 1 << 20, compression: str = "zstd", record_camera: bool = True,
                 camera_color_format: str = "jpeg", jpeg_quality: int = 90, scene: SceneFrames | None = None):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.record_camera = record_camera
        self.camera_color_format = camera_color_format
        self.jpeg_quality = int(jpeg_quality)
        self.scene = scene  # the frames, with every observation: a client joining mid-episode gets them too
        self.steps = 0
        self._file = open(self.path, "wb")  # noqa: SIM115 - closed in close(), which callers run in finally
        self._closed = False
        # The DataEnd CRC covers the metadata records too: a flipped bit in a value that still parses
        # (a config number, an id) is otherwise invisible to readers and `mcap inspect --verify`.
        self._writer = McapWriter(self._file, chunk_size=chunk_bytes, compression=_COMPRESSION[compression],
                                  enable_data_crcs=True)
        self._writer.start(profile="", library="romannet actor")
        self._channels: dict[str, int] = {}
        self._schema_ids: dict[str, int] = {}
        name, encoding, data = mcap_schema("Transition")
        self._transition_channel = self._writer.register_channel(
            TRANSITION_TOPIC, "protobuf", self._writer.register_schema(name, encoding, data))
        self._step_channel = self._writer.register_channel(
            STEP_TOPIC, "json", self._writer.register_schema(STEP_SCHEMA, "jsonschema",
                                                            _STEP_SCHEMA.encode()))
        meta = dict(metadata)
        meta.setdefault("camera_depth_units", "mm (16UC1)")
        meta.setdefault("heightmap_depth_units", "1e-5 m above the workspace floor (16UC1)")
        self._writer.add_metadata("romannet", {k: str(v) for k, v in meta.items()})
        if config_toml:
            self._writer.add_metadata("config", {"toml": config_toml})

    # ------------------------------------------------------------------------------------- helpers
    def _channel(self, topic: str, message_class: Any) -> int:
        if topic not in self._channels:
            full_name = message_class.DESCRIPTOR.full_name
            if full_name not in self._schema_ids:
                fds = build_file_descriptor_set(message_class).SerializeToString()
                self._schema_ids[full_name] = self._writer.register_schema(full_name, "protobuf", fds)
            self._channels[topic] = self._writer.register_channel(topic, "protobuf", self._schema_ids[full_name])
        return self._channels[topic]

    def _write(self, topic: str, msg: Any, t_ns: int) -> None:
        self._writer.add_message(self._channel(topic, type(msg)), log_time=int(t_ns), data=msg.SerializeToString(),
                                 publish_time=int(t_ns))

    def _compressed(self, topic: str, data: bytes, fmt: str, t_ns: int, frame_id: str) -> None:
        self._write(topic, _stamp(CompressedImage(data=data, format=fmt), t_ns, frame_id), t_ns)

    def _raw16(self, topic: str, units: np.ndarray, t_ns: int, frame_id: str) -> None:
        units = np.ascontiguousarray(units, dtype="<u2")
        msg = RawImage(width=units.shape[1], height=units.shape[0], encoding="16UC1", step=units.shape[1] * 2,
                       data=units.tobytes())
        self._write(topic, _stamp(msg, t_ns, frame_id), t_ns)

    # ---------------------------------------------------------------------------------------- API
    def write_observation(self, obs: Observation, t_ns: int) -> None:
        """Both heightmaps and (if recorded and present) the camera frame, stamped t_ns (ns since epoch)."""
        self._compressed("/heightmap/color", encode_color_png(obs.color_hm, level=1), "png", t_ns, "heightmap")
        self._raw16("/heightmap/depth", depth_m_to_units(obs.depth_hm), t_ns, "heightmap")
        for topic, msg in frame_messages(self.scene, t_ns) if self.scene is not None else ():
            self._write(topic, msg, t_ns)
        if not self.record_camera:
            return
        if obs.camera_color is not None:
            bgr = cv2.cvtColor(np.ascontiguousarray(obs.camera_color[..., :3]), cv2.COLOR_RGB2BGR)
            if self.camera_color_format == "jpeg":
                ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
            else:
                ok, buf = cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, 1])
            if ok:
                self._compressed("/camera/color", buf.tobytes(), self.camera_color_format, t_ns, "camera")
        if obs.camera_depth_m is not None:
            depth = np.nan_to_num(np.asarray(obs.camera_depth_m, np.float64), nan=0.0, posinf=0.0, neginf=0.0)
            self._raw16("/camera/depth", np.clip(np.rint(depth * 1000.0), 0, 65535).astype(np.uint16), t_ns,
                        "camera")

    def write_q_maps(self, q_maps: dict[str, np.ndarray], t_ns: int) -> dict[str, tuple[float, float]]:
        """Each net's Q map as a colormapped PNG; returns {primitive: (q_min, q_max)} of the scaling."""
        ranges = {}
        for primitive, q in q_maps.items():
            img, lo, hi = colorize(q)
            self._compressed(f"/q/{primitive}", _png_bgr(img), "png", t_ns, "heightmap")
            ranges[primitive] = (lo, hi)
        return ranges

    def write_step(self, transition_bytes: bytes, extras: dict[str, Any], t_ns: int) -> None:
        """The step's encoded Transition and its JSON record (extras), then flush the chunk to the file."""
        self._writer.add_message(self._transition_channel, log_time=int(t_ns), data=transition_bytes,
                                 publish_time=int(t_ns), sequence=self.steps)
        self._writer.add_message(self._step_channel, log_time=int(t_ns), data=json.dumps(extras, default=_plain).encode(),
                                 publish_time=int(t_ns), sequence=self.steps)
        self.steps += 1
        self._writer.flush()  # one chunk per step: a crash loses at most the step being written

    def close(self, summary: dict[str, Any] | None = None) -> None:
        """Write the closing metadata (e.g. the done reason) and the summary, and close the file. Idempotent."""
        if self._closed:
            return
        self._closed = True
        try:
            if summary is not None:
                self._writer.add_metadata("episode_end", {k: str(v) for k, v in summary.items()})
            self._writer.finish()
        finally:
            self._file.close()


def count_steps(path: str | Path) -> int:
    """Transition messages in an MCAP episode, read front to back without seeking, so it works on files
    that were never finished (a crash): what is unreadable at the end is not counted."""
    steps, channel_ids = 0, set()
    with open(path, "rb") as f:
        try:
            for record in StreamReader(f, skip_magic=False).records:
                if isinstance(record, Channel) and record.topic == TRANSITION_TOPIC:
                    channel_ids.add(record.id)
                elif isinstance(record, Message) and record.channel_id in channel_ids:
                    steps += 1
        except Exception as err:  # a truncated last chunk: everything before it counted
            log.debug("%s: stopped reading at a damaged record: %s", path, err)
    return steps

