"""A subject's bone lengths from the sequence itself: the whole trajectory and one length factor per group
of bones (left and right together) fitted at once, from an estimate made with the template's lengths.

Energy, over the T frames and G groups:

    E(q, s) = sum_t reprojection_t(q_t; lengths(s))                 robust, as costs.* set it
            + smooth_weight * sum_t |q_t+1 - q_t|^2 / (2 smooth_sigma^2)
            + limits_weight * sum_t limits(q_t)
            + sum_g s_g^2 / (2 prior_sigma^2)                        s_g = log(length factor of group g)

lengths(s)_j = template_j * exp(s_g(j)) (joints in no group keep their length). One camera's 2D constrains a
bone's length only through the frames where the bone lies near the image plane and through perspective;
the prior (the template's proportions, from the subject's height) holds what the 2D does not tell.
Minimised by L-BFGS over (q, s) together: alternating (poses, then lengths) stalls, since poses fitted to
wrong lengths tilt the bones until their 2D fits. The factors' standard deviations are those of the
energy's Hessian in s with the poses held (a lower bound: it ignores the poses' share of the uncertainty).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from ptrack.costs import JointLimits, PoseEval, Reprojection
from ptrack.costs.config import CostsConfig
from ptrack.problem import Estimate, Problem


class LengthFit(NamedTuple):
    """The refined estimate (q, joints with the fitted lengths), the fitted bone lengths (J,) metres, each
    group's log factor (G,) and its standard deviation (G,) (poses held), and the energy before and after."""

    estimate: Estimate
    lengths: Tensor
    log_factors: Tensor
    log_factor_std: Tensor
    energy_start: float
    energy_final: float


def fit_lengths(
    problem: Problem,
    start: Estimate,
    groups: Tensor,
    costs: CostsConfig,
    prior_sigma: float = 0.08,
    iterations: int = 200,
) -> LengthFit:
    """Fit the trajectory and the bone-length factors of `groups` (G, J) 0/1 membership, from `start`'s q
    (T, D). Returns a `LengthFit`; the estimate keeps `start`'s other fields but hypotheses and joint_std
    (made with the template's lengths)."""
    sk, obs, kps = problem.skeleton, problem.observations, problem.keypoints
    dtype, device = obs.keypoints.dtype, obs.keypoints.device
    base = torch.as_tensor(sk.lengths, dtype=dtype, device=device)
    member = groups.to(dtype=dtype, device=device)
    idx = kps.index(device)
    reproj = Reprojection(
        obs.keypoints, obs.confidence, sigma_px=costs.sigma_px, loss=costs.loss, scale=costs.robust_scale
    )
    lower, upper = sk.limits(dtype=dtype, device=device)
    limits = JointLimits(lower, upper, sigma=costs.limits_sigma)
    q = start.q.detach().to(dtype).clone().requires_grad_(True)
    s = torch.zeros(member.shape[0], dtype=dtype, device=device, requires_grad=True)

    def energy(q: Tensor, s: Tensor) -> Tensor:
        lengths = base * torch.exp(s @ member)
        joints = sk.forward_kinematics(q, lengths=lengths)
        proj = obs.camera.project(joints.index_select(-2, idx))
        ev = PoseEval(q=q, joints=joints, pixels=proj.pixels, depth=proj.depth)
        e = reproj.energy(ev) + costs.limits_weight * limits.energy(ev).sum()
        e = e + costs.smooth_weight * 0.5 * ((q[1:] - q[:-1]) / costs.smooth_sigma).pow(2).sum()
        return e + 0.5 * (s / prior_sigma).pow(2).sum()

    with torch.no_grad():
        e0 = float(energy(q, s))
    opt = torch.optim.LBFGS(
        [q, s], lr=1.0, max_iter=iterations, line_search_fn="strong_wolfe", tolerance_grad=1e-9, tolerance_change=1e-12
    )

    def closure() -> Tensor:
        opt.zero_grad()
        e = energy(q, s)
        e.backward()
        return e

    opt.step(closure)
    q_fit, s_fit = q.detach(), s.detach()
    if not bool(torch.isfinite(q_fit).all() & torch.isfinite(s_fit).all()):  # keep the start rather than NaN
        q_fit, s_fit = start.q.detach().to(dtype), torch.zeros_like(s_fit)
    hess = torch.autograd.functional.hessian(lambda x: energy(q_fit, x), s_fit)
    std = torch.linalg.inv(hess).diagonal().clamp_min(0).sqrt()
    lengths = base * torch.exp(s_fit @ member)
    with torch.no_grad():
        e1 = float(energy(q_fit, s_fit))
        joints = sk.forward_kinematics(q_fit, lengths=lengths)
    est = start._replace(q=q_fit, joints=joints, hypotheses=None, hypothesis_weights=None, hypothesis_costs=None)
    est = est._replace(joint_std=None, hypothesis_directions=None)
    return LengthFit(est, lengths, s_fit, std, e0, e1)
