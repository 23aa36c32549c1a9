"""One window of the golf tracker (`method: pca`, eq. 7): its predictions (`Prediction`), the Levenberg-Marquardt
linearisation of its energy (`window_linearization`), its state vector and box. Shapes: N states, f frames,
m PCA weights, K' tracked joints, P pairs, J joints."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from ptrack.costs import robust_loss, robust_loss_derivative
from ptrack.costs.ray_silhouette import RaySilhouette
from ptrack.estimators.pca.pairs import StartBody, WindowPairs
from ptrack.estimators.pca.poses import body_poses, rotation_exp
from ptrack.estimators.pca.setup import Setup
from ptrack.optim.jacobians import joint_and_point_jacobian, joint_jacobian
from ptrack.optim.solvers import Linearization


def _world(s: Setup, x_body: Tensor, dx_body: Tensor, rot: Tensor, trans: Tensor) -> tuple[Tensor, Tensor]:
    """Body joints (the root at its rest position r0, unrotated) turned by rot (..., 3, 3) about r0 and moved
    by trans (..., 3): x_body (..., J, 3), dx_body (..., J, 3, P) -> world joints and their derivative."""
    r0 = x_body[..., :1, :]
    x = trans[..., None, :] + r0 + (x_body - r0) @ rot.mT
    return x, rot[..., None, :, :] @ dx_body


@dataclass(frozen=True)
class Prediction:
    """The E_D terms of a window of f frames: predicted alpha (m,), mu (f,), root translation (f, 3);
    None drops a term. The predicted root rotations are the window's reference rotations (its rotation
    parameters are rotation vectors about them, predicted 0)."""

    alpha: Tensor | None
    mu: Tensor | None
    trans: Tensor | None
    rotation: bool = True  # the rotation prediction term (0 for the start's placement)
    timing: Tensor | None = None  # (f,) the frames' start times, held by the prior of std pca.timing_sigma


def window_linearization(
    s: Setup,
    frames: Tensor,
    ref: Tensor,
    pred: Prediction,
    silhouette: RaySilhouette | None,
    pairs: WindowPairs | None = None,
    start: StartBody | None = None,
) -> Callable[[Tensor], Linearization]:
    """The LM `linearize` of one window: state x (N, m + 7 f) = [alpha, mu, (translation, rotation vector)
    per frame] -> residuals, Jacobian, IRLS weights, energy. ref (N|1, f, 3, 3): the frames' reference
    root rotations; a frame's rotation is exp(w) ref. pairs: the window's correspondences (`window_pairs`).
    start: body poses already computed (`start_pairs`), used for a state whose alpha and mu equal its key."""
    p, cc = s.cfg.pca, s.cfg.costs
    m, f = s.m, frames.shape[0]
    sk, cam = s.problem.skeleton, s.problem.observations.camera
    obs, w_obs = s.observed[frames], s.weight[frames]  # (f, K', 2), (f, K')
    rho, drho = robust_loss(cc.loss), robust_loss_derivative(cc.loss)
    scale = cc.robust_scale
    sqrt_joint, sqrt_fg = math.sqrt(p.joint_weight), math.sqrt(p.silhouette_weight)
    sqrt_corr = math.sqrt(p.correspondence_weight)
    n_joints, n_tracked = sk.num_joints, s.tracked.numel()
    seen, target, w_seen = s.tracked, obs, w_obs  # what is projected: the tracked joints, and the pairs' points
    if pairs is not None:
        n_pairs = pairs.weight.shape[-1]
        seen = torch.cat([seen, n_joints + torch.arange(n_pairs, device=seen.device)])
        target, w_seen = torch.cat([obs, pairs.target], -2), torch.cat([w_obs, pairs.weight], -1)
    alpha_pred_sigma = p.alpha_sigma * s.alpha_sigma
    sqrt_prior = math.sqrt(p.alpha_prior_weight)
    fr = torch.arange(f, device=frames.device)
    t_cols = m + f + 6 * fr[:, None] + torch.arange(3, device=frames.device)  # (f, 3) translation columns
    w_cols = t_cols + 3  # rotation-vector columns

    def linearize(x: Tensor) -> Linearization:
        n, npar = x.shape
        alpha, mu, g = x[:, :m], x[:, m : m + f], x[:, m + f :].reshape(n, f, 6)
        trans, w = g[..., :3], g[..., 3:]
        fk = None
        if start is not None and n == 1 and torch.equal(x[:, : m + f], start.key):  # the same body poses
            q, dq, fk = start.q, start.dq, (start.joints, start.rotations)
        else:
            q, dq = body_poses(s, alpha, mu)
        if pairs is None:
            xb, dxb_dq = joint_jacobian(sk, q)  # (N, f, J, 3), (N, f, J, 3, D)
        else:  # the pairs' body-fixed points ride along as extra "joints" J .. J + P - 1 (one FK for both)
            xb, dxb_dq, xp, dxp_dq = joint_and_point_jacobian(sk, q, pairs.anchors.joint, pairs.anchors.local, fk)
            xb, dxb_dq = torch.cat([xb, xp], -2), torch.cat([dxb_dq, dxp_dq], -3)
        dxb = dxb_dq @ dq[:, :, None]  # (N, f, J (+ P), 3, m + f)
        r_w, jl = rotation_exp(w)
        rot = r_w @ ref
        joints, dj_body = _world(s, xb, dxb, rot, trans)
        dj = x.new_zeros(*joints.shape, npar)
        dj[..., : m + f] = dj_body
        eye3 = torch.eye(3, dtype=x.dtype, device=x.device)
        dj[:, fr[:, None], :, :, t_cols] = eye3[:, None, None, :]  # (f, 3 columns, N, J, 3): every joint moves
        lever = joints - trans[..., None, :] - xb[..., :1, :]  # (N, f, J, 3) from the root
        # d joint / d w_k = (J_l e_k) x lever: (N, f, J, 3 columns k, 3 coordinates)
        dw = torch.linalg.cross(jl.mT[:, :, None], lever[..., None, :].expand(*lever.shape[:-1], 3, 3))
        dj[:, fr[:, None], :, :, w_cols] = dw.permute(1, 3, 0, 2, 4)
        # tracked joints (and the pairs' points, projected with them): robust reprojection
        proj, dpix = cam.project_jacobian(joints[..., seen, :])
        r_seen = (proj.pixels - target) * w_seen[..., None]  # (N, f, K' (+ P), 2) whitened
        j_seen = (dpix @ dj[..., seen, :, :]) * w_seen[..., None, None]  # (N, f, K' (+ P), 2, P)
        r_kp, j_kp = r_seen[..., :n_tracked, :], j_seen[..., :n_tracked, :, :]
        sq = r_kp.square().sum(-1)
        res = [sqrt_joint * r_kp.reshape(n, -1)]
        jac = [sqrt_joint * j_kp.reshape(n, -1, npar)]
        wts = [drho(sq, scale)[..., None].expand_as(r_kp).reshape(n, -1)]
        energy = 0.5 * p.joint_weight * rho(sq, scale).flatten(1).sum(-1)
        if pairs is not None:  # correspondences: robust reprojection of the moved points against p2
            r_c, j_c = r_seen[..., n_tracked:, :], j_seen[..., n_tracked:, :, :]  # `reprojection_rows`
            r_c = torch.where(pairs.weight[..., None] > 0, r_c, torch.zeros_like(r_c))  # a dropped pair's p2: anything
            sq_c = r_c.square().sum(-1)
            res.append(sqrt_corr * r_c.reshape(n, -1))
            jac.append(sqrt_corr * j_c.reshape(n, -1, npar))
            wts.append(drho(sq_c, scale)[..., None].expand_as(r_c).reshape(n, -1))
            energy = energy + 0.5 * p.correspondence_weight * rho(sq_c, scale).flatten(1).sum(-1)
            joints, dj = joints[..., :n_joints, :], dj[..., :n_joints, :, :]
        plain = []  # least-squares blocks: (residual (N, M), jacobian (N, M, P) or (M, P))
        if silhouette is not None:
            r_fg, j_fg = silhouette.linearize_joints(joints, dj)
            plain.append((sqrt_fg * r_fg, sqrt_fg * j_fg))
        eye = torch.eye(npar, dtype=x.dtype, device=x.device)
        if pred.alpha is not None:
            plain.append(((alpha - pred.alpha) / alpha_pred_sigma, eye[:m] / alpha_pred_sigma[:, None]))
        if sqrt_prior > 0:
            plain.append((sqrt_prior * alpha / s.alpha_sigma, sqrt_prior * eye[:m] / s.alpha_sigma[:, None]))
        if pred.mu is not None:
            plain.append(((mu - pred.mu) / p.time_sigma, eye[m : m + f] / p.time_sigma))
        if pred.timing is not None and p.timing_sigma is not None:
            plain.append(((mu - pred.timing) / p.timing_sigma, eye[m : m + f] / p.timing_sigma))
        if pred.trans is not None:
            plain.append(((trans - pred.trans).reshape(n, -1) / p.root_sigma_m, eye[t_cols.flatten()] / p.root_sigma_m))
        if pred.rotation:
            sig = math.radians(p.root_sigma_deg)
            plain.append((w.reshape(n, -1) / sig, eye[w_cols.flatten()] / sig))
        for r, j in plain:
            res.append(r)
            jac.append(j.expand(n, *j.shape[-2:]) if j.ndim == 2 else j)
            wts.append(torch.ones_like(r))
            energy = energy + 0.5 * r.square().sum(-1)
        return Linearization(torch.cat(res, -1), torch.cat(jac, -2), torch.cat(wts, -1), energy)

    return linearize


def window_silhouette(s: Setup, frames: Tensor) -> RaySilhouette | None:
    if s.rays is None:
        return None
    assert s.ray_valid is not None  # set with rays
    cam = s.problem.observations.camera
    return RaySilhouette(
        s.rays[frames], s.ray_valid[frames], cam.center, s.bones, s.radii, sigma_m=s.cfg.pca.silhouette_sigma_m
    )


def state_vector(alpha: Tensor, mu: Tensor, trans: Tensor) -> Tensor:
    """(m,), (f,), (f, 3) -> x (1, m + 7 f): rotation vectors 0 (the window starts at its reference rotations)."""
    return torch.cat([alpha, mu, torch.cat([trans, torch.zeros_like(trans)], -1).flatten()])[None]


def window_bounds(
    s: Setup, f: int, like: Tensor, alpha: Tensor | None = None, mu: Tensor | None = None
) -> tuple[Tensor, Tensor]:
    """Box of a window's state: mu in [0, 1], alpha within pca.alpha_bound training stds; alpha and mu held
    (lower = upper) where given."""
    m = s.m
    lo = torch.full((m + 7 * f,), -math.inf, dtype=like.dtype, device=like.device)
    hi = torch.full_like(lo, math.inf)
    lo[m : m + f], hi[m : m + f] = 0.0, 1.0
    bound = s.cfg.pca.alpha_bound * s.alpha_sigma
    lo[:m], hi[:m] = -bound, bound
    if alpha is not None:
        lo[:m], hi[:m] = alpha, alpha
    if mu is not None:
        lo[m : m + f], hi[m : m + f] = mu, mu
    return lo, hi
