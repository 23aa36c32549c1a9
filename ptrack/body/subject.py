"""The person: a template skeleton given a subject's height, and where a detector's landmarks sit on it.

A detector's keypoints mark anatomical landmarks (`ptrack.body.keypoint_sets.LANDMARKS`), not the joint
centres of a motion-capture skeleton. `CMU_LANDMARK_JOINTS` places each landmark that has a counterpart
on a CMU ASF skeleton at the end point of one of its bones (the knee at the end of the femur, the base of
the neck at the end of the thorax, ...). Landmarks without a counterpart (eyes, ears, heels, hand points)
are not placed: a run leaves those keypoints out and says so.

`scale_to_height` gives the template the body proportions of a person of a given height: each segment's
length is a fixed fraction of the height (`SEGMENTS`, from Winter's anthropometric table, below), fitted
on the template's rest pose by adjusting groups of bones (left and right together). The segment lengths
are between the landmarks a detector reports (hip to knee, knee to ankle, ...), so they are what the 2D
constrains.

Sources: D. A. Winter, *Biomechanics and Motor Control of Human Movement*, 4th ed. (2009), fig. 4.1
(segment lengths as fractions of the body height H, after Drillis and Contini 1966): shoulder height
0.818 H, hip (greater trochanter) 0.530 H, knee 0.285 H, ankle 0.039 H, upper arm 0.186 H, forearm
0.146 H, shoulder width 0.259 H, hip width 0.191 H, foot length 0.152 H. Two rows are not in the table and
are approximations stated here: the distance between the hip joint centres (0.11 H, about 60% of the
hip width, as hip joint centre regressions on the pelvis width give) and the distance between a
detector's shoulder points (0.20 H: the shoulder joint centres lie about 0.03 H inside the acromia on
each side).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping

import numpy as np
import torch

from ptrack.body.skeleton import Skeleton
from ptrack.errors import InputError

#: landmark -> CMU ASF bone whose end point marks it ("root" is the pelvis centre)
CMU_LANDMARK_JOINTS: dict[str, str] = {
    "pelvis": "root",
    "spine": "upperback",
    "thorax": "thorax",
    # BODY_25's Neck (the shoulders' midpoint) and BODY_25B's UpperNeck (on the Pose2Sim data 4-6 cm above
    # that midpoint) both fall nearest the lower neck's end: CMU's shoulders sit 6 cm above its thorax's end
    "neck": "lowerneck",
    "upper_neck": "lowerneck",
    "head_top": "head",
    **{
        f"{s}_{part}": f"{s}{bone}"
        for s in "lr"
        for part, bone in (
            ("shoulder", "clavicle"),
            ("elbow", "humerus"),
            ("wrist", "radius"),
            ("hip", "hipjoint"),
            ("knee", "femur"),
            ("ankle", "tibia"),
            ("big_toe", "toes"),
            ("foot_index", "toes"),
        )
    },
    **{
        m: f"lm_{m}"
        for m in ("nose", "l_eye", "r_eye", "l_ear", "r_ear", "l_heel", "r_heel", "l_small_toe", "r_small_toe")
    },
}

#: landmarks placed off the skeleton's joints: landmark -> (CMU bone it moves with, the bone whose end the
#: offset starts from, offset / height in the rest pose: x the person's left, y up, z forward). Head points
#: from the head's end (the vertex): eyes 0.07 H below it (mid head: the head is 0.13 H from chin to
#: vertex), 0.045 H forward, 0.018 H to each side (pupils 6.3 cm apart at 1.75 m); the nose tip 0.09 H below
#: and 0.06 H forward; the ears (tragus) 0.075 H below, 0.045 H to each side (head breadth 0.09 H). Foot
#: points from the ankle (the tibia's end, 0.039 H above the floor): the heel 0.035 H back and 0.03 H down,
#: the little toe 0.11 H forward (the foot is 0.152 H long from the heel), 0.03 H outwards and 0.03 H down.
#: Approximations from the head and foot dimensions of Winter (2009) fig. 4.1 and adult head anthropometry
#: (head height 0.13 H, breadth 0.09 H); a detector marks these points within a few centimetres anyway.
OFFSET_LANDMARKS: dict[str, tuple[str, str, tuple[float, float, float]]] = {
    "nose": ("head", "head", (0.0, -0.09, 0.06)),
    **{
        f"{s}_{part}": (bone.replace("*", s), end.replace("*", s), (sign * dx, dy, dz))
        for s, sign in (("l", 1.0), ("r", -1.0))
        for part, bone, end, (dx, dy, dz) in (
            ("eye", "head", "head", (0.018, -0.07, 0.045)),
            ("ear", "head", "head", (0.045, -0.075, 0.0)),
            ("heel", "*foot", "*tibia", (0.0, -0.03, -0.035)),
            ("small_toe", "*foot", "*tibia", (0.03, -0.03, 0.11)),
        )
    },
}


def add_landmark_joints(skeleton: Skeleton, height_m: float) -> Skeleton:
    """`skeleton` (CMU ASF) with one joint more per landmark of `OFFSET_LANDMARKS`, named "lm_<landmark>":
    no dofs, a child of the bone it moves with, at the offset (times `height_m`) from its start bone's end
    in the rest pose. Existing joints, dofs and limits are unchanged (new joints come last)."""
    q0 = torch.zeros(skeleton.num_dofs, dtype=torch.float64)
    joints, rotations = skeleton.forward_kinematics(q0, rotations=True)
    joints, rotations = joints.numpy(), rotations.numpy()
    names, parents, offsets, lengths = [], [], [], []
    for landmark, (bone, start, offset) in OFFSET_LANDMARKS.items():
        b, a = skeleton.joint_index(bone), skeleton.joint_index(start)
        target = joints[a] + height_m * np.asarray(offset)
        v = rotations[b].T @ (target - joints[b])  # in the bone's frame: turns with it
        names.append(f"lm_{landmark}")
        parents.append(b)
        lengths.append(float(np.linalg.norm(v)))
        offsets.append(v / max(lengths[-1], 1e-12))
    n = len(names)

    def grow(x: np.ndarray, fill: np.ndarray) -> np.ndarray:
        return np.concatenate([x, np.broadcast_to(fill, (n, *x.shape[1:]))])

    return dataclasses.replace(
        skeleton,
        joint_names=(*skeleton.joint_names, *names),
        parents=(*skeleton.parents, *parents),
        axes=grow(skeleton.axes, np.zeros((3, 3))),
        axis_dof=grow(skeleton.axis_dof, -np.ones(3, dtype=skeleton.axis_dof.dtype)),
        rest_rotation=grow(skeleton.rest_rotation, np.eye(3)),
        offset_parent=np.concatenate([skeleton.offset_parent, np.zeros((n, 3))]),
        offset_local=np.concatenate([skeleton.offset_local, np.asarray(offsets)]),
        lengths=np.concatenate([skeleton.lengths, np.asarray(lengths)]),
        frozen_axes=grow(skeleton.frozen_axes, np.zeros(3)),
        axis_scale=grow(skeleton.axis_scale, np.ones(3)),
        slide_axis=grow(skeleton.slide_axis, np.zeros(3)),
        slide_dof=grow(skeleton.slide_dof, -np.ones((), dtype=skeleton.slide_dof.dtype)),
    )


#: the ankle joint centre's height above the floor when standing, / height (Winter 2009, fig. 4.1: 0.039 H);
#: `OFFSET_LANDMARKS` places the heel and little toe from it
ANKLE_HEIGHT = 0.039


def standing_height(skeleton: Skeleton) -> float:
    """The height a person with `skeleton`'s bone lengths would give, metres, standing straight: the head's end
    above the hip joints (the hip bones' ends) in the rest pose, plus the legs' length (femur and tibia, the
    mean of both sides) hanging straight down, that being (1 - `ANKLE_HEIGHT`) of the height (Winter 2009).

    The legs are counted by their length, not by where the rest pose puts the ankles: a CMU ASF's rest pose
    splays them about 20 degrees outwards, and the ankles' height there would take 2.5-3.2% off the stature of
    the 14 CMU subjects in ../shared (before 2026-11-30 it did)."""
    joints = skeleton.forward_kinematics(torch.zeros(skeleton.num_dofs, dtype=torch.float64)).numpy()
    top = joints[skeleton.joint_index("head"), 1]
    hips = [skeleton.joint_index(f"{s}hipjoint") for s in "lr"]
    legs = [
        skeleton.lengths[skeleton.joint_index(f"{s}femur")] + skeleton.lengths[skeleton.joint_index(f"{s}tibia")]
        for s in "lr"
    ]
    return float((top - joints[hips, 1].mean() + np.mean(legs)) / (1 - ANKLE_HEIGHT))


#: the skeleton's points that touch the floor: CMU's toe ends and the heel and little-toe landmark joints
FLOOR_POINTS = ("ltoes", "rtoes", "lm_l_heel", "lm_r_heel", "lm_l_small_toe", "lm_r_small_toe")


def floor_points(skeleton: Skeleton, height_m: float) -> tuple[tuple[int, ...], float]:
    """The joints of `FLOOR_POINTS` that `skeleton` has (a CMU ASF skeleton with `add_landmark_joints`) and the
    height of the lowest of them above the floor when the rest pose stands with its ankles `ANKLE_HEIGHT` *
    `height_m` above it -> (joint indices (F,), clearance metres). InputError when it has none."""
    joints = tuple(skeleton.joint_index(n) for n in FLOOR_POINTS if n in skeleton.joint_names)
    if not joints:
        raise InputError(f"skeleton {skeleton.name!r} has none of the foot points {', '.join(FLOOR_POINTS)}")
    rest = skeleton.forward_kinematics(torch.zeros(skeleton.num_dofs, dtype=torch.float64)).numpy()
    ankles = [skeleton.joint_index(n) for n in ("ltibia", "rtibia") if n in skeleton.joint_names]
    floor = (rest[ankles, 1].mean() if ankles else rest[list(joints), 1].min()) - ANKLE_HEIGHT * height_m
    return joints, float(max(rest[list(joints), 1].min() - floor, 0.0))


#: height of the neck landmark above the line between the shoulder points, / height (on the Pose2Sim data:
#: 4-6 cm for a 1.72 m participant)
NECK_ABOVE_SHOULDERS = 0.025

#: segment -> (landmark a, landmark b, length / height): Winter (2009) fig. 4.1, see the module docstring
SEGMENTS: dict[str, tuple[str, str, float]] = {
    "thigh": ("l_hip", "l_knee", 0.530 - 0.285),
    "shank": ("l_knee", "l_ankle", 0.285 - 0.039),
    "upper_arm": ("l_shoulder", "l_elbow", 0.186),
    "forearm": ("l_elbow", "l_wrist", 0.146),
    "hips": ("l_hip", "r_hip", 0.11),
    "shoulders": ("l_shoulder", "r_shoulder", 0.20),
    "trunk": ("l_hip", "l_shoulder", math.hypot(0.818 - 0.530, (0.20 - 0.11) / 2)),
    "head": ("neck", "head_top", 1.0 - 0.818 - NECK_ABOVE_SHOULDERS),
    "foot": ("l_ankle", "l_big_toe", 0.152 - 0.039),
}

#: segment -> the CMU bones scaled together to fit it (each side's bones get the same factor)
CMU_SEGMENT_BONES: dict[str, tuple[str, ...]] = {
    "thigh": ("lfemur", "rfemur"),
    "shank": ("ltibia", "rtibia"),
    "upper_arm": ("lhumerus", "rhumerus"),
    "forearm": ("lradius", "rradius", "lwrist", "rwrist", "lhand", "rhand", "lfingers", "rfingers", "lthumb", "rthumb"),
    "hips": ("lhipjoint", "rhipjoint"),
    "shoulders": ("lclavicle", "rclavicle"),
    "trunk": ("lowerback", "upperback", "thorax", "lowerneck"),
    "head": ("upperneck", "head"),
    "foot": ("lfoot", "rfoot", "ltoes", "rtoes"),
}

#: the plausible range of a subject's height, metres
HEIGHT_RANGE_M = (0.5, 2.6)


def check_height(height_m: float, key: str = "subject.height_m") -> float:
    """`height_m` as a float; InputError unless it is finite and within `HEIGHT_RANGE_M`."""
    h = float(height_m)
    lo, hi = HEIGHT_RANGE_M
    if not (lo <= h <= hi):  # also false for NaN
        raise InputError(f"config key {key!r} is {height_m} m; a person's height must be within {lo}-{hi} m")
    return h


def landmark_joints(skeleton: Skeleton, landmarks: tuple[str, ...]) -> list[str | None]:
    """For each landmark (K,), the joint of `skeleton` that marks it, None where it has no place.

    Only CMU ASF skeletons (joint names as in `CMU_LANDMARK_JOINTS`) are placed; InputError for others."""
    placed = [CMU_LANDMARK_JOINTS.get(m) for m in landmarks]
    missing = sorted({j for j in placed if j is not None and j not in skeleton.joint_names})
    if missing:
        raise InputError(
            f"skeleton {skeleton.name!r} lacks the CMU joints {missing} that place a detector's keypoints; "
            f"real keypoint files need a CMU ASF skeleton (data.asf)"
        )
    return placed


def segment_lengths(skeleton: Skeleton) -> dict[str, float]:
    """Each segment of `SEGMENTS` measured on `skeleton`'s rest pose, metres."""
    joints = skeleton.forward_kinematics(torch.zeros(skeleton.num_dofs, dtype=torch.float64)).numpy()
    out = {}
    for name, (a, b, _) in SEGMENTS.items():
        ia, ib = (skeleton.joint_index(CMU_LANDMARK_JOINTS[m]) for m in (a, b))
        out[name] = float(np.linalg.norm(joints[ia] - joints[ib]))
    return out


def symmetric_lengths(skeleton: Skeleton) -> np.ndarray:
    """(J,) the bone lengths of `skeleton` with each left bone ("l<name>") and its right counterpart
    ("r<name>") both at their mean; unpaired bones as they are."""
    lengths = np.array(skeleton.lengths, dtype=np.float64)
    names = skeleton.joint_names
    for j, n in enumerate(names):
        if n.startswith("l") and "r" + n[1:] in names:
            k = names.index("r" + n[1:])
            lengths[j] = lengths[k] = 0.5 * (skeleton.lengths[j] + skeleton.lengths[k])
    return lengths


def scale_to_height(skeleton: Skeleton, height_m: float, targets: Mapping[str, float] | None = None) -> Skeleton:
    """`skeleton` (a CMU ASF model) with its bone lengths set so that every segment of `SEGMENTS` has its
    fraction of `height_m` (or the length `targets` gives it, metres), the root's rest height scaled along.

    The bones of a segment (`CMU_SEGMENT_BONES`) share one factor, found by Gauss-Newton on the rest pose's
    segment lengths (the segments overlap: the trunk's length depends on the hips' bones too). Each left bone and
    its right counterpart ("l..." and "r...") start from their mean length: a template's left/right differences
    are its own subject's (CMU subject 10's right humerus is 9% longer than the left), not the person's."""
    h = check_height(height_m)
    want = {name: frac * h for name, (_, _, frac) in SEGMENTS.items()}
    want.update(targets or {})
    names = list(SEGMENTS)
    groups = [[skeleton.joint_index(b) for b in CMU_SEGMENT_BONES[n]] for n in names]
    landmarks = [
        (skeleton.joint_index(CMU_LANDMARK_JOINTS[a]), skeleton.joint_index(CMU_LANDMARK_JOINTS[b]))
        for a, b, _ in SEGMENTS.values()
    ]
    base = torch.as_tensor(symmetric_lengths(skeleton), dtype=torch.float64)
    target = torch.tensor([want[n] for n in names], dtype=torch.float64)
    q = torch.zeros(skeleton.num_dofs, dtype=torch.float64)
    member = torch.zeros(len(names), skeleton.num_joints, dtype=torch.float64)
    for g, idx in enumerate(groups):
        member[g, idx] = 1.0

    def residual(log_s: torch.Tensor) -> torch.Tensor:
        lengths = base * torch.exp(log_s @ member)
        joints = skeleton.forward_kinematics(q, lengths=lengths)
        seg = torch.stack([(joints[a] - joints[b]).norm() for a, b in landmarks])
        return torch.log(seg / target)

    log_s = torch.zeros(len(names), dtype=torch.float64)
    r = residual(log_s)
    for _ in range(50):
        if float(r.abs().max()) < 1e-10:
            break
        jac = torch.autograd.functional.jacobian(residual, log_s)
        step = torch.linalg.lstsq(jac, r.unsqueeze(-1)).solution.squeeze(-1)
        step = step * min(1.0, 0.3 / float(step.abs().max()))  # at most a 35% change per bone group and step
        for _ in range(30):  # backtrack until the squared residual drops
            trial = residual(log_s - step)
            if bool(torch.isfinite(trial).all()) and float(trial @ trial) < float(r @ r):
                break
            step = step / 2
        else:
            break
        log_s, r = log_s - step, trial
    if float(r.abs().max()) > 1e-3:
        raise InputError(f"the template skeleton {skeleton.name!r} cannot take the proportions of a {h} m person")
    factor = torch.exp(log_s @ member).numpy()
    lengths = base.numpy() * factor
    # the root's rest position (ASF: where it is in the rest pose) follows the legs
    legs = float(torch.exp(log_s[[names.index("thigh"), names.index("shank")]]).mean())
    return dataclasses.replace(
        skeleton,
        name=f"{skeleton.name} scaled to {h:.2f} m",
        lengths=lengths,
        root_position=skeleton.root_position * legs,
    )


#: the landmark joints of `OFFSET_LANDMARKS` scale with these segments
_OFFSET_SEGMENT = {"nose": "head", "eye": "head", "ear": "head", "heel": "foot", "small_toe": "foot"}


def segment_groups(skeleton: Skeleton) -> tuple[tuple[str, ...], np.ndarray]:
    """The segments of `CMU_SEGMENT_BONES` as bone groups of `skeleton`: (names (G,), membership (G, J) 0/1);
    the landmark joints ("lm_...") join their segment (the face the head's, the heel and little toe the
    foot's)."""
    names = tuple(CMU_SEGMENT_BONES)
    member = np.zeros((len(names), skeleton.num_joints))
    for g, name in enumerate(names):
        for bone in CMU_SEGMENT_BONES[name]:
            member[g, skeleton.joint_index(bone)] = 1.0
    for j, joint in enumerate(skeleton.joint_names):
        if joint.startswith("lm_"):
            part = joint[3:].removeprefix("l_").removeprefix("r_")
            member[names.index(_OFFSET_SEGMENT[part]), j] = 1.0
    return names, member


def rescale_segments(skeleton: Skeleton, height_m: float, targets: Mapping[str, float]) -> Skeleton:
    """`skeleton` (already scaled to `height_m`, landmark joints included) with the segments of `targets`
    (metres) at those lengths and the others at their fractions of the height; each landmark joint
    ("lm_...") takes its segment's mean factor."""
    new = scale_to_height(skeleton, height_m, targets)
    names, member = segment_groups(skeleton)
    lengths = new.lengths.copy()
    bones = member.copy()
    bones[:, [j for j, n in enumerate(skeleton.joint_names) if n.startswith("lm_")]] = 0.0
    ratio = np.divide(new.lengths, skeleton.lengths, out=np.ones_like(new.lengths), where=skeleton.lengths > 0)
    for g in range(len(names)):
        factor = float((bones[g] * ratio).sum() / max(bones[g].sum(), 1.0))
        for j, n in enumerate(skeleton.joint_names):
            if n.startswith("lm_") and member[g, j]:
                lengths[j] = skeleton.lengths[j] * factor
    return dataclasses.replace(new, lengths=lengths)
