"""`ptrack export --format trc|mot|c3d` (ptrack.io.trc, mot, c3d, opensim_ik, markers), read back by the
tools biomechanists use: OpenSim's own readers and inverse kinematics, ezc3d and the `c3d` package.

Two short real runs are made once for the module: a footage run on Pose2Sim's balancing trial (cam01's
OpenPose BODY_25B keypoints, the Qualisys calibration; skipped without ../shared/data/pose2sim) and a
simulated CMU run of the demo clip (every 4th frame: 30 fps). Tests that need a package of the optional
`export` extra skip, saying which, when it is absent.
"""

from __future__ import annotations

import importlib.util
import re
import shlex
import sys
from pathlib import Path

import numpy as np
import pytest
from cli_errors import fail
from keypoint_fixtures import pose2sim

from ptrack.cli import main
from ptrack.io.exporters import ExportOptions, export_run
from ptrack.io.markers import pose2sim_names
from ptrack.io.opensim_ik import import_opensim, inverse_kinematics
from ptrack.io.run_folder import load_run

REPO = Path(__file__).resolve().parents[1]
HAS = {name: importlib.util.find_spec(name) is not None for name in ("opensim", "ezc3d", "c3d")}


def needs(name: str):
    return pytest.mark.skipif(not HAS[name], reason=f"{name} is not installed (pip install 'ptrack[export]')")


@pytest.fixture(scope="module")
def footage_run(tmp_path_factory) -> Path:
    """cam01 of Pose2Sim's balancing trial, frames 0-9, a cheap tracking (the exports are tested, not it)."""
    src = pose2sim("balancing/pose/cam01_json")
    out = tmp_path_factory.mktemp("footage") / "run"
    argv = ["run", str(REPO / "configs" / "video.yaml"), f"observations.file={src}"]
    argv += [f"camera.file={pose2sim('Calib_qualisys.toml')}", "camera.name=cam01", "subject.height_m=1.72"]
    argv += ["observations.fps=60", "data.stop=10", "kjs.modes=2", "kjs.samples=32", "progress=false"]
    assert main([*argv, "subject.lengths=template", f"out_dir={out}"]) == 0
    return out


@pytest.fixture(scope="module")
def cmu_run(tmp_path_factory) -> Path:
    """The demo clip, simulated observations, every 4th of 48 frames (30 fps)."""
    out = tmp_path_factory.mktemp("cmu") / "run"
    argv = ["run", str(REPO / "configs" / "demo.yaml"), "data.stop=48", "data.stride=4", "frame.iterations=15"]
    assert main([*argv, "frame.first_iterations=60", "progress=false", f"out_dir={out}"]) == 0
    return out


def test_pose2sim_names_of_each_keypoint_set():
    """BODY_25B's UpperNeck/HeadTop are Pose2Sim's Neck/Head, COCO-17 gets Pose2Sim's CamelCase, BODY_25's
    MidHip is CHip, HALPE-26 keeps its names, and MediaPipe's foot index is Pose2Sim's BigToe."""
    assert pose2sim_names("BODY_25B", ["UpperNeck", "HeadTop", "LBigToe", "RKnee"]) == [
        "Neck",
        "Head",
        "LBigToe",
        "RKnee",
    ]
    assert pose2sim_names("COCO_17", ["nose", "left_hip", "right_ankle"]) == ["Nose", "LHip", "RAnkle"]
    assert pose2sim_names("BODY_25", ["MidHip", "Neck", "RHeel"]) == ["CHip", "Neck", "RHeel"]
    assert pose2sim_names("HALPE_26", ["Hip", "Neck", "Head", "LSmallToe"]) == ["Hip", "Neck", "Head", "LSmallToe"]
    assert pose2sim_names("MEDIAPIPE_33", ["left_foot_index", "right_heel"]) == ["LBigToe", "RHeel"]


def _model_markers() -> list[str]:
    text = pose2sim("balancing/opensim_model_scaled.osim").read_text()
    return re.findall(r'<Marker name="([^"]+)"', text)


def test_trc_of_footage_keypoints_has_pose2sim_marker_names(footage_run):
    """The TRC of a BODY_25B run names its markers as the shipped scaled model does (every one of the
    model's 21 markers is there), at exactly 60 Hz."""
    (path,) = export_run(footage_run, "trc", footage_run / "x")
    lines = path.read_text().splitlines()
    assert lines[2].split("\t")[:2] == ["60", "60"]
    names = [n for n in lines[3].split("\t")[2:] if n]
    assert set(_model_markers()) <= set(names)
    assert "UpperNeck" not in names and "HeadTop" not in names


@needs("opensim")
@pytest.mark.parametrize("up", ["y", "z"])
def test_trc_read_by_opensim(footage_run, tmp_path, up):
    """OpenSim's TRC reader (TimeSeriesTableVec3 of a .trc path reads it with TRCFileAdapter) gets the rate,
    names, units, times (input frame / fps) and values (1e-5 m) of the run's keypoints, Y up (the model
    frame) or Z up (the calibration's world: result.npz's `keypoints`)."""
    opensim = import_opensim()

    (path,) = export_run(footage_run, "trc", tmp_path / "o.trc", ExportOptions(up=up))
    table = opensim.TimeSeriesTableVec3(str(path))
    run = load_run(footage_run)
    names = pose2sim_names("BODY_25B", run.keypoint_names)
    assert list(table.getColumnLabels()) == names
    assert table.getTableMetaDataAsString("Units") == "m"
    assert float(table.getTableMetaDataAsString("DataRate")) == 60.0
    frames = run.arrays["frames"]
    np.testing.assert_allclose(np.asarray(table.getIndependentColumn()), frames / 60.0, atol=1e-8)
    got = np.array(
        [[[table.getRowAtIndex(t)[k].get(i) for i in range(3)] for k in range(len(names))] for t in range(len(frames))]
    )
    want = run.keypoints_model if up == "y" else run.arrays["keypoints"]  # Pose2Sim's calibration is Z up
    np.testing.assert_allclose(got, want, atol=1e-5)


@needs("opensim")
def test_trc_of_cmu_joints_read_by_opensim(cmu_run, tmp_path):
    """A simulated CMU run exports its skeleton's joints (the default without keypoints) at 30 fps (every
    4th frame of 120), times from its first frame."""
    opensim = import_opensim()

    (path,) = export_run(cmu_run, "trc", tmp_path)
    table = opensim.TimeSeriesTableVec3(str(path))
    run = load_run(cmu_run)
    assert list(table.getColumnLabels()) == run.joint_names
    assert float(table.getTableMetaDataAsString("DataRate")) == 30.0
    np.testing.assert_allclose(np.asarray(table.getIndependentColumn()), np.arange(run.num_frames) / 30.0, atol=1e-8)
    last = table.getRowAtIndex(run.num_frames - 1)
    got = np.array([[last[k].get(i) for i in range(3)] for k in range(len(run.joint_names))])
    np.testing.assert_allclose(got, run.joints[-1], atol=1e-5)


@needs("ezc3d")
@needs("c3d")
@pytest.mark.filterwarnings("ignore:No analog data found")  # the c3d package's note: these files hold points only
@pytest.mark.parametrize("up", ["y", "z"])
def test_c3d_read_by_ezc3d_and_c3d(footage_run, tmp_path, up):
    """ezc3d and the `c3d` package read the keypoints back in millimetres within 1 mm of result.npz, with the
    labels, the rate and the axes stated (POINT:Y_SCREEN)."""
    import c3d
    import ezc3d

    (path,) = export_run(footage_run, "c3d", tmp_path, ExportOptions(up=up))
    run = load_run(footage_run)
    want_m = run.keypoints_model if up == "y" else run.arrays["keypoints"]
    names = pose2sim_names("BODY_25B", run.keypoint_names)
    f = ezc3d.c3d(str(path))
    point = f["parameters"]["POINT"]
    assert [s.strip() for s in point["LABELS"]["value"]] == names
    assert point["UNITS"]["value"] == ["mm"]
    assert point["RATE"]["value"][0] == 60.0
    assert point["Y_SCREEN"]["value"] == ["+Y" if up == "y" else "+Z"]
    np.testing.assert_allclose(f["data"]["points"][:3].transpose(2, 1, 0), want_m * 1000.0, atol=1.0)
    with open(path, "rb") as handle:
        reader = c3d.Reader(handle)
        assert reader.point_rate == 60.0
        assert [s.strip() for s in reader.point_labels] == names
        frames = np.array([pts[:, :3] for _, pts, _ in reader.read_frames()])
    np.testing.assert_allclose(frames, want_m * 1000.0, atol=1.0)


@needs("ezc3d")
def test_c3d_of_cmu_joints(cmu_run, tmp_path):
    """Joints of a simulated run: the skeleton's joint names at 30 fps, within 1 mm."""
    import ezc3d

    (path,) = export_run(cmu_run, "c3d", tmp_path / "j.c3d")
    run = load_run(cmu_run)
    f = ezc3d.c3d(str(path))
    assert [s.strip() for s in f["parameters"]["POINT"]["LABELS"]["value"]] == run.joint_names
    assert f["parameters"]["POINT"]["RATE"]["value"][0] == 30.0
    np.testing.assert_allclose(f["data"]["points"][:3].transpose(2, 1, 0), run.joints * 1000.0, atol=1.0)


@needs("opensim")
def test_mot_read_by_opensim_is_q(cmu_run, tmp_path):
    """OpenSim's Storage reads ptrack's angles back: q's rotations in degrees, the root translation in metres
    (within the 1e-8 of the text), in the dof order, at the frame times."""
    opensim = import_opensim()

    (path,) = export_run(cmu_run, "mot", tmp_path)
    run = load_run(cmu_run)
    storage = opensim.Storage(str(path))
    assert storage.isInDegrees()
    column_labels = storage.getColumnLabels()
    labels = [column_labels.get(i) for i in range(column_labels.getSize())]
    assert labels == ["time", *(str(n) for n in run.arrays["dof_names"])]
    table = opensim.TimeSeriesTable(str(path))
    got = table.getMatrix().to_numpy()
    want = run.arrays["q"].astype(np.float64).copy()
    angular = run.skeleton.angular_dofs()
    assert angular.sum() > 0 and (~angular).sum() == 3  # the root's translation is in metres
    want[:, angular] = np.degrees(want[:, angular])
    np.testing.assert_allclose(got, want, atol=1e-7)
    np.testing.assert_allclose(np.asarray(table.getIndependentColumn()), np.arange(run.num_frames) / 30.0, atol=1e-8)


@needs("opensim")
def test_mot_with_opensim_ik_gives_the_models_coordinates(footage_run, tmp_path, capfd):
    """`--opensim` runs OpenSim's IK of the run's keypoints on the shipped scaled model: all the model's
    coordinates at the run's frame times, the pelvis where the same IK of the 4-camera triangulation puts it
    on those frames (same axes: Y up, the lab's horizontal axes as Pose2Sim's TRC has them; the one-camera
    depth makes the 0.15 m); nothing printed, nothing but result.mot left, no opensim.log."""
    model = pose2sim("balancing/opensim_model_scaled.osim")
    opensim = import_opensim()
    capfd.readouterr()
    (path,) = export_run(footage_run, "mot", tmp_path, ExportOptions(opensim=str(model)))
    out, err = capfd.readouterr()
    assert out == "" and err == ""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result.mot"]
    assert not (Path.cwd() / "opensim.log").exists()
    table = opensim.TimeSeriesTable(str(path))
    labels = list(table.getColumnLabels())
    osim_model = opensim.Model(str(model))
    coordinates = osim_model.getCoordinateSet()
    assert labels == [coordinates.get(i).getName() for i in range(coordinates.getSize())]  # knee_angle_r, ...
    run = load_run(footage_run)
    frames = run.arrays["frames"]
    np.testing.assert_allclose(np.asarray(table.getIndependentColumn()), frames / 60.0, atol=1e-6)
    ours = table.getMatrix().to_numpy()
    assert np.isfinite(ours).all()
    reference = _first_rows(pose2sim("balancing/triangulated.trc"), int(frames.max()) + 1, tmp_path / "tri.trc")
    inverse_kinematics(model, reference, tmp_path / "tri.mot", tmp_path)
    tri_table = opensim.TimeSeriesTable(str(tmp_path / "tri.mot"))  # kept: getMatrix() is a view into it
    tri = tri_table.getMatrix().to_numpy()[frames]  # row i: frame i
    pelvis = [labels.index(n) for n in ("pelvis_tx", "pelvis_ty", "pelvis_tz")]
    assert np.abs(ours[:, pelvis] - tri[:, pelvis]).max() < 0.15, np.abs(ours[:, pelvis] - tri[:, pelvis]).max(0)


def _first_rows(trc: Path, n: int, out: Path) -> Path:
    """A copy of a TRC file with its first n frames."""
    lines = trc.read_text().splitlines()
    counts = lines[2].split("\t")
    counts[2] = counts[7] = str(n)  # NumFrames, OrigNumFrames
    out.write_text("\n".join([*lines[:2], "\t".join(counts), *lines[3:5], *lines[5 : 5 + n]]) + "\n")
    return out


def test_options_a_format_cannot_honour_are_errors(cmu_run, tmp_path, capsys):
    """TRC keypoints of a run without keypoints, MOT with Z up, --opensim with another format."""
    out = tmp_path / "o"
    base = ["export", str(cmu_run), "--out", str(out)]
    fail(capsys, out, [*base, "--format", "trc", "--points", "keypoints"], "no keypoints", "--points joints")
    fail(capsys, out, [*base, "--format", "mot", "--up", "z"], "--up z", "MOT")
    fail(capsys, out, [*base, "--format", "trc", "--opensim", "m.osim"], "--opensim", "mot")


@needs("opensim")
def test_opensim_model_that_is_not_a_model_is_an_error(footage_run, tmp_path, capsys):
    text = tmp_path / "model.osim"
    text.write_text("this is not an OpenSim model\n")
    xml = tmp_path / "bad.osim"
    xml.write_text('<?xml version="1.0"?>\n<OpenSimDocument Version="40000"><Model name="x"><Broken>')
    for model in (text, xml, tmp_path / "absent.osim"):
        out = tmp_path / "o"
        argv = ["export", str(footage_run), "--format", "mot", "--opensim", str(model), "--out", str(out)]
        fail(capsys, out, argv, str(model))


def test_missing_packages_are_one_line_errors(footage_run, tmp_path, capsys, monkeypatch):
    """Without ezc3d (C3D) or opensim (--opensim): one line naming the `export` extra, nothing written."""
    monkeypatch.setitem(sys.modules, "ezc3d", None)  # import ezc3d raises ImportError
    monkeypatch.setitem(sys.modules, "opensim", None)
    out = tmp_path / "o"
    fail(capsys, out, ["export", str(footage_run), "--format", "c3d", "--out", str(out)], "ptrack[export]", "ezc3d")
    argv = ["export", str(footage_run), "--format", "mot", "--opensim", "m.osim", "--out", str(out)]
    fail(capsys, out, argv, "ptrack[export]", "opensim")


@needs("opensim")
@needs("ezc3d")
def test_readme_export_block_runs_as_written(footage_run, capsys):
    """The README's "### Export" commands, with the run folder and the shipped scaled model filled in, write
    their files into RUN_DIR/export/."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    section = text[text.index("\n### Export\n") :]
    block = re.search(r"```bash\n(.*?)```", section, flags=re.S).group(1)
    model = pose2sim("balancing/opensim_model_scaled.osim")
    commands = [shlex.split(line.split("#")[0]) for line in block.splitlines() if line.strip()]
    assert len(commands) >= 3
    for argv in commands:
        assert argv[0] == "ptrack"
        args = [str(footage_run) if a == "RUN_DIR" else str(model) if a == "MODEL.osim" else a for a in argv[1:]]
        assert main(args) == 0, capsys.readouterr().err
    names = sorted(p.name for p in (footage_run / "export").iterdir())
    assert names == ["result.bvh", "result.c3d", "result.json", "result.mot", "result.trc"]
