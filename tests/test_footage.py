"""Real footage into runs (`ptrack.pipeline.footage`): a detector's keypoint file, a camera file or none, a
height -> result.npz's keypoints under the format's names in the calibration's world; and the one-line
errors of bad footage inputs."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from cli_errors import fail

from ptrack.body.skeleton import Skeleton
from ptrack.body.subject import (
    CMU_LANDMARK_JOINTS,
    SEGMENTS,
    add_landmark_joints,
    rescale_segments,
    scale_to_height,
    segment_lengths,
)
from ptrack.cli import main
from ptrack.package_data import data_file
from ptrack.pipeline.footage import axis_to_y

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))
import synthetic_footage  # noqa: E402

VIDEO_YAML = str(REPO / "configs" / "video.yaml")
P2S = REPO.parent / "shared" / "data" / "pose2sim"


def test_scale_to_height_gives_every_segment_its_fraction():
    sk = scale_to_height(Skeleton.from_asf(data_file("10.asf")), 1.72)
    got = segment_lengths(sk)
    for name, (_, _, frac) in SEGMENTS.items():
        assert got[name] == pytest.approx(frac * 1.72, rel=1e-6), name


def test_landmark_joints_move_with_their_bone():
    """A face point keeps its distance to the head's end and a heel its distance to the ankle in any pose,
    and sits at its rest offset in the rest pose."""
    sk = scale_to_height(Skeleton.from_asf(data_file("10.asf")), 1.7)
    lm = add_landmark_joints(sk, 1.7)
    assert lm.num_dofs == sk.num_dofs and lm.joint_names[: sk.num_joints] == sk.joint_names
    rest = lm.forward_kinematics(torch.zeros(lm.num_dofs, dtype=torch.float64))
    nose, head = lm.joint_index("lm_nose"), lm.joint_index("head")
    torch.testing.assert_close(rest[nose] - rest[head], torch.tensor([0.0, -0.09, 0.06], dtype=torch.float64) * 1.7)
    q = torch.randn(5, lm.num_dofs, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 0.4
    X = lm.forward_kinematics(q)
    heel, ankle = lm.joint_index("lm_l_heel"), lm.joint_index("ltibia")
    for a, b in ((nose, head), (heel, ankle)):
        d = (X[:, a] - X[:, b]).norm(dim=-1)
        torch.testing.assert_close(d, (rest[a] - rest[b]).norm().expand(5), atol=1e-9, rtol=0)
    # the original joints do not move
    torch.testing.assert_close(X[:, : sk.num_joints], sk.forward_kinematics(q))
    assert {j for j in CMU_LANDMARK_JOINTS.values() if j.startswith("lm_")} <= set(lm.joint_names)


@pytest.mark.parametrize("up", [(0, 0, 1), (0, 0, -1), (1, 0, 0), (0, -1, 0), (0.3, 0.2, 0.9)])
def test_axis_to_y_is_a_rotation_taking_up_to_y(up):
    u = np.asarray(up, dtype=float) / np.linalg.norm(up)
    A = axis_to_y(u)
    np.testing.assert_allclose(A @ A.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(A) == pytest.approx(1.0)
    np.testing.assert_allclose(A @ u, [0.0, 1.0, 0.0], atol=1e-12)


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """A CMU kick seen by a camera with intrinsics only, as a COCO-17 results JSON with a bystander and an
    empty image (scripts/synthetic_footage.py)."""
    out = tmp_path_factory.mktemp("synthetic")
    info = synthetic_footage.make(data_file("10_02.amc"), data_file("10.asf"), out, frames=24)
    return out, info


def _run_synthetic(synthetic, out: Path, *extra: str) -> int:
    folder, info = synthetic
    argv = ["run", VIDEO_YAML, f"observations.file={folder / 'keypoints.json'}", f"camera.file={folder / 'camera.yml'}"]
    argv += [f"subject.height_m={info['height_m']:.3f}", "observations.fps=30", f"out_dir={out}", "progress=false"]
    return main([*argv, *extra])


def test_synthetic_coco_run(synthetic, tmp_path, capsys):
    """The whole path on a COCO results file: the person (not the bystander), every image with someone in
    it, the keypoints under COCO's names, reprojecting onto the 2D, and the 3D shape of the truth."""
    out = tmp_path / "run"
    assert _run_synthetic(synthetic, out) == 0
    folder, info = synthetic
    with np.load(out / "result.npz") as r:
        names = [str(n) for n in r["keypoint_names"]]
        frames, kp = r["frames"], r["keypoints"]
        observed, reproj, conf = r["keypoints_observed"], r["keypoints_reprojected"], r["confidence"]
    assert names[:3] == ["nose", "left_eye", "right_eye"] and len(names) == 17
    assert info["nobody"] not in frames and len(frames) == 23
    assert kp.shape == (23, 17, 3) and np.isfinite(kp).all()
    err = np.linalg.norm(observed - reproj, axis=-1)[conf > 0]
    assert np.median(err) < 5.0  # the chosen person's 2D (2 px noise), not the bystander's
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["footage"]["keypoint_set"] == "COCO_17" and metrics["footage"]["tracks"] == 2
    assert metrics["footage"]["camera"].startswith("file ")
    assert metrics["footage"]["floor_m"] is None  # intrinsics only: no floor known
    per_kp = metrics["reprojection_error_px_per_keypoint"]
    assert set(per_kp) == set(names) and per_kp["nose"] is None  # the face is never observed (score 0)
    assert 0 < metrics["jitter_mm_per_frame2"] < 100 and set(metrics["foot_skating_mm_per_frame"]) == {
        "left_ankle",
        "right_ankle",
    }
    assert 0 <= metrics["ambiguous_frame_share"] <= 1  # kjs has modes
    score = synthetic_footage.score(out / "result.npz", folder / "truth.npz")
    # the frame method from no 3D at all, on a skeleton with other proportions than the template's: a loose
    # bound (a pose with the torso turned by 90 degrees scores over 200 mm); docs/results.md has the numbers
    assert score["pa_mpjpe_mm"] < 150.0, score


def test_without_a_camera_file_the_focal_is_the_image_diagonal(synthetic, tmp_path):
    out = tmp_path / "run"
    assert (
        _run_synthetic(synthetic, out, "camera.file=null", "camera.width=1280", "camera.height=720", "data.stop=4") == 0
    )
    with np.load(out / "result.npz") as r:
        assert r["camera_K"][0, 0] == pytest.approx(np.hypot(1280, 720))
    assert "no camera file" in json.loads((out / "metrics.json").read_text())["footage"]["camera"]


@pytest.mark.parametrize(
    ("override", "fragment"),
    [
        ("subject.height_m=-1", "subject.height_m"),
        ("subject.height_m=7", "subject.height_m"),
        ("camera.name=cam09", "cam09"),
        ("observations.person=[1, 2, 3]", "observations.person"),
        ("observations.min_score=1.5", "observations.min_score"),
        ("camera.fov_deg=0", "camera.fov_deg"),
        ("subject.lengths=guess", "subject.lengths"),
    ],
)
def test_bad_footage_settings_are_one_line_errors(synthetic, tmp_path, capsys, override, fragment):
    folder, _ = synthetic
    out = tmp_path / "run"
    argv = ["run", VIDEO_YAML, f"observations.file={folder / 'keypoints.json'}", f"camera.file={folder / 'camera.yml'}"]
    fail(capsys, out, [*argv, "observations.fps=30", f"out_dir={out}", override], fragment)


def test_bad_footage_files_are_one_line_errors(synthetic, tmp_path, capsys):
    folder, _ = synthetic
    out = tmp_path / "run"
    base = ["run", VIDEO_YAML, "observations.fps=30", f"out_dir={out}"]
    empty = tmp_path / "empty"
    empty.mkdir()
    fail(capsys, out, [*base, f"observations.file={empty}"], str(empty))
    fail(capsys, out, [*base, f"observations.file={folder / 'keypoints.json'}"], "camera.width")  # no size known
    fail(capsys, out, [*base, f"observations.file={tmp_path / 'nothing.json'}"], "nothing.json")
    both = [f"observations.file={folder / 'keypoints.json'}", f"observations.video={tmp_path / 'v.mp4'}"]
    fail(capsys, out, [*base, *both], "observations.video")
    bad_cam = tmp_path / "cam.yml"
    bad_cam.write_text((folder / "camera.yml").read_text().replace("1000.000000, 0.000000, 640", "0.0, 0.000000, 640"))
    fail(capsys, out, [*base, f"observations.file={folder / 'keypoints.json'}", f"camera.file={bad_cam}"], "cam.yml")


@pytest.mark.skipif(not P2S.is_dir(), reason=f"Pose2Sim data not found at {P2S}")
def test_pose2sim_openpose_folder_in_the_lab_frame(tmp_path, capsys):
    """Real OpenPose BODY_25B and the real calibration: the participant chosen over the bystander, the
    keypoints in the lab's Z-up world, where the multi-camera triangulation puts them (within 0.3 m)."""
    src = P2S / "balancing" / "pose" / "cam01_json"
    out = tmp_path / "run"
    argv = ["run", VIDEO_YAML, f"observations.file={src}", f"camera.file={P2S / 'Calib_qualisys.toml'}"]
    argv += ["subject.height_m=1.72", "observations.fps=60", "data.stop=8", f"out_dir={out}"]
    fail(capsys, out, argv, "camera.name", "cam_01, cam_02")  # four cameras in the file: which one?
    assert main([*argv, "camera.name=cam01", "progress=false"]) == 0
    with np.load(out / "result.npz") as r:
        names = [str(n) for n in r["keypoint_names"]]
        kp, frames = r["keypoints"], r["frames"]
    lines = (P2S / "balancing" / "triangulated.trc").read_text().splitlines()
    markers = [n for n in lines[3].split("\t")[2:] if n.strip()]
    rows = np.array([[float(x) for x in line.split("\t")[2 : 2 + 3 * len(markers)]] for line in lines[5:13]])
    ref = rows.reshape(8, len(markers), 3)[:, :, [2, 0, 1]]  # TRC (X, Y, Z) = lab (Y, Z, X)
    common = [n for n in ("LHip", "RHip", "LShoulder", "RShoulder") if n in names]
    est_c = kp[:, [names.index(n) for n in common]].mean(1)
    ref_c = ref[frames][:, [markers.index(n) for n in common]].mean(1)
    assert np.linalg.norm(est_c - ref_c, axis=-1).max() < 0.3
    assert kp[:, names.index("LShoulder"), 2].mean() > kp[:, names.index("LAnkle"), 2].mean() + 1.0  # Z is up
    # the calibration gives the floor (Z = 0): a foot rests on it in every frame of this balancing trial
    assert json.loads((out / "metrics.json").read_text())["footage"]["floor_m"] == 0.0
    feet = [names.index(n) for n in ("LBigToe", "RBigToe", "LHeel", "RHeel", "LSmallToe", "RSmallToe")]
    assert np.abs(kp[:, feet, 2].min(1)).max() < 0.1


def test_footage_fixture_copy_runs_from_a_plain_clone(tmp_path):
    """The shipped OpenPose frames (tests/data/keypoints) read without ../shared: three frames, two people."""
    from ptrack.observe.keypoint_files import read_keypoints
    from ptrack.observe.people import select_person

    src = REPO / "tests" / "data" / "keypoints" / "two_people_cam01"
    shutil.copytree(src, tmp_path / "kp")
    track = select_person(read_keypoints(tmp_path / "kp"))
    assert track.keypoint_set == "BODY_25B" and track.points.shape[1:] == (25, 2)


def test_segment_lengths_from_2d_reach_the_length_in_the_image_plane():
    """Exact 2D of a body turning in front of a level camera: a vertical segment (thigh, shank, trunk of the rest
    pose) lies in the image plane in every frame, so d Z / f gives its length; a horizontal one (the arms of the
    T pose) only when the body faces the camera, so the maximum over a half turn is its length, the median less."""
    from ptrack.body.keypoint_sets import COCO_17
    from ptrack.body.keypoints import landmark_keypoints
    from ptrack.body.subject import landmark_joints
    from ptrack.estimators.lengths import segment_lengths_from_2d
    from ptrack.observe.camera import look_at
    from ptrack.observe.observations import Observations
    from ptrack.problem import Estimate, Problem

    sk = add_landmark_joints(scale_to_height(Skeleton.from_asf(data_file("10.asf")), 1.7), 1.7)
    joints = [str(j) for j in landmark_joints(sk, COCO_17.landmarks)]
    kps = landmark_keypoints(sk, COCO_17.names, COCO_17.landmarks, joints)
    T = 19
    q = torch.zeros(T, sk.num_dofs, dtype=torch.float64)
    q[:, sk.dof_names.index("root.ry")] = torch.linspace(-torch.pi / 2, torch.pi / 2, T)
    X = sk.forward_kinematics(q)
    cam = look_at([0.0, 0.0, 0.0], 4.0, 0.0, 0.0, 1000.0, 1280, 720)
    px = cam.project(X[:, kps.index()]).pixels
    obs = Observations(px, torch.ones(T, 17, dtype=torch.float64), torch.arange(T) / 30.0, cam, COCO_17.names)
    problem = Problem(skeleton=sk, keypoints=kps, observations=obs)
    est = Estimate(q=q, joints=X, cost=torch.zeros(T), terms={})
    segments = {n: (a, b) for n, (a, b, _) in SEGMENTS.items() if n in ("thigh", "trunk", "upper_arm")}
    rest = sk.forward_kinematics(torch.zeros(sk.num_dofs, dtype=torch.float64))

    def length(a: str, b: str) -> float:
        return float((rest[kps.joints[COCO_17.index(a)]] - rest[kps.joints[COCO_17.index(b)]]).norm())

    # the CMU template is not symmetric (its right humerus is 9% longer): the longer side reaches the top quantile
    want = {n: max(length(a, b), length(*("r_" + m[2:] for m in (a, b)))) for n, (a, b) in segments.items()}
    top = segment_lengths_from_2d(problem, est, COCO_17.landmarks, segments, quantile=1.0)
    mid = segment_lengths_from_2d(problem, est, COCO_17.landmarks, segments, quantile=0.5)
    for name in segments:
        assert top[name][0] == pytest.approx(want[name], rel=0.01), name
        assert top[name][1] == 2 * T
    assert mid["upper_arm"][0] < 0.9 * want["upper_arm"]  # the arm turns out of the image plane
    assert mid["thigh"][0] == pytest.approx(want["thigh"], rel=0.05)


def test_rescale_segments_sets_the_targets_and_moves_the_landmark_joints():
    sk = add_landmark_joints(scale_to_height(Skeleton.from_asf(data_file("10.asf")), 1.7), 1.7)
    new = rescale_segments(sk, 1.7, {"shank": 0.5, "forearm": 0.2})
    got = segment_lengths(new)
    assert got["shank"] == pytest.approx(0.5, rel=1e-6) and got["forearm"] == pytest.approx(0.2, rel=1e-6)
    assert got["thigh"] == pytest.approx(SEGMENTS["thigh"][2] * 1.7, rel=1e-6)
    heel = sk.joint_index("lm_l_heel")
    foot = [sk.joint_index(b) for b in ("lfoot", "rfoot")]
    assert new.lengths[heel] / sk.lengths[heel] == pytest.approx(np.mean(new.lengths[foot] / sk.lengths[foot]))
