"""H.264 video files through PyAV (FFmpeg's libx264, bundled in PyAV's wheels): yuv420p in an mp4 with its
index at the front (faststart), which browsers play as they load it. OpenCV's mp4 writer can only give
MPEG-4 Part 2 (mp4v), which browsers do not play.
"""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import av
import cv2
import numpy as np

from romannet.common.errors import RomannetError

CODEC = "libx264"


def fit(frame: np.ndarray, width: int, height: int) -> np.ndarray:
    """The frame cropped or padded (black, bottom and right) to width x height."""
    frame = frame[:height, :width]
    pad_h, pad_w = height - frame.shape[0], width - frame.shape[1]
    if pad_h or pad_w:
        frame = cv2.copyMakeBorder(frame, 0, pad_h, 0, pad_w, cv2.BORDER_CONSTANT, value=(0, 0, 0))
    return frame


class VideoFile:
    """An H.264 mp4 of BGR uint8 frames of one size (even width and height); call close() to finish it."""

    def __init__(self, path: Path, fps: float, width: int, height: int, crf: int = 23):
        if width % 2 or height % 2:
            raise RomannetError(f"{path}: H.264 in yuv420p needs an even frame size, not {width}x{height}")
        self.path, self.width, self.height = path, width, height
        self._closed = False
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._container = av.open(str(path), mode="w", format="mp4", options={"movflags": "+faststart"})
        except (OSError, av.FFmpegError) as err:
            raise RomannetError(f"cannot write {path}: {err}") from None
        try:
            self._stream = self._container.add_stream(CODEC, rate=Fraction(fps).limit_denominator(1001))
        except (ValueError, av.FFmpegError) as err:  # a PyAV built without libx264
            self._container.close()
            raise RomannetError(f"cannot write {path}: this PyAV has no {CODEC} encoder ({err})") from None
        self._stream.width, self._stream.height, self._stream.pix_fmt = width, height, "yuv420p"
        self._stream.options = {"crf": str(crf), "preset": "veryfast"}  # a few times faster than medium

    def write(self, frame_bgr: np.ndarray) -> None:
        frame = av.VideoFrame.from_ndarray(np.ascontiguousarray(fit(frame_bgr, self.width, self.height)),
                                           format="bgr24")
        self._encode(frame)

    def _encode(self, frame: av.VideoFrame | None) -> None:
        """Encode a frame (None: flush) and mux its packets; an error (the file cannot be written: a
        directory, a full disk) closes the file and is one RomannetError."""
        try:
            for packet in self._stream.encode(frame):
                self._container.mux(packet)
        except (OSError, av.FFmpegError) as err:
            self._closed = True
            try:
                self._container.close()
            except (OSError, av.FFmpegError):
                pass  # already failing: the first error is the one to tell
            raise RomannetError(f"cannot write {self.path}: {err}") from None

    def close(self) -> None:
        """Flush the encoder and finish the file (once; nothing after a write error)."""
        if self._closed:
            return
        self._encode(None)
        self._closed = True
        self._container.close()


def video_codec(path: Path) -> tuple[str, str, int]:
    """(codec name, pixel format, decoded frame count) of a video file's first video stream, read back."""
    with av.open(str(path)) as container:
        stream = container.streams.video[0]
        name, pix_fmt = stream.codec_context.name, stream.codec_context.pix_fmt
        return name, pix_fmt, sum(1 for _ in container.decode(stream))
