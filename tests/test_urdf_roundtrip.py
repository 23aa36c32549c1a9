"""`Skeleton.from_urdf(sk.to_urdf())` gives `sk` back: the links `to_urdf` adds between a joint's
rotation axes (and its base link `world`) are merged again, so the same joints, parents, offsets,
dofs, axes, limits and forward kinematics come back. Also: the merge of bare links in URDF files
from elsewhere (`collapse=True`) and the one-joint-per-link form (`collapse=False`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from ptrack.body.skeleton import Skeleton

REPO = Path(__file__).resolve().parents[1]
BUNDLED_ASF = REPO / "ptrack" / "data" / "10.asf"
CORPUS_DIR = REPO / "tests" / "data" / "urdf"


def _driven_axes(sk: Skeleton, i: int) -> list[tuple[int, float, float, np.ndarray]]:
    """Joint i's slots that move (driven or held at a non-zero angle), in order: (dof, scale, angle, axis)."""
    out = []
    for k in range(3):
        d = int(sk.axis_dof[i, k])
        if d >= 0 or sk.frozen_axes[i, k] != 0.0:
            out.append((d, float(sk.axis_scale[i, k]) if d >= 0 else 0.0, float(sk.frozen_axes[i, k]), sk.axes[i, k]))
    return out


def _assert_same_model(a: Skeleton, b: Skeleton, fk_rows: torch.Tensor) -> None:
    """b is a: names, tree, dofs, limits, offsets, rest rotations, moving axes in order, and FK on
    the poses `fk_rows` (N, D) in float64 (to 1e-12 m) and float32 (to 1e-6 m)."""
    assert b.joint_names == a.joint_names
    assert b.parents == a.parents
    assert b.dof_names == a.dof_names
    np.testing.assert_array_equal(b.translation_dof, a.translation_dof)
    np.testing.assert_array_equal(b.lower, a.lower)  # written with 17 digits: exact
    np.testing.assert_array_equal(b.upper, a.upper)
    np.testing.assert_allclose(b.lengths, a.lengths, rtol=1e-14, atol=0)
    tol = dict(rtol=0, atol=1e-14)
    np.testing.assert_allclose(b.lengths[:, None] * b.offset_parent, a.lengths[:, None] * a.offset_parent, **tol)
    np.testing.assert_allclose(b.lengths[:, None] * b.offset_local, a.lengths[:, None] * a.offset_local, **tol)
    np.testing.assert_allclose(b.root_position, a.root_position, **tol)
    np.testing.assert_allclose(b.rest_rotation, a.rest_rotation, **tol)
    np.testing.assert_array_equal(b.slide_dof, a.slide_dof)
    np.testing.assert_allclose(b.slide_axis, a.slide_axis, **tol)
    for i in range(a.num_joints):
        sa, sb = _driven_axes(a, i), _driven_axes(b, i)
        assert [s[:2] for s in sb] == [s[:2] for s in sa], a.joint_names[i]
        for (_, _, ang_a, ax_a), (_, _, ang_b, ax_b) in zip(sa, sb):
            # a slot held at an angle is written as a fixed rotation: its axis may come back negated
            sign = 1.0 if np.dot(ax_a, ax_b) > 0 else -1.0
            assert sign * ang_b == pytest.approx(ang_a, abs=1e-13)
            np.testing.assert_allclose(sign * ax_b, ax_a, rtol=0, atol=1e-14)
    q = fk_rows.to(torch.float64)
    ja, ra = a.forward_kinematics(q, rotations=True)
    jb, rb = b.forward_kinematics(q, rotations=True)
    torch.testing.assert_close(jb, ja, rtol=0, atol=1e-12)
    torch.testing.assert_close(rb, ra, rtol=0, atol=1e-12)
    torch.testing.assert_close(b.forward_kinematics(q.float()), a.forward_kinematics(q.float()), rtol=0, atol=1e-6)


def _poses(sk: Skeleton, n: int = 6, seed: int = 0) -> torch.Tensor:
    """(n, D) poses within the limits (unlimited: angles in [-pi, pi], translations in [-1, 1] m)."""
    rng = np.random.default_rng(seed)
    span = np.where(sk.angular_dofs(), np.pi, 1.0)
    lo = np.where(np.isfinite(sk.lower), sk.lower, -span)
    hi = np.where(np.isfinite(sk.upper), sk.upper, span)
    return torch.tensor(rng.uniform(lo, hi, size=(n, sk.num_dofs)))


def test_bundled_skeleton_comes_back_as_it_was():
    sk = Skeleton.from_asf(BUNDLED_ASF)
    back = Skeleton.from_urdf(sk.to_urdf())
    assert back.num_joints == sk.num_joints == 31
    _assert_same_model(sk, back, _poses(sk))


@pytest.mark.parametrize("limits", ["asf", "data"])
def test_cmu_skeleton_with_limits_comes_back_as_it_was(tmp_path, cmu_file, limits):
    sk = Skeleton.from_asf(cmu_file("64.asf")).with_limits(limits)
    assert np.isfinite(sk.lower).sum() > 20  # limits to carry
    p = tmp_path / "64.urdf"
    p.write_text(sk.to_urdf())
    back = Skeleton.from_urdf(p)
    q = sk.load_amc(cmu_file("64_01.amc")).q[::200]
    _assert_same_model(sk, back, torch.cat([q, _poses(sk)]))
    assert back.name == "64"  # a file is named after its stem


@pytest.mark.parametrize("value", [0.25, -3.1])
def test_reduced_model_comes_back_with_its_frozen_slots(cmu_file, value):
    """Slots held at a non-zero angle (written as fixed rotations) come back as held slots."""
    sk = Skeleton.from_asf(cmu_file("64.asf")).freeze(["*fingers", "*thumb", "lfemur.rz", "rradius"], value=value)
    back = Skeleton.from_urdf(sk.to_urdf())
    _assert_same_model(sk, back, _poses(sk))


def test_axis_angle_of_a_fixed_rotation():
    """The angle and axis of a fixed joint's rotation, to rounding at any angle (0 to pi)."""
    from ptrack.body.rotations import axis_angle_matrix, matrix_to_axis_angle_np

    rng = np.random.default_rng(0)
    for angle in (0.0, 1e-9, 0.3, 2.999, 3.0, 3.1, np.pi - 1e-7, np.pi):
        for _ in range(10):
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            r = axis_angle_matrix(torch.tensor(axis), torch.tensor(angle, dtype=torch.float64)).numpy()
            b, a = matrix_to_axis_angle_np(r)
            assert 0.0 <= a <= np.pi and abs(a - angle) < 1e-7
            back = axis_angle_matrix(torch.tensor(b), torch.tensor(a, dtype=torch.float64)).numpy()
            np.testing.assert_allclose(back, r, rtol=0, atol=1e-14)


def test_the_fast_forward_kinematics_path_is_kept():
    """The merged joints keep a (z, y, x) frame of axes, so FK takes the closed form as before."""
    from ptrack.body.kinematics import _plan

    sk = Skeleton.from_asf(BUNDLED_ASF)
    back = Skeleton.from_urdf(sk.to_urdf())
    assert _plan(back, torch.float64, torch.device("cpu")).closed_form


@pytest.mark.parametrize("path", sorted(CORPUS_DIR.rglob("*.urdf")), ids=lambda p: p.name)
def test_urdf_models_come_back_as_they_were(path):
    """Models read from the URDF files of tests/data/urdf (prismatic joints, mimic joints, a
    floating base or not)."""
    for floating in (False, True):
        sk = Skeleton.from_urdf(path, floating_base=floating)
        back = Skeleton.from_urdf(sk.to_urdf())
        _assert_same_model(sk, back, _poses(sk))


def test_one_joint_per_link_on_request():
    sk = Skeleton.from_asf(BUNDLED_ASF)
    full = Skeleton.from_urdf(sk.to_urdf(), collapse=False)
    assert full.num_joints == 124 and full.joint_names[0] == "world"
    assert set(sk.joint_names) < set(full.joint_names)
    q = _poses(sk)
    idx = [full.joint_names.index(n) for n in sk.joint_names]
    torch.testing.assert_close(full.forward_kinematics(q)[:, idx], sk.forward_kinematics(q), rtol=0, atol=1e-12)


def test_other_files_keep_one_joint_per_link_unless_asked():
    """A file ptrack did not write: every link is a joint by default; `collapse=True` merges bare
    links that have one child, with the same FK at the links that remain."""
    arm = """<robot name="arm">
      <link name="base"/><link name="wrist_yaw"/><link name="wrist_pitch"/>
      <link name="hand"><visual><geometry><box size="0.1 0.1 0.1"/></geometry></visual></link>
      <link name="tool"/>
      <joint name="yaw" type="revolute"><parent link="base"/><child link="wrist_yaw"/>
        <origin xyz="0.1 0.2 0.3" rpy="0.1 0.2 0.3"/><axis xyz="0 0 1"/><limit lower="-1" upper="1"/></joint>
      <joint name="pitch" type="revolute"><parent link="wrist_yaw"/><child link="wrist_pitch"/>
        <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 1 0"/><limit lower="-1" upper="1"/></joint>
      <joint name="roll" type="continuous"><parent link="wrist_pitch"/><child link="hand"/>
        <origin xyz="0 0 0" rpy="0.3 0 0"/><axis xyz="1 0 0"/></joint>
      <joint name="tip" type="fixed"><parent link="hand"/><child link="tool"/>
        <origin xyz="0 0 0.2" rpy="0 0 0"/></joint>
    </robot>"""
    every = Skeleton.from_urdf(arm, floating_base=False)
    assert every.joint_names == ("base", "wrist_yaw", "wrist_pitch", "hand", "tool")
    merged = Skeleton.from_urdf(arm, floating_base=False, collapse=True)
    assert merged.joint_names == ("base", "hand", "tool")  # a leaf and a link with a visual stay
    assert merged.dof_names == every.dof_names
    q = _poses(every)
    idx = [every.joint_names.index(n) for n in merged.joint_names]
    for a, b in zip(merged.forward_kinematics(q, rotations=True), every.forward_kinematics(q, rotations=True)):
        torch.testing.assert_close(a, b[:, idx], rtol=0, atol=1e-12)
    # a translation between two rotations does not fit one joint: that link stays
    offset = arm.replace(
        '<origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 1 0"/>', '<origin xyz="0 0.1 0"/><axis xyz="0 1 0"/>'
    )
    assert Skeleton.from_urdf(offset, floating_base=False, collapse=True).joint_names == (
        "base",
        "wrist_yaw",
        "hand",
        "tool",
    )
