"""Video files: their size, frame rate and frame count, and their frames as RGB arrays (OpenCV's decoder).

OpenCV comes with the `video` extra (`pip install -c constraints.txt -e '.[video]'`) and is imported only
when a video is opened, so the rest of ptrack runs without it. Frame numbers count from 0 in decoding
order; a frame is `(H, W, 3)` uint8 RGB, as decoded (OpenCV applies the file's rotation tag).

FFmpeg's own log (e.g. "moov atom not found" for a file that is no video) is silenced unless the
environment sets `OPENCV_FFMPEG_LOGLEVEL`: a file that cannot be decoded is reported once, as an
`InputError` naming it.
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType

import numpy as np

from ptrack.errors import InputError

log = logging.getLogger(__name__)

#: how to get what reading a video needs
INSTALL_HINT = "install the video extra: pip install -c constraints.txt -e '.[video]'"


def import_cv2() -> ModuleType:
    """OpenCV's module; InputError naming the `video` extra when it is not installed."""
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET; read when the decoder first loads
    try:
        import cv2
    except ImportError as e:
        raise InputError(f"reading a video needs OpenCV ({e}): {INSTALL_HINT}") from None
    return cv2


@dataclass(frozen=True)
class VideoInfo:
    """A video as its container describes it. frames: the count the container gives (0 when it gives none);
    fps: frames per second (NaN when it gives none); width, height: pixels of a decoded frame."""

    path: Path
    frames: int
    fps: float
    width: int
    height: int


def check_video_file(path: Path) -> None:
    """InputError naming `path` when it does not exist or is a folder (checked before OpenCV is needed)."""
    if not path.exists():
        raise InputError(f"video not found: {path}")
    if path.is_dir():
        raise InputError(f"video {path} is a folder, not a video file")


def _open(cv2: ModuleType, path: Path):  # -> cv2.VideoCapture
    check_video_file(path)
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        cap.release()
        raise InputError(f"cannot decode video {path}: not a video file OpenCV can read")
    return cap


def video_info(path: str | Path) -> VideoInfo:
    """Open `path`, decode its first frame and describe it. InputError: no such file, a folder, a file that
    is no video or has no frame that decodes, OpenCV not installed."""
    path = Path(path)
    check_video_file(path)  # a missing file is named before a missing OpenCV
    cv2 = import_cv2()
    cap = _open(cv2, path)
    try:
        ok, bgr = cap.read()
        if not ok or bgr is None or bgr.ndim != 3:
            raise InputError(f"cannot decode video {path}: no frame decodes")
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
    finally:
        cap.release()
    if not (math.isfinite(fps) and fps > 0):
        fps = math.nan
    return VideoInfo(path=path, frames=max(count, 0), fps=fps, width=int(bgr.shape[1]), height=int(bgr.shape[0]))


class VideoFrames:
    """The frames `start <= i < stop` of a video, each `(i, rgb)` with rgb `(H, W, 3)` uint8; a new pass over
    the file at each iteration. `len()` is the count the container announces (what a progress bar shows); a
    file that ends early ends the iteration early, with a warning."""

    def __init__(self, info: VideoInfo, start: int = 0, stop: int | None = None) -> None:
        if start < 0 or (stop is not None and stop < start):
            raise InputError(f"video frames {start}:{stop}: need 0 <= start <= stop")
        if info.frames and start >= info.frames:
            raise InputError(f"video {info.path} has {info.frames} frames: frame {start} is past its end")
        self.info, self.start = info, start
        if stop is None:
            self.stop: int | None = info.frames or None  # None: to the end, length unknown
        else:
            self.stop = min(stop, info.frames) if info.frames else stop

    def __len__(self) -> int:
        return max(0, (self.stop or 0) - self.start)

    def __iter__(self) -> Iterator[tuple[int, np.ndarray]]:
        cv2 = import_cv2()
        cap = _open(cv2, self.info.path)
        i = 0
        try:
            while self.stop is None or i < self.stop:
                if i < self.start:
                    ok = cap.grab()  # skipped: not converted
                    bgr = None
                else:
                    ok, bgr = cap.read()
                if not ok:
                    break
                if bgr is not None:
                    yield i, cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
                i += 1
        finally:
            cap.release()
        if self.stop is not None and i < self.stop:
            log.warning("video %s ended after %d frames, not the %d its container gives", self.info.path, i, self.stop)


def read_frames(path: str | Path, start: int = 0, stop: int | None = None) -> VideoFrames:
    """The RGB frames `start:stop` of the video at `path` (checked now: `video_info`'s errors)."""
    return VideoFrames(video_info(path), start, stop)
