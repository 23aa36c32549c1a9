"""`method: pca` — the golf-swing tracker of Urtasun, Fleet & Fua (2004), over a PCA motion model.

The motion model (`ptrack.motion.motion_model`) gives every joint angle but the root's as a function of the
PCA weights alpha (m,) and a normalised time mu in [0, 1] (eq. 2). The tracker fits it over sliding
windows of f frames (`pca.window`, slid by `pca.step`, default one frame); the state of a window is (eq. 5)

    S = [alpha_1 .. alpha_m, mu_1 .. mu_f, G_1 .. G_f]     (m + 7 f parameters)

with alpha shared by the window and, per frame, a normalised time and the root pose G_t (translation,
and a rotation vector w_t turning the frame's predicted root rotation: R_t = exp(w_t) R^_t; the root,
which the model leaves out, is not parametrised by the skeleton's Euler angles because CMU subject 64
stands near their singularity). Its energy (eq. 7) is

    w_joint  sum rho(|proj(joint) - observed|^2 / sigma_px^2)   tracked joints (knees, ankles, wrists, head)
    + w_fg   sum (ray-to-model distance / sigma_m)^2             foreground samples (section 4.1,
                                                                 `ptrack.costs.ray_silhouette`)
    + w_corr sum rho(|proj(x_i) - p2_i|^2 / sigma_px^2)         point correspondences (section 4.3,
                                                                 `ptrack.costs.correspondence`)
    + |(G - G^) / sigma_G|^2 + |(mu - mu^) / sigma_mu|^2 + |(alpha - alpha^) / (s sigma_alpha)|^2
    + w_prior |alpha / sigma_alpha|^2 + |(mu - mu_0) / sigma_timing|^2

where the predictions ^ are the previous window's trajectory continued at its last speed (the frames
the window shares with the previous one keep their previous values as prediction), alpha^ the previous
window's weights, sigma_alpha the spread of the training swings' weights (the model's `sigma`), and
mu_0 the start's timing (below; `pca.timing_sigma`, null drops it). Beyond the paper's eq. 7, which has
none of them, time never runs backwards (each window's times are bounded below by the time of the frame
that last left a window), the weights are boxed in `pca.alpha_bound` training stds, and the timing prior
is there: without it the tracker read a held-out downswing as the backswing reversed (docs/notes/golf-history.md).
Each window is one Levenberg-Marquardt solve of `ptrack.optim.solvers` with a closed-form Jacobian: the
decoder is linear in alpha and piecewise linear in mu, the joints' Jacobian is the geometric one
(`ptrack.optim.jacobians.joint_jacobian`), the projections' is the camera's, and the silhouette term's comes
from the envelope theorem. A frame's result is its value in the last window that holds it.

Correspondences (p1 in frame t-1, p2 in frame t; `Problem.correspondences`), where given: before each
window's solve, every pair whose frame t is in the window has p1 backprojected onto the capsule model of
the current estimate of frame t-1 (the window's starting state, or the final estimate for the frame
before the window; a line of sight that misses the model, or passes within `pca.correspondence_margin_m` of
any capsule's surface, drops the pair for this window) and attached to
the hit capsule's frame; x_i is that body-fixed point moved with frame t's pose in the window, whose
Jacobian is the geometric one of a point on the segment (`ptrack.optim.jacobians.point_jacobian`). The pair's
weight (1 for simulated ones) scales its squared residual. Cost: p1's rays are made once; per window one FK
pass of the frame before it and the window's starting state serves the backprojection and the solve's first
linearisation (`StartBody`); each linearisation has one FK pass for joints and points
(`ptrack.optim.jacobians.joint_and_point_jacobian`) and projects them together.

Start (section 5.1), with no 3D input: the four key postures are found in the 2D wrist track
(`ptrack.motion.key_postures.detect_key_postures_2d`, rules `motion.key_postures`), every frame's normalised
time is interpolated through them (`initial_times`), the PCA weights are zero, and the root is placed
from the first frame: the mean motion's pose at that time under `pca.init_yaws` headings, at the depth
its 2D size gives, each fitted rigidly (root only) to the first frame's tracked joints and silhouette;
the best fit is kept. `pca.iterations: 0` returns that start itself: the mean motion with the initial
timing, the root held where the first frame put it (the paper's fig. 8).

The model is read from `motion.model_file` (default ~/.cache/ptrack/motion/<config name>.npz); when no
file is there it is fitted from `motion.clips` (`ptrack fit-motion` does the same) and saved there.
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from ptrack.body.rotations import matrix_to_euler_np, skew
from ptrack.body.skeleton import Skeleton
from ptrack.costs import robust_loss, robust_loss_derivative
from ptrack.costs.ray_silhouette import RaySilhouette, mask_samples
from ptrack.errors import InputError
from ptrack.motion.key_postures import detect_key_postures_2d, initial_times
from ptrack.motion.motion_model import (
    MotionModel,
    clip_paths,
    decode,
    dof_index,
    fit_motion_model,
    load_motion_model,
    model_path,
    read_clips,
    save_motion_model,
)
from ptrack.observe.backprojection import Anchors, anchor_points, backproject_rays
from ptrack.observe.silhouette import capsule_radii
from ptrack.optim.jacobians import joint_and_point_jacobian, joint_jacobian
from ptrack.optim.solvers import Linearization, levenberg_marquardt
from ptrack.problem import Estimate, Problem

log = logging.getLogger(__name__)


def motion_model_for(cfg, skeleton: Skeleton) -> MotionModel:
    """The run's motion model: `motion.model_file` (or the cache path) if it exists, else fitted from
    `motion.clips` and saved there. InputError for a corrupt file, one of another skeleton, or no file
    and no clips."""
    path = model_path(cfg)
    if path.is_file():
        log.info("pca: motion model %s", path)
        return load_motion_model(path, skeleton)
    if not cfg.motion.clips:
        raise InputError(
            f"no motion model at {path} (config key 'motion.model_file') and no training clips to fit "
            f"one (config key 'motion.clips'); run `ptrack fit-motion` or set motion.clips"
        )
    clips = read_clips(clip_paths(cfg.motion.clips))
    model = fit_motion_model(clips, cfg.motion)
    save_motion_model(model, path)
    log.info("pca: fitted a motion model on %d clips, saved to %s", len(clips), path)
    return load_motion_model(path, skeleton)


# ---------------------------------------------------------------- set-up


@dataclass(frozen=True, eq=False)
class Setup:
    """Everything fixed over the sequence: model, index maps, observations of the tracked joints, rays of the
    foreground samples."""

    problem: Problem
    cfg: Any  # the run's config (ptrack.pipeline.config.RunConfig, not imported: estimators sit below it)
    model: MotionModel
    model_dofs: Tensor  # (Dm,) positions of the model's dofs in q
    root_dofs: Tensor  # (6,) positions of root tx, ty, tz and the root's three angles in q
    tracked: Tensor  # (K',) skeleton joints of the tracked keypoints
    observed: Tensor  # (T, K', 2) pixels
    weight: Tensor  # (T, K') sqrt(confidence) / sigma_px
    rays: Tensor | None  # (T, S, 3) unit world rays of the foreground samples
    ray_valid: Tensor | None  # (T, S) bool
    bones: tuple[tuple[int, int], ...]
    radii: Tensor  # (B,) capsule radii, metres
    alpha_sigma: Tensor  # (m,) the training swings' spread of each PCA weight
    root_order: str  # the root's Euler order for `matrix_to_euler_np` ("XYZ": x applied first)
    root_xyz: tuple[int, ...]  # (3,) coordinate axis (0 x, 1 y, 2 z) of each of root_dofs[3:]
    root_rest: Tensor  # (3, 3) the root's world rotation at zero angles (the ASF root orientation)
    # correspondences by second frame t (None: none, or pca.correspondence_weight 0): p1 (T, P, 2) pixels in
    # frame t-1, p2 (T, P, 2) in frame t, weight (T, P) sqrt(pair weight) / sigma_px (0: padding)
    corr: tuple[Tensor, Tensor, Tensor] | None = None
    corr_rays: Tensor | None = None  # (T, P, 3) unit world rays of p1 (set with corr)

    @property
    def m(self) -> int:
        return self.model.num_components


def _setup(problem: Problem, cfg) -> Setup:
    sk, obs, kps = problem.skeleton, problem.observations, problem.keypoints
    p = cfg.pca
    dtype, device = obs.keypoints.dtype, obs.keypoints.device
    model = motion_model_for(cfg, sk)
    model_dofs = dof_index(model, sk).to(device)
    root = [int(d) for d in (*sk.translation_dof, *sorted(sk.axis_dof[0].tolist())) if d >= 0]
    if len(root) != 6:
        raise InputError(
            f"method pca needs a root with 3 translation and 3 rotation dofs; {sk.name!r} has "
            f"{len(root)} (check model.freeze)"
        )
    other = sorted(set(range(sk.num_dofs)) - set(root) - set(model_dofs.tolist()))
    if other:
        log.warning(
            "pca: %d dofs are not in the motion model and held at zero (e.g. %s)", len(other), sk.dof_names[other[0]]
        )
    missing = [j for j in p.joints if j not in kps.names]
    if missing:
        raise InputError(
            f"config key 'pca.joints': unknown keypoint {missing[0]!r} (keypoints: {', '.join(kps.names)})"
        )
    kp = [kps.names.index(j) for j in p.joints]
    tracked = torch.as_tensor([kps.joints[k] for k in kp], dtype=torch.long, device=device)
    observed = obs.keypoints[:, kp].to(dtype)
    conf = obs.confidence[:, kp].to(dtype)
    observed = torch.where(conf[..., None] > 0, observed, 0.0)
    weight = conf.sqrt() / cfg.costs.sigma_px
    bones = tuple((int(a), int(b)) for a, b in sk.bones())
    bone_t = torch.as_tensor(bones, dtype=torch.long)
    radii = capsule_radii(
        [sk.joint_names[b] for _, b in bones], torch.as_tensor(sk.lengths[bone_t[:, 1]], dtype=dtype)
    ).to(device)
    rays = valid = None
    if p.silhouette_weight > 0:
        if obs.masks is None:
            log.warning(
                "pca: pca.silhouette_weight is %g but the observations have no silhouettes "
                "(observations.silhouettes); tracking the joints only",
                p.silhouette_weight,
            )
        else:
            pixels, valid = mask_samples(obs.masks, p.silhouette_step_px, p.silhouette_samples)
            _, rays = obs.camera.rays(pixels.to(dtype))
    # the root turns by R(a1) R(a2) R(a3) (slot axes a1..a3, a3 applied first): its Euler order and axes
    axes = sk.axes[0]
    coord = [int(abs(a).argmax()) for a in axes]
    if any(not (abs(a[c] - 1.0) < 1e-9) for a, c in zip(axes, coord)):
        raise InputError(
            f"method pca needs a root turning about the coordinate axes; {sk.name!r}'s root axes are {axes.tolist()}"
        )
    order = "".join("XYZ"[c] for c in reversed(coord))
    slot_of = {int(d): k for k, d in enumerate(sk.axis_dof[0].tolist()) if d >= 0}
    root_xyz = tuple(coord[slot_of[d]] for d in root[3:])
    with torch.no_grad():
        _, rest = sk.forward_kinematics(torch.zeros(sk.num_dofs, dtype=dtype, device=device), rotations=True)
    corr = corr_rays = None
    if problem.correspondences is not None and p.correspondence_weight > 0:
        p1, p2, w = problem.correspondences.to(device=device, dtype=dtype).by_frame(obs.num_frames)
        corr = (p1, p2, w.sqrt() / cfg.costs.sigma_px)
        _, corr_rays = obs.camera.rays(p1)  # backprojected once per window: made once here
    return Setup(
        problem,
        cfg,
        model,
        model_dofs,
        torch.as_tensor(root, device=device),
        tracked,
        observed,
        weight,
        rays,
        valid,
        bones,
        radii,
        model.sigma.to(dtype=dtype, device=device),
        order,
        root_xyz,
        rest[0],
        corr,
        corr_rays,
    )


# ---------------------------------------------------------------- poses of a state


def _decode_jacobian(model: MotionModel, alpha: Tensor, mu: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """`decode` and its derivatives in closed form: alpha (N, m), mu (N, f) -> q (N, f, Dm),
    dq/dalpha (N, f, Dm, m), dq/dmu (N, f, Dm). The decoder interpolates linearly between its N samples,
    so dq/dalpha is the interpolated components and dq/dmu the slope of the sample interval (0 outside
    [0, 1], where decode clamps); tests/test_pca.py checks both against `decode`."""
    n = model.num_samples
    mean, comp = model.mean.to(alpha), model.components.to(alpha)  # (N_s, Dm), (m, N_s, Dm)
    sm = mu.clamp(0.0, 1.0) * (n - 1)
    i0 = sm.floor().clamp(0, n - 2).long()
    w = (sm - i0.to(sm))[..., None]
    ca, cb = comp[:, i0].movedim(0, -1), comp[:, i0 + 1].movedim(0, -1)  # (N, f, Dm, m)
    dq_da = ca + w[..., None] * (cb - ca)
    ma, mb = mean[i0], mean[i0 + 1]
    q = ma + w * (mb - ma) + (dq_da @ alpha[:, None, :, None])[..., 0]
    inside = ((mu >= 0) & (mu <= 1)).to(alpha)[..., None]
    dq_dmu = (n - 1) * ((mb - ma) + ((cb - ca) @ alpha[:, None, :, None])[..., 0]) * inside
    return q, dq_da, dq_dmu


def _body(s: Setup, alpha: Tensor, mu: Tensor) -> tuple[Tensor, Tensor]:
    """Body poses (the root's dofs at zero) and their derivative: alpha (N, m), mu (N, f) -> q (N, f, D),
    dq/d(alpha, mu) (N, f, D, m + f) (each frame's q depends on its own mu only)."""
    n, f = mu.shape
    m = alpha.shape[-1]
    d = s.problem.skeleton.num_dofs
    qm, da, dmu = _decode_jacobian(s.model, alpha, mu)
    q = alpha.new_zeros(n, f, d)
    q[..., s.model_dofs] = qm
    dq = alpha.new_zeros(n, f, d, m + f)
    dq[..., s.model_dofs, :m] = da
    fr = torch.arange(f, device=mu.device)
    dq[:, fr, :, m + fr] = dq.new_zeros(n, f, d).index_copy_(-1, s.model_dofs, dmu).transpose(0, 1)
    return q, dq


def _exp(w: Tensor) -> tuple[Tensor, Tensor]:
    """Rotation vectors (..., 3) -> rotation matrices exp([w]x) (..., 3, 3) and the left Jacobians
    J_l(w) (..., 3, 3), with d/dw (exp(w) p) = -[exp(w) p]x J_l(w)."""
    t2 = w.square().sum(-1)[..., None, None]
    small = t2 < 1e-8
    t2s = torch.where(small, torch.ones_like(t2), t2)
    t = t2s.sqrt()
    a = torch.where(small, 1 - t2 / 6, torch.sin(t) / t)
    b = torch.where(small, 0.5 - t2 / 24, (1 - torch.cos(t)) / t2s)
    c = torch.where(small, 1.0 / 6 - t2 / 120, (t - torch.sin(t)) / (t2s * t))
    k = skew(w)
    kk = k @ k
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + a * k + b * kk, eye + b * k + c * kk


def _orthonormal(r: Tensor) -> Tensor:
    """The nearest rotations (..., 3, 3) to near-rotations r: products of many rotations drift, and the
    constant-speed prediction R_{t-1} R_{t-2}^T R_{t-1} triples any drift each frame."""
    u, _, vt = torch.linalg.svd(r)
    return u @ vt


def _world(s: Setup, x_body: Tensor, dx_body: Tensor, rot: Tensor, trans: Tensor) -> tuple[Tensor, Tensor]:
    """Body joints (the root at its rest position r0, unrotated) turned by rot (..., 3, 3) about r0 and moved
    by trans (..., 3): x_body (..., J, 3), dx_body (..., J, 3, P) -> world joints and their derivative."""
    r0 = x_body[..., :1, :]
    x = trans[..., None, :] + r0 + (x_body - r0) @ rot.mT
    return x, rot[..., None, :, :] @ dx_body


def root_angles(s: Setup, rot: Tensor) -> Tensor:
    """The root's Euler angles (..., 3), in the order of `s.root_dofs[3:]`, of world rotations (..., 3, 3)."""
    ang = torch.as_tensor(matrix_to_euler_np(rot.detach().cpu().double().numpy(), s.root_order))  # (..., 3) x, y, z
    return ang[..., list(s.root_xyz)].to(rot)


def _rotation_of(s: Setup, angles: Tensor) -> Tensor:
    """World rotations (..., 3, 3) of the root's Euler angles (..., 3) (inverse of `root_angles`)."""
    q = angles.new_zeros(*angles.shape[:-1], s.problem.skeleton.num_dofs)
    q[..., s.root_dofs[3:]] = angles
    _, rot = s.problem.skeleton.forward_kinematics(q, rotations=True)
    return rot[..., 0, :, :] @ s.root_rest.to(angles).mT


def poses_of(s: Setup, alpha: Tensor, mu: Tensor, rot: Tensor, trans: Tensor) -> Tensor:
    """Full poses q (..., D) of PCA weights alpha (..., m), times mu (...), root rotations (..., 3, 3) and
    translations (..., 3)."""
    q = trans.new_zeros(*mu.shape, s.problem.skeleton.num_dofs)
    q[..., s.model_dofs] = decode(s.model, alpha, mu)
    q[..., s.root_dofs[:3]] = trans
    q[..., s.root_dofs[3:]] = root_angles(s, rot)
    return q


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


@dataclass(frozen=True)
class WindowPairs:
    """The correspondences of a window of f frames, P per frame: body-fixed points (anchors (f, P)) to be
    seen at target (f, P, 2) pixels in their frame, with weight (f, P) (sqrt(pair weight) / sigma_px, 0 for
    padding and pairs whose p1 missed the model)."""

    anchors: Anchors
    target: Tensor
    weight: Tensor


@dataclass(frozen=True)
class StartBody:
    """A window's body poses at its starting state, computed before its solve for the backprojection and kept
    for the solve's first linearisation (the LM starts there): key (1, m + f) the state's alpha and mu; q
    (1, f, D) and dq (1, f, D, m + f) of `_body`; joints (1, f, J, 3) and world rotations (1, f, J, 3, 3) of
    the skeleton's FK of q."""

    key: Tensor
    q: Tensor
    dq: Tensor
    joints: Tensor
    rotations: Tensor


def _window_linearization(
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
    root rotations; a frame's rotation is exp(w) ref. pairs: the window's correspondences (`_window_pairs`).
    start: body poses already computed (`_start_pairs`), used for a state whose alpha and mu equal its key."""
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
            q, dq = _body(s, alpha, mu)
        if pairs is None:
            xb, dxb_dq = joint_jacobian(sk, q)  # (N, f, J, 3), (N, f, J, 3, D)
        else:  # the pairs' body-fixed points ride along as extra "joints" J .. J + P - 1 (one FK for both)
            xb, dxb_dq, xp, dxp_dq = joint_and_point_jacobian(sk, q, pairs.anchors.joint, pairs.anchors.local, fk)
            xb, dxb_dq = torch.cat([xb, xp], -2), torch.cat([dxb_dq, dxp_dq], -3)
        dxb = dxb_dq @ dq[:, :, None]  # (N, f, J (+ P), 3, m + f)
        r_w, jl = _exp(w)
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


def _silhouette(s: Setup, frames: Tensor) -> RaySilhouette | None:
    if s.rays is None:
        return None
    assert s.ray_valid is not None  # set with rays
    cam = s.problem.observations.camera
    return RaySilhouette(
        s.rays[frames], s.ray_valid[frames], cam.center, s.bones, s.radii, sigma_m=s.cfg.pca.silhouette_sigma_m
    )


def _world_frames(xb: Tensor, rb: Tensor, rot: Tensor, trans: Tensor) -> tuple[Tensor, Tensor]:
    """World joints (k, J, 3) and joint rotations (k, J, 3, 3) of k frames' body FK (joints xb (k, J, 3),
    rotations rb (k, J, 3, 3)) turned by root rotations rot (k, 3, 3) about the root and moved by trans (k, 3),
    as in `_window_linearization`."""
    r0 = xb[:, :1]
    return trans[:, None] + r0 + (xb - r0) @ rot.mT, rot[:, None] @ rb


def _start_pairs(
    s: Setup, frames: Tensor, a_start: Tensor, mu_start: Tensor, rot_start: Tensor, trans_start: Tensor, before
) -> tuple[WindowPairs | None, StartBody]:
    """The window's correspondences (`_window_pairs`) backprojected on the frames before its frames: the final
    estimate of the frame before the window, then the window's frames but its last at the window's starting
    state (alpha a_start (m,), mu_start (f,), root rotations (f, 3, 3) and translations (f, 3)); and that
    state's body poses (`StartBody`), from one FK pass with the frame before. before: the estimate of the frame
    before the window (alpha (m,), mu (), rotation (3, 3), translation (3,)), None for a window at frame 0."""
    f = frames.shape[0]
    q, dq = _body(s, a_start[None], mu_start[None])  # (1, f, D), (1, f, D, m + f)
    body, rot, trans = q[0], rot_start, trans_start
    if before is not None:
        a_b, mu_b, rot_b, trans_b = before
        q_b, _ = _body(s, a_b[None], mu_b.reshape(1, 1))
        body, rot, trans = torch.cat([q_b[0], body]), torch.cat([rot_b[None], rot]), torch.cat([trans_b[None], trans])
    xb, rb = s.problem.skeleton.forward_kinematics(body, rotations=True)  # (f (+ 1), J, 3), (f (+ 1), J, 3, 3)
    start = StartBody(torch.cat([a_start, mu_start])[None], q, dq, xb[-f:][None], rb[-f:][None])
    # frame 0 has no pairs: any pose stands before it
    prev = (
        torch.arange(f, device=frames.device)
        if before is not None
        else (torch.arange(f, device=frames.device) - 1).clamp_min(0)
    )
    x_prev, r_prev = _world_frames(xb[prev], rb[prev], rot[prev], trans[prev])
    return _window_pairs(s, frames, x_prev, r_prev), start


def _backproject(s: Setup, rays: Tensor, joints: Tensor, rotations: Tensor) -> Anchors:
    """Anchors (k, P) of the pixels p1 whose rays (k, P, 3) are given (`Setup.corr_rays`) on the capsule model of
    poses joints (k, J, 3), rotations (k, J, 3, 3)."""
    bones = torch.as_tensor(s.bones, dtype=torch.long, device=joints.device)
    cam = s.problem.observations.camera
    return backproject_rays(cam.center, rays, joints[:, None], rotations[:, None], bones, s.radii)


def _window_pairs(s: Setup, frames: Tensor, joints_prev: Tensor, rotations_prev: Tensor) -> WindowPairs | None:
    """The correspondences whose second frame is in the window `frames` (f,), backprojected on the poses of the
    frames before them: joints_prev (f, J, 3), rotations_prev (f, J, 3, 3) (anything for frame 0, which has no
    pairs). None when the run has no correspondences."""
    if s.corr is None or s.corr_rays is None:
        return None
    _, p2, w = (x[frames] for x in s.corr)
    anchors = _backproject(s, s.corr_rays[frames], joints_prev, rotations_prev)
    keep = anchors.valid & (anchors.clearance >= s.cfg.pca.correspondence_margin_m)
    return WindowPairs(anchors, p2, torch.where(keep, w, torch.zeros_like(w)))


def correspondence_residuals(s: Setup, joints: Tensor, rotations: Tensor) -> Tensor | None:
    """Per frame t and pair, the correspondence residuals (T, P, 2) (whitened pixels) of a trajectory's world
    joints (T, J, 3) and rotations (T, J, 3, 3): p1 backprojected at frame t-1, moved with frame t. Frame 0
    and pairs that miss the model are 0. None without correspondences."""
    if s.corr is None or s.corr_rays is None:
        return None
    _, p2, w = s.corr
    prev = (torch.arange(joints.shape[0], device=joints.device) - 1).clamp_min(0)
    anchors = _backproject(s, s.corr_rays, joints[prev], rotations[prev])
    x = anchor_points(anchors, joints[:, None], rotations[:, None])
    r = (s.problem.observations.camera.project(x).pixels - p2) * w[..., None]
    return torch.where((anchors.valid & (w > 0))[..., None], r, torch.zeros_like(r))


def _state(alpha: Tensor, mu: Tensor, trans: Tensor) -> Tensor:
    """(m,), (f,), (f, 3) -> x (1, m + 7 f): rotation vectors 0 (the window starts at its reference rotations)."""
    return torch.cat([alpha, mu, torch.cat([trans, torch.zeros_like(trans)], -1).flatten()])[None]


def _bounds(
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


# ---------------------------------------------------------------- start (section 5.1)


def initial_timing(s: Setup) -> tuple[Tensor, Tensor]:
    """Key-posture frames (P,) from the 2D wrists and every frame's normalised time (T,)."""
    obs, kps = s.problem.observations, s.problem.keypoints
    wrists = [kps.names.index(k) for k in ("l_wrist", "r_wrist") if k in kps.names]
    if not wrists:
        raise InputError(
            "method pca finds the key postures from the 2D wrists: the keypoint set needs "
            "l_wrist or r_wrist (config key 'model.keypoints')"
        )
    fps = 1.0 / obs.frame_interval
    rules = dataclasses.replace(s.cfg.motion, smooth_s=s.cfg.pca.key_smooth_s)
    keys = detect_key_postures_2d(
        obs.keypoints[:, wrists].detach().cpu(), fps, rules, valid=(obs.confidence[:, wrists] > 0).cpu()
    )
    mu = initial_times(keys, s.model.key_times, obs.num_frames)
    return keys, mu.to(dtype=obs.keypoints.dtype, device=obs.keypoints.device)


def place_root(s: Setup, mu0: Tensor) -> tuple[Tensor, Tensor]:
    """Root rotation (3, 3) and translation (3,) of the mean motion at normalised time mu0 that best explain
    the first frame showing two tracked joints: `pca.init_yaws` headings about world Y, each at the depth
    its 2D size gives, fitted rigidly to the tracked joints and the silhouette; the lowest energy wins."""
    obs = s.problem.observations
    sk, cam = s.problem.skeleton, obs.camera
    dtype, device = obs.keypoints.dtype, obs.keypoints.device
    m, y = s.m, s.cfg.pca.init_yaws
    seen_frames = (s.weight > 0).sum(-1) >= 2
    if not bool(seen_frames.any()):
        raise InputError("method pca: no frame shows two of the tracked joints (pca.joints)")
    frame = int(torch.nonzero(seen_frames)[0, 0])
    seen = s.weight[frame] > 0
    alpha = torch.zeros(m, dtype=dtype, device=device)
    yaw = torch.arange(y, dtype=dtype, device=device) * (2 * math.pi / y)
    ref, _ = _exp(torch.stack([torch.zeros_like(yaw), yaw, torch.zeros_like(yaw)], -1))  # (Y, 3, 3)
    with torch.no_grad():
        q, _ = _body(s, alpha[None], mu0.reshape(1, 1))
        xb = sk.forward_kinematics(q)[0, 0]  # (J, 3)
        r0 = xb[:1]
        joints = ((xb - r0) @ ref.mT + r0)[:, s.tracked][:, seen]  # (Y, k, 3), root translation 0
        pix = s.observed[frame][seen]
        size3 = (joints - joints.mean(1, keepdim=True)).norm(dim=-1).mean(-1)  # (Y,)
        size2 = (pix - pix.mean(0)).norm(dim=-1).mean().clamp(min=1.0)
        depth = cam.K[0, 0] * size3 / size2
        origin, direction = cam.rays(pix.mean(0))
        target = origin + direction * (depth / (direction @ cam.R[2]))[:, None]
        trans = target - joints.mean(1)  # (Y, 3)
    x0 = torch.cat([_state(alpha, mu0.reshape(1), t[None]) for t in trans])
    lo, hi = _bounds(s, 1, x0, alpha=alpha, mu=mu0.reshape(1))
    frames = torch.tensor([frame], device=device)
    lin = _window_linearization(
        s, frames, ref[:, None], Prediction(None, None, None, rotation=False), _silhouette(s, frames)
    )
    x, info = levenberg_marquardt(lin, x0, lo, hi, max_iter=30, tol=1e-8)
    best = int(torch.argmin(torch.where(torch.isfinite(info.cost), info.cost, math.inf)))
    rot = _exp(x[best, m + 4 : m + 7])[0] @ ref[best]
    return rot, x[best, m + 1 : m + 4]


# ---------------------------------------------------------------- tracking


def estimate_pca(
    problem: Problem, cfg, generator: torch.Generator, progress: Callable[[Iterable], Iterable] = lambda x: x
) -> Estimate:
    """Track the whole sequence with the PCA motion model (see the module docstring). Deterministic."""
    s = _setup(problem, cfg)
    p = cfg.pca
    obs = problem.observations
    sk = problem.skeleton
    dtype, device = obs.keypoints.dtype, obs.keypoints.device
    t_count, m = obs.num_frames, s.m
    f = min(p.window, t_count)
    keys, mu_init = initial_timing(s)
    log.info("pca: key postures at frames %s", keys.tolist())
    rot0, trans0 = place_root(s, mu_init[0])
    alpha = torch.zeros(t_count, m, dtype=dtype, device=device)  # per frame: the weights of its last window
    mu = mu_init.clone()
    rot = rot0.expand(t_count, 3, 3).clone()
    trans = trans0.expand(t_count, 3).clone()
    if p.iterations > 0:
        a_prev = torch.zeros(m, dtype=dtype, device=device)
        lo, hi = _bounds(s, f, mu)
        step = min(p.step, f)
        starts = list(range(0, t_count - f + 1, step))
        if starts[-1] != t_count - f:
            starts.append(t_count - f)
        known = 0  # frames [0, known) have been in a window
        for start in progress(starts):
            frames = torch.arange(start, start + f, device=device)
            for t in range(max(known, 1), start + f):  # frames new to this window: the trajectory continued
                if t >= 2:  # at the speed of the two frames before (each new frame from the ones predicted before it)
                    mu[t] = (2 * mu[t - 1] - mu[t - 2]).clamp(0, 1)
                    trans[t] = 2 * trans[t - 1] - trans[t - 2]
                    rot[t] = _orthonormal(rot[t - 1] @ rot[t - 2].mT @ rot[t - 1])
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
                pairs, body0 = _start_pairs(s, frames, a_prev, mu_hat, rot_hat, trans_hat, before)
            lin = _window_linearization(s, frames, rot_hat[None], pred, _silhouette(s, frames), pairs, body0)
            x, _ = levenberg_marquardt(lin, _state(a_prev, mu_hat, trans_hat), lo, hi, max_iter=p.iterations, tol=1e-6)
            x = x[0]
            a_prev = x[:m]
            g = x[m + f :].reshape(f, 6)
            alpha[frames] = a_prev
            mu[frames] = x[m : m + f]
            trans[frames] = g[:, :3]
            rot[frames] = _orthonormal(_exp(g[:, 3:])[0] @ rot_hat)
    q = poses_of(s, alpha, mu, rot, trans)
    with torch.no_grad():
        joints = sk.forward_kinematics(q)
        # per frame, the observation terms of the final poses (the prediction terms belong to windows)
        proj = obs.camera.project(joints[:, s.tracked])
        r = (proj.pixels - s.observed) * s.weight[..., None]
        terms = {
            "joints": 0.5
            * p.joint_weight
            * robust_loss(cfg.costs.loss)(r.square().sum(-1), cfg.costs.robust_scale).sum(-1)
        }
        if s.rays is not None:
            assert s.ray_valid is not None  # set with rays
            sil = RaySilhouette(s.rays, s.ray_valid, obs.camera.center, s.bones, s.radii, sigma_m=p.silhouette_sigma_m)
            terms["silhouette"] = 0.5 * p.silhouette_weight * sil.residual_per_frame(joints).square().sum(-1)
        if s.corr is not None:
            _, rotations = sk.forward_kinematics(q, rotations=True)
            r_c = correspondence_residuals(s, joints, rotations)
            assert r_c is not None  # s.corr is set
            rho = robust_loss(cfg.costs.loss)(r_c.square().sum(-1), cfg.costs.robust_scale)
            terms["correspondence"] = 0.5 * p.correspondence_weight * rho.sum(-1)
    return Estimate(q=q.detach(), joints=joints, cost=sum(terms.values()), terms=terms)
