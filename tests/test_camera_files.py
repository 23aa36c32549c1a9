"""Camera calibration files (ptrack/observe/camera_files.py): the real Pose2Sim calibration in
../shared/data/pose2sim (skipped when absent), fixtures written from each format's published layout,
OpenCV's distortion model and its inverse, the default camera, and every user error."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from ptrack.body.rotations import matrix_to_axis_angle_np
from ptrack.errors import InputError
from ptrack.observe.camera_files import (
    DEFAULT_DIAGONAL_FOV_DEG,
    CameraFile,
    default_intrinsics,
    distort_points,
    read_camera,
    read_cameras,
    rodrigues,
    to_camera,
    undistort_points,
    world_up,
)

POSE2SIM = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "pose2sim"
CALIB = POSE2SIM / "Calib_qualisys.toml"

# BODY_25B index of each keypoint of the Pose2Sim TRC (its README)
BODY_25B = {
    "Nose": 0, "LShoulder": 5, "RShoulder": 6, "LElbow": 7, "RElbow": 8, "LWrist": 9, "RWrist": 10,
    "LHip": 11, "RHip": 12, "LKnee": 13, "RKnee": 14, "LAnkle": 15, "RAnkle": 16, "Neck": 17,
    "Head": 18, "LBigToe": 19, "LSmallToe": 20, "LHeel": 21, "RBigToe": 22, "RSmallToe": 23, "RHeel": 24,
}  # fmt: skip


@pytest.fixture(scope="module")
def calib() -> Path:
    if not CALIB.is_file():
        pytest.skip(f"Pose2Sim data not found at {CALIB.resolve()} (expected ../shared/data/pose2sim)")
    return CALIB


def _K(fx=500.0, fy=510.0, cx=320.0, cy=240.0) -> np.ndarray:
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _rot(rvec) -> np.ndarray:
    return rodrigues(np.asarray(rvec, dtype=np.float64))


def _rvec(R: np.ndarray) -> np.ndarray:
    axis, angle = matrix_to_axis_angle_np(R)
    return axis * angle


def _write(path: Path, text: str, newline: str = "\n") -> Path:
    path.write_bytes(text.replace("\n", newline).encode())
    return path


def _grid(width: int, height: int, n: int = 25) -> np.ndarray:
    """(n * n, 2) pixels covering the whole image, corners included."""
    u, v = np.meshgrid(np.linspace(0, width, n), np.linspace(0, height, n))
    return np.stack([u, v], axis=-1).reshape(-1, 2)


# -- the real Pose2Sim calibration ---------------------------------------------------------------


def test_pose2sim_calibration_both_cameras(calib):
    cams = read_cameras(calib)
    assert {"cam_01", "cam_02"} <= set(cams)
    c1, c2 = cams["cam_01"], cams["cam_02"]
    assert (c1.name, c1.width, c1.height, c1.fisheye, c1.file_format) == ("cam_01", 1088, 1920, False, "pose2sim-toml")
    np.testing.assert_array_equal(c1.K[0], [1681.244873046875, 0.0, 532.97369384375])
    np.testing.assert_array_equal(c2.dist, [-0.000747609375, 0.00213728125, 1.51875e-05, 4.546875e-06])
    np.testing.assert_array_equal(c1.t, [0.3211048899999996, 0.9563320600000009, 2.8907130499999996])
    for cam in (c1, c2):
        assert cam.R is not None
        np.testing.assert_allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-12)
        center = to_camera(cam, dtype=torch.float64).center.numpy()
        assert 1.0 < center[2] < 3.0  # Qualisys lab, Z up: the cameras hang above the floor
        np.testing.assert_array_equal(world_up(cam), [0.0, 0.0, 1.0])
    np.testing.assert_allclose(_rvec(c1.R), [1.68827548, 1.04832205, -0.41955852], atol=1e-8)


def _trc_frame(path: Path, row: int) -> tuple[list[str], np.ndarray]:
    """Keypoint names and (K, 3) lab coordinates (Z up) of one TRC row; TRC (X, Y, Z) = lab (Y, Z, X)."""
    lines = path.read_text().splitlines()
    names = [n for n in lines[3].split("\t")[2:] if n]
    trc = np.array(lines[5 + row].split("\t")[2 : 2 + 3 * len(names)], dtype=np.float64).reshape(-1, 3)
    return names, trc[:, [2, 0, 1]]


@pytest.mark.parametrize("camera", ["cam01", "cam02"])
def test_pose2sim_reprojects_triangulated_keypoints_onto_openpose(calib, camera):
    """The TRC's frame-0 keypoints, projected by the calibration and distorted, land on the camera's
    OpenPose detections of the participant (the README: a median of about 8-12 px)."""
    names, lab = _trc_frame(POSE2SIM / "balancing" / "triangulated.trc", 0)
    frame = json.loads((POSE2SIM / "balancing" / "pose" / f"{camera}_json" / f"{camera}.0000.json").read_text())
    detected = np.array(frame["people"][0]["pose_keypoints_2d"]).reshape(25, 3)[[BODY_25B[n] for n in names]]
    seen = detected[:, 2] > 0
    assert seen.sum() >= 15
    cam = read_camera(calib, camera)
    pinhole = to_camera(cam, dtype=torch.float64).project(torch.from_numpy(lab)).pixels.numpy()
    error = np.linalg.norm(distort_points(pinhole, cam) - detected[:, :2], axis=-1)[seen]
    assert np.median(error) < 25.0
    # the same comparison the other way: the detections undistorted onto the pinhole image
    error_undistorted = np.linalg.norm(undistort_points(detected[:, :2], cam) - pinhole, axis=-1)[seen]
    np.testing.assert_allclose(error_undistorted, error, atol=0.1)  # this lens distorts < 1 px here
    # a wrong camera does not fit: the other camera's calibration puts the points far away
    other = read_camera(calib, "cam02" if camera == "cam01" else "cam01")
    wrong = to_camera(other, dtype=torch.float64).project(torch.from_numpy(lab)).pixels.numpy()
    assert np.median(np.linalg.norm(wrong - detected[:, :2], axis=-1)[seen]) > 100.0


def test_pose2sim_round_trip_over_the_whole_image(calib):
    cam = read_camera(calib, "cam01")
    ideal = _grid(cam.width, cam.height)
    distorted = distort_points(ideal, cam)
    assert np.abs(distorted - ideal).max() > 0.1  # the lens moves the corners
    np.testing.assert_allclose(undistort_points(distorted, cam), ideal, rtol=0, atol=1e-6)


@pytest.mark.parametrize("name", ["cam01", "cam_01", "CAM-1", "1", "01", 1, "cam_1"])
def test_pose2sim_camera_names(calib, name):
    assert read_camera(calib, name).name == "cam_01"


def test_pose2sim_unknown_name_lists_the_cameras(calib):
    with pytest.raises(InputError, match=r"no camera 'cam07'; its cameras: cam_01, cam_02") as e:
        read_camera(calib, "cam07")
    assert str(calib.name) in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(InputError, match=r"holds 4 cameras \(cam_01, cam_02, cam_03, cam_04\): give the name"):
        read_camera(calib)


# -- aniposelib TOML -----------------------------------------------------------------------------

# aniposelib CameraGroup.dump: sections cam_0, cam_1, ..., the camera names in `name`, fisheye flag,
# a [metadata] table (toml.dump formatting)
ANIPOSE_TOML = """\
[cam_0]
name = "A"
size = [ 640, 480,]
matrix = [ [ 500.0, 0.0, 320.0,], [ 0.0, 510.0, 240.0,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.2, 0.05, 0.001, -0.001, 0.0,]
rotation = [ 0.1, -0.2, 0.3,]
translation = [ 0.5, 0.1, 3.0,]

[cam_1]
name = "B"
size = [ 1280, 720,]
matrix = [ [ 600.0, 0.0, 640.0,], [ 0.0, 600.0, 360.0,], [ 0.0, 0.0, 1.0,],]
distortions = [ 0.1, -0.05, 0.01, -0.002,]
rotation = [ 0.0, 0.0, 0.0,]
translation = [ 0.0, 0.0, 0.0,]
fisheye = true

[metadata]
adjusted = false
error = 0.35
"""


def test_aniposelib_toml(tmp_path):
    path = _write(tmp_path / "calibration.toml", ANIPOSE_TOML)
    cams = read_cameras(path)
    assert list(cams) == ["cam_0", "cam_1"]
    a, b = cams["cam_0"], cams["cam_1"]
    assert (a.name, a.width, a.height, a.fisheye, b.name, b.fisheye) == ("A", 640, 480, False, "B", True)
    np.testing.assert_allclose(a.R, _rot([0.1, -0.2, 0.3]), atol=1e-15)
    np.testing.assert_array_equal(b.R, np.eye(3))
    np.testing.assert_array_equal(b.dist, [0.1, -0.05, 0.01, -0.002])
    for name in ("B", "b", "cam_1", "cam1", "1"):
        assert read_camera(path, name).name == "B"
    assert read_camera(path, "0").name == "A"


def test_ambiguous_name(tmp_path):
    text = ANIPOSE_TOML.replace("[cam_1]", "[cam_00]").replace('name = "B"', 'name = "cam_0b"')
    path = _write(tmp_path / "calibration.toml", text)
    assert read_camera(path, "cam_0").name == "A"  # exact wins
    with pytest.raises(InputError, match=r"'cam0' is ambiguous, it matches cam_0, cam_00"):
        read_camera(path, "cam0")


# -- OpenCV FileStorage --------------------------------------------------------------------------

R_CV = _rot([0.2, -0.1, 0.05])
T_CV = np.array([0.1, -0.3, 2.5])

# as cv::FileStorage writes it (OpenCV 4: "%YAML:1.0" then "---"; matrices in a flow sequence that
# wraps lines), keys of OpenCV's calibration sample (samples/cpp/calibration.cpp)
OPENCV_YAML = """\
%YAML:1.0
---
calibration_time: "Sat Nov 28 07:00:00 2026"
image_width: 640
image_height: 480
flags: 0
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 5.0000000000000000e+02, 0., 3.2000000000000000e+02, 0.,
       5.1000000000000000e+02, 2.4000000000000000e+02, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 5
   cols: 1
   dt: d
   data: [ -2.8000000000000003e-01, 7.0000000000000007e-02,
       1.0000000000000000e-03, -5.0000000000000001e-04, 0. ]
rvec: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ {r0!r}, {r1!r}, {r2!r} ]
tvec: !!opencv-matrix
   rows: 3
   cols: 1
   dt: d
   data: [ 1.0000000000000001e-01, -2.9999999999999999e-01, 2.5 ]
avg_reprojection_error: 2.1e-01
"""


def _opencv_yaml(header: str = "%YAML:1.0\n---\n") -> str:
    r = _rvec(R_CV)
    body = OPENCV_YAML.format(r0=float(r[0]), r1=float(r[1]), r2=float(r[2]))
    return header + body.split("---\n", 1)[1]


@pytest.mark.parametrize("header", ["%YAML:1.0\n---\n", "%YAML:1.0\n", "%YAML 1.0\n---\n", ""])
@pytest.mark.parametrize("newline", ["\n", "\r\n"])
def test_opencv_yaml(tmp_path, header, newline):
    path = _write(tmp_path / "front.yml", _opencv_yaml(header), newline)
    cam = read_camera(path)
    assert (cam.name, cam.width, cam.height, cam.fisheye, cam.file_format) == ("front", 640, 480, False, "opencv")
    np.testing.assert_array_equal(cam.K, _K())
    np.testing.assert_array_equal(cam.dist, [-0.28, 0.07, 0.001, -0.0005, 0.0])
    np.testing.assert_allclose(cam.R, R_CV, atol=1e-15)
    np.testing.assert_allclose(cam.t, T_CV, atol=1e-15)
    assert world_up(cam) is None
    assert list(read_cameras(path)) == ["front"]


def _cv_json_matrix(a) -> dict:
    a = np.atleast_2d(np.asarray(a, dtype=np.float64))
    return {"type_id": "opencv-matrix", "rows": a.shape[0], "cols": a.shape[1], "dt": "d", "data": a.ravel().tolist()}


def test_opencv_yaml_multichannel_and_plain_sequences(tmp_path):
    # a Mat of one 3-channel element (dt "3d") and cv::FileStorage's plain sequence (a Vec3d)
    r = [float(v) for v in _rvec(R_CV)]
    text = _opencv_yaml().split("rvec:")[0] + (
        f'rvec: !!opencv-matrix\n   rows: 1\n   cols: 1\n   dt: "3d"\n   data: [ {r[0]!r}, {r[1]!r}, {r[2]!r} ]\n'
        "tvec: [ 0.1, -0.3, 2.5 ]\n"
    )
    cam = read_camera(_write(tmp_path / "cam.yml", text))
    np.testing.assert_allclose(cam.R, R_CV, atol=1e-15)
    np.testing.assert_allclose(cam.t, T_CV, atol=1e-15)


def test_opencv_json_filestorage_and_plain_lists(tmp_path):
    # cv::FileStorage's JSON form (a matrix is {"type_id": "opencv-matrix", rows, cols, dt, data}); R/T keys
    doc = {
        "image_width": 1920,
        "image_height": 1080,
        "camera_matrix": _cv_json_matrix(_K(1400.0, 1400.0, 960.0, 540.0)),
        "distortion_coefficients": _cv_json_matrix([[0.05, -0.1, 0.0, 0.0, 0.02, 0.0, 0.0, 0.01]]),
        "R": _cv_json_matrix(R_CV),
        "T": _cv_json_matrix(T_CV[:, None]),
    }
    path = tmp_path / "cam.json"
    path.write_text(json.dumps(doc, indent=4))
    cam = read_camera(path)
    np.testing.assert_array_equal(cam.R, R_CV)
    np.testing.assert_array_equal(cam.t, T_CV)
    assert cam.dist.shape == (8,) and (cam.width, cam.height) == (1920, 1080)
    # the same keys as plain JSON lists, intrinsics only, other key spellings, no size
    plain = {"K": _K().tolist(), "dist_coeffs": [0.1, 0.0, 0.0, 0.0], "camera_name": "phone"}
    path2 = tmp_path / "intrinsics.json"
    path2.write_text(json.dumps(plain))
    cam2 = read_camera(path2, "phone")
    assert (cam2.name, cam2.width, cam2.height, cam2.R, cam2.t) == ("phone", None, None, None, None)
    with pytest.raises(InputError, match="has no image size"):
        to_camera(cam2)
    assert to_camera(cam2, width=640, height=480).width == 640


def test_ros_camera_info_yaml_fisheye(tmp_path):
    # ROS camera_calibration_parsers' YAML: untagged {rows, cols, data}; "equidistant" = OpenCV fisheye
    text = """\
image_width: 800
image_height: 600
camera_name: wide
camera_matrix:
  rows: 3
  cols: 3
  data: [400.0, 0.0, 400.0, 0.0, 400.0, 300.0, 0.0, 0.0, 1.0]
distortion_model: equidistant
distortion_coefficients:
  rows: 1
  cols: 4
  data: [0.05, -0.01, 0.002, -0.0005]
"""
    cam = read_camera(_write(tmp_path / "wide.yaml", text))
    assert cam.fisheye and cam.name == "wide" and cam.dist.shape == (4,)


# -- EasyMocap -----------------------------------------------------------------------------------

EASYMOCAP_NAMES = ("01", "02")
EASY_R = {"01": _rot([0.3, 0.2, -0.1]), "02": _rot([-1.2, 0.4, 0.9])}
EASY_T = {"01": np.array([0.2, 1.0, 3.5]), "02": np.array([-0.5, 0.8, 4.0])}


def _easymocap_matrix(key: str, value: np.ndarray) -> str:
    """easymocap/mytools/camera_utils.py FileStorage.write(key, value, 'mat')."""
    data = ", ".join(f"{v:.6f}" for v in value.reshape(-1))
    return f"{key}: !!opencv-matrix\n  rows: {value.shape[0]}\n  cols: {value.shape[1]}\n  dt: d\n  data: [{data}]\n"


def _easymocap_files(folder: Path, rot_only: bool = False, sizes: bool = True) -> tuple[Path, Path]:
    """intri.yml / extri.yml as EasyMocap's write_camera writes them (\\r\\n line ends, names quoted)."""
    folder.mkdir(parents=True, exist_ok=True)
    header = "%YAML:1.0\n---\nnames:\n" + "".join(f'  - "{n}"\n' for n in EASYMOCAP_NAMES)
    intri, extri = header, header
    for i, n in enumerate(EASYMOCAP_NAMES):
        intri += _easymocap_matrix(f"K_{n}", _K(1000.0 + i, 1001.0 + i, 960.0, 540.0))
        intri += _easymocap_matrix(f"dist_{n}", np.array([[-0.1, 0.02, 0.0, 0.001, 0.0]]))
        if sizes:
            intri += f"H_{n}: 1080\nW_{n}: 1920\n"
        if not rot_only:
            extri += _easymocap_matrix(f"R_{n}", _rvec(EASY_R[n])[:, None])
        extri += _easymocap_matrix(f"Rot_{n}", EASY_R[n])
        extri += _easymocap_matrix(f"T_{n}", EASY_T[n][:, None])
    return _write(folder / "intri.yml", intri, "\r\n"), _write(folder / "extri.yml", extri, "\r\n")


@pytest.mark.parametrize("given", ["folder", "intri", "extri"])
def test_easymocap(tmp_path, given):
    intri, extri = _easymocap_files(tmp_path / "calib")
    path = {"folder": intri.parent, "intri": intri, "extri": extri}[given]
    cams = read_cameras(path)
    assert list(cams) == ["01", "02"]
    for n, cam in cams.items():
        assert (cam.width, cam.height, cam.file_format) == (1920, 1080, "easymocap")
        np.testing.assert_allclose(cam.R, EASY_R[n], atol=2e-6)  # written with 6 decimals
        np.testing.assert_allclose(cam.t, EASY_T[n], atol=1e-12)
        np.testing.assert_array_equal(cam.dist, [-0.1, 0.02, 0.0, 0.001, 0.0])
        assert world_up(cam) is None
    assert cams["02"].K[0, 0] == 1001.0
    assert read_camera(path, "2").name == "02"


def test_easymocap_rotation_matrix_and_intrinsics_only(tmp_path):
    intri, extri = _easymocap_files(tmp_path / "calib", rot_only=True, sizes=False)
    cam = read_camera(extri.parent, "01")
    np.testing.assert_allclose(cam.R, EASY_R["01"], atol=2e-6)
    assert cam.width is None
    extri.unlink()
    cam = read_camera(intri, "01")
    assert cam.R is None and cam.t is None and not cam.has_extrinsics


def test_easymocap_one_file_with_both(tmp_path):
    intri, extri = _easymocap_files(tmp_path / "calib")
    both = tmp_path / "cameras.yml"
    both.write_text(intri.read_text() + extri.read_text().split("\n", 5)[5])  # extri without its header
    cam = read_camera(both, "02")
    np.testing.assert_allclose(cam.t, EASY_T["02"], atol=1e-12)
    assert cam.source == str(both)


def test_easymocap_unquoted_numeric_names(tmp_path):
    # `- 01` unquoted would be the integer 1 to a YAML reader: the names are kept as written
    intri, _ = _easymocap_files(tmp_path / "calib")
    intri.write_text(intri.read_text().replace('"01"', "01").replace('"02"', "02"))
    assert list(read_cameras(intri)) == ["01", "02"]


# -- distortion ----------------------------------------------------------------------------------

STANDARD = {
    "4": [-0.25, 0.08, 0.001, -0.0015],
    "5": [-0.3, 0.1, 0.001, -0.002, -0.02],
    "8 rational": [-0.28, 0.07, 0.001, -0.0005, 0.0, 0.01, 0.002, 0.001],
    "12 thin prism": [-0.2, 0.05, 0.0, 0.001, 0.01, 0.0, 0.0, 0.0, 0.001, -0.0005, 0.0005, 0.0002],
}


@pytest.mark.parametrize("dist", list(STANDARD.values()), ids=list(STANDARD))
def test_undistort_inverts_distort_standard(dist):
    cam = CameraFile("c", 640, 480, _K(), np.array(dist), None, None)
    ideal = _grid(640, 480)
    distorted = distort_points(ideal, cam)
    assert np.abs(distorted - ideal).max() > 20.0  # a strongly distorted lens
    np.testing.assert_allclose(undistort_points(distorted, cam), ideal, rtol=0, atol=1e-6)
    # and the other way: distorted pixels -> undistorted -> distorted again
    back = distort_points(undistort_points(ideal, cam), cam)
    np.testing.assert_allclose(back, ideal, rtol=0, atol=1e-6)


def test_undistort_inverts_distort_fisheye():
    cam = CameraFile(
        "f", 1280, 960, _K(400.0, 400.0, 640.0, 480.0), np.array([0.1, -0.05, 0.01, -0.002]), None, None, True
    )
    ideal = _grid(1280, 960)
    distorted = distort_points(ideal, cam)
    assert np.abs(distorted - ideal).max() > 100.0
    np.testing.assert_allclose(undistort_points(distorted, cam), ideal, rtol=0, atol=1e-6)


def test_fisheye_forward_model_known_value():
    # OpenCV fisheye: theta = atan(r), theta_d = theta (1 + k1 theta^2 + ...), x_d = x theta_d / r
    cam = CameraFile("f", 100, 100, _K(100.0, 100.0, 50.0, 50.0), np.array([0.1, 0.0, 0.0, 0.0]), None, None, True)
    theta = math.atan(1.0)
    theta_d = theta * (1 + 0.1 * theta**2)
    np.testing.assert_allclose(distort_points(np.array([150.0, 50.0]), cam), [50.0 + 100.0 * theta_d, 50.0], atol=1e-12)


def test_standard_forward_model_known_value():
    # cv::projectPoints: x' = x (1 + k1 r2 + k2 r4 + k3 r6) + 2 p1 x y + p2 (r2 + 2 x^2), ...
    k1, k2, p1, p2, k3 = -0.2, 0.05, 0.01, 0.02, 0.003
    cam = CameraFile("c", 100, 100, _K(100.0, 100.0, 0.0, 0.0), np.array([k1, k2, p1, p2, k3]), None, None)
    x, y = 0.3, -0.4
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    expected = [
        100 * (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)),
        100 * (y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y),
    ]
    np.testing.assert_allclose(distort_points([100 * x, 100 * y], cam), expected, atol=1e-12)


def test_undistort_shapes_nan_and_tensors():
    cam = CameraFile("c", 640, 480, _K(), np.array(STANDARD["5"]), None, None)
    pts = np.random.default_rng(0).uniform([0, 0], [640, 480], size=(7, 25, 2))
    pts[2, 3] = np.nan
    out = undistort_points(pts, cam)
    assert isinstance(out, np.ndarray) and out.shape == (7, 25, 2)
    assert np.isnan(out[2, 3]).all() and np.isfinite(np.delete(out.reshape(-1, 2), 2 * 25 + 3, axis=0)).all()
    t = torch.from_numpy(pts).float()
    out_t = undistort_points(t, cam)
    assert isinstance(out_t, torch.Tensor) and out_t.dtype == torch.float32 and out_t.shape == (7, 25, 2)
    np.testing.assert_allclose(out_t.numpy(), out, atol=1e-3, equal_nan=True)
    # no distortion: unchanged
    plain = CameraFile("p", 640, 480, _K(), np.zeros(5), None, None)
    np.testing.assert_array_equal(undistort_points(pts, plain), pts)
    with pytest.raises(InputError, match=r"shape \(\.\.\., 2\), got \(7, 25\)"):
        undistort_points(pts[..., 0], cam)


def test_undistort_outside_the_invertible_region_is_nan(caplog):
    cam = CameraFile("c", 640, 480, _K(), np.array([-0.5, 0.0, 0.0, 0.0]), None, None)
    # r2 > 2 makes 1 + k1 r2 negative: no undistorted point maps there
    far = np.array([[320.0 + 500.0 * 3.0, 240.0], [320.0, 240.0]])
    with caplog.at_level(logging.WARNING, logger="ptrack.observe.camera_files"):
        out = undistort_points(far, cam)
    assert np.isnan(out[0]).all() and np.isfinite(out[1]).all()
    assert "1 of 2 points could not be undistorted" in caplog.text


def test_undistort_matches_cv2():
    cv2 = pytest.importorskip("cv2")
    pts = _grid(640, 480, 13)[:, None, :]
    term = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    for dist in STANDARD.values():
        cam = CameraFile("c", 640, 480, _K(), np.array(dist), None, None)
        if hasattr(cv2, "undistortPointsIter"):  # OpenCV 4
            ref = cv2.undistortPointsIter(pts, cam.K, cam.dist, None, cam.K, term)[:, 0]
        else:  # OpenCV 5: undistortPoints takes the criteria
            ref = cv2.undistortPoints(pts, cam.K, cam.dist, R=None, P=cam.K, criteria=term)[:, 0]
        np.testing.assert_allclose(undistort_points(pts[:, 0], cam), ref, rtol=0, atol=1e-8)
        und = undistort_points(pts[:, 0], cam)
        normalised = np.c_[(und - cam.K[:2, 2]) / np.diag(cam.K)[:2], np.ones(len(und))]
        ref_fwd = cv2.projectPoints(normalised, np.zeros(3), np.zeros(3), cam.K, cam.dist)[0][:, 0]
        np.testing.assert_allclose(distort_points(und, cam), ref_fwd, rtol=0, atol=1e-8)
    fish = CameraFile("f", 640, 480, _K(), np.array([0.1, -0.05, 0.01, -0.002]), None, None, True)
    ref = cv2.fisheye.undistortPoints(pts, fish.K, fish.dist, P=fish.K, criteria=term)[:, 0]
    np.testing.assert_allclose(undistort_points(pts[:, 0], fish), ref, rtol=0, atol=1e-8)


# -- default camera, ptrack camera, up axis ------------------------------------------------------


def test_default_intrinsics():
    K = default_intrinsics(1920, 1080)
    f = math.sqrt(1920**2 + 1080**2)
    np.testing.assert_allclose(K, [[f, 0, 960], [0, f, 540], [0, 0, 1]], rtol=1e-15)
    np.testing.assert_allclose(default_intrinsics(1920, 1080, DEFAULT_DIAGONAL_FOV_DEG), K, rtol=1e-12)
    assert default_intrinsics(1080, 1920)[0, 0] == K[0, 0]  # portrait: the same lens
    np.testing.assert_allclose(default_intrinsics(300, 400, fov_deg=90.0)[0, 0], 250.0, rtol=1e-12)
    # a wider field of view is a shorter focal length
    assert default_intrinsics(640, 480, 70.0)[0, 0] < default_intrinsics(640, 480, 40.0)[0, 0]
    for bad in (0.0, 180.0, -10.0, float("nan"), True):
        with pytest.raises(InputError, match="field of view"):
            default_intrinsics(640, 480, bad)
    with pytest.raises(InputError, match="width must be a positive whole number"):
        default_intrinsics(0, 480)


def test_to_camera_projects_like_the_file():
    cam = CameraFile("c", 640, 480, _K(), np.zeros(5), R_CV, T_CV, source="x.yml", file_format="opencv")
    X = np.array([[0.1, 0.2, 0.3], [-0.4, 0.1, 1.0]])
    pc = to_camera(cam, dtype=torch.float64)
    x_cam = X @ R_CV.T + T_CV
    expected = (x_cam[:, :2] / x_cam[:, 2:]) @ cam.K[:2, :2].T + cam.K[:2, 2]
    np.testing.assert_allclose(pc.project(torch.from_numpy(X)).pixels.numpy(), expected, atol=1e-10)
    intr = to_camera(cam, extrinsics=False, width=1280, height=960)
    assert intr.dtype == torch.get_default_dtype() and (intr.width, intr.height) == (1280, 960)
    torch.testing.assert_close(intr.R, torch.eye(3))
    torch.testing.assert_close(intr.t, torch.zeros(3))


def test_world_up():
    cam = CameraFile("c", 640, 480, _K(), np.zeros(5), R_CV, T_CV, file_format="opencv")
    assert world_up(cam) is None
    np.testing.assert_array_equal(world_up(cam, "-y"), [0.0, -1.0, 0.0])
    np.testing.assert_array_equal(world_up(cam, "+Z"), [0.0, 0.0, 1.0])
    np.testing.assert_allclose(world_up(cam, [0.0, 2.0, 2.0]), [0.0, math.sqrt(0.5), math.sqrt(0.5)])
    toml_cam = CameraFile("c", 640, 480, _K(), np.zeros(5), R_CV, T_CV, file_format="pose2sim-toml")
    np.testing.assert_array_equal(world_up(toml_cam), [0.0, 0.0, 1.0])
    assert world_up(CameraFile("c", 640, 480, _K(), np.zeros(5), None, None, file_format="pose2sim-toml")) is None
    for bad in ("w", "up", [0.0, 0.0, 0.0], [1.0, 2.0]):
        with pytest.raises(InputError, match="up"):
            world_up(cam, bad)


# -- errors --------------------------------------------------------------------------------------

_CAM = '[cam_01]\nname = "cam_01"\nsize = [ 640.0, 480.0]\n'
_GOOD = (
    "matrix = [ [ 500.0, 0.0, 320.0], [ 0.0, 500.0, 240.0], [ 0.0, 0.0, 1.0]]\n"
    "distortions = [ -0.1, 0.01, 0.0, 0.0]\nrotation = [ 0.1, 0.2, 0.3]\ntranslation = [ 0.0, 1.0, 3.0]\n"
)


def _toml(tmp_path: Path, body: str) -> Path:
    return _write(tmp_path / "Calib.toml", _CAM + body)


TOML_ERRORS = {
    "no intrinsics": (_GOOD.split("\n", 1)[1], r"\[cam_01\] has no intrinsics \(no 'matrix' key\)"),
    "singular K": (_GOOD.replace("[ 500.0, 0.0, 320.0]", "[ 0.0, 0.0, 320.0]"), "K is singular"),
    "negative focal": (_GOOD.replace("[ 0.0, 500.0, 240.0]", "[ 0.0, -500.0, 240.0]"), "non-positive focal"),
    "not upper triangular": (_GOOD.replace("[ 0.0, 500.0, 240.0]", "[ 3.0, 500.0, 240.0]"), "upper triangular"),
    "last row": (_GOOD.replace("[ 0.0, 0.0, 1.0]]", "[ 0.0, 0.0, 2.0]]"), "upper triangular"),
    "K 2 x 3": (_GOOD.replace(", [ 0.0, 0.0, 1.0]]", "]"), r"K must be 3 x 3, got shape \(2, 3\)"),
    "K ragged": (_GOOD.replace("[ 0.0, 0.0, 1.0]]", "[ 0.0, 1.0]]"), "matrix: expected numbers"),
    "3 distortions": (_GOOD.replace("-0.1, 0.01, 0.0, 0.0", "-0.1, 0.01, 0.0"), "3 distortion coefficients"),
    "rotation of 4": (_GOOD.replace("0.1, 0.2, 0.3", "0.1, 0.2, 0.3, 0.4"), r"rotation: expected a Rodrigues vector"),
    "translation of 2": (_GOOD.replace("0.0, 1.0, 3.0", "1.0, 3.0"), "translation must have 3 values"),
    "no translation": (_GOOD.split("translation")[0], "extrinsics need both"),
    "string focal": (_GOOD.replace("500.0, 0.0, 320.0", '"500", 0.0, 320.0'), "expected numbers"),
    "nan": (_GOOD.replace("-0.1, 0.01", "nan, 0.01"), "non-finite"),
    "fisheye 5": (
        _GOOD.replace("0.0, 0.0]\nrot", "0.0, 0.0, 0.0]\nrot") + "fisheye = true\n",
        "fisheye k1..k4 takes 4",
    ),
}


@pytest.mark.parametrize("body, message", list(TOML_ERRORS.values()), ids=list(TOML_ERRORS))
def test_toml_errors(tmp_path, body, message):
    path = _toml(tmp_path, body)
    with pytest.raises(InputError, match=message) as e:
        read_cameras(path)
    assert str(path) in str(e.value) and "\n" not in str(e.value)


def test_the_error_fixture_is_valid(tmp_path):
    """The base of the error cases reads: each error above is its one change."""
    assert read_camera(_toml(tmp_path, _GOOD), "cam01").K[0, 0] == 500.0


def _yaml_with(**changes: str) -> str:
    text = _opencv_yaml()
    for old, new in changes.items():
        text = text.replace(old, new)
    return text


@pytest.mark.parametrize(
    "name, text, message",
    [
        (
            "no K",
            _opencv_yaml().replace("camera_matrix", "matrix_of_camera"),
            "a camera without intrinsics: none of the keys",
        ),
        (
            "matrix size",
            _opencv_yaml().replace("rows: 3\n   cols: 3", "rows: 3\n   cols: 4", 1),
            "an OpenCV matrix of 3 x 4 with 9 values",
        ),
        ("matrix fields", _opencv_yaml().replace("   rows: 5\n", "", 1), "'rows' is missing"),
        ("bad yaml", _opencv_yaml().replace("image_width: 640", "image_width: [640"), "not a valid OpenCV YAML file"),
        ("unknown tag", _opencv_yaml().replace("!!opencv-matrix", "!!opencv-thing", 1), "not a valid OpenCV YAML file"),
        ("rvec no tvec", _opencv_yaml().split("tvec:")[0], "has 'rvec', no tvec/T/t"),
        ("size", _opencv_yaml().replace("image_width: 640\n", ""), "needs both image_width and image_height"),
        (
            "width 0",
            _opencv_yaml().replace("image_width: 640", "image_width: 0"),
            "image_width must be a positive whole number",
        ),
        ("not a mapping", "%YAML:1.0\n---\n- 1\n- 2\n", "not a camera file"),
    ],
)
def test_opencv_errors(tmp_path, name, text, message):
    path = _write(tmp_path / "cam.yml", text)
    with pytest.raises(InputError, match=message) as e:
        read_cameras(path)
    assert str(path) in str(e.value) and "\n" not in str(e.value)


def test_rotation_that_is_not_a_rotation(tmp_path):
    doc = {"K": _K().tolist(), "R": (2.0 * R_CV).tolist(), "T": T_CV.tolist()}
    path = tmp_path / "cam.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"R is not a rotation: \|R R\^T - I\| = 3, det = 8") as e:
        read_camera(path)
    assert str(path) in str(e.value)
    mirror = {"K": _K().tolist(), "R": (R_CV @ np.diag([1.0, 1.0, -1.0])).tolist(), "T": T_CV.tolist()}
    path.write_text(json.dumps(mirror))
    with pytest.raises(InputError, match="det = -1"):
        read_camera(path)


def test_easymocap_errors(tmp_path):
    intri, extri = _easymocap_files(tmp_path / "calib")
    text = intri.read_text()
    intri.write_text(text.replace("K_02:", "Kx_02:"))
    with pytest.raises(InputError, match=r"intri.yml: camera '02' has no intrinsics \(no K_02\)"):
        read_cameras(intri.parent)
    intri.write_text(text)
    extri.write_text(extri.read_text().replace("T_02:", "Tx_02:"))
    with pytest.raises(InputError, match=r"extri.yml: camera '02' needs R_02 \(or Rot_02\) and T_02"):
        read_cameras(extri)
    _easymocap_files(tmp_path / "calib")
    intri.unlink()
    with pytest.raises(InputError, match="a camera without intrinsics: an EasyMocap extri file"):
        read_cameras(extri)
    with pytest.raises(InputError, match=r"has no intri\.yml"):
        read_cameras(extri.parent)
    intri, extri = _easymocap_files(tmp_path / "rot")
    extri.write_text(
        extri.read_text()
        .replace("R_01", "Rx_01")
        .replace(_easymocap_matrix("Rot_01", EASY_R["01"]), _easymocap_matrix("Rot_01", 1.1 * EASY_R["01"]))
    )
    with pytest.raises(InputError, match="R is not a rotation"):
        read_cameras(extri)


def test_file_errors(tmp_path):
    with pytest.raises(InputError, match=r"camera file not found: .*nowhere\.toml"):
        read_cameras(tmp_path / "nowhere.toml")
    (tmp_path / "bin.yml").write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe")
    with pytest.raises(InputError, match=r"bin\.yml: not a text camera file"):
        read_cameras(tmp_path / "bin.yml")
    bad_toml = _write(tmp_path / "bad.toml", "[cam_01\nmatrix = 1\n")
    with pytest.raises(InputError, match=r"bad\.toml: not valid TOML") as e:
        read_cameras(bad_toml)
    assert "\n" not in str(e.value)
    only_meta = _write(tmp_path / "meta.toml", "[metadata]\nadjusted = false\n")
    with pytest.raises(InputError, match="no camera sections"):
        read_cameras(only_meta)
    bad_json = _write(tmp_path / "bad.json", '{"K": [1, 2,}')
    with pytest.raises(InputError, match=r"bad\.json: not valid JSON"):
        read_cameras(bad_json)


def test_camera_file_validates_arrays_built_in_code():
    with pytest.raises(InputError, match="extrinsics need both"):
        CameraFile("c", 640, 480, _K(), np.zeros(5), np.eye(3), None)
    with pytest.raises(InputError, match="tilted-sensor"):
        CameraFile("c", 640, 480, _K(), np.r_[np.zeros(12), 0.1, 0.0], None, None)
    with pytest.raises(InputError, match="image height must be a positive whole number"):
        CameraFile("c", 640, 480.5, _K(), np.zeros(5), None, None)
    cam = CameraFile("c", 640.0, 480, _K(), [0.0] * 14, None, None)
    assert cam.width == 640 and cam.dist.shape == (14,) and not cam.K.flags.writeable
