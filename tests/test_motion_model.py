"""Tests for ptrack.motion.motion_model on the 7 CMU golf swings of subject 64: the time-warped resampling, PCA
(encode/decode with every component gives a swing back), the decoder's gradients (float64 gradcheck in
alpha and mu), the model file, and the bad inputs of `ptrack fit-motion` through the command line."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from ptrack.body.skeleton import Skeleton
from ptrack.cli import main
from ptrack.errors import InputError
from ptrack.motion.motion_model import (
    clip_paths,
    decode,
    dof_index,
    encode,
    fit_motion_model,
    load_motion_model,
    modelled_dofs,
    motion_vector,
    read_clips,
    resample,
    save_motion_model,
    warp_times,
)
from ptrack.pipeline.config import MotionConfig, load_config

REPO = Path(__file__).resolve().parents[1]
GOLF = REPO / "configs" / "golf_motion.yaml"
CLIPS = REPO / "configs" / "clips" / "golf.txt"


@pytest.fixture(scope="module")
def clips(cmu_dir):
    return read_clips(clip_paths([str(CLIPS)]))


@pytest.fixture(scope="module")
def model(clips):
    return fit_motion_model(clips, MotionConfig())


@pytest.fixture(scope="module")
def full_model(clips):
    return fit_motion_model(clips, MotionConfig(components=len(clips) - 1))


def test_model_shapes_and_names(model, clips):
    sk = clips[0].skeleton
    assert len(clips) == 7 and model.num_samples == 200 and model.num_components == 4
    d = len(model.dof_names)
    assert model.mean.shape == (200, d) and model.components.shape == (4, 200, d)
    assert model.skeleton_dof_names == sk.dof_names
    assert not any(n.startswith("root.") or "thumb" in n or "fingers" in n for n in model.dof_names)
    assert "lhumerus.rz" in model.dof_names and "ltibia.rx" in model.dof_names
    assert [sk.dof_names.index(n) for n in model.dof_names] == sorted(dof_index(model, sk).tolist())
    assert model.key_names == ("start", "top", "hit", "end")
    kt = model.key_times
    assert kt[0] == 0 and kt[-1] == 1 and torch.all(kt.diff() > 0)
    # variance ratios: decreasing, below 1 in all; the coefficients' stds follow them
    e = model.explained
    assert torch.all(e.diff() <= 0) and 0.5 < e.sum() < 1
    assert torch.all(model.sigma.diff() <= 0)
    flat = model.components.flatten(1)
    assert torch.allclose(flat @ flat.T, torch.eye(4, dtype=flat.dtype), atol=1e-10)


def _training_motion(model, clip):
    """A training clip resampled as the fit does: its key frames (recorded in the model) to the key times."""
    i = model.info["clips"].index(clip.name)
    q = torch.from_numpy(np.unwrap(clip.q.numpy(), axis=0))
    x = resample(clip.skeleton, q, warp_times(model.info["key_frames"][i], model.key_times.numpy(), 200))
    return torch.from_numpy(x[:, modelled_dofs(clip.skeleton, MotionConfig().exclude)])


def test_encode_decode_reproduces_a_swing(full_model, model, clips):
    for clip in (clips[0], clips[4]):
        motion = _training_motion(full_model, clip)
        shift = 2 * np.pi * torch.round((full_model.mean - motion).mean(0) / (2 * np.pi))
        motion = motion + shift  # the fit's choice of turn per dof
        alpha = encode(full_model, motion)
        assert torch.allclose(motion_vector(full_model, alpha), motion, atol=1e-9)
        # the decoder at the sample times is the motion, between them the linear interpolation
        mu = torch.linspace(0, 1, 200, dtype=torch.float64)
        got = decode(full_model, alpha.expand(200, -1), mu)
        assert torch.allclose(got, motion, atol=1e-9)
        mid = decode(full_model, alpha, (mu[10] + mu[11]) / 2)
        assert torch.allclose(mid, (motion[10] + motion[11]) / 2, atol=1e-9)
        # 4 components leave a residual, smaller than the swing's own spread about the mean
        alpha4 = encode(model, motion)
        residual = (motion_vector(model, alpha4) - motion).norm()
        assert 0 < residual < 0.8 * (motion - model.mean).norm()


def test_resample_keeps_the_captured_frames_and_interpolates(clips):
    clip = clips[0]
    times = np.arange(40, 60, dtype=np.float64)
    x = resample(clip.skeleton, clip.q, times)
    assert np.allclose(x, clip.q[40:60].numpy(), atol=1e-12)
    half = resample(clip.skeleton, clip.q, times + 0.5)
    lin = ((clip.q[40:60] + clip.q[41:61]) / 2).numpy()
    assert np.allclose(half, lin, atol=1e-3)  # slerp differs from the angles' mean only in the last digits
    assert not np.allclose(half, lin, atol=1e-12)
    warped = warp_times([10, 50, 70, 100], np.array([0.0, 0.5, 0.75, 1.0]), 5)
    assert np.allclose(warped, [10, 30, 50, 70, 100])


def test_decode_batched_and_clamped(model):
    g = torch.Generator().manual_seed(0)
    alpha = torch.randn(3, 5, 4, generator=g, dtype=torch.float64)
    mu = torch.rand(3, 5, generator=g, dtype=torch.float64)
    out = decode(model, alpha, mu)
    assert out.shape == (3, 5, len(model.dof_names))
    assert torch.allclose(out[1, 2], decode(model, alpha[1, 2], mu[1, 2]))
    assert decode(model, alpha[0, 0], mu[0]).shape == (5, len(model.dof_names))  # alpha broadcast over times
    assert torch.equal(decode(model, alpha[0, 0], torch.tensor(-0.3)), decode(model, alpha[0, 0], torch.tensor(0.0)))
    assert torch.equal(decode(model, alpha[0, 0], torch.tensor(1.7)), decode(model, alpha[0, 0], torch.tensor(1.0)))
    assert decode(model, alpha.float(), mu.float()).dtype == torch.float32
    zero = decode(model, torch.zeros(4, dtype=torch.float64), torch.tensor(0.0, dtype=torch.float64))
    assert torch.allclose(zero, model.mean[0])


def test_decode_gradcheck(model):
    g = torch.Generator().manual_seed(0)
    alpha = torch.randn(2, 4, generator=g, dtype=torch.float64, requires_grad=True)
    # away from the sample knots, where the interpolation's derivative in mu jumps
    mu = ((torch.tensor([0.13, 0.61], dtype=torch.float64) * 199).floor() + 0.4) / 199
    mu.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda a, m: decode(model, a, m), (alpha, mu), eps=1e-6, atol=1e-6)
    assert torch.autograd.gradgradcheck(lambda a, m: decode(model, a, m), (alpha, mu), eps=1e-6, atol=1e-6)


def test_save_load_round_trip(model, clips, tmp_path):
    path = save_motion_model(model, tmp_path / "sub" / "golf.npz")
    assert path.stat().st_size < 1_000_000
    back = load_motion_model(path, clips[0].skeleton)
    for f in ("dof_names", "skeleton_dof_names", "key_names"):
        assert getattr(back, f) == getattr(model, f)
    for f in ("mean", "components", "explained", "key_times", "sigma"):
        assert torch.equal(getattr(back, f), getattr(model, f))
    assert back.info["clips"] == [f"64_0{i}.amc" for i in (1, 2, 4, 5, 6, 8, 9)]
    # the trackers' reduced skeleton (fingers, thumbs, hands, toes frozen) is the same skeleton
    reduced = clips[0].skeleton.freeze(("*fingers", "*thumb", "*hand", "*toes"))
    assert load_motion_model(path, reduced).dof_names == model.dof_names
    idx = dof_index(model, reduced)
    assert [reduced.dof_names[i] for i in idx] == list(model.dof_names)


def test_load_refuses_another_skeleton(model, tmp_path, asf_64):
    path = save_motion_model(model, tmp_path / "golf.npz")
    text = asf_64.read_text()
    block = "name ltoes"
    i = text.index(block)
    j = text.index("end", i)
    other = text[:i] + text[i:j].replace("dof rx", "").replace("limits (-90.0 20.0)", "") + text[j:]
    (tmp_path / "other.asf").write_text(other)
    sk = Skeleton.from_asf(tmp_path / "other.asf")
    assert "ltoes.rx" not in sk.dof_names
    with pytest.raises(InputError, match=r"fitted on another skeleton.*'ltoes\.rx'"):
        load_motion_model(path, sk)
    with pytest.raises(InputError, match=r"no dof 'lhumerus\.rx'"):
        dof_index(model, Skeleton.from_asf(asf_64).freeze(("lhumerus",)))


def _corrupt(path: Path, how: str) -> None:
    if how == "garbage":
        path.write_bytes(b"\x00\x01not a zip at all" * 10)
    elif how == "truncated":
        path.write_bytes(path.read_bytes()[:2000])
    else:
        with np.load(path) as z:
            arrays = {k: z[k] for k in z.files}
        meta = json.loads(str(arrays["meta"]))
        if how == "no-mean":
            del arrays["mean"]
        elif how == "shape":
            arrays["components"] = arrays["components"][:, :-1]
        elif how == "nan":
            arrays["mean"][3, 3] = np.nan
        elif how == "format":
            meta["format"] = "something-else"
        elif how == "dofs":
            meta["dof_names"] = meta["dof_names"][:-1]
        elif how == "pickle":
            arrays["meta"] = np.array([{"a": 1}], dtype=object)
        if how != "pickle":
            arrays["meta"] = np.array(json.dumps(meta))
        np.savez(path, **arrays)


@pytest.mark.parametrize("how", ["garbage", "truncated", "no-mean", "shape", "nan", "format", "dofs", "pickle"])
def test_load_refuses_a_corrupt_file(model, tmp_path, how):
    path = save_motion_model(model, tmp_path / "golf.npz")
    _corrupt(path, how)
    with pytest.raises(InputError, match="is corrupt or not a motion model"):
        load_motion_model(path)


def test_fit_refuses_bad_inputs(clips):
    with pytest.raises(InputError, match="at least 2 training clips, got 1"):
        fit_motion_model(clips[:1], MotionConfig(components=1))
    with pytest.raises(InputError, match=r"'motion.components' \(3\) must be at most .* minus one \(2\)"):
        fit_motion_model(clips[:3], MotionConfig(components=3))
    still = dataclasses.replace(clips[2], name="still.amc", q=clips[2].q[:60])  # the address only
    with pytest.raises(InputError, match=r"^still\.amc: key posture"):
        fit_motion_model([clips[0], still], MotionConfig(components=1))


def test_config_section(tmp_path):
    cfg = load_config(GOLF, run=False)
    assert cfg.motion.clips == (str(CLIPS.resolve()),)
    assert cfg.motion.model_file == str((REPO / "logs" / "motion" / "golf.npz").resolve())
    assert cfg.motion.samples == 200 and cfg.motion.components == 4
    with pytest.raises(InputError, match=r"unknown config key 'motion\.sample'"):
        load_config(GOLF, ["motion.sample=3"], run=False)
    with pytest.raises(InputError, match=r"'motion\.key_postures\.end': rule refers to unknown key posture 'impact'"):
        load_config(GOLF, ["motion.key_postures={start: max speed, end: max height after impact}"], run=False)
    with pytest.raises(InputError, match=r"'motion\.components' must be >= 1"):
        load_config(GOLF, ["motion.components=0"], run=False)
    with pytest.raises(InputError, match=r"data\.asf"):
        load_config(GOLF)  # a run needs its data; fit-motion does not
    # overrides' paths are relative to the working directory
    cfg = load_config(GOLF, ["motion.clips=[a.amc, b.amc]"], cwd=tmp_path, run=False)
    assert cfg.motion.clips == (str(tmp_path / "a.amc"), str(tmp_path / "b.amc"))


# ---------------------------------------------------------------- the command line


def _cli(*argv: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "ptrack.cli", *argv], capture_output=True, text=True, timeout=300, cwd=cwd
    )


def test_cli_fit_motion(tmp_path, cmu_dir):
    out = tmp_path / "m" / "golf.npz"
    proc = _cli("fit-motion", "--out", str(out), str(GOLF), "motion.components=3", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == f"{out}\n"
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ptrack: 7 clips, 3 components explain "), lines
    assert "fitted in" in lines[0]
    model = load_motion_model(out)
    assert model.num_components == 3
    assert lines[0].count("%") == 4  # one share per component and the sum


def _fails(tmp_path: Path, *argv: str, message: str, capsys=None) -> None:
    """fit-motion with `argv` exits 2 with one error line holding `message`, and writes nothing; through a
    subprocess, or in-process (`main`) given capsys."""
    out = tmp_path / "out" / "model.npz"
    args = ["fit-motion", str(GOLF), "--out", str(out), *argv]
    if capsys is None:
        proc = _cli(*args, cwd=tmp_path)
        code, stdout, stderr = proc.returncode, proc.stdout, proc.stderr
    else:
        capsys.readouterr()
        code = main(args)
        stdout, stderr = capsys.readouterr()
    assert code == 2, stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ptrack: error: ") and message in lines[0], lines
    assert stdout == ""
    assert not (tmp_path / "out").exists()


def test_cli_bad_inputs(tmp_path, cmu_file, capsys):
    one = cmu_file("64_01.amc")
    _fails(tmp_path, f"motion.clips=[{one}]", message="at least 2 training clips, got 1")
    # a clip where the swing's postures cannot be found: the address only (the first 100 frames)
    lines = one.read_text().splitlines(keepends=True)
    end = lines.index("101\n")
    short = tmp_path / "data" / "64_99.amc"
    short.parent.mkdir()
    short.write_text("".join(lines[:end]))
    (tmp_path / "data" / "64.asf").write_text(cmu_file("64.asf").read_text())
    _fails(
        tmp_path,
        f"motion.clips=[{one}, {short}]",
        "motion.components=1",
        message="64_99.amc: key posture 'start' (rest before top) not found",
    )
    _fails(
        tmp_path,
        "motion.components=7",
        capsys=capsys,
        message="'motion.components' (7) must be at most the number of training clips minus one (6)",
    )
    _fails(
        tmp_path,
        "motion.clips=[gone.amc, gone2.amc]",
        "motion.components=1",
        capsys=capsys,
        message="training clip not found",
    )
    _fails(tmp_path, "motion.samples=1", capsys=capsys, message="'motion.samples' must be >= 2")
    _fails(tmp_path, "motion.key_postures.top=highest", capsys=capsys, message="cannot read rule 'highest'")
    (tmp_path / "file").write_text("")
    out = tmp_path / "file" / "m.npz"
    capsys.readouterr()
    assert main(["fit-motion", str(GOLF), "--out", str(out)]) == 2
    assert "is a file, not a folder" in capsys.readouterr().err
    assert main(["fit-motion", str(GOLF), "--out", str(tmp_path)]) == 2
    assert "is a folder; give a file name" in capsys.readouterr().err
