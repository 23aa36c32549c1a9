"""Detections for a run's video (`ptrack.pipeline.detections`): detected once per video content, cached, copied
into the run folder; corrupt cache entries and interruptions. `detect` is replaced by a counting fake except
in the last test, which runs MediaPipe on 5 frames of the Pose2Sim video (skipped without it)."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from ptrack.errors import InputError
from ptrack.observe import detector
from ptrack.observe.keypoint_files import MediaPipeLandmarks, read_keypoints, read_mediapipe_landmarks
from ptrack.pipeline import detections
from ptrack.pipeline.detections import FINGERPRINT_BYTES, default_cache_dir, detections_for_video, video_key

CAM01 = (
    Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "pose2sim" / "balancing" / "videos" / "cam01.mp4"
)


def _landmarks(video: str, T: int = 4) -> MediaPipeLandmarks:
    rng = np.random.default_rng(0)
    lm = rng.uniform(0, 100, (T, 33, 3))
    lm[..., 2] = 0.9
    return MediaPipeLandmarks(np.arange(T), lm, rng.normal(size=(T, 33, 3)), 30.0, 640, 480, video)


@pytest.fixture
def calls(monkeypatch) -> list[str]:
    """`detect` replaced by a fake that records the videos it is given."""
    seen: list[str] = []

    def fake(video, progress=None, **options):
        assert options == {"min_detection_confidence": 0.5, "min_tracking_confidence": 0.5, "smooth_landmarks": True}
        seen.append(str(video))
        return _landmarks(str(video))

    monkeypatch.setattr(detector, "detect", fake)
    return seen


def _video(path: Path, size: int = 3 * FINGERPRINT_BYTES, seed: int = 1) -> Path:
    path.write_bytes(np.random.default_rng(seed).bytes(size))  # the key reads bytes only; the fake decodes nothing
    return path


def test_a_second_run_on_the_same_video_does_not_detect(tmp_path, calls):
    cache = tmp_path / "cache"
    video = _video(tmp_path / "a.mp4")
    first = detections_for_video(video, tmp_path / "run1", cache_dir=cache)
    assert first == tmp_path / "run1" / "detections.npz" and calls == [str(video)]
    assert [p.name for p in cache.iterdir()] == [f"{video_key(video)}.npz"]
    copy = tmp_path / "b.mp4"  # the same content under another name: reused, and named as given
    copy.write_bytes(video.read_bytes())
    second = detections_for_video(copy, tmp_path / "run2", cache_dir=cache)
    assert calls == [str(video)]
    a, b = read_mediapipe_landmarks(first), read_mediapipe_landmarks(second)
    np.testing.assert_array_equal(a.landmarks, b.landmarks)
    assert (a.video, b.video) == (str(video), str(copy))
    det = read_keypoints(second)
    assert det.keypoint_set == "MEDIAPIPE_33" and det.video == str(copy) and det.people.shape == (4, 1, 33, 3)
    assert sorted(p.name for p in (tmp_path / "run2").iterdir()) == ["detections.npz"]  # no temporary file


@pytest.mark.parametrize("where", [0, FINGERPRINT_BYTES // 2, -1])
def test_a_changed_video_is_detected_again(tmp_path, calls, where):
    cache = tmp_path / "cache"
    video = _video(tmp_path / "a.mp4")
    detections_for_video(video, tmp_path / "run1", cache_dir=cache)
    data = bytearray(video.read_bytes())
    data[where] ^= 0xFF  # one byte of the first or the last MiB
    video.write_bytes(bytes(data))
    detections_for_video(video, tmp_path / "run2", cache_dir=cache)
    assert len(calls) == 2 and len(list(cache.iterdir())) == 2


def test_the_key_reads_size_and_both_ends(tmp_path, monkeypatch):
    small = _video(tmp_path / "small.mp4", size=1000)  # shorter than a MiB: read once from each end
    assert len(video_key(small)) == 64 and video_key(small) == video_key(small)
    longer = _video(tmp_path / "longer.mp4", size=1001)
    assert video_key(longer) != video_key(small)
    key = video_key(small)
    monkeypatch.setattr(detections, "DETECT_OPTIONS", detections.DetectOptions(min_detection_confidence=0.6))
    assert video_key(small) != key  # other detector options: another entry
    monkeypatch.setattr(detector, "OUTPUT_VERSION", detector.OUTPUT_VERSION + 1)
    monkeypatch.setattr(detections, "DETECT_OPTIONS", detections.DetectOptions())
    assert video_key(small) != key  # another version of detect's output


@pytest.mark.parametrize("damage", ["truncate", "flip", "not npz"])
def test_a_corrupt_cache_entry_is_detected_again(tmp_path, calls, caplog, damage):
    cache = tmp_path / "cache"
    video = _video(tmp_path / "a.mp4")
    detections_for_video(video, tmp_path / "run1", cache_dir=cache)
    entry = cache / f"{video_key(video)}.npz"
    data = bytearray(entry.read_bytes())
    if damage == "truncate":
        data = data[: len(data) // 2]
    elif damage == "flip":
        data[len(data) // 3] ^= 0xFF  # inside the landmarks array: its CRC no longer matches
    else:
        data = bytearray(b"not an npz archive")
    entry.write_bytes(bytes(data))
    with caplog.at_level(logging.WARNING, logger="ptrack.pipeline.detections"):
        out = detections_for_video(video, tmp_path / "run2", cache_dir=cache)
    assert len(calls) == 2 and "cannot be read" in caplog.text
    read_mediapipe_landmarks(entry)  # replaced by a whole one
    np.testing.assert_allclose(read_mediapipe_landmarks(out).landmarks, _landmarks("").landmarks, rtol=1e-6)


def test_an_interrupted_detection_leaves_nothing(tmp_path, monkeypatch):
    def interrupted(video, progress=None, **options):
        raise KeyboardInterrupt

    monkeypatch.setattr(detector, "detect", interrupted)
    video = _video(tmp_path / "a.mp4")
    with pytest.raises(KeyboardInterrupt):
        detections_for_video(video, tmp_path / "run", cache_dir=tmp_path / "cache")
    assert not (tmp_path / "run").exists() and not (tmp_path / "cache").exists()


def test_an_unwritable_cache_is_logged_and_skipped(tmp_path, calls, caplog):
    blocker = tmp_path / "file"
    blocker.write_text("")  # the cache folder would be under a file
    video = _video(tmp_path / "a.mp4")
    with caplog.at_level(logging.WARNING, logger="ptrack.pipeline.detections"):
        out = detections_for_video(video, tmp_path / "run", cache_dir=blocker / "cache")
    assert read_mediapipe_landmarks(out).video == str(video) and "not cached" in caplog.text


def test_default_cache_dir(monkeypatch, tmp_path):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert default_cache_dir() == tmp_path / "ptrack" / "detections"
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_cache_dir() == tmp_path / "home" / ".cache" / "ptrack" / "detections"


def test_a_missing_video_is_named(tmp_path, calls):
    with pytest.raises(InputError, match=r"video not found: .*gone\.mp4"):
        detections_for_video(tmp_path / "gone.mp4", tmp_path / "run", cache_dir=tmp_path / "cache")
    assert calls == [] and not (tmp_path / "run").exists()


def test_real_detection_is_cached(tmp_path, monkeypatch):
    """MediaPipe on a 5-frame clip cut from the Pose2Sim video: the second run copies the first's landmarks."""
    pytest.importorskip("mediapipe", reason="the video extra is not installed")
    cv2 = pytest.importorskip("cv2", reason="the video extra is not installed")
    if not CAM01.is_file():
        pytest.skip(f"Pose2Sim demo video not found at {CAM01.resolve()}")
    from ptrack.observe.video import read_frames

    clip = tmp_path / "clip.mp4"
    writer = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"mp4v"), 60.0, (1080, 1920))
    for _, rgb in read_frames(CAM01, stop=5):
        writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    writer.release()
    real, runs = detector.detect, []

    def counted(*args, **kwargs):
        runs.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(detector, "detect", counted)
    lengths: list[int] = []

    def progress(frames):
        lengths.append(len(frames))
        return frames

    first = read_keypoints(detections_for_video(clip, tmp_path / "run1", progress, cache_dir=tmp_path / "c"))
    second = read_keypoints(detections_for_video(clip, tmp_path / "run2", progress, cache_dir=tmp_path / "c"))
    assert runs == [1] and lengths == [5]
    assert first.frames.tolist() == list(range(5)) and first.present.all() and first.fps == 60.0
    np.testing.assert_array_equal(first.people, second.people)
