"""Least-squares and robust cost terms on poses and trajectories: reprojection, joint limits, keyframes, pose
priors (the smoothing prior is `ptrack.costs.smoothness`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import torch
from torch import Tensor

from ptrack.body.limits import wrapped_difference
from ptrack.checks import as_float_tensor
from ptrack.costs.base import (
    LeastSquaresMixin,
    PoseEval,
    PoseJacobian,
    RobustMixin,
    check_frame_count,
    check_index,
    check_mask,
    check_positive,
    check_times,
    robust_loss,
    shape_of,
)
from ptrack.errors import InputError

# ---------------------------------------------------------------------------------------------
# Terms.


@dataclass(frozen=True, eq=False)
class Reprojection(RobustMixin):
    """2D keypoint reprojection error, robust per keypoint.

    observed (*O, K, 2) pixels, confidence (*O, K) >= 0 (0 = missing; NaN observations allowed
    there); *O is () for one frame or (T,) for a trajectory. Reads ev.pixels (..., *O, K, 2).
    residual (..., |O|*K*2): r_k = sqrt(confidence_k) (pixels_k - observed_k) / sigma_px, the x, y
    of keypoint k adjacent; rho(s, scale) is applied to s_k = |r_k|^2 (both coordinates together),
    so `scale` is in units of sigma_px. With `per_problem` the first axis of observed (N, K, 2) and
    confidence (N, K) runs over N independent problems, each pose with its own frame's keypoints: ev.pixels
    (N, K, 2) -> residual (N, K*2), not one problem's (N*K*2) residual over a trajectory. `keypoints` (K,) long:
    the entries of ev.pixels' keypoint axis the term reads (ev.pixels (..., *O, K_all, 2), e.g. the tracked
    joints and other projected points side by side); None: all of them (K_all = K).
    """

    observed: Tensor
    confidence: Tensor
    sigma_px: float = 1.0
    loss: str = "cauchy"
    scale: float = 1.0
    per_problem: bool = False
    keypoints: Tensor | None = None
    _group: ClassVar[int] = 2
    _target: Tensor = field(init=False, repr=False)
    _sqrt_conf: Tensor = field(init=False, repr=False)

    def __post_init__(self) -> None:
        obs, conf = as_float_tensor(self.observed, "observed"), as_float_tensor(self.confidence, "confidence")
        if obs.ndim < 2 or obs.shape[-1] != 2 or obs.shape[-2] == 0:
            raise InputError(f"Reprojection.observed must have shape (*O, K, 2) with K >= 1, got {shape_of(obs)}")
        if conf.shape != obs.shape[:-1]:
            raise InputError(
                f"Reprojection.confidence must have shape {shape_of(obs)[:-1]} to "
                f"match observed {shape_of(obs)}, got {shape_of(conf)}"
            )
        if self.per_problem and obs.ndim != 3:
            raise InputError(f"Reprojection.observed must have shape (N, K, 2) with per_problem, got {shape_of(obs)}")
        if not (torch.isfinite(conf).all() and (conf >= 0).all()):
            raise InputError("Reprojection.confidence must be finite and >= 0")
        valid = conf > 0
        bad = valid & ~torch.isfinite(obs).all(-1)
        if bad.any():
            raise InputError(
                f"Reprojection.observed has NaN/inf at keypoints with confidence > 0, "
                f"indices {bad.nonzero().tolist()[:5]}"
            )
        check_positive("Reprojection.sigma_px", self.sigma_px)
        check_positive("Reprojection.scale", self.scale)
        robust_loss(self.loss)
        if self.keypoints is not None:
            k = check_index("Reprojection.keypoints", self.keypoints, obs.shape[-2], f"observed {shape_of(obs)}")
            object.__setattr__(self, "keypoints", k)
        object.__setattr__(self, "observed", obs)
        object.__setattr__(self, "confidence", conf)
        object.__setattr__(self, "_target", torch.where(valid[..., None], obs, 0.0))
        object.__setattr__(self, "_sqrt_conf", conf.sqrt() / self.sigma_px)

    def _pixels(self, ev: PoseEval) -> Tensor:
        """ev.pixels of the keypoints the term reads, (..., *O, K, 2); InputError unless they end in observed's
        shape."""
        p, n = ev.pixels, self.observed.ndim
        if self.keypoints is not None:
            p = p.index_select(-2, self.keypoints.to(p.device))
        if p.ndim < n or p.shape[-n:] != self.observed.shape:
            raise InputError(
                f"{type(self).__name__}: ev.pixels {shape_of(p)} must end in observed's shape {shape_of(self.observed)}"
            )
        return p

    def _whitened(self, p: Tensor, order: Tensor | None = None) -> Tensor:
        """`_pixels`' output (..., *O, K, 2) -> its whitened residuals, same shape; with `order` (K,) against the
        detections (and their confidences) read in that order, keypoint k against detection order[k]."""
        target, sc = self._target.to(p), self._sqrt_conf.to(p)
        if order is not None:
            target, sc = target.index_select(-2, order), sc.index_select(-1, order)
        return (p - target) * sc[..., None]

    def _read_rows(self, d_pixels: Tensor) -> Tensor:
        """Derivatives of ev.pixels (..., K_ev, 2, V) -> those of the keypoints the term reads (..., K, 2, V)."""
        return d_pixels if self.keypoints is None else d_pixels.index_select(-3, self.keypoints.to(d_pixels.device))

    def residual(self, ev: PoseEval) -> Tensor:
        """ev.pixels (..., *O, K, 2) -> (..., |O|*K*2) whitened pixel residuals."""
        return self._whitened(self._pixels(ev)).flatten(-(self.observed.ndim - self.per_problem))

    def jacobian(self, ev: PoseEval, jac: PoseJacobian) -> Tensor:
        """jac.pixels (..., *O, K, 2, D) -> (..., |O|*K*2, D), rows as in `residual` (`pixel_jacobian`)."""
        return self.pixel_jacobian(jac.pixels)

    def pixel_jacobian(self, d_pixels: Tensor) -> Tensor:
        """The residual's derivatives from the pixels': d_pixels (..., *O, K, 2, V) (K as ev.pixels' keypoint
        axis) -> (..., |O|*K*2, V), rows as in `residual`. The residual is the pixels times sqrt(confidence)
        / sigma_px, so this is the chain rule's first factor for any V variables: the pose (V = D, d pixels / d q:
        `jacobian`), or each keypoint's own 3D position (V = 3, d pixels / d X from `Camera.project_jacobian`:
        the blocks of a block-diagonal Jacobian, which `ptrack.optim.trajectory.add_point_rows` takes on to the
        pose without forming (K, 3, D) rows)."""
        n = self.observed.ndim - self.per_problem
        jp = self._read_rows(d_pixels)
        j = jp * self._sqrt_conf.to(jp)[..., None, None]
        return j.flatten(-n - 1, -2)


@dataclass(frozen=True, eq=False)
class SwapReprojection(Reprojection):
    """`Reprojection` of one frame per problem that also reads the detections with every left and right label
    exchanged, at a price: a 2D detector sometimes takes a person for one facing the other way and labels the
    whole body mirrored for a stretch of frames (MediaPipe on the Pose2Sim trial's cam02, frames 41-73). A body
    that keeps its heading then fits the exchanged labels, at `swap_cost`; one that turns round to follow the
    labels pays the dynamics instead. A pose's energy is min(E(labels), E(exchanged labels) + swap_cost), E the
    robust reprojection energy of `Reprojection`.

    partners (K,) long: each keypoint's left/right partner (itself when it has none), as
    `ptrack.body.keypoints.KeypointSet.swap_pairs` give them. swap_cost > 0, in energy units (the energy is
    0.5 sum rho(s_k)). Residual (..., K*2 + 2): the chosen reading's whitened pixel residuals (rows as in
    `Reprojection`), then a marker pair (sqrt(2 swap_cost), 0) where the exchanged reading was chosen and (0, 0)
    elsewhere, outside the robust kernel (its energy is exactly swap_cost; its Jacobian rows are zero).
    One frame per problem only: observed (K, 2) for every pose, or (N, K, 2) with `per_problem`."""

    partners: Tensor | None = None
    swap_cost: float = 1.0

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.observed.ndim - self.per_problem != 2:
            raise InputError(
                f"SwapReprojection reads one frame per problem: observed (K, 2), or (N, K, 2) with per_problem, "
                f"got {shape_of(self.observed)}"
            )
        k = self.observed.shape[-2]
        p = check_index("SwapReprojection.partners", self.partners, k, f"observed {shape_of(self.observed)}")
        if not bool((p >= 0).all() and (p < k).all() and (p[p] == torch.arange(k)).all()):
            raise InputError("SwapReprojection.partners must pair keypoints with each other (an involution)")
        check_positive("SwapReprojection.swap_cost", self.swap_cost)
        object.__setattr__(self, "partners", p)

    def _partners(self, device: torch.device) -> Tensor:
        assert self.partners is not None  # checked in __post_init__
        return self.partners.to(device)

    def _readings(self, p: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """pixels (..., K, 2) of the read keypoints -> residuals as read (..., K*2) and with the labels
        exchanged (..., K*2), and which reading each problem takes (...,) bool (True: exchanged)."""
        r_a = self._whitened(p).flatten(-2)
        r_b = self._whitened(p, self._partners(p.device)).flatten(-2)
        swapped = super().energy_of(r_b) + self.swap_cost < super().energy_of(r_a)
        return r_a, r_b, swapped

    def _marked(self, r_a: Tensor, r_b: Tensor, swapped: Tensor) -> Tensor:
        r = torch.where(swapped[..., None], r_b, r_a)
        mark = torch.zeros(*r.shape[:-1], 2, dtype=r.dtype, device=r.device)
        mark[..., 0] = swapped.to(r.dtype) * math.sqrt(2.0 * self.swap_cost)
        return torch.cat([r, mark], -1)

    def residual(self, ev: PoseEval) -> Tensor:
        """ev.pixels (..., K, 2) -> (..., K*2 + 2) (the class docstring)."""
        return self._marked(*self._readings(self._pixels(ev)))

    def residual_jacobian(self, ev: PoseEval, jac: PoseJacobian) -> tuple[Tensor, Tensor]:
        """`residual` and its Jacobian (..., K*2 + 2, D): each problem's rows those of the reading it takes."""
        r_a, r_b, swapped = self._readings(self._pixels(ev))
        jp = self._read_rows(jac.pixels)
        sc = self._sqrt_conf.to(jp)
        sc = torch.where(swapped[..., None], sc.index_select(-1, self._partners(jp.device)), sc)
        j = (jp * sc[..., None, None]).flatten(-3, -2)
        j = torch.cat([j, j.new_zeros(*j.shape[:-2], 2, j.shape[-1])], -2)
        return self._marked(r_a, r_b, swapped), j

    def jacobian(self, ev: PoseEval, jac: PoseJacobian) -> Tensor:
        return self.residual_jacobian(ev, jac)[1]

    def pixel_jacobian(self, d_pixels: Tensor) -> Tensor:
        raise NotImplementedError("SwapReprojection's rows depend on the pose: use residual_jacobian")

    def energy_of(self, r: Tensor) -> Tensor:
        """The robust energy of the pixel residuals plus the marker's swap_cost (...,)."""
        return super().energy_of(r[..., :-2]) + 0.5 * r[..., -2:].square().sum(-1)

    def weights_and_energy(self, r: Tensor) -> tuple[Tensor, Tensor]:
        w, e = super().weights_and_energy(r[..., :-2])
        return torch.cat([w, torch.ones_like(r[..., -2:])], -1), e + 0.5 * r[..., -2:].square().sum(-1)

    def robust_weights(self, ev: PoseEval) -> Tensor:
        return self.weights_and_energy(self.residual(ev))[0]

    def swapped(self, ev: PoseEval) -> Tensor:
        """Which reading each problem takes (...,) bool: True where the exchanged labels fit at their cost."""
        return self._readings(self._pixels(ev))[2]


@dataclass(frozen=True, eq=False)
class JointLimits(LeastSquaresMixin):
    """Two-sided joint-limit barrier (DiFranco et al. eq. 2, both sides), on ev.q.

    lower, upper (D,) (+-inf = no bound); sigma: float or (D,), the violation (radians/metres)
    costing energy 0.5. residual = [min(0, q - lower) + max(0, q - upper)] / sigma.
    time_axis=False: q (..., D) -> residual (..., D), energy (...,).
    time_axis=True: q (..., T, D) -> residual (..., T*D), energy (...,).
    """

    lower: Tensor
    upper: Tensor
    sigma: float | Tensor = 0.05
    time_axis: bool = False

    def __post_init__(self) -> None:
        lo, hi = as_float_tensor(self.lower, "lower"), as_float_tensor(self.upper, "upper")
        if lo.ndim != 1 or lo.shape != hi.shape:
            raise InputError(
                f"JointLimits.lower and .upper must both have shape (D,), got {shape_of(lo)} and {shape_of(hi)}"
            )
        if lo.isnan().any() or hi.isnan().any() or (lo > hi).any() or (lo == math.inf).any() or (hi == -math.inf).any():
            raise InputError("JointLimits bounds must be non-NaN with lower <= upper, lower < inf and upper > -inf")
        sigma = as_float_tensor(self.sigma, "sigma")
        if sigma.ndim > 1 or (sigma.ndim == 1 and sigma.shape != lo.shape):
            raise InputError(f"JointLimits.sigma must be a float or shape {shape_of(lo)}, got {shape_of(sigma)}")
        check_positive("JointLimits.sigma", sigma)
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)
        object.__setattr__(self, "sigma", sigma)

    @property
    def _sigma(self) -> Tensor:
        """sigma as `__post_init__` stored it: a tensor."""
        assert isinstance(self.sigma, Tensor)
        return self.sigma

    def residual(self, ev: PoseEval) -> Tensor:
        """ev.q (..., D) or (..., T, D) with time_axis -> (..., D) or (..., T*D)."""
        q = ev.q
        if q.ndim < 1 + self.time_axis or q.shape[-1] != self.lower.shape[0]:
            raise InputError(
                f"JointLimits: ev.q {shape_of(q)} must be (..., {'T, ' * self.time_axis}{self.lower.shape[0]})"
            )
        below = torch.clamp(q - self.lower.to(q), max=0.0)
        above = torch.clamp(q - self.upper.to(q), min=0.0)
        r = (below + above) / self._sigma.to(q)
        return r.flatten(-2) if self.time_axis else r

    def jacobian(self, ev: PoseEval, jac: PoseJacobian) -> Tensor:
        """(..., D) -> (..., D, D) diagonal: 1/sigma where q is outside its limits (time_axis: autograd)."""
        if self.time_axis:
            raise NotImplementedError("JointLimits.jacobian with time_axis")
        return torch.diag_embed(self.diagonal_jacobian(ev))

    def diagonal_jacobian(self, ev: PoseEval) -> Tensor:
        """(..., D) -> (..., D): the Jacobian's diagonal (it has no other entries), 1/sigma outside the
        limits, 0 inside."""
        if self.time_axis:
            raise NotImplementedError("JointLimits.diagonal_jacobian with time_axis")
        q = ev.q
        outside = (q < self.lower.to(q)) | (q > self.upper.to(q))
        return outside.to(q) / self._sigma.to(q).expand(q.shape[-1:])


def whitening(name: str, covariance: Tensor, mask: Tensor, diagonal: bool | None = None) -> Tensor:
    """The whitening matrices of F keyframes whose N entries are given where mask (F, N) is True:
    covariance (N, N) or (F, N, N) full, or (N,) / (F, N) variances (a 2-D covariance is ambiguous when
    F == N: then say `diagonal=`); inf variances count as not given. -> W (F, N, N) float64 with
    W_f = L_S^{-1} on the given entries S of keyframe f (L_S the Cholesky factor of their
    sub-covariance) and zero rows and columns elsewhere, so |W_f e|^2 is the Mahalanobis distance of
    the given entries of e. InputError naming `name` on shapes, NaN/inf, asymmetry and covariances of
    the given entries that are not positive definite."""
    n_f, d = mask.shape
    cov = as_float_tensor(covariance, "covariance").double()
    if diagonal is None:
        if cov.ndim == 2 and n_f == d:
            raise InputError(
                f"{name}.covariance {shape_of(cov)} is ambiguous with F == D == "
                f"{d}: pass diagonal=True (per-keyframe variances) or False"
            )
        diagonal = cov.ndim == 1 or (cov.ndim == 2 and cov.shape == (n_f, d) and n_f != d)
    m = mask.double()
    if diagonal:
        if shape_of(cov) not in ((d,), (n_f, d)):
            raise InputError(f"{name}.covariance (diagonal) must be (D,) or (F, D) = ({n_f}, {d}), got {shape_of(cov)}")
        if cov.isnan().any() or (cov <= 0).any():
            raise InputError(f"{name}.covariance variances must be > 0 (inf = unset)")
        return torch.diag_embed(m * cov.expand(n_f, d).rsqrt())
    if shape_of(cov) not in ((d, d), (n_f, d, d)):
        raise InputError(f"{name}.covariance must be (D, D) or (F, D, D) with D={d}, F={n_f}, got {shape_of(cov)}")
    cov = cov.expand(n_f, d, d)
    keep = mask[:, :, None] & mask[:, None, :]
    if not torch.isfinite(cov[keep]).all() or not torch.allclose(
        torch.where(keep, cov, 0.0), torch.where(keep, cov.mT, 0.0), atol=1e-9
    ):
        raise InputError(f"{name}.covariance must be finite and symmetric")
    eye = torch.eye(d, dtype=cov.dtype).expand_as(cov)
    chol, info = torch.linalg.cholesky_ex(torch.where(keep, cov, eye))
    if (info != 0).any():
        raise InputError(
            f"{name}.covariance of the kept entries is not positive definite "
            f"for keyframes {(info != 0).nonzero().flatten().tolist()}"
        )
    # Kept and masked entries are uncoupled in the patched matrix, so its inverse factor is L_S^{-1} on
    # the kept block; zeroing the masked rows leaves exactly that.
    return torch.linalg.solve_triangular(chol, eye, upper=False) * m[:, :, None]


@dataclass(frozen=True, eq=False)
class Keyframe(LeastSquaresMixin):
    """3D keyframe prior (DiFranco et al. eq. 4) on a trajectory ev.q (..., T, D).

    times (F,) frame indices; target (F, D); covariance (D, D) or (F, D, D) full, or (D,) / (F, D)
    variances (a 2-D covariance is ambiguous when F == D: then say `diagonal=`); mask (F, D) bool,
    True = dof set by the keyframe (None: all). Masked-out dofs have infinite variance: the residual
    whitens the kept entries with the Cholesky factor of their sub-covariance (`whitening`),
    r_j = L_S^{-1}(q[t_j] - f_j)_S, and is 0 for the masked ones, so |r_j|^2 is the Mahalanobis
    distance of the kept dofs. Diagonal variances may be inf (= masked); target may be NaN where
    masked. angular (D,) bool or None: the differences of those dofs (angles) are taken on the circle,
    in [-pi, pi) (`wrapped_difference`). residual (..., F*D), energy (...,). The residual is linear in
    the keyframes' poses: d r_f / d q[t_f] = `whiten` (F, D, D), r_f = `frame_residual`.
    """

    times: Tensor
    target: Tensor
    covariance: Tensor
    mask: Tensor | None = None
    diagonal: bool | None = None
    angular: Tensor | None = None
    _whiten: Tensor = field(init=False, repr=False)
    _target: Tensor = field(init=False, repr=False)
    _last: int = field(init=False, repr=False)

    def __post_init__(self) -> None:
        times, target = check_times("Keyframe", self.times), as_float_tensor(self.target, "target")
        if target.ndim != 2 or target.shape[0] != times.shape[0]:
            raise InputError(f"Keyframe.target must have shape (F={times.shape[0]}, D), got {shape_of(target)}")
        n_f, d = target.shape
        mask = check_mask("Keyframe.mask", self.mask, (n_f, d))
        if not torch.isfinite(target[mask]).all():
            raise InputError("Keyframe.target has NaN/inf at dofs the mask keeps")
        if self.angular is not None:
            angular = torch.as_tensor(self.angular)
            if angular.dtype != torch.bool or shape_of(angular) != (d,):
                raise InputError(f"Keyframe.angular must be a bool tensor of shape ({d},), got {shape_of(angular)}")
            object.__setattr__(self, "angular", angular)
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "target", target)
        object.__setattr__(self, "mask", mask)
        object.__setattr__(self, "_whiten", whitening("Keyframe", self.covariance, mask, self.diagonal))
        object.__setattr__(self, "_target", torch.where(mask, target, 0.0))
        object.__setattr__(self, "_last", int(times.max()) if n_f else -1)

    @property
    def whiten(self) -> Tensor:
        """(F, D, D) float64: each keyframe's whitening matrix, the Jacobian of its residual w.r.t. its pose."""
        return self._whiten

    def frame_residual(self, q: Tensor) -> Tensor:
        """The keyframes' poses q (..., F, D) (the trajectory at `times`) -> (..., F, D) whitened residuals."""
        e = q - self._target.to(q)
        if self.angular is not None:
            e = wrapped_difference(e, self.angular.to(q.device))
        return torch.einsum("fij,...fj->...fi", self._whiten.to(q), e)

    def residual(self, ev: PoseEval) -> Tensor:
        """ev.q (..., T, D) -> (..., F*D) whitened keyframe residuals."""
        q = ev.q
        if q.ndim < 2 or q.shape[-1] != self.target.shape[1]:
            raise InputError(f"Keyframe: ev.q {shape_of(q)} must be (..., T, {self.target.shape[1]})")
        check_frame_count("Keyframe", q, self._last, -2)
        return self.frame_residual(q.index_select(-2, self.times.to(q.device))).flatten(-2)


@dataclass(frozen=True, eq=False)
class JointKeyframe(LeastSquaresMixin):
    """User-given 3D joint positions at some frames, on ev.joints (..., T, J, 3).

    times (F,), target_joints (F, J, 3) metres (NaN allowed where masked), mask (F, J) bool or None
    (all); sigma_m metres: a float, or (F, J) per given joint, the std of each of its coordinates;
    covariance (F, 3J, 3J) or None: the full covariance of each keyframe's joint coordinates (row 3j + c
    is joint j's coordinate c; m^2; only the given joints' block is read), replacing sigma_m.
    residual = W_f (joints[t_f] - target_f) flattened per frame (`whitening`: the given joints' Cholesky
    whitening, 0 for the others; with sigma_m alone, mask (joints - target) / sigma_m), (..., F*J*3). The
    residual is linear in the joints: d r_f / d joints[t_f] = `whiten` (F, 3J, 3J).
    """

    times: Tensor
    target_joints: Tensor
    mask: Tensor | None = None
    sigma_m: float | Tensor = 0.05
    covariance: Tensor | None = None
    _target: Tensor = field(init=False, repr=False)
    _whiten: Tensor = field(init=False, repr=False)
    _last: int = field(init=False, repr=False)

    def __post_init__(self) -> None:
        times = check_times("JointKeyframe", self.times)
        target = as_float_tensor(self.target_joints, "target_joints")
        if target.ndim != 3 or target.shape[0] != times.shape[0] or target.shape[2] != 3:
            raise InputError(
                f"JointKeyframe.target_joints must have shape (F={times.shape[0]}, J, 3), got {shape_of(target)}"
            )
        n_f, j = shape_of(target)[:2]
        mask = check_mask("JointKeyframe.mask", self.mask, (n_f, j))
        if not torch.isfinite(target[mask]).all():
            raise InputError("JointKeyframe.target_joints has NaN/inf at joints the mask keeps")
        sigma = as_float_tensor(self.sigma_m, "sigma_m")
        if sigma.ndim not in (0, 2) or (sigma.ndim == 2 and shape_of(sigma) != (n_f, j)):
            raise InputError(f"JointKeyframe.sigma_m must be a float or shape ({n_f}, {j}), got {shape_of(sigma)}")
        check_positive("JointKeyframe.sigma_m", sigma[mask] if sigma.ndim else sigma)
        coords = mask.repeat_interleave(3, -1)  # (F, 3J)
        if self.covariance is None:
            variance = sigma.double().square().expand(n_f, j).repeat_interleave(3, -1)
            variance = torch.where(coords, variance, 1.0)  # not read: a masked joint's sigma may be anything
            whiten = whitening("JointKeyframe", variance, coords, diagonal=True)
        else:
            whiten = whitening("JointKeyframe", self.covariance, coords, diagonal=False)
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "target_joints", target)
        object.__setattr__(self, "mask", mask)
        object.__setattr__(self, "sigma_m", sigma)
        object.__setattr__(self, "_target", torch.where(mask[..., None], target, 0.0))
        object.__setattr__(self, "_whiten", whiten)
        object.__setattr__(self, "_last", int(times.max()) if times.numel() else -1)

    @property
    def whiten(self) -> Tensor:
        """(F, 3J, 3J) float64: each keyframe's whitening matrix, the Jacobian of its residual w.r.t. its
        flattened joints."""
        return self._whiten

    @property
    def joints_given(self) -> tuple[int, ...]:
        """The joints some keyframe gives (the residual does not depend on the others)."""
        assert self.mask is not None  # set by __post_init__
        return tuple(torch.nonzero(self.mask.any(0)).flatten().tolist())

    def frame_residual(self, joints: Tensor) -> Tensor:
        """The keyframes' joints (..., F, J, 3) (the trajectory's at `times`) -> (..., F, 3J) whitened residuals."""
        e = (joints - self._target.to(joints)).flatten(-2)
        return torch.einsum("fij,...fj->...fi", self._whiten.to(joints), e)

    def residual(self, ev: PoseEval) -> Tensor:
        """ev.joints (..., T, J, 3) -> (..., F*J*3)."""
        x = ev.joints
        if x.ndim < 3 or x.shape[-2:] != self.target_joints.shape[1:]:
            raise InputError(
                f"JointKeyframe: ev.joints {shape_of(x)} must be (..., T, {self.target_joints.shape[1]}, 3)"
            )
        check_frame_count("JointKeyframe", x, self._last, -3)
        return self.frame_residual(x.index_select(-3, self.times.to(x.device))).flatten(-2)


@dataclass(frozen=True, eq=False)
class PosePrior(LeastSquaresMixin):
    """Gaussian prior around a predicted pose, one prediction per hypothesis (a tracker's dynamics).

    mean (..., D') predicted values of the entries `dofs` (D',) long of q (None: all of them, D' = D;
    broadcast against ev.q (..., D)); sigma float, (D',) or (..., D') standard deviations (radians / metres;
    per hypothesis too). residual (..., D') = (q[..., dofs] - mean) / sigma, energy (...,). With `dofs` it
    holds a part of any parameter vector read as ev.q (the golf tracker's PCA weights, times, root poses).
    """

    mean: Tensor
    sigma: float | Tensor = 0.15
    dofs: Tensor | None = None

    def __post_init__(self) -> None:
        mean = as_float_tensor(self.mean, "mean")
        if mean.ndim < 1 or not torch.isfinite(mean).all():
            raise InputError(f"PosePrior.mean must be finite with shape (..., D), got {shape_of(mean)}")
        sigma = as_float_tensor(self.sigma, "sigma")
        if sigma.ndim >= 1 and sigma.shape[-1] != mean.shape[-1]:
            raise InputError(f"PosePrior.sigma must be a float or shape (..., {mean.shape[-1]}), got {shape_of(sigma)}")
        check_positive("PosePrior.sigma", sigma)
        if self.dofs is not None:
            dofs = check_index("PosePrior.dofs", self.dofs, mean.shape[-1], f"mean {shape_of(mean)}")
            object.__setattr__(self, "dofs", dofs)
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "sigma", sigma)

    @property
    def _sigma(self) -> Tensor:
        """sigma as `__post_init__` stored it: a tensor."""
        assert isinstance(self.sigma, Tensor)
        return self.sigma

    def _held(self, q: Tensor) -> Tensor:
        """q (..., D) -> the entries the prior holds (..., D')."""
        if self.dofs is None:
            if q.shape[-1] != self.mean.shape[-1]:
                raise InputError(f"PosePrior: ev.q {shape_of(q)} must end in D={self.mean.shape[-1]}")
            return q
        if q.shape[-1] <= int(self.dofs.max()):
            raise InputError(f"PosePrior: ev.q {shape_of(q)} has no entry {int(self.dofs.max())} (dofs)")
        return q[..., self.dofs.to(q.device)]

    def residual(self, ev: PoseEval) -> Tensor:
        """ev.q (..., D) -> (..., D')."""
        return (self._held(ev.q) - self.mean.to(ev.q)) / self._sigma.to(ev.q)

    def jacobian(self, ev: PoseEval, jac: PoseJacobian) -> Tensor:
        """(..., D) -> (..., D', D): diag(1 / sigma), its rows `dofs` with them."""
        q = ev.q
        inv = 1.0 / self._sigma.to(q)
        if self.dofs is not None:
            rows = torch.eye(q.shape[-1], dtype=q.dtype, device=q.device)[self.dofs.to(q.device)]  # (D', D)
            j = rows * inv[..., None]
            return j.expand(*q.shape[:-1], *j.shape[-2:])
        if inv.ndim <= 1:
            return torch.diag_embed(inv.expand(q.shape[-1:])).expand(*q.shape, q.shape[-1])
        return torch.diag_embed(inv.expand(q.shape))  # a std per hypothesis: (..., D) like q

    def diagonal_jacobian(self, ev: PoseEval) -> Tensor:
        """(..., D) -> (..., D): the Jacobian's diagonal, 1 / sigma (it has no other entries); not with `dofs`."""
        if self.dofs is not None:
            raise NotImplementedError("PosePrior with dofs: its rows are stacked")
        return (1.0 / self._sigma.to(ev.q)).expand(ev.q.shape)


@dataclass(frozen=True, eq=False)
class HeavyTailedPrior(RobustMixin):
    """A prior around predicted poses with heavy tails (the long-tailed mixture components of
    Sminchisescu & Triggs 2003): Gaussian within about `scale` standard deviations of the mean, then
    growing only like the robust `loss` (cauchy: logarithmically), per dof. A tracker's dynamics
    held this way still pin the weakly observed dofs near the prediction, yet a kinematic jump far
    from it (a limb flipped in depth) stays a local minimum of comparable cost instead of being
    dragged back.

    mean (..., D); sigma float, (D,) or (..., D); loss a robust loss name; scale in sigmas.
    residual (..., D) = (q - mean) / sigma, energy (...,) = 0.5 sum rho(r^2, scale).
    """

    mean: Tensor
    sigma: float | Tensor = 0.15
    loss: str = "cauchy"
    scale: float = 3.0
    _group: ClassVar[int] = 1
    _gaussian: PosePrior = field(init=False, repr=False)  # the same residual, checks and Jacobian

    def __post_init__(self) -> None:
        gaussian = PosePrior(self.mean, self.sigma)
        robust_loss(self.loss)
        check_positive("HeavyTailedPrior.scale", self.scale)
        object.__setattr__(self, "_gaussian", gaussian)
        object.__setattr__(self, "mean", gaussian.mean)
        object.__setattr__(self, "sigma", gaussian.sigma)

    def residual(self, ev: PoseEval) -> Tensor:
        """ev.q (..., D) -> (..., D)."""
        return self._gaussian.residual(ev)

    def jacobian(self, ev: PoseEval, jac: PoseJacobian) -> Tensor:
        """(..., D) -> (..., D, D) = diag(1 / sigma)."""
        return torch.diag_embed(self.diagonal_jacobian(ev))

    def diagonal_jacobian(self, ev: PoseEval) -> Tensor:
        """(..., D) -> (..., D): the Jacobian's diagonal, 1 / sigma (it has no other entries)."""
        return self._gaussian.diagonal_jacobian(ev)
