"""Tests for ptrack.body.skeleton: ASF models, AMC loading, reduced (frozen) models and Motion clips."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from ptrack.body.acclaim import parse_asf
from ptrack.body.skeleton import CMU_FPS, Motion, Skeleton, load_amc
from ptrack.errors import InputError

M_PER_UNIT = 0.0254 / 0.45  # CMU: (1/0.45) * 2.54 / 100 = 0.056444 m per ASF unit
DEG = math.pi / 180.0
REDUCE = ["*fingers", "*thumb", "*toes", "*clavicle"]
# dofs those patterns remove from a CMU skeleton: fingers 1+1, thumbs 2+2, toes 1+1, clavicles 2+2
N_REDUCED_AWAY = 12


@pytest.fixture(scope="module")
def sk(asf_64) -> Skeleton:
    return Skeleton.from_asf(asf_64)


@pytest.fixture(scope="module")
def motion(sk, amc_64_01) -> Motion:
    return sk.load_amc(amc_64_01)


@pytest.fixture(scope="module")
def q_clip(motion) -> torch.Tensor:
    """12 frames spread over the swing, float64."""
    return motion.q[::40]


# -- from_asf ----------------------------------------------------------------------------------


def test_from_asf_sizes_and_names(sk, asf_64):
    asf = parse_asf(asf_64)
    assert sk.num_joints == 31 and len(sk.joint_names) == 31
    assert sk.num_dofs == 62 and len(sk.dof_names) == 62
    assert sk.joint_names[0] == "root"
    assert set(sk.joint_names[1:]) == {b.name for b in asf.bones}
    assert sk.dof_names[:6] == ("root.tx", "root.ty", "root.tz", "root.rx", "root.ry", "root.rz")
    expected = {f"{b.name}.{d}" for b in asf.bones for d in b.dof}
    assert set(sk.dof_names[6:]) == expected and len(set(sk.dof_names)) == 62
    assert sk.name == "VICON"


def test_from_asf_parents_before_children(sk, asf_64):
    assert sk.parents[0] == -1
    assert all(0 <= p < i for i, p in enumerate(sk.parents) if i > 0)
    named = {(sk.joint_names[p], sk.joint_names[c]) for p, c in sk.bones()}
    assert named == set(parse_asf(asf_64).hierarchy)
    assert len(sk.bones()) == 30


def test_from_asf_lengths_in_metres(sk):
    assert sk.lengths[0] == 0.0
    assert sk.lengths[sk.joint_index("lfemur")] == pytest.approx(7.40817 * M_PER_UNIT, rel=1e-12)
    assert sk.lengths[sk.joint_index("lfemur")] == pytest.approx(7.40817 * 0.056444, rel=1e-5)
    assert np.all(sk.lengths[1:] > 0.0) and np.all(sk.lengths < 0.6)
    t = sk.length_tensor(dtype=torch.float64)
    assert t.shape == (31,) and t.dtype == torch.float64
    np.testing.assert_array_equal(t.numpy(), sk.lengths)


def test_joint_index(sk):
    assert sk.joint_names[sk.joint_index("head")] == "head"
    with pytest.raises(InputError, match="'tail'"):
        sk.joint_index("tail")


def test_limits_in_radians_root_unlimited(sk):
    lo, hi = sk.limits(dtype=torch.float64)
    assert lo.shape == (62,) and hi.shape == (62,) and lo.dtype == torch.float64
    assert torch.all(torch.isinf(lo[:6])) and torch.all(lo[:6] < 0) and torch.all(torch.isinf(hi[:6]) & (hi[:6] > 0))
    i = sk.dof_names.index("lfemur.rx")
    assert lo[i].item() == pytest.approx(-160 * DEG) and hi[i].item() == pytest.approx(20 * DEG)
    i = sk.dof_names.index("rtoes.rx")
    assert lo[i].item() == pytest.approx(-90 * DEG) and hi[i].item() == pytest.approx(20 * DEG)
    assert torch.all(torch.isfinite(lo[6:])) and torch.all(lo <= hi)
    assert sk.limits()[0].dtype == torch.float32


def test_from_asf_rejects_translation_bone_dof(tmp_path, asf_64):
    text = asf_64.read_bytes().decode()
    text = text.replace("dof rx\r\n    limits (-90.0 20.0)", "dof tx\r\n    limits (-1 1)", 1)
    assert "dof tx" in text
    p = tmp_path / "tdof.asf"
    p.write_bytes(text.encode())
    with pytest.raises(InputError, match=r"'tx'.*rotational"):
        Skeleton.from_asf(p)


def test_from_asf_bones_not_connected_to_root(tmp_path, asf_64):
    """A two-bone cycle has one parent per bone but never reaches the root."""
    text = asf_64.read_bytes().decode()
    text = text.replace("lhand lfingers", "lthumb lfingers")
    text = text.replace("lwrist lhand lthumb", "lwrist lhand\r\n    lfingers lthumb")
    p = tmp_path / "cycle.asf"
    p.write_bytes(text.encode())
    with pytest.raises(InputError, match=r"not connected to the root.*lfingers"):
        Skeleton.from_asf(p)


def test_from_asf_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError):
        Skeleton.from_asf(tmp_path / "none.asf")


@pytest.mark.parametrize("subject", ["02", "05", "131"])
def test_other_subjects_same_layout(cmu_file, subject, sk):
    other = Skeleton.from_asf(cmu_file(f"{subject}.asf"))
    assert other.joint_names == sk.joint_names and other.dof_names == sk.dof_names
    assert not np.allclose(other.lengths, sk.lengths)  # different people


# -- load_amc ----------------------------------------------------------------------------------


def test_load_amc_units(sk, motion, amc_64_01):
    q = motion.q
    assert q.shape == (448, 62) and q.dtype == torch.float64
    assert q[0, 0].item() == pytest.approx(-5.82914 * 0.056444, abs=1e-5)
    assert q[0, 0].item() == pytest.approx(-5.82914 * M_PER_UNIT, rel=1e-12)
    assert q[0, 1].item() == pytest.approx(17.8741 * M_PER_UNIT, rel=1e-12)
    np.testing.assert_allclose(q[0, 3:6].numpy(), np.radians([-78.4182, 86.296, -96.1138]), rtol=1e-12)
    i = sk.dof_names.index("lfemur.rx")
    np.testing.assert_allclose(q[0, i : i + 3].numpy(), np.radians([-31.3742, 5.01646, -9.07132]), rtol=1e-12)
    assert q[0, sk.dof_names.index("rfingers.rx")].item() == pytest.approx(math.radians(7.12502))
    np.testing.assert_array_equal(motion.frames, np.arange(1, 449))
    assert motion.fps == CMU_FPS == 120.0
    assert motion.times[0] == 0.0 and motion.times[-1] == pytest.approx(447 / 120)
    assert motion.path == str(amc_64_01)


def test_load_amc_function_equals_method(sk, motion, amc_64_01):
    m2 = load_amc(amc_64_01, sk)
    assert torch.equal(m2.q, motion.q)


def test_load_amc_other_subject(cmu_file):
    sk2 = Skeleton.from_asf(cmu_file("02.asf"))
    m = sk2.load_amc(cmu_file("02_01.amc"))
    assert m.q.shape == (343, 62)


def test_load_amc_wrong_skeleton(tmp_path, amc_64_01):
    """A two-bone skeleton cannot read a full-body AMC."""
    asf = (
        ":units\n length 0.45\n angle deg\n:root\n order TX TY TZ RX RY RZ\n axis XYZ\n"
        ":bonedata\n begin\n name hip\n direction 0 -1 0\n length 2\n axis 0 0 0 XYZ\n dof rx\n end\n"
        ":hierarchy\n begin\n root hip\n end\n"
    )
    p = tmp_path / "tiny.asf"
    p.write_text(asf)
    tiny = Skeleton.from_asf(p)
    assert tiny.num_joints == 2 and tiny.num_dofs == 7
    with pytest.raises(InputError, match="belong to this ASF"):
        tiny.load_amc(amc_64_01)


def test_load_amc_missing_file(sk, tmp_path):
    with pytest.raises(FileNotFoundError):
        sk.load_amc(tmp_path / "none.amc")


# -- freeze / reduced models -------------------------------------------------------------------


def test_freeze_reduces_dofs(sk):
    r = sk.freeze(REDUCE)
    assert r.num_dofs == 62 - N_REDUCED_AWAY == 50
    assert r.num_joints == sk.num_joints and r.joint_names == sk.joint_names
    assert not any(n.split(".")[0].endswith(("fingers", "thumb", "toes", "clavicle")) for n in r.dof_names)
    assert r.dof_names == tuple(n for n in sk.dof_names if n in set(r.dof_names))  # order kept
    idx = [sk.dof_names.index(n) for n in r.dof_names]
    np.testing.assert_array_equal(r.lower, sk.lower[idx])
    np.testing.assert_array_equal(r.upper, sk.upper[idx])
    assert r.limits()[0].shape == (50,)
    assert sk.num_dofs == 62  # the full model is untouched


def test_freeze_fk_equals_full_fk_with_frozen_dofs_zeroed(sk, q_clip):
    full_fk = sk.forward_kinematics(q_clip)  # fills the full model's cache first
    r = sk.freeze(REDUCE)
    q_r = r.reduce(q_clip, sk)
    assert q_r.shape == (q_clip.shape[0], 50)
    q_zeroed = q_clip.clone()
    frozen = [i for i, n in enumerate(sk.dof_names) if n not in r.dof_names]
    assert len(frozen) == N_REDUCED_AWAY
    q_zeroed[:, frozen] = 0.0
    reduced_fk, reduced_rot = r.forward_kinematics(q_r, rotations=True)
    zeroed_fk, zeroed_rot = sk.forward_kinematics(q_zeroed, rotations=True)
    torch.testing.assert_close(reduced_fk, zeroed_fk, rtol=0, atol=1e-12)
    torch.testing.assert_close(reduced_rot, zeroed_rot, rtol=0, atol=1e-12)
    # the frozen dofs do matter in this clip (clavicles, thumbs): otherwise the test proves nothing
    assert (full_fk - zeroed_fk).abs().max() > 1e-3
    torch.testing.assert_close(sk.forward_kinematics(q_clip), full_fk)  # the full model is unchanged


def test_expand_reduce_roundtrip(sk, q_clip):
    r = sk.freeze(REDUCE)
    q_r = r.reduce(q_clip, sk)
    q_full = r.expand(q_r, sk)
    assert q_full.shape == q_clip.shape and q_full.dtype == q_clip.dtype
    torch.testing.assert_close(r.reduce(q_full, sk), q_r, rtol=0, atol=0)
    torch.testing.assert_close(sk.forward_kinematics(q_full), r.forward_kinematics(q_r), rtol=0, atol=1e-12)


def test_expand_batched(sk):
    r = sk.freeze(["root.t*"])
    q_r = torch.randn(2, 3, r.num_dofs, generator=torch.Generator().manual_seed(0))
    assert r.expand(q_r, sk).shape == (2, 3, 62)
    assert torch.all(r.expand(q_r, sk)[..., :3] == 0)


def test_freeze_with_value_matches_full_model(sk, q_clip):
    r = sk.freeze(["*toes", "lfemur.rz"], value=0.3)
    assert r.num_dofs == 59
    q_set = q_clip.clone()
    for n in ("ltoes.rx", "rtoes.rx", "lfemur.rz"):
        q_set[:, sk.dof_names.index(n)] = 0.3
    torch.testing.assert_close(
        r.forward_kinematics(r.reduce(q_clip, sk)), sk.forward_kinematics(q_set), rtol=0, atol=1e-12
    )


def test_expand_fills_frozen_value(sk, q_clip):
    """`expand` documents: "Frozen dofs get their frozen value (0 unless freeze(value=...) said otherwise)",
    so the full model at the expanded pose must be the reduced model's pose."""
    r = sk.freeze(["*toes", "lfemur.rz"], value=0.3)
    q_r = r.reduce(q_clip, sk)
    q_full = r.expand(q_r, sk)
    assert q_full[:, sk.dof_names.index("lfemur.rz")].eq(0.3).all()
    torch.testing.assert_close(sk.forward_kinematics(q_full), r.forward_kinematics(q_r), rtol=0, atol=1e-12)


def test_freeze_root_translation(sk, q_clip):
    r = sk.freeze(["root.t*"])
    assert r.dof_names[:3] == ("root.rx", "root.ry", "root.rz") and r.num_dofs == 59
    q0 = q_clip.clone()
    q0[:, :3] = 0
    torch.testing.assert_close(r.forward_kinematics(q_clip[:, 3:]), sk.forward_kinematics(q0), rtol=0, atol=1e-12)
    r1 = sk.freeze(["root.ty"], value=1.5)  # the root held 1.5 m up
    joints = r1.forward_kinematics(torch.zeros(r1.num_dofs, dtype=torch.float64))
    assert joints[0].tolist() == pytest.approx([0.0, 1.5, 0.0])


def test_freeze_twice_equals_freeze_once(sk, q_clip):
    a = sk.freeze(["*fingers", "*thumb"]).freeze(["*toes", "*clavicle"])
    b = sk.freeze(REDUCE)
    assert a.dof_names == b.dof_names
    q_r = b.reduce(q_clip, sk)
    torch.testing.assert_close(a.forward_kinematics(q_r), b.forward_kinematics(q_r), rtol=0, atol=1e-12)


def test_freeze_joint_without_dofs_is_allowed(sk):
    assert sk.freeze(["lhipjoint"]).num_dofs == 62


@pytest.mark.parametrize("pattern", ["*tail", "lfemur.tx", "Head"])
def test_freeze_pattern_matching_nothing(sk, pattern):
    with pytest.raises(InputError, match=f"'{pattern.replace('*', '[*]')}'"):
        sk.freeze(["*toes", pattern])


def test_load_amc_on_reduced_model(sk, motion, amc_64_01):
    r = sk.freeze(REDUCE)
    m = r.load_amc(amc_64_01)
    assert m.q.shape == (448, 50)
    torch.testing.assert_close(m.q, r.reduce(motion.q, sk), rtol=0, atol=0)


# -- Motion ------------------------------------------------------------------------------------


def test_motion_slice_with_stride(motion):
    s = motion.slice(10, 50, stride=4)
    assert s.q.shape == (10, 62)
    torch.testing.assert_close(s.q, motion.q[10:50:4], rtol=0, atol=0)
    np.testing.assert_array_equal(s.frames, np.arange(11, 51, 4))
    assert s.fps == pytest.approx(30.0) and s.path == motion.path
    tail = motion.slice(440)
    assert tail.q.shape == (8, 62) and tail.fps == 120.0


def test_motion_slice_keeps_times(motion):
    """A strided clip keeps the real time of each frame: frames 11, 15, ... are 4/120 s apart."""
    s = motion.slice(10, 50, stride=4)
    np.testing.assert_allclose(s.times, motion.times[10:50:4] - motion.times[10], atol=1e-12)
    assert s.times[1] == pytest.approx(1 / s.fps)


@pytest.mark.parametrize("args", [(0, None, 0), (-1, None, 1), (448, None, 1), (5, 5, 1), (5, 449, 1)])
def test_motion_slice_bad_arguments(motion, args):
    start, stop, stride = args
    with pytest.raises(InputError):
        motion.slice(start, stop, stride)


def test_motion_is_frozen(motion):
    with pytest.raises(AttributeError):  # dataclasses.FrozenInstanceError
        motion.fps = 60.0  # type: ignore[misc]


def test_skeleton_validation(sk):
    with pytest.raises(InputError, match="parent"):
        replace(sk, parents=(-1, 2) + sk.parents[2:])
    with pytest.raises(InputError, match="unique"):
        replace(sk, joint_names=("root", "root") + sk.joint_names[2:])
