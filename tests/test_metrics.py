import math

import numpy as np
import pytest
import torch
from scipy.linalg import orthogonal_procrustes
from scipy.spatial.transform import Rotation

from ptrack.errors import InputError
from ptrack.pipeline import metrics as M
from ptrack.pipeline.metrics import (
    JointLimitReport,
    accel_error,
    best_of_k_mpjpe,
    flip_error_rate,
    joint_limit_violations,
    limb_flip_errors,
    mpjpe,
    mpjpe_absolute,
    pa_mpjpe,
    reprojection_error_px,
)

NAN = float("nan")


def _gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def _skeleton(*shape: int, seed: int = 0, dtype=torch.float64) -> torch.Tensor:
    return torch.randn(*shape, 3, generator=_gen(seed), dtype=dtype) * 0.3


def _rotation(seed: int, dtype=torch.float64) -> torch.Tensor:
    return torch.as_tensor(Rotation.random(random_state=seed).as_matrix(), dtype=dtype)


# ---------------------------------------------------------------- mpjpe / absolute


def test_constant_offset_is_zero_after_root_alignment_but_not_absolute():
    gt = _skeleton(4, 17)
    offset = torch.tensor([0.3, -0.4, 0.0], dtype=gt.dtype)  # 0.5 m
    pred = gt + offset
    torch.testing.assert_close(mpjpe(pred, gt), torch.zeros(4, dtype=gt.dtype), atol=1e-9, rtol=0)
    torch.testing.assert_close(mpjpe_absolute(pred, gt), torch.full((4,), 500.0, dtype=gt.dtype))


def test_mpjpe_exact_single_joint_error():
    gt = torch.zeros(4, 3)
    gt[1:, 1] = torch.tensor([0.1, 0.2, 0.3])
    pred = gt.clone()
    pred[2, 0] += 0.1  # one of four joints off by 100 mm
    assert mpjpe(pred, gt).shape == ()
    torch.testing.assert_close(mpjpe(pred, gt), torch.tensor(25.0))
    # Root on the displaced joint: the other three move by 100 mm relative to it.
    torch.testing.assert_close(mpjpe(pred, gt, root=2), torch.tensor(75.0))
    torch.testing.assert_close(mpjpe(pred, gt, root=-2), torch.tensor(75.0))


def test_mpjpe_absolute_camera_frame_matches_world():
    gt = _skeleton(3, 10, seed=1)
    pred = gt + 0.05 * torch.randn(gt.shape, generator=_gen(2), dtype=gt.dtype)
    R, t = _rotation(3), torch.tensor([0.1, 0.2, 4.0], dtype=gt.dtype)
    torch.testing.assert_close(mpjpe_absolute(pred, gt, R, t), mpjpe_absolute(pred, gt))
    with pytest.raises(InputError, match="both R and t"):
        mpjpe_absolute(pred, gt, R=R)
    with pytest.raises(InputError, match=r"R must have shape \(3, 3\)"):
        mpjpe_absolute(pred, gt, R=torch.eye(4), t=t)
    with pytest.raises(InputError, match=r"t must have shape \(3,\)"):
        mpjpe_absolute(pred, gt, R=R, t=torch.zeros(1, 3))


def test_mpjpe_accepts_numpy_and_follows_dtype():
    gt = np.random.default_rng(0).normal(size=(5, 6, 3))
    pred = gt + 0.01
    out = mpjpe_absolute(pred.astype(np.float32), gt.astype(np.float32))
    assert out.dtype == torch.float32 and out.shape == (5,)
    np.testing.assert_allclose(out.numpy(), 10.0 * math.sqrt(3), rtol=1e-4)
    assert mpjpe(pred, gt).dtype == torch.float64


def test_mpjpe_batched_matches_loop():
    gt, pred = _skeleton(2, 5, 7, seed=4), _skeleton(2, 5, 7, seed=5)
    out = mpjpe(pred, gt, root=3)
    assert out.shape == (2, 5)
    for i in range(2):
        for j in range(5):
            torch.testing.assert_close(out[i, j], mpjpe(pred[i, j], gt[i, j], root=3))


def test_mpjpe_bad_shapes_raise():
    with pytest.raises(InputError, match=r"pred and gt .* \(4, 5, 3\) and \(4, 6, 3\)"):
        mpjpe(torch.zeros(4, 5, 3), torch.zeros(4, 6, 3))
    with pytest.raises(InputError, match=r"pred must have shape .* got \(4, 5, 2\)"):
        mpjpe(torch.zeros(4, 5, 2), torch.zeros(4, 5, 2))
    with pytest.raises(InputError, match="root=5"):
        mpjpe(torch.zeros(4, 5, 3), torch.zeros(4, 5, 3), root=5)


def test_mpjpe_gradcheck():
    gt = _skeleton(2, 5, seed=6)
    pred = _skeleton(2, 5, seed=7).requires_grad_()
    assert torch.autograd.gradcheck(lambda p: mpjpe(p, gt, root=1), (pred,))
    R, t = _rotation(8), torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda p: mpjpe_absolute(p, gt, R, t), (pred,))


# ---------------------------------------------------------------- pa_mpjpe


def test_pa_mpjpe_removes_similarity_transform():
    gt = _skeleton(3, 15, seed=10)
    R, s, t = _rotation(11), 1.7, torch.tensor([0.5, -1.0, 2.0], dtype=gt.dtype)
    pred = s * gt @ R.T + t
    torch.testing.assert_close(pa_mpjpe(pred, gt), torch.zeros(3, dtype=gt.dtype), atol=1e-8, rtol=0)
    assert (mpjpe(pred, gt) > 10.0).all()


def test_pa_mpjpe_does_not_align_away_reflection():
    gt = _skeleton(2, 15, seed=12)
    pred = gt * torch.tensor([-1.0, 1.0, 1.0], dtype=gt.dtype)
    assert (pa_mpjpe(pred, gt) > 20.0).all()
    # With a reflection allowed (scipy's orthogonal Procrustes) the mirror would vanish.
    for p, g in zip(pred.numpy(), gt.numpy()):
        pc, gc = p - p.mean(0), g - g.mean(0)
        rot, _ = orthogonal_procrustes(pc, gc)
        assert np.linalg.det(rot) < 0
        np.testing.assert_allclose(pc @ rot, gc, atol=1e-9)


def _pa_reference(pred: np.ndarray, gt: np.ndarray) -> float:
    pc, gc = pred - pred.mean(0), gt - gt.mean(0)
    rot, sv_sum = orthogonal_procrustes(pc, gc)
    assert np.linalg.det(rot) > 0  # the data below is built so no reflection is optimal
    scale = sv_sum / (pc**2).sum()
    aligned = scale * pc @ rot + gt.mean(0)
    return float(np.linalg.norm(aligned - gt, axis=-1).mean() * 1000.0)


def test_pa_mpjpe_matches_scipy_reference():
    gt = _skeleton(20, 17, seed=13)
    rots = torch.as_tensor(Rotation.random(20, random_state=14).as_matrix())
    noise = 0.05 * torch.randn(gt.shape, generator=_gen(15), dtype=gt.dtype)
    pred = 0.8 * (gt + noise) @ rots.transpose(-1, -2) + 0.3
    out = pa_mpjpe(pred, gt)
    ref = [_pa_reference(p, g) for p, g in zip(pred.numpy(), gt.numpy())]
    np.testing.assert_allclose(out.numpy(), ref, rtol=1e-9)
    assert (out > 1.0).all()


def test_pa_mpjpe_batched_float32_and_nan_frames():
    gt = _skeleton(2, 3, 12, seed=16, dtype=torch.float32)
    pred = gt + 0.02 * torch.randn(gt.shape, generator=_gen(17))
    pred[1, 2, 4, 0] = NAN
    out = pa_mpjpe(pred, gt)
    assert out.shape == (2, 3) and out.dtype == torch.float32
    assert torch.isnan(out[1, 2]) and torch.isfinite(out.flatten()[:-1]).all()
    torch.testing.assert_close(out[0, 1], pa_mpjpe(pred[0, 1], gt[0, 1]))


def test_pa_mpjpe_collapsed_prediction_is_finite():
    gt = _skeleton(6, seed=18)
    pred = torch.zeros_like(gt)  # all joints at one point: scale goes to 0, pred lands on gt's mean
    expected = torch.linalg.vector_norm(gt - gt.mean(0), dim=-1).mean() * 1000.0
    torch.testing.assert_close(pa_mpjpe(pred, gt), expected)


def test_pa_mpjpe_gradcheck():
    gt = _skeleton(2, 6, seed=19)
    pred = (gt @ _rotation(20).T + 0.1 * _skeleton(2, 6, seed=21)).requires_grad_()
    assert torch.autograd.gradcheck(lambda p: pa_mpjpe(p, gt), (pred,))


# ---------------------------------------------------------------- accel_error


def test_accel_error_constant_velocity_vs_shifted_is_zero():
    T = 8
    x0, v = _skeleton(5, seed=22), _skeleton(5, seed=23) * 0.1
    frames = torch.arange(T, dtype=torch.float64)[:, None, None]
    gt = x0 + frames * v
    pred = gt + torch.tensor([1.0, 2.0, 3.0], dtype=gt.dtype)
    out = accel_error(pred, gt)
    assert out.shape == (T - 2,)
    torch.testing.assert_close(out, torch.zeros(T - 2, dtype=gt.dtype), atol=1e-9, rtol=0)


def test_accel_error_exact_bump():
    gt = torch.zeros(5, 2, 3)
    pred = gt.clone()
    pred[2, 0, 0] = 0.01  # 10 mm bump in one joint of two
    torch.testing.assert_close(accel_error(pred, gt), torch.tensor([5.0, 10.0, 5.0]))


def test_accel_error_root_centred_ignores_root_jitter():
    """VIBE's definition subtracts the pelvis: a jittering root with a rigid body scores 0 with
    root=0 and the jitter itself without."""
    gen = torch.Generator().manual_seed(3)
    T, J = 6, 4
    body = torch.randn(1, J, 3, generator=gen, dtype=torch.float64).expand(T, J, 3)
    jitter = torch.zeros(T, 1, 3, dtype=torch.float64)
    jitter[2, 0, 0] = 0.01  # 10 mm sideways at frame 2
    pred = body + jitter
    torch.testing.assert_close(accel_error(pred, body, root=0), torch.zeros(T - 2, dtype=torch.float64))
    torch.testing.assert_close(accel_error(pred, body), torch.tensor([10.0, 20.0, 10.0, 0.0], dtype=torch.float64))
    with pytest.raises(InputError, match="root=7"):
        accel_error(pred, body, root=7)


def test_accel_error_batched_shapes_and_gradcheck():
    gt, pred = _skeleton(2, 6, 4, seed=24), _skeleton(2, 6, 4, seed=25)
    out = accel_error(pred, gt)
    assert out.shape == (2, 4)
    torch.testing.assert_close(out[1], accel_error(pred[1], gt[1]))
    p = pred[0].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda x: accel_error(x, gt[0]), (p,))
    with pytest.raises(InputError, match="at least 3 frames"):
        accel_error(pred[0, :2], gt[0, :2])
    with pytest.raises(InputError, match=r"pred must have shape \(\.\.\., T, J, 3\)"):
        accel_error(pred[0, 0], gt[0, 0])


# ---------------------------------------------------------------- limb flips


def _mirror_end_in_depth(joints: torch.Tensor, start: int, end: int, R, t) -> torch.Tensor:
    """Mirror joint `end` in camera depth around joint `start` (same image-plane offset)."""
    cam = joints @ R.T + t
    cam[..., end, 2] = 2 * cam[..., start, 2] - cam[..., end, 2]
    return (cam - t) @ R  # back to world


def test_limb_flip_detects_depth_mirrored_limb():
    R, t = _rotation(26), torch.tensor([0.0, 0.0, 5.0], dtype=torch.float64)
    cam = torch.tensor(  # camera-frame joints: 0 root, 1 and 2 in front/behind of it, 3 far off
        [[[0.0, 0.0, 0.0], [0.1, 0.2, 0.3], [0.0, 0.3, -0.2], [0.5, 0.0, 0.1]]], dtype=torch.float64
    ).repeat(3, 1, 1)
    cam[2, 3, 2] = 0.01  # frame 2: limb (0, 3) near-parallel to the image plane
    gt = (cam - t) @ R
    pred = _mirror_end_in_depth(gt, 0, 1, R, t)
    limbs = [(0, 1), (0, 2), (0, 3)]
    flips = limb_flip_errors(pred, gt, limbs, R, t)
    expected = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 0.0, NAN]], dtype=torch.float64)
    torch.testing.assert_close(flips, expected, equal_nan=True)
    # The mirrored limb has the same length and the same image-plane offset.
    torch.testing.assert_close(
        torch.linalg.vector_norm(pred[:, 1] - pred[:, 0], dim=-1),
        torch.linalg.vector_norm(gt[:, 1] - gt[:, 0], dim=-1),
    )
    # Reversed limb direction is flipped the same way; numpy limbs work too.
    torch.testing.assert_close(limb_flip_errors(pred, gt, np.array([[1, 0]]), R, t)[:, 0], expected[:, 0])
    rate = flip_error_rate(flips)
    torch.testing.assert_close(rate, torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(flips.nanmean(), torch.tensor(3.0 / 8.0, dtype=torch.float64))


def test_limb_flip_threshold_nan_pred_and_batched():
    R, t = torch.eye(3), torch.zeros(3)
    gt = torch.tensor([[[0.0, 0.0, 1.0], [0.0, 0.0, 1.03]]]).repeat(4, 1, 1)
    pred = gt.clone()
    pred[1, 1, 2] = 0.9  # flipped
    pred[2, 1, 2] = NAN
    pred[3, 1, 2] = 1.0  # zero depth difference: sign differs from gt's
    flips = limb_flip_errors(pred, gt, [(0, 1)], R, t)
    torch.testing.assert_close(flips[:, 0], torch.tensor([0.0, 1.0, NAN, 1.0]), equal_nan=True)
    # Raising the threshold above the 3 cm gt depth difference makes every frame undefined.
    assert torch.isnan(limb_flip_errors(pred, gt, [(0, 1)], R, t, min_depth_diff=0.05)).all()
    batched = limb_flip_errors(pred.expand(2, 4, 2, 3), gt.expand(2, 4, 2, 3), [(0, 1), (1, 0)], R, t)
    assert batched.shape == (2, 4, 2)
    assert limb_flip_errors(pred, gt, [], R, t).shape == (4, 0)


def test_limb_flip_bad_inputs_raise():
    gt = torch.zeros(3, 4, 3)
    R, t = torch.eye(3), torch.zeros(3)
    with pytest.raises(InputError, match="out of range for 4 joints"):
        limb_flip_errors(gt, gt, [(0, 4)], R, t)
    with pytest.raises(InputError, match=r"limbs must be .* got \(1, 3\)"):
        limb_flip_errors(gt, gt, [(0, 1, 2)], R, t)
    with pytest.raises(InputError, match=r"pred and gt"):
        limb_flip_errors(gt, gt[:2], [(0, 1)], R, t)
    with pytest.raises(InputError, match=r"R must have shape"):
        limb_flip_errors(gt, gt, [(0, 1)], torch.eye(3)[:2], t)


def test_flip_error_rate_undefined_limb_and_shapes():
    flips = torch.tensor([[1.0, NAN, 0.0], [0.0, NAN, 0.0], [1.0, NAN, NAN], [NAN, NAN, 1.0]])
    torch.testing.assert_close(flip_error_rate(flips), torch.tensor([2 / 3, NAN, 1 / 3]), equal_nan=True)
    torch.testing.assert_close(flip_error_rate(np.stack([flips, flips]))[1], flip_error_rate(flips), equal_nan=True)
    with pytest.raises(InputError, match=r"flips must have shape .* got \(3,\)"):
        flip_error_rate(torch.zeros(3))


# ---------------------------------------------------------------- reprojection


def test_reprojection_error_with_missing_keypoints():
    pixels = torch.zeros(2, 3, 2)
    observed = torch.tensor([[[3.0, 4.0], [NAN, NAN], [0.0, 10.0]], [[1.0, 1.0], [2.0, 2.0], [3.0, 3.0]]])
    confidence = torch.tensor([[1.0, 0.0, 0.5], [0.0, 0.0, -1.0]])
    out = reprojection_error_px(pixels, observed, confidence)
    torch.testing.assert_close(out, torch.tensor([7.5, NAN]), equal_nan=True)


def test_reprojection_error_batched_nan_pixels_and_gradcheck():
    gen = _gen(27)
    pixels = torch.rand(2, 4, 5, 2, generator=gen, dtype=torch.float64) * 100
    observed = torch.rand(2, 4, 5, 2, generator=gen, dtype=torch.float64) * 100
    confidence = (torch.rand(2, 4, 5, generator=gen, dtype=torch.float64) > 0.3).double()
    confidence[..., 0] = 1.0
    out = reprojection_error_px(pixels, observed, confidence)
    assert out.shape == (2, 4)
    torch.testing.assert_close(out[1], reprojection_error_px(pixels[1], observed[1], confidence[1]))
    observed[..., 1, :] = torch.where(confidence[..., 1, None] > 0, observed[..., 1, :], NAN)
    p = pixels[0].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda x: reprojection_error_px(x, observed[0], confidence[0]), (p,))
    bad = pixels.clone()
    bad[0, 0, 0, 0] = NAN  # confident keypoint: propagates
    assert torch.isnan(reprojection_error_px(bad, observed, confidence)[0, 0])


def test_reprojection_error_bad_shapes_raise():
    with pytest.raises(InputError, match=r"confidence must have shape \(2, 3\) .* got \(2, 4\)"):
        reprojection_error_px(torch.zeros(2, 3, 2), torch.zeros(2, 3, 2), torch.ones(2, 4))
    with pytest.raises(InputError, match="pixels and observed"):
        reprojection_error_px(torch.zeros(2, 3, 2), torch.zeros(2, 4, 2), torch.ones(2, 3))
    with pytest.raises(InputError, match=r"pixels must have shape .* got \(2, 3, 3\)"):
        reprojection_error_px(torch.zeros(2, 3, 3), torch.zeros(2, 3, 3), torch.ones(2, 3))


# ---------------------------------------------------------------- joint limits


def test_joint_limit_counts_and_infinite_bounds():
    inf = math.inf
    lower = torch.tensor([-1.0, -inf, 0.0, -inf])
    upper = torch.tensor([1.0, inf, 0.5, 0.2])
    q = torch.tensor(
        [
            [0.0, 1e6, 0.25, 0.0],  # all fine; dof 1 unlimited
            [1.0005, -1e6, -0.1, 0.2],  # dof 0 within tol; dof 2 below by 0.1 rad
            [-1.5, 0.0, 0.7, 0.3],  # dof 0 below by 0.5, dof 2 above by 0.2, dof 3 above by 0.1
        ]
    )
    report = joint_limit_violations(q, lower, upper)
    assert isinstance(report, JointLimitReport)
    assert report.per_frame.tolist() == [0, 1, 3]
    # 4 violations among 3 frames x 3 limited dofs (dof 1 has no bound and does not count)
    torch.testing.assert_close(report.fraction, torch.tensor(4 / 9))
    torch.testing.assert_close(report.max_deg, torch.tensor(math.degrees(0.5)))
    # A looser tolerance swallows the small violations.
    loose = joint_limit_violations(q, lower, upper, tol=0.15)
    assert loose.per_frame.tolist() == [0, 0, 2]


def test_joint_limit_fraction_counts_limited_dofs_only():
    """Unlimited dofs (root translation and rotation) must not dilute the violation fraction."""
    inf = math.inf
    lower = torch.tensor([-inf, -inf, -1.0])
    upper = torch.tensor([inf, inf, 1.0])
    q = torch.tensor([[5.0, 5.0, 2.0], [5.0, 5.0, 0.0]])
    assert joint_limit_violations(q, lower, upper).fraction == 0.5
    assert joint_limit_violations(q, torch.full((3,), -inf), torch.full((3,), inf)).fraction == 0


def test_joint_limit_angles_are_periodic():
    """An angle 2 pi away from one inside its arc is the same pose: inside with `angular`."""
    lower = torch.tensor([0.0, 0.0, -4.0], dtype=torch.float64)
    upper = torch.tensor([1.0, 1.0, 4.0], dtype=torch.float64)  # dof 2's arc spans > 2 pi: no limit
    q = torch.tensor([[0.5 + 2 * math.pi, 1.2 - 4 * math.pi, 100.0]], dtype=torch.float64)
    angular = torch.tensor([True, True, True])
    report = joint_limit_violations(q, lower, upper, angular=angular)
    assert report.per_frame.tolist() == [1]  # dof 1 is 0.2 rad above its arc after unwrapping
    torch.testing.assert_close(report.max_deg, torch.tensor(math.degrees(0.2), dtype=torch.float64))
    linear = joint_limit_violations(q, lower, upper)
    assert linear.per_frame.tolist() == [3]
    translation = joint_limit_violations(q, lower, upper, angular=torch.tensor([False, True, True]))
    assert translation.per_frame.tolist() == [2]


def test_joint_limit_no_violation_batched_and_nan():
    lower, upper = -torch.ones(3, dtype=torch.float64), torch.ones(3, dtype=torch.float64)
    q = torch.zeros(2, 5, 3, dtype=torch.float64)
    report = joint_limit_violations(q, lower, upper)
    assert report.per_frame.shape == (2, 5) and report.per_frame.sum() == 0
    assert report.fraction == 0 and report.max_deg == 0 and report.max_deg.dtype == torch.float64
    q[1, 2, 0] = NAN
    nan_report = joint_limit_violations(q, lower, upper)
    assert nan_report.per_frame.sum() == 0 and torch.isnan(nan_report.max_deg)
    report_np = joint_limit_violations(np.full((2, 3), 2.0), [-1, -1, -1], [1, 1, 1])
    assert report_np.per_frame.tolist() == [3, 3] and report_np.fraction == 1


def test_joint_limit_bad_inputs_raise():
    with pytest.raises(InputError, match=r"lower must have shape \(3,\) .* got \(2,\)"):
        joint_limit_violations(torch.zeros(4, 3), torch.zeros(2), torch.ones(3))
    with pytest.raises(InputError, match=r"upper must have shape"):
        joint_limit_violations(torch.zeros(4, 3), torch.zeros(3), torch.ones(3, 1))
    with pytest.raises(InputError, match="lower must not exceed upper"):
        joint_limit_violations(torch.zeros(4, 3), torch.ones(3), torch.zeros(3))
    with pytest.raises(InputError, match=r"q must have shape"):
        joint_limit_violations(torch.zeros(0, 3), torch.zeros(3), torch.ones(3))


# ---------------------------------------------------------------- best of K


def test_best_of_k_picks_right_hypothesis():
    T, N, J = 4, 5, 6
    gt = _skeleton(T, J, seed=28)
    hyps = gt[:, None] + 0.2 * _skeleton(T, N, J, seed=29)
    best = torch.tensor([3, 0, 4, 1])
    hyps[torch.arange(T), best] = gt + 0.001 * _skeleton(T, J, seed=30) + 1.0  # near gt, shifted root
    out = best_of_k_mpjpe(hyps, gt)
    assert out.shape == (T,)
    per_hyp = torch.stack([mpjpe(hyps[:, n], gt) for n in range(N)], dim=-1)
    assert (per_hyp.argmin(dim=-1) == best).all()
    torch.testing.assert_close(out, per_hyp[torch.arange(T), best])
    assert (out < 5.0).all()


def test_best_of_k_batched_gradcheck_and_bad_shapes():
    gt = _skeleton(2, 3, 4, seed=31)
    hyps = gt[..., None, :, :] + 0.1 * _skeleton(2, 3, 5, 4, seed=32)
    out = best_of_k_mpjpe(hyps, gt, root=2)
    assert out.shape == (2, 3)
    torch.testing.assert_close(out[1, 2], best_of_k_mpjpe(hyps[1, 2][None], gt[1, 2][None], root=2)[0])
    h = hyps[0].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda x: best_of_k_mpjpe(x, gt[0]), (h,))
    with pytest.raises(InputError, match=r"hypotheses must have shape .* got \(2, 3, 5, 4, 3\) and gt \(2, 3, 5, 3\)"):
        best_of_k_mpjpe(hyps, gt[..., :1, :].expand(2, 3, 5, 3))
    with pytest.raises(InputError, match="at least one hypothesis"):
        best_of_k_mpjpe(hyps[..., :0, :, :], gt)
    with pytest.raises(InputError, match=r"gt must have shape"):
        best_of_k_mpjpe(hyps, gt[..., :2])


def test_checks_without_ground_truth():
    """Per-keypoint reprojection medians, jitter, foot skating and ambiguous limb frames on hand-made cases."""
    from ptrack.pipeline.metrics import (
        ambiguous_limb_frames,
        foot_skating_mm,
        foot_sliding_steps_mm,
        reprojection_error_per_keypoint,
        second_differences_mm,
    )

    obs = torch.zeros(5, 2, 2)
    pix = obs.clone()
    pix[:, 0, 0] = torch.tensor([1.0, 2.0, 3.0, 4.0, 100.0])  # keypoint 0: errors 1..4 and an outlier
    conf = torch.ones(5, 2)
    conf[:, 1] = 0  # keypoint 1 never observed
    med = reprojection_error_per_keypoint(pix, obs, conf)
    assert float(med[0]) == 3.0 and torch.isnan(med[1])

    t = torch.arange(6, dtype=torch.float64)
    line = torch.stack([t * 0.01, torch.zeros(6), torch.zeros(6)], -1)[:, None]  # constant velocity: no jitter
    shake = line.clone()
    shake[::2, 0, 1] += 0.002  # +-1 mm zigzag
    assert float(second_differences_mm(line).mean(0)[0]) == pytest.approx(0.0, abs=1e-9)
    assert float(second_differences_mm(shake).mean(0)[0]) == pytest.approx(4.0, rel=1e-6)  # |2 mm + 2 mm| each frame

    up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    planted = torch.zeros(6, 1, 3, dtype=torch.float64)
    sliding = line.clone()  # on the floor, 10 mm per frame sideways
    lifted = line.clone()
    lifted[:, 0, 1] = torch.linspace(0, 0.5, 6)  # moving while leaving the floor: contact only at the start
    got = foot_skating_mm(torch.cat([planted, sliding, lifted], 1), up)
    assert float(got[0]) == pytest.approx(0.0) and float(got[1]) == pytest.approx(10.0)
    assert torch.isnan(got[2])  # in contact in frame 0 only: no step on the floor
    # frame by frame (the rerun log's series): the step into each frame while on the floor, NaN off it
    steps = foot_sliding_steps_mm(torch.cat([planted, sliding, lifted], 1), up)
    assert steps.shape == (5, 3)
    assert steps[:, 0].tolist() == [0.0] * 5 and steps[:, 1].tolist() == pytest.approx([10.0] * 5)
    assert torch.isnan(steps[:, 2]).all()
    lift = sliding[:4].clone()
    lift[3, 0, 1] = 0.3  # the foot leaves the floor in frame 3
    assert torch.isnan(foot_sliding_steps_mm(lift, up)[:, 0]).tolist() == [False, False, True]
    wild = torch.cat([sliding.repeat(5, 1, 1), sliding[:1]])  # 31 frames on the floor, then one far under it
    wild[-1, 0, 1] = -0.4  # (a lone detection fitted wildly): the floor is not set by it
    assert foot_sliding_steps_mm(wild, up)[:-1, 0].isfinite().sum() >= 25

    # two modes of one limb (keypoints 0 -> 1) seen by a camera at the origin looking along +z
    R, tt = torch.eye(3), torch.zeros(3)
    near = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.3, 2.8]])  # end nearer the camera
    far = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.3, 3.2]])
    hyp = torch.stack([near, far])[None].repeat(3, 1, 1, 1)  # (T=3, N=2, K=2, 3)
    w = torch.tensor([[0.5, 0.5], [0.95, 0.05], [0.0, 1.0]])
    amb = ambiguous_limb_frames(hyp, w, [(0, 1)], R, tt)
    assert amb[:, 0].tolist() == [True, False, False]


def test_bone_lengths_report_says_where_each_length_and_its_spread_come_from():
    from ptrack.pipeline.metrics import TEMPLATE_LENGTH_SPREAD, bone_lengths_report

    lengths = {"thigh": 0.42, "shank": 0.40, "hips": 0.19}
    template = bone_lengths_report(lengths, None)
    assert {n: (r["source"], r["std_source"]) for n, r in template.items()} == dict.fromkeys(
        lengths, ("template", "prior")
    )
    assert (
        template["thigh"]["std_m"] == pytest.approx(TEMPLATE_LENGTH_SPREAD * 0.42) and "frames" not in template["thigh"]
    )
    measured = {"thigh": {"length_m": 0.42, "frames": 80, "std_m": 0.003}, "shank": {"length_m": 0.4, "frames": 12}}
    mixed = bone_lengths_report(lengths, measured)
    assert mixed["thigh"] == {
        "length_m": 0.42,
        "source": "observed",
        "std_m": 0.003,
        "std_source": "bootstrap",
        "frames": 80,
    }
    assert mixed["shank"]["std_m"] is None  # measured, but too few resamples for a spread
    assert mixed["hips"] == template["hips"]


def test_depth_order_scores_and_heaviest_mode_on_two_modes():
    """Brier score of a limb's depth-order probability, whether a mode holds the true order, and the heaviest mode,
    on hand-made modes of one limb (keypoints 0 -> 1) seen by a camera at the origin looking along +z."""
    from ptrack.pipeline.metrics import depth_order_scores, distinct_modes, heaviest_mode

    R, tt = torch.eye(3), torch.zeros(3)
    near = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.3, 2.8]])  # end nearer the camera
    far = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.3, 3.2]])
    flat = torch.tensor([[0.0, 0.0, 3.0], [0.0, 0.3, 3.01]])  # within 2 cm of the image plane
    hyp = torch.stack([near, far])[None].repeat(4, 1, 1, 1)  # (T=4, N=2, K=2, 3)
    w = torch.tensor([[0.5, 0.5], [0.9, 0.1], [1.0, 0.0], [0.3, 0.7]])
    gt = torch.stack([near, near, far, flat])  # the truth: near, near, far (only in a weight-0 mode), undefined
    s = depth_order_scores(hyp, w, gt, [(0, 1)], R, tt)
    assert s.brier[:3, 0].tolist() == pytest.approx([0.25, 0.01, 1.0])
    assert s.in_modes[:3, 0].tolist() == [1.0, 1.0, 0.0]  # frame 2: the far mode has weight 0
    assert torch.isnan(s.brier[3, 0]) and torch.isnan(s.in_modes[3, 0])
    assert torch.equal(heaviest_mode(hyp, w), torch.stack([near, near, near, far]))
    # readings 5 cm apart: near and far (40 cm apart in depth) are two, a copy 1 cm off is not a third; padding none
    copy = near + torch.tensor([0.0, 0.0, 0.01])
    three = torch.stack([near, far, copy])[None].repeat(2, 1, 1, 1)
    assert distinct_modes(three, torch.tensor([[0.5, 0.3, 0.2], [1.0, 0.0, 0.0]])).tolist() == [2, 1]
    with pytest.raises(InputError, match="weights"):
        depth_order_scores(hyp, w[:, :1], gt, [(0, 1)], R, tt)


def test_std_coverage_counts_errors_within_k_std():
    gt = torch.zeros(2, 2, 3)
    pred = gt.clone()
    pred[..., 0] = torch.tensor([[0.01, 0.03], [0.05, 0.0]])  # errors 1, 3, 5, 0 cm
    std = torch.full((2, 2), 0.02)
    assert float(M.std_coverage(pred, gt, std, 1.0)) == pytest.approx(0.5)  # 1 and 0 cm
    assert float(M.std_coverage(pred, gt, std, 2.0)) == pytest.approx(0.75)  # and 3 cm
    assert float(M.std_coverage(pred, gt, std, 3.0)) == pytest.approx(1.0)
    std[0, 0] = float("nan")  # left out
    assert float(M.std_coverage(pred, gt, std, 1.0)) == pytest.approx(1 / 3)
    with pytest.raises(InputError, match="std"):
        M.std_coverage(pred, gt, std[0], 1.0)


def test_exchanged_label_frames():
    """Frames whose detections fit the reprojection better with left and right exchanged; None without pairs."""
    from ptrack.pipeline.metrics import exchanged_label_frames

    pixels = torch.tensor([[[0.0, 0.0], [10.0, 0.0], [0.0, 50.0], [10.0, 50.0], [5.0, 80.0]]]).repeat(4, 1, 1)
    observed = pixels + 0.5
    observed[1] = observed[1, [1, 0, 3, 2, 4]]  # the detector's mirrored body
    observed[2, :2] = observed[2, [1, 0]]  # only the first pair exchanged, the second seen as is ...
    confidence = torch.ones(4, 5)
    confidence[2, 2:4] = 0.0  # ... but missing: the frame reads exchanged on what is seen
    confidence[3, :4] = 0.0  # only the unpaired keypoint seen: nothing to tell
    got = exchanged_label_frames(pixels, observed, confidence, torch.tensor([1, 0, 3, 2, 4]))
    assert got.tolist() == [False, True, True, False]
    assert exchanged_label_frames(pixels, observed, confidence, torch.arange(5)) is None
