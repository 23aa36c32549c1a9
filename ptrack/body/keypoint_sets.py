"""Detectors' keypoint sets: each format's keypoint names and order, left/right pairs, and the anatomical
landmark every keypoint marks.

A `KeypointDefinition` is one published keypoint set (OpenPose BODY_25 and BODY_25B, COCO-17, HALPE-26,
the body and feet of COCO-WholeBody-133, MediaPipe-33, Human3.6M-17). `names` are the format's own
spelling in its own order (index k of a detection file is `names[k]`); `landmarks[k]` names the same point
in ONE vocabulary shared by every set (`LANDMARKS`), so that two formats' keypoints are compared by
landmark, not by name. A landmark is where on the body a format puts its point; the formats do not agree
on the exact place (a detector's hip is not the mocap hip joint centre, MediaPipe's shoulders sit higher
than COCO's): those offsets belong to the body model that places keypoints on bones, not to this list.

The landmark vocabulary (`l_` / `r_` is the person's own left / right):

    nose            tip of the nose
    l_eye           centre of the eye (pupil)
    l_eye_inner     inner corner of the eye (MediaPipe)
    l_eye_outer     outer corner of the eye (MediaPipe)
    l_ear           the ear (tragus)
    l_mouth         corner of the mouth (MediaPipe)
    head_top        top of the head (vertex)
    upper_neck      top of the neck, under the chin (OpenPose BODY_25B UpperNeck, Human3.6M Neck/Nose)
    neck            base of the neck, midway between the shoulders (OpenPose BODY_25 Neck, HALPE Neck)
    thorax          top of the thoracic spine at shoulder height (Human3.6M Thorax)
    spine           middle of the back (Human3.6M Spine)
    pelvis          midway between the hips (OpenPose MidHip, HALPE Hip, Human3.6M Hip)
    l_shoulder, l_elbow, l_wrist
    l_pinky         little-finger point of the hand (MediaPipe)
    l_index         index-finger point of the hand (MediaPipe)
    l_thumb         thumb point of the hand (MediaPipe)
    l_hip, l_knee, l_ankle
    l_heel          back of the heel
    l_big_toe       tip of the big toe
    l_small_toe     tip of the little toe
    l_foot_index    tip of the foot (MediaPipe foot index)

and the same `r_` landmarks. Hand and face points of COCO-WholeBody (indices 23-132) are not part of its
body+feet set: a file with 133 points a person is read keeping the first 23.

Choosing a set from the keypoint count (`infer_keypoint_set`): 23, 26, 33 and 133 points name one set
each. 17 (COCO-17 or Human3.6M-17) and 25 (BODY_25B or BODY_25) are told apart by content, over every
detected person, each measure divided by the person's size (the diagonal of the bounding box of its
points) and its median taken over the people that show the points it needs:

- face spread: the diagonal of the bounding box of keypoints 0-4. In COCO-17 and BODY_25B they are the
  face (nose, eyes, ears), within a head-sized region; in Human3.6M-17 they are the pelvis, right hip, knee,
  ankle and left hip, in BODY_25 the nose, neck and right arm, spread over much of the body.
- midpoint test: how far keypoint a lies from the midpoint of keypoints b and c, for the triplets that
  hold in the limb-first set: for 25 points (8, 9, 12) and (1, 2, 5), BODY_25's MidHip between its hips
  and Neck between its shoulders (in BODY_25B: the right elbow against the right wrist and hip, the left
  eye against the right eye and left shoulder); for 17 points (8, 11, 14), Human3.6M's thorax between its
  shoulders (in COCO-17: the right elbow against the left hip and right knee). The largest of the
  triplets' medians counts.

Each measure votes: a face spread under `FACE_SPREAD_MAX` for the face-first set (COCO-17, BODY_25B),
over `LIMB_SPREAD_MIN` for the other; a midpoint distance under `MIDPOINT_MAX` for the limb-first set
(Human3.6M-17, BODY_25), over `MIDPOINT_MIN` for the face-first one. The set with more votes wins; a tie
(no evidence, or the two measures disagree) needs the set given (`keypoint_set=`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from ptrack.body.keypoints import H36M17
from ptrack.errors import InputError

#: the shared landmark vocabulary (name -> where it is); see the module docstring
LANDMARKS: dict[str, str] = {
    "nose": "tip of the nose",
    "head_top": "top of the head (vertex)",
    "upper_neck": "top of the neck, under the chin",
    "neck": "base of the neck, midway between the shoulders",
    "thorax": "top of the thoracic spine at shoulder height",
    "spine": "middle of the back",
    "pelvis": "midway between the hips",
    **{
        f"{s}_{part}": f"{side} {what}"
        for s, side in (("l", "left"), ("r", "right"))
        for part, what in (
            ("eye", "eye (centre)"),
            ("eye_inner", "eye, inner corner"),
            ("eye_outer", "eye, outer corner"),
            ("ear", "ear"),
            ("mouth", "corner of the mouth"),
            ("shoulder", "shoulder"),
            ("elbow", "elbow"),
            ("wrist", "wrist"),
            ("pinky", "hand, little-finger point"),
            ("index", "hand, index-finger point"),
            ("thumb", "hand, thumb point"),
            ("hip", "hip"),
            ("knee", "knee"),
            ("ankle", "ankle"),
            ("heel", "heel"),
            ("big_toe", "big toe tip"),
            ("small_toe", "little toe tip"),
            ("foot_index", "tip of the foot"),
        )
    },
}

#: median face spread / person size under which a 17- or 25-point file votes COCO-17 / BODY_25B ...
FACE_SPREAD_MAX = 0.2
#: ... and over which it votes Human3.6M-17 / BODY_25
LIMB_SPREAD_MIN = 0.3
#: median midpoint distance / person size under which a 17- or 25-point file votes Human3.6M-17 / BODY_25 ...
MIDPOINT_MAX = 0.05
#: ... and over which it votes COCO-17 / BODY_25B
MIDPOINT_MIN = 0.08


@dataclass(frozen=True)
class KeypointDefinition:
    """One detector's keypoint set.

    name: the registry name (e.g. "BODY_25B"); names: (K,) the format's keypoint names in its order;
    landmarks: (K,) the landmark of each keypoint (keys of `LANDMARKS`); pairs: (left, right) index pairs
    of keypoints that swap under a left/right mirror, derived from the landmarks; file_count: keypoints a
    person in a file of this format (133 for COCO-WholeBody, whose first K are kept), K otherwise;
    other_names: (K,) another spelling of the same keypoints that files are known to use (Pose2Sim's for
    BODY_25B, ptrack's simulated H36M17), or empty; source: where the order is published.
    """

    name: str
    names: tuple[str, ...]
    landmarks: tuple[str, ...]
    source: str
    file_count: int = 0
    other_names: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if len(self.names) != len(self.landmarks):
            raise ValueError(f"{self.name}: {len(self.names)} names but {len(self.landmarks)} landmarks")
        unknown = [m for m in self.landmarks if m not in LANDMARKS]
        if unknown:
            raise ValueError(f"{self.name}: landmarks not in the vocabulary: {unknown}")
        if len(set(self.landmarks)) != len(self.landmarks):
            raise ValueError(f"{self.name}: a landmark appears twice")
        if self.other_names and len(self.other_names) != len(self.names):
            raise ValueError(f"{self.name}: other_names must name every keypoint")
        if self.file_count == 0:
            object.__setattr__(self, "file_count", len(self.names))

    @property
    def num_keypoints(self) -> int:
        return len(self.names)

    @property
    def pairs(self) -> tuple[tuple[int, int], ...]:
        """(left, right) keypoint index pairs, in the order of the left keypoints."""
        pos = {m: i for i, m in enumerate(self.landmarks)}
        return tuple((i, pos["r_" + m[2:]]) for i, m in enumerate(self.landmarks) if m.startswith("l_"))

    def mirror_index(self) -> np.ndarray:
        """(K,) int permutation that swaps every left keypoint with its right partner."""
        perm = np.arange(self.num_keypoints)
        for a, b in self.pairs:
            perm[a], perm[b] = b, a
        return perm

    def index(self, name: str) -> int:
        """Index of a keypoint given by its name, its other name or its landmark."""
        for seq in (self.names, self.other_names, self.landmarks):
            if name in seq:
                return seq.index(name)
        raise InputError(f"keypoint set {self.name} has no keypoint {name!r} (keypoints: {', '.join(self.names)})")

    def landmark_index(self, landmark: str) -> int | None:
        """Index of the keypoint marking `landmark`, None when this set has none."""
        return self.landmarks.index(landmark) if landmark in self.landmarks else None


def _lr(*parts: str) -> tuple[str, ...]:
    """("l_a", "r_a", "l_b", "r_b", ...) for parts a, b, ..."""
    return tuple(f"{s}_{p}" for p in parts for s in "lr")


_COCO17_LANDMARKS = ("nose", *_lr("eye", "ear", "shoulder", "elbow", "wrist", "hip", "knee", "ankle"))
_COCO17_NAMES = (
    "nose",
    "left_eye",
    "right_eye",
    "left_ear",
    "right_ear",
    "left_shoulder",
    "right_shoulder",
    "left_elbow",
    "right_elbow",
    "left_wrist",
    "right_wrist",
    "left_hip",
    "right_hip",
    "left_knee",
    "right_knee",
    "left_ankle",
    "right_ankle",
)
# OpenPose's CamelCase spelling of the COCO body, shared by BODY_25B and HALPE-26
# OpenPose's six foot keypoints (BODY_25 and BODY_25B put them last, in this order) and their landmarks
_OPENPOSE_FEET = ("LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel")
_OPENPOSE_FEET_LANDMARKS = ("l_big_toe", "l_small_toe", "l_heel", "r_big_toe", "r_small_toe", "r_heel")
_COCO17_CAMEL = (
    "Nose",
    "LEye",
    "REye",
    "LEar",
    "REar",
    "LShoulder",
    "RShoulder",
    "LElbow",
    "RElbow",
    "LWrist",
    "RWrist",
    "LHip",
    "RHip",
    "LKnee",
    "RKnee",
    "LAnkle",
    "RAnkle",
)

# OpenPose BODY_25: doc/02_output.md ("Keypoint Ordering in C++/Python", POSE_BODY_25_BODY_PARTS) and
# src/openpose/pose/poseParameters.cpp of github.com/CMU-Perceptual-Computing-Lab/openpose. Neck is the
# point between the shoulders, MidHip the point between the hips.
BODY_25 = KeypointDefinition(
    name="BODY_25",
    names=(
        "Nose",
        "Neck",
        "RShoulder",
        "RElbow",
        "RWrist",
        "LShoulder",
        "LElbow",
        "LWrist",
        "MidHip",
        "RHip",
        "RKnee",
        "RAnkle",
        "LHip",
        "LKnee",
        "LAnkle",
        "REye",
        "LEye",
        "REar",
        "LEar",
        *_OPENPOSE_FEET,
    ),
    landmarks=(
        "nose",
        "neck",
        "r_shoulder",
        "r_elbow",
        "r_wrist",
        "l_shoulder",
        "l_elbow",
        "l_wrist",
        "pelvis",
        "r_hip",
        "r_knee",
        "r_ankle",
        "l_hip",
        "l_knee",
        "l_ankle",
        "r_eye",
        "l_eye",
        "r_ear",
        "l_ear",
        *_OPENPOSE_FEET_LANDMARKS,
    ),
    source="OpenPose doc/02_output.md, POSE_BODY_25_BODY_PARTS",
)

# OpenPose BODY_25B (experimental model): POSE_BODY_25B_BODY_PARTS in src/openpose/pose/poseParameters.cpp
# of the OpenPose repository; the model is described in github.com/CMU-Perceptual-Computing-Lab/openpose_train
# (experimental_models/README.md). The first 17 are the COCO order. Pose2Sim (Pose2Sim/skeletons.py, and
# the markers of its TRC files) calls 17 and 18 "Neck" and "Head"; OpenPose calls them UpperNeck, HeadTop:
# in ../shared/data/pose2sim the UpperNeck lies between the shoulders' midpoint and the nose, so it is the
# upper neck, not OpenPose BODY_25's Neck.
BODY_25B = KeypointDefinition(
    name="BODY_25B",
    names=(
        *_COCO17_CAMEL,
        "UpperNeck",
        "HeadTop",
        *_OPENPOSE_FEET,
    ),
    landmarks=(
        *_COCO17_LANDMARKS,
        "upper_neck",
        "head_top",
        *_OPENPOSE_FEET_LANDMARKS,
    ),
    other_names=(*_COCO17_CAMEL, "Neck", "Head", "LBigToe", "LSmallToe", "LHeel", "RBigToe", "RSmallToe", "RHeel"),
    source="OpenPose src/openpose/pose/poseParameters.cpp, POSE_BODY_25B_BODY_PARTS",
)

# COCO-17: the "person" category's keypoints of the COCO dataset (cocodataset.org/#format-data, the
# `keypoints` list of person_keypoints_*.json), as written by Detectron, MMPose, AlphaPose (COCO models),
# YOLO-pose.
COCO_17 = KeypointDefinition(
    name="COCO_17",
    names=_COCO17_NAMES,
    landmarks=_COCO17_LANDMARKS,
    source="COCO keypoint annotations (cocodataset.org/#format-data)",
)

# HALPE-26 (AlphaPose full body, and RTMPose's body8 models): github.com/Fang-Haoshu/Halpe-FullBody
# README.md ("26 body keypoints"); the same order in AlphaPose docs/MODEL_ZOO.md and Pose2Sim/skeletons.py.
# "Head" is the top of the head, "Neck" the base of the neck, "Hip" the point between the hips. The
# README's "Rknee" (index 14) is written RKnee, as AlphaPose and Pose2Sim do.
HALPE_26 = KeypointDefinition(
    name="HALPE_26",
    names=(
        *_COCO17_CAMEL,
        "Head",
        "Neck",
        "Hip",
        "LBigToe",
        "RBigToe",
        "LSmallToe",
        "RSmallToe",
        "LHeel",
        "RHeel",
    ),
    landmarks=(
        *_COCO17_LANDMARKS,
        "head_top",
        "neck",
        "pelvis",
        "l_big_toe",
        "r_big_toe",
        "l_small_toe",
        "r_small_toe",
        "l_heel",
        "r_heel",
    ),
    source="github.com/Fang-Haoshu/Halpe-FullBody README.md",
)

# COCO-WholeBody: github.com/jin-s13/COCO-WholeBody (README and data format): 17 COCO body points, 6 foot
# points (17-22), then 68 face (23-90), 21 left hand (91-111), 21 right hand (112-132). Names as in
# MMPose's configs/_base_/datasets/coco_wholebody.py. Only the body and feet are kept.
COCO_WHOLEBODY = KeypointDefinition(
    name="COCO_WHOLEBODY",
    names=(
        *_COCO17_NAMES,
        "left_big_toe",
        "left_small_toe",
        "left_heel",
        "right_big_toe",
        "right_small_toe",
        "right_heel",
    ),
    landmarks=(*_COCO17_LANDMARKS, "l_big_toe", "l_small_toe", "l_heel", "r_big_toe", "r_small_toe", "r_heel"),
    file_count=133,
    source="github.com/jin-s13/COCO-WholeBody (body 0-16, feet 17-22 of 133)",
)

# MediaPipe Pose (BlazePose, 33 landmarks): the PoseLandmark enum of mediapipe.solutions.pose and the
# pose landmarker guide (ai.google.dev/edge/mediapipe/solutions/vision/pose_landmarker, "Pose landmarker
# model": 0 nose ... 32 right foot index).
_MP_PARTS = (
    ("eye_inner", "eye", "eye_outer"),
    ("ear",),
    ("mouth",),
    ("shoulder", "elbow", "wrist", "pinky", "index", "thumb", "hip", "knee", "ankle", "heel", "foot_index"),
)
MEDIAPIPE_33 = KeypointDefinition(
    name="MEDIAPIPE_33",
    names=(
        "nose",
        "left_eye_inner",
        "left_eye",
        "left_eye_outer",
        "right_eye_inner",
        "right_eye",
        "right_eye_outer",
        "left_ear",
        "right_ear",
        "mouth_left",
        "mouth_right",
        *(f"{side}_{p}" for p in _MP_PARTS[3] for side in ("left", "right")),
    ),
    landmarks=(
        "nose",
        "l_eye_inner",
        "l_eye",
        "l_eye_outer",
        "r_eye_inner",
        "r_eye",
        "r_eye_outer",
        *_lr("ear", "mouth", *_MP_PARTS[3]),
    ),
    source="MediaPipe PoseLandmark (ai.google.dev/edge/mediapipe/solutions/vision/pose_landmarker)",
)

# Human3.6M, the 17 joints used by 2D-to-3D lifting work (VideoPose3D's h36m skeleton with its unused
# joints removed; MMPose configs/_base_/datasets/h36m.py), with the dataset's joint names. "Neck/Nose"
# (MMPose: neck_base) lies at the chin, i.e. the top of the neck; "Head" is the top of the head.
H36M_17 = KeypointDefinition(
    name="H36M_17",
    names=(
        "Hip",
        "RHip",
        "RKnee",
        "RFoot",
        "LHip",
        "LKnee",
        "LFoot",
        "Spine",
        "Thorax",
        "Neck/Nose",
        "Head",
        "LShoulder",
        "LElbow",
        "LWrist",
        "RShoulder",
        "RElbow",
        "RWrist",
    ),
    landmarks=(
        "pelvis",
        "r_hip",
        "r_knee",
        "r_ankle",
        "l_hip",
        "l_knee",
        "l_ankle",
        "spine",
        "thorax",
        "upper_neck",
        "head_top",
        "l_shoulder",
        "l_elbow",
        "l_wrist",
        "r_shoulder",
        "r_elbow",
        "r_wrist",
    ),
    other_names=H36M17,  # ptrack's own spelling, the simulated observations' keypoint_names
    source="Human3.6M 17-joint subset (VideoPose3D; MMPose configs/_base_/datasets/h36m.py)",
)

#: registry name -> keypoint set
KEYPOINT_SETS: dict[str, KeypointDefinition] = {
    d.name: d for d in (BODY_25, BODY_25B, COCO_17, HALPE_26, COCO_WHOLEBODY, MEDIAPIPE_33, H36M_17)
}

#: other accepted names (compared after `_key`: lower case, without "-", "_", " ")
_ALIASES: dict[str, str] = {
    "coco": "COCO_17",
    "halpe": "HALPE_26",
    "coco133": "COCO_WHOLEBODY",
    "cocowholebody133": "COCO_WHOLEBODY",
    "wholebody": "COCO_WHOLEBODY",
    "mediapipe": "MEDIAPIPE_33",
    "blazepose": "MEDIAPIPE_33",
    "h36m": "H36M_17",
    "human36m": "H36M_17",
}


def _key(name: str) -> str:
    return re.sub(r"[-_ .]", "", name.lower())


def get_keypoint_set(name: str) -> KeypointDefinition:
    """The keypoint set called `name` (case, "-" and "_" ignored: "coco-17", "body25b", "BlazePose").

    Raises InputError naming the known sets for an unknown name.
    """
    k = _key(str(name))
    for reg in KEYPOINT_SETS:
        if _key(reg) == k:
            return KEYPOINT_SETS[reg]
    if k in _ALIASES:
        return KEYPOINT_SETS[_ALIASES[k]]
    raise InputError(f"unknown keypoint set {name!r} (known: {', '.join(KEYPOINT_SETS)})")


def keypoint_sets_with_count(count: int) -> list[KeypointDefinition]:
    """The sets whose files carry `count` keypoints a person (K or `file_count`), in registry order."""
    return [d for d in KEYPOINT_SETS.values() if count in (d.num_keypoints, d.file_count)]


#: the ambiguous counts: (face-first set, limb-first set, the limb-first set's midpoint triplets (a, b, c))
_AMBIGUOUS: dict[int, tuple[str, str, tuple[tuple[int, int, int], ...]]] = {
    17: ("COCO_17", "H36M_17", ((8, 11, 14),)),
    25: ("BODY_25B", "BODY_25", ((8, 9, 12), (1, 2, 5))),
}


def _median_over_people(points: np.ndarray, need: list[int], measure) -> float | None:
    """Median over people showing every keypoint in `need` of measure(xy (K, 2)) / the person's size."""
    pts = np.asarray(points, dtype=float)
    ok = np.isfinite(pts).all(-1) & (pts[..., 2] > 0)
    values = []
    for p, m in zip(pts, ok, strict=True):
        if not m[need].all() or m.sum() < 3:
            continue
        size = np.linalg.norm(np.ptp(p[m, :2], axis=0))
        if size > 0:
            values.append(measure(p[:, :2]) / size)
    return float(np.median(values)) if values else None


def face_spread(points: np.ndarray) -> float | None:
    """Median over people of (bounding-box diagonal of keypoints 0-4) / (that of all their keypoints).

    points: (N, K, 3) [x, y, score] of N detected people (score <= 0 or non-finite: missing). People
    without all five first keypoints are skipped; None when nobody is left.
    """
    return _median_over_people(points, [0, 1, 2, 3, 4], lambda xy: np.linalg.norm(np.ptp(xy[:5], axis=0)))


def midpoint_distance(points: np.ndarray, a: int, b: int, c: int) -> float | None:
    """Median over people of |x_a - (x_b + x_c) / 2| / the person's size; points (N, K, 3) as in
    `face_spread`; None when nobody shows a, b and c."""
    return _median_over_people(points, [a, b, c], lambda xy: np.linalg.norm(xy[a] - (xy[b] + xy[c]) / 2))


def infer_keypoint_set(count: int, points: np.ndarray | None = None, source: str = "") -> KeypointDefinition:
    """The keypoint set of a file with `count` keypoints a person (rule in the module docstring).

    points: (N, count, 3) [x, y, score] of detected people, used to tell the 17- and 25-point sets apart.
    Raises InputError when no set has `count` keypoints or the content does not decide.
    """
    where = f"{source}: " if source else ""
    if count in _AMBIGUOUS:
        face, limb, triplets = _AMBIGUOUS[count]
        spread = mid = None
        if points is not None and len(points) > 0:
            spread = face_spread(points)
            mids = [m for t in triplets if (m := midpoint_distance(points, *t)) is not None]
            mid = max(mids) if mids else None
        votes = 0
        if spread is not None:
            votes += (spread < FACE_SPREAD_MAX) - (spread > LIMB_SPREAD_MIN)
        if mid is not None:
            votes += (mid > MIDPOINT_MIN) - (mid < MIDPOINT_MAX)
        if votes > 0:
            return KEYPOINT_SETS[face]
        if votes < 0:
            return KEYPOINT_SETS[limb]
        found = ", ".join(
            f"{what} {v:.2f}" if v is not None else f"no {what}"
            for what, v in (("face spread", spread), ("midpoint", mid))
        )
        raise InputError(
            f"{where}{count} keypoints a person could be {face} or {limb} and the content does not tell ({found}): "
            f"give the keypoint set (observations.keypoint_set)"
        )
    found_sets = keypoint_sets_with_count(count)
    if not found_sets:
        counts = sorted({n for d in KEYPOINT_SETS.values() for n in (d.num_keypoints, d.file_count)})
        raise InputError(
            f"{where}{count} keypoints a person matches no known keypoint set "
            f"(known counts: {', '.join(map(str, counts))}; sets: {', '.join(KEYPOINT_SETS)})"
        )
    return found_sets[0]
