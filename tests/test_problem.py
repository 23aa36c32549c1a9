"""ptrack.problem: records, validation, and FK + projection for the cost terms."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from torch import Tensor

from ptrack.body.keypoints import make_keypoints
from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.errors import InputError
from ptrack.observe.camera import camera_for_motion
from ptrack.observe.observations import ChannelConfig, simulate_observations
from ptrack.problem import Keyframes, Problem, evaluate_pose

DATA = Path(__file__).resolve().parents[1] / "ptrack" / "data"


@pytest.fixture(scope="module")
def setup():
    sk = Skeleton.from_asf(DATA / "10.asf")
    q = load_amc(DATA / "10_02.amc", sk).q[:40:10]
    joints = sk.forward_kinematics(q)
    cam = camera_for_motion(joints, 6.0, 30.0, 10.0, 1000.0, 640, 480).to(dtype=torch.float64)
    kps = make_keypoints(sk)
    obs, _ = simulate_observations(
        joints,
        kps.index(),
        cam,
        torch.arange(4, dtype=torch.float64) / 30,
        ChannelConfig(noise_px=0.0),
        torch.Generator().manual_seed(0),
        kps.names,
    )
    return sk, q, cam, kps, obs


def test_evaluate_pose_shapes_and_values(setup):
    sk, q, cam, kps, obs = setup
    ev = evaluate_pose(sk, cam, kps, q.reshape(2, 2, -1), joint_pixels=True)
    assert ev.joints.shape == (2, 2, 31, 3) and ev.pixels.shape == (2, 2, 17, 2) and ev.depth.shape == (2, 2, 17)
    assert ev.joint_pixels.shape == (2, 2, 31, 2)
    torch.testing.assert_close(ev.pixels.reshape(4, 17, 2), obs.keypoints)  # noise-free observations
    assert evaluate_pose(sk, cam, kps, q).joint_pixels is None


def test_evaluate_pose_gradcheck(setup):
    sk, q, cam, kps, _ = setup
    x = q[:1].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda v: evaluate_pose(sk, cam, kps, v).pixels, (x,))


def test_problem_and_keyframe_validation(setup):
    sk, q, _, kps, obs = setup
    kf = Keyframes(frames=torch.tensor([0]), q=q[:1])
    assert Problem(sk, kps, obs, kf).keyframes is kf
    with pytest.raises(InputError, match="keyframes"):
        Keyframes(frames=torch.tensor([0, 1]), q=q[:1])
    with pytest.raises(InputError, match="mask"):
        Keyframes(frames=torch.tensor([0]), q=q[:1], mask=torch.ones(1, 3, dtype=torch.bool))
    with pytest.raises(InputError, match="dofs"):
        Problem(sk, kps, obs, Keyframes(frames=torch.tensor([0]), q=q[:1, :10]))
    other = make_keypoints(sk, {"pelvis": "root", "head": "head"})
    with pytest.raises(InputError, match="keypoints"):
        Problem(sk, other, obs)


def _keyed(setup, kf_frames: list[int], jk_frame: int) -> tuple[Problem, Tensor]:
    """The setup's problem with angle keyframes (the true poses, std 0.1) on kf_frames and one joint keyframe
    (every joint at 0, std 0.02) on jk_frame -> (problem, the keyframes' poses (F, D))."""
    from ptrack.problem import JointKeyframes

    sk, q_all, _cam, kps, obs = setup
    q = q_all[kf_frames].to(obs.keypoints)
    kf = Keyframes(torch.tensor(kf_frames), q, sigma=torch.full_like(q, 0.1))
    jk = JointKeyframes(
        torch.tensor([jk_frame]),
        torch.zeros(1, sk.num_joints, 3),
        torch.ones(1, sk.num_joints, dtype=torch.bool),
        torch.tensor([0.02]),
    )
    return Problem(sk, kps, obs, kf, jk), q


def test_later_frames(setup):
    """A problem's frames from `start` on: observations and masks sliced, keyframes renumbered (earlier ones
    dropped), correspondences left out."""
    from ptrack.problem import later_frames

    sk, _q_all, _cam, _kps, obs = setup
    t = obs.num_frames
    full, _ = _keyed(setup, [0, t - 1], 1)
    tail = later_frames(full, 2)
    assert tail.observations.num_frames == t - 2
    assert torch.equal(tail.observations.keypoints, obs.keypoints[2:])
    assert torch.equal(tail.observations.times, obs.times[2:])
    assert tail.keyframes is not None and tail.keyframes.frames.tolist() == [t - 3]
    assert tail.keyframes.sigma is not None and tail.keyframes.sigma.shape == (1, sk.num_dofs)
    assert tail.joint_keyframes is None  # its only frame (1) is before the start
    assert tail.correspondences is None
    with pytest.raises(ValueError, match="start"):
        later_frames(full, t)


def test_every_nth(setup):
    """A problem over every n-th frame: observations and times strided (the frame interval n times longer),
    keyframes on those frames renumbered (the others dropped), correspondences left out; n = 1 is the problem."""
    from ptrack.problem import every_nth

    sk, _q_all, _cam, _kps, obs = setup
    t = obs.num_frames
    full, q = _keyed(setup, [0, 1], 2)
    assert every_nth(full, 1) is full
    half = every_nth(full, 2)
    assert half.observations.num_frames == (t + 1) // 2
    assert torch.equal(half.observations.keypoints, obs.keypoints[::2])
    assert half.observations.frame_interval == pytest.approx(2 * obs.frame_interval)
    assert half.keyframes is not None and half.keyframes.frames.tolist() == [0]  # frame 1 is not tracked
    assert torch.equal(half.keyframes.q, q[:1])
    assert half.joint_keyframes is not None and half.joint_keyframes.frames.tolist() == [1]  # frame 2 -> 1
    assert half.correspondences is None and half.skeleton is sk
    with pytest.raises(ValueError, match="at least 1"):
        every_nth(full, 0)
