"""Shared by the keypoint-file and person tests: a standing person drawn in any keypoint set, and where the
real Pose2Sim material is (../shared/data/pose2sim relative to the repo root)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ptrack.body.keypoint_sets import LANDMARKS, KeypointDefinition

POSE2SIM = (Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "pose2sim").resolve()
#: a few real OpenPose BODY_25B frames copied from POSE2SIM/two_people/pose/cam01_json (frames 2-5)
SHIPPED_FRAMES = Path(__file__).resolve().parent / "data" / "keypoints" / "two_people_cam01"


def pose2sim(relative: str) -> Path:
    """A path under the Pose2Sim folder; skips the test when it is absent."""
    p = POSE2SIM / relative
    if not p.exists():
        pytest.skip(f"Pose2Sim data not found at {p} (expected ../shared/data/pose2sim next to the repo)")
    return p


# a person standing, facing the camera (their left is the image's right): x right, y down, in units of
# their height, from the top of the head (y = 0) to the soles (y = 1)
_RIGHT_SIDE = {
    "eye": (0.02, 0.05),
    "eye_inner": (0.01, 0.05),
    "eye_outer": (0.03, 0.05),
    "ear": (0.045, 0.055),
    "mouth": (0.012, 0.085),
    "shoulder": (0.11, 0.18),
    "elbow": (0.13, 0.33),
    "wrist": (0.14, 0.46),
    "pinky": (0.145, 0.50),
    "index": (0.14, 0.51),
    "thumb": (0.12, 0.49),
    "hip": (0.06, 0.52),
    "knee": (0.065, 0.72),
    "ankle": (0.065, 0.93),
    "heel": (0.06, 0.96),
    "big_toe": (0.05, 1.0),
    "small_toe": (0.09, 0.99),
    "foot_index": (0.065, 1.0),
}
STANDING: dict[str, tuple[float, float]] = {
    "head_top": (0.0, 0.0),
    "nose": (0.0, 0.065),
    "upper_neck": (0.0, 0.11),
    "neck": (0.0, 0.18),
    "thorax": (0.0, 0.19),
    "spine": (0.0, 0.33),
    "pelvis": (0.0, 0.52),
    **{f"l_{k}": v for k, v in _RIGHT_SIDE.items()},
    **{f"r_{k}": (-v[0], v[1]) for k, v in _RIGHT_SIDE.items()},
}
assert set(STANDING) == set(LANDMARKS)


def person(kset: KeypointDefinition, x: float, y: float, height: float, score: float = 0.9) -> np.ndarray:
    """(K, 3) [x px, y px, score] of the standing person in `kset`, head top at (x, y), `height` pixels tall."""
    xy = np.array([STANDING[m] for m in kset.landmarks]) * height + [x, y]
    return np.concatenate([xy, np.full((kset.num_keypoints, 1), score)], axis=1)
