"""Tests for ptrack.body.keypoints: the default H36M-17 set on CMU skeletons, custom mappings, errors."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from ptrack.body.keypoints import CMU_H36M17, H36M17, H36M17_LIMBS, KeypointSet, make_keypoints
from ptrack.body.skeleton import Skeleton
from ptrack.errors import InputError

ASF = Path(__file__).resolve().parents[1] / "ptrack" / "data" / "10.asf"
FREEZE = ["*fingers", "*thumb", "*hand", "*toes"]


@pytest.fixture(scope="module")
def skeleton() -> Skeleton:
    return Skeleton.from_asf(ASF)


@pytest.fixture(scope="module")
def kps(skeleton) -> KeypointSet:
    return make_keypoints(skeleton)


def test_default_set_names_and_joints(skeleton, kps):
    assert kps.names == H36M17
    assert kps.num_keypoints == 17 == len(kps.joints)
    assert set(CMU_H36M17) == set(H36M17)
    for name, j in zip(kps.names, kps.joints):
        assert skeleton.joint_names[j] == CMU_H36M17[name]
    assert kps.joints[kps.names.index("pelvis")] == 0  # the root
    assert len(set(kps.joints)) == 17  # no two keypoints on one joint


def test_default_swap_pairs_are_left_right_partners(kps):
    pairs = {(kps.names[a], kps.names[b]) for a, b in kps.swap_pairs}
    assert pairs == {(f"l_{p}", f"r_{p}") for p in ("hip", "knee", "ankle", "shoulder", "elbow", "wrist")}
    for a, b in kps.swap_pairs:
        assert kps.names[a][2:] == kps.names[b][2:]


def test_mirror_index_exchanges_left_and_right(kps):
    m = kps.mirror_index()
    names = kps.names
    assert [names[i] for i in m] == [n.replace("l_", "#").replace("r_", "l_").replace("#", "r_") for n in names]
    assert m.dtype == torch.long and torch.equal(m[m], torch.arange(len(names)))


def test_default_limbs(skeleton, kps):
    assert len(kps.limbs) == len(H36M17_LIMBS) == 10
    assert [(kps.names[a], kps.names[b]) for a, b in kps.limbs] == list(H36M17_LIMBS)
    idx = {n: skeleton.joint_names.index(j) for n, j in CMU_H36M17.items()}
    assert kps.limb_joints() == [(idx[a], idx[b]) for a, b in H36M17_LIMBS]


def test_index_tensor(kps):
    i = kps.index()
    assert i.dtype == torch.long and i.shape == (17,)
    assert i.tolist() == list(kps.joints)
    assert kps.index(device="cpu").device.type == "cpu"


def test_default_set_is_anatomically_placed(skeleton, kps):
    """At the rest pose (Y up, CMU left = +X): head above thorax above pelvis above knees above ankles;
    left keypoints on the +X side of their right partners."""
    X = skeleton.forward_kinematics(torch.zeros(skeleton.num_dofs, dtype=torch.float64))
    P = {n: X[j] for n, j in zip(kps.names, kps.joints)}
    y = {n: float(p[1]) for n, p in P.items()}
    for side in "lr":
        assert y["head"] > y["thorax"] > y["pelvis"] > y[f"{side}_knee"] > y[f"{side}_ankle"]
        assert y[f"{side}_shoulder"] > y[f"{side}_hip"]
    for a, b in kps.swap_pairs:
        assert float(P[kps.names[a]][0]) > float(P[kps.names[b]][0])


def test_default_set_on_reduced_model(skeleton, kps):
    reduced = skeleton.freeze(FREEZE)
    assert reduced.num_dofs < skeleton.num_dofs
    assert make_keypoints(reduced) == kps


def test_default_set_on_another_cmu_skeleton(asf_64):
    other = Skeleton.from_asf(asf_64)
    k = make_keypoints(other)
    assert k.names == H36M17
    assert [other.joint_names[j] for j in k.joints] == [CMU_H36M17[n] for n in H36M17]


def test_custom_mapping(skeleton):
    mapping = {"nose": "head", "l_knee": "lfemur", "r_knee": "rfemur", "l_foot": "lfoot", "r_hip": "rhipjoint"}
    k = make_keypoints(skeleton, mapping)
    assert k.names == tuple(mapping)  # order kept
    assert k.joints == tuple(skeleton.joint_names.index(j) for j in mapping.values())
    assert k.swap_pairs == ((1, 2),)  # l_foot has no r_foot, r_hip has no l_hip
    assert k.limbs == ((4, 2),)  # (r_hip, r_knee): the only H36M limb with both ends here
    k2 = make_keypoints(skeleton, {"r_hip": "rhipjoint", "r_knee": "rfemur", "head": "head"})
    assert k2.limbs == ((0, 1),) and k2.swap_pairs == ()


def test_mapping_to_unknown_joint(skeleton):
    with pytest.raises(InputError) as info:
        make_keypoints(skeleton, {"head": "head", "l_knee": "leftknee"})
    msg = str(info.value)
    assert "l_knee" in msg and "leftknee" in msg


def test_empty_mapping(skeleton):
    with pytest.raises(InputError, match="empty"):
        make_keypoints(skeleton, {})


def test_keypoint_set_is_frozen(kps):
    with pytest.raises(AttributeError):
        kps.names = ()  # type: ignore[misc]
