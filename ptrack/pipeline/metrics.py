"""Evaluation metrics for 3D human pose reconstruction.

Joints are in metres in the world frame (Y up); camera axes are OpenCV (x right, y down,
z forward) with x_cam = R @ x_world + t. Every metric returns per-frame values (a tensor) so that
callers can log per-frame scalars and take means themselves. Names ending in `mm` or the
docstrings say which results are in millimetres; pixel errors are in pixels, joint limit
violations in degrees.

Inputs may be torch tensors or numpy arrays (converted with `torch.as_tensor`); integer inputs
are promoted to the default float dtype. dtype and device follow the inputs. NaNs in predictions
propagate into the result (callers check) rather than raising.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from ptrack.body.limits import limited_dofs, outside_limits
from ptrack.checks import as_float_tensor
from ptrack.errors import InputError
from ptrack.hypotheses.mixture import distinct_minima

M_TO_MM = 1000.0


class JointLimitReport(NamedTuple):
    """Joint limit violations of a pose trajectory `q: (..., D)`.

    per_frame: (...,) int64 count of dofs outside [lower - tol, upper + tol] in each frame.
    fraction: () violating (frame, dof) entries / number of (frame, limited dof) entries, in q's dtype.
    max_deg: () largest amount (degrees) by which a violating entry lies outside
        [lower, upper]; 0 if nothing violates, NaN if q contains NaN.
    """

    per_frame: Tensor
    fraction: Tensor
    max_deg: Tensor


def _check_same(a: Tensor, b: Tensor, name_a: str, name_b: str) -> None:
    if a.shape != b.shape:
        raise InputError(f"{name_a} and {name_b} must have the same shape, got {tuple(a.shape)} and {tuple(b.shape)}")


def _joint_pair(pred, gt, min_dim: int = 2) -> tuple[Tensor, Tensor]:
    """Convert pred and gt, check both are (..., J, 3) (ndim >= min_dim) and alike, promote dtypes."""
    pred, gt = as_float_tensor(pred, "pred"), as_float_tensor(gt, "gt")
    if pred.ndim < min_dim or pred.shape[-1] != 3:
        expected = "(..., J, 3)" if min_dim == 2 else "(..., T, J, 3)"
        raise InputError(f"pred must have shape {expected}, got {tuple(pred.shape)}")
    _check_same(pred, gt, "pred", "gt")
    dtype = torch.promote_types(pred.dtype, gt.dtype)
    return pred.to(dtype), gt.to(dtype)


def _check_root(root: int, num_joints: int) -> None:
    if not -num_joints <= root < num_joints:
        raise InputError(f"root={root} is out of range for {num_joints} joints")


def _camera(R, t, like: Tensor) -> tuple[Tensor, Tensor]:
    R = as_float_tensor(R, "R").to(dtype=like.dtype, device=like.device)
    t = as_float_tensor(t, "t").to(dtype=like.dtype, device=like.device)
    if R.shape != (3, 3):
        raise InputError(f"R must have shape (3, 3), got {tuple(R.shape)}")
    if t.shape != (3,):
        raise InputError(f"t must have shape (3,), got {tuple(t.shape)}")
    return R, t


def _mean_joint_distance_mm(a: Tensor, b: Tensor) -> Tensor:
    """(..., J, 3) x2 -> (...,) mean Euclidean distance in mm."""
    return torch.linalg.vector_norm(a - b, dim=-1).mean(dim=-1) * M_TO_MM


def mpjpe(pred, gt, root: int = 0) -> Tensor:
    """Mean per-joint position error after root alignment, in millimetres.

    Joint `root` is subtracted from every joint of `pred` and of `gt` before comparing.

    pred, gt: (..., J, 3) metres -> (...,) mm.
    """
    pred, gt = _joint_pair(pred, gt)
    _check_root(root, pred.shape[-2])
    pred_rel = pred - pred[..., root, :].unsqueeze(-2)
    gt_rel = gt - gt[..., root, :].unsqueeze(-2)
    return _mean_joint_distance_mm(pred_rel, gt_rel)


def procrustes_align(pred: Tensor, gt: Tensor) -> Tensor:
    """Similarity-align pred to gt per frame (Umeyama, no reflections).

    pred, gt: (..., J, 3) -> (..., J, 3) s * R @ pred + t minimising the squared error to gt.
    Frames with non-finite values come back as NaN.
    """
    mu_p = pred.mean(dim=-2, keepdim=True)
    mu_g = gt.mean(dim=-2, keepdim=True)
    p = pred - mu_p
    g = gt - mu_g
    num_joints = pred.shape[-2]
    cov = g.transpose(-1, -2) @ p / num_joints  # (..., 3, 3), maps pred to gt
    finite = torch.isfinite(cov).all(dim=-1).all(dim=-1)
    eye = torch.eye(3, dtype=cov.dtype, device=cov.device)
    # linalg.svd raises on non-finite input: decompose a stand-in, then mark those frames NaN.
    cov_safe = torch.where(finite[..., None, None], cov, eye)
    U, S, Vh = torch.linalg.svd(cov_safe)
    sign = torch.sign(torch.linalg.det(U) * torch.linalg.det(Vh))  # -1 where the best fit reflects
    d = torch.stack([torch.ones_like(sign), torch.ones_like(sign), sign], dim=-1)  # (..., 3)
    rot = (U * d[..., None, :]) @ Vh
    var_p = (p * p).sum(dim=(-1, -2)) / num_joints
    tiny = torch.finfo(pred.dtype).tiny
    scale = (S * d).sum(dim=-1) / var_p.clamp_min(tiny)
    aligned = scale[..., None, None] * (p @ rot.transpose(-1, -2)) + mu_g
    return torch.where(finite[..., None, None], aligned, torch.full_like(aligned, float("nan")))


def std_coverage(pred, gt, std, k: float = 2.0) -> Tensor:
    """Share of joint-frames whose 3D error lies within k standard deviations: |pred - gt| <= k std.

    pred, gt: (T, J, 3) metres (every joint, camera-independent: no alignment); std: (T, J) metres, the
    square root of each joint's 3D covariance trace (`joint_std`) -> () in [0, 1]. A calibrated std puts
    0.95-0.99 within 2 (a 3D Gaussian: 0.95 when the error lies along one axis, e.g. depth, 0.99 isotropic).
    Joint-frames with a non-finite std are left out (NaN if none is finite)."""
    pred, gt = _joint_pair(pred, gt)
    std = torch.as_tensor(std, dtype=pred.dtype, device=pred.device)
    if std.shape != pred.shape[:-1]:
        raise InputError(f"std_coverage: std must be {tuple(pred.shape[:-1])}, got {tuple(std.shape)}")
    err = (pred - gt).norm(dim=-1)
    ok = torch.isfinite(std)
    return ((err <= k * std) & ok).sum() / ok.sum()


def pa_mpjpe(pred, gt) -> Tensor:
    """Procrustes-aligned MPJPE, in millimetres.

    Each frame of `pred` is aligned to `gt` by the similarity transform (rotation, translation,
    uniform scale; reflections are not allowed) minimising the squared joint error, then the mean
    joint distance is taken.

    pred, gt: (..., J, 3) metres -> (...,) mm.
    """
    pred, gt = _joint_pair(pred, gt)
    return _mean_joint_distance_mm(procrustes_align(pred, gt), gt)


def mpjpe_absolute(pred, gt, R=None, t=None) -> Tensor:
    """Absolute MPJPE (no alignment at all), in millimetres.

    With R (3, 3) and t (3,) given, both skeletons are first mapped to the camera frame
    x_cam = R @ x + t; for a rigid camera the distances are unchanged, but this is the documented
    "absolute MPJPE in the camera frame". Give both R and t or neither.

    pred, gt: (..., J, 3) metres -> (...,) mm.
    """
    pred, gt = _joint_pair(pred, gt)
    if (R is None) != (t is None):
        raise InputError("mpjpe_absolute: give both R and t or neither")
    if R is not None:
        R, t = _camera(R, t, pred)
        pred = pred @ R.transpose(0, 1) + t
        gt = gt @ R.transpose(0, 1) + t
    return _mean_joint_distance_mm(pred, gt)


def accel_error(pred, gt, root: int | None = None) -> Tensor:
    """Acceleration error, in millimetres per frame^2.

    For each interior frame, the mean over joints of |a_pred - a_gt| where a = x[t-1] - 2 x[t] +
    x[t+1] is the second difference. With `root` (HMR/VIBE's definition, which centres both
    skeletons on the pelvis first) joint `root` is subtracted from every joint of each frame; with
    `root=None` the absolute positions are used, so root (global) jitter counts too.

    pred, gt: (..., T, J, 3) metres with T >= 3 -> (..., T - 2) mm / frame^2.
    """
    pred, gt = _joint_pair(pred, gt, min_dim=3)
    if pred.shape[-3] < 3:
        raise InputError(f"accel_error needs at least 3 frames, pred has shape {tuple(pred.shape)}")
    if root is not None:
        _check_root(root, pred.shape[-2])
        pred = pred - pred[..., root, :].unsqueeze(-2)
        gt = gt - gt[..., root, :].unsqueeze(-2)

    def second_diff(x: Tensor) -> Tensor:
        return x[..., :-2, :, :] - 2 * x[..., 1:-1, :, :] + x[..., 2:, :, :]

    return _mean_joint_distance_mm(second_diff(pred), second_diff(gt))


def _limb_depth_differences(x: Tensor, pairs: Tensor, R, t) -> Tensor:
    """Each limb's depth(end) - depth(start) in the camera frame (z of x_cam = R x + t): x (..., J, 3), pairs (L, 2)
    joint indices, R (3, 3), t (3,) -> (..., L); negative where the end is nearer the camera."""
    R, t = _camera(R, t, x)
    depth = x @ R[2] + t[2]
    return depth[..., pairs[:, 1]] - depth[..., pairs[:, 0]]


def limb_flip_errors(pred, gt, limbs: Sequence[tuple[int, int]], R, t, min_depth_diff: float = 0.02) -> Tensor:
    """Per-frame, per-limb depth-order flips (the monocular forwards/backwards ambiguity).

    A limb (start, end) is flipped in a frame when the sign of depth(end) - depth(start) in the
    camera frame (z of x_cam = R @ x + t) differs between pred and gt. Frames where the gt depth
    difference is below `min_depth_diff` metres in magnitude (limb near-parallel to the image
    plane), or not finite, are undefined.

    pred, gt: (..., T, J, 3) metres; limbs: L (start_joint, end_joint) index pairs, a sequence or
    an (L, 2) integer array; R: (3, 3), t: (3,) world -> camera.
    Returns (..., T, L) in pred's dtype: 1 = flipped, 0 = correct, NaN = undefined or pred NaN.
    """
    pred, gt = _joint_pair(pred, gt)
    R, t = _camera(R, t, pred)
    try:
        pairs = torch.as_tensor(limbs, dtype=torch.long, device=pred.device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise InputError(f"limbs: cannot read as (start, end) index pairs ({exc})") from exc
    if pairs.numel() == 0:
        pairs = pairs.reshape(0, 2)
    if pairs.ndim != 2 or pairs.shape[-1] != 2:
        raise InputError(f"limbs must be L (start, end) pairs, shape (L, 2), got {tuple(pairs.shape)}")
    num_joints = pred.shape[-2]
    if pairs.numel() and (pairs.min() < -num_joints or pairs.max() >= num_joints):
        raise InputError(f"limbs index a joint out of range for {num_joints} joints: {pairs.tolist()}")

    d_pred, d_gt = _limb_depth_differences(pred, pairs, R, t), _limb_depth_differences(gt, pairs, R, t)
    flipped = (torch.sign(d_pred) != torch.sign(d_gt)).to(pred.dtype)
    undefined = ~(d_gt.abs() >= min_depth_diff) | torch.isnan(d_pred)
    return torch.where(undefined, torch.full_like(flipped, float("nan")), flipped)


def flip_error_rate(flips) -> Tensor:
    """Per-limb fraction of defined frames that are flipped.

    flips: (..., T, L) from `limb_flip_errors` -> (..., L); NaN for a limb with no defined frame.
    The overall rate over all defined (frame, limb) entries is `flips.nanmean()`; the mean of
    per-limb rates (each limb weighted equally) is `flip_error_rate(flips).nanmean()`.
    """
    flips = as_float_tensor(flips, "flips")
    if flips.ndim < 2:
        raise InputError(f"flips must have shape (..., T, L), got {tuple(flips.shape)}")
    defined = ~torch.isnan(flips)
    count = defined.sum(dim=-2).to(flips.dtype)
    flipped = torch.where(defined, flips, torch.zeros_like(flips)).sum(dim=-2)
    return flipped / count  # 0 / 0 = NaN where nothing is defined


def reprojection_error_px(pixels, observed, confidence) -> Tensor:
    """Mean pixel distance between projected and observed keypoints.

    Only keypoints with confidence > 0 count (their observed values may be NaN otherwise).

    pixels, observed: (..., T, K, 2) pixels; confidence: (..., T, K) -> (..., T) pixels;
    NaN for frames with no keypoint of positive confidence.
    """
    pixels, observed = as_float_tensor(pixels, "pixels"), as_float_tensor(observed, "observed")
    confidence = as_float_tensor(confidence, "confidence")
    if pixels.ndim < 2 or pixels.shape[-1] != 2:
        raise InputError(f"pixels must have shape (..., K, 2), got {tuple(pixels.shape)}")
    _check_same(pixels, observed, "pixels", "observed")
    if confidence.shape != pixels.shape[:-1]:
        raise InputError(
            f"confidence must have shape {tuple(pixels.shape[:-1])} to match pixels, got {tuple(confidence.shape)}"
        )
    used = confidence > 0
    diff = torch.where(used[..., None], pixels - observed, torch.zeros_like(pixels))
    dist = torch.linalg.vector_norm(diff, dim=-1)
    return dist.sum(dim=-1) / used.sum(dim=-1).to(dist.dtype)  # 0 / 0 = NaN for empty frames


def joint_limit_violations(q, lower, upper, tol: float = 1e-3, angular=None) -> JointLimitReport:
    """Count pose dofs outside their limits.

    An entry violates when it lies outside [lower - tol, upper + tol]; infinite bounds (unlimited
    dofs such as root translation) never violate. With `angular` (D,) bool, those dofs are angles
    measured on the circle: an entry is inside when some 2 pi shift of it is (`ptrack.body.limits`).
    The fraction counts only limited dofs (a finite bound on at least one side). NaN entries are not
    counted, but make max_deg NaN.

    q: (..., T, D) radians (any leading dims; at least one entry); lower, upper: (D,) radians.
    Returns JointLimitReport(per_frame (..., T) int64, fraction (), max_deg () degrees);
    fraction is 0 when no dof is limited.
    """
    q = as_float_tensor(q, "q")
    if q.ndim < 1 or q.numel() == 0:
        raise InputError(f"q must have shape (..., D) with at least one entry, got {tuple(q.shape)}")
    num_dofs = q.shape[-1]
    lower = as_float_tensor(lower, "lower").to(dtype=q.dtype, device=q.device)
    upper = as_float_tensor(upper, "upper").to(dtype=q.dtype, device=q.device)
    for name, bound in (("lower", lower), ("upper", upper)):
        if bound.shape != (num_dofs,):
            raise InputError(f"{name} must have shape ({num_dofs},) to match q, got {tuple(bound.shape)}")
    if bool((lower > upper).any()):
        raise InputError("lower must not exceed upper for any dof")
    if angular is not None:
        angular = torch.as_tensor(angular, dtype=torch.bool, device=q.device)
        if angular.shape != (num_dofs,):
            raise InputError(f"angular must have shape ({num_dofs},) to match q, got {tuple(angular.shape)}")
    outside = outside_limits(q, lower, upper, angular)
    violating = outside > tol
    per_frame = violating.sum(dim=-1)
    limited = limited_dofs(lower, upper)
    entries = limited.sum() * (q.numel() // num_dofs)
    fraction = violating.sum().to(q.dtype) / entries.clamp_min(1).to(q.dtype)
    kept = torch.where(violating | torch.isnan(outside), outside, torch.zeros_like(outside))
    max_deg = kept.max() * (180.0 / math.pi)
    return JointLimitReport(per_frame=per_frame, fraction=fraction, max_deg=max_deg)


def best_of_k_mpjpe(hypotheses, gt, root: int = 0) -> Tensor:
    """Best-of-N root-aligned MPJPE, in millimetres.

    Per frame, the smallest `mpjpe` among the N hypotheses (a NaN hypothesis makes it NaN).

    hypotheses: (..., N, J, 3) metres; gt: (..., J, 3) metres -> (...,) mm.
    """
    hypotheses, gt = as_float_tensor(hypotheses, "hypotheses"), as_float_tensor(gt, "gt")
    if gt.ndim < 2 or gt.shape[-1] != 3:
        raise InputError(f"gt must have shape (..., J, 3), got {tuple(gt.shape)}")
    if hypotheses.ndim != gt.ndim + 1 or hypotheses.shape[:-3] + hypotheses.shape[-2:] != gt.shape:
        raise InputError(
            f"hypotheses must have shape (..., N, J, 3) with gt (..., J, 3), got {tuple(hypotheses.shape)} "
            f"and gt {tuple(gt.shape)}"
        )
    if hypotheses.shape[-3] == 0:
        raise InputError(f"hypotheses must hold at least one hypothesis, got {tuple(hypotheses.shape)}")
    errors = mpjpe(hypotheses, gt.unsqueeze(-3).expand_as(hypotheses), root=root)
    return errors.min(dim=-1).values


# ---------------------------------------------------------------------------------------------
# Checks without ground truth: what a person can look at on real footage.


def reprojection_error_per_keypoint(pixels, observed, confidence) -> Tensor:
    """Median reprojection error of each keypoint over the frames that observe it, pixels.

    pixels, observed: (T, K, 2); confidence (T, K) -> (K,), NaN for a keypoint never observed."""
    err = (torch.as_tensor(pixels) - torch.as_tensor(observed)).norm(dim=-1)
    seen = torch.as_tensor(confidence) > 0
    return torch.stack(
        [err[seen[:, k], k].median() if seen[:, k].any() else err.new_tensor(float("nan")) for k in range(err.shape[1])]
    )


def exchanged_label_frames(pixels, observed, confidence, partners) -> Tensor | None:
    """The frames whose detections the reprojected estimate fits better with every left and right label exchanged
    (a 2D detector's mirrored body): the mean pixel distance over the keypoints seen in both readings, each
    keypoint against its partner's detection, below the labels' own.

    pixels, observed: (T, K, 2); confidence (T, K); partners (K,) each keypoint's left/right partner
    (`KeypointSet.mirror_index`) -> (T,) bool, or None when no keypoint has a partner."""
    partners = torch.as_tensor(partners)
    paired = partners != torch.arange(len(partners))
    if not bool(paired.any()):
        return None
    pixels, observed, confidence = (torch.as_tensor(x) for x in (pixels, observed, confidence))
    seen = (confidence > 0) & (confidence.index_select(1, partners) > 0) & paired
    own = (pixels - observed).norm(dim=-1)
    other = (pixels - observed.index_select(1, partners)).norm(dim=-1)
    count = seen.sum(1)
    mean_own = torch.where(seen, own, 0.0).sum(1) / count.clamp_min(1)
    mean_other = torch.where(seen, other, 0.0).sum(1) / count.clamp_min(1)
    return (count > 0) & (mean_other < mean_own)


def second_differences_mm(points) -> Tensor:
    """|x_{t+1} - 2 x_t + x_{t-1}| of each point, mm per frame^2: how much an estimate shakes (motion capture of
    a walk at 30 fps: a few mm). Their mean over the frames is the jitter.

    points: (T, K, 3) metres -> (T-2, K); (0, K) with fewer than 3 frames."""
    x = torch.as_tensor(points)
    return 1000 * (x[2:] - 2 * x[1:-1] + x[:-2]).norm(dim=-1)


#: a foot point's floor height in `foot_sliding_steps_mm`: this quantile of its heights over the frames, not their
#: minimum, which one wild frame sets (a lone detection at the start of the outdoor clip put its feet 0.2 m under the
#: 5% quantile, and no other frame then counted as on the floor)
CONTACT_QUANTILE = 0.05


def foot_sliding_steps_mm(feet, up, contact_m: float = 0.05) -> Tensor:
    """The horizontal step of each foot point from frame t-1 to frame t, mm, where it is in contact in both frames
    (within `contact_m` above that point's floor height, the `CONTACT_QUANTILE` of its heights over the sequence),
    else NaN: frame by frame, what `foot_skating_mm` averages.

    feet: (T, F, 3) metres; up: (3,) unit vector of the world's up -> (T-1, F), row t-1 the step into frame t."""
    x = torch.as_tensor(feet)
    u = torch.as_tensor(up, dtype=x.dtype)
    h = x @ u  # (T, F)
    contact = (h - torch.quantile(h, CONTACT_QUANTILE, dim=0)) < contact_m
    step = x[1:] - x[:-1]
    horizontal = (step - (step @ u)[..., None] * u).norm(dim=-1)  # (T-1, F)
    both = contact[1:] & contact[:-1]
    return torch.where(both, 1000 * horizontal, torch.full_like(horizontal, float("nan")))


def foot_skating_mm(feet, up, contact_m: float = 0.05) -> Tensor:
    """Foot skating: the mean horizontal speed of each foot point in the frames where it is in contact, mm per
    frame, contact = within `contact_m` above that point's floor height (a low quantile of its heights over the
    sequence; a foot on the floor should not slide); the mean over the frames of `foot_sliding_steps_mm`.

    feet: (T, F, 3) metres; up: (3,) unit vector of the world's up -> (F,), NaN where never in contact."""
    return foot_sliding_steps_mm(feet, up, contact_m).nanmean(0)


def depth_order_probability(hypotheses, weights, limbs: Sequence[tuple[int, int]], R, t) -> Tensor:
    """Each limb's probability of pointing towards the camera under a weighted mixture: in each frame, the summed
    weight of the hypotheses that put the limb's end nearer the camera than its start (z of x_cam = R x + t).

    hypotheses: (T, N, J, 3) metres; weights (T, N) summing to 1 (0: padding); limbs L (start, end) joint index
    pairs; R (3, 3), t (3,) world -> camera -> (T, L) in [0, 1]."""
    X = torch.as_tensor(hypotheses)
    w = torch.as_tensor(weights, dtype=X.dtype, device=X.device)
    idx = torch.as_tensor(list(limbs), dtype=torch.long, device=X.device).reshape(-1, 2)
    nearer = (_limb_depth_differences(X, idx, R, t) < 0).to(X.dtype)  # (T, N, L)
    return (w[..., None] * nearer).sum(1)


def ambiguous_limb_frames(hypotheses, weights, limbs: Sequence[tuple[int, int]], R, t, share: float = 0.1) -> Tensor:
    """Whether the modes disagree about a limb's depth order: in each frame and limb, the summed weight of the
    modes that put the limb's end nearer the camera than its start (`depth_order_probability`) lies in
    [share, 1 - share].

    hypotheses: (T, N, K, 3) keypoints; weights (T, N) summing to 1; limbs (L,) keypoint index pairs; R (3, 3),
    t (3,) world -> camera -> (T, L) bool."""
    p = depth_order_probability(hypotheses, weights, limbs, R, t)
    return (p >= share) & (p <= 1 - share)


class DepthOrderScores(NamedTuple):
    """How well a mixture's weights state each limb's depth order, per frame and limb (T, L), NaN where the
    limb lies within the margin of the image plane in the truth: `brier` (p - truth)^2, p the summed weight of
    the modes that put the limb's end nearer the camera (`depth_order_probability`), truth 1 where it is;
    `in_modes` 1 where some mode of positive weight has the true order, else 0."""

    brier: Tensor
    in_modes: Tensor


def depth_order_scores(
    hypotheses, weights, gt, limbs: Sequence[tuple[int, int]], R, t, min_depth_diff: float = 0.02
) -> DepthOrderScores:
    """`DepthOrderScores` of a mixture against the truth. hypotheses (T, N, J, 3) and gt (T, J, 3) metres, weights
    (T, N) summing to 1 (0: padding), limbs L (start, end) joint pairs, R (3, 3), t (3,) world -> camera; limb-frames
    whose true depth difference is under `min_depth_diff` metres are NaN (as in `limb_flip_errors`)."""
    X, g = as_float_tensor(hypotheses, "hypotheses"), as_float_tensor(gt, "gt")
    w = torch.as_tensor(weights, dtype=X.dtype, device=X.device)
    if X.ndim != 4 or g.shape != X.shape[:1] + X.shape[2:] or w.shape != X.shape[:2]:
        raise InputError(
            f"hypotheses (T, N, J, 3), weights (T, N) and gt (T, J, 3) expected, got {tuple(X.shape)}, "
            f"{tuple(w.shape)} and {tuple(g.shape)}"
        )
    idx = torch.as_tensor(list(limbs), dtype=torch.long, device=X.device).reshape(-1, 2)
    per_mode = (_limb_depth_differences(X, idx, R, t) < 0).to(X.dtype)  # (T, N, L) 1: the end nearer
    d_gt = _limb_depth_differences(g, idx, R, t)  # (T, L)
    truth = (d_gt < 0).to(X.dtype)
    p = (w[..., None] * per_mode).sum(1)  # (T, L): `depth_order_probability`
    undefined = ~(d_gt.abs() >= min_depth_diff)
    agrees = (per_mode == truth[:, None]) & (w[..., None] > 0)  # (T, N, L)
    nan = torch.full_like(p, float("nan"))
    return DepthOrderScores(
        brier=torch.where(undefined, nan, (p - truth).square()),
        in_modes=torch.where(undefined, nan, agrees.any(1).to(p.dtype)),
    )


def distinct_modes(hypotheses, weights, min_distance: float = 0.05) -> Tensor:
    """How many different readings a mixture holds per frame: its modes of positive weight, taken heaviest first,
    that differ from every one taken before by `min_distance` metres or more in some joint coordinate (root
    included; the greedy suppression of `ptrack.hypotheses.mixture.distinct_minima`). hypotheses (T, N, J, 3),
    weights (T, N) -> (T,) counts."""
    X = torch.as_tensor(hypotheses)
    w = torch.as_tensor(weights, device=X.device)
    rank = torch.where(w > 0, -w, torch.full_like(w, math.inf)).to(X.dtype)  # padding (weight 0) never counts
    counts = [distinct_minima(x.flatten(-2), r, min_distance).numel() for x, r in zip(X, rank)]
    return torch.tensor(counts, dtype=torch.long)


def heaviest_mode(hypotheses, weights) -> Tensor:
    """Each frame's heaviest hypothesis: hypotheses (T, N, J, 3), weights (T, N) -> (T, J, 3)."""
    X = torch.as_tensor(hypotheses)
    pick = torch.as_tensor(weights, device=X.device).argmax(-1)
    return X[torch.arange(X.shape[0], device=X.device), pick]


#: the spread (1 sd, a share of the length) reported for a segment length taken from the height's proportions
#: (`ptrack.body.subject.SEGMENTS`, Winter 2009 fig. 4.1) rather than measured: an assumed anthropometric prior, not
#: a measurement of this person. Winter's fractions are means without a spread; adult limb segment lengths vary
#: between people by about 5% of their mean (coefficient of variation in anthropometric surveys such as ANSUR II:
#: C. C. Gordon et al., "2012 Anthropometric Survey of U.S. Army Personnel", NATICK/TR-15/007, 2014), and less
#: among people of one height, so for a given height this is a generous figure.
TEMPLATE_LENGTH_SPREAD = 0.05


def bone_lengths_report(
    lengths: dict[str, float], measured: dict[str, dict] | None, given: bool = False
) -> dict[str, dict]:
    """The segment lengths a run's model has and how well they are known, for metrics.json: {segment: {length_m,
    source, std_m, std_source[, frames]}}. Measured segments (`measured`: {segment: {"frames", "std_m"}}, from
    `subject.lengths: observed`) have source "observed" and the data's spread (std_source "bootstrap": the moving-block
    bootstrap over frames of `ptrack.estimators.lengths.segment_length_spread`, null when it could not be taken);
    segments from `subject.static` (entries with "source": "static") have source "static", std_m half the
    interquartile range of the static trial's samples (std_source "static_iqr") and frames its sample count;
    the others keep the template's proportions (source "template") with the prior spread TEMPLATE_LENGTH_SPREAD x
    length (std_source "prior"), which says nothing about the data. given (`subject.lengths: asf`): every segment is
    the skeleton file's (source "asf", std_m 0, std_source "given"). lengths: {segment: metres} of the model."""
    out: dict[str, dict] = {}
    for name, length in lengths.items():
        m = (measured or {}).get(name)
        if given:
            out[name] = {"length_m": length, "source": "asf", "std_m": 0.0, "std_source": "given"}
        elif m is not None and m.get("source") == "static":  # subject.static: the static trial's samples
            out[name] = {"length_m": length, "source": "static", "std_m": m["spread_m"], "std_source": "static_iqr"}
            out[name]["frames"] = m["samples"]
        elif m is not None:
            out[name] = {"length_m": length, "source": "observed", "std_m": m.get("std_m"), "std_source": "bootstrap"}
            out[name]["frames"] = m["frames"]
        else:
            out[name] = {
                "length_m": length,
                "source": "template",
                "std_m": TEMPLATE_LENGTH_SPREAD * length,
                "std_source": "prior",
            }
    return out
