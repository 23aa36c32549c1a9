"""Detections for a run's video: MediaPipe Pose on the whole video, done once per video and kept.

`detections_for_video(video, out_dir)` writes `out_dir/detections.npz`, the MediaPipe landmarks file that
`ptrack detect` writes (`ptrack.observe.keypoint_files`, read back by `read_keypoints`), and returns its path.
The detection is cached: the first run on a video stores its landmarks in the cache folder under the video's
key; a later run on a video with the same key copies them instead of detecting again (minutes saved).

The key (`video_key`) is the sha256 of
- the video file's size in bytes and its first and last MiB (`FINGERPRINT_BYTES`): the same content, whatever
  the file's name, path or time stamps (a video container keeps its frame index at one end, so an edit moves
  one of these; two files that differ only in the middle of the stream, at the same size, are taken as one);
- the detector: `ptrack.observe.detector.OUTPUT_VERSION`, its MediaPipe model (`MODEL_COMPLEXITY`), the
  installed mediapipe version and the options `detect` is given (`DETECT_OPTIONS`).
A cache entry is `CACHE/<key>.npz`. The cache folder is `cache_dir` when given, else
`$XDG_CACHE_HOME/ptrack/detections`, else `~/.cache/ptrack/detections` (beside the motion models in
`~/.cache/ptrack/motion`). Deleting it only costs a detection.

Every file is written whole or not at all (a hidden file beside it, renamed when complete), so an interrupted
detection leaves neither a cache entry nor `detections.npz`. A cache entry that does not read as a landmarks
file (truncated, bytes changed: the npz members' CRC) is logged, detected again and replaced. A cache folder
that cannot be written is logged and the run goes on without it.
"""

from __future__ import annotations

import hashlib
import logging
import os
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, replace
from importlib import metadata
from pathlib import Path

from ptrack.errors import InputError
from ptrack.observe import detector
from ptrack.observe.keypoint_files import MediaPipeLandmarks, read_mediapipe_landmarks, write_mediapipe_landmarks
from ptrack.observe.video import check_video_file

log = logging.getLogger(__name__)

#: the bytes read from each end of a video for its key
FINGERPRINT_BYTES = 1 << 20


@dataclass(frozen=True)
class DetectOptions:
    """The options a run's detection passes to `detect` (MediaPipe's), stated so that the key names them."""

    min_detection_confidence: float = 0.5
    min_tracking_confidence: float = 0.5
    smooth_landmarks: bool = True


DETECT_OPTIONS = DetectOptions()
#: the file written in the run folder
DETECTIONS_FILE = "detections.npz"


def default_cache_dir() -> Path:
    """`$XDG_CACHE_HOME/ptrack/detections`, or `~/.cache/ptrack/detections` when XDG_CACHE_HOME is unset."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "ptrack" / "detections"


def _mediapipe_version() -> str:
    try:
        return metadata.version("mediapipe")
    except metadata.PackageNotFoundError:  # not installed (InputError naming the video extra) or no metadata
        return str(getattr(detector.import_mediapipe(), "__version__", "unknown"))


def video_key(video: str | Path) -> str:
    """The cache key of detecting `video` (module docstring): 64 hex digits. InputError: no such file, a folder,
    an unreadable file, MediaPipe not installed."""
    video = Path(video)
    check_video_file(video)
    h = hashlib.sha256()
    detector_id = (
        f"ptrack-detections output={detector.OUTPUT_VERSION} model_complexity={detector.MODEL_COMPLEXITY} "
        f"mediapipe={_mediapipe_version()} " + " ".join(f"{k}={v}" for k, v in sorted(asdict(DETECT_OPTIONS).items()))
    )
    h.update(detector_id.encode())
    try:
        with open(video, "rb") as f:
            size = os.fstat(f.fileno()).st_size
            h.update(f"\nsize={size}\n".encode())
            h.update(f.read(FINGERPRINT_BYTES))
            f.seek(max(size - FINGERPRINT_BYTES, 0))
            h.update(f.read(FINGERPRINT_BYTES))
    except OSError as e:
        raise InputError(f"cannot read video {video} ({e.strerror})") from None
    return h.hexdigest()


def _cached(entry: Path) -> MediaPipeLandmarks | None:
    """The landmarks of a cache entry; None when there is none or it does not read (logged)."""
    if not entry.exists():
        return None
    try:
        return read_mediapipe_landmarks(entry)
    except InputError as e:
        log.warning("cached detections %s cannot be read (%s): detecting again", entry, e)
        return None  # replaced once detected


def detections_for_video(
    video: str | Path,
    out_dir: str | Path,
    progress: Callable[[Iterable], Iterable] | None = None,
    cache_dir: str | Path | None = None,
) -> Path:
    """MediaPipe's landmarks of every frame of `video` as `out_dir/detections.npz` (the `ptrack detect` layout;
    its `video` is the path given here) -> that path; reused from the cache when the same video was detected
    before (module docstring: key, folder, atomic writes).

    progress: wraps the frames while detecting, as `detect`'s. cache_dir: None = `default_cache_dir()`.
    InputError: `detect`'s (a video that is missing or does not decode, the video extra not installed)."""
    video = Path(video)
    out = Path(out_dir) / DETECTIONS_FILE
    key = video_key(video)
    cache = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    entry = cache / f"{key}.npz"
    found = _cached(entry)
    if found is not None:
        log.info("%s: detections reused from %s", video, entry)
    else:
        o = DETECT_OPTIONS
        found = detector.detect(
            video,
            progress=progress,
            min_detection_confidence=o.min_detection_confidence,
            min_tracking_confidence=o.min_tracking_confidence,
            smooth_landmarks=o.smooth_landmarks,
        )
        try:
            write_mediapipe_landmarks(entry, found)
        except OSError as e:
            log.warning("cannot keep the detections of %s in %s (%s): they are not cached", video, cache, e)
    return write_mediapipe_landmarks(out, replace(found, video=str(video)))
