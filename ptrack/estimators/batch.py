"""`method: batch` — the maximum a posteriori trajectory of the whole sequence (DiFranco, Cham &
Rehg 2001, eq. 5), by Levenberg-Marquardt on its block-banded normal equations.

For the trajectory Q = (q_0 .. q_{T-1}), q_t (D,), the energy is

    L(Q) = sum_t [ robust reprojection_t(q_t) + joint limits_t(q_t) ]        per frame (eqs. 1, 2)
         + 1/2 sum_n sum_t,d rho(|a_n * diff_n(Q)_t,d|^2)                   smoothing (eq. 3), n = 1, 2
         + 1/2 sum_f |(q_{t_f} - f_f) / sigma_f|^2 over the given dofs       angle keyframes (eq. 4)
         + 1/2 sum_g |(X_j(q_{t_g}) - x_g) / sigma_g|^2 over the given joints joint-position keyframes

with a_1 = 1 / (dt sigma_velocity), a_2 = 1 / (dt^2 sigma_acceleration) per dof: by default
(`batch.prior: cmu`) each CMU dof's own scale, the RMS velocity and acceleration of real motion
(`ptrack/data/cmu_smoothing.json`, fitted to the dev clips by `scripts/make_smoothing_prior.py`: a
knee accelerates at ~27 rad/s^2, the head at ~7), else `batch.velocity_sigma` / `accel_sigma` for
angles and `*_sigma_m` for the root position. rho is `batch.smooth_loss` at `batch.smooth_scale`
prior std (default Cauchy at 2: quadratic for the motion the prior expects, logarithmic for faster
motion, so a run's legs are not pulled flat; l2 is the paper's Gaussian). Missing keypoints
(confidence 0) and frames without any 2D add nothing: the dynamics fill them, which is how
`batch.upsample` reconstructs frames between the observed ones. The per-frame terms give the
diagonal blocks J_t^T W J_t of the Gauss-Newton Hessian (J_t from the geometric joint Jacobian, one
FK pass batched over all frames); the smoothing prior is linear in Q and couples each dof only with
itself, so it adds a band of diagonal couplings (block-pentadiagonal with an acceleration term;
constant for l2, else D_n^T diag(w a_n^2) D_n with the IRLS weights w = rho' of the residuals at the
current Q). `ptrack.optim.solvers.banded_levenberg_marquardt` solves it with `ptrack.optim.banded` (never a
dense (T*D)^2 matrix) inside the joint-limit box.

Uncertainty: the diagonal blocks of the inverse Gauss-Newton Hessian at the solution (the banded
recursion of `ptrack.optim.banded.marginal_blocks`) are the per-frame marginal covariances of the pose;
through the joint Jacobian G_t (J, 3, D) each joint's position covariance is G Sigma_t G^T, and
`joint_std` (T, J) is the square root of its trace (metres: the RMS 3D error it predicts). That
Laplace approximation only sees the curvature of the branch the solution took; with
`batch.uncertainty: branches` (the default) each limb's depth flips are added as a mixture
(`flip_posterior`, `ptrack.hypotheses.branches`): their second moment about the solution joins the trace.
The same re-solved branches restart the solve (`batch.flip_restarts` rounds, `lower_branch`): one
whose whole energy is lower than the solution's shows the solve stopped in a local minimum on the
other branch, and the solve continues from it.

The start is the per-frame fit (`method: frame`), or an earlier run's trajectory (`init_from`, warped
onto the keyframes: `warp_to_keyframes`), or the keyframes interpolated (`batch.init: keyframes`;
the per-frame fit where no keyframe gives every dof, e.g. a user's file of partial or joint keyframes).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import Tensor

from ptrack.body.limits import wrap_to_limits, wrapped_difference
from ptrack.body.pose_prior import smoothing_prior
from ptrack.costs import PoseEval, Reprojection, robust_loss, robust_loss_derivative
from ptrack.costs.base import PoseJacobian
from ptrack.errors import InputError
from ptrack.hypotheses.branches import BranchPosterior, branch_posterior, relax_branches
from ptrack.hypotheses.ik import ik_plan
from ptrack.hypotheses.jumps import check_independent, default_chains
from ptrack.optim.banded import BlockBanded, factorize, marginal_blocks, numpy_path
from ptrack.optim.jacobians import joint_jacobian, joint_jacobian_product
from ptrack.optim.solvers import BandedLinearization, BandedLMInfo, banded_levenberg_marquardt
from ptrack.problem import Estimate, Problem
from ptrack.threads import on_two_threads, one_thread, parallel_halves

log = logging.getLogger(__name__)

#: (problem, cfg, generator, progress) -> Estimate: an estimator whose per-frame fits start the batch solve
PerFrame = Callable[[Problem, Any, torch.Generator, Callable[[Iterable], Iterable]], Estimate]
_MIN_PART = 32  # `evaluate` splits the frames in two halves for two threads from 2 * _MIN_PART frames


@dataclass(frozen=True, eq=False)
class Trajectory:
    """The MAP objective of one sequence of T frames (D dofs, J joints, K keypoints); see the module
    docstring. Built by `trajectory_objective`.

    reprojection: `Reprojection` on observed (T, K, 2); lower, upper (D,) joint limits; limits_scale
    sqrt(weight) / sigma; smooth: ((n, a_n (D,)), ...) difference order and per-dof weight;
    band (T, W+1, D) the smoothing Hessian (band[t, k] = its (t, t-k) diagonal block's diagonal);
    kf_frames (F,), kf_target (F, D), kf_weight (F, D) = 1/sigma (0 where not given), angular (D,)
    bool; jk_frames (G,), jk_target (G, J, 3), jk_weight (G, J) = 1/sigma (0 where not given),
    jk_joints the joints some joint keyframe gives (the others' weights are all 0).
    """

    problem: Problem
    reprojection: Reprojection
    lower: Tensor
    upper: Tensor
    limits_scale: float
    smooth: tuple[tuple[int, Tensor], ...]
    band: Tensor
    kf_frames: Tensor
    kf_target: Tensor
    kf_weight: Tensor
    angular: Tensor
    jk_frames: Tensor
    jk_target: Tensor
    jk_weight: Tensor
    jk_joints: tuple[int, ...]
    smooth_loss: str = "l2"
    smooth_scale: float = 1.0

    def smooth_rho(self) -> Callable[[Tensor], Tensor] | None:
        """The smoothing residuals' robust loss on their squares (in prior std units), None for l2."""
        if self.smooth_loss == "l2":
            return None
        rho, c = robust_loss(self.smooth_loss), self.smooth_scale
        return lambda s: rho(s, c)


def _difference_coefficients(n: int) -> list[float]:
    """The n-th forward difference's coefficients: residual i = sum_j coef[j] q[i + j]. -> n+1 floats."""
    return [float((-1) ** (n - j) * math.comb(n, j)) for j in range(n + 1)]


def smoothing_band(t_len: int, smooth: tuple[tuple[int, Tensor], ...], like: Tensor) -> Tensor:
    """Band of sum_n a_n^2 D_n^T D_n (D_n: n-th forward difference over T frames, per dof).
    -> (T, W+1, D) with W = the largest n (at least 1); entry [t, k] is the (t, t-k) block's diagonal."""
    return weighted_band(t_len, tuple((n, a.square().expand(max(t_len - n, 0), -1)) for n, a in smooth), like)


def weighted_band(t_len: int, smooth: tuple[tuple[int, Tensor], ...], like: Tensor) -> Tensor:
    """Band of sum_n D_n^T diag(c_n) D_n with a weight per residual: smooth ((n, c_n (..., T-n, D)), ...)
    -> (..., T, W+1, D), W the largest n (at least 1); entry [t, k] is the (t, t-k) block's diagonal."""
    d = like.shape[-1]
    w = max([n for n, _ in smooth] + [1])
    lead = torch.broadcast_shapes(*[c.shape[:-2] for _, c in smooth]) if smooth else ()
    band = like.new_zeros(*lead, t_len, w + 1, d)
    for n, c in smooth:
        if t_len <= n:
            continue
        coef = _difference_coefficients(n)
        rows = t_len - n  # residual i covers frames i .. i+n
        for j in range(n + 1):
            for k in range(j + 1):
                band[..., j : rows + j, j - k, :] += coef[j] * coef[k] * c
    return band


def _difference_transpose(n: int, v: Tensor) -> Tensor:
    """D_n^T v over the frames: v (..., T-n, D) -> (..., T, D)."""
    coef = _difference_coefficients(n)
    return sum(
        (coef[j] * torch.nn.functional.pad(v, (0, 0, j, n - j)) for j in range(n + 1)),
        torch.zeros((), dtype=v.dtype, device=v.device),
    )


def robust_smoothing(
    obj: Trajectory, q: Tensor, derivatives: bool = True
) -> tuple[Tensor, Tensor | None, tuple[tuple[int, Tensor], ...]]:
    """The smoothing prior under the robust loss `obj.smooth_loss` (scale `obj.smooth_scale` prior std):
    q (B, T, D) -> energy (B, T) (each residual at its middle frame), gradient (B, T, D), and the
    Gauss-Newton weights ((n, w a_n^2 (B, T-n, D)), ...) with w the IRLS weight of each residual;
    without `derivatives`, the energy only (gradient None, no weights)."""
    rho, drho = robust_loss(obj.smooth_loss), robust_loss_derivative(obj.smooth_loss)
    b_len, t_len, _ = q.shape
    energy = q.new_zeros(b_len, t_len)
    grad = torch.zeros_like(q) if derivatives else None
    weights = []
    for n, a in obj.smooth:
        if t_len <= n:
            continue
        r = a * torch.diff(q, n=n, dim=-2)  # (B, T-n, D) in prior std units
        s = r.square()
        e = 0.5 * rho(s, obj.smooth_scale).sum(-1)
        energy = energy + torch.nn.functional.pad(e, ((n + 1) // 2, n - (n + 1) // 2))
        if grad is None:
            continue
        c = drho(s, obj.smooth_scale) * a.square()
        grad = grad + _difference_transpose(n, c * torch.diff(q, n=n, dim=-2))
        weights.append((n, c))
    return energy, grad, tuple(weights)


def _band_matvec(band: Tensor, q: Tensor) -> Tensor:
    """The smoothing Hessian times q: band (T, W+1, D), q (B, T, D) -> (B, T, D)."""
    out = band[:, 0] * q
    t_len = q.shape[-2]
    for k in range(1, min(band.shape[1] - 1, t_len - 1) + 1):
        c = band[k:, k]
        out = (
            out
            + torch.nn.functional.pad(c * q[:, :-k], (0, 0, k, 0))
            + torch.nn.functional.pad(c * q[:, k:], (0, 0, 0, k))
        )
    return out


def trajectory_objective(
    problem: Problem, cfg, dtype: torch.dtype, device: torch.device, smoothing: bool = True, limits: bool = True
) -> Trajectory:
    """The batch objective of `problem` under config `cfg` (costs.*, batch.*, keyframes.*).
    smoothing / limits False drop those terms (the ablation)."""
    sk, obs, cc, bc = problem.skeleton, problem.observations, cfg.costs, cfg.batch
    t_len, d = obs.num_frames, sk.num_dofs
    reproj = Reprojection(
        obs.keypoints.to(device=device, dtype=dtype),
        obs.confidence.to(device=device, dtype=dtype),
        sigma_px=cc.sigma_px,
        loss=cc.loss,
        scale=cc.robust_scale,
    )
    lower, upper = sk.limits(dtype=dtype, device=device)
    if not limits:
        lower, upper = torch.full_like(lower, -math.inf), torch.full_like(upper, math.inf)
    dt = obs.frame_interval
    trans = torch.zeros(d, dtype=torch.bool, device=device)
    trans[[i for i in sk.translation_dof.tolist() if i >= 0]] = True
    angular = torch.as_tensor(sk.angular_dofs(), device=device)

    table = smoothing_prior(bc.prior)

    def weights(sigma_angle: float | None, sigma_m: float | None, n: int, per_dof: dict) -> Tensor | None:
        if sigma_angle is None and sigma_m is None:
            return None
        sigma = [(sigma_m if is_t else sigma_angle) for is_t in trans.tolist()]
        # the prior's scale replaces the scalar of the dofs it names, in the terms that are on
        sigma = [per_dof.get(name, s) if s is not None else None for name, s in zip(sk.dof_names, sigma)]
        return torch.tensor([0.0 if s is None else 1.0 / (dt**n * s) for s in sigma], dtype=dtype, device=device)

    smooth = []
    if smoothing:
        for n, sa, sm, key in (
            (1, bc.velocity_sigma, bc.velocity_sigma_m, "velocity"),
            (2, bc.accel_sigma, bc.accel_sigma_m, "accel"),
        ):
            a = weights(sa, sm, n, table.get(key, {}))
            if a is not None:
                smooth.append((n, a))
    like = torch.zeros(d, dtype=dtype, device=device)
    band = smoothing_band(t_len, tuple(smooth), like)

    kf = problem.keyframes
    if kf is not None:
        frames = kf.frames.to(device=device, dtype=torch.long)
        mask = torch.ones_like(kf.q, dtype=torch.bool) if kf.mask is None else kf.mask
        mask = mask.to(device)
        default = torch.where(trans, cfg.keyframes.sigma_m, math.radians(cfg.keyframes.sigma_deg)).to(dtype)
        sigma = default.expand(kf.q.shape) if kf.sigma is None else kf.sigma.to(device=device, dtype=dtype)
        target = torch.where(mask, kf.q.to(device=device, dtype=dtype), 0.0)
        target = wrap_to_limits(target, *sk.limits(dtype=dtype, device=device), angular)
        kf_frames, kf_target, kf_weight = frames, target, torch.where(mask, 1.0 / sigma, 0.0)
    else:
        kf_frames, kf_target, kf_weight = (
            torch.zeros(0, dtype=torch.long, device=device),
            like.new_zeros(0, d),
            like.new_zeros(0, d),
        )
    jk = problem.joint_keyframes
    j = sk.num_joints
    if jk is not None:
        mask = jk.mask.to(device)
        jk_frames = jk.frames.to(device=device, dtype=torch.long)
        jk_target = torch.where(mask[..., None], jk.joints.to(device=device, dtype=dtype), 0.0)
        jk_weight = torch.where(mask, 1.0 / jk.sigma.to(device=device, dtype=dtype)[:, None], 0.0)
    else:
        jk_frames = torch.zeros(0, dtype=torch.long, device=device)
        jk_target, jk_weight = like.new_zeros(0, j, 3), like.new_zeros(0, j)
    for name, fr in (("keyframe", kf_frames), ("joint keyframe", jk_frames)):
        if fr.numel() and (int(fr.min()) < 0 or int(fr.max()) >= t_len):
            raise InputError(f"a {name} at frame {int(fr.max())} lies outside the {t_len} reconstructed frames")
    return Trajectory(
        problem,
        reproj,
        lower,
        upper,
        math.sqrt(cc.limits_weight) / cc.limits_sigma,
        tuple(smooth),
        band,
        kf_frames,
        kf_target,
        kf_weight,
        angular,
        jk_frames,
        jk_target,
        jk_weight,
        tuple(torch.nonzero((jk_weight != 0).any(0)).flatten().tolist()),
        bc.smooth_loss,
        bc.smooth_scale,
    )


class Evaluation(NamedTuple):
    """`evaluate`'s result: terms {name: (B, T)} (reprojection, limits, smooth, keyframes; each
    smoothing residual counted at its middle frame), h (B, T, D, D) the per-frame blocks J_t^T W J_t
    of every term but the smoothing band, g (B, T, D) the gradient of the whole energy (smoothing
    included), smooth_weights the robust smoothing's Gauss-Newton weights (`robust_smoothing`; empty
    for l2, whose band is the fixed `Trajectory.band`); h and g are None and smooth_weights empty
    without the Jacobian."""

    terms: dict[str, Tensor]
    h: Tensor | None
    g: Tensor | None
    smooth_weights: tuple[tuple[int, Tensor], ...]


def evaluate(obj: Trajectory, q: Tensor, with_jacobian: bool = True) -> Evaluation:
    """Per-frame energies of each term, and the per-frame Gauss-Newton pieces: q (B, T, D) ->
    `Evaluation`."""
    p = obj.problem
    sk, cam, kps = p.skeleton, p.observations.camera.to(device=q.device, dtype=q.dtype), p.keypoints
    b_len, t_len, _d = q.shape
    idx = kps.index(q.device)
    # the per-frame work (joint Jacobians, projections, J^T W J) runs on the two halves of the
    # sequence at once when torch may use two threads (`ptrack.threads.parallel_halves`)
    parts = [slice(0, t_len)]
    if with_jacobian and t_len >= 2 * _MIN_PART and parallel_halves(q.device):
        parts = [slice(0, t_len // 2), slice(t_len // 2, t_len)]

    def per_parts(fn: Callable[..., Any], extra: list | None = None) -> list:
        """fn(part, extra[i]) for every part, on two threads if two."""
        args = [(part,) if extra is None else (part, e) for part, e in zip(parts, extra or parts)]
        return [fn(*args[0])] if len(parts) == 1 else list(on_two_threads(fn, args[0], args[1]))

    fk: list[tuple[Tensor, Tensor]] | None = None
    if with_jacobian:

        def geometry(part: slice) -> tuple[Tensor, ...]:
            joints, rot = sk.forward_kinematics(q[:, part], rotations=True)  # (B, t, J, 3), (B, t, J, 3, 3)
            proj, dpix = cam.project_jacobian(joints.index_select(-2, idx))  # d pixels / d X (B, t, K, 2, 3)
            return joints, rot, proj.pixels, proj.depth, dpix

        geo = per_parts(geometry)
        joints, pixels, depth, dpix = (torch.cat([part[i] for part in geo], 1) for i in (0, 2, 3, 4))
        fk = [(part[0], part[1]) for part in geo]  # each part's FK, not joined: only read per part
        ev = PoseEval(q=q, joints=joints, pixels=pixels, depth=depth)
    else:
        from ptrack.problem import evaluate_pose

        ev = evaluate_pose(sk, cam, kps, q)
    rp = obj.reprojection
    k = rp.observed.shape[-2]
    r = rp.residual(ev).unflatten(-1, (t_len, k, 2))  # (B, T, K, 2)
    s = r.square().sum(-1)
    terms = {"reprojection": 0.5 * robust_loss(rp.loss)(s, rp.scale).sum(-1)}
    lim = (torch.clamp(q - obj.lower, max=0.0) + torch.clamp(q - obj.upper, min=0.0)) * obj.limits_scale
    terms["limits"] = 0.5 * lim.square().sum(-1)
    # the smoothing's derivatives only where used: l2's gradient and band come from the fixed band
    robust = with_jacobian and obj.smooth_loss != "l2"
    terms["smooth"], smooth_grad, smooth_weights = robust_smoothing(obj, q, derivatives=robust)
    kf_r = wrapped_difference(q[:, obj.kf_frames] - obj.kf_target, obj.angular) * obj.kf_weight  # (B, F, D)
    keyframes = q.new_zeros(b_len, t_len).index_add(1, obj.kf_frames, 0.5 * kf_r.square().sum(-1))
    jk_r = (ev.joints[:, obj.jk_frames] - obj.jk_target) * obj.jk_weight[..., None]  # (B, G, J, 3)
    terms["keyframes"] = keyframes.index_add(1, obj.jk_frames, 0.5 * jk_r.square().sum((-1, -2)))
    if not with_jacobian:
        return Evaluation(terms, None, None, smooth_weights)
    assert fk is not None  # with_jacobian

    # J_t^T W J_t of the reprojection: per keypoint, the residual's 2 x 3 derivative w.r.t. its joint
    # (`Reprojection.jacobian` on d pixels / d X) times sqrt(W), times that joint's geometric Jacobian
    # (`joint_jacobian_product`: from the keypoints' joints' (joint, ancestor slot) pairs, 2 values
    # each, never the (K, 3, D) rows)
    root_w = robust_loss_derivative(rp.loss)(s, rp.scale).sqrt()[..., None]  # (B, T, K, 1) sqrt IRLS weights
    jp = rp.jacobian(ev, PoseJacobian(ev.joints, dpix, ev.depth)).unflatten(-2, (t_len, k, 2))  # (B, T, K, 2, 3)
    jp = jp * root_w[..., None]
    rw = (r * root_w).flatten(-2)[..., None]  # (B, T, 2K, 1)
    h = q.new_empty(b_len, t_len, _d, _d)
    g = q.new_empty(b_len, t_len, _d)

    def normal_equations(part: slice, fk_part: tuple[Tensor, Tensor]) -> None:
        jw = joint_jacobian_product(sk, q[:, part], kps.joints, jp[:, part], fk_part)  # (B, t, K, 2, D)
        jw = jw.flatten(-3, -2)  # (B, t, 2K, D), rows (keypoint, x|y)
        if numpy_path(jw):  # CPU: numpy's batched product (BLAS per frame, less overhead than torch's)
            np.matmul(jw.numpy().swapaxes(-1, -2), jw.numpy(), out=h[:, part].numpy())
        else:
            torch.matmul(jw.mT, jw, out=h[:, part])  # one batched product per frame, in place
        torch.matmul(jw.mT, rw[:, part], out=g[:, part, :, None])

    per_parts(normal_equations, fk)
    outside = ((q < obj.lower) | (q > obj.upper)).to(q.dtype)
    diag = outside * obj.limits_scale**2
    g = g + lim * obj.limits_scale
    kf_w2 = obj.kf_weight.square()
    diag = diag.index_add(1, obj.kf_frames, kf_w2.expand(b_len, -1, -1))
    g = g.index_add(1, obj.kf_frames, kf_r * obj.kf_weight)
    if obj.jk_frames.numel():
        # only the rows of joints some joint keyframe gives (the others weigh 0): (B, G, J', 3, D)
        _, dx_jk = joint_jacobian(sk, q[:, obj.jk_frames], obj.jk_joints)
        gj = dx_jk * obj.jk_weight[:, list(obj.jk_joints), None, None]
        h.index_add_(1, obj.jk_frames, torch.einsum("bgjcd,bgjce->bgde", gj, gj))
        g = g.index_add(1, obj.jk_frames, torch.einsum("bgjcd,bgjc->bgd", gj, jk_r[:, :, list(obj.jk_joints)]))
    h.diagonal(dim1=-2, dim2=-1).add_(diag)  # in place: a diag_embed would write T D^2 zeros
    g = g + (smooth_grad if smooth_grad is not None else _band_matvec(obj.band, q))
    return Evaluation(terms, h, g, smooth_weights)


def linearization(obj: Trajectory) -> Callable[[Tensor], BandedLinearization]:
    """q (B, T, D) -> `BandedLinearization` of the whole objective (smoothing on the band; with a
    robust smoothing loss, the band of its IRLS weights at q)."""
    band = obj.band[None]  # (1, T, W+1, D)

    def linearize(q: Tensor) -> BandedLinearization:
        terms, h, g, weights = evaluate(obj, q)
        assert h is not None and g is not None  # with_jacobian
        b = weighted_band(q.shape[1], weights, q) if weights else band  # robust: the IRLS weights' band
        lower = b[:, :, 1:]  # (B|1, T, W, D): [t, k-1] = block (t, t-k)
        h.diagonal(dim1=-2, dim2=-1).add_(b[:, :, 0])
        energy = torch.stack(list(terms.values())).sum(0).sum(-1)
        return BandedLinearization(BlockBanded(h, lower.to(q)), g, energy)

    return linearize


def joint_std(obj: Trajectory, q: Tensor, hessian: BlockBanded, branches: BranchPosterior | None = None) -> Tensor:
    """Per-joint 3D standard deviation from the Gauss-Newton Hessian at the solution.

    q (B, T, D), hessian (diagonal (B, T, D, D)) -> (B, T, J) metres = sqrt(trace(G_t Sigma_t G_t^T))
    per joint, Sigma_t the marginal covariance of q_t (banded recursion). A tiny ridge (1e-9 of the
    largest diagonal entry) keeps directions no term constrains finite. With `branches`
    (`flip_posterior`), the flip branches' second moment about q is added to the variance:
    sqrt(trace(G Sigma G^T) + sum_c sum_l p_l |X_l - X|^2), each branch with q's curvature."""
    ridge = 1e-9 * hessian.diagonal.diagonal(dim1=-2, dim2=-1).amax((-2, -1)).clamp(min=1e-30)
    eye = torch.eye(q.shape[-1], dtype=q.dtype, device=q.device)
    factor, ok = factorize(BlockBanded(hessian.diagonal + ridge[:, None, None, None] * eye, hessian.lower))
    sigma = marginal_blocks(factor)  # (B, T, D, D)
    _, g = joint_jacobian(obj.problem.skeleton, q)  # (B, T, J, 3, D)
    var = torch.einsum("btjcd,btde,btjce->btj", g, sigma, g)
    if branches is not None:
        var = var + branches.variance
    std = var.clamp(min=0).sqrt()
    return torch.where(ok[:, None, None], std, torch.full_like(std, math.nan))


def solve_trajectory(
    obj: Trajectory, start: Tensor, bc, callback: Callable[[int, Tensor, Tensor], None] | None = None
) -> tuple[Tensor, BandedLMInfo]:
    """The whole objective's Levenberg-Marquardt from start (B, T, D) inside the joint-limit box, with
    the `batch.*` settings bc (iterations, tol, damping) -> q (B, T, D), `BandedLMInfo`."""
    return banded_levenberg_marquardt(
        linearization(obj),
        start,
        obj.lower,
        obj.upper,
        max_iter=bc.iterations,
        tol=bc.tol,
        gtol=bc.tol * 1e-2,
        damping=bc.damping,
        callback=callback,
    )


def flip_posterior(obj: Trajectory, q: Tensor, bc) -> BranchPosterior | None:
    """The flip branches of the solution q (B, T, D) in the posterior (`ptrack.hypotheses.branches`): every limb's
    depth-labelled leaves (the default chains: arms, legs, head) through q's projections, each leaf's
    whole trajectory re-solved from there by `solve_trajectory` with the `batch.*` settings bc (0
    iterations: the rigid leaves), and their marginal
    probabilities per frame from the objective itself (per-frame terms, smoothing between
    consecutive frames' leaves; forward-backward). None (with a warning) for a model without the
    default chains. Costs one batched solve of 4 trajectories per chain (20 on CMU skeletons)."""
    sk = obj.problem.skeleton
    try:
        chains = default_chains(sk)
        check_independent(sk, chains)
        plans = tuple(ik_plan(sk, c) for c in chains)
    except InputError as e:
        log.warning("batch: no flip chains on this model (%s): no flip restarts, the Laplace std only", e)
        return None

    def frame_energy(x: Tensor) -> Tensor:
        terms = evaluate(obj, x, with_jacobian=False).terms
        return terms["reprojection"] + terms["limits"] + terms["keyframes"]

    def relax(starts: Tensor) -> Tensor:
        return relax_branches(starts, lambda x: solve_trajectory(obj, x, bc)[0])

    cam = obj.problem.observations.camera
    relaxed = relax if bc.iterations > 0 else None
    return branch_posterior(sk, cam, q, chains, plans, frame_energy, obj.smooth, relaxed, obj.smooth_rho())


def lower_branch(obj: Trajectory, q: Tensor, branches: BranchPosterior) -> Tensor | None:
    """The re-solved flip branch (`flip_posterior`) of lowest whole energy, if it is lower than the
    solution q's (B = 1): -> (1, T, D), or None. A flipped limb's trajectory that the objective itself
    prefers means the solve stopped in a local minimum on the other branch."""
    cand = branches.branches.q[0].flatten(0, 1)  # (C L, T, D)
    energy = _energy(obj, torch.cat([q, cand]))
    best = int(torch.argmin(energy[1:]))
    if not bool(energy[1 + best] < energy[0] - 1e-9 * energy[0].abs()):
        return None
    return cand[best][None]


def _energy(obj: Trajectory, q: Tensor) -> Tensor:
    """The whole objective of trajectories q (N, T, D) -> (N,)."""
    terms = evaluate(obj, q, with_jacobian=False).terms
    return torch.stack(list(terms.values())).sum(0).sum(-1)


def load_init(run_dir: str | Path, problem: Problem, dtype: torch.dtype, device: torch.device) -> Tensor:
    """The trajectory q (T, D) of an earlier run folder, checked to be the same model and frames."""
    path = Path(run_dir) / "result.npz"
    if not path.is_file():
        raise InputError(f"init_from {run_dir}: not a run folder (no result.npz)")
    try:
        with np.load(path) as z:
            q, names, times = z["q"], [str(n) for n in z["dof_names"]], z["times"]
    except (OSError, ValueError, KeyError) as e:
        raise InputError(f"init_from {path}: unreadable run result ({' '.join(str(e).split())})") from None
    sk, obs = problem.skeleton, problem.observations
    if names != list(sk.dof_names):
        raise InputError(
            f"init_from {run_dir}: its dofs ({len(names)}) are not this model's ({sk.num_dofs}); "
            f"the run must use the same skeleton and model.freeze"
        )
    own = obs.times.detach().double().cpu().numpy()
    if q.shape != (obs.num_frames, sk.num_dofs) or times.shape != own.shape or not np.allclose(times, own, atol=1e-6):
        raise InputError(
            f"init_from {run_dir}: its {q.shape[0]} frames are not this run's {obs.num_frames} frames "
            f"(data.start/stop/stride and batch.upsample must match)"
        )
    if not np.isfinite(q).all():
        raise InputError(f"init_from {run_dir}: its trajectory has non-finite values")
    return torch.as_tensor(q, dtype=dtype, device=device)


def has_full_keyframe(problem: Problem) -> bool:
    """Whether some keyframe gives every dof (an angle keyframe with no dof left out)."""
    kf = problem.keyframes
    return kf is not None and kf.frames.numel() > 0 and (kf.mask is None or bool(kf.mask.all(-1).any()))


def interpolate_keyframes(problem: Problem, lower: Tensor, upper: Tensor) -> Tensor:
    """A start from the full angle keyframes: linear between them, constant beyond. -> (T, D)."""
    kf = problem.keyframes
    t_len = problem.observations.num_frames
    full = (
        None
        if kf is None
        else (torch.ones(kf.frames.shape, dtype=torch.bool) if kf.mask is None else kf.mask.all(-1).cpu())
    )
    if kf is None or full is None or not bool(full.any()):
        raise InputError(
            "batch.init is 'keyframes' but no keyframe gives every dof: start from the per-frame fits "
            "(batch.init=frame) or add a full keyframe"
        )
    frames = kf.frames.cpu()[full]
    order = torch.argsort(frames)
    frames, q = frames[order], kf.q.to(lower)[full.to(lower.device)][order.to(lower.device)]
    angular = torch.as_tensor(problem.skeleton.angular_dofs(), device=lower.device)
    q = wrap_to_limits(q, lower, upper, angular)
    t = torch.arange(t_len, dtype=lower.dtype, device=lower.device)
    f = frames.to(lower)
    idx = torch.searchsorted(f, t, right=True).clamp(1, max(len(f) - 1, 1)) - 1
    nxt = (idx + 1).clamp(max=len(f) - 1)
    span = (f[nxt] - f[idx]).clamp(min=1)
    u = ((t - f[idx]) / span).clamp(0, 1)[:, None]
    out = q[idx] + u * (q[nxt] - q[idx])
    return torch.minimum(torch.maximum(out, lower), upper)


def warp_to_keyframes(q: Tensor, obj: Trajectory) -> Tensor:
    """Motion warping of a start (Witkin & Popovic 1995): per dof, the offsets that bring q (T, D) onto
    each angle keyframe giving that dof, linearly interpolated in time between those keyframes (held
    beyond the first and last), added to q; keyframe dofs already met within 3 of their std count as
    offset 0 (anchors: a solution misses some keyframe dofs by 1-2 std where the data pulls against
    them, and re-meeting those exactly would only move the start off its minimum). -> (T, D). A start
    from an earlier solution (`init_from`) already meets the keyframes it was solved with (offsets ~0
    there), so a keyframe added since is met at once and its change fades out towards its neighbours:
    the solver refines that stretch instead of first dragging it there."""
    if obj.kf_frames.numel() == 0:
        return q
    diff = wrapped_difference(obj.kf_target - q[obj.kf_frames], obj.angular)  # (F, D)
    given = (obj.kf_weight > 0).cpu().numpy()
    frames = obj.kf_frames.cpu().numpy()
    # a dof the start already meets within 3 of its keyframe's std is an anchor: offset 0 there
    delta = torch.where(diff.abs() * obj.kf_weight > 3, diff, 0.0).detach().cpu().double().numpy()
    order = np.argsort(frames, kind="stable")
    frames, delta, given = frames[order], delta[order], given[order]
    t = np.arange(q.shape[0], dtype=np.float64)
    offset = np.zeros(tuple(q.shape))
    for d in range(q.shape[1]):
        sel = given[:, d]
        if sel.any():
            offset[:, d] = np.interp(t, frames[sel].astype(np.float64), delta[sel, d])
    return q + torch.as_tensor(offset, dtype=q.dtype, device=q.device)


def estimate_batch(
    problem: Problem,
    cfg,
    generator: torch.Generator,
    progress: Callable[[Iterable], Iterable] = lambda x: x,
    callback: Callable[[int, Tensor, Tensor], None] | None = None,
    per_frame: PerFrame | None = None,
) -> Estimate:
    """The MAP trajectory (module docstring). Deterministic given its start (uses no randomness).
    Solved in float64 on the observations' device; the Estimate is in the observations' dtype.

    per_frame(problem, cfg, generator, progress) -> Estimate: the per-frame fits the start comes from when
    neither `init_from` nor the keyframes give it (`ptrack.estimators.estimate_batch` passes
    `estimate_frames`; no estimator imports another). Needed then, and None, it raises ValueError.

    callback(iteration, q (1, T, D), cost (1,)) is called after every solver iteration. Runs on one
    intra-op thread (`ptrack.threads.one_thread`: small per-frame products, shared cores); with torch
    allowed 2 or more threads, the linearisation's per-frame work runs on the sequence's two halves on
    two threads (`evaluate`)."""
    with one_thread():
        return _estimate(problem, cfg, generator, progress, callback, per_frame)


def _estimate(
    problem: Problem,
    cfg,
    generator: torch.Generator,
    progress: Callable[[Iterable], Iterable],
    callback: Callable[[int, Tensor, Tensor], None] | None,
    per_frame: PerFrame | None,
) -> Estimate:
    bc = cfg.batch
    obs = problem.observations
    out_dtype, device = obs.keypoints.dtype, obs.keypoints.device
    dtype = torch.float64  # the whole-sequence normal equations are solved in double precision
    obj = trajectory_objective(problem, cfg, dtype, device)
    lower, upper = obj.lower, obj.upper
    if cfg.init_from:
        q0 = warp_to_keyframes(load_init(cfg.init_from, problem, dtype, device), obj)
    elif bc.init == "keyframes" and has_full_keyframe(problem):
        q0 = interpolate_keyframes(problem, lower, upper)
    else:
        if bc.init == "keyframes":
            log.info("batch: no keyframe gives every dof, so the start is the per-frame fits (as batch.init=frame)")
        if per_frame is None:
            raise ValueError("estimate_batch: the start is the per-frame fit here; pass per_frame (estimate_frames)")
        kf = problem.keyframes
        full0 = kf is not None and any(
            bool(kf.mask is None or kf.mask[i].all()) for i in torch.nonzero(kf.frames == 0).flatten().tolist()
        )
        frame_cfg = cfg if full0 else dataclasses.replace(cfg, frame=dataclasses.replace(cfg.frame, init="rest"))
        q0 = per_frame(problem, frame_cfg, generator, progress).q
    q0 = wrap_to_limits(q0.detach().to(dtype), lower, upper, obj.angular)
    done = 0  # iterations so far: a restart's costs follow the first solve's on the logged timeline

    def solve(start: Tensor) -> tuple[Tensor, BandedLMInfo]:
        def logged(it: int, x: Tensor, cost: Tensor) -> None:
            if callback is not None:
                callback(done + it, x, cost)

        return solve_trajectory(obj, start, bc, logged)

    q, info = solve(q0[None])
    history = info.history
    log.info(
        "batch: %d iterations, cost %.6g -> %.6g", int(info.iterations[0]), float(history[0, 0]), float(info.cost[0])
    )
    branches: BranchPosterior | None = None
    for _ in range(bc.flip_restarts):
        with torch.no_grad():
            branches = flip_posterior(obj, q, bc)
            start = None if branches is None else lower_branch(obj, q, branches)
        if start is None:
            break
        done = history.shape[0] - 1
        q, info = solve(start)
        history = torch.cat([history, info.history[1:]])
        branches = None  # the posterior of the trajectory it replaced
        log.info("batch: restarted from a flip branch, cost -> %.6g", float(info.cost[0]))
    with torch.no_grad():
        terms = evaluate(obj, q, with_jacobian=False).terms
        joints = problem.skeleton.forward_kinematics(q[0])
        std = None
        if bc.uncertainty:
            mode = "branches" if bc.uncertainty is True else bc.uncertainty
            if mode == "branches" and branches is None:
                branches = flip_posterior(obj, q, bc)
            std = joint_std(obj, q, info.hessian, branches if mode == "branches" else None)[0]
    terms = {name: v[0].to(out_dtype) for name, v in terms.items()}
    return Estimate(
        q=q[0].to(out_dtype),
        joints=joints.to(out_dtype),
        cost=torch.stack(list(terms.values())).sum(0),
        terms=terms,
        joint_std=None if std is None else std.to(out_dtype),
        solver_cost=history[:, 0].to(out_dtype),
    )
