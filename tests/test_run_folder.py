"""A run folder read back (`load_run`) and the export registry's contract: one error line, nothing written."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from bvh_text import assert_bvh_close

from ptrack.errors import InputError
from ptrack.io.exporters import export_run
from ptrack.io.run_folder import load_run

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("runs") / "frame"
    argv = ["run", str(ROOT / "configs" / "demo.yaml"), "data.stop=40", "data.stride=4", f"out_dir={out}", "--quiet"]
    subprocess.run([sys.executable, "-m", "ptrack.cli", *argv], check=True, capture_output=True, timeout=300)
    return out


def test_load_run_reads_the_arrays_and_the_model(run_dir):
    run = load_run(run_dir)
    assert run.fps == pytest.approx(30.0, abs=1e-12)  # 120 fps mocap, stride 4: exact, not from float32 times
    assert run.num_frames == 10 and run.joints.shape == (10, len(run.joint_names), 3)
    assert not run.is_footage and run.keypoints_model is None
    sk = run.skeleton  # skeleton.urdf: its forward kinematics of q is the run's joints
    fk = sk.forward_kinematics(torch.as_tensor(run.arrays["q"], dtype=torch.float64)).numpy()
    np.testing.assert_allclose(fk, run.joints, atol=2e-5)  # joints were stored as float32


def test_bvh_export_is_the_runs_bvh(run_dir, tmp_path):
    (path,) = export_run(run_dir, "BVH", tmp_path / "out")
    assert path == tmp_path / "out" / "result.bvh"
    assert sorted(p.name for p in path.parent.iterdir()) == ["result.bvh"]  # no temporary folder left
    # the same file up to the last digits: the export reads q back from result.npz (float32) and the model from
    # skeleton.urdf, the run wrote it from its own tensors
    assert_bvh_close(path.read_text(), (run_dir / "result.bvh").read_text(), atol=2e-5)


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda d: d, "not a ptrack run folder: no result.npz, metrics.json, config.yaml"),
        (lambda d: d / "absent", "is not a folder"),
    ],
)
def test_not_a_run(tmp_path, make, match):
    with pytest.raises(InputError, match=match):
        load_run(make(tmp_path))


def test_broken_result_is_one_error(run_dir, tmp_path):
    broken = tmp_path / "run"
    broken.mkdir()
    for name in ("metrics.json", "config.yaml"):
        (broken / name).write_bytes((run_dir / name).read_bytes())
    (broken / "result.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="not a readable npz"):
        load_run(broken)
    with np.load(run_dir / "result.npz") as z:
        arrays = {k: z[k] for k in z.files if k != "joints"}
    np.savez(broken / "result.npz", **arrays)
    with pytest.raises(InputError, match="lacks joints"):
        load_run(broken)


def test_cli_errors_write_nothing(run_dir, tmp_path):
    for argv, match in [
        (["export", str(run_dir), "--format", "nope", "--out", str(tmp_path / "x")], "unknown export format 'nope'"),
        (["export", str(tmp_path), "--format", "bvh", "--out", str(tmp_path / "x")], "not a ptrack run folder"),
    ]:
        proc = subprocess.run([sys.executable, "-m", "ptrack.cli", *argv], capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2 and proc.stdout == ""
        assert proc.stderr.startswith("ptrack: error: ") and match in proc.stderr and "Traceback" not in proc.stderr
        assert not (tmp_path / "x").exists()
