"""The offline 2D detector: MediaPipe Pose on every frame of a video, and its landmarks file.

`detect(video)` runs `mediapipe.solutions.pose.Pose(model_complexity=1, static_image_mode=False)` (the
model shipped inside the `mediapipe==0.10.14` wheel; complexities 0 and 2 download theirs at run time)
frame by frame in decoding order, tracking one person from frame to frame as MediaPipe's video mode does
(its landmark smoothing takes every video as 30 fps: the Python API stamps frames 1/30 s apart). There is no
randomness: the same frames give the same landmarks.

Per frame and landmark (the 33 of MediaPipe Pose, `ptrack.body.keypoint_sets.MEDIAPIPE_33`):
- image landmarks in pixels: MediaPipe's normalised (x, y) times the decoded frame's (W, H), so the
  image's left/top edge is at 0 (OpenCV's pixel-centre convention puts it at -0.5); they may lie outside
  the image (MediaPipe predicts landmarks it does not see). The score is MediaPipe's `visibility`.
- world landmarks: MediaPipe's own 3D estimate, metres, origin between the hips, axes roughly the
  camera's (x right, y down, z away from the camera).
A frame where MediaPipe finds nobody has score 0 and NaN coordinates.

The result is a `ptrack.observe.keypoint_files.MediaPipeLandmarks`; `write_mediapipe_landmarks` there writes
it as the landmarks file (layout in that module's docstring) that `read_keypoints` reads back.
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import tempfile
import warnings
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from types import ModuleType

import numpy as np

from ptrack.body.keypoint_sets import MEDIAPIPE_33
from ptrack.errors import InputError
from ptrack.observe.keypoint_files import MediaPipeLandmarks
from ptrack.observe.video import INSTALL_HINT, read_frames

log = logging.getLogger(__name__)

K = MEDIAPIPE_33.num_keypoints
#: MediaPipe Pose's model: 1 is the one inside the wheel (0 and 2 download theirs)
MODEL_COMPLEXITY = 1
#: the version of what `detect` makes of MediaPipe's output: raise it when that changes for the same video, so
#: that cached detections (`ptrack.pipeline.detections`, keyed on it) are made again
OUTPUT_VERSION = 1


def import_mediapipe() -> ModuleType:
    """MediaPipe's module; InputError naming the `video` extra when it is not installed."""
    try:
        import mediapipe
    except ImportError as e:
        raise InputError(f"detecting people in a video needs MediaPipe ({e}): {INSTALL_HINT}") from None
    return mediapipe


@contextlib.contextmanager
def _native_stderr_to_log() -> Iterator[None]:
    """Hold what native code writes to file descriptor 2 (TensorFlow Lite's and absl's start-up notes, which
    bypass Python) and log it at DEBUG instead; Python's own warnings inside are logged the same way."""
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):  # no real stderr (an embedding host): nothing to hold
        fd = None
    with tempfile.TemporaryFile() as held, warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        saved = None
        if fd is not None:
            sys.stderr.flush()
            saved = os.dup(fd)
            os.dup2(held.fileno(), fd)
        try:
            yield
        finally:
            if saved is not None:
                os.dup2(saved, fd)  # type: ignore[arg-type]  # fd is set when saved is
                os.close(saved)
            held.seek(0)
            for line in held.read().decode(errors="replace").splitlines():
                log.debug("mediapipe: %s", line)
            for w in caught:
                log.debug("mediapipe: %s", w.message)


def detect(
    video: str | Path,
    progress: Callable[[Iterable], Iterable] | None = None,
    start: int = 0,
    stop: int | None = None,
    min_detection_confidence: float = 0.5,
    min_tracking_confidence: float = 0.5,
    smooth_landmarks: bool = True,
) -> MediaPipeLandmarks:
    """MediaPipe Pose on the frames `start:stop` of `video` -> `MediaPipeLandmarks` (T = the frames decoded).

    progress: wraps the iterable of frames (`(frame number, rgb)`, sized by the container's count), e.g. a
    progress bar; None: none. The confidences and `smooth_landmarks` are MediaPipe's options. InputError: the
    video is missing or cannot be decoded, OpenCV or MediaPipe is not installed, a confidence outside [0, 1].
    """
    for name, value in (
        ("min_detection_confidence", min_detection_confidence),
        ("min_tracking_confidence", min_tracking_confidence),
    ):
        if not 0.0 <= value <= 1.0:
            raise InputError(f"{name} must lie in [0, 1], got {value}")
    frames = read_frames(video, start, stop)  # the video's errors before MediaPipe loads
    info = frames.info
    mp = import_mediapipe()
    numbers: list[int] = []
    image: list[np.ndarray] = []
    world: list[np.ndarray] = []
    scale = np.array([info.width, info.height, 1.0])
    missing = np.full((K, 3), np.nan)
    pose = None
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="SymbolDatabase.GetPrototype", category=UserWarning)  # protobuf's
        try:
            for i, rgb in (progress or (lambda it: it))(frames):
                if pose is None:
                    # the graph writes its start-up notes from its own threads, from the constructor on
                    with _native_stderr_to_log():
                        pose = mp.solutions.pose.Pose(
                            static_image_mode=False,
                            model_complexity=MODEL_COMPLEXITY,
                            smooth_landmarks=smooth_landmarks,
                            enable_segmentation=False,
                            min_detection_confidence=min_detection_confidence,
                            min_tracking_confidence=min_tracking_confidence,
                        )
                        result = pose.process(rgb)
                else:
                    result = pose.process(rgb)
                numbers.append(i)
                if result.pose_landmarks is None:
                    image.append(np.concatenate([missing[:, :2], np.zeros((K, 1))], axis=1))
                    world.append(missing)
                    continue
                lm = [(p.x, p.y, p.visibility) for p in result.pose_landmarks.landmark]
                image.append(np.array(lm, dtype=np.float64) * scale)
                w = result.pose_world_landmarks
                world.append(missing if w is None else np.array([(p.x, p.y, p.z) for p in w.landmark], dtype=float))
        finally:
            if pose is not None:
                pose.close()
    T = len(numbers)
    out = MediaPipeLandmarks(
        frames=np.asarray(numbers, dtype=np.int64),
        landmarks=np.stack(image) if T else np.zeros((0, K, 3)),
        world_landmarks=np.stack(world) if T else np.zeros((0, K, 3)),
        fps=info.fps,
        width=info.width,
        height=info.height,
        video=str(video),
    )
    log.info("%s: a person in %d of %d frames", video, int(out.found.sum()), T)
    return out


def check_output(path: str | Path) -> Path:
    """InputError if a landmarks file could not be written at `path` (a folder, or under a file, or in a folder
    this process may not write in); checked before a detection that takes minutes."""
    path = Path(path)
    if path.is_dir():
        raise InputError(f"landmarks output {path} is a folder; give a file name (e.g. {path / 'video.landmarks.npz'})")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(f"landmarks output {path}: {parent} is a file, not a folder")
            if not os.access(parent, os.W_OK):
                raise InputError(f"landmarks output {path}: cannot write in {parent}")
            break
    return path


def default_output(video: str | Path) -> Path:
    """`VIDEO_STEM.landmarks.npz` in the current folder."""
    return Path(f"{Path(video).stem}.landmarks.npz")
