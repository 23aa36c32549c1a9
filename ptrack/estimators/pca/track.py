"""`estimate_pca`: the golf tracker's sliding windows over a whole sequence (`ptrack.estimators.pca`)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable, Mapping
from typing import cast

import torch
from torch import Tensor

from ptrack.costs import PoseEval, Reprojection, robust_loss
from ptrack.costs.ray_silhouette import RaySilhouette
from ptrack.estimators.pca.config import PcaRunConfig
from ptrack.estimators.pca.pairs import correspondence_points, start_pairs
from ptrack.estimators.pca.poses import orthonormal, poses_of, rotation_exp
from ptrack.estimators.pca.setup import Setup, make_setup
from ptrack.estimators.pca.start import initial_timing, place_root
from ptrack.estimators.pca.window import (
    Prediction,
    state_vector,
    window_bounds,
    window_linearization,
    window_silhouette,
)
from ptrack.optim.solvers import levenberg_marquardt
from ptrack.problem import Estimate, MotionFit, Problem, later_frames
from ptrack.threads import one_thread

log = logging.getLogger(__name__)


def estimate_pca(
    problem: Problem,
    cfg: PcaRunConfig,
    generator: torch.Generator,
    progress: Callable[[Iterable], Iterable] = lambda x: x,
    after: Mapping[str, Callable[..., Estimate]] | None = None,
) -> Estimate:
    """Track the whole sequence with the PCA motion model (`ptrack.estimators.pca`). Deterministic. Runs on one
    intra-op thread (`ptrack.threads.one_thread`): a window's solve is small (m + 7 f parameters, f frames'
    FK), which multithreaded BLAS does not speed up and which, on a machine whose cores other jobs hold, waits
    on its spinning threads: `scripts/bench_pca.py --threads` measured the swing 11.4x faster on one thread than
    on torch's default 2 (2 shared cores, load 10).

    after: `pca.after_swing` value -> `(problem, cfg, q_before, progress) -> Estimate`, the estimator that tracks
    the frames after the swing's end (a `Problem` of those frames) from the swing's last pose q_before (D,)
    (`ptrack.estimators` passes `frame`: the per-frame fits, and `batch`: the MAP trajectory with q_before as a
    keyframe). The swing ends at its last key posture found in the 2D (the end of the follow-through): the
    model's time stops at 1 there, and a clip that goes on (the golfer lowers the club, turns, walks) shows
    motion no training swing has. With `pca.after_swing: hold`, or no such estimator given, the model's last
    pose is held over those frames and only the root is tracked."""
    with one_thread():
        return _track(problem, cfg, progress, after)


def _track(
    problem: Problem,
    cfg: PcaRunConfig,
    progress: Callable[[Iterable], Iterable],
    after: Mapping[str, Callable[..., Estimate]] | None,
) -> Estimate:
    s = make_setup(problem, cfg)
    p = cfg.pca
    obs = problem.observations
    sk = problem.skeleton
    dtype, device = obs.keypoints.dtype, obs.keypoints.device
    t_count, m = obs.num_frames, s.m
    keys, mu_init = initial_timing(s)
    log.info("pca: key postures at frames %s", keys.tolist())
    wanted = p.after_swing != "hold" and p.iterations > 0
    hand_on = (after or {}).get(p.after_swing) if wanted else None
    if wanted and hand_on is None:
        log.warning("pca: no estimator %r given for pca.after_swing; the swing's last pose is held", p.after_swing)
    # frames [0, swing) are the swing's, tracked by the model's windows; the rest is handed on (or held)
    swing = min(int(keys[-1]) + 1, t_count) if hand_on is not None else t_count
    f = min(p.window, swing)
    rot0, trans0 = place_root(s, mu_init[0])
    alpha = torch.zeros(t_count, m, dtype=dtype, device=device)  # per frame: the weights of its last window
    mu = mu_init.clone()
    rot = rot0.expand(t_count, 3, 3).clone()
    trans = trans0.expand(t_count, 3).clone()
    if p.iterations > 0:
        a_prev = torch.zeros(m, dtype=dtype, device=device)
        lo, hi = window_bounds(s, f, mu)
        step = min(p.step, f)
        starts = list(range(0, swing - f + 1, step))
        if starts[-1] != swing - f:
            starts.append(swing - f)
        known = 0  # frames [0, known) have been in a window
        for start in progress(starts):
            frames = torch.arange(start, start + f, device=device)
            for t in range(max(known, 1), start + f):  # frames new to this window: the trajectory continued
                if t >= 2:  # at the speed of the two frames before (each new frame from the ones predicted before it)
                    mu[t] = (2 * mu[t - 1] - mu[t - 2]).clamp(0, 1)
                    trans[t] = 2 * trans[t - 1] - trans[t - 2]
                    rot[t] = orthonormal(rot[t - 1] @ rot[t - 2].mT @ rot[t - 1])
                else:
                    mu[t], rot[t], trans[t] = mu[t - 1], rot[t - 1], trans[t - 1]
            known = start + f
            mu_hat, rot_hat, trans_hat = mu[frames].clone(), rot[frames].clone(), trans[frames].clone()
            if start > 0:  # time runs forward: no frame of the window before the frame that left it last
                lo[m : m + f] = mu[start - 1]
                mu_hat = torch.maximum(mu_hat, mu[start - 1])
            pred = Prediction(a_prev, mu_hat, trans_hat, timing=mu_init[frames])
            pairs = body0 = None
            if s.corr is not None:  # backprojected on the window's starting state (frame start - 1: its estimate)
                b = start - 1
                before = (alpha[b], mu[b], rot[b], trans[b]) if start > 0 else None
                pairs, body0 = start_pairs(s, frames, a_prev, mu_hat, rot_hat, trans_hat, before)
            lin = window_linearization(s, frames, rot_hat[None], pred, window_silhouette(s, frames), pairs, body0)
            x, _ = levenberg_marquardt(
                lin, state_vector(a_prev, mu_hat, trans_hat), lo, hi, max_iter=p.iterations, tol=1e-6
            )
            x = x[0]
            a_prev = x[:m]
            g = x[m + f :].reshape(f, 6)
            alpha[frames] = a_prev
            mu[frames] = x[m : m + f]
            trans[frames] = g[:, :3]
            rot[frames] = orthonormal(rotation_exp(g[:, 3:])[0] @ rot_hat)
    q = poses_of(s, alpha, mu, rot, trans)
    modelled = torch.arange(t_count, device=device) < swing
    if swing < t_count:
        assert hand_on is not None  # swing < t_count
        log.info("pca: the swing ends at frame %d; frames %d-%d by %s", swing - 1, swing, t_count - 1, p.after_swing)
        alpha[swing:], mu[swing:] = alpha[swing - 1], mu[swing - 1]
        rest = hand_on(later_frames(problem, swing), cfg, q[swing - 1], progress)
        q = torch.cat([q[:swing], rest.q.to(q)])
    with torch.no_grad():
        joints, rotations = sk.forward_kinematics(q, rotations=True)
        terms = final_terms(s, joints, rotations)
    fit = MotionFit(alpha.detach(), mu.detach(), keys.to(torch.int64), tuple(s.model.key_names), modelled)
    return Estimate(q=q.detach(), joints=joints, cost=cast(Tensor, sum(terms.values())), terms=terms, motion=fit)


def final_terms(s: Setup, joints: Tensor, rotations: Tensor) -> dict[str, Tensor]:
    """Per frame (T,), the observation terms of the final poses, weighted as in the windows (`window_objective`;
    the prediction terms belong to windows): world joints (T, J, 3) and rotations (T, J, 3, 3)."""
    p, cc = s.cfg.pca, s.cfg.costs
    cam = s.problem.observations.camera
    proj = cam.project(joints[:, s.tracked])
    ev = PoseEval(joints, joints, proj.pixels, proj.depth)  # q: unread
    terms = {
        "joints": p.joint_weight
        * Reprojection(s.observed, s.confidence, cc.sigma_px, cc.loss, cc.robust_scale, per_problem=True).energy(ev)
    }
    if s.rays is not None:
        assert s.ray_valid is not None  # set with rays
        sil = RaySilhouette(s.rays, s.ray_valid, cam.center, s.bones, s.silhouette_radii, sigma_m=p.silhouette_sigma_m)
        rho = robust_loss(p.silhouette_loss)(sil.residual_per_frame(joints).square(), p.silhouette_scale)
        terms["silhouette"] = 0.5 * p.silhouette_weight * rho.sum(-1)
    moved = correspondence_points(s, joints, rotations)
    if moved is not None:
        points, confidence = moved
        assert s.corr is not None  # set with the points
        at = cam.project(points)
        pairs = Reprojection(s.corr[1], confidence, cc.sigma_px, cc.loss, cc.robust_scale, per_problem=True)
        terms["correspondence"] = p.correspondence_weight * pairs.energy(PoseEval(points, points, at.pixels, at.depth))
    return terms
