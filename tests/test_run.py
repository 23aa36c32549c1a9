"""Tests for ptrack.pipeline.run: `execute(cfg)` on the bundled CMU clip writes exactly config.yaml, metrics.json,
result.npz, result.bvh, run.rrd and plots/, atomically; `prepare` makes silhouettes or reads an observation file."""

from __future__ import annotations

import json
import math
import os
import re
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import rerun.chunk
import torch

import ptrack.io.viz
import ptrack.pipeline.run
from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.errors import EstimationError, InputError
from ptrack.estimators import ESTIMATORS, estimate_frames
from ptrack.pipeline import metrics as M
from ptrack.pipeline.config import load_config, to_dict
from ptrack.pipeline.run import execute, json_safe, prepare
from ptrack.problem import Estimate

REPO = Path(__file__).resolve().parents[1]
DEMO = REPO / "configs" / "demo.yaml"
ASF = REPO / "ptrack" / "data" / "10.asf"
AMC = REPO / "ptrack" / "data" / "10_02.amc"
FAST = ["data.stop=48", "data.stride=4", "frame.iterations=15", "frame.first_iterations=60", "progress=false"]
QUICK = [*FAST, "frame.iterations=3", "frame.first_iterations=5"]  # for runs whose accuracy is not checked
T = 12
FREEZE = ["*fingers", "*thumb", "*hand", "*toes"]
OUTPUTS = ["config.yaml", "metrics.json", "plots", "result.bvh", "result.npz", "run.rrd", "skeleton.urdf"]
METRIC_KEYS = (
    "seconds",
    "frames",
    "mpjpe_mm",
    "pa_mpjpe_mm",
    "mpjpe_abs_mm",
    "accel_error_mm_per_frame2",
    "accel_error_abs_mm_per_frame2",
    "flip_error_rate",
    "reprojection_error_px",
    "joint_limit_violation_fraction",
    "gt_joint_limit_violation_fraction",
)


def _cfg(out: Path, *extra: str, fast=FAST):
    return load_config(DEMO, [*fast, f"out_dir={out}", *extra])


def _entities(rrd: Path) -> Counter:
    """(entity path, static) -> rows in the recording."""
    rows: Counter = Counter()
    for chunk in rerun.chunk.RrdReader(rrd).stream().to_chunks():
        rows[(chunk.entity_path.lstrip("/"), chunk.is_static)] += chunk.num_rows
    return rows


def _leftovers(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir()] if folder.exists() else []


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("run") / "demo"
    cfg = _cfg(out)
    assert execute(cfg) == out
    return out


@pytest.fixture(scope="module")
def result(run_dir):
    with np.load(run_dir / "result.npz") as f:
        return {k: f[k] for k in f.files}


def test_writes_exactly_the_outputs(run_dir):
    assert sorted(os.listdir(run_dir)) == OUTPUTS
    assert _leftovers(run_dir.parent) == [run_dir.name]  # no hidden .partial sibling left


def test_metrics_json(run_dir):
    m = json.loads((run_dir / "metrics.json").read_text())
    for k in METRIC_KEYS:
        assert k in m, f"metrics.json has no {k!r}"
        assert isinstance(m[k], (int, float)) and math.isfinite(m[k]), (k, m[k])
    assert m["frames"] == T and isinstance(m["frames"], int)
    assert m["seconds"] > 0 and m["method"] == "frame"
    assert 0 <= m["flip_error_rate"] <= 1 and 0 <= m["joint_limit_violation_fraction"] <= 1
    # the demo's 2 px noise, 5% missing keypoints, keyframe start: measured 21 mm and 1.7 px
    assert m["mpjpe_mm"] < 35 and m["reprojection_error_px"] < 4
    assert m["mpjpe_abs_mm"] >= 0 and m["pa_mpjpe_mm"] >= 0


def test_result_frames_are_amc_frame_numbers(result):
    assert result["frames"].tolist() == list(range(1, 48, 4))  # start 0, stride 4: AMC frames 1, 5, 9, ...
    assert np.allclose(result["times"], np.arange(T) * 4 / 120.0, atol=1e-6)


def test_result_arrays(result):
    full = Skeleton.from_asf(ASF)
    model = full.freeze(FREEZE)
    D, J = model.num_dofs, model.num_joints
    assert result["q"].shape == (T, D) and result["dof_names"].tolist() == list(model.dof_names)
    assert result["joints"].shape == (T, J, 3) and result["gt_joints"].shape == (T, J, 3)
    names = result["joint_names"].tolist()
    assert names[0] == "root" and names == list(full.joint_names)
    asf_bones = re.findall(r"^\s+name\s+(\S+)", ASF.read_text(), flags=re.M)  # bonedata names
    assert sorted(names[1:]) == sorted(asf_bones)
    assert result["parents"].tolist() == list(model.parents)
    assert result["keypoints_observed"].shape == (T, 17, 2) and result["confidence"].shape == (T, 17)
    assert result["keypoints_reprojected"].shape == (T, 17, 2)
    assert result["image_size"].tolist() == [640, 480]
    assert result["camera_K"].shape == (3, 3) and result["cost"].shape == (T,)


def test_result_joints_are_fk_of_q(result):
    model = Skeleton.from_asf(ASF).freeze(FREEZE)
    fk = model.forward_kinematics(torch.as_tensor(result["q"], dtype=torch.float64)).numpy()
    assert np.allclose(result["joints"], fk, atol=1e-4)


def test_result_reprojection_matches_camera(result):
    K, R, t = result["camera_K"], result["camera_R"], result["camera_t"]
    idx = [result["joint_names"].tolist().index(j) for j in ("root", "head")]
    cam = result["joints"][:, idx] @ R.T + t
    pix = cam[..., :2] / cam[..., 2:] * K[[0, 1], [0, 1]] + K[:2, 2]
    kp = result["keypoint_names"].tolist()
    assert np.allclose(pix, result["keypoints_reprojected"][:, [kp.index("pelvis"), kp.index("head")]], atol=1e-2)


def test_ground_truth_in_mocap_world_frame(result):
    full = Skeleton.from_asf(ASF)
    motion = load_amc(AMC, full)
    assert motion.frames[:48:4].tolist() == result["frames"].tolist()
    gt = full.forward_kinematics(motion.q[:48:4]).numpy()
    assert np.allclose(result["gt_joints"], gt, atol=1e-4)
    names = result["joint_names"].tolist()
    head, feet = names.index("head"), [names.index("ltoes"), names.index("rtoes")]
    for X in (result["gt_joints"], result["joints"]):  # Y up: the head is well above both feet
        assert (X[:, head, 1] > X[:, feet, 1].max(axis=1) + 1.0).all()


def test_config_yaml_loads_back(run_dir):
    again = load_config(run_dir / "config.yaml")
    assert to_dict(again) == to_dict(_cfg(run_dir))
    assert again.name == "demo" and again.out_dir == str(run_dir)


def test_recording(run_dir, result):
    rows = _entities(run_dir / "run.rrd")
    for e in (
        "world/estimate/joints",
        "world/estimate/bones",
        "world/ground_truth/joints",
        "world/camera/image/observed",
        "metrics/mpjpe_mm",
        "metrics/reprojection_error_px",
        "metrics/pa_mpjpe_mm",
        "metrics/cost",
    ):
        assert rows[(e, False)] == T, f"{e}: {rows[(e, False)]} rows"
    assert rows[("world/camera", True)] > 0
    assert not any(e.startswith("world/camera/image/silhouette") for e, _ in rows)
    # the estimate logged at the first AMC frame is result.npz's first frame
    found = False
    for chunk in rerun.chunk.RrdReader(run_dir / "run.rrd").stream().to_chunks():
        if chunk.entity_path.lstrip("/") == "world/estimate/joints" and not chunk.is_static:
            batch = chunk.to_record_batch()
            frames = batch.column("frame").to_pylist()
            if 1 in frames:
                pos = np.asarray(batch.column("Points3D:positions")[frames.index(1)].as_py())
                assert np.allclose(pos, result["joints"][0], atol=1e-5)
                found = True
    assert found


def test_run_folder_has_ordinary_permissions(run_dir, tmp_path):
    # The folder is assembled in a tempfile.mkdtemp() sibling (mode 0700) and renamed into place; the
    # run folder should still get the permissions any new folder gets (umask), like its files do.
    ref = tmp_path / "ref"
    ref.mkdir()
    assert oct(run_dir.stat().st_mode & 0o777) == oct(ref.stat().st_mode & 0o777)


# ---------------------------------------------------------------- observations: silhouettes, files


def test_silhouettes_put_masks_in_observations(tmp_path):
    small = ["camera.width=160", "camera.height=120", "camera.focal_px=250", "observations.silhouettes=true"]
    cfg = _cfg(tmp_path / "sil", *small, fast=QUICK)
    masks = prepare(cfg).problem.observations.masks
    assert masks is not None and masks.shape == (T, 120, 160) and masks.dtype == torch.bool
    area = masks.flatten(1).float().mean(1)
    assert (area > 0.01).all() and (area < 0.5).all()
    out = execute(cfg)
    assert _entities(out / "run.rrd")[("world/camera/image/silhouette", False)] == T
    assert prepare(_cfg(tmp_path / "x", fast=QUICK)).problem.observations.masks is None


def test_run_from_observation_file(tmp_path):
    obs = prepare(_cfg(tmp_path / "unused", "seed=4", fast=QUICK)).problem.observations
    path = tmp_path / "obs.npz"
    obs.save_npz(path)
    out = execute(_cfg(tmp_path / "from_file", f"observations.file={path}", "seed=0", fast=QUICK))
    with np.load(out / "result.npz") as r:
        assert np.array_equal(r["keypoints_observed"], obs.keypoints.numpy(), equal_nan=True)
        assert np.array_equal(r["camera_R"], obs.camera.R.numpy())
        assert r["frames"].tolist() == list(range(1, 48, 4))
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"] == T and math.isfinite(m["mpjpe_mm"])


def test_run_from_observation_file_without_motion(tmp_path):
    obs = prepare(_cfg(tmp_path / "unused", fast=QUICK)).problem.observations
    path = tmp_path / "obs.npz"
    obs.save_npz(path)
    out = execute(_cfg(tmp_path / "no_gt", f"observations.file={path}", 'data.amc=""', "frame.init=rest", fast=QUICK))
    m = json.loads((out / "metrics.json").read_text())
    assert m["frames"] == T and math.isfinite(m["reprojection_error_px"])
    assert "mpjpe_mm" not in m  # no ground truth
    with np.load(out / "result.npz") as r:
        assert r["frames"].tolist() == list(range(T)) and "gt_joints" not in r.files


def test_observation_file_frame_count_must_match(tmp_path):
    obs = prepare(_cfg(tmp_path / "unused", fast=QUICK)).problem.observations
    path = tmp_path / "obs.npz"
    obs.save_npz(path)
    with pytest.raises(InputError, match=r"obs\.npz"):
        execute(_cfg(tmp_path / "o", f"observations.file={path}", "data.stop=80", fast=QUICK))
    assert not (tmp_path / "o").exists()


# ---------------------------------------------------------------- failures leave nothing behind


def test_camera_that_sees_nothing_leaves_nothing(tmp_path):
    out = tmp_path / "runs" / "blind"
    with pytest.raises(InputError, match="sees none"):
        execute(_cfg(out, "camera.focal_px=10000000", fast=QUICK))
    assert not out.exists()
    assert not any(".partial" in n for n in _leftovers(out.parent))


def test_failure_inside_writer_leaves_nothing(tmp_path, monkeypatch):
    def boom(path, log):
        Path(path).write_bytes(b"half a recording")
        raise RuntimeError("disk on fire")

    monkeypatch.setattr(ptrack.io.viz, "write_recording", boom)
    out = tmp_path / "runs" / "doomed"
    with pytest.raises(RuntimeError, match="disk on fire"):
        execute(_cfg(out, fast=QUICK))
    assert not out.exists()
    assert _leftovers(out.parent) == []  # the hidden .partial folder is gone too


def test_existing_non_empty_out_dir_is_refused(tmp_path):
    out = tmp_path / "taken"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(InputError, match="out_dir"):
        execute(_cfg(out, fast=QUICK))
    assert _leftovers(out) == ["keep.txt"] and (out / "keep.txt").read_text() == "mine"
    assert _leftovers(tmp_path) == ["taken"]


def test_out_dir_that_is_a_file_is_refused(tmp_path):
    out = tmp_path / "file"
    out.write_text("x")
    with pytest.raises(InputError, match=r"out_dir .* is an existing file, not a folder"):
        execute(_cfg(out, fast=QUICK))
    assert out.read_text() == "x"


def test_out_dir_under_a_file_fails_before_any_work(tmp_path, monkeypatch):
    (tmp_path / "file").write_text("x")
    out = tmp_path / "file" / "runs" / "a"

    def no_work(cfg):
        raise AssertionError("the run started before out_dir was checked")

    monkeypatch.setattr(ptrack.pipeline.run, "prepare", no_work)
    with pytest.raises(InputError, match=f"out_dir .* cannot be made: {tmp_path / 'file'} is a file"):
        execute(_cfg(out, fast=QUICK))
    assert _leftovers(tmp_path) == ["file"]


@pytest.mark.skipif(not Path("/proc/self").is_dir(), reason="needs Linux /proc (no folder can be made in it)")
def test_unwritable_out_dir_fails_before_any_work(tmp_path, monkeypatch):
    monkeypatch.setattr(
        ptrack.pipeline.run, "prepare", lambda cfg: pytest.fail("the run started before out_dir was checked")
    )
    with pytest.raises(InputError, match="out_dir /proc/ptrack-run cannot be made: cannot write in /proc"):
        execute(_cfg(Path("/proc/ptrack-run"), fast=QUICK))


def test_existing_empty_out_dir_is_used(tmp_path):
    out = tmp_path / "empty"
    out.mkdir()
    assert execute(_cfg(out, fast=QUICK)) == out
    assert sorted(os.listdir(out)) == OUTPUTS
    assert _leftovers(tmp_path) == ["empty"]


def test_default_out_dir(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cfg = load_config(DEMO, QUICK)
    assert cfg.out_dir is None and cfg.name == "demo"
    out = execute(cfg)
    assert out.parent == Path("logs")
    assert re.fullmatch(r"demo-\d{8}-\d{6}(-\d+)?", out.name), out.name
    assert [p.name for p in (tmp_path / "logs").iterdir()] == [out.name]
    assert sorted(os.listdir(tmp_path / out)) == OUTPUTS
    # config.yaml records the folder actually used, not `out_dir: null`
    assert load_config(tmp_path / out / "config.yaml").out_dir == str((tmp_path / out).resolve())


def test_bvh_output_matches_result(run_dir):
    """result.bvh holds the estimated motion: its frame count and root positions match result.npz."""
    from test_export import read_bvh

    res = np.load(run_dir / "result.npz")
    names, _, _, _channels, frame_time, values = read_bvh((run_dir / "result.bvh").read_text())
    assert names[0] == "root" and values.shape[0] == res["q"].shape[0]
    assert frame_time == pytest.approx(4 / 120, abs=1e-6)  # stride 4 of the 120 fps clip
    np.testing.assert_allclose(values[:, :3], res["joints"][:, 0], atol=2e-5)


def test_metrics_use_the_configured_limits_and_report_the_truths_own(run_dir):
    """The default limits are the data-derived ones, which the truth obeys; the CMU ASF limits are not."""
    m = json.loads((run_dir / "metrics.json").read_text())
    assert m["gt_joint_limit_violation_fraction"] == 0.0
    assert yaml_limits(run_dir) == "data"
    asf = execute(_cfg(run_dir.parent / "asf", "model.limits=asf", "data.stop=null", fast=QUICK))
    m_asf = json.loads((asf / "metrics.json").read_text())
    # the whole 10_02 clip breaks the ASF limits in 1.8% of the limited dof-frames (measured 0.0178)
    assert m_asf["gt_joint_limit_violation_fraction"] > 0.01
    none = execute(_cfg(run_dir.parent / "none", "model.limits=none", fast=QUICK))
    m_none = json.loads((none / "metrics.json").read_text())
    assert m_none["gt_joint_limit_violation_fraction"] == 0 and m_none["joint_limit_violation_fraction"] == 0


def yaml_limits(run_dir: Path) -> str:
    import yaml

    return yaml.safe_load((run_dir / "config.yaml").read_text())["model"]["limits"]


def test_accel_error_is_pelvis_centred_and_absolute_is_reported_too(run_dir, result):
    """accel_error_mm_per_frame2 is VIBE's (pelvis subtracted); the absolute one has its own key."""
    m = json.loads((run_dir / "metrics.json").read_text())
    names = list(result["keypoint_names"])
    idx = [list(result["joint_names"]).index(j) for j in _keypoint_joints(result)]
    est, gt = torch.as_tensor(result["joints"][:, idx]), torch.as_tensor(result["gt_joints"][:, idx])
    pelvis = names.index("pelvis")
    assert m["accel_error_mm_per_frame2"] == pytest.approx(float(M.accel_error(est, gt, root=pelvis).mean()), rel=1e-5)
    assert m["accel_error_abs_mm_per_frame2"] == pytest.approx(float(M.accel_error(est, gt).mean()), rel=1e-5)
    assert m["accel_error_mm_per_frame2"] != m["accel_error_abs_mm_per_frame2"]


def _keypoint_joints(result) -> list[str]:
    from ptrack.body.keypoints import make_keypoints

    sk = Skeleton.from_asf(ASF).freeze(FREEZE)
    kps = make_keypoints(sk)
    assert list(kps.names) == list(result["keypoint_names"])
    return [sk.joint_names[j] for j in kps.joints]


def _nan_every_other_frame(problem, cfg, gen, progress):
    est = estimate_frames(problem, cfg, gen, progress)
    q = est.q.clone()
    q[1::2] = float("nan")
    joints = problem.skeleton.forward_kinematics(q)
    return Estimate(q=q, joints=joints, cost=est.cost, terms=est.terms)


def test_non_finite_estimate_fails_the_run_and_writes_nothing(tmp_path, monkeypatch):
    """An estimate with every odd frame NaN must not score like a complete one (nanmean did that)."""
    monkeypatch.setitem(ESTIMATORS, "frame", _nan_every_other_frame)
    out = tmp_path / "nan"
    with pytest.raises(
        EstimationError,
        match=r"non-finite poses in 6 of 12 frames \(nonfinite_frames=6; first at "
        r"frame indices \[1, 3, 5, 7, 9\]\)",
    ):
        execute(_cfg(out, fast=QUICK))
    assert not out.exists() and _leftovers(tmp_path) == []


def test_json_never_holds_nan():
    assert json_safe({"a": float("nan"), "b": [1.0, float("inf"), {"c": -float("inf")}], "d": 2, "e": "x"}) == {
        "a": None,
        "b": [1.0, None, {"c": None}],
        "d": 2,
        "e": "x",
    }


def test_metrics_json_writes_null_for_undefined_metrics(tmp_path, monkeypatch):
    """A metric that comes out NaN is written as null: metrics.json is strict JSON (it had bare NaN)."""
    monkeypatch.setattr(M, "accel_error", lambda pred, gt, root=None: torch.full((pred.shape[0] - 2,), float("nan")))
    out = execute(_cfg(tmp_path / "r", fast=QUICK))
    text = (out / "metrics.json").read_text()
    m = json.loads(text, parse_constant=lambda c: pytest.fail(f"metrics.json holds {c}"))
    assert m["accel_error_mm_per_frame2"] is None and m["accel_error_abs_mm_per_frame2"] is None
    assert isinstance(m["mpjpe_mm"], float)


def test_metrics_record_the_visible_fraction(run_dir):
    m = json.loads((run_dir / "metrics.json").read_text())
    assert m["visible_fraction"] == 1.0  # the demo camera sees every keypoint of these frames


def test_visibility_check_needs_three_frames_a_third_seen(caplog):
    from ptrack.pipeline.run import check_visibility

    visible = torch.zeros(10, 6, dtype=torch.bool)
    visible[:2, :2] = True  # two frames with a third of the keypoints: refused
    with pytest.raises(InputError, match="2 of 10 frames have at least a third"):
        check_visibility(visible)
    visible[2, :2] = True  # three: runs, with a warning (6 of 60 visible)
    check_visibility(visible)
    assert [r.levelname for r in caplog.records] == ["WARNING"]
    assert "visible_fraction 0.100" in caplog.records[0].getMessage()
    caplog.clear()
    check_visibility(torch.ones(10, 6, dtype=torch.bool))
    assert caplog.records == []
