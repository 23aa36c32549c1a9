"""Observed keypoint sets: which skeleton joints a 2D detector (or annotator) reports.

The standard set is Human3.6M-like, 17 keypoints. `CMU_H36M17` maps it to CMU ASF joints (a joint
is a bone's end point, so e.g. the knee is the end of the femur). Any model can use another mapping
(config `keypoints.mapping`), as long as every name is one of the model's joints.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import Tensor

from ptrack.body.skeleton import Skeleton
from ptrack.errors import InputError

H36M17: tuple[str, ...] = (
    "pelvis",
    "r_hip",
    "r_knee",
    "r_ankle",
    "l_hip",
    "l_knee",
    "l_ankle",
    "spine",
    "thorax",
    "neck",
    "head",
    "l_shoulder",
    "l_elbow",
    "l_wrist",
    "r_shoulder",
    "r_elbow",
    "r_wrist",
)

#: H36M-17 keypoint -> CMU ASF joint (bone end point).
CMU_H36M17: dict[str, str] = {
    "pelvis": "root",
    "r_hip": "rhipjoint",
    "r_knee": "rfemur",
    "r_ankle": "rtibia",
    "l_hip": "lhipjoint",
    "l_knee": "lfemur",
    "l_ankle": "ltibia",
    "spine": "upperback",
    "thorax": "thorax",
    "neck": "upperneck",
    "head": "head",
    "l_shoulder": "lclavicle",
    "l_elbow": "lhumerus",
    "l_wrist": "lradius",
    "r_shoulder": "rclavicle",
    "r_elbow": "rhumerus",
    "r_wrist": "rradius",
}

#: limbs whose depth order the flip-error metric checks (start keypoint, end keypoint)
H36M17_LIMBS: tuple[tuple[str, str], ...] = (
    ("r_hip", "r_knee"),
    ("r_knee", "r_ankle"),
    ("l_hip", "l_knee"),
    ("l_knee", "l_ankle"),
    ("r_shoulder", "r_elbow"),
    ("r_elbow", "r_wrist"),
    ("l_shoulder", "l_elbow"),
    ("l_elbow", "l_wrist"),
    ("thorax", "head"),
    ("pelvis", "thorax"),
)


@dataclass(frozen=True)
class KeypointSet:
    """K named keypoints placed on skeleton joints.

    names: (K,) keypoint names; joints: (K,) skeleton joint indices; swap_pairs: left/right partner
    keypoint index pairs; limbs: (start, end) keypoint index pairs for the flip metric; landmarks: (K,) the
    landmark each marks in the shared vocabulary (`ptrack.body.keypoint_sets.LANDMARKS`: "l_hip", not a
    format's "LHip" or "left_hip"), None where the names are those landmarks (the simulated sets).
    """

    names: tuple[str, ...]
    joints: tuple[int, ...]
    swap_pairs: tuple[tuple[int, int], ...]
    limbs: tuple[tuple[int, int], ...]
    landmarks: tuple[str, ...] | None = None

    @property
    def num_keypoints(self) -> int:
        return len(self.names)

    def index(self, device=None) -> Tensor:
        """(K,) long tensor of skeleton joint indices."""
        return torch.as_tensor(self.joints, dtype=torch.long, device=device)

    def mirror_index(self, device=None) -> Tensor:
        """(K,) long tensor: each keypoint's left/right partner (`swap_pairs`), itself when it has none; indexing
        the keypoint axis with it exchanges every left and right label."""
        partners = torch.arange(self.num_keypoints, device=device)
        for a, b in self.swap_pairs:
            partners[a], partners[b] = b, a
        return partners

    def find(self, landmark: str) -> int | None:
        """The index of the keypoint that marks `landmark` ("l_hip"; by name where `landmarks` is None), or None
        when the set has none."""
        marks = self.names if self.landmarks is None else self.landmarks
        return marks.index(landmark) if landmark in marks else None

    def limb_joints(self) -> list[tuple[int, int]]:
        """Limbs as skeleton joint index pairs."""
        return [(self.joints[a], self.joints[b]) for a, b in self.limbs]


def make_keypoints(skeleton: Skeleton, mapping: Mapping[str, str] | None = None) -> KeypointSet:
    """Keypoint set for `skeleton` from a {keypoint name: joint name} mapping (default CMU_H36M17).

    Left/right swap pairs are found by name ("l_x" <-> "r_x"); limbs are the H36M17 limbs present.
    """
    mapping = dict(CMU_H36M17 if mapping is None else mapping)
    if not mapping:
        raise InputError("keypoint mapping is empty")
    names = tuple(mapping)
    joints = []
    for k in names:
        j = mapping[k]
        if j not in skeleton.joint_names:
            raise InputError(
                f"keypoint {k!r} maps to {j!r}, which is not a joint of skeleton "
                f"{skeleton.name!r} (joints: {', '.join(skeleton.joint_names[:8])}, ...)"
            )
        joints.append(skeleton.joint_names.index(j))
    pos = {n: i for i, n in enumerate(names)}
    swaps = tuple((pos[n], pos["r_" + n[2:]]) for n in names if n.startswith("l_") and "r_" + n[2:] in pos)
    limbs = tuple((pos[a], pos[b]) for a, b in H36M17_LIMBS if a in pos and b in pos)
    return KeypointSet(names=names, joints=tuple(joints), swap_pairs=swaps, limbs=limbs)


#: limbs of the landmark vocabulary (`ptrack.body.keypoint_sets.LANDMARKS`) whose depth order the flip
#: metric checks, as `H36M17_LIMBS` does for the simulated set
LANDMARK_LIMBS: tuple[tuple[str, str], ...] = tuple(
    (f"{s}_{a}", f"{s}_{b}")
    for s in "rl"
    for a, b in (("hip", "knee"), ("knee", "ankle"), ("shoulder", "elbow"), ("elbow", "wrist"))
)


def landmark_keypoints(
    skeleton: Skeleton, names: tuple[str, ...], landmarks: tuple[str, ...], joints: list[str]
) -> KeypointSet:
    """Keypoint set of a detector's format: names (K,) as the format spells them, the landmark (K,) each
    marks and the joint (K,) of `skeleton` placed there. Swap pairs and limbs come from the landmarks."""
    if not (len(names) == len(landmarks) == len(joints)):
        raise InputError(f"{len(names)} keypoint names, {len(landmarks)} landmarks and {len(joints)} joints differ")
    index = tuple(skeleton.joint_index(j) for j in joints)
    pos = {m: i for i, m in enumerate(landmarks)}
    swaps = tuple((pos[m], pos["r_" + m[2:]]) for m in landmarks if m.startswith("l_") and "r_" + m[2:] in pos)
    limbs = tuple((pos[a], pos[b]) for a, b in LANDMARK_LIMBS if a in pos and b in pos)
    return KeypointSet(names=names, joints=index, swap_pairs=swaps, limbs=limbs, landmarks=tuple(landmarks))
