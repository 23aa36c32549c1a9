"""The floor under a person from its feet (`ptrack.estimators.ground.floor_from_feet`)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ptrack.estimators.ground import MIN_CONTACTS, floor_from_feet


def _rotation(axis, deg: float) -> np.ndarray:
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = math.radians(deg)
    return np.eye(3) + math.sin(t) * K + (1 - math.cos(t)) * K @ K


def _walk(T: int = 120, rng=None, spread_m: float = 3.0, lateral_m: float = 1.5) -> np.ndarray:
    """(T, 4, 3) toe and heel points of two feet on the floor y = 0 walking over a patch of the floor, one foot
    in the air every other half-second (its points 5-25 cm up), on a level floor."""
    rng = rng or np.random.default_rng(0)
    t = np.arange(T) / 30.0
    path = np.stack([spread_m * (t / t[-1] - 0.5), np.zeros(T), lateral_m * np.sin(2 * t)], axis=1)  # (T, 3)
    feet = np.repeat(path[:, None], 4, axis=1) + np.array(
        [[0.1, 0, 0.1], [-0.1, 0, 0.1], [0.1, 0, -0.1], [-0.1, 0, -0.1]]
    )
    swing = (np.floor(t * 2) % 2 == 1)[:, None] & (np.arange(4) >= 2)[None]  # the second foot lifts
    feet[..., 1] += np.where(swing, rng.uniform(0.05, 0.25, (T, 1)), 0.0)
    return feet


@pytest.mark.parametrize("tilt", [5.0, 20.0])
def test_walking_feet_give_the_floors_tilt_and_height(tilt):
    rng = np.random.default_rng(1)
    R = _rotation([1.0, 0.0, 0.3], tilt)
    level = _walk(rng=rng)
    feet = level @ R.T + np.array([0.0, -1.3, 4.0]) @ R.T  # the floor 1.3 m under the origin, tilted
    feet += rng.normal(0.0, 0.01, feet.shape)
    fit = floor_from_feet(feet, np.array([0.0, 1.0, 0.0]), clearance_m=0.0)
    assert fit is not None
    true_up = R @ np.array([0.0, 1.0, 0.0])
    assert math.degrees(math.acos(min(1.0, float(fit.normal @ true_up)))) < 1.5  # ridge shrink + noise
    assert fit.tilt_deg == pytest.approx(tilt, abs=1.5)
    on_floor = feet[level[..., 1] == 0]  # the standing feet's points lie on the fitted plane (where they are)
    assert np.median(np.abs(on_floor @ fit.normal - fit.height_m)) < 0.03
    assert fit.contacts > 60 and fit.spread_m[0] > 0.5


def test_a_person_in_one_place_keeps_the_guess_and_finds_the_height():
    rng = np.random.default_rng(2)
    feet = _walk(rng=rng, spread_m=0.0, lateral_m=0.0) + np.array([0.0, -1.0, 3.0]) + rng.normal(0, 0.01, (120, 4, 3))
    fit = floor_from_feet(feet, np.array([0.0, 1.0, 0.0]), clearance_m=0.02)
    assert fit is not None and fit.tilt_deg < 2.0  # contacts spread 0.1 m: the ridge keeps the guess
    assert fit.height_m == pytest.approx(-1.02, abs=0.02)  # the lowest point sits clearance_m above the floor


def test_too_few_frames_or_nan_give_none():
    feet = _walk()
    assert floor_from_feet(feet[: MIN_CONTACTS - 1], np.array([0.0, 1.0, 0.0])) is None
    feet[MIN_CONTACTS - 1 :] = np.nan
    assert floor_from_feet(feet, np.array([0.0, 1.0, 0.0])) is None
