"""The README's Python API (its guide) runs as written, from the repository root, and `ptrack.estimate` returns
what `ptrack run` writes for the same config."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch

import ptrack
from ptrack.pipeline.run import execute

REPO = Path(__file__).resolve().parents[1]


def _python_blocks(section: str) -> list[str]:
    """The ```python blocks of the README section headed `section` (up to the next heading of any level)."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    start = text.index(f"\n{section}\n")
    end = re.search(r"\n#+ ", text[start + 1 :])
    body = text[start : start + 1 + end.start()] if end else text[start:]
    return re.findall(r"```python\n(.*?)```", body, flags=re.S)


#: what the test adds to each README config so that the guide runs in seconds (the README's own overrides stay)
LIGHT = {
    "kjs.yaml": {"kjs.samples": 64},
    "demo.yaml": {"frame.iterations": 5},
    "batch.yaml": {"batch.iterations": 4, "batch.uncertainty": "laplace", "batch.flip_restarts": 0},
    "golf.yaml": {"pca.iterations": 1, "observations.silhouettes": False, "data.stride": 8},
    "video.yaml": {"method": "frame", "data.stop": 20, "frame.iterations": 5, "frame.first_iterations": 20},
}


@pytest.fixture
def repo_copy(tmp_path, monkeypatch):
    """A folder laid out as the repository beside ../shared (links to the real ones), as the working directory: the
    README's relative paths resolve, and what it writes lands in tmp_path."""
    root = tmp_path / "repo"
    root.mkdir()
    for name in ("configs", "tests", "ptrack"):
        (root / name).symlink_to(REPO / name)
    shared = REPO.parent / "shared"
    if shared.exists():
        (tmp_path / "shared").symlink_to(shared)
    monkeypatch.chdir(root)
    return root


def test_python_api_blocks_run(monkeypatch, cmu_dir, repo_copy, tmp_path):
    """The blocks of "### Python API" run one after another in one namespace (the first reads ../shared/data/cmu,
    hence `cmu_dir`; the footage block ../shared/data/pose2sim), with lighter solver settings (LIGHT) and the golf
    motion model fitted into tmp_path; what they make has the shapes their comments state."""
    pytest.importorskip("ptrack.observe.camera_files")
    if not (repo_copy.parent / "shared" / "data" / "pose2sim").exists():
        pytest.skip("the Pose2Sim data is not at ../shared/data/pose2sim")
    blocks = _python_blocks("### Python API")
    assert len(blocks) == 7
    real = ptrack.load_config

    def light(path=None, overrides=(), **kw):
        extra = {**LIGHT.get(Path(path).name, {}), "progress": False}
        if Path(path).name == "golf.yaml":
            extra["motion.model_file"] = str(tmp_path / "golf.npz")
        if isinstance(overrides, dict):
            return real(path, {**overrides, **extra}, **kw)
        return real(path, [*overrides, *(f"{k}={v}" for k, v in extra.items())], **kw)

    monkeypatch.setattr(ptrack, "load_config", light)
    space: dict = {}
    for code in blocks:
        exec(compile(code, "README.md", "exec"), space)  # the README's own example
    est, prep = space["est"], space["prep"]
    t, d = est.q.shape
    assert t == 15 and d == prep.problem.skeleton.num_dofs
    j = prep.problem.skeleton.num_joints
    assert space["joints"].shape == (t, j, 3) and space["truth"].shape == (t, j, 3)
    assert space["modes"].shape == (t, 8, j, 3)
    torch.testing.assert_close(est.hypothesis_weights.sum(-1), torch.ones(t, dtype=est.q.dtype))
    err_mm = 1000 * (space["joints"] - space["truth"]).norm(dim=-1).mean()
    assert torch.isfinite(err_mm) and err_mm < 150  # a tracked body, not a stray pose

    # keypoint files and cameras: every container gives the OpenPose frames, every camera file the same camera
    dets = space["dets"]
    assert dets.keypoint_set == "BODY_25B" and dets.frames.tolist() == [2, 3, 4, 5] and dets.people.shape[2:] == (25, 3)
    for other in ("coco", "mmpose", "arrays"):
        np.testing.assert_allclose(space[other].people, dets.people, atol=1e-3)  # rounded to 1/1000 px
    assert space["arrays"].fps == 25
    for other in ("same", "easy"):
        for field in ("K", "dist", "R", "t"):
            np.testing.assert_allclose(getattr(space[other], field), getattr(space["cam"], field), atol=1e-12)

    # the other methods and the footage
    assert space["frame"].hypotheses is None and space["frame"].q.shape[0] == 15
    assert space["batch"].joint_std.shape == (15, space["batch"].joints.shape[1])
    assert space["golf"].q.ndim == 2 and torch.isfinite(space["golf"].q).all()
    kps = space["footage_res"]["keypoints"]
    assert kps.shape == (20, 25, 3) and np.isfinite(kps).any()

    # exporting: the files where the block says, read back
    run_dir = space["run_dir"]
    assert space["bvh"] == [run_dir / "export" / "result.bvh"] and "mixamorig:Hips" in space["bvh"][0].read_text()
    assert space["trc"] == [Path("logs/guide-kjs.trc")] and space["trc"][0].read_text().startswith("PathFileType")
    assert json.loads(space["table"][0].read_text())["schema_version"]

    # reading and replaying
    assert space["knee"].shape == (t,)
    np.testing.assert_allclose(space["weights"].sum(-1), 1.0, atol=1e-5)
    rrd = repo_copy / "kjs.rrd"
    assert rrd.stat().st_size > 0 and rrd.read_bytes()[:4] == b"RRF2"


def test_format_examples_are_the_openpose_frames():
    """tests/data/keypoints/formats (the README's examples) holds the shipped OpenPose frames in the other containers
    (tests/data/keypoints/make_formats.py): each reads back the same people, to the 1/1000 px they are rounded to."""
    kp = REPO / "tests" / "data" / "keypoints"
    dets = ptrack.read_keypoints(kp / "two_people_cam01")
    for name in ("two_people_cam01.alphapose.json", "two_people_cam01.mmpose.json", "two_people_cam01.npz"):
        other = ptrack.read_keypoints(kp / "formats" / name)
        assert other.keypoint_set == dets.keypoint_set and other.frames.tolist() == dets.frames.tolist()
        np.testing.assert_allclose(other.people, dets.people, atol=1e-3)
    opencv = ptrack.read_camera(kp / "formats" / "cam01.yml")
    easy = ptrack.read_camera(kp / "formats" / "easymocap", "01")
    assert (opencv.width, opencv.height) == (easy.width, easy.height) == (1088, 1920)
    for field in ("K", "dist", "R", "t"):
        np.testing.assert_allclose(getattr(opencv, field), getattr(easy, field), atol=1e-12)


@pytest.mark.parametrize("method", ["kjs", "frame"])
def test_estimate_is_what_run_writes(tmp_path, method):
    """`ptrack.estimate(cfg)` gives the trajectory and hypotheses `execute(cfg)` writes to result.npz (the same
    two seeds), and writes nothing itself."""
    over = ["data.stop=28", "progress=false", f"method={method}", "kjs.samples=64", "frame.iterations=5"]
    cfg = ptrack.load_config(REPO / "configs" / "kjs.yaml", [*over, f"out_dir={tmp_path / 'run'}"])
    out = execute(cfg)
    before = sorted(tmp_path.rglob("*"))
    prep, est = ptrack.estimate(cfg)
    assert sorted(tmp_path.rglob("*")) == before
    saved = np.load(out / "result.npz")
    np.testing.assert_array_equal(saved["q"], est.q.numpy())
    np.testing.assert_array_equal(saved["joints"], est.joints.numpy())
    if method == "kjs":
        np.testing.assert_array_equal(saved["hypothesis_weights"], est.hypothesis_weights.numpy())
    else:
        assert est.hypotheses is None and "hypotheses" not in saved
    assert prep.gt_joints is not None and prep.gt_joints.shape == est.joints.shape
