"""Tests for ptrack.motion.key_postures: the rules, the golf swing's key postures on the 7 CMU dev swings of
subject 64 (3D, checked against postures located independently of the detector), and the 2D detector
on projected wrist tracks (image y down)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import Tensor

from ptrack.body.skeleton import Skeleton
from ptrack.errors import InputError
from ptrack.motion.key_postures import (
    Rule,
    detect_key_postures,
    detect_key_postures_2d,
    initial_times,
    parse_rule,
    parse_rules,
)
from ptrack.observe.camera import camera_for_motion
from ptrack.pipeline.config import MotionConfig

SWINGS = ("64_01", "64_02", "64_04", "64_05", "64_06", "64_08", "64_09")


@pytest.fixture(scope="module")
def swings(cmu_file):
    """name -> (skeleton, joints (T, J, 3)) of the 7 dev swings at 120 fps."""
    sk = Skeleton.from_asf(cmu_file("64.asf"))
    out = {}
    for name in SWINGS:
        with torch.no_grad():
            out[name] = (sk, sk.forward_kinematics(sk.load_amc(cmu_file(f"{name}.amc")).q))
    return out


def test_parse_rule():
    assert parse_rule("max height") == Rule("max", "height", "global", None, None)
    assert parse_rule("first min height after top") == Rule("min", "height", "first", "after", "top")
    assert parse_rule("rest before top") == Rule("rest", "speed", "global", "before", "top")
    assert parse_rule("min speed after hit within 0.8 s") == Rule("min", "speed", "global", "after", "hit", 0.8)
    assert parse_rule("last max speed before x within 2s").within_s == 2.0


@pytest.mark.parametrize(
    "rules, message",
    [
        ({"a": "max height"}, "at least 2 key postures"),
        ({"a": "max height", "b": "highest"}, "cannot read rule 'highest'"),
        ({"a": "max height", "b": "rest"}, "cannot read rule 'rest'"),
        ({"a": "max height", "b": "max height within 1 s"}, "cannot read rule"),
        ({"a": "max height", "b": "min height after c"}, "unknown key posture 'c'"),
        ({"a": "max height after b", "b": "min height after a"}, "in a cycle"),
    ],
)
def test_bad_rules(rules, message):
    with pytest.raises(InputError, match=message):
        parse_rules(rules)


def _independent_postures(sk: Skeleton, joints: Tensor) -> np.ndarray:
    """The four golf postures located without the detector: other joints (the hand ends, not the wrists),
    no smoothing, displacements instead of speeds, and the ball hit as the hands' return to the address."""
    x = joints.numpy()
    hand = (x[:, sk.joint_index("lhand")] + x[:, sk.joint_index("rhand")]) / 2
    step = np.linalg.norm(hand[6:] - hand[:-6], axis=1)  # metres moved over the next 50 ms
    fastest = int(np.argmax(step))
    top = int(np.argmax(hand[:fastest, 1]))  # top of the backswing: the hands highest before the downswing
    away = np.linalg.norm(hand - hand[0], axis=1)
    gone = int(np.nonzero(away > 0.10)[0][0])  # 10 cm from the address: the takeaway is under way
    start = int(np.nonzero(step[:gone] < 0.01)[0][-1])  # the last still moment before it
    hit = top + int(np.argmin(away[top : fastest + 60]))  # the hands back at the address
    end = hit + 10 + int(np.argmin(step[hit + 10 : hit + 96]))  # the finish: the hands' slowest after the hit
    return np.array([start, top, hit, end])


def test_golf_key_postures_on_the_dev_swings(swings):
    cfg = MotionConfig()
    assert tuple(cfg.key_postures) == ("start", "top", "hit", "end")
    for name, (sk, joints) in swings.items():
        found = detect_key_postures(joints, sk, 120.0, cfg, clip=name).numpy()
        truth = _independent_postures(sk, joints)
        # within 6 frames (50 ms at 120 fps); the hit within 2
        err = np.abs(found - truth)
        assert np.all(err <= [6, 6, 2, 6]), (name, found, truth)
        assert np.all(np.diff(found) > 20), (name, found)


def test_golf_key_postures_from_projected_wrists(swings):
    """The tracker's start: the 2D wrist track at 30 fps with 2 px noise, from several directions, gives the
    3D postures' frames to within a few frames (image y grows downward)."""
    cfg = MotionConfig()
    g = torch.Generator().manual_seed(0)
    errors = []
    for name, (sk, joints) in swings.items():
        truth = detect_key_postures(joints, sk, 120.0, cfg).numpy()
        wrists = joints[::4][:, [sk.joint_index("lradius"), sk.joint_index("rradius")]]
        for azimuth in (0.0, 45.0, 90.0):
            cam = camera_for_motion(joints, 5.0, azimuth, 10.0, 1000.0, 640, 480)
            uv = cam.project(wrists).pixels
            uv = uv + 2.0 * torch.randn(uv.shape, generator=g, dtype=uv.dtype)
            found = detect_key_postures_2d(uv, 30.0, cfg, clip=name).numpy()
            errors.append(np.abs(found * 4 - truth) / 4)  # in 30 fps frames
    errors = np.array(errors)
    assert errors.max() <= 6, errors.max(0)
    assert np.all(errors.mean(0) <= 2), errors.mean(0)
    # one wrist alone, the image upside down (y up) no longer finds the top of the swing
    sk, joints = swings["64_01"]
    cam = camera_for_motion(joints, 5.0, 30.0, 10.0, 1000.0, 640, 480)
    uv = cam.project(joints[::4, sk.joint_index("lradius")]).pixels
    truth = detect_key_postures(joints, sk, 120.0, cfg).numpy()
    assert np.all(np.abs(detect_key_postures_2d(uv, 30.0, cfg).numpy() * 4 - truth) <= 12)
    flipped = uv * torch.tensor([1.0, -1.0])
    try:
        wrong = detect_key_postures_2d(flipped, 30.0, cfg).numpy()
        assert abs(wrong[1] * 4 - truth[1]) > 12
    except InputError:
        pass


def test_2d_detector_with_missing_points(swings):
    sk, joints = swings["64_05"]
    cfg = MotionConfig()
    truth = detect_key_postures(joints, sk, 120.0, cfg).numpy()
    wrists = joints[::4][:, [sk.joint_index("lradius"), sk.joint_index("rradius")]]
    uv = camera_for_motion(joints, 5.0, 30.0, 10.0, 1000.0, 640, 480).project(wrists).pixels
    g = torch.Generator().manual_seed(1)
    valid = torch.rand(uv.shape[:2], generator=g) > 0.2  # a fifth of the points missing
    uv = torch.where(valid[..., None], uv, torch.full_like(uv, 1e6))  # whatever they hold is ignored
    uv[3, 0] = float("nan")
    found = detect_key_postures_2d(uv, 30.0, cfg, valid=valid).numpy()
    assert np.all(np.abs(found * 4 - truth) <= 24), (found * 4, truth)  # 6 frames at 30 fps, as without gaps
    with pytest.raises(InputError, match="valid mask"):
        detect_key_postures_2d(uv, 30.0, cfg, valid=valid[:-1])
    with pytest.raises(InputError, match="seen in 0 frames"):
        detect_key_postures_2d(uv, 30.0, cfg, valid=torch.zeros_like(valid))
    with pytest.raises(InputError, match="shape"):
        detect_key_postures_2d(uv[..., :1], 30.0, cfg)


def test_not_found_names_the_clip(swings):
    sk, joints = swings["64_01"]
    still = joints[:100]  # the golfer at the address: no swing
    with pytest.raises(InputError, match=r"^64_01-address: key posture"):
        detect_key_postures(still, sk, 120.0, MotionConfig(), clip="64_01-address")
    with pytest.raises(InputError, match="no joint 'lpalm'"):
        detect_key_postures(joints, sk, 120.0, MotionConfig(joints=("lpalm",)), clip="x")


def test_initial_times():
    mu = initial_times(torch.tensor([10, 40, 60, 90]), torch.tensor([0.0, 0.45, 0.7, 1.0], dtype=torch.float64), 100)
    assert mu.shape == (100,) and mu.dtype == torch.float64
    assert torch.allclose(mu[[10, 40, 60, 90]], torch.tensor([0.0, 0.45, 0.7, 1.0], dtype=torch.float64))
    assert torch.all(mu[:11] == 0) and torch.all(mu[90:] == 1)
    assert torch.all(mu.diff() >= 0)
    with pytest.raises(InputError, match="increasing"):
        initial_times([10, 5], torch.tensor([0.0, 1.0]), 20)
