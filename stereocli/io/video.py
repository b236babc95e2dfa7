"""Video files for stereo sequences: probing, decoding frames, splitting stacked views, writing.

Videos are decoded with OpenCV's ``VideoCapture`` (its FFmpeg backend) and frames come out as
RGB, as :func:`~stereocli.io.images.read_image` gives images. A file is a video when its suffix
says so (:data:`VIDEO_SUFFIXES`), or, for a suffix that is neither a video's nor an image's,
when FFmpeg opens it and decodes frames.

A stereo video holds both views in one frame: ``side-by-side`` (left half = left view) or
``top-bottom`` (top half = left view) (:data:`STACKED_LAYOUTS`).
"""

from __future__ import annotations

import contextlib
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..errors import DataError
from .images import IMAGE_SUFFIXES

#: Suffixes read as videos.
VIDEO_SUFFIXES = (".mp4", ".m4v", ".mov", ".avi", ".mkv", ".webm", ".mpg", ".mpeg", ".ts", ".mts", ".wmv",
                  ".flv", ".ogv", ".3gp")
#: Layouts of one video holding both views: the left view in the left (top) half.
STACKED_LAYOUTS = ("side-by-side", "top-bottom")
#: FourCC codes :func:`open_writer` tries for each output suffix, first that opens wins.
WRITER_CODECS = {".mp4": ("mp4v", "avc1"), ".m4v": ("mp4v",), ".mov": ("mp4v",), ".avi": ("MJPG", "XVID"),
                 ".mkv": ("FFV1", "mp4v", "MJPG")}


@dataclass(frozen=True)
class VideoInfo:
    """What :func:`probe_video` found: frame size (px), rate (frames per second, None when the
    file gives none), the frames that decode, and the count the file's header states."""

    path: str
    width: int
    height: int
    fps: float | None
    frames: int
    header_frames: int


def _capture(path: str | os.PathLike):
    import cv2

    capture = cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)
    if not capture.isOpened():
        capture.release()
        raise DataError(f"{path}: cannot be read as a video (OpenCV's FFmpeg backend does not open it)")
    return capture


def is_video(path: str | os.PathLike) -> bool:
    """Whether ``path`` (an existing file) is a video: by its suffix, else (a suffix that is no
    image's) when FFmpeg opens it and decodes two frames (one frame is a picture, not a video)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix in VIDEO_SUFFIXES:
        return True
    if suffix in IMAGE_SUFFIXES or not path.is_file():
        return False
    try:
        capture = _capture(path)
    except DataError:
        return False
    try:
        return bool(capture.grab() and capture.grab())
    finally:
        capture.release()


def probe_video(path: str | os.PathLike) -> VideoInfo:
    """Open ``path`` and count the frames that decode (the header's count is often an estimate).

    Raises :class:`DataError` naming the file when it does not open or no frame decodes.
    """
    import cv2

    capture = _capture(path)
    try:
        width = int(capture.get(cv2.CAP_PROP_FRAME_WIDTH))
        height = int(capture.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(capture.get(cv2.CAP_PROP_FPS))
        header = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        frames = 0
        while capture.grab():
            frames += 1
    finally:
        capture.release()
    if frames == 0 or width <= 0 or height <= 0:
        raise DataError(f"{path}: no video frame decodes (empty, truncated or not a video)")
    return VideoInfo(str(path), width, height, fps if np.isfinite(fps) and fps > 0 else None, frames, max(header, 0))


class FrameReader:
    """The frames of one video in order, RGB ``(H, W, 3)`` uint8 (grey videos too: FFmpeg gives
    colour). :meth:`read` may skip forward; going back reopens the file."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = str(path)
        self._capture: Any = None
        self._next = 0  # index of the frame the next decode gives

    def read(self, index: int) -> np.ndarray:
        """Frame ``index`` (0-based). Raises :class:`DataError` when the video ends before it."""
        import cv2

        if self._capture is None or index < self._next:
            self.close()
            self._capture, self._next = _capture(self.path), 0
        capture = self._capture
        while self._next < index:
            if not capture.grab():
                raise DataError(f"{self.path}: the video ends after {self._next} frames (frame {index} asked for)")
            self._next += 1
        ok, frame = capture.read()
        if not ok or frame is None:
            raise DataError(f"{self.path}: frame {index} does not decode (the video ends or is damaged there)")
        self._next += 1
        if frame.ndim == 2:
            return frame
        return cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)

    def close(self) -> None:
        if self._capture is not None:
            self._capture.release()
            self._capture = None


def split_stacked(frame: np.ndarray, layout: str, source: str = "") -> tuple[np.ndarray, np.ndarray]:
    """The ``(left, right)`` views of a ``side-by-side`` or ``top-bottom`` frame (views of
    ``frame``, no copy). Raises :class:`DataError` when the split side has an odd length."""
    if layout not in STACKED_LAYOUTS:
        raise ValueError(f"layout must be one of {', '.join(STACKED_LAYOUTS)}, got {layout!r}")
    axis = 1 if layout == "side-by-side" else 0
    length = frame.shape[axis]
    if length % 2:
        what = "width" if axis else "height"
        raise DataError(f"{source + ': ' if source else ''}{layout} frames need an even {what} to split into two "
                        f"views; this one is {length} px")
    half = length // 2
    if axis:
        return frame[:, :half], frame[:, half:]
    return frame[:half], frame[half:]


@contextlib.contextmanager
def open_writer(path: str | os.PathLike, fps: float, size: tuple[int, int]) -> Iterator:
    """A ``VideoWriter`` for ``path`` (``size`` = (width, height) px), written under a temporary
    name and renamed onto ``path`` when the block succeeds (:func:`~stereocli.io.atomic.atomic_path`).
    Its ``write`` takes RGB ``(H, W, 3)`` uint8 frames. The codec follows the suffix
    (:data:`WRITER_CODECS`); raises :class:`DataError` when none opens."""
    import cv2

    from .atomic import atomic_path

    suffix = Path(path).suffix.lower()
    if suffix not in WRITER_CODECS:
        raise DataError(f"{path}: cannot write a video of this kind; use one of {', '.join(WRITER_CODECS)}")
    with atomic_path(path) as tmp:
        writer = None
        for code in WRITER_CODECS[suffix]:
            writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*code), float(fps), size)
            if writer.isOpened():
                break
            writer.release()
            writer = None
        if writer is None:
            raise DataError(f"{path}: OpenCV has no codec to write {suffix} videos here "
                            f"(tried {', '.join(WRITER_CODECS[suffix])})")
        try:
            yield _RgbWriter(writer, size)
        finally:
            writer.release()


class _RgbWriter:
    """Takes RGB frames for an OpenCV (BGR) ``VideoWriter``."""

    def __init__(self, writer, size: tuple[int, int]) -> None:
        self._writer, self.size = writer, size

    def write(self, frame: np.ndarray) -> None:
        import cv2

        if (frame.shape[1], frame.shape[0]) != self.size:
            raise ValueError(f"frame of {frame.shape[1]}x{frame.shape[0]} for a {self.size[0]}x{self.size[1]} video")
        self._writer.write(cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2BGR))
