"""One window of the golf tracker (`method: pca`, eq. 7): its predictions (`Prediction`), its energy from the
shared cost terms (`window_objective`), the Levenberg-Marquardt linearisation of it (`window_linearization`: the
state's kinematics, then the terms), its state vector and box. Shapes: N states, f frames,
m PCA weights, K' tracked joints, P pairs, J joints."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from ptrack.costs import CostTerm, Objective, PoseEval, PosePrior, Reprojection, Robust
from ptrack.costs.base import PoseJacobian
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


def window_objective(
    s: Setup, frames: Tensor, pred: Prediction, silhouette: RaySilhouette | None, pairs: WindowPairs | None = None
) -> Objective:
    """The energy of one window (eq. 7) from the shared cost terms, over a `PoseEval` whose q is the window's
    state x (N, m + 7 f), joints its world joints (N, f, J (+ P), 3) and pixels the projections (N, f, K' (+ P), 2)
    of its tracked joints (and of the pairs' moved points, after them; `window_linearization`): the tracked joints'
    robust reprojection (`Reprojection`, pca.joint_weight), the pairs' (pca.correspondence_weight), the foreground
    samples (`RaySilhouette`, pca.silhouette_weight), and the Gaussian priors on parts of the state (`PosePrior`
    with dofs): the predictions of alpha, mu, the root translation and rotation, alpha ~ N(0, sigma^2)
    (pca.alpha_prior_weight) and the start's timing."""
    p, cc = s.cfg.pca, s.cfg.costs
    m, f = s.m, frames.shape[0]
    device = frames.device
    k = s.tracked.numel()
    terms: dict[str, CostTerm] = {}
    weights = {}
    terms["joints"] = Reprojection(
        s.observed[frames], s.confidence[frames], cc.sigma_px, cc.loss, cc.robust_scale, keypoints=torch.arange(k)
    )
    weights["joints"] = p.joint_weight
    if pairs is not None:  # the pairs' points are projected after the tracked joints
        n_pairs = pairs.confidence.shape[-1]
        terms["correspondence"] = Reprojection(
            pairs.target, pairs.confidence, cc.sigma_px, cc.loss, cc.robust_scale, keypoints=k + torch.arange(n_pairs)
        )
        weights["correspondence"] = p.correspondence_weight
    if silhouette is not None:  # least squares, or robust per sample (pca.silhouette_loss)
        robust = p.silhouette_loss != "l2"
        terms["silhouette"] = Robust(silhouette, p.silhouette_loss, p.silhouette_scale) if robust else silhouette
        weights["silhouette"] = p.silhouette_weight
    fr = torch.arange(f, device=device)
    mus = m + fr
    t_cols = m + f + 6 * fr[:, None] + torch.arange(3, device=device)  # (f, 3) translation entries of x
    if pred.alpha is not None:
        terms["alpha"] = PosePrior(pred.alpha, p.alpha_sigma * s.alpha_sigma, dofs=torch.arange(m, device=device))
    if p.alpha_prior_weight > 0:
        terms["alpha_prior"] = PosePrior(torch.zeros_like(s.alpha_sigma), s.alpha_sigma, torch.arange(m, device=device))
        weights["alpha_prior"] = p.alpha_prior_weight
    if pred.mu is not None:
        terms["time"] = PosePrior(pred.mu, p.time_sigma, dofs=mus)
    if pred.timing is not None and p.timing_sigma is not None:
        terms["timing"] = PosePrior(pred.timing, p.timing_sigma, dofs=mus)
    if pred.trans is not None:
        terms["root_position"] = PosePrior(pred.trans.flatten(), p.root_sigma_m, dofs=t_cols.flatten())
    if pred.rotation:
        w_cols = (t_cols + 3).flatten()  # rotation-vector entries, predicted 0
        terms["root_rotation"] = PosePrior(s.alpha_sigma.new_zeros(3 * f), math.radians(p.root_sigma_deg), w_cols)
    return Objective(terms, weights)


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
    per frame] -> residuals, Jacobian, IRLS weights, energy of `window_objective`. ref (N|1, f, 3, 3): the frames'
    reference root rotations; a frame's rotation is exp(w) ref. pairs: the window's correspondences
    (`window_pairs`). start: body poses already computed (`start_pairs`), used for a state whose alpha and mu
    equal its key. The state's kinematics are here: the decoder's poses (`body_poses`), the joints' geometric
    Jacobian (and the pairs' body-fixed points', one FK for both), the root's turn and shift, the camera."""
    m, f = s.m, frames.shape[0]
    sk, cam = s.problem.skeleton, s.problem.observations.camera
    objective = window_objective(s, frames, pred, silhouette, pairs)
    n_joints = sk.num_joints
    seen = s.tracked  # what is projected: the tracked joints, and the pairs' points (joints J .. J + P - 1)
    if pairs is not None:
        n_pairs = pairs.confidence.shape[-1]
        seen = torch.cat([seen, n_joints + torch.arange(n_pairs, device=seen.device)])
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
        proj, dpix = cam.project_jacobian(joints[..., seen, :])
        d_seen = dj[..., seen, :, :]  # (N, f, K' (+ P), 3, P)
        depth_row = cam.R[2].to(x)[:, None]
        ev = PoseEval(x, joints, proj.pixels, proj.depth)
        jac = PoseJacobian(dj, dpix @ d_seen, (depth_row * d_seen).sum(-2))
        out = objective.linearize(ev, jac)  # unfolded: residuals, Jacobian, IRLS weights, energy
        return Linearization(out[0], out[1], out[2], out[3])

    return linearize


def window_silhouette(s: Setup, frames: Tensor) -> RaySilhouette | None:
    if s.rays is None:
        return None
    assert s.ray_valid is not None  # set with rays
    cam = s.problem.observations.camera
    return RaySilhouette(
        s.rays[frames],
        s.ray_valid[frames],
        cam.center,
        s.bones,
        s.silhouette_radii,
        sigma_m=s.cfg.pca.silhouette_sigma_m,
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
