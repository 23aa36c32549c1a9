"""Detector keypoint sets: the registry, names against landmarks, and the choice of a set from a count."""

from __future__ import annotations

import numpy as np
import pytest
from keypoint_fixtures import person, pose2sim

from ptrack.body.keypoint_sets import (
    BODY_25,
    BODY_25B,
    COCO_17,
    H36M_17,
    KEYPOINT_SETS,
    LANDMARKS,
    get_keypoint_set,
    infer_keypoint_set,
)
from ptrack.errors import InputError


def _side(name: str) -> str | None:
    """'l' / 'r' / None from a format's spelling of a keypoint name."""
    low = name.lower()
    if low.startswith(("left", "l_")) or low.endswith("_left") or (name[0] == "L" and name[1].isupper()):
        return "l"
    if low.startswith(("right", "r_")) or low.endswith("_right") or (name[0] == "R" and name[1].isupper()):
        return "r"
    return None


@pytest.mark.parametrize("name", list(KEYPOINT_SETS))
def test_set_names_agree_with_landmarks(name):
    d = KEYPOINT_SETS[name]
    assert len(set(d.names)) == d.num_keypoints == len(d.landmarks)
    assert set(d.landmarks) <= set(LANDMARKS)
    for n, m in zip(d.names, d.landmarks, strict=True):
        side = m[0] if m[:2] in ("l_", "r_") else None
        assert _side(n) == side, (n, m)
    pairs = d.pairs
    assert all(d.landmarks[a] == "l_" + d.landmarks[b][2:] for a, b in pairs)
    perm = d.mirror_index()
    assert (perm[perm] == np.arange(d.num_keypoints)).all()
    assert sum(m[:2] in ("l_", "r_") for m in d.landmarks) == 2 * len(pairs)


def test_known_orders_from_their_sources():
    # OpenPose doc/02_output.md: BODY_25 index 8 is MidHip, 1 Neck; pose2sim README: BODY_25B 17 Neck, 18 Head
    assert BODY_25.names[1] == "Neck" and BODY_25.names[8] == "MidHip" and BODY_25.names[24] == "RHeel"
    assert BODY_25B.names[:17] == KEYPOINT_SETS["HALPE_26"].names[:17]
    assert BODY_25B.other_names[17:19] == ("Neck", "Head")
    assert BODY_25B.landmarks[17:19] == ("upper_neck", "head_top")
    assert KEYPOINT_SETS["HALPE_26"].names[17:20] == ("Head", "Neck", "Hip")
    assert KEYPOINT_SETS["COCO_WHOLEBODY"].file_count == 133 and KEYPOINT_SETS["COCO_WHOLEBODY"].num_keypoints == 23
    mp = KEYPOINT_SETS["MEDIAPIPE_33"]
    assert mp.names[0] == "nose" and mp.names[11] == "left_shoulder" and mp.names[32] == "right_foot_index"
    assert H36M_17.landmarks[0] == "pelvis" and H36M_17.names[9] == "Neck/Nose"
    assert COCO_17.index("right_ankle") == 16 == COCO_17.index("r_ankle")
    assert H36M_17.index("neck") == 9  # ptrack's simulated H36M17 spelling


def test_pose2sim_markers_are_body25b_names():
    trc = pose2sim("balancing/triangulated.trc")
    markers = trc.read_text().splitlines()[3].split("\t")[2:]
    markers = [m for m in markers if m]
    assert len(markers) == 21
    assert set(markers) <= set(BODY_25B.other_names)


@pytest.mark.parametrize(
    "name, expected",
    [("coco-17", "COCO_17"), ("Body25B", "BODY_25B"), ("blazepose", "MEDIAPIPE_33"), ("coco133", "COCO_WHOLEBODY")],
)
def test_get_keypoint_set_names(name, expected):
    assert get_keypoint_set(name).name == expected


def test_get_keypoint_set_unknown_lists_known():
    with pytest.raises(InputError, match=r"unknown keypoint set 'body_99'.*BODY_25B.*H36M_17"):
        get_keypoint_set("body_99")


@pytest.mark.parametrize(
    "count, expected", [(26, "HALPE_26"), (33, "MEDIAPIPE_33"), (133, "COCO_WHOLEBODY"), (23, "COCO_WHOLEBODY")]
)
def test_infer_unique_counts(count, expected):
    assert infer_keypoint_set(count).name == expected


@pytest.mark.parametrize("kset", [COCO_17, H36M_17, BODY_25, BODY_25B])
def test_infer_ambiguous_counts_by_content(kset):
    rng = np.random.default_rng(0)
    people = np.stack([person(kset, rng.uniform(0, 800), rng.uniform(0, 300), rng.uniform(200, 900)) for _ in range(6)])
    people[..., :2] += rng.normal(0, 2, people[..., :2].shape)
    assert infer_keypoint_set(kset.num_keypoints, people).name == kset.name


def test_infer_ambiguous_without_evidence_asks_for_the_set():
    p = person(BODY_25B, 100, 100, 500)
    p[[0, 1, 2, 8, 9], 2] = 0  # neither the face nor the midpoint triplets
    with pytest.raises(InputError, match=r"BODY_25B or BODY_25.*keypoint_set"):
        infer_keypoint_set(25, p[None])
    with pytest.raises(InputError, match="COCO_17 or H36M_17"):
        infer_keypoint_set(17)


def test_infer_unknown_count():
    with pytest.raises(InputError, match="20 keypoints a person matches no known keypoint set"):
        infer_keypoint_set(20, source="x.json")
