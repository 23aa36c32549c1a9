"""Real footage into runs (`ptrack.pipeline.footage`): a detector's keypoint file, a camera file or none, a
height -> result.npz's keypoints under the format's names in the calibration's world; and the one-line
errors of bad footage inputs."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from cli_errors import fail

from ptrack.body.keypoint_sets import get_keypoint_set
from ptrack.body.skeleton import Skeleton
from ptrack.body.subject import (
    ANKLE_HEIGHT,
    CMU_LANDMARK_JOINTS,
    FLOOR_POINTS,
    SEGMENTS,
    add_landmark_joints,
    rescale_segments,
    scale_to_height,
    segment_lengths,
    standing_height,
)
from ptrack.cli import main
from ptrack.package_data import data_file
from ptrack.pipeline.footage import axis_to_y
from ptrack.pipeline.metrics import pa_mpjpe

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "scripts"))
import synthetic_footage  # noqa: E402

VIDEO_YAML = str(REPO / "configs" / "video.yaml")
P2S = REPO.parent / "shared" / "data" / "pose2sim"


def logged_metrics(rrd: Path) -> dict[str, dict[int, float]]:
    """The per-frame scalars a run logged under metrics/ in its rerun file: {name: {frame: value}}."""
    import rerun.chunk

    out: dict[str, dict[int, float]] = {}
    for chunk in rerun.chunk.RrdReader(rrd).stream().to_chunks():
        entity = chunk.entity_path.lstrip("/")
        if chunk.is_static or not entity.startswith("metrics/"):
            continue
        batch = chunk.to_record_batch()
        values = batch.column("Scalars:scalars").to_pylist()
        frames = batch.column("frame").to_pylist()
        out.setdefault(entity.removeprefix("metrics/"), {}).update({f: v[0] for f, v in zip(frames, values)})
    return out


def test_scale_to_height_gives_every_segment_its_fraction():
    sk = scale_to_height(Skeleton.from_asf(data_file("10.asf")), 1.72)
    got = segment_lengths(sk)
    for name, (_, _, frac) in SEGMENTS.items():
        assert got[name] == pytest.approx(frac * 1.72, rel=1e-6), name


def test_standing_height_counts_the_legs_straight():
    """A CMU ASF's rest pose splays the legs outwards: the stature is the same as that of the same skeleton with
    its legs turned to hang straight down (measured there as the head's end above the ankles), and above what the
    splayed ankles' height would give."""
    sk = Skeleton.from_asf(data_file("10.asf"))
    _, rot = sk.forward_kinematics(torch.zeros(sk.num_dofs, dtype=torch.float64), rotations=True)
    local = sk.offset_local.copy()
    for bone in ("lfemur", "rfemur", "ltibia", "rtibia"):  # the bone vector, in the joint's frame, made world -Y
        j = sk.joint_index(bone)
        local[j] = rot[j].numpy().T @ np.array([0.0, -1.0, 0.0])
    straight = dataclasses.replace(sk, offset_local=local)
    joints = straight.forward_kinematics(torch.zeros(sk.num_dofs, dtype=torch.float64)).numpy()
    hip, ankle = joints[straight.joint_index("lfemur") - 1], joints[straight.joint_index("ltibia")]
    assert np.allclose(hip[[0, 2]], ankle[[0, 2]])  # the ankle right below the hip
    top = joints[sk.joint_index("head"), 1]
    extent = (top - joints[[sk.joint_index("ltibia"), sk.joint_index("rtibia")], 1].mean()) / (1 - ANKLE_HEIGHT)
    assert standing_height(sk) == pytest.approx(extent, rel=1e-9)
    assert standing_height(straight) == pytest.approx(extent, rel=1e-9)
    splayed = sk.forward_kinematics(torch.zeros(sk.num_dofs, dtype=torch.float64)).numpy()
    assert (top - splayed[sk.joint_index("ltibia"), 1]) / (1 - ANKLE_HEIGHT) < 0.98 * extent


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


def test_synthetic_footage_with_the_feet_and_the_camera_pose(tmp_path):
    """scripts/synthetic_footage.py's lab-like variant: HALPE-26 (the feet, neck and pelvis scored, the face and
    head top not) and the camera's pose in its YAML, which ptrack reads as a calibration; the floor it states lies
    under the feet, the truth keeps the camera frame turned Y-up, and a run's keypoints score as the plain footage's."""
    from ptrack.observe.camera_files import read_camera

    info = synthetic_footage.make(
        data_file("10_02.amc"), data_file("10.asf"), tmp_path, frames=6, keypoints="halpe26", extrinsics=True
    )
    images = json.loads((tmp_path / "keypoints.json").read_text())
    person = next(r for r in images if r["image_id"] == 1)
    kp = np.asarray(person["keypoints"]).reshape(26, 3)
    halpe = get_keypoint_set("halpe26")
    seen = {halpe.landmarks[i] for i in np.flatnonzero(kp[:, 2] > 0)}
    assert {"l_heel", "r_big_toe", "neck", "pelvis", "l_ankle"} <= seen
    assert not seen & {"nose", "l_eye", "r_ear", "head_top"}
    cam = read_camera(tmp_path / "camera.yml")
    assert cam.R is not None and cam.t is not None
    with np.load(tmp_path / "truth.npz") as t:
        assert str(t["keypoint_set"]) == "halpe26" and t["keypoints"].shape == (6, 26, 3)
        assert float(t["floor_m"]) == pytest.approx(info["floor_m"])
    # the world is the CMU clip's (Y up): the camera looks slightly down at a person standing on a floor below it
    centre = -cam.R.T @ cam.t
    assert centre[1] > info["floor_m"] + 0.3
    # the score reads the set from the truth: the truth scored against itself is 0
    res = tmp_path / "self.npz"
    with np.load(tmp_path / "truth.npz") as t:
        np.savez(
            res,
            keypoints=t["keypoints"] * np.array([1.0, -1.0, -1.0]),
            keypoint_names=t["keypoint_names"],
            world_from_model=np.eye(3),
            camera_R=np.eye(3),
            camera_t=np.zeros(3),
            frames=t["frames"],
        )
    s = synthetic_footage.score(res, tmp_path / "truth.npz")
    assert s["pa_mpjpe_mm"] == pytest.approx(0.0, abs=1e-6) and s["mpjpe_mm"] == pytest.approx(0.0, abs=1e-6)


def test_error_breakdown_splits_position_and_shape(tmp_path, capsys):
    """scripts/error_breakdown.py on a synthetic run folder (its truth found beside it): a shifted copy of the
    truth has the shift as its mid-hip offset and no other error; a copy scaled about the mid-hips keeps
    PA-MPJPE at 0 and shows the scale in every segment's ratio and in the hip-aligned error."""
    import error_breakdown

    synthetic_footage.make(data_file("10_02.amc"), data_file("10.asf"), tmp_path / "clip" / "footage", frames=6)
    truth = tmp_path / "clip" / "footage" / "truth.npz"
    run = tmp_path / "clip" / "observed"
    run.mkdir()

    def write(move):  # the truth moved by `move` (truth frame), as a run with R = I, t = 0 would report it
        with np.load(truth) as t:
            kp = move(t["keypoints"]) * np.array([1.0, -1.0, -1.0])
            names, frames = t["keypoint_names"], t["frames"]
        np.savez(
            run / "result.npz",
            keypoints=kp,
            keypoint_names=names,
            world_from_model=np.eye(3),
            camera_R=np.eye(3),
            camera_t=np.zeros(3),
            frames=frames,
        )

    write(lambda x: x + np.array([0.1, 0.0, -0.05]))
    b = error_breakdown.breakdown(*error_breakdown.pairs(run, None, None))
    assert b["offset"] == pytest.approx([100.0, 0.0, -50.0], abs=1e-6)
    assert b["depth"] == pytest.approx(50.0, abs=1e-6)  # -Z is the viewing direction in the truth's frame
    assert b["trunk_tilt"] == pytest.approx(0.0, abs=1e-6) and b["legs_tilt"] == pytest.approx(0.0, abs=1e-6)
    assert b["pa"] == pytest.approx(0.0, abs=1e-6) and b["hip_aligned"] == pytest.approx(0.0, abs=1e-6)
    assert b["mpjpe"] == pytest.approx(np.hypot(100.0, 50.0), rel=1e-9)
    assert b["est_lengths"] == pytest.approx(b["ref_lengths"], rel=1e-9)

    hips = synthetic_footage.body_names(truth)[6:8]
    with np.load(truth) as t:
        idx = [[str(n) for n in t["keypoint_names"]].index(h) for h in hips]
    write(lambda x: x[:, idx].mean(1, keepdims=True) + 1.1 * (x - x[:, idx].mean(1, keepdims=True)))
    b = error_breakdown.breakdown(*error_breakdown.pairs(run, None, None))
    assert b["pa"] == pytest.approx(0.0, abs=1e-4) and b["offset"] == pytest.approx([0.0, 0.0, 0.0], abs=1e-6)
    assert b["est_lengths"] / b["ref_lengths"] == pytest.approx(np.full(11, 1.1), rel=1e-9)
    assert b["hip_aligned"] > 10.0 and b["trunk_tilt"] == pytest.approx(0.0, abs=1e-6)
    assert error_breakdown.main([str(run), str(run), "--mean"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("mean of 2 runs") and "| L shank |" in out and "| 1.100 |" in out


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
    # intrinsics only: up and the floor from the person's feet (a kick in place: its height, not its tilt, which stays
    # near the camera's image-up; the camera looks 5 degrees down), the second pass's lowest foot points on it
    footage = metrics["footage"]
    assert footage["up"] == "person" and footage["ground"]["tilt_deg"] < 10 and footage["ground"]["contacts"] >= 10
    assert footage["mirror_switch_frames"] == [] and footage["swap_cost"] == 0.0  # nothing mirrored: the labels only
    with np.load(out / "result.npz") as r:
        joint_names, joints = [str(n) for n in r["joint_names"]], r["joints"]
    feet = [joint_names.index(n) for n in FLOOR_POINTS if n in joint_names]
    low = joints[:, feet, 1].min(-1) - footage["floor_m"]
    assert np.median(low) == pytest.approx(0.0, abs=0.05)  # the clearance (a centimetre or two) and the 2D's noise
    per_kp = metrics["reprojection_error_px_per_keypoint"]
    assert set(per_kp) == set(names) and per_kp["nose"] is None  # the face is never observed (score 0)
    assert 0 < metrics["jitter_mm_per_frame2"] < 100 and set(metrics["foot_skating_mm_per_frame"]) == {
        "left_ankle",
        "right_ankle",
    }
    assert 0 <= metrics["ambiguous_frame_share"] <= 1  # kjs has modes
    # the same checks frame by frame in the rerun log, on the run's frames
    logged = logged_metrics(out / "run.rrd")
    assert set(logged["ambiguous_frame"]) == set(frames.tolist()) and set(logged["ambiguous_frame"].values()) <= {0, 1}
    assert np.mean(list(logged["ambiguous_frame"].values())) == pytest.approx(metrics["ambiguous_frame_share"])
    shares = metrics["ambiguous_frame_share_per_limb"].values()
    assert np.mean(list(logged["ambiguous_limb_share"].values())) == pytest.approx(np.mean(list(shares)))
    assert logged["person_missing"] == dict.fromkeys(frames.tolist(), 0.0)  # the empty image is not a frame
    assert logged["left_right_exchanged"] == dict.fromkeys(frames.tolist(), 0.0)  # nothing mirrored, none read so
    skating = logged["foot_skating_mm_per_frame"]  # the feet's mean step while on the floor
    assert 3 <= len(skating) < len(frames) and frames[0] not in skating
    assert all(v >= 0 for v in skating.values())
    per_foot = [v for v in metrics["foot_skating_mm_per_frame"].values() if v is not None]
    assert min(per_foot) <= max(skating.values()) and max(per_foot) >= min(skating.values())
    assert len(logged["jitter_mm_per_frame2"]) == len(frames) - 2
    # video.yaml's subject.lengths: observed: the limbs and the trunk measured (the model has those lengths), the
    # others the height's proportions with a stated prior spread, not the data's
    lengths, measured = metrics["bone_lengths"], metrics["footage"]["segments_measured"]
    assert set(lengths) == set(SEGMENTS) and set(measured) == {"thigh", "shank", "upper_arm", "forearm", "trunk"}
    for name, (_, _, fraction) in SEGMENTS.items():
        row = lengths[name]
        if name in measured:
            assert row["source"] == "observed" and row["length_m"] == pytest.approx(measured[name]["length_m"]), name
            continue
        assert (row["source"], row["std_source"]) == ("template", "prior"), name
        assert row["length_m"] == pytest.approx(fraction * info["height_m"], rel=1e-3), name
        assert row["std_m"] == pytest.approx(0.05 * row["length_m"]), name
    score = synthetic_footage.score(out / "result.npz", folder / "truth.npz")
    # kjs from no 3D at all, on a skeleton with other proportions than the template's: a loose bound (a pose with
    # the torso turned by 90 degrees scores over 200 mm); docs/results.md has the numbers
    assert score["pa_mpjpe_mm"] < 150.0, score


def test_a_detector_that_mirrors_the_person_turns_the_exchanged_reading_on(synthetic, tmp_path):
    """`costs.swap_cost: null` (the default): where the detector exchanged every left/right label of the person between
    two frames (here images 8-15 of the synthetic footage), the run reads the labels exchanged too, at AUTO_SWAP_COST,
    and the footage record says where and at what price; on the clean file, and with a price given, it does not."""
    from ptrack.costs.config import AUTO_SWAP_COST
    from ptrack.pipeline.config import load_config
    from ptrack.pipeline.run import prepare, with_swap_cost

    folder, info = synthetic
    mirrored_folder = tmp_path / "mirrored"  # the same footage with the participant mirrored in images 8-15
    synthetic_footage.make(data_file("10_02.amc"), data_file("10.asf"), mirrored_folder, frames=24, mirrored=(8, 15))
    mirrored = mirrored_folder / "keypoints.json"
    images = json.loads(mirrored.read_text())
    clean = json.loads((folder / "keypoints.json").read_text())
    mirror = get_keypoint_set("coco17").mirror_index()
    for a, b in zip(images, clean, strict=True):  # the participant's labels exchanged there, nothing else
        same = a["image_id"] not in range(8, 16) or a["score"] < 0.9  # (the bystander's score is 0.7)
        want = np.reshape(b["keypoints"], (-1, 3)) if same else np.reshape(b["keypoints"], (-1, 3))[mirror]
        np.testing.assert_array_equal(np.reshape(a["keypoints"], (-1, 3)), want)
    seen = sorted({e["image_id"] for e in images} - {info["nobody"]})
    switches = [min(i for i in seen if i >= 8), min(i for i in seen if i >= 16)]
    base = [f"camera.file={folder / 'camera.yml'}", f"subject.height_m={info['height_m']:.3f}", "observations.fps=30"]
    for keypoints, extra, frames, price in (
        (folder / "keypoints.json", [], [], 0.0),
        (mirrored, [], switches, AUTO_SWAP_COST),
        (mirrored, ["costs.swap_cost=0"], switches, 0.0),
        (folder / "keypoints.json", ["costs.swap_cost=1.5"], [], 1.5),
    ):
        cfg = load_config(VIDEO_YAML, [f"observations.file={keypoints}", *base, *extra])
        cfg, prep = with_swap_cost(cfg, prepare(cfg, tmp_path))
        assert prep.footage is not None
        assert list(prep.footage.mirror_switches) == frames and cfg.costs.swap_cost == price, (keypoints, extra)
        assert prep.footage.summary()["swap_cost"] == price
        assert prep.footage.summary()["mirror_switch_frames"] == frames
    # the whole run: the mirrored images read exchanged, and their reprojection error counted in that reading
    out = tmp_path / "run"
    assert _run_synthetic((mirrored_folder, info), out) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["footage"]["swap_cost"] == AUTO_SWAP_COST
    assert metrics["left_right_exchanged_frames"] == [i for i in seen if 8 <= i <= 15]
    assert metrics["reprojection_error_px"] < 10.0  # 2 px noise: the labels the run used, not the detector's
    with np.load(out / "result.npz") as r:  # the detections as labelled: the mirrored images far off
        err = np.linalg.norm(r["keypoints_observed"] - r["keypoints_reprojected"], axis=-1)
        err = np.where(r["confidence"] > 0, err, np.nan)
        mirrored_rows = np.isin(r["frames"], np.arange(8, 16))
    assert np.nanmean(err[mirrored_rows]) > 3 * metrics["reprojection_error_px"]


def test_known_skeleton_keeps_the_asf_bone_lengths(synthetic, tmp_path):
    """subject.lengths: asf: the model has the bone lengths of data.asf as they are (not the height's proportions),
    metrics.json says so (source asf, spread 0, given), and without a height the skeleton's standing height is used
    (the one the footage was made with)."""
    folder, info = synthetic
    asf = data_file("10.asf")
    out = tmp_path / "run"
    argv = ["run", VIDEO_YAML, f"observations.file={folder / 'keypoints.json'}", f"camera.file={folder / 'camera.yml'}"]
    argv += ["observations.fps=30", "data.stop=4", "kjs.modes=2", "kjs.samples=32", f"out_dir={out}", "progress=false"]
    assert main([*argv, "subject.lengths=asf", f"data.asf={asf}", "subject.height_m=null"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    skeleton = Skeleton.from_asf(asf)
    assert metrics["footage"]["height_m"] == pytest.approx(info["height_m"], rel=1e-9)
    assert metrics["footage"]["height_given"] is False
    want, template = segment_lengths(skeleton), segment_lengths(scale_to_height(skeleton, info["height_m"]))
    assert max(abs(want[n] / template[n] - 1) for n in want) > 0.05  # the template's proportions differ
    for name, row in metrics["bone_lengths"].items():
        assert row["length_m"] == pytest.approx(want[name], rel=1e-9), name
        assert (row["source"], row["std_m"], row["std_source"]) == ("asf", 0.0, "given"), name
    # every ASF bone of the fitted motion at the file's length: float32 joints some metres from the origin (5 um)
    with np.load(out / "result.npz") as r:
        names, joints, parents = [str(n) for n in r["joint_names"]], r["joints"], r["parents"]
    for j, bone in enumerate(skeleton.joint_names[1:], 1):
        k = names.index(bone)
        d = np.linalg.norm(joints[:, k] - joints[:, parents[k]], axis=-1)
        np.testing.assert_allclose(d, skeleton.lengths[j], rtol=0, atol=5e-6, err_msg=bone)


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
        ("subject.measure_stride=0", "subject.measure_stride"),
        ("observations.track_fps=0", "observations.track_fps"),
        ("subject.measure_backward_pass=sometimes", "subject.measure_backward_pass"),
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
    # the detector's foot points sit 3-8 cm up in the 4-camera reference; without the floor the lowest is 0.29 m up
    # at the median. Measured: 0.05-0.11 m; 0.18-0.21 m since the CMU pose mixture ranks the modes (configs/video.yaml,
    # 2026-11-29): in these first frames it takes the right knee bent, the foot lifted (docs/notes/footage-history.md)
    lowest = kp[:, feet, 2].min(1)
    assert np.abs(lowest).max() < 0.25 and np.median(lowest) < 0.23


@pytest.mark.skipif(not P2S.is_dir(), reason=f"Pose2Sim data not found at {P2S}")
def test_observed_lengths_carry_their_spread_over_the_frames(tmp_path):
    """subject.lengths: observed on real OpenPose: the measured segments report the length the model used and a
    bootstrap spread, the segments it cannot measure the template's length and the prior spread."""
    out = tmp_path / "run"
    argv = ["run", VIDEO_YAML, f"observations.file={P2S / 'balancing' / 'pose' / 'cam01_json'}", "camera.name=cam01"]
    argv += [f"camera.file={P2S / 'Calib_qualisys.toml'}", "subject.height_m=1.72", "observations.fps=60"]
    argv += ["data.stop=6", "kjs.modes=2", "kjs.samples=32"]  # a short, cheap tracking: the lengths' report is tested
    assert main([*argv, "subject.lengths=observed", f"out_dir={out}", "progress=false"]) == 0
    metrics = json.loads((out / "metrics.json").read_text())
    lengths, measured = metrics["bone_lengths"], metrics["footage"]["segments_measured"]
    assert set(measured) == {"thigh", "shank", "upper_arm", "forearm", "trunk"}  # left and right: 12 >= 10 samples
    for name, row in lengths.items():
        if name in measured:
            assert row["source"] == "observed" and row["frames"] == measured[name]["frames"] == 12, name
            assert row["length_m"] == pytest.approx(measured[name]["length_m"], rel=1e-4), name  # what the model has
            assert row["std_m"] == measured[name]["std_m"] and 0 < row["std_m"] < 0.1 * row["length_m"], name
        else:
            assert (row["source"], row["std_source"]) == ("template", "prior"), name
            assert row["length_m"] == pytest.approx(SEGMENTS[name][2] * 1.72, rel=1e-4), name


@pytest.mark.skipif(not P2S.is_dir(), reason=f"Pose2Sim data not found at {P2S}")
def test_a_strided_first_run_measures_on_every_frame_and_reports_every_frame(tmp_path):
    """subject.measure_stride=2 with kjs's first run forwards only: the first run tracks frames 0, 2, 4, the lengths
    are measured on all six frames' 2D at depths between them, and the second run reports every input frame."""
    out = tmp_path / "run"
    argv = ["run", VIDEO_YAML, f"observations.file={P2S / 'balancing' / 'pose' / 'cam01_json'}", "camera.name=cam01"]
    argv += [f"camera.file={P2S / 'Calib_qualisys.toml'}", "subject.height_m=1.72", "observations.fps=60"]
    argv += ["data.stop=6", "kjs.modes=2", "kjs.samples=32", "subject.measure_stride=2"]
    argv += ["subject.measure_backward_pass=never", f"out_dir={out}", "progress=false"]
    assert main(argv) == 0
    measured = json.loads((out / "metrics.json").read_text())["footage"]["segments_measured"]
    assert set(measured) == {"thigh", "shank", "upper_arm", "forearm", "trunk"}
    assert all(row["frames"] == 12 for row in measured.values())  # 6 frames, left and right: all the 2D
    with np.load(out / "result.npz") as r:
        assert r["q"].shape[0] == 6 and np.isfinite(r["keypoints"]).all()


def test_between_frames_is_linear_and_holds_the_last():
    """Every n-th frame's values -> every frame: linear between them, the last held after it."""
    from ptrack.pipeline.run import between_frames

    x = torch.tensor([[0.0, 10.0], [2.0, 30.0], [4.0, 50.0]])  # frames 0, 2, 4
    y = between_frames(x, 2, 6)
    torch.testing.assert_close(y[:, 0], torch.tensor([0.0, 1.0, 2.0, 3.0, 4.0, 4.0]))
    torch.testing.assert_close(y[:, 1], torch.tensor([10.0, 20.0, 30.0, 40.0, 50.0, 50.0]))
    torch.testing.assert_close(between_frames(x, 1, 3), x)


def test_lowpass_trajectory_smooths_between_jumps_and_keeps_the_body():
    """`observations.filter_hz`: a slow swing with noise comes out nearer the swing; a jump of the whole body (a
    change of reading) stays a jump, not smeared over its neighbours; the yaw crossing +-pi is filtered as one
    angle; the poses stay within the limits, the joints are their forward kinematics, the rest as tracked."""
    from ptrack.pipeline.run import lowpass_trajectory
    from ptrack.problem import Estimate

    sk = Skeleton.from_asf(data_file("10.asf"))
    T, fps = 120, 60.0
    gen = torch.Generator().manual_seed(0)
    t = torch.arange(T, dtype=torch.float64) / fps
    clean = torch.zeros(T, sk.num_dofs, dtype=torch.float64)
    knee, x, yaw = sk.dof_names.index("ltibia.rx"), sk.dof_names.index("root.tx"), sk.dof_names.index("root.ry")
    clean[:, knee] = 0.6 + 0.4 * torch.sin(2 * math.pi * 0.5 * t)  # a slow bend, 0.5 Hz
    clean[:, yaw] = math.pi - 0.2 + 0.4 * t / t[-1]  # turning through +pi
    clean[60:, x] += 1.0  # the whole body a metre aside from frame 60 on: a jump
    lower, upper = sk.limits(dtype=torch.float64)
    clean = torch.maximum(torch.minimum(clean, upper), lower)
    noisy = clean + 0.03 * torch.randn(T, sk.num_dofs, generator=gen, dtype=torch.float64)
    noisy[:, yaw] = torch.remainder(noisy[:, yaw] + math.pi, 2 * math.pi) - math.pi  # reported in (-pi, pi]
    noisy = torch.maximum(torch.minimum(noisy, upper), lower)
    est = Estimate(q=noisy, joints=sk.forward_kinematics(noisy), cost=torch.ones(T), terms={})
    out = lowpass_trajectory(sk, est, fps, 6.0)

    def err(q: torch.Tensor) -> float:
        return float((q[:, knee] - clean[:, knee]).abs().mean())

    assert err(out.q) < 0.6 * err(noisy)  # nearer the slow bend
    torch.testing.assert_close(out.joints, sk.forward_kinematics(out.q))
    assert (out.q >= lower - 1e-12).all() and (out.q <= upper + 1e-12).all()
    assert abs(float(out.q[59, x] - clean[59, x])) < 0.05 and abs(float(out.q[60, x] - clean[60, x])) < 0.05
    turned = torch.remainder(out.q[:, yaw] - clean[:, yaw] + math.pi, 2 * math.pi) - math.pi
    assert turned.abs().max() < 0.1  # no swing the long way round at the crossing
    assert out.cost is est.cost and out.terms is est.terms


def test_filter_hz_not_under_half_the_frame_rate_is_a_warning(synthetic, tmp_path, caplog):
    """configs/video.yaml low-passes at 6 Hz; footage at 10 fps or less cannot hold that: a warning, no filter."""
    from ptrack.pipeline.config import load_config
    from ptrack.pipeline.run import prepare, with_filter

    folder, info = synthetic
    base = [f"observations.file={folder / 'keypoints.json'}", f"camera.file={folder / 'camera.yml'}"]
    base += [f"subject.height_m={info['height_m']:.3f}"]
    for fps, warned in ((30, False), (12, True)):
        caplog.clear()
        cfg = load_config(VIDEO_YAML, [*base, f"observations.fps={fps}"])
        assert cfg.observations.filter_hz == 6
        prep = with_filter(cfg, prepare(cfg, tmp_path))
        assert ("not under half the frame rate" in caplog.text) == warned, fps
        assert prep.footage is not None and prep.footage.filter_hz == (None if warned else 6), fps


def test_fill_frames_interpolates_the_pose_and_moves_the_hypotheses():
    """An estimate of frames 0, 2, 4 -> frames 0-5: the tracked frames as they were, the pose halfway between them
    (an angle the shorter way round, through +-pi), the joints its forward kinematics, the hypotheses moved with the
    body, no jumps on the filled frames, the last frame held."""
    from ptrack.pipeline.run import fill_frames
    from ptrack.problem import Estimate

    sk = Skeleton.from_asf(data_file("10.asf"))
    gen = torch.Generator().manual_seed(0)
    q = 0.2 * torch.randn(3, sk.num_dofs, generator=gen, dtype=torch.float64)
    yaw = sk.dof_names.index("root.ry")
    q[:, yaw] = torch.tensor([3.0, -3.0, -2.9], dtype=torch.float64)  # 3.0 -> -3.0 crosses pi, not 0
    joints = sk.forward_kinematics(q)
    hyp = joints[:, None] + torch.randn(3, 4, sk.num_joints, 3, generator=gen, dtype=torch.float64)
    est = Estimate(
        q=q,
        joints=joints,
        cost=torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64),
        terms={"mode_cost": torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)},
        hypotheses=hyp,
        hypothesis_weights=torch.full((3, 4), 0.25, dtype=torch.float64),
        jumps={"larm": torch.tensor([1, 2, 3])},
    )
    out = fill_frames(sk, est, 2, 6)
    assert out.q.shape == (6, sk.num_dofs) and out.hypotheses is not None and out.hypotheses.shape[0] == 6
    torch.testing.assert_close(out.q[[0, 2, 4]], q)
    torch.testing.assert_close(out.q[5], q[2])  # held after the last tracked frame
    mid = 0.5 * (q[0] + q[1])
    assert abs(math.remainder(float(out.q[1, yaw]) - math.pi, 2 * math.pi)) < 1e-9  # 3.0 -> -3.0 the short way
    keep = [d for d in range(sk.num_dofs) if d != yaw]
    torch.testing.assert_close(out.q[1, keep], mid[keep])
    torch.testing.assert_close(out.joints, sk.forward_kinematics(out.q))
    torch.testing.assert_close(out.hypotheses[1] - out.joints[1], hyp[0] - joints[0])
    assert out.jumps is not None and out.jumps["larm"].tolist() == [1, 0, 2, 0, 3, 0]
    assert out.cost.tolist() == [1.0, 1.0, 2.0, 2.0, 3.0, 3.0]
    assert fill_frames(sk, est, 1, 3) is est


@pytest.mark.skipif(not P2S.is_dir(), reason=f"Pose2Sim data not found at {P2S}")
def test_footage_above_track_fps_is_tracked_every_nth_frame_and_reported_whole(tmp_path):
    """observations.track_fps=30 on 60 fps footage: every input frame is in the result, the tracked ones (0, 2, 4)
    fit their own 2D, metrics.json says every 2nd frame was tracked; at 60 (the input's rate) every frame is."""
    base = ["run", VIDEO_YAML, f"observations.file={P2S / 'balancing' / 'pose' / 'cam01_json'}", "camera.name=cam01"]
    base += [f"camera.file={P2S / 'Calib_qualisys.toml'}", "subject.height_m=1.72", "observations.fps=60"]
    base += ["data.stop=6", "kjs.modes=2", "kjs.samples=32", "progress=false"]
    for track_fps, every in ((30, 2), (60, 1)):
        out = tmp_path / f"run{track_fps}"
        assert main([*base, f"observations.track_fps={track_fps}", f"out_dir={out}"]) == 0
        assert json.loads((out / "metrics.json").read_text())["footage"]["tracked_every"] == every
        with np.load(out / "result.npz") as r:
            assert r["q"].shape[0] == 6 and r["hypotheses"].shape[0] == 6 and np.isfinite(r["keypoints"]).all()
            err = np.linalg.norm(r["keypoints_reprojected"] - r["keypoints_observed"], axis=-1)
            seen = r["confidence"] > 0
            assert np.median(err[::2][seen[::2]]) < 25.0  # px: the tracked frames fit their 2D


@pytest.mark.skipif(not P2S.is_dir(), reason=f"Pose2Sim data not found at {P2S}")
def test_two_people_trial_fits_the_person_chosen(tmp_path):
    """End to end on real OpenPose of the two-people trial (three people tracked, 2-4 detections a frame): by
    default the largest, most present person, who enters at frame 2 (frames 0 and 1 reported without the person, in
    metrics.json and frame by frame in the rerun log); by a point in the first frame, the person at the image's left
    edge. The 2D fitted is the chosen person's: the estimate reprojects within a few tens of pixels of that person's
    detections, as read from the raw files here, and over 100 px from everyone else's (the nearest other person stands
    130-200 px away in these frames)."""
    src = P2S / "two_people" / "pose" / "cam01_json"
    argv = ["run", VIDEO_YAML, f"observations.file={src}", f"camera.file={P2S / 'Calib_qualisys.toml'}"]
    argv += ["camera.name=cam01", "subject.height_m=1.72", "observations.fps=60", "data.stop=6", "progress=false"]

    def detections(frame: int) -> list[np.ndarray]:  # each person's (25, 3) x, y, score in the raw OpenPose file
        people = json.loads((src / f"cam01.{frame:04d}.json").read_text())["people"]
        return [np.asarray(p["pose_keypoints_2d"], dtype=float).reshape(-1, 3) for p in people]

    def fitted(out: Path) -> tuple[dict, np.ndarray]:
        """-> metrics.json, and per frame the median distance (px) from the reprojected keypoints to each person
        detected in the raw file (NaN for a frame without the chosen person), nearest first: (T, people)."""
        metrics = json.loads((out / "metrics.json").read_text())
        with np.load(out / "result.npz") as r:
            assert [str(n) for n in r["keypoint_names"]] == list(get_keypoint_set("BODY_25B").names)  # file order
            frames, reproj, observed, conf = (
                r["frames"],
                r["keypoints_reprojected"],
                r["keypoints_observed"],
                r["confidence"],
            )
        rows = []
        for t, frame in enumerate(frames):
            people = [k for k in detections(int(frame)) if (k[:, 2] > 0.3).sum() >= 6]
            dist = [float(np.median(np.linalg.norm(reproj[t] - k[:, :2], axis=-1)[k[:, 2] > 0.3])) for k in people]
            seen = conf[t] > 0
            if not seen.any():
                rows.append([np.nan] * 4)
                continue
            nearest = people[int(np.argmin(dist))]  # the observations are its detections (undistorted: a few px)
            assert np.median(np.linalg.norm(observed[t, seen] - nearest[seen, :2], axis=-1)) < 5.0
            rows.append(sorted(dist) + [np.nan] * (4 - len(dist)))
        return metrics, np.asarray(rows)

    default = tmp_path / "default"
    assert main([*argv, f"out_dir={default}"]) == 0
    metrics, dist = fitted(default)
    assert metrics["footage"]["tracks"] == 3 and metrics["footage"]["frames_without_person"] == [0, 1]
    assert np.isnan(dist[:2]).all() and (dist[2:, 0] < 40).all() and (dist[2:, 1] > 100).all(), dist
    assert logged_metrics(default / "run.rrd")["person_missing"] == {0: 1.0, 1: 1.0, 2: 0.0, 3: 0.0, 4: 0.0, 5: 0.0}

    by_point = tmp_path / "by_point"
    assert main([*argv, "observations.person=[60, 700]", f"out_dir={by_point}"]) == 0  # a pixel of frame 0
    other, dist = fitted(by_point)
    assert other["footage"]["person_track"] != metrics["footage"]["person_track"]
    assert other["footage"]["frames_without_person"] == []
    assert (dist[:, 0] < 40).all() and (dist[:, 1] > 100).all(), dist


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


def test_floor_depth_factor_moves_the_standing_feet_onto_the_floor():
    """A body standing on a known floor, seen by a camera that looks down at it, estimated 10% nearer along every
    camera ray (what a template too short in the limbs does): the standing feet's rays meet the floor 1.1 times as
    far, and the lengths measured at the depths times that factor are the true ones; without a floor there is none."""
    import dataclasses

    from ptrack.body.keypoint_sets import COCO_17
    from ptrack.body.keypoints import landmark_keypoints
    from ptrack.body.subject import floor_points, landmark_joints
    from ptrack.estimators.lengths import floor_depth_factor, segment_lengths_from_2d
    from ptrack.observe.camera import look_at
    from ptrack.observe.observations import Observations
    from ptrack.problem import Estimate, Floor, Problem

    sk = add_landmark_joints(scale_to_height(Skeleton.from_asf(data_file("10.asf")), 1.7), 1.7)
    joints = [str(j) for j in landmark_joints(sk, COCO_17.landmarks)]
    kps = landmark_keypoints(sk, COCO_17.names, COCO_17.landmarks, joints)
    T = 12
    q = torch.zeros(T, sk.num_dofs, dtype=torch.float64)
    q[:, sk.dof_names.index("root.ry")] = torch.linspace(-0.3, 0.3, T)
    X = sk.forward_kinematics(q)
    feet, clearance = floor_points(sk, 1.7)
    floor = Floor(float(X[:, list(feet), 1].amin()) - clearance, feet, clearance)
    cam = look_at([0.0, 0.0, 0.0], 4.0, 20.0, 15.0, 1000.0, 1280, 720)
    px = cam.project(X[:, kps.index()]).pixels
    obs = Observations(px, torch.ones(T, 17, dtype=torch.float64), torch.arange(T) / 30.0, cam, COCO_17.names)
    problem = Problem(skeleton=sk, keypoints=kps, observations=obs, floor=floor)
    near = cam.center + (X - cam.center) / 1.1  # every point 10% nearer the camera along its ray: the same 2D
    est = Estimate(q=q, joints=near, cost=torch.zeros(T), terms={})
    factor = floor_depth_factor(problem, est)
    assert factor == pytest.approx(1.1, rel=1e-6)
    segments = {n: (a, b) for n, (a, b, _) in SEGMENTS.items() if n in ("thigh", "shank", "trunk")}
    truth = segment_lengths_from_2d(
        problem, Estimate(q=q, joints=X, cost=torch.zeros(T), terms={}), COCO_17.landmarks, segments
    )
    short = segment_lengths_from_2d(problem, est, COCO_17.landmarks, segments)
    fixed = segment_lengths_from_2d(problem, est, COCO_17.landmarks, segments, scale=factor)
    for name in segments:
        assert short[name][0] == pytest.approx(truth[name][0] / 1.1, rel=1e-6), name
        assert fixed[name][0] == pytest.approx(truth[name][0], rel=1e-6), name
    assert floor_depth_factor(dataclasses.replace(problem, floor=None), est) is None


def test_rescale_segments_sets_the_targets_and_moves_the_landmark_joints():
    sk = add_landmark_joints(scale_to_height(Skeleton.from_asf(data_file("10.asf")), 1.7), 1.7)
    new = rescale_segments(sk, 1.7, {"shank": 0.5, "forearm": 0.2})
    got = segment_lengths(new)
    assert got["shank"] == pytest.approx(0.5, rel=1e-6) and got["forearm"] == pytest.approx(0.2, rel=1e-6)
    assert got["thigh"] == pytest.approx(SEGMENTS["thigh"][2] * 1.7, rel=1e-6)
    heel = sk.joint_index("lm_l_heel")
    foot = [sk.joint_index(b) for b in ("lfoot", "rfoot")]
    assert new.lengths[heel] / sk.lengths[heel] == pytest.approx(np.mean(new.lengths[foot] / sk.lengths[foot]))


def test_segment_length_spread_is_the_spread_over_other_frames_and_noise():
    """The bootstrap's std of each measured length on a body turning in front of the camera, with 8 px of 2D noise:
    the order of the std over independent re-filmings of the same motion (other noise) for a segment that stays in
    the image plane (thigh, trunk), larger for the upper arm whose measurement depends on which frames are drawn
    (it turns out of the image plane); seeded, so the same twice."""
    from ptrack.body.keypoint_sets import COCO_17
    from ptrack.body.keypoints import landmark_keypoints
    from ptrack.body.subject import landmark_joints
    from ptrack.estimators.lengths import segment_length_spread, segment_lengths_from_2d
    from ptrack.observe.camera import look_at
    from ptrack.observe.observations import Observations
    from ptrack.problem import Estimate, Problem

    sk = add_landmark_joints(scale_to_height(Skeleton.from_asf(data_file("10.asf")), 1.7), 1.7)
    kps = landmark_keypoints(
        sk, COCO_17.names, COCO_17.landmarks, [str(j) for j in landmark_joints(sk, COCO_17.landmarks)]
    )
    T = 60  # 2 s at 30 fps: four 0.5 s blocks
    q = torch.zeros(T, sk.num_dofs, dtype=torch.float64)
    q[:, sk.dof_names.index("root.ry")] = torch.linspace(-torch.pi / 2, torch.pi / 2, T)
    X = sk.forward_kinematics(q)
    cam = look_at([0.0, 0.0, 0.0], 4.0, 0.0, 0.0, 1000.0, 1280, 720)
    px = cam.project(X[:, kps.index()]).pixels
    est = Estimate(q=q, joints=X, cost=torch.zeros(T), terms={})
    segments = {n: (a, b) for n, (a, b, _) in SEGMENTS.items() if n in ("thigh", "trunk", "upper_arm")}

    def filmed(seed: int) -> Problem:
        noise = 8.0 * torch.randn(px.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
        obs = Observations(
            px + noise, torch.ones(T, 17, dtype=torch.float64), torch.arange(T) / 30.0, cam, COCO_17.names
        )
        return Problem(skeleton=sk, keypoints=kps, observations=obs)

    refilmed = [segment_lengths_from_2d(filmed(s), est, COCO_17.landmarks, segments) for s in range(100, 200)]
    across = {n: float(np.std([r[n][0] for r in refilmed], ddof=1)) for n in segments}  # 6-9 mm
    spreads = [segment_length_spread(filmed(seed), est, COCO_17.landmarks, segments) for seed in range(3)]
    for seed, spread in enumerate(spreads):
        for n in ("thigh", "trunk"):  # ratios 0.5-1.4 over seeds 0-5
            assert across[n] / 3 < spread[n] < 3 * across[n], (seed, n, spread, across)
        assert spread["upper_arm"] > 2 * across["upper_arm"], (seed, spread, across)  # ratios 3.0-4.1
    assert segment_length_spread(filmed(0), est, COCO_17.landmarks, segments) == spreads[0]


@pytest.mark.skipif(not P2S.is_dir(), reason=f"Pose2Sim data not found at {P2S}")
def test_detector_check_finds_mirrored_frames(tmp_path):
    """scripts/detector_check.py on the first 12 frames of the Pose2Sim trial's cam01 OpenPose files: none mirrored
    as shipped; with every left/right label exchanged in frames 4-6 (every person's), exactly those; the detections
    lie within tens of pixels of the triangulation reprojected."""
    import detector_check

    files = sorted((P2S / "balancing" / "pose" / "cam01_json").glob("*.json"))[:12]
    mirror = get_keypoint_set("BODY_25B").mirror_index()
    for name, exchanged in (("shipped", ()), ("mirrored", (4, 5, 6))):
        folder = tmp_path / name
        folder.mkdir()
        for t, f in enumerate(files):
            doc = json.loads(f.read_text())
            if t in exchanged:
                for person in doc["people"]:
                    kp = np.asarray(person["pose_keypoints_2d"]).reshape(-1, 3)
                    person["pose_keypoints_2d"] = kp[mirror].ravel().tolist()
            (folder / f.name).write_text(json.dumps(doc))
        c = detector_check.compare(folder, "cam01")
        assert c["frames"].tolist() == list(range(12))
        assert c["frames"][c["mirrored"]].tolist() == list(exchanged)
        err = c["error"][np.setdiff1d(np.arange(12), exchanged)]
        assert 2.0 < np.nanmedian(err) < 30.0  # one camera's OpenPose against four cameras' triangulation
        for pair, flags in c["pairs"].items():  # each pair alone reads exchanged in the mirrored frames too
            assert flags.tolist() == [t in exchanged for t in range(12)], pair


@pytest.mark.skipif(not P2S.is_dir(), reason=f"Pose2Sim data not found at {P2S}")
def test_footage_floor_fit_keeps_a_consistent_body_and_follows_the_detector():
    """scripts/footage_floor.py on cam01's first 30 frames: the nearest rigid body to the reference has constant
    lengths; seen through its own exact 2D it is a minimum of the fit (it stays within a millimetre); seen through
    OpenPose's 2D the fit leaves it by tens of millimetres (the floor docs/results.md reports)."""
    import footage_floor as ff

    uv, conf, P, frames = ff.camera_inputs("cam01", None)
    uv, conf, frames = uv[:30], conf[:30], frames[:30]
    ref = ff.reference(frames)
    rigid = ff.fit(ref, uv, conf, P, None, 0.0)
    spread = ff.lengths(torch.as_tensor(rigid)).std(0)
    assert float(spread.max()) < 0.002  # metres: rigid within the length term's 1 cm scale
    assert float(ff.lengths(torch.as_tensor(ref)).std(0).max()) > 0.01  # the triangulation's bones are not rigid
    h = np.concatenate([rigid, np.ones_like(rigid[..., :1])], -1) @ P.T
    exact = h[..., :2] / h[..., 2:]
    same = ff.fit(rigid, exact, np.ones_like(conf), P, 8.0, 0.0)
    assert np.abs(same - rigid).max() < 1e-3
    moved = ff.fit(rigid, uv, conf, P, 8.0, 1.0)
    pa = float(pa_mpjpe(torch.as_tensor(moved), torch.as_tensor(rigid)).mean())
    assert 10.0 < pa < 250.0  # mm: the one camera's 2D disagrees with the four cameras' triangulation


@pytest.mark.skipif(not P2S.is_dir(), reason=f"Pose2Sim data not found at {P2S}")
def test_eval_opensim_ik_floor_trc_replaces_only_the_body_markers(tmp_path):
    """scripts/eval_opensim_ik.py --floor's TRC (the nearest rigid body): the triangulated file with its 12 body
    markers moved by centimetres (the triangulation's bones vary by 3-10%), every other marker and the header kept."""
    import eval_opensim_ik
    import footage_floor
    from eval_footage import read_trc

    eval_opensim_ik.floor_trc(tmp_path / "floor.trc", "cam01", with_2d=False)
    names, moved = read_trc(tmp_path / "floor.trc")
    names_ref, ref = read_trc(P2S / "balancing" / "triangulated.trc")
    assert names == names_ref and moved.shape == ref.shape
    body = [names.index(n) for n in footage_floor.BODY12]
    rest = np.setdiff1d(np.arange(len(names)), body)
    assert np.abs(moved[:, rest] - ref[:, rest]).max() < 1e-5
    shift = np.linalg.norm(moved[:, body] - ref[:, body], axis=-1)
    assert 0.001 < shift.mean() < 0.05
    text, text_ref = (
        p.read_text().splitlines() for p in (tmp_path / "floor.trc", P2S / "balancing" / "triangulated.trc")
    )
    assert text[:5] == text_ref[:5]


@pytest.mark.skipif(not P2S.is_dir(), reason=f"Pose2Sim data not found at {P2S}")
def test_footage_floor_model_fits_the_reference_and_the_2d_moves_it():
    """scripts/footage_floor.py's `model_floor` on cam02's first 15 frames: ptrack's skeleton with the reference's
    segment lengths comes within a few centimetres of the triangulation in 3D, and polishing on the one camera's 2D
    moves it away (the floor docs/results.md reports)."""
    import footage_floor as ff

    ref, fitted, polished = ff.model_floor("cam02", None, ("data.stop=15",))
    assert ref.shape == fitted.shape == polished.shape == (15, 12, 3)
    pa_fit = float(pa_mpjpe(torch.as_tensor(fitted), torch.as_tensor(ref)).mean())
    pa_polished = float(pa_mpjpe(torch.as_tensor(polished), torch.as_tensor(ref)).mean())
    assert pa_fit < 30.0  # mm: the model can stand where the reference stands
    assert pa_fit + 10.0 < pa_polished < 250.0


def test_every_format_finds_its_hips_and_wrists_by_landmark():
    """A detector's keypoint set names its points its own way (BODY_25B "LHip", COCO-17 "left_hip"); the estimators find
    them by landmark (`KeypointSet.find`): the kjs tracker's lead-pass check the hips (`lattice._hips`; before,
    it looked for the name "l_hip" and found none on any detector's file), pca the wrists."""
    from types import SimpleNamespace

    from ptrack.body.keypoint_sets import KEYPOINT_SETS
    from ptrack.body.keypoints import landmark_keypoints
    from ptrack.body.subject import landmark_joints
    from ptrack.estimators.kjs.lattice import _hips

    sk = add_landmark_joints(scale_to_height(Skeleton.from_asf(data_file("10.asf")), 1.7), 1.7)
    for name, ks in KEYPOINT_SETS.items():
        joints = landmark_joints(sk, ks.landmarks)
        placed = [k for k, j in enumerate(joints) if j is not None]  # as `prepare_footage` places them
        names, landmarks = tuple(ks.names[k] for k in placed), tuple(ks.landmarks[k] for k in placed)
        kps = landmark_keypoints(sk, names, landmarks, [str(joints[k]) for k in placed])
        for landmark in ("l_hip", "r_hip", "l_wrist", "r_wrist"):
            k = kps.find(landmark)
            assert k is not None and ks.landmarks[placed[k]] == landmark, (name, landmark)
            assert kps.names[k] == ks.names[placed[k]] != landmark, (name, landmark)  # the format's own name
        assert kps.find("l_hip") != kps.find("r_hip") and kps.find("nowhere") is None
        setup = SimpleNamespace(problem=SimpleNamespace(keypoints=kps))  # what `_hips` reads of a kjs Setup
        assert _hips(setup) == (kps.joints[kps.find("l_hip")], kps.joints[kps.find("r_hip")]), name


def test_the_path_keeps_one_set_of_root_angles_through_the_low_pass():
    """Every root orientation has two sets of angles (`Skeleton.root_twin`: the same joints). A path through modes
    of two tree starts can change sets between frames where the body hardly moves; `continuous_root` puts every
    frame in the set nearest the frame before's, and the low-pass (`lowpass_trajectory`) then follows the motion.
    Filtering the angles across the change instead turned the body over (the trial's cam02, seed 1)."""
    from ptrack.pipeline.run import continuous_root, lowpass_trajectory
    from ptrack.problem import Estimate

    sk = Skeleton.from_asf(data_file("10.asf"))
    assert sk.root_twin_dofs() is not None
    T = 60
    gen = torch.Generator().manual_seed(0)
    t = torch.linspace(0, 1, T, dtype=torch.float64)[:, None]
    q = 0.1 * torch.randn(1, sk.num_dofs, generator=gen, dtype=torch.float64) + 0.4 * torch.sin(2 * math.pi * t)
    q[:, [sk.dof_names.index(n) for n in ("root.tx", "root.ty", "root.tz")]] = 0.0
    joints = sk.forward_kinematics(q)
    twin = sk.root_twin(q)
    torch.testing.assert_close(sk.forward_kinematics(twin), joints)  # the same body
    assert (twin - q).abs().max() > 3.0  # other angles
    mixed = torch.where((torch.arange(T) % 3 == 1)[:, None], twin, q)  # every third frame in the other set
    fixed = continuous_root(sk, mixed)
    turns = torch.remainder(fixed - q + math.pi, 2 * math.pi) - math.pi  # back in frame 0's set (up to whole turns)
    torch.testing.assert_close(turns, torch.zeros_like(q), atol=1e-9, rtol=0)
    torch.testing.assert_close(continuous_root(sk, q), q)
    est = Estimate(q=mixed, joints=joints, cost=torch.zeros(T), terms={})
    smooth = lowpass_trajectory(sk, est._replace(q=q), 60.0, 6.0).joints  # the path that never changed sets
    good = lowpass_trajectory(sk, est._replace(q=fixed), 60.0, 6.0).joints
    torch.testing.assert_close(good, smooth, atol=1e-9, rtol=0)
    bad = lowpass_trajectory(sk, est, 60.0, 6.0).joints  # across the changes of set: the body turned
    assert float((bad - smooth).norm(dim=-1).mean()) > 0.2  # metres
