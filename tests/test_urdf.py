"""Tests for ptrack.urdf: URDF export of `Skeleton` models and URDF import through pytorch-kinematics."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import numpy as np
import pytest
import torch

from ptrack.errors import InputError
from ptrack.kinematics import forward_kinematics
from ptrack.skeleton import Skeleton
from ptrack.urdf import skeleton_from_urdf, skeleton_to_urdf

pk = pytest.importorskip("pytorch_kinematics")

# A 2-link arm: a revolute shoulder with a rotated origin, then a fixed wrist offset.
SHOULDER_XYZ, SHOULDER_RPY, SHOULDER_AXIS = (0.1, 0.2, 0.5), (0.3, -0.4, 0.5), (0.0, 1.0, 0.0)
WRIST_XYZ, WRIST_RPY = (0.3, 0.0, -0.1), (0.2, 0.0, 0.1)
ARM_URDF = f"""<?xml version="1.0"?>
<robot name="arm">
  <link name="base"/>
  <link name="upper">
    <visual>
      <origin xyz="0 0 0.15" rpy="0 1.2 0"/>
      <geometry><box size="0.05 0.05 0.3"/></geometry>
    </visual>
  </link>
  <link name="tip"/>
  <joint name="shoulder" type="revolute">
    <parent link="base"/>
    <child link="upper"/>
    <origin xyz="{' '.join(map(str, SHOULDER_XYZ))}" rpy="{' '.join(map(str, SHOULDER_RPY))}"/>
    <axis xyz="{' '.join(map(str, SHOULDER_AXIS))}"/>
    <limit lower="-1.0" upper="2.0" effort="1" velocity="1"/>
  </joint>
  <joint name="wrist" type="fixed">
    <parent link="upper"/>
    <child link="tip"/>
    <origin xyz="{' '.join(map(str, WRIST_XYZ))}" rpy="{' '.join(map(str, WRIST_RPY))}"/>
  </joint>
</robot>
"""


def _rx(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]])


def _ry(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])


def _rz(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def _rpy(r, p, y):
    """URDF convention: roll about x, then pitch about y, then yaw about z (fixed axes)."""
    return _rz(y) @ _ry(p) @ _rx(r)


def _arm_fk_by_hand(theta: float, t=(0.0, 0.0, 0.0), rxyz=(0.0, 0.0, 0.0)):
    """(positions (3, 3), rotations (3, 3, 3)) of base, upper, tip; the base at t with Rz Ry Rx."""
    g0 = _rz(rxyz[2]) @ _ry(rxyz[1]) @ _rx(rxyz[0])
    p0 = np.asarray(t, dtype=np.float64)
    # the shoulder axis is y: rotation about it is _ry
    g1 = g0 @ _rpy(*SHOULDER_RPY) @ _ry(theta)
    p1 = p0 + g0 @ np.asarray(SHOULDER_XYZ)
    g2 = g1 @ _rpy(*WRIST_RPY)
    p2 = p1 + g1 @ np.asarray(WRIST_XYZ)
    return np.stack([p0, p1, p2]), np.stack([g0, g1, g2])


@pytest.fixture()
def arm_path(tmp_path):
    p = tmp_path / "arm.urdf"
    p.write_text(ARM_URDF)
    return p


# -- hand-written URDF ------------------------------------------------------------------------


def test_arm_fixed_base_structure(arm_path):
    arm = Skeleton.from_urdf(arm_path, floating_base=False)
    assert arm.joint_names == ("base", "upper", "tip")
    assert arm.parents == (-1, 0, 1)
    assert arm.dof_names == ("shoulder",)
    assert arm.lower.tolist() == [-1.0] and arm.upper.tolist() == [2.0]
    assert arm.amc_layout is None


@pytest.mark.parametrize("theta", [0.0, 0.7, -1.0, 2.0])
def test_arm_fixed_base_fk_by_hand(arm_path, theta):
    arm = Skeleton.from_urdf(arm_path, floating_base=False)
    joints, rots = arm.forward_kinematics(torch.tensor([theta], dtype=torch.float64), rotations=True)
    p, g = _arm_fk_by_hand(theta)
    # pytorch-kinematics stores URDF origins in float32, so the import is float32-accurate
    np.testing.assert_allclose(joints.numpy(), p, rtol=0, atol=1e-6)
    np.testing.assert_allclose(rots.numpy(), g, rtol=0, atol=1e-6)


def test_arm_floating_base_fk_by_hand(arm_path):
    arm = Skeleton.from_urdf(arm_path, floating_base=True)
    assert arm.dof_names == ("root.tx", "root.ty", "root.tz", "root.rx", "root.ry", "root.rz", "shoulder")
    assert np.all(np.isinf(arm.lower[:6])) and arm.lower[6] == -1.0
    g = torch.Generator().manual_seed(0)
    q = torch.rand(5, 7, generator=g, dtype=torch.float64) * 2 - 1
    joints, rots = arm.forward_kinematics(q, rotations=True)
    assert joints.shape == (5, 3, 3) and rots.shape == (5, 3, 3, 3)
    jg, rg = forward_kinematics(arm, q, rotations=True, generic=True)  # the other FK implementation
    torch.testing.assert_close(jg, joints, rtol=0, atol=1e-12)
    torch.testing.assert_close(rg, rots, rtol=0, atol=1e-12)
    for b in range(5):
        qb = q[b].tolist()
        p, r = _arm_fk_by_hand(qb[6], t=qb[:3], rxyz=qb[3:6])
        np.testing.assert_allclose(joints[b].numpy(), p, rtol=0, atol=1e-6)
        np.testing.assert_allclose(rots[b].numpy(), r, rtol=0, atol=1e-6)


def test_arm_matches_pytorch_kinematics(arm_path):
    arm = Skeleton.from_urdf(arm_path, floating_base=False)
    chain = pk.build_chain_from_urdf(ARM_URDF.encode())
    th = torch.linspace(-1, 2, 7).unsqueeze(-1)
    tf = chain.forward_kinematics(th)
    joints, rots = arm.forward_kinematics(th, rotations=True)
    for i, name in enumerate(arm.joint_names):
        m = tf[name].get_matrix()
        assert (m[:, :3, 3] - joints[:, i]).abs().max() < 1e-6
        assert (m[:, :3, :3] - rots[:, i]).abs().max() < 1e-6


def test_arm_gradcheck(arm_path):
    arm = Skeleton.from_urdf(arm_path, floating_base=True)
    q = (torch.rand(2, 7, generator=torch.Generator().manual_seed(1), dtype=torch.float64) - 0.5)
    assert torch.autograd.gradcheck(lambda x: arm.forward_kinematics(x, rotations=True), (q.requires_grad_(),))


def test_continuous_joint_is_unlimited(tmp_path):
    text = ARM_URDF.replace('type="revolute"', 'type="continuous"').replace(
        '<limit lower="-1.0" upper="2.0" effort="1" velocity="1"/>', "")
    p = tmp_path / "cont.urdf"
    p.write_text(text)
    arm = Skeleton.from_urdf(p, floating_base=False)
    assert arm.dof_names == ("shoulder",)
    assert arm.lower[0] == -math.inf and arm.upper[0] == math.inf
    joints = arm.forward_kinematics(torch.tensor([0.4], dtype=torch.float64))
    np.testing.assert_allclose(joints.numpy(), _arm_fk_by_hand(0.4)[0], rtol=0, atol=1e-6)


def test_arm_roundtrip_through_to_urdf(tmp_path, arm_path):
    arm = Skeleton.from_urdf(arm_path, floating_base=True)
    p = tmp_path / "again.urdf"
    p.write_text(arm.to_urdf())
    back = Skeleton.from_urdf(p, floating_base=False)
    assert sorted(back.dof_names) == sorted(arm.dof_names)
    q = torch.rand(4, 7, generator=torch.Generator().manual_seed(2), dtype=torch.float64) - 0.5
    jb = back.forward_kinematics(q[:, [arm.dof_names.index(n) for n in back.dof_names]])
    ja = arm.forward_kinematics(q)
    idx = [back.joint_names.index(n) for n in arm.joint_names]
    torch.testing.assert_close(jb[:, idx], ja, rtol=0, atol=1e-6)


# -- unsupported and malformed URDFs ------------------------------------------------------------


def test_prismatic_joint_in_the_middle(tmp_path):
    text = ARM_URDF.replace('type="fixed"', 'type="prismatic"').replace(
        "</joint>\n</robot>", '  <axis xyz="1 0 0"/>\n    <limit lower="0" upper="1" effort="1" velocity="1"/>\n'
        "  </joint>\n</robot>")
    p = tmp_path / "prism.urdf"
    p.write_text(text)
    assert 'type="prismatic"' in p.read_text()
    with pytest.raises(InputError, match="'wrist'.*prismatic"):
        Skeleton.from_urdf(p, floating_base=False)


def test_prismatic_base_joint_along_a_diagonal(tmp_path):
    text = ARM_URDF.replace('type="revolute"', 'type="prismatic"').replace('axis xyz="0.0 1.0 0.0"',
                                                                           'axis xyz="0.6 0.8 0.0"')
    p = tmp_path / "diag.urdf"
    p.write_text(text)
    with pytest.raises(InputError, match="'shoulder'"):
        Skeleton.from_urdf(p, floating_base=False)


def test_prismatic_base_joint_is_a_root_translation(tmp_path):
    text = ARM_URDF.replace('type="revolute"', 'type="prismatic"').replace('axis xyz="0.0 1.0 0.0"',
                                                                           'axis xyz="0.0 0.0 1.0"')
    text = text.replace('rpy="0.3 -0.4 0.5"', 'rpy="0 0 0"')
    p = tmp_path / "slide.urdf"
    p.write_text(text)
    m = Skeleton.from_urdf(p, floating_base=False)
    assert m.dof_names == ("shoulder",) and m.translation_dof.tolist() == [-1, -1, 0]
    j = m.forward_kinematics(torch.tensor([0.25], dtype=torch.float64))
    np.testing.assert_allclose(j[1].numpy(), np.asarray(SHOULDER_XYZ) + [0, 0, 0.25], atol=1e-6)


def test_unsupported_joint_type(tmp_path):
    p = tmp_path / "floating.urdf"
    p.write_text(ARM_URDF.replace('type="fixed"', 'type="floating"'))
    with pytest.raises(InputError):
        Skeleton.from_urdf(p)


@pytest.mark.parametrize("text", [
    '<robot name="x"><link name="a"/><joint name="j" type="fixed"><parent link="a"/>',
    "this is not xml",
    "",
    "<robot name='x'><link name='a'/><link name='b'/><joint name='j' type='revolute'>"
    "<parent link='a'/><child link='missing'/></joint></robot>",
])
def test_malformed_urdf(tmp_path, text):
    p = tmp_path / "bad.urdf"
    p.write_text(text)
    with pytest.raises(InputError, match="bad.urdf"):
        Skeleton.from_urdf(p)


def test_missing_urdf_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.urdf"):
        Skeleton.from_urdf(tmp_path / "nope.urdf")
    with pytest.raises(FileNotFoundError):
        skeleton_from_urdf(tmp_path / "nope.urdf", floating_base=False)


# -- CMU skeletons: export and re-import -------------------------------------------------------


@pytest.fixture(scope="module")
def sk(asf_64) -> Skeleton:
    return Skeleton.from_asf(asf_64)


def test_to_urdf_is_valid_xml_with_one_joint_per_dof(sk):
    text = sk.to_urdf()
    assert text == skeleton_to_urdf(sk)
    robot = ET.fromstring(text)
    assert robot.tag == "robot" and robot.get("name") == "VICON"
    moving = [j for j in robot.iter("joint") if j.get("type") != "fixed"]
    assert sorted(j.get("name") for j in moving) == sorted(sk.dof_names)
    assert {j.get("type") for j in moving} == {"prismatic", "revolute", "continuous"}
    links = {ln.get("name") for ln in robot.iter("link")}
    assert set(sk.joint_names) <= links


def test_to_urdf_escapes_names(sk):
    from dataclasses import replace

    odd = replace(sk, name='a "quoted" & <odd> name')
    robot = ET.fromstring(odd.to_urdf())
    assert robot.get("name") == 'a "quoted" & <odd> name'


@pytest.mark.parametrize("subject,clip", [("64", "64_01"), ("05", "05_02"), ("131", "131_03")])
def test_cmu_roundtrip_reproduces_asf_fk(tmp_path, cmu_file, subject, clip):
    sk = Skeleton.from_asf(cmu_file(f"{subject}.asf"))
    p = tmp_path / f"{subject}.urdf"
    p.write_text(sk.to_urdf())
    back = Skeleton.from_urdf(p, floating_base=False)
    assert sorted(back.dof_names) == sorted(sk.dof_names)
    # limits survive by name (the URDF carries them as text)
    for n in back.dof_names:
        i, k = sk.dof_names.index(n), back.dof_names.index(n)
        if np.isfinite(sk.lower[i]):
            assert back.lower[k] == pytest.approx(sk.lower[i], abs=1e-12)
            assert back.upper[k] == pytest.approx(sk.upper[i], abs=1e-12)
    q = sk.load_amc(cmu_file(f"{clip}.amc")).q[::50]
    order = [sk.dof_names.index(n) for n in back.dof_names]
    jb, rb = back.forward_kinematics(q[:, order], rotations=True)
    ja, ra = sk.forward_kinematics(q, rotations=True)
    idx = [back.joint_names.index(n) for n in sk.joint_names]
    # float64 on both sides; pytorch-kinematics parses URDF origins in float32
    torch.testing.assert_close(jb[:, idx], ja, rtol=0, atol=1e-6)
    torch.testing.assert_close(rb[:, idx], ra, rtol=0, atol=1e-6)


def test_reduced_model_roundtrip(tmp_path, sk, amc_64_01):
    """Frozen axes held at a non-zero angle are exported as fixed rotations."""
    r = sk.freeze(["*fingers", "*thumb", "*toes", "*clavicle", "lfemur.rz"], value=0.25)
    p = tmp_path / "reduced.urdf"
    p.write_text(r.to_urdf())
    back = Skeleton.from_urdf(p, floating_base=False)
    assert sorted(back.dof_names) == sorted(r.dof_names)
    q = r.load_amc(amc_64_01).q[::60]
    jb = back.forward_kinematics(q[:, [r.dof_names.index(n) for n in back.dof_names]])
    ja = r.forward_kinematics(q)
    torch.testing.assert_close(jb[:, [back.joint_names.index(n) for n in r.joint_names]], ja, rtol=0, atol=1e-6)


def test_roundtrip_with_the_default_arguments(tmp_path, sk, amc_64_01):
    p = tmp_path / "64.urdf"
    p.write_text(sk.to_urdf())
    back = Skeleton.from_urdf(p)  # the file moves its own base: no second floating base
    assert sorted(back.dof_names) == sorted(sk.dof_names)
    q = sk.load_amc(amc_64_01).q[::60]
    jb = back.forward_kinematics(q[:, [sk.dof_names.index(n) for n in back.dof_names]])
    torch.testing.assert_close(jb[:, [back.joint_names.index(n) for n in sk.joint_names]], sk.forward_kinematics(q),
                               rtol=0, atol=1e-6)


def test_default_is_a_floating_base_for_a_fixed_arm(arm_path):
    assert Skeleton.from_urdf(arm_path).dof_names == Skeleton.from_urdf(arm_path, floating_base=True).dof_names
