"""`romannet mcap export FILE --video OUT.mp4 | --frames DIR`: one frame per recorded step, for people.

Each frame (romannet/mcaptools/render.py): the camera image before the action, the colour heightmap before
it with the executed net's Q map over it, the depth heightmap, the action drawn on both, and text: step, primitive, pixel, angle,
Q value, explored or greedy, success or failure (with the robot's reason), reward, progress before and
after, weights version, exploration rate, and the end reason on the last step. Lengths drawn come from
the config recorded in the file (push distance, the hand's opening, heightmap resolution). The video is
H.264 in an mp4 (romannet/mcaptools/video.py), which browsers play.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import tomllib

from romannet.common.config import Config
from romannet.common.configbase import from_dict
from romannet.common.episode_file import (
    CAMERA_COLOR_TOPIC,
    HEIGHTMAP_COLOR_TOPIC,
    HEIGHTMAP_DEPTH_TOPIC,
    Q_TOPIC_PREFIX,
    STEP_TOPIC,
    TRANSITION_TOPIC,
    EpisodeReader,
)
from romannet.common.errors import RomannetError
from romannet.common.heightmap import look_at
from romannet.common.imagecodec import decode_color_png, decode_depth_png, units_to_depth_m
from romannet.common.pictures import TEXT_BGR, ActionGlyph, camera_turns, tick_labels

from .bar import ProgressBar
from .render import FAIL_BGR, OK_BGR, StepView, compose, decode_compressed, decode_raw16
from .steps import RecordedStep, group_steps, parse_transition, primitive_of
from .video import VideoFile

log = logging.getLogger(__name__)

_TOPICS = (CAMERA_COLOR_TOPIC, HEIGHTMAP_COLOR_TOPIC, HEIGHTMAP_DEPTH_TOPIC, TRANSITION_TOPIC, STEP_TOPIC,
           *(f"{Q_TOPIC_PREFIX}{p}" for p in ("push", "pick", "place")))


def recorded_config(reader: EpisodeReader) -> Config | None:
    """The resolved config recorded in the file, or None if it is missing or does not load here."""
    try:
        return from_dict(Config, tomllib.loads(reader.config_toml)) if reader.config_toml else None
    except (tomllib.TOMLDecodeError, ValueError, TypeError) as err:
        log.warning("%s: the recorded config does not load (%s)", reader.path, err)
        return None


@dataclass(frozen=True)
class Geometry:
    """Lengths drawn, in heightmap pixels, and the camera image's quarter turns to the heightmaps' view."""

    push_length_px: float
    gripper_width_px: float
    camera_turns: int

    @classmethod
    def of(cls, cfg: Config | None) -> Geometry:
        """From the recorded config: the push distance, the hand's full opening (both fingers' travel) and
        the simulated camera's pose (a real camera's pose is not in the config: drawn as the sim's)."""
        cfg = cfg or Config()
        res, sim = cfg.workspace.resolution_m, cfg.sim
        pose = look_at(np.array(sim.camera_eye_m), np.array(sim.camera_target_m), np.array(sim.camera_up))
        return cls(sim.push_distance_m / res, 2 * sim.finger_travel_m / res, camera_turns(pose))


def _text_lines(step: RecordedStep, t, episode_id: str) -> tuple[tuple[str, tuple[int, int, int]], ...]:
    record = step.record or {}
    primitive = primitive_of(t)
    a = t.action
    deg = math.degrees(a.angle_rad)
    first = (f"{episode_id}  step {t.step}   {primitive.upper()} at row {a.row}, col {a.col}, {deg:.0f} deg   "
             f"Q {a.q_value:.3f}   {'explored' if a.explored else 'greedy'}")
    detail = f" ({record['detail']})" if record.get("detail") else ""
    second = (f"{'SUCCESS' if t.success else 'FAILED'}{detail}   reward {t.reward:.3f}   progress "
              f"{t.progress_before:.2f} -> {t.progress_after:.2f}")
    third = f"weights v{t.policy_version}   explore rate {t.explore_rate:.2f}"
    q_range = (record.get("q_ranges") or {}).get(primitive)
    if isinstance(q_range, list | tuple) and len(q_range) == 2:
        lo, hi = tick_labels([float(q_range[0]), float(q_range[1])])
        third += f"   Q map {lo}..{hi}"
    if t.done:
        third += f"   END: {t.done_reason or 'done'}"
    return ((first, TEXT_BGR), (second, OK_BGR if t.success else FAIL_BGR), (third, TEXT_BGR))


def _q_range(record: dict, primitive: str) -> tuple[float, float] | None:
    q_range = (record.get("q_ranges") or {}).get(primitive)
    if isinstance(q_range, list | tuple) and len(q_range) == 2 and float(q_range[1]) > float(q_range[0]):
        return float(q_range[0]), float(q_range[1])
    return None


def step_view(step: RecordedStep, episode_id: str, geometry: Geometry) -> StepView:
    """The StepView of a recorded step (images from the recorded observation before the action)."""
    t = parse_transition(step.transition.data)
    before = step.before
    if HEIGHTMAP_COLOR_TOPIC in before:
        heightmap = decode_compressed(before[HEIGHTMAP_COLOR_TOPIC].data)
    else:
        heightmap = cv2.cvtColor(decode_color_png(t.color_before_png), cv2.COLOR_RGB2BGR)
    if HEIGHTMAP_DEPTH_TOPIC in before:
        depth = units_to_depth_m(decode_raw16(before[HEIGHTMAP_DEPTH_TOPIC].data))
    else:
        depth = decode_depth_png(t.depth_before_png)
    camera = decode_compressed(before[CAMERA_COLOR_TOPIC].data) if CAMERA_COLOR_TOPIC in before else None
    primitive = primitive_of(t)
    q = decode_compressed(step.q_maps[primitive].data) if primitive in step.q_maps else None
    glyph = ActionGlyph(primitive, int(t.action.row), int(t.action.col), float(t.action.angle_rad),
                        geometry.push_length_px, geometry.gripper_width_px)
    return StepView(heightmap, depth, camera, geometry.camera_turns, q, _q_range(step.record or {}, primitive),
                    glyph, _text_lines(step, t, episode_id))


class FrameSink:
    """Writes frames to an H.264 mp4 (PyAV's libx264, yuv420p: what browsers play) and/or numbered PNGs;
    the video opens on the first frame, whose size every later frame is fitted to."""

    def __init__(self, video: Path | None, frames_dir: Path | None, fps: float):
        self.video_path, self.frames_dir, self.fps = video, frames_dir, fps
        self._video: VideoFile | None = None
        self.count = 0

    def write(self, frame: np.ndarray) -> None:
        if self.video_path is not None:
            if self._video is None:
                self._video = VideoFile(self.video_path, self.fps, frame.shape[1], frame.shape[0])
            self._video.write(frame)
        if self.frames_dir is not None:
            self.frames_dir.mkdir(parents=True, exist_ok=True)
            out = self.frames_dir / f"step_{self.count:05d}.png"
            if not cv2.imwrite(str(out), frame):
                raise RomannetError(f"cannot write {out}")
        self.count += 1

    def close(self) -> None:
        if self._video is not None:
            self._video.close()


def export_episode(path: str | Path, sink: FrameSink, panel_px: int = 448,
                   on_progress: Callable[[float, int], None] | None = None) -> int:
    """Render every step of the episode at `path` into `sink`; returns the number of frames."""
    reader = EpisodeReader(path)
    episode_id = ""
    geometry: Geometry | None = None
    for step in group_steps(reader.messages(_TOPICS)):
        if geometry is None:  # the metadata is read by now: it precedes every message
            geometry = Geometry.of(recorded_config(reader))
            episode_id = reader.episode.get("episode_id", "")
        sink.write(compose(step_view(step, episode_id, geometry), panel_px))
        if on_progress is not None:
            on_progress(step.transition.end_offset / max(reader.file_bytes, 1), sink.count)
    if reader.health is not None and (not reader.health.complete or reader.health.damaged):
        log.warning("%s: %s", path, reader.health.describe())
    return sink.count


def run_export(args: argparse.Namespace) -> int:
    """`romannet mcap export`; exit code 0 when at least one frame was written."""
    if args.video is None and args.frames is None:
        raise RomannetError("nothing to write: pass --video OUT.mp4 and/or --frames DIR")
    if not args.fps > 0 or not 64 <= args.size <= 4096:
        raise RomannetError(f"--fps {args.fps} / --size {args.size}: use fps > 0 and a size of 64..4096 px")
    sink = FrameSink(Path(args.video) if args.video else None, Path(args.frames) if args.frames else None, args.fps)
    try:
        with ProgressBar("export", "frames") as bar:
            frames = export_episode(args.file, sink, args.size,
                                    lambda fraction, n: bar.update(fraction, f"{n} frames", count=n))
    finally:
        sink.close()
    where = " and ".join(str(p) for p in (args.video, args.frames) if p)
    sys.stdout.write(f"wrote {frames} frame(s) of {args.file} to {where}\n")
    return 0 if frames else 1
