"""The batch objective (`method: batch`; its energy in `ptrack.estimators.batch`): `Trajectory`, built from a
problem and the config by `trajectory_objective`, and `evaluate`, each term's per-frame energy with the per-frame
Gauss-Newton pieces. Shapes: B trajectories, T frames, D dofs, J joints, K keypoints."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import Any, NamedTuple

import torch
from torch import Tensor

from ptrack.body.limits import wrap_to_limits
from ptrack.body.pose_prior import held_sigma, pose_prior, smoothing_prior
from ptrack.costs import (
    JointKeyframe,
    JointLimits,
    Keyframe,
    PoseEval,
    PosePrior,
    Reprojection,
    Smoothness,
)
from ptrack.errors import InputError
from ptrack.estimators.batch.config import ROOT_VELOCITY
from ptrack.estimators.batch.smoothing import robust_smoothing, smoothing_band, smoothing_terms
from ptrack.optim.trajectory import (
    FrameRows,
    add_diagonal_rows,
    add_frame_rows,
    add_point_rows,
    band_matvec,
    joint_rows,
)
from ptrack.problem import Problem
from ptrack.threads import on_two_threads, parallel_halves

_MIN_PART = 32  # `evaluate` splits the frames in two halves for two threads from 2 * _MIN_PART frames


@dataclass(frozen=True, eq=False)
class Trajectory:
    """The MAP objective of one sequence of T frames (D dofs, J joints, K keypoints); see
    `ptrack.estimators.batch`. Built by `trajectory_objective`; its per-frame terms are the shared cost
    terms of `ptrack.costs`, linearised by `evaluate` through the banded trajectory assembler
    (`ptrack.optim.trajectory`).

    reprojection: `Reprojection` on observed (T, K, 2); lower, upper (D,) joint limits; limits_sigma: the
    violation (radians / metres) their barrier (eq. 2) prices at energy 1/2, costs.limits_sigma /
    sqrt(costs.limits_weight) (None: no barrier), whose term is `limits`;
    hard_limits: whether the solver also keeps every iterate inside [lower, upper] (`box`; then the
    barrier is 0 throughout); pose_prior: the CMU per-dof pose prior on every frame (`batch.pose_prior_weight`;
    None: none), whose term is `pose_prior`; smooth: ((n, a_n (D,)), ...) difference order and per-dof weight,
    whose terms under `smooth_loss` at `smooth_scale` are `smooth_terms`; band (T, W+1, D) the least-squares
    smoothing Hessian (band[t, k] = its (t, t-k) diagonal block's diagonal);
    keyframe: the angle keyframes, `Keyframe` (full or diagonal covariance, partial ones masked, angles
    compared on the circle) or None; joint_keyframe: the joint-position keyframes, `JointKeyframe` or
    None; angular (D,) bool; kf_frames (F,), kf_target (F, D) (0 where not given) and kf_weight (F, D) =
    1 / the marginal std of each given dof (0 where not given): the angle keyframes as `warp_to_keyframes`
    reads them.
    """

    problem: Problem
    reprojection: Reprojection
    lower: Tensor
    upper: Tensor
    limits_sigma: float | None
    smooth: tuple[tuple[int, Tensor], ...]
    band: Tensor
    keyframe: Keyframe | None
    joint_keyframe: JointKeyframe | None
    angular: Tensor
    kf_frames: Tensor
    kf_target: Tensor
    kf_weight: Tensor
    smooth_loss: str = "l2"
    smooth_scale: float = 1.0
    hard_limits: bool = False
    pose_prior: PosePrior | None = None

    @property
    def jk_frames(self) -> Tensor:
        """(G,) the frames of the joint-position keyframes."""
        jk = self.joint_keyframe
        return self.kf_frames.new_zeros(0) if jk is None else jk.times.to(self.kf_frames.device)

    @cached_property
    def smooth_terms(self) -> tuple[tuple[int, Smoothness], ...]:
        """`smooth` as the shared `Smoothness` terms under `smooth_loss` at `smooth_scale` (`smoothing_terms`)."""
        return smoothing_terms(self.smooth, self.smooth_loss, self.smooth_scale)

    @cached_property
    def limits(self) -> JointLimits | None:
        """The joint-limit barrier, `JointLimits` on [lower, upper] (read on each angle's nearest turn into
        the limits, `evaluate`), None without one."""
        if self.limits_sigma is None:
            return None
        sigma = torch.tensor(self.limits_sigma, dtype=self.lower.dtype, device=self.lower.device)  # not float32
        return JointLimits(self.lower, self.upper, sigma)

    @property
    def limits_scale(self) -> float:
        """sqrt(costs.limits_weight) / costs.limits_sigma: the barrier's residual per unit of violation."""
        return 0.0 if self.limits_sigma is None else 1.0 / self.limits_sigma

    def box(self) -> tuple[Tensor, Tensor]:
        """The solver's bounds (D,), (D,): the joint limits with `hard_limits`, else none (+-inf: the
        barrier alone keeps the trajectory near its limits)."""
        if self.hard_limits:
            return self.lower, self.upper
        return torch.full_like(self.lower, -math.inf), torch.full_like(self.upper, math.inf)


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
    # the root translations without a velocity prior (`batch.root_velocity`): their constant velocity is free
    unheld = {i for i, held in zip(sk.translation_dof.tolist(), ROOT_VELOCITY[bc.root_velocity]) if i >= 0 and not held}

    def weights(sigma_angle: float | None, sigma_m: float | None, n: int, per_dof: dict) -> Tensor | None:
        if sigma_angle is None and sigma_m is None:
            return None
        sigma = [(sigma_m if is_t else sigma_angle) for is_t in trans.tolist()]
        if n == 1:
            sigma = [None if i in unheld else s for i, s in enumerate(sigma)]
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
    band = smoothing_band(t_len, smoothing_terms(tuple(smooth)), like)  # l2's: the weights do not change it

    keyframe, kf_frames, kf_target, kf_weight = _angle_keyframes(problem, cfg, angular, dtype, device)
    joint_keyframe = _joint_keyframes(problem)
    jk_frames = kf_frames.new_zeros(0) if joint_keyframe is None else joint_keyframe.times
    for name, fr in (("keyframe", kf_frames), ("joint keyframe", jk_frames)):
        if fr.numel() and (int(fr.min()) < 0 or int(fr.max()) >= t_len):
            raise InputError(f"a {name} at frame {int(fr.max())} lies outside the {t_len} reconstructed frames")
    barrier = cc.limits_sigma / math.sqrt(cc.limits_weight) if cc.limits_weight > 0 else None
    prior = None
    if bc.pose_prior_weight > 0:  # as the trackers hold it (`kjs.model`): the dofs the table names, std >= 0.5 deg
        mean, std, known = pose_prior(sk, lower, upper, angular)
        prior = PosePrior(mean, held_sigma(std, known, math.radians(0.5)) / math.sqrt(bc.pose_prior_weight))
    return Trajectory(
        problem,
        reproj,
        lower,
        upper,
        barrier,
        tuple(smooth),
        band,
        keyframe,
        joint_keyframe,
        angular,
        kf_frames,
        kf_target,
        kf_weight,
        bc.smooth_loss,
        bc.smooth_scale,
        bc.hard_limits,
        prior,
    )


def _angle_keyframes(
    problem: Problem, cfg, angular: Tensor, dtype: torch.dtype, device: torch.device
) -> tuple[Keyframe | None, Tensor, Tensor, Tensor]:
    """The problem's angle keyframes as the shared `Keyframe` term: each given dof's std (`Keyframes.sigma`,
    else `keyframes.sigma_deg` / `sigma_m`) or each keyframe's full covariance, targets written in the limits'
    2 pi window, differences on the circle. -> (term or None, frames (F,), target (F, D), 1 / marginal std
    (F, D), 0 where not given)."""
    sk, kf, d = problem.skeleton, problem.keyframes, problem.skeleton.num_dofs
    if kf is None:
        empty = torch.zeros(0, d, dtype=dtype, device=device)
        return None, torch.zeros(0, dtype=torch.long, device=device), empty, empty
    trans = ~angular
    frames = kf.frames.to(device=device, dtype=torch.long)
    mask = (torch.ones_like(kf.q, dtype=torch.bool) if kf.mask is None else kf.mask).to(device)
    target = torch.where(mask, kf.q.to(device=device, dtype=dtype), 0.0)
    target = wrap_to_limits(target, *sk.limits(dtype=dtype, device=device), angular)
    if kf.covariance is not None:
        covariance = kf.covariance.to(device=device, dtype=dtype)
        std = covariance.diagonal(dim1=-2, dim2=-1).clamp(min=0).sqrt()
        term = Keyframe(frames, target, covariance, mask, diagonal=False, angular=angular)
    else:
        default = torch.where(trans, cfg.keyframes.sigma_m, math.radians(cfg.keyframes.sigma_deg)).to(dtype)
        std = default.expand(kf.q.shape) if kf.sigma is None else kf.sigma.to(device=device, dtype=dtype)
        variance = torch.where(mask, std, 1.0).square()  # a dof not given is not read
        term = Keyframe(frames, target, variance, mask, diagonal=True, angular=angular)
    weight = torch.where(mask, 1.0 / torch.where(mask, std, 1.0), 0.0)
    return term, frames, target, weight


def _joint_keyframes(problem: Problem) -> JointKeyframe | None:
    """The problem's joint-position keyframes as the shared `JointKeyframe` term (None without any)."""
    jk = problem.joint_keyframes
    if jk is None:
        return None
    sigma = torch.where(jk.mask, jk.sigma, 1.0)  # a joint not given is not read
    return JointKeyframe(jk.frames.long(), jk.joints, jk.mask, sigma, jk.covariance)


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
    r = rp.residual(ev).unflatten(-1, (t_len, 2 * k))  # (B, T, 2K): each frame's rows (keypoint, x|y)
    if with_jacobian:
        rp_w, rp_e = rp.weights_and_energy(r)  # IRLS weights (B, T, 2K), energy (B, T)
    else:
        rp_e = rp.energy_of(r)
    terms = {"reprojection": rp_e}
    # the barrier on each limited angle's nearest turn (an unboxed solve may carry it past +-pi; the
    # shift is constant, so the derivatives are q's)
    qw = wrap_to_limits(q, obj.lower, obj.upper, obj.angular)
    pose = PoseEval(qw, ev.joints, ev.pixels, ev.depth)  # the prior too on each angle's turn in the limits' window
    limits, prior = obj.limits, obj.pose_prior
    lim = None if limits is None else limits.residual(pose)
    prior_r = None if prior is None else prior.residual(pose)
    for name, term, res in (("limits", limits, lim), ("pose_prior", prior, prior_r)):
        terms[name] = q.new_zeros(b_len, t_len) if term is None or res is None else term.energy_of(res)
    # the smoothing's derivatives only where used: l2's gradient and band come from the fixed band
    robust = with_jacobian and obj.smooth_loss != "l2"
    terms["smooth"], smooth_grad, smooth_weights = robust_smoothing(obj, q, derivatives=robust)
    kf, jk = obj.keyframe, obj.joint_keyframe
    keyframes = q.new_zeros(b_len, t_len)
    kf_r = jk_r = None
    if kf is not None:
        kf_r = kf.frame_residual(q[:, obj.kf_frames])  # (B, F, D)
        keyframes.index_add_(1, obj.kf_frames, kf.energy_of(kf_r))
    if jk is not None:
        jk_frames = obj.jk_frames
        jk_r = jk.frame_residual(ev.joints[:, jk_frames])  # (B, G, 3J)
        keyframes.index_add_(1, jk_frames, jk.energy_of(jk_r))
    terms["keyframes"] = keyframes
    if not with_jacobian:
        return Evaluation(terms, None, None, smooth_weights)
    assert fk is not None  # with_jacobian

    # J_t^T W J_t of the reprojection: per keypoint, the residual's 2 x 3 derivative w.r.t. its joint's
    # position (`Reprojection.pixel_jacobian` on d pixels / d X) times sqrt(W), taken on to the pose by the
    # assembler (`add_point_rows`: the joint Jacobian's (joint, ancestor slot) pairs, never (K, 3, D) rows)
    root_w = rp_w.sqrt()  # (B, T, 2K)
    jp = rp.pixel_jacobian(dpix).unflatten(-2, (t_len, k, 2))  # (B, T, K, 2, 3)
    jp = jp * root_w.unflatten(-1, (k, 2))[..., None]
    rw = (r * root_w)[..., None]  # (B, T, 2K, 1)
    h = q.new_empty(b_len, t_len, _d, _d)
    g = q.new_empty(b_len, t_len, _d)

    def normal_equations(part: slice, fk_part: tuple[Tensor, Tensor]) -> None:
        add_point_rows(h[:, part], g[:, part], sk, q[:, part], kps.joints, jp[:, part], rw[:, part], fk_part)

    per_parts(normal_equations, fk)
    if limits is not None and lim is not None:
        g = add_diagonal_rows(h, g, lim, limits.diagonal_jacobian(pose))
    if prior is not None and prior_r is not None:
        g = add_diagonal_rows(h, g, prior_r, prior.diagonal_jacobian(pose))
    if kf is not None and kf_r is not None:
        add_frame_rows(h, g, FrameRows(obj.kf_frames, kf_r, kf.whiten.to(q)[None]))
    if jk is not None and jk_r is not None:
        # only the rows and columns of joints some joint keyframe gives (the others weigh 0)
        given = jk.joints_given
        cols = torch.tensor([3 * j + c for j in given for c in range(3)], device=q.device)
        w = jk.whiten.to(q)[:, cols][:, :, cols]  # (G, 3J', 3J')
        rows = joint_rows(sk, q[:, jk_frames], given, w.unflatten(-1, (len(given), 3))[None])
        add_frame_rows(h, g, FrameRows(jk_frames, jk_r[:, :, cols], rows))
    g = g + (smooth_grad if smooth_grad is not None else band_matvec(obj.band, q))
    return Evaluation(terms, h, g, smooth_weights)


def total_energy(obj: Trajectory, q: Tensor) -> Tensor:
    """The whole objective of trajectories q (N, T, D) -> (N,)."""
    terms = evaluate(obj, q, with_jacobian=False).terms
    return torch.stack(list(terms.values())).sum(0).sum(-1)
