"""`ptrack export --format bvh|json|csv` (ptrack/io/export.py, ptrack/io/json_csv.py): the BVH read back by an
independent library (bvhio) at every frame, in each rest pose and name map, at the exact frame time; the JSON
validated against its shipped schema; the CSV read by pandas into the documented columns; the one-line errors."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from bvh_text import assert_bvh_close
from cli_errors import fail

from ptrack.cli import main
from ptrack.io.export import MIXAMO, export_bvh
from ptrack.io.exporters import ExportOptions, export_run
from ptrack.io.json_csv import ANGLE_COLUMNS, JOINT_COLUMNS, SCHEMA_FILE, load_schema
from ptrack.io.run_folder import load_run

REPO = Path(__file__).resolve().parents[1]
P2S = REPO.parent / "shared" / "data" / "pose2sim"
pytestmark = pytest.mark.filterwarnings("ignore:Importing PyGLM:PendingDeprecationWarning")  # bvhio's own import
FAST_KJS = ["kjs.modes=3", "kjs.samples=32", "progress=false"]


def _run(out: Path, argv: list[str]) -> Path:
    assert main(["run", *argv, f"out_dir={out}"]) == 0
    return out


@pytest.fixture(scope="module")
def kjs_run(tmp_path_factory) -> Path:
    """The bundled soccer kick, 10 frames at 30 fps, method kjs (hypotheses and weights)."""
    return _run(tmp_path_factory.mktemp("kjs") / "run", [str(REPO / "configs/kjs.yaml"), "data.stop=40", *FAST_KJS])


@pytest.fixture(scope="module")
def batch_run(tmp_path_factory) -> Path:
    """The same 10 frames, method batch (per-joint uncertainty)."""
    return _run(
        tmp_path_factory.mktemp("batch") / "run", [str(REPO / "configs/batch.yaml"), "data.stop=40", "progress=false"]
    )


@pytest.fixture(scope="module")
def footage_run(tmp_path_factory) -> Path:
    """Pose2Sim's real OpenPose keypoints of cam01 at 60 fps with its calibration (floor known), 8 frames."""
    if not P2S.is_dir():
        pytest.skip(f"Pose2Sim data not found at {P2S}")
    argv = [str(REPO / "configs/video.yaml"), f"observations.file={P2S / 'balancing/pose/cam01_json'}"]
    argv += [f"camera.file={P2S / 'Calib_qualisys.toml'}", "camera.name=cam01", "subject.height_m=1.72"]
    argv += ["observations.fps=60", "data.stop=8", "subject.lengths=template", *FAST_KJS]
    return _run(tmp_path_factory.mktemp("footage") / "run", argv)


# ------------------------------------------------------------------ BVH


def bvhio_points(path: Path) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], float]:
    """bvhio's reading of a BVH: each joint's world position (T, 3) by name (its hierarchy), each chain end's
    End Site position (T, 3) by its joint's name (its parsed channels composed along the chain), frame time."""
    import bvhio
    from pyglm import glm

    bvh = bvhio.readAsBvh(str(path))
    root = bvhio.readAsHierarchy(str(path))
    frames = bvh.FrameCount
    joints: dict[str, np.ndarray] = {j.Name: np.zeros((frames, 3)) for j, _, _ in root.layout()}
    for f in range(frames):
        root.loadPose(f)
        for j, _, _ in root.layout():
            joints[j.Name][f] = np.asarray(j.PositionWorld)
    ends: dict[str, np.ndarray] = {}

    def walk(j, f: int, p, w) -> None:
        key = j.Keyframes[f]
        rot = glm.mat3_cast(key.Rotation)
        p, w = (glm.vec3(key.Position), rot) if p is None else (p + w * j.Offset, w * rot)
        if not j.Children:
            ends.setdefault(j.Name, np.zeros((frames, 3)))[f] = np.asarray(p + w * j.EndSite)
        for c in j.Children:
            walk(c, f, p, w)

    for f in range(frames):
        walk(bvh.Root, f, None, None)
    return joints, ends, float(bvh.FrameTime)


def _expected(run, name_of: dict[str, str]) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """Where each BVH joint and End Site should be, from result.npz alone: BVH joint i sits at its bone's start,
    ptrack's joints[parents[i]] (the root at joints[0]); bone i's end, joints[i], is an End Site where i has no
    children. The floor (when known) moved to Y = 0."""
    joints = run.joints.copy()
    joints[..., 1] -= run.floor_m or 0.0
    parents = run.parents
    has_child = set(int(p) for p in parents if p >= 0)
    at = {name_of.get(n, n): joints[:, max(int(parents[i]), 0)] for i, n in enumerate(run.joint_names)}
    ends = {name_of.get(n, n): joints[:, i] for i, n in enumerate(run.joint_names) if i not in has_child}
    return at, ends


@pytest.mark.parametrize(("rest", "names"), [(None, None), ("tpose", None), (None, "mixamo"), ("tpose", "mixamo")])
@pytest.mark.parametrize("which", ["kjs_run", "footage_run"])
def test_bvh_read_back_by_bvhio_within_1mm(request, tmp_path, which, rest, names):
    run = load_run(request.getfixturevalue(which))
    (path,) = export_run(run.path, "bvh", tmp_path / "m.bvh", ExportOptions(rest=rest, names=names))
    got, got_ends, frame_time = bvhio_points(path)
    want, want_ends = _expected(run, MIXAMO if names else {})
    assert sorted(got) == sorted(want) and sorted(got_ends) == sorted(want_ends)
    err = max(np.abs(got[n] - want[n]).max() for n in want)
    err_end = max(np.abs(got_ends[n] - want_ends[n]).max() for n in want_ends)
    assert err < 1e-3 and err_end < 1e-3, (err, err_end)
    assert frame_time == pytest.approx(1.0 / run.fps, abs=1e-10)


def test_bvh_frame_time_is_exact_in_the_run_and_the_export(kjs_run, tmp_path):
    """A 30 fps run writes 0.0333333333 (10 decimals of the exact rate), not float32's 0.03333330."""
    assert "\nFrame Time: 0.0333333333\n" in (kjs_run / "result.bvh").read_text()
    (path,) = export_run(kjs_run, "bvh", tmp_path)
    assert "\nFrame Time: 0.0333333333\n" in path.read_text()


def test_footage_bvh_frame_time_and_the_run_bvh_equal_the_export(footage_run, tmp_path):
    (path,) = export_run(footage_run, "bvh", tmp_path)
    assert "\nFrame Time: 0.0166666667\n" in path.read_text()
    # the run's own BVH is the default export (its model from memory, the export's from skeleton.urdf: to rounding)
    assert_bvh_close(path.read_text(), (footage_run / "result.bvh").read_text(), atol=1e-5)


def _rest_points(path: Path) -> dict[str, np.ndarray]:
    """Each BVH joint's position (3,) in the rest pose (every channel zero: the offsets summed), by bvhio's parse."""
    import bvhio

    out: dict[str, np.ndarray] = {}

    def walk(j, p: np.ndarray) -> None:
        p = p + np.asarray(j.Offset)
        out[j.Name] = p
        if not j.Children:
            out[j.Name + "/end"] = p + np.asarray(j.EndSite)
        for c in j.Children:
            walk(c, p)

    walk(bvhio.readAsBvh(str(path)).Root, np.zeros(3))
    return out


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


@pytest.mark.parametrize("which", ["kjs_run", "footage_run"])
def test_tpose_rest_is_a_tpose_facing_z(request, tmp_path, which):
    """--rest tpose: the offsets put arms out along +-X (left +X), thighs and shins straight down, the spine and
    neck up and the feet forward (+Z): Y up, facing +Z. The skeleton's own rest (CMU's) has its legs apart."""
    folder = request.getfixturevalue(which)
    (t_path,) = export_run(folder, "bvh", tmp_path / "t.bvh", ExportOptions(rest="tpose"))
    (a_path,) = export_run(folder, "bvh", tmp_path / "a.bvh", ExportOptions(rest="asf"))
    for path, tpose in ((t_path, True), (a_path, False)):
        p = _rest_points(path)
        legs = [("lfemur", "ltibia"), ("ltibia", "lfoot"), ("rfemur", "rtibia"), ("rtibia", "rfoot")]
        down = [_unit(p[b] - p[a]) @ [0, -1, 0] for a, b in legs]
        if not tpose:
            assert min(down) < 0.99  # CMU's rest: legs 20 degrees apart
            continue
        np.testing.assert_allclose(down, 1.0, atol=1e-9)
        for side, sign in (("l", 1.0), ("r", -1.0)):
            for a, b in ((f"{side}clavicle", f"{side}humerus"), (f"{side}humerus", f"{side}radius")):
                np.testing.assert_allclose(_unit(p[b] - p[a]), [sign, 0, 0], atol=1e-9)
            assert _unit(p[f"{side}toes"] - p[f"{side}foot"])[2] > 0.9  # the foot points forward
        for a, b in (("lowerback", "upperback"), ("upperback", "thorax"), ("lowerneck", "upperneck")):
            np.testing.assert_allclose(_unit(p[b] - p[a]), [0, 1, 0], atol=1e-9)


def test_mixamo_names(footage_run, tmp_path):
    """--names mixamo renames the joints with a Mixamo counterpart; the others (hip joints, landmarks) keep theirs."""
    (path,) = export_run(footage_run, "bvh", tmp_path, ExportOptions(names="mixamo"))
    text = path.read_text()
    assert text.startswith("HIERARCHY\nROOT mixamorig:Hips\n")
    for name in ("mixamorig:LeftUpLeg", "mixamorig:RightForeArm", "mixamorig:Spine2", "mixamorig:Head"):
        assert f"JOINT {name}\n" in text
    for name in ("lhipjoint", "upperneck", "lm_nose", "lm_r_heel"):
        assert f"JOINT {name}\n" in text
    assert "JOINT lfemur" not in text


def test_bvh_floor_moved_to_zero(kjs_run, tmp_path):
    """A known floor (footage with a calibrated up axis) is at Y = 0 in the BVH: every point moves down by it."""
    run = load_run(kjs_run)
    assert run.floor_m is None  # CMU: the mocap floor is Y = 0 already, nothing moves
    raised = dataclasses.replace(run, metrics={**run.metrics, "footage": {"floor_m": 0.25}})
    (path,) = export_bvh(raised, tmp_path, ExportOptions())
    got, _, _ = bvhio_points(path)
    np.testing.assert_allclose(got["root"], run.joints[:, 0] - [0, 0.25, 0], atol=1e-6)


# ------------------------------------------------------------------ JSON and CSV


@pytest.mark.parametrize("which", ["kjs_run", "batch_run", "footage_run"])
def test_json_valid_against_its_schema_and_equal_to_the_run(request, tmp_path, which):
    import jsonschema

    run = load_run(request.getfixturevalue(which))
    (path,) = export_run(run.path, "json", tmp_path)
    doc = json.loads(path.read_text())
    schema = load_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    jsonschema.validate(doc, schema, cls=jsonschema.Draft202012Validator)
    assert SCHEMA_FILE.parent.name == "data" and SCHEMA_FILE.parent.parent.name == "ptrack"  # shipped as package data
    a = run.arrays
    assert doc["fps"] == run.fps and doc["num_frames"] == run.num_frames
    assert doc["skeleton"]["joint_names"] == run.joint_names and doc["skeleton"]["parents"] == run.parents.tolist()
    np.testing.assert_allclose(np.asarray(doc["joints"]), run.joints, rtol=0, atol=5.1e-7)
    np.testing.assert_allclose(np.asarray(doc["q"]), a["q"], rtol=0, atol=5.1e-7)
    units = doc["skeleton"]["dof_units"]
    assert units[:3] == ["m"] * 3 and set(units[3:]) == {"rad"}
    np.testing.assert_allclose(np.asarray(doc["camera"]["K"]), a["camera_K"], atol=1e-4)
    if which == "kjs_run":
        np.testing.assert_allclose(np.asarray(doc["hypotheses"]["weights"]).sum(-1), 1.0, atol=1e-5)
        np.testing.assert_allclose(np.asarray(doc["hypotheses"]["joints"]), a["hypotheses"], atol=5.1e-7)
        assert doc["joint_std"] is None and doc["camera"]["focal_source"] == "config"
    if which == "batch_run":
        np.testing.assert_allclose(np.asarray(doc["joint_std"]), a["joint_std"], atol=5.1e-7)
        assert doc["hypotheses"] is None
    if which == "footage_run":
        assert doc["camera"]["focal_source"] == "calibration_file" and doc["floor_m"] == run.floor_m
        np.testing.assert_allclose(np.asarray(doc["keypoints_3d"]), run.keypoints_model, atol=5.1e-7)
    # the schema is strict: a missing field or a wrong type is refused
    for broken in ({k: v for k, v in doc.items() if k != "fps"}, {**doc, "fps": "30"}):
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate(broken, schema, cls=jsonschema.Draft202012Validator)


@pytest.mark.parametrize("which", ["kjs_run", "batch_run"])
def test_csv_loads_with_pandas_into_the_documented_columns(request, tmp_path, which):
    import pandas as pd

    run = load_run(request.getfixturevalue(which))
    paths = export_run(run.path, "csv", tmp_path)
    assert [p.name for p in paths] == ["joints.csv", "angles.csv"]
    joints = pd.read_csv(tmp_path / "joints.csv")
    angles = pd.read_csv(tmp_path / "angles.csv")
    assert tuple(joints.columns) == JOINT_COLUMNS and tuple(angles.columns) == ANGLE_COLUMNS
    t, j, d = run.num_frames, len(run.joint_names), run.arrays["q"].shape[1]
    assert len(joints) == t * j and len(angles) == t * d
    xyz = joints[["x_m", "y_m", "z_m"]].to_numpy().reshape(t, j, 3)
    np.testing.assert_allclose(xyz, run.joints, rtol=0, atol=5.1e-7)
    assert (
        joints["joint"].tolist()[:j] == run.joint_names
        and (joints["frame"].to_numpy()[::j] == run.arrays["frames"]).all()
    )
    np.testing.assert_allclose(joints["time_s"].to_numpy()[::j], run.arrays["times"], atol=5.1e-7)
    if "joint_std" in run.arrays:
        np.testing.assert_allclose(joints["std_m"].to_numpy().reshape(t, j), run.arrays["joint_std"], atol=5.1e-7)
    else:
        assert joints["std_m"].isna().all()
    q = angles["value"].to_numpy().reshape(t, d)
    np.testing.assert_allclose(q, run.arrays["q"], rtol=0, atol=5.1e-7)
    assert angles["dof"].tolist()[:d] == [str(n) for n in run.arrays["dof_names"]]
    assert set(angles["unit"]) == {"m", "rad"}


# ------------------------------------------------------------------ bad input


@pytest.mark.parametrize(
    ("fmt", "options", "fragments"),
    [
        ("bvh", ["--names", "unity"], ("unknown BVH name map 'unity'", "mixamo")),
        ("bvh", ["--up", "z"], ("bvh", "Y up")),
        ("bvh", ["--points", "joints"], ("--points", "bvh")),
        ("json", ["--rest", "tpose"], ("--rest", "json")),
        ("json", ["--names", "mixamo"], ("--names", "json")),
        ("csv", ["--up", "z"], ("csv", "Y up")),
    ],
)
def test_options_a_format_cannot_honour(capsys, kjs_run, tmp_path, fmt, options, fragments):
    out = tmp_path / "export"
    fail(capsys, out, ["export", str(kjs_run), "--format", fmt, "--out", str(out), *options], *fragments)
    assert not (kjs_run / "export").exists()


@pytest.mark.parametrize("fmt", ["bvh", "json", "csv"])
def test_unwritable_out_and_a_failing_writer_leave_nothing(capsys, kjs_run, tmp_path, fmt):
    blocker = tmp_path / "file.txt"
    blocker.write_text("a file, not a folder")
    fail(
        capsys,
        tmp_path / "unused",
        ["export", str(kjs_run), "--format", fmt, "--out", str(blocker / "export")],
        str(blocker),
    )
    assert [p.name for p in tmp_path.iterdir()] == ["file.txt"] and blocker.read_text() == "a file, not a folder"
    # a writer failing after it started (the model file gone): nothing in the output folder, not even its temp
    broken = tmp_path / "broken"
    shutil.copytree(kjs_run, broken)
    (broken / "skeleton.urdf").unlink()
    target = tmp_path / "out"
    target.mkdir()
    fail(capsys, target / "x", ["export", str(broken), "--format", fmt, "--out", str(target)], "skeleton.urdf")
    assert list(target.iterdir()) == []
