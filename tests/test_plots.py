"""Tests for ptrack.io.plots: a run writes plots/ with the pictures its arrays allow (config key `plots`), a
picture that fails is a warning and never the run's failure, `ptrack evaluate` writes results.png."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import ptrack.io.plots as P
from ptrack.observe.camera import camera_for_motion
from ptrack.pipeline.config import load_config
from ptrack.pipeline.evaluate import evaluate
from ptrack.pipeline.run import execute

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "configs" / "demo.yaml"
KJS = REPO / "configs" / "kjs.yaml"
AMC = REPO / "ptrack" / "data" / "10_02.amc"
QUICK = ["data.stop=24", "data.stride=4", "frame.iterations=3", "frame.first_iterations=5", "progress=false"]
TRACKER = ["data.stop=24", "progress=false", "kjs.samples=16", "kjs.modes=4"]


def _png_size(path: Path) -> tuple[int, int]:
    with Image.open(path) as im:
        assert im.format == "PNG"
        return im.size


@pytest.fixture(scope="module")
def kjs_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("plots") / "kjs"
    return execute(load_config(KJS, [*TRACKER, f"out_dir={out}"]))


@pytest.fixture(scope="module")
def arrays(kjs_run) -> dict[str, np.ndarray]:
    with np.load(kjs_run / "result.npz") as z:
        return {k: z[k] for k in z.files}


def test_a_tracker_run_writes_its_pictures(kjs_run):
    names = sorted(p.name for p in (kjs_run / "plots").iterdir())
    assert names == ["errors.png", "hypothesis_weights.png", "joint_angles.png", "skeleton.png"]  # no joint_std
    for name in names:
        w, h = _png_size(kjs_run / "plots" / name)
        assert w >= 400 and h >= 250


def test_plots_false_writes_none(tmp_path):
    out = execute(load_config(DEMO, [*QUICK, "plots=false", f"out_dir={tmp_path / 'run'}"]))
    assert not (out / "plots").exists() and (out / "result.npz").is_file()


def test_a_failing_picture_is_a_warning_and_the_others_are_written(tmp_path, monkeypatch, caplog):
    def broken(arrays, series):
        raise RuntimeError("no skeleton today")

    monkeypatch.setitem(P.PICTURES, "skeleton.png", broken)
    with caplog.at_level(logging.WARNING, logger="ptrack.io.plots"):
        out = execute(load_config(DEMO, [*QUICK, f"out_dir={tmp_path / 'run'}"]))
    assert sorted(p.name for p in (out / "plots").iterdir()) == ["errors.png", "joint_angles.png"]
    assert "skeleton.png not written: RuntimeError: no skeleton today" in caplog.text


def test_a_plotting_failure_does_not_fail_the_run(tmp_path, monkeypatch, caplog):
    """Whatever goes wrong in plotting (matplotlib missing, a folder it cannot make), the run is written."""

    def broken(folder, arrays, series=None):
        raise ImportError("No module named 'matplotlib'")

    monkeypatch.setattr(P, "write_plots", broken)
    with caplog.at_level(logging.WARNING, logger="ptrack.pipeline.run"):
        out = execute(load_config(DEMO, [*QUICK, f"out_dir={tmp_path / 'run'}"]))
    assert (out / "metrics.json").is_file() and (out / "result.npz").is_file()
    assert "plots not written: ImportError" in caplog.text


def test_uncertainty_and_errors_follow_the_arrays(arrays, tmp_path):
    """uncertainty.png only with joint_std (method batch); errors.png without ground truth: the reprojection alone;
    hypothesis_weights.png only with hypotheses."""
    T, J = arrays["joints"].shape[:2]
    with_std = {**arrays, "joint_std": np.full((T, J), 0.02)}
    series = {"reprojection_error_px": np.linspace(1, 2, T), "mpjpe_mm": np.linspace(20, 30, T)}
    written = [p.name for p in P.write_plots(tmp_path / "a", with_std, series)]
    assert "uncertainty.png" in written and "hypothesis_weights.png" in written
    footage = {k: v for k, v in arrays.items() if k not in ("gt_joints", "hypothesis_weights")}
    reprojection = {"reprojection_error_px": series["reprojection_error_px"]}
    written = [p.name for p in P.write_plots(tmp_path / "b", footage, reprojection)]
    assert written == ["errors.png", "joint_angles.png", "skeleton.png"]
    _, one_panel = _png_size(tmp_path / "b" / "errors.png")
    _, two_panels = _png_size(tmp_path / "a" / "errors.png")
    assert one_panel < two_panels  # no ground truth: no MPJPE panel


def test_no_main_joint_no_angles_picture(arrays):
    renamed = {**arrays, "dof_names": np.asarray([f"j{i}.rx" for i in range(len(arrays["dof_names"]))])}
    assert P.joint_angles_figure(renamed, {}) is None
    assert P.joint_angles_figure(arrays, {}) is not None


def test_the_camera_view_is_the_camera_projection():
    """_project maps world points to the pixels Camera.project gives (the camera row of skeleton.png), head above
    the feet (image rows grow downwards) for a person standing in the Y-up world."""
    joints = torch.tensor([[[0.0, 0.0, 0.0], [0.0, 1.7, 0.0], [0.3, 0.9, 0.2]]], dtype=torch.float64)
    cam = camera_for_motion(joints, 4.0, 30.0, 10.0, 800.0, 640, 480)
    ours = P._project(joints.numpy(), cam.K.numpy(), cam.R.numpy(), cam.t.numpy())
    np.testing.assert_allclose(ours, cam.project(joints).pixels.numpy(), atol=1e-9)
    assert ours[0, 1, 1] < ours[0, 0, 1]  # the head (y = 1.7 m) lies above the feet in the image


def test_snapshot_frames_and_bone_colours():
    assert P.snapshot_frames(15).tolist() == [0, 3, 6, 8, 11, 14]
    assert P.snapshot_frames(3).tolist() == [0, 1, 2]
    names = ["root", "lfemur", "rfemur", "lowerback", "lm_nose", "lm_l_eye", "lm_r_eye"]
    assert P._bone_colors(names, []) == [P.CENTRE, P.LEFT, P.RIGHT, P.CENTRE, P.CENTRE, P.LEFT, P.RIGHT]


def test_evaluate_writes_a_bar_chart(tmp_path):
    out = tmp_path / "eval"
    evaluate(REPO / "configs" / "eval_frame.yaml", str(AMC), QUICK, out=out)
    assert _png_size(out / "results.png")[0] >= 300
    off = tmp_path / "off"
    evaluate(REPO / "configs" / "eval_frame.yaml", str(AMC), [*QUICK, "plots=false"], out=off)
    assert not (off / "results.png").exists() and not (off / "10_02" / "plots").exists()


def test_evaluation_figure_marks_failures_and_the_mean(tmp_path):
    rows = [("a", {"mpjpe_mm": 20.0}), ("b", {"mpjpe_mm": 40.0}), ("c", "too short")]
    fig = P.evaluation_figure(rows, "t", {"a": 1.0, "b": 2.0})
    ax = fig.axes[0]
    assert [t.get_text() for t in ax.get_xticklabels()] == ["a", "b", "c"]
    assert ax.get_legend().get_texts()[0].get_text() == "mean 30.0 (2 clips)"
    assert any(t.get_text() == "failed" for t in ax.texts)
    P.save(fig, tmp_path / "r.png")
    assert _png_size(tmp_path / "r.png")[0] > 0
