"""The offline detector (`ptrack.observe.detector`), the video reader (`ptrack.observe.video`) and `ptrack detect`.

Real footage: the first frames of the Pose2Sim balancing trial (`../shared/data/pose2sim`, skipped when absent),
checked against the OpenPose BODY_25B detections of the same frames. Tests that run MediaPipe skip when the
`video` extra is not installed; the errors for a missing extra are checked by hiding the modules.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_errors import fail

from ptrack.cli import main
from ptrack.errors import InputError
from ptrack.observe.detector import default_output, detect
from ptrack.observe.keypoint_files import MediaPipeLandmarks, read_keypoints, write_mediapipe_landmarks
from ptrack.observe.video import read_frames, video_info

REPO = Path(__file__).resolve().parents[1]
POSE2SIM = REPO / ".." / "shared" / "data" / "pose2sim"
CAM01 = POSE2SIM / "balancing" / "videos" / "cam01.mp4"
CAM01_JSON = POSE2SIM / "balancing" / "pose" / "cam01_json"
FRAMES = 5
#: MediaPipe index -> BODY_25B index: shoulders and hips (left, right)
MP_TO_B25B = {11: 5, 12: 6, 23: 11, 24: 12}
BODY = list(range(11, 29))  # MediaPipe's shoulders .. ankles
HINT = "pip install -c constraints.txt -e '.[video]'"


@pytest.fixture(scope="module")
def cam01() -> Path:
    if not CAM01.is_file():
        pytest.skip(f"Pose2Sim demo video not found at {CAM01.resolve()} (expected ../shared/data/pose2sim)")
    return CAM01


@pytest.fixture(scope="module")
def mediapipe():
    pytest.importorskip("cv2", reason="the video extra (opencv) is not installed")
    return pytest.importorskip("mediapipe", reason="the video extra (mediapipe) is not installed")


@pytest.fixture(scope="module")
def detected(cam01, mediapipe) -> tuple[MediaPipeLandmarks, list[int]]:
    """detect() on cam01's first FRAMES frames, and the lengths its progress wrapper was given."""
    lengths: list[int] = []

    def progress(frames):
        lengths.append(len(frames))
        return frames

    return detect(cam01, progress=progress, stop=FRAMES), lengths


@pytest.fixture(scope="module")
def short_clip(cam01, mediapipe, tmp_path_factory) -> Path:
    """cam01's first FRAMES frames re-encoded (mp4v) as a small video of its own."""
    import cv2

    path = tmp_path_factory.mktemp("clip") / "clip.mp4"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 60.0, (1080, 1920))
    for _, rgb in read_frames(cam01, stop=FRAMES):
        writer.write(cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    writer.release()
    return path


def _openpose(frame: int) -> list[np.ndarray]:
    """The BODY_25B keypoints (25, 3) of every person OpenPose found in cam01's frame."""
    data = json.loads((CAM01_JSON / f"cam01.{frame:04d}.json").read_text())
    return [np.asarray(p["pose_keypoints_2d"], dtype=float).reshape(25, 3) for p in data["people"]]


# ---------------------------------------------------------------- the video


def test_video_info_of_the_pose2sim_clip(cam01, mediapipe):
    info = video_info(cam01)
    assert (info.frames, info.fps, info.width, info.height) == (100, 60.0, 1080, 1920)  # README: decodes 1080 wide
    frames = read_frames(cam01, start=2, stop=4)
    got = list(frames)
    assert len(frames) == 2 and [i for i, _ in got] == [2, 3]
    assert all(rgb.shape == (1920, 1080, 3) and rgb.dtype == np.uint8 for _, rgb in got)


def test_video_errors_name_the_file(tmp_path, cam01, mediapipe):
    text = tmp_path / "notes.mp4"
    text.write_text("not a video\n")
    with pytest.raises(InputError, match=r"cannot decode video .*notes\.mp4"):
        video_info(text)
    with pytest.raises(InputError, match=r"video not found: .*nothing\.mp4"):
        video_info(tmp_path / "nothing.mp4")
    with pytest.raises(InputError, match="is a folder"):
        video_info(tmp_path)
    with pytest.raises(InputError, match="100 frames: frame 100 is past its end"):
        read_frames(cam01, start=100)


def test_missing_opencv_is_named(monkeypatch, cam01):
    monkeypatch.setitem(sys.modules, "cv2", None)  # import cv2 -> ImportError
    with pytest.raises(InputError, match="needs OpenCV") as e:
        video_info(cam01)
    assert HINT in str(e.value)


def test_missing_mediapipe_is_named(monkeypatch, cam01):
    pytest.importorskip("cv2")
    monkeypatch.setitem(sys.modules, "mediapipe", None)
    with pytest.raises(InputError, match="needs MediaPipe") as e:
        detect(cam01, stop=1)
    assert HINT in str(e.value)


def test_cli_without_the_video_extra(tmp_path, monkeypatch, capsys, cam01):
    monkeypatch.setitem(sys.modules, "cv2", None)
    out = tmp_path / "out.npz"
    fail(capsys, out, ["detect", str(cam01), "--out", str(out)], "needs OpenCV", HINT)


# ---------------------------------------------------------------- detection


def test_detect_finds_the_participant_where_openpose_does(detected):
    lm, lengths = detected
    T = FRAMES
    assert lengths == [T]  # the progress wrapper gets the sized frames
    assert lm.frames.tolist() == list(range(T))
    assert lm.landmarks.shape == (T, 33, 3) and lm.world_landmarks.shape == (T, 33, 3)
    assert (lm.width, lm.height, lm.fps) == (1080, 1920, 60.0)
    assert lm.found.all()
    xy, score = lm.landmarks[:, BODY, :2], lm.landmarks[:, BODY, 2]
    assert ((xy >= 0) & (xy <= [1080, 1920])).all()  # the participant stands inside the portrait frame
    assert (score > 0.5).all() and (score <= 1).all()
    for t in range(T):
        people = _openpose(t)
        mp_pts = lm.landmarks[t, list(MP_TO_B25B), :2]
        op_idx = list(MP_TO_B25B.values())
        person = min(people, key=lambda p: np.nanmean(np.linalg.norm(p[op_idx, :2] - mp_pts, axis=1)))
        assert (person[op_idx, 2] > 0).all()
        dist = np.linalg.norm(person[op_idx, :2] - mp_pts, axis=1)
        assert dist.max() < 40, f"frame {t}: shoulders/hips {dist.round(1)} px from OpenPose's"


def test_world_landmarks_are_metres_between_the_hips(detected):
    lm, _ = detected
    w = lm.world_landmarks
    assert np.isfinite(w).all()
    mid_hip = (w[:, 23] + w[:, 24]) / 2
    np.testing.assert_allclose(mid_hip, 0, atol=0.01)  # MediaPipe's origin: halfway between the hips
    shoulders = np.linalg.norm(w[:, 11] - w[:, 12], axis=1)
    assert ((shoulders > 0.25) & (shoulders < 0.5)).all(), shoulders  # an adult's shoulder width, metres
    thigh = np.linalg.norm(w[:, 23] - w[:, 25], axis=1)
    assert ((thigh > 0.3) & (thigh < 0.55)).all(), thigh
    assert (w[:, 27, 1] > w[:, 11, 1]).all()  # y down: the ankles below the shoulders (the participant stands)


def test_detection_is_deterministic(cam01, detected):
    again = detect(cam01, stop=3)
    first, _ = detected
    # the same frames through the same model and threads; a tolerance in case XNNPACK's thread split changes
    np.testing.assert_allclose(again.landmarks, first.landmarks[:3], rtol=0, atol=1e-3)
    np.testing.assert_allclose(again.world_landmarks, first.world_landmarks[:3], rtol=0, atol=1e-5)


def test_frames_without_a_person_are_nan_with_score_zero(tmp_path, mediapipe):
    import cv2

    path = tmp_path / "black.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (64, 48))
    for _ in range(3):
        writer.write(np.zeros((48, 64, 3), np.uint8))
    writer.release()
    lm = detect(path)
    assert lm.frames.tolist() == [0, 1, 2] and not lm.found.any()
    assert np.isnan(lm.landmarks[..., :2]).all() and (lm.landmarks[..., 2] == 0).all()
    assert np.isnan(lm.world_landmarks).all()


# ---------------------------------------------------------------- the landmarks file


def _landmarks(T: int = 4) -> MediaPipeLandmarks:
    rng = np.random.default_rng(0)
    return MediaPipeLandmarks(
        frames=np.arange(T) + 10,
        landmarks=rng.uniform(0, 100, (T, 33, 3)),
        world_landmarks=rng.normal(size=(T, 33, 3)),
        fps=30.0,
        width=640,
        height=480,
        video="clip.mp4",
    )


def test_landmarks_file_layout(tmp_path):
    lm = _landmarks()
    path = write_mediapipe_landmarks(tmp_path / "sub" / "clip.landmarks.npz", lm)
    with np.load(path, allow_pickle=False) as z:
        assert set(z.files) == {
            "frames",
            "landmarks",
            "world_landmarks",
            "fps",
            "width",
            "height",
            "video",
            "keypoint_set",
        }
        assert z["frames"].dtype == np.int64 and z["frames"].tolist() == [10, 11, 12, 13]
        np.testing.assert_allclose(z["landmarks"], lm.landmarks, rtol=1e-6)  # float32
        np.testing.assert_allclose(z["world_landmarks"], lm.world_landmarks, rtol=1e-6)
        assert (float(z["fps"]), int(z["width"]), int(z["height"])) == (30.0, 640, 480)
        assert (str(z["video"]), str(z["keypoint_set"])) == ("clip.mp4", "MEDIAPIPE_33")
    assert list(path.parent.iterdir()) == [path]  # no temporary file left
    assert default_output("/data/videos/cam01.mp4") == Path("cam01.landmarks.npz")


@pytest.mark.parametrize("stop", [KeyboardInterrupt, OSError])
def test_interrupted_write_leaves_nothing(tmp_path, monkeypatch, stop):
    out = tmp_path / "clip.landmarks.npz"
    out.write_bytes(b"the previous file")

    def broken(f, **arrays):
        f.write(b"half")
        raise stop("stopped while writing")

    monkeypatch.setattr(np, "savez", broken)
    with pytest.raises(stop):
        write_mediapipe_landmarks(out, _landmarks())
    assert out.read_bytes() == b"the previous file"  # replaced only when complete
    assert [p.name for p in tmp_path.iterdir()] == [out.name]


# ---------------------------------------------------------------- ptrack detect


def test_cli_detect_writes_landmarks_in_the_current_folder(short_clip, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["detect", str(short_clip), "--quiet"]) == 0
    captured = capsys.readouterr()
    assert captured.out == "clip.landmarks.npz\n"
    assert "a person in 5 of 5 frames" in captured.err
    with np.load(tmp_path / "clip.landmarks.npz", allow_pickle=False) as z:
        assert z["landmarks"].shape == (FRAMES, 33, 3) and np.isfinite(z["landmarks"]).all()
        assert str(z["video"]) == str(short_clip)
    det = read_keypoints(tmp_path / "clip.landmarks.npz")
    assert det.keypoint_set == "MEDIAPIPE_33" and det.frames.tolist() == list(range(FRAMES)) and det.present.all()


def test_read_keypoints_reads_what_detect_writes(cam01, detected, tmp_path, monkeypatch, capsys):
    """`ptrack detect`'s file, read back as keypoints: MediaPipe-33, the video's frames, size, rate and path."""
    monkeypatch.setattr("ptrack.observe.detector.detect", lambda *a, **k: detected[0])  # the FRAMES already found
    out = tmp_path / "cam01.landmarks.npz"
    assert main(["detect", str(cam01), "--out", str(out), "--quiet"]) == 0
    assert capsys.readouterr().out == f"{out}\n"
    det = read_keypoints(out)  # the format inferred from the content
    lm = detected[0]
    assert det.keypoint_set == "MEDIAPIPE_33" and det.definition.names[23] == "left_hip"
    assert det.frames.tolist() == list(range(FRAMES)) and det.people.shape == (FRAMES, 1, 33, 3)
    assert (det.fps, det.image_size, det.video) == (60.0, (1080, 1920), str(cam01))
    np.testing.assert_allclose(det.people[:, 0], lm.landmarks, rtol=1e-6)  # float32 in the file
    assert det.present.all()


def test_a_video_without_a_rate_writes_and_reads(tmp_path):
    """A container without a frame rate: detect's fps is NaN; the file keeps it, and read_keypoints takes it as
    unknown (or the given fps)."""
    lm = _landmarks()
    path = write_mediapipe_landmarks(tmp_path / "x.npz", MediaPipeLandmarks(**{**lm.__dict__, "fps": float("nan")}))
    assert read_keypoints(path).fps is None and read_keypoints(path, fps=25).fps == 25.0


def test_cli_detect_bad_video(tmp_path, capsys, mediapipe):
    text = tmp_path / "notes.mp4"
    text.write_text("not a video\n")
    out = tmp_path / "out.npz"
    fail(capsys, out, ["detect", str(text), "--out", str(out)], "cannot decode video", str(text))
    fail(capsys, out, ["detect", str(tmp_path / "gone.mp4"), "--out", str(out)], "video not found", "gone.mp4")


def test_cli_detect_refuses_an_output_it_cannot_write_before_detecting(cam01, tmp_path, capsys, monkeypatch):
    import ptrack.observe.detector as detector

    monkeypatch.setattr(detector, "detect", lambda *a, **k: pytest.fail("detected before checking --out"))
    fail(capsys, tmp_path / "x", ["detect", str(cam01), "--out", str(tmp_path)], "is a folder")
    blocker = tmp_path / "file"
    blocker.write_text("")
    fail(capsys, tmp_path / "x", ["detect", str(cam01), "--out", str(blocker / "out.npz")], "is a file")


def test_cli_detect_stderr_holds_only_ptrack_lines(short_clip, tmp_path):
    """Off a terminal: progress lines (PTRACK_PROGRESS_SECONDS=0: every frame after the first) and the summary;
    MediaPipe's native start-up notes (TensorFlow Lite, absl) are held back from stderr."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "PTRACK_PROGRESS_SECONDS": "0"}
    out = tmp_path / "clip.npz"
    cmd = [sys.executable, "-m", "ptrack.cli", "detect", str(short_clip), "--out", str(out)]
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert r.stdout == f"{out}\n"
    lines = r.stderr.splitlines()
    assert all(line.startswith("ptrack: ") for line in lines), r.stderr
    assert lines[0].startswith("ptrack: INFO: detect: frame 1/5 (20%), ")
    assert lines[-1].startswith("ptrack: a person in 5 of 5 frames; ")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="POSIX signals")
def test_cli_detect_killed_leaves_nothing(cam01, mediapipe, tmp_path):
    """SIGTERM while detecting: `ptrack: terminated`, status 143, no landmarks file and no temporary one."""
    import signal
    import time

    env = {**os.environ, "PYTHONPATH": str(REPO), "PTRACK_PROGRESS_SECONDS": "0"}
    out = tmp_path / "out.npz"
    log = tmp_path / "stderr.txt"
    with log.open("w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "ptrack.cli", "detect", str(cam01), "--out", str(out)], env=env, stderr=err
        )
    try:
        deadline = time.monotonic() + 300  # a slow, shared machine: never an assertion on speed
        while "detect: frame" not in log.read_text():
            assert proc.poll() is None, log.read_text()
            assert time.monotonic() < deadline, "no progress line"
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=300) == 143, log.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert log.read_text().splitlines()[-1] == "ptrack: terminated"
    assert list(tmp_path.iterdir()) == [log]
