"""`subject.static`: segment lengths from a static standing trial (`ptrack.pipeline.static`,
`ptrack.estimators.lengths.vertical_segment_lengths`), and its one-line errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from cli_errors import fail

from ptrack.body.keypoint_sets import BODY_25B, COCO_17
from ptrack.body.keypoints import landmark_keypoints
from ptrack.body.skeleton import Skeleton
from ptrack.body.subject import SEGMENTS, add_landmark_joints, landmark_joints, rescale_segments, scale_to_height
from ptrack.cli import main
from ptrack.estimators.lengths import segment_lengths_from_2d, vertical_segment_lengths
from ptrack.observe.camera import look_at
from ptrack.observe.observations import Observations
from ptrack.package_data import data_file
from ptrack.pipeline.static import stature, stature_scale
from ptrack.problem import Estimate, Problem

REPO = Path(__file__).resolve().parents[1]
VIDEO_YAML = str(REPO / "configs" / "video.yaml")
P2S = REPO.parent / "shared" / "data" / "pose2sim"
MEASURED = ("thigh", "shank", "trunk")


def _standing(sk: Skeleton, yaw_deg: float, T: int) -> torch.Tensor:
    """(T, D) the rest pose (legs and trunk vertical) turned by yaw_deg, held still."""
    q = torch.zeros(T, sk.num_dofs, dtype=torch.float64)
    q[:, sk.dof_names.index("root.ry")] = math.radians(yaw_deg)
    return q


def test_vertical_segment_lengths_recover_a_standing_person_under_a_tilted_camera():
    """A standing person whose legs differ from the height's template by 9-12%, turned 20 degrees
    from a camera that looks down on them by 25 degrees; the depths come from a fit with the template's
    lengths (the template's rest pose at the same place). The back-projection into the upright plane facing
    the camera recovers each length within 3% (the thighs of the CMU rest pose lean 20 degrees inwards, a
    little of it towards the camera); the 2D length times depth / f sees them shortened by the camera's tilt
    (cos 25 deg = 0.91)."""
    template = add_landmark_joints(scale_to_height(Skeleton.from_asf(data_file("10.asf")), 1.72), 1.72)
    truth = rescale_segments(template, 1.72, {"thigh": 0.37, "shank": 0.385, "trunk": 0.55})
    joints = landmark_joints(truth, BODY_25B.landmarks)
    placed = [k for k, j in enumerate(joints) if j is not None]
    names = tuple(BODY_25B.names[k] for k in placed)
    landmarks = tuple(BODY_25B.landmarks[k] for k in placed)
    kps = landmark_keypoints(truth, names, landmarks, [str(joints[k]) for k in placed])
    T = 6
    q = _standing(truth, 20.0, T)
    X = truth.forward_kinematics(q)
    cam = look_at(X[0, 0].tolist(), 3.0, 20.0, 25.0, 1400.0, 1088, 1920)
    px = cam.project(X[:, kps.index()]).pixels
    px = px + 0.5 * torch.randn(px.shape, generator=torch.Generator().manual_seed(0), dtype=px.dtype)
    obs = Observations(px, torch.ones(T, len(names), dtype=torch.float64), torch.arange(T) / 60.0, cam, names)
    problem = Problem(skeleton=truth, keypoints=kps, observations=obs)
    fitted = template.forward_kinematics(q)  # the template standing where the person stands
    est = Estimate(q=q, joints=fitted, cost=torch.zeros(T), terms={})
    # the legs: the CMU rest pose's trunk leans back 11 degrees, which a camera in front sees only shortened
    segments = {n: (a, b) for n, (a, b, _) in SEGMENTS.items() if n in ("thigh", "shank")}
    rest = truth.forward_kinematics(torch.zeros(truth.num_dofs, dtype=torch.float64))

    def length(a: str, b: str) -> float:
        ja, jb = (kps.joints[names.index(BODY_25B.names[BODY_25B.landmark_index(m)])] for m in (a, b))
        return float((rest[ja] - rest[jb]).norm())

    def both_sides(a: str, b: str) -> float:  # the CMU template's left and right differ by a few %
        return (length(a, b) + length(*("r_" + m[2:] if m.startswith("l_") else m for m in (a, b)))) / 2

    got = vertical_segment_lengths(problem, est, landmarks, segments)
    plain = segment_lengths_from_2d(problem, est, landmarks, segments, quantile=0.5, min_frames=3)
    for name, (a, b) in segments.items():
        want = both_sides(a, b)
        assert got[name][0] == pytest.approx(want, rel=0.03), name
        assert got[name][2] == 2 * T and 0 <= got[name][1] < 0.02  # the spread: left against right, 0.5 px noise
        assert plain[name][0] < 0.95 * want, name  # foreshortened by the tilt


def test_stature_scale_keeps_the_template_stature():
    """Legs measured 15% shorter than the template's: one common factor brings them (and the trunk) back to
    the template's standing height, keeping their proportions."""
    template = add_landmark_joints(scale_to_height(Skeleton.from_asf(data_file("10.asf")), 1.72), 1.72)
    measured = {"thigh": 0.36, "shank": 0.36, "trunk": 0.5}
    k = stature_scale(template, 1.72, measured)
    scaled = rescale_segments(template, 1.72, {n: k * v for n, v in measured.items()})
    assert 1.05 < k < 1.2
    assert stature(scaled) == pytest.approx(stature(template), abs=1e-3)
    assert stature(rescale_segments(template, 1.72, measured)) < stature(template) - 0.05


def _run(tmp_path: Path, cam: str, static: str | Path, stop: int = 3) -> list[str]:
    return [
        "run",
        VIDEO_YAML,
        f"observations.file={P2S / 'balancing' / 'pose' / f'{cam}_json'}",
        f"camera.file={P2S / 'Calib_qualisys.toml'}",
        f"camera.name={cam}",
        "subject.height_m=1.72",
        "observations.fps=60",
        f"data.stop={stop}",
        f"subject.static={static}",
        f"out_dir={tmp_path / 'run'}",
        "progress=false",
    ]


@pytest.mark.skipif(not P2S.is_dir(), reason=f"Pose2Sim data not found at {P2S}")
def test_static_trial_sets_the_legs_of_the_main_trial(tmp_path):
    """The shipped static trial, cam02, before 3 frames of the balancing trial: the legs and trunk measured on
    it are within 10% of the lengths in the trial's triangulated TRC and nearer them than the template's (whose
    thigh is 15% long), and the model the main trial is fitted with has them."""
    assert main(_run(tmp_path, "cam02", P2S / "static" / "pose" / "cam02_json")) == 0
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    measured = metrics["footage"]["segments_measured"]
    assert set(measured) == set(MEASURED) and all(v["source"] == "static" for v in measured.values())
    bones = metrics["bone_lengths"]  # the lengths the model used, with the static trial's spread
    for name, v in measured.items():
        assert bones[name]["source"] == "static" and bones[name]["length_m"] == pytest.approx(v["length_m"], rel=1e-6)
        assert bones[name]["std_m"] == v["spread_m"] and bones[name]["frames"] == v["samples"]
    assert bones["upper_arm"]["source"] == "template"
    lines = (P2S / "static" / "triangulated.trc").read_text().splitlines()
    names = [n for n in lines[3].split("\t")[2:] if n.strip()]
    trc = np.array([[float(x) for x in r.split("\t")[2 : 2 + 3 * len(names)]] for r in lines[5:] if r.strip()])
    trc = trc.reshape(len(trc), len(names), 3)

    def ref(a: str, b: str) -> float:
        return float(
            np.mean(
                [np.linalg.norm(trc[:, names.index(s + a)] - trc[:, names.index(s + b)], axis=-1).mean() for s in "LR"]
            )
        )

    want = {"thigh": ref("Hip", "Knee"), "shank": ref("Knee", "Ankle"), "trunk": ref("Hip", "Shoulder")}
    for name, v in measured.items():
        assert v["length_m"] == pytest.approx(want[name], rel=0.1), name
        assert abs(v["template_m"] / want[name] - 1) > abs(v["length_m"] / want[name] - 1), name
    with np.load(tmp_path / "run" / "result.npz") as z:
        j, joint_names = z["joints"][0], [str(n) for n in z["joint_names"]]
    knee, ankle = (j[joint_names.index(b)] for b in ("lfemur", "ltibia"))
    assert np.linalg.norm(knee - ankle) == pytest.approx(measured["shank"]["length_m"], rel=0.05)


def _openpose_folder(folder: Path, people: list[np.ndarray], frames: int = 3) -> Path:
    folder.mkdir()
    for n in range(frames):
        entries = [{"person_id": [-1], "pose_keypoints_2d": p.ravel().tolist()} for p in people]
        (folder / f"static.{n:04d}.json").write_text(json.dumps({"people": entries}))
    return folder


@pytest.mark.skipif(not P2S.is_dir(), reason=f"Pose2Sim data not found at {P2S}")
def test_static_trial_errors_are_one_line(tmp_path, capsys):
    from keypoint_fixtures import person

    out = tmp_path / "run"
    fail(capsys, out, _run(tmp_path, "cam01", tmp_path / "nowhere"), "subject.static", "not found", "nowhere")
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / "static.0000.json").write_text('{"people": [')
    fail(capsys, out, _run(tmp_path, "cam01", bad), "subject.static", "malformed JSON")
    empty = _openpose_folder(tmp_path / "empty", [])
    fail(capsys, out, _run(tmp_path, "cam01", empty), "subject.static", "no person")
    coco = _openpose_folder(tmp_path / "coco", [person(COCO_17, 500, 300, 1200)])
    fail(capsys, out, _run(tmp_path, "cam01", coco), "subject.static", "COCO_17", "BODY_25B", "same detector")
    fail(capsys, out, [*_run(tmp_path, "cam01", coco), "subject.lengths=asf"], "subject.static", "subject.lengths")
