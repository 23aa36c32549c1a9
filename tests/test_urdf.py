"""Tests for ptrack.body.urdf: URDF import (ptrack's own reader) and export of `Skeleton` models, checked
by hand, against yourdfpy (an independent reader, a test-only dependency) on a corpus of URDF files
that others wrote (tests/data/urdf, see its README), and through round trips."""

from __future__ import annotations

import contextlib
import io
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import torch

from ptrack.body.kinematics import forward_kinematics
from ptrack.body.rotations import euler_matrix_np
from ptrack.body.skeleton import Skeleton
from ptrack.body.urdf import (
    UNLIMITED_PRISMATIC,
    parse_urdf,
    skeleton_from_urdf,
    skeleton_to_urdf,
)
from ptrack.errors import InputError

try:
    import yourdfpy
except ImportError:  # a test-only dependency: pip install -e ".[test]"
    yourdfpy = None
needs_yourdfpy = pytest.mark.skipif(yourdfpy is None, reason="yourdfpy is not installed (pip install -e '.[test]')")

CORPUS_DIR = Path(__file__).parent / "data" / "urdf"
CORPUS = sorted(CORPUS_DIR.rglob("*.urdf"))

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
    <origin xyz="{" ".join(map(str, SHOULDER_XYZ))}" rpy="{" ".join(map(str, SHOULDER_RPY))}"/>
    <axis xyz="{" ".join(map(str, SHOULDER_AXIS))}"/>
    <limit lower="-1.0" upper="2.0" effort="1" velocity="1"/>
  </joint>
  <joint name="wrist" type="fixed">
    <parent link="upper"/>
    <child link="tip"/>
    <origin xyz="{" ".join(map(str, WRIST_XYZ))}" rpy="{" ".join(map(str, WRIST_RPY))}"/>
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
    np.testing.assert_allclose(joints.numpy(), p, rtol=0, atol=1e-12)
    np.testing.assert_allclose(rots.numpy(), g, rtol=0, atol=1e-12)


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
        np.testing.assert_allclose(joints[b].numpy(), p, rtol=0, atol=1e-12)
        np.testing.assert_allclose(rots[b].numpy(), r, rtol=0, atol=1e-12)


def test_arm_matches_pytorch_kinematics(arm_path):
    pk = pytest.importorskip("pytorch_kinematics")
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
    q = torch.rand(2, 7, generator=torch.Generator().manual_seed(1), dtype=torch.float64) - 0.5
    assert torch.autograd.gradcheck(lambda x: arm.forward_kinematics(x, rotations=True), (q.requires_grad_(),))


def test_continuous_joint_is_unlimited(tmp_path):
    text = ARM_URDF.replace('type="revolute"', 'type="continuous"').replace(
        '<limit lower="-1.0" upper="2.0" effort="1" velocity="1"/>', ""
    )
    p = tmp_path / "cont.urdf"
    p.write_text(text)
    arm = Skeleton.from_urdf(p, floating_base=False)
    assert arm.dof_names == ("shoulder",)
    assert arm.lower[0] == -math.inf and arm.upper[0] == math.inf
    joints = arm.forward_kinematics(torch.tensor([0.4], dtype=torch.float64))
    np.testing.assert_allclose(joints.numpy(), _arm_fk_by_hand(0.4)[0], rtol=0, atol=1e-12)


def test_arm_roundtrip_through_to_urdf(tmp_path, arm_path):
    arm = Skeleton.from_urdf(arm_path, floating_base=True)
    p = tmp_path / "again.urdf"
    p.write_text(arm.to_urdf())
    back = Skeleton.from_urdf(p)
    assert sorted(back.dof_names) == sorted(arm.dof_names)
    q = torch.rand(4, 7, generator=torch.Generator().manual_seed(2), dtype=torch.float64) - 0.5
    jb = back.forward_kinematics(q[:, [arm.dof_names.index(n) for n in back.dof_names]])
    ja = arm.forward_kinematics(q)
    idx = [back.joint_names.index(n) for n in arm.joint_names]
    torch.testing.assert_close(jb[:, idx], ja, rtol=0, atol=1e-12)


# -- unsupported and malformed URDFs ------------------------------------------------------------


def test_unsupported_joint_type(tmp_path):
    p = tmp_path / "floating.urdf"
    p.write_text(ARM_URDF.replace('type="fixed"', 'type="floating"'))
    with pytest.raises(InputError):
        Skeleton.from_urdf(p)


@pytest.mark.parametrize(
    "text",
    [
        '<robot name="x"><link name="a"/><joint name="j" type="fixed"><parent link="a"/>',
        "this is not xml",
        "",
        "<robot name='x'><link name='a'/><link name='b'/><joint name='j' type='revolute'>"
        "<parent link='a'/><child link='missing'/></joint></robot>",
    ],
)
def test_malformed_urdf(tmp_path, text):
    p = tmp_path / "bad.urdf"
    p.write_text(text)
    with pytest.raises(InputError, match=r"bad\.urdf"):
        Skeleton.from_urdf(p)


def test_missing_urdf_file(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"nope\.urdf"):
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
    torch.testing.assert_close(jb[:, idx], ja, rtol=0, atol=1e-9)
    torch.testing.assert_close(rb[:, idx], ra, rtol=0, atol=1e-9)


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
    torch.testing.assert_close(jb[:, [back.joint_names.index(n) for n in r.joint_names]], ja, rtol=0, atol=1e-9)


def test_roundtrip_with_the_default_arguments(tmp_path, sk, amc_64_01):
    p = tmp_path / "64.urdf"
    p.write_text(sk.to_urdf())
    back = Skeleton.from_urdf(p)  # the file moves its own base: no second floating base
    assert sorted(back.dof_names) == sorted(sk.dof_names)
    q = sk.load_amc(amc_64_01).q[::60]
    jb = back.forward_kinematics(q[:, [sk.dof_names.index(n) for n in back.dof_names]])
    torch.testing.assert_close(
        jb[:, [back.joint_names.index(n) for n in sk.joint_names]], sk.forward_kinematics(q), rtol=0, atol=1e-9
    )


def test_default_is_a_floating_base_for_a_fixed_arm(arm_path):
    assert Skeleton.from_urdf(arm_path).dof_names == Skeleton.from_urdf(arm_path, floating_base=True).dof_names


# -- helpers: an independent reader -------------------------------------------------------------


def _load_yourdfpy(path):
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        return yourdfpy.URDF.load(
            str(path), load_meshes=False, build_collision_scene_graph=False, load_collision_meshes=False
        )


def _random_q(sk: Skeleton, rng: np.random.Generator) -> np.ndarray:
    """A pose within the limits (unlimited angles in [-pi, pi], unlimited translations in [-1, 1] m)."""
    span = np.where(sk.angular_dofs(), math.pi, 1.0)
    lo = np.where(np.isfinite(sk.lower), sk.lower, -span)
    hi = np.where(np.isfinite(sk.upper), sk.upper, span)
    return rng.uniform(lo, hi)


def _fk_error_vs_yourdfpy(sk: Skeleton, path, n: int = 3, seed: int = 0, exported: bool = False) -> float:
    """Largest difference (metres, and rotation matrix entries) between ptrack's FK of `sk` and
    yourdfpy's FK of the file at `path` on n random poses in float64. `sk`'s joints are the file's
    links; with a floating base that the file lacks (not `exported` by ptrack), yourdfpy's frames
    are moved by the root's pose."""
    u = _load_yourdfpy(path)
    rng = np.random.default_rng(seed)
    worst = 0.0
    for _ in range(n):
        q = _random_q(sk, rng)
        joints, rots = sk.forward_kinematics(torch.tensor(q, dtype=torch.float64), rotations=True)
        u.update_cfg({name: q[sk.dof_names.index(name)] for name in u.actuated_joint_names})
        g, t = np.eye(3), np.zeros(3)
        if "root.tx" in sk.dof_names and not exported:
            k = sk.dof_names.index("root.tx")
            t, g = q[k : k + 3], euler_matrix_np(tuple(q[k + 3 : k + 6]), "XYZ")
        for i, link in enumerate(sk.joint_names):
            m = u.get_transform(frame_to=link, frame_from=u.base_link)
            worst = max(
                worst, np.abs(g @ m[:3, 3] + t - joints[i].numpy()).max(), np.abs(g @ m[:3, :3] - rots[i].numpy()).max()
            )
    return worst


def _roundtrip_error(sk: Skeleton, back: Skeleton, n: int = 3, seed: int = 1) -> float:
    """Largest FK difference between `sk` and `back` (its re-import) on n random poses, by name."""
    assert sorted(back.dof_names) == sorted(sk.dof_names)
    rng = np.random.default_rng(seed)
    order = [sk.dof_names.index(name) for name in back.dof_names]
    idx = [back.joint_names.index(name) for name in sk.joint_names]
    q = torch.tensor(np.stack([_random_q(sk, rng) for _ in range(n)]), dtype=torch.float64)
    ja, ra = sk.forward_kinematics(q, rotations=True)
    jb, rb = back.forward_kinematics(q[:, order], rotations=True)
    return max((jb[:, idx] - ja).abs().max().item(), (rb[:, idx] - ra).abs().max().item())


def _write(tmp_path, text: str, name: str = "m.urdf"):
    p = tmp_path / name
    p.write_text(text)
    return p


def _robot(*joints: str, links=None) -> str:
    """A URDF of the given <joint> elements; links are every parent and child named in them."""
    import re

    names = links or list(dict.fromkeys(re.findall(r'link="([^"]+)"', "".join(joints))))
    return "<robot name='t'>" + "".join(f"<link name='{n}'/>" for n in names) + "".join(joints) + "</robot>"


def _joint(name, kind, parent, child, xyz="0 0 0", rpy="0 0 0", axis="1 0 0", extra=""):
    return (
        f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
        f'<origin xyz="{xyz}" rpy="{rpy}"/><axis xyz="{axis}"/>{extra}</joint>'
    )


# -- the corpus: URDF files that others wrote ----------------------------------------------------


def test_corpus_is_there():
    assert len(CORPUS) >= 25
    assert (CORPUS_DIR / "README.md").is_file()


@needs_yourdfpy
@pytest.mark.parametrize("path", CORPUS, ids=lambda p: str(p.relative_to(CORPUS_DIR)))
@pytest.mark.parametrize("floating", [False, True])
def test_corpus_fk_matches_yourdfpy(path, floating):
    """Every corpus file imports, and ptrack's FK equals yourdfpy's to 1e-4 mm in float64."""
    sk = Skeleton.from_urdf(path, floating_base=floating)
    assert _fk_error_vs_yourdfpy(sk, path) < 1e-7


@pytest.mark.parametrize("path", CORPUS, ids=lambda p: str(p.relative_to(CORPUS_DIR)))
def test_corpus_roundtrip(tmp_path, path):
    """to_urdf, then from_urdf with the default arguments (and read by yourdfpy), agree to 1e-6 mm."""
    for floating in (False, True):
        sk = Skeleton.from_urdf(path, floating_base=floating)
        out = _write(tmp_path, sk.to_urdf(), f"back_{floating}.urdf")
        assert _roundtrip_error(sk, Skeleton.from_urdf(out)) < 1e-9
        if yourdfpy is not None:
            assert _fk_error_vs_yourdfpy(sk, out, exported=True) < 1e-9


def test_import_is_quiet(capfd, caplog):
    """No 'Unknown tag' lines or other chatter on stdout/stderr, no log records for a clean file."""
    for path in CORPUS:
        Skeleton.from_urdf(path)
    out, err = capfd.readouterr()
    assert out == "" and err == ""
    assert not [r for r in caplog.records if r.name.startswith("ptrack")]


# -- defect 1: prismatic joints anywhere, with their limits ---------------------------------------

LIFT = (
    _joint("base_to_wheel", "continuous", "base", "wheel", xyz="0.1 0 0", axis="0 1 0")
    + _joint("torso_fixed", "fixed", "base", "torso_fixed_link", xyz="-0.06 0 0.2")
    + _joint(
        "torso_lift",
        "prismatic",
        "torso_fixed_link",
        "torso",
        xyz="0 0 0.6",
        rpy="0 0 0.4",
        axis="0 0 1",
        extra='<limit lower="0" upper="0.35" effort="1" velocity="1"/>',
    )
    + _joint(
        "head",
        "revolute",
        "torso",
        "head_link",
        xyz="0.2 0 0.3",
        axis="0 1 0",
        extra='<limit lower="-1" upper="1" effort="1" velocity="1"/>',
    )
    + _joint(
        "finger",
        "prismatic",
        "head_link",
        "finger_link",
        xyz="0.05 0 0",
        axis="0 0.6 0.8",
        extra='<limit lower="-0.02" upper="0.04" effort="1" velocity="1"/>',
    )
)


def test_prismatic_torso_lift_moves_only_its_subtree(tmp_path):
    """TIAGo's torso lift: only the links above it move, by the lift along its axis."""
    m = Skeleton.from_urdf(_write(tmp_path, _robot(LIFT)), floating_base=False)
    assert m.dof_names == ("base_to_wheel", "torso_lift", "head", "finger")
    assert m.translation_dof.tolist() == [-1, -1, -1]
    q0 = torch.zeros(4, dtype=torch.float64)
    q1 = q0.clone()
    q1[1] = 0.3
    moved = (m.forward_kinematics(q1) - m.forward_kinematics(q0)).norm(dim=-1)
    for name in ("base", "wheel", "torso_fixed_link"):
        assert moved[m.joint_index(name)] == 0.0
    for name in ("torso", "head_link", "finger_link"):
        assert moved[m.joint_index(name)].item() == pytest.approx(0.3, abs=1e-12)


def test_prismatic_limits_are_kept(tmp_path):
    m = Skeleton.from_urdf(_write(tmp_path, _robot(LIFT)), floating_base=False)
    assert (m.lower[1], m.upper[1]) == (0.0, 0.35)
    assert (m.lower[3], m.upper[3]) == (-0.02, 0.04)
    assert m.lower[0] == -math.inf and m.upper[0] == math.inf


@needs_yourdfpy
@pytest.mark.parametrize("floating", [False, True])
def test_prismatic_joints_match_yourdfpy(tmp_path, floating):
    p = _write(tmp_path, _robot(LIFT))
    assert _fk_error_vs_yourdfpy(Skeleton.from_urdf(p, floating_base=floating), p, n=5) < 1e-12


def test_prismatic_gradients(tmp_path):
    """Slides: the analytical backward of the FK equals finite differences (float64 gradcheck)."""
    m = Skeleton.from_urdf(_write(tmp_path, _robot(LIFT)), floating_base=True)
    q = torch.rand(3, m.num_dofs, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda x: m.forward_kinematics(x), (q.requires_grad_(),))
    assert torch.autograd.gradcheck(lambda x: m.forward_kinematics(x, rotations=True), (q,))
    j1 = m.forward_kinematics(q)
    j2 = forward_kinematics(m, q, generic=True)
    torch.testing.assert_close(j1, j2, rtol=0, atol=1e-12)


def test_a_finger_slide_with_a_floating_base(tmp_path):
    """A prismatic finger does not 'move the base': floating_base=True and the default both float."""
    p = _write(tmp_path, _robot(LIFT))
    m = Skeleton.from_urdf(p, floating_base=True)
    assert m.dof_names[:6] == ("root.tx", "root.ty", "root.tz", "root.rx", "root.ry", "root.rz")
    assert Skeleton.from_urdf(p).dof_names == m.dof_names


def test_freezing_a_slide(tmp_path):
    m = Skeleton.from_urdf(_write(tmp_path, _robot(LIFT)), floating_base=False)
    r = m.freeze(["torso_lift"], value=0.2)
    q = torch.tensor([0.3, 0.2, 0.5, 0.01], dtype=torch.float64)
    torch.testing.assert_close(r.forward_kinematics(r.reduce(q, m)), m.forward_kinematics(q), rtol=0, atol=1e-12)


# -- defect 2: continuous joints are unlimited ---------------------------------------------------


def test_continuous_joint_with_a_limit_element_is_unlimited(tmp_path):
    """A continuous joint with <limit effort velocity> (no lower/upper) is unlimited, and is
    re-exported as continuous."""
    text = _robot(_joint("spin", "continuous", "a", "b", axis="0 0 1", extra='<limit effort="10" velocity="3"/>'))
    m = Skeleton.from_urdf(_write(tmp_path, text), floating_base=False)
    assert m.lower.tolist() == [-math.inf] and m.upper.tolist() == [math.inf]
    robot = ET.fromstring(m.to_urdf())
    assert [j.get("type") for j in robot.iter("joint") if j.get("name") == "spin"] == ["continuous"]


def test_pybullet_unlimited_convention(tmp_path):
    """pybullet writes lower > upper (e.g. lower=1 upper=-1) for an unlimited joint."""
    text = _robot(
        _joint("r", "revolute", "a", "b", extra='<limit lower="1" upper="-1" effort="1" velocity="1"/>'),
        _joint("s", "prismatic", "b", "c", extra='<limit lower="1" upper="-1" effort="1" velocity="1"/>'),
    )
    m = Skeleton.from_urdf(_write(tmp_path, text), floating_base=False)
    assert np.all(m.lower == -math.inf) and np.all(m.upper == math.inf)


# -- defect 3: a model whose root link is 'world' --------------------------------------------------


def test_export_of_a_model_rooted_at_world(tmp_path):
    """UR, xArm7 and Z1 root their tree at a link named 'world': the export has unique links, one
    root, and reads back (ptrack, and yourdfpy when installed)."""
    text = _robot(
        _joint("world_joint", "fixed", "world", "base_link", xyz="0 0 0.1"),
        _joint(
            "shoulder",
            "revolute",
            "base_link",
            "upper",
            xyz="0 0 0.2",
            axis="0 0 1",
            extra='<limit lower="-3" upper="3" effort="1" velocity="1"/>',
        ),
    )
    for floating in (False, True):
        m = Skeleton.from_urdf(_write(tmp_path, text), floating_base=floating)
        assert m.joint_names[0] == "world"
        out = m.to_urdf()
        model = parse_urdf(out)
        assert len(model.links) == len(set(model.links))
        p = _write(tmp_path, out, "back.urdf")
        assert _roundtrip_error(m, Skeleton.from_urdf(p)) < 1e-12
        if yourdfpy is not None:
            assert _fk_error_vs_yourdfpy(m, p, exported=True) < 1e-12


# -- defect 4: rotations at pitch +-pi/2 -----------------------------------------------------------


@pytest.mark.parametrize("pitch", [math.pi / 2, -math.pi / 2, 1.5707963, math.pi / 2 + 1e-9])
def test_export_at_pitch_half_pi(tmp_path, pitch):
    """Origins at the gimbal lock of URDF's roll-pitch-yaw export exactly (they were off by up to
    180 degrees, 707 mm on this arm)."""
    text = _robot(
        _joint(
            "j",
            "revolute",
            "a",
            "b",
            xyz="0.2 0.3 0.4",
            rpy=f"0.3 {pitch!r} -0.7",
            axis="0 1 0",
            extra='<limit lower="-2" upper="2" effort="1" velocity="1"/>',
        ),
        _joint("f", "fixed", "b", "c", xyz="0.5 0 0", rpy=f"-1.1 {-pitch!r} 0.2"),
    )
    m = Skeleton.from_urdf(_write(tmp_path, text), floating_base=False)
    p = _write(tmp_path, m.to_urdf(), "back.urdf")
    assert _roundtrip_error(m, Skeleton.from_urdf(p)) < 1e-12
    if yourdfpy is not None:
        assert _fk_error_vs_yourdfpy(m, p, exported=True) < 1e-12


# -- defect 5: mimic joints ------------------------------------------------------------------------

MIMIC = (
    _joint(
        "lead",
        "revolute",
        "base",
        "l1",
        xyz="0 0 0.1",
        axis="0 0 1",
        extra='<limit lower="-1" upper="1" effort="1" velocity="1"/>',
    )
    + _joint(
        "follow",
        "revolute",
        "base",
        "f1",
        xyz="0.1 0 0",
        axis="0 1 0",
        extra='<limit lower="-3" upper="3" effort="1" velocity="1"/><mimic joint="lead" multiplier="-2" offset="0.3"/>',
    )
    + _joint(
        "follow2",
        "continuous",
        "f1",
        "f2",
        xyz="0.1 0 0",
        axis="1 0 0",
        extra='<mimic joint="lead" multiplier="0.5" offset="-0.1"/>',
    )
    + _joint(
        "grip",
        "prismatic",
        "l1",
        "g1",
        xyz="0 0.05 0",
        axis="0 1 0",
        extra='<limit lower="0" upper="0.04" effort="1" velocity="1"/>',
    )
    + _joint(
        "grip2",
        "prismatic",
        "l1",
        "g2",
        xyz="0 -0.05 0",
        axis="0 -1 0",
        extra='<limit lower="0" upper="0.04" effort="1" velocity="1"/><mimic joint="grip" offset="0.01"/>',
    )
)


def test_mimic_joints_follow_their_leader(tmp_path):
    m = Skeleton.from_urdf(_write(tmp_path, _robot(MIMIC)), floating_base=False)
    assert m.dof_names == ("lead", "grip")  # mimic joints have no dof of their own
    q = torch.tensor([0.4, 0.03], dtype=torch.float64)
    j, r = m.forward_kinematics(q, rotations=True)
    follow = -2 * 0.4 + 0.3
    np.testing.assert_allclose(r[m.joint_index("f1")].numpy(), _ry(follow), atol=1e-12)
    np.testing.assert_allclose(r[m.joint_index("f2")].numpy(), _ry(follow) @ _rx(0.5 * 0.4 - 0.1), atol=1e-12)
    g1, g2 = j[m.joint_index("g1")].numpy(), j[m.joint_index("g2")].numpy()
    np.testing.assert_allclose(g1 - g2, _rz(0.4) @ np.array([0, 0.1 + 0.03 + 0.03 + 0.01, 0]), atol=1e-12)


def test_a_chain_of_mimics(tmp_path):
    """c mimics b, which mimics a: q_c = 0.5 (-2 q_a + 0.3) - 0.1 (yourdfpy would hold c at its offset)."""
    lim = '<limit lower="-3" upper="3" effort="1" velocity="1"/>'
    text = _robot(
        _joint("a", "revolute", "l0", "l1", axis="0 0 1", extra=lim),
        _joint(
            "b", "revolute", "l1", "l2", axis="0 0 1", extra=lim + '<mimic joint="a" multiplier="-2" offset="0.3"/>'
        ),
        _joint(
            "c", "revolute", "l2", "l3", axis="0 0 1", extra=lim + '<mimic joint="b" multiplier="0.5" offset="-0.1"/>'
        ),
    )
    m = Skeleton.from_urdf(_write(tmp_path, text), floating_base=False)
    assert m.dof_names == ("a",)
    r = m.forward_kinematics(torch.tensor([0.4], dtype=torch.float64), rotations=True)[1]
    np.testing.assert_allclose(r[3].numpy(), _rz(0.4 + (-0.8 + 0.3) + 0.5 * (-0.8 + 0.3) - 0.1), atol=1e-12)


@needs_yourdfpy
def test_mimic_joints_match_yourdfpy(tmp_path):
    p = _write(tmp_path, _robot(MIMIC))
    for floating in (False, True):
        assert _fk_error_vs_yourdfpy(Skeleton.from_urdf(p, floating_base=floating), p, n=5) < 1e-12


def test_mimic_roundtrip_and_gradients(tmp_path):
    m = Skeleton.from_urdf(_write(tmp_path, _robot(MIMIC)), floating_base=False)
    out = m.to_urdf()
    assert out.count("<mimic") == 3
    back = Skeleton.from_urdf(_write(tmp_path, out, "back.urdf"))
    assert _roundtrip_error(m, back) < 1e-12
    q = torch.tensor([[0.4, 0.03], [-0.2, 0.01]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: m.forward_kinematics(x), (q,))


@pytest.mark.parametrize(
    "extra,match",
    [
        ('<mimic joint="b_to_c"/>', "loop"),
        ('<mimic joint="fixed_one"/>', "fixed joint"),
    ],
)
def test_bad_mimic(tmp_path, extra, match):
    lim = '<limit lower="-1" upper="1" effort="1" velocity="1"/>'
    text = _robot(
        _joint("a_to_b", "revolute", "a", "b", extra=lim + extra),
        _joint(
            "b_to_c",
            "revolute",
            "b",
            "c",
            extra='<limit lower="-1" upper="1" effort="1" velocity="1"/><mimic joint="a_to_b"/>',
        ),
        _joint("fixed_one", "fixed", "c", "d"),
    )
    with pytest.raises(InputError, match=match):
        Skeleton.from_urdf(_write(tmp_path, text))


def test_mimic_of_a_missing_joint_is_held_at_its_offset(tmp_path, caplog):
    """As yourdfpy does (example-robot-data's alex_psyonic_hands.urdf has such joints), with a warning."""
    text = _robot(
        _joint(
            "a_to_b",
            "revolute",
            "a",
            "b",
            axis="0 0 1",
            extra='<limit lower="-1" upper="1" effort="1" velocity="1"/><mimic joint="nope" offset="0.5"/>',
        ),
        _joint("b_to_c", "fixed", "b", "c", xyz="1 0 0"),
    )
    with caplog.at_level("WARNING", logger="ptrack.body.urdf"):
        m = Skeleton.from_urdf(_write(tmp_path, text), floating_base=False)
    assert m.num_dofs == 0 and "nope" in caplog.text
    j = m.forward_kinematics(torch.zeros(0, dtype=torch.float64))
    np.testing.assert_allclose(j[2].numpy(), [math.cos(0.5), math.sin(0.5), 0], atol=1e-12)


# -- defect 6: files urdfdom accepts ---------------------------------------------------------------


@pytest.mark.parametrize(
    "text",
    [
        # an XML declaration after a comment
        '<!-- generated -->\n<?xml version="1.0" encoding="utf-8"?>\n' + _robot(_joint("j", "fixed", "a", "b")),
        _robot(_joint("j", "fixed", "a", "b")).replace("<robot name='t'>", "<robot name='t' version='0.0'>"),
        # several geometry children, a transmission, a texture without a filename, gazebo and unknown tags
        "<robot name='t'><material name='m'><texture/></material>"
        "<link name='a'><visual><geometry><box size='1 1 1'/><sphere radius='1'/></geometry>"
        "<material name='m'/></visual>"
        "<collision><geometry><mesh filename='package://x/y.stl'/><cylinder radius='1' length='2'/></geometry>"
        "</collision>"
        "<inertial><mass value='1'/></inertial><contact><lateral_friction value='1'/></contact></link>"
        "<link name='b'/>"
        + _joint(
            "j",
            "revolute",
            "a",
            "b",
            extra='<limit lower="-1" upper="1" effort="1" velocity="1"/>'
            "<dynamics damping='1'/><safety_controller k_velocity='1'/><calibration rising='0'/>",
        )
        + "<transmission name='t1'><type>transmission_interface/SimpleTransmission</type><joint name='j'/>"
        "<actuator name='m1'><mechanicalReduction>1</mechanicalReduction></actuator></transmission>"
        "<gazebo reference='a'><mu1>0.2</mu1></gazebo><whatever/></robot>",
    ],
)
def test_files_urdfdom_accepts_load_quietly(tmp_path, capfd, text):
    m = Skeleton.from_urdf(_write(tmp_path, text), floating_base=False)
    assert m.joint_names == ("a", "b")
    out, err = capfd.readouterr()
    assert out == "" and err == ""


@pytest.mark.parametrize(
    "text,match",
    [
        ("<robot name='x'><link name='a'/><link name='a'/></robot>", "'a' is not unique"),
        ("<robot name='x'><link name='a'/><link name='b'/></robot>", "2 root links"),
        ("<robot name='x'></robot>", "no <link>"),
        ("<model name='x'><link name='a'/></model>", "<model>"),
        (_robot(_joint("j", "revolute", "a", "b", axis="0 0 0")), "axis is zero"),
        (_robot(_joint("j", "revolute", "a", "b", xyz="1, 2, 3")), "xyz='1, 2, 3'"),
        (_robot(_joint("j", "planar", "a", "b")), "'planar'"),
        (
            _robot(_joint("j", "fixed", "a", "b"), _joint("k", "fixed", "c", "b"), links=["a", "b", "c"]),
            "child of two joints",
        ),
    ],
)
def test_files_urdfdom_refuses(tmp_path, text, match):
    with pytest.raises(InputError, match=match):
        Skeleton.from_urdf(_write(tmp_path, text, "bad.urdf"))


# -- defect 7: edge cases --------------------------------------------------------------------------


def test_single_link_file(tmp_path):
    p = _write(
        tmp_path,
        "<robot name='ball'><link name='ball'><visual><geometry><sphere radius='0.1'/>"
        "</geometry></visual></link></robot>",
    )
    m = Skeleton.from_urdf(p, floating_base=False)
    assert m.joint_names == ("ball",) and m.num_dofs == 0
    assert m.forward_kinematics(torch.zeros(2, 0, dtype=torch.float64)).shape == (2, 1, 3)
    f = Skeleton.from_urdf(p)
    assert f.num_dofs == 6
    q = torch.tensor([1.0, 2.0, 3.0, 0.1, 0.2, 0.3], dtype=torch.float64)
    assert f.forward_kinematics(q)[0].tolist() == [1.0, 2.0, 3.0]


def test_model_without_dofs(tmp_path):
    """Fixed joints only: FK takes q of shape (..., 0), gradients included; to_urdf round-trips."""
    m = Skeleton.from_urdf(
        _write(tmp_path, _robot(_joint("j", "fixed", "a", "b", xyz="1 0 0", rpy="0 0 1"))), floating_base=False
    )
    q = torch.zeros(4, 0, dtype=torch.float64, requires_grad=True)
    j, r = m.forward_kinematics(q, rotations=True)
    assert j.shape == (4, 2, 3) and j[0, 1].tolist() == [1.0, 0.0, 0.0]
    assert r.shape == (4, 2, 3, 3)
    m.forward_kinematics(q).sum().backward()
    assert q.grad.shape == (4, 0)
    back = Skeleton.from_urdf(_write(tmp_path, m.to_urdf(), "back.urdf"))
    assert back.num_dofs == 0 and _roundtrip_error(m, back) < 1e-12


def test_floating_joint_is_refused_with_advice(tmp_path):
    with pytest.raises(InputError, match="floating_base=True"):
        Skeleton.from_urdf(_write(tmp_path, _robot(_joint("j", "floating", "a", "b"))))


def test_a_folder_is_not_a_urdf(tmp_path):
    with pytest.raises(InputError, match="folder"):
        Skeleton.from_urdf(tmp_path)


# -- defect 8: round trips with the default arguments ----------------------------------------------


def test_roundtrip_default_arguments_keeps_the_base(tmp_path, arm_path):
    """A floating-base model exported and read back with the defaults: the same dofs (no second
    floating base), and the base where it was, also for a fixed-base export."""
    for floating in (True, False):
        arm = Skeleton.from_urdf(arm_path, floating_base=floating)
        back = Skeleton.from_urdf(_write(tmp_path, arm.to_urdf(), "back.urdf"))
        assert back.dof_names == arm.dof_names
        assert _roundtrip_error(arm, back) < 1e-12
        q = torch.zeros(arm.num_dofs, dtype=torch.float64)
        assert back.forward_kinematics(q)[back.joint_index("base")].abs().max() == 0.0


def test_unlimited_translations_export_as_large_limits(sk):
    robot = ET.fromstring(sk.to_urdf())
    tx = next(j for j in robot.iter("joint") if j.get("name") == "root.tx")
    assert float(tx.find("limit").get("upper")) == UNLIMITED_PRISMATIC


def test_a_base_moved_by_three_prismatic_joints_is_not_floated(tmp_path):
    """Without ptrack's mark, a root translated by three prismatic joints (pybullet's
    cube_no_rotation.urdf) gets no second floating base by default."""
    p = CORPUS_DIR / "pybullet_data" / "cube_no_rotation.urdf"
    assert "root.tx" not in Skeleton.from_urdf(p).dof_names


def test_geometric_jacobian_of_slides_and_mimics(tmp_path):
    """ptrack.optim.jacobians on prismatic joints below the root (a slider moves its subtree along its axis)
    and mimic joints (a follower turns by multiplier per unit of its leader): equal to autograd
    through FK, on the small repro models and on corpus robots that have both (Panda's fingers,
    TIAGo's torso lift, xArm's gripper, Talos, r2d2), with and without a floating base."""
    from ptrack.optim.jacobians import joint_jacobian

    models = [Skeleton.from_urdf(_write(tmp_path, text), floating_base=False) for text in (_robot(LIFT), _robot(MIMIC))]
    for name in ("panda.urdf", "tiago.urdf", "r2d2.urdf", "talos_full_v2.urdf", "xarm6_with_gripper.urdf"):
        path = sorted(CORPUS_DIR.rglob(name))[0]
        models += [Skeleton.from_urdf(path, floating_base=fb) for fb in (False, True)]
    gen = torch.Generator().manual_seed(0)
    for m in models:
        assert m.has_slides_or_mimics
        lo, hi = m.limits(dtype=torch.float64)
        lo, hi = lo.clamp(min=-3.0), hi.clamp(max=3.0)
        q = lo + (hi - lo) * torch.rand(3, m.num_dofs, dtype=torch.float64, generator=gen)
        _, jac = joint_jacobian(m, q)
        auto = torch.autograd.functional.jacobian(lambda x: m.forward_kinematics(x).sum(0), q).permute(2, 0, 1, 3)
        torch.testing.assert_close(jac, auto, atol=1e-12, rtol=1e-12)


@pytest.mark.parametrize(
    "extra,match",
    [
        ('<limit lower="nan" upper="1" effort="1" velocity="1"/>', "lower='nan'"),
        ('<limit lower="-1" upper="x" effort="1" velocity="1"/>', "upper='x'"),
        (
            '<limit lower="-1" upper="1" effort="1" velocity="1"/><mimic joint="a_to_b" multiplier="inf"/>',
            "multiplier='inf'",
        ),
    ],
)
def test_numbers_that_are_not(tmp_path, extra, match):
    text = _robot(
        _joint("a_to_b", "revolute", "a", "b", extra='<limit lower="-1" upper="1" effort="1" velocity="1"/>'),
        _joint("b_to_c", "revolute", "b", "c", extra=extra),
    )
    with pytest.raises(InputError, match=match):
        Skeleton.from_urdf(_write(tmp_path, text))


def test_infinite_limits_are_unlimited(tmp_path):
    text = _robot(_joint("j", "prismatic", "a", "b", extra='<limit lower="-inf" upper="inf" effort="1" velocity="1"/>'))
    m = Skeleton.from_urdf(_write(tmp_path, text), floating_base=False)
    assert m.lower.tolist() == [-math.inf] and m.upper.tolist() == [math.inf]


try:
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st
except ImportError:  # a test dependency; without it only the fuzz test below is skipped
    st = None

_FUZZ_BASE = (CORPUS_DIR / "example_robot_data" / "panda_description" / "panda.urdf").read_text()
_FUZZ_VALUES = [
    "nan",
    "inf",
    "-inf",
    "",
    "1 2",
    "0 0 0 0",
    "1e400",
    "-0",
    "x",
    "1 -1",
    "0 0 0",
    "world",
    "panda_link0",
    "panda_finger_joint1",
    "revolute",
    "prismatic",
    "continuous",
    "fixed",
    "floating",
]


if st is None:

    @pytest.mark.skip(reason="hypothesis is not installed (pip install -e '.[test]')")
    def test_fuzzed_urdf_loads_or_raises_input_error():
        pass
else:

    @settings(
        max_examples=60,
        deadline=None,
        derandomize=True,
        database=None,
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    )
    @given(
        edits=st.lists(st.tuples(st.integers(0, 10_000), st.sampled_from(_FUZZ_VALUES)), min_size=1, max_size=4),
        cut=st.one_of(st.none(), st.tuples(st.integers(0, len(_FUZZ_BASE)), st.integers(0, 60))),
    )
    def test_fuzzed_urdf_loads_or_raises_input_error(tmp_path, edits, cut):
        """Panda's URDF with attribute values replaced (and a slice cut out): it loads, with finite FK
        and limits that are numbers, or raises InputError; never another exception."""
        import re

        text = _FUZZ_BASE
        for k, value in edits:
            attrs = list(re.finditer(r'="([^"]*)"', text))
            m = attrs[k % len(attrs)]
            text = text[: m.start(1)] + value + text[m.end(1) :]
        if cut is not None:
            text = text[: cut[0]] + text[cut[0] + cut[1] :]
        try:
            sk = Skeleton.from_urdf(_write(tmp_path, text, "fuzz.urdf"))
        except InputError:
            return
        assert not np.any(np.isnan(sk.lower)) and not np.any(np.isnan(sk.upper))
        assert torch.isfinite(sk.forward_kinematics(torch.zeros(sk.num_dofs, dtype=torch.float64))).all()
        assert isinstance(sk.to_urdf(), str)


def test_from_urdf_reads_the_text_to_urdf_returns():
    """`Skeleton.from_urdf(sk.to_urdf())`, the round trip the docstrings show, works on the string
    itself (no file): same dofs, same joints, for a CMU skeleton and a corpus robot."""
    bundled = Path(__file__).resolve().parents[1] / "ptrack" / "data" / "10.asf"
    for m in (Skeleton.from_asf(bundled), Skeleton.from_urdf(sorted(CORPUS_DIR.rglob("panda.urdf"))[0])):
        back = Skeleton.from_urdf(m.to_urdf())
        assert back.dof_names == m.dof_names
        q = torch.rand(4, m.num_dofs, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 0.3
        idx = [back.joint_names.index(n) for n in m.joint_names]  # the export adds a link per axis
        torch.testing.assert_close(back.forward_kinematics(q)[:, idx], m.forward_kinematics(q), atol=1e-12, rtol=0)
    with pytest.raises(InputError):
        Skeleton.from_urdf("<robot name='x'><link name='a'/><link name='a'/></robot>")
