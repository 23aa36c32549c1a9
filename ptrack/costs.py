"""Cost terms and the objective that sums them.

A cost term is three separate pieces (after theseus): a *residual* (a whitened vector per sample,
shape (..., M)), a *weight* (a float held by the `Objective`) and a *robust loss* rho applied to
squared residuals. A term's energy is 0.5 * sum rho(|r_g|^2) over its residual groups g (a group is
one residual entry, or both coordinates of one keypoint for `Reprojection`). Least-squares priors
use rho(s) = s. Gauss-Newton solvers read `Objective.residuals` plus the IRLS weights
`Objective.robust_weights`; particle trackers and L-BFGS read the energies.

Terms never run kinematics: they read a `PoseEval` made elsewhere (forward kinematics + camera).
For a trajectory the time axis is the last batch dim: q (..., T, D), joints (..., T, J, 3).
The batch shape of `energy` is the input's leading dims before the term's own event dims.
Pixel coordinates follow OpenCV: pixel (u, v) = (column, row), integer values at pixel centres.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Callable, ClassVar, Mapping, NamedTuple, Protocol

import torch
import torch.nn.functional as F
from torch import Tensor

from ptrack.errors import InputError

log = logging.getLogger(__name__)

Loss = Callable[[Tensor, float], Tensor]


class PoseEval(NamedTuple):
    """What the cost terms read about a batch of poses (one frame, or a trajectory with T last).

    q (..., D) pose parameters (root translation metres, angles radians); joints (..., J, 3) world
    joint positions, metres; pixels (..., K, 2) projected observed keypoints; depth (..., K)
    camera-frame depth of those keypoints; joint_pixels (..., J, 2) projected skeleton joints,
    only needed by `Silhouette`.
    """

    q: Tensor
    joints: Tensor
    pixels: Tensor
    depth: Tensor
    joint_pixels: Tensor | None = None


# ---------------------------------------------------------------------------------------------
# Robust losses: rho(s; c) of the squared whitened residual s, with rho(s) ~ s near 0.


def l2(s: Tensor, scale: float = 1.0) -> Tensor:
    """Plain least squares, rho(s) = s. s: (...) -> (...)."""
    return s


def huber(s: Tensor, scale: float = 1.0) -> Tensor:
    """Huber: s for s <= c^2, else 2 c sqrt(s) - c^2 (linear in |r|). s: (...) -> (...)."""
    c2 = scale * scale
    return torch.where(s <= c2, s, 2.0 * scale * torch.sqrt(s.clamp(min=c2)) - c2)


def cauchy(s: Tensor, scale: float = 1.0) -> Tensor:
    """Cauchy: c^2 log1p(s / c^2) (logarithmic in |r|). s: (...) -> (...)."""
    c2 = scale * scale
    return c2 * torch.log1p(s / c2)


def geman_mcclure(s: Tensor, scale: float = 1.0) -> Tensor:
    """Geman-McClure: s c^2 / (s + c^2), bounded by c^2. s: (...) -> (...)."""
    c2 = scale * scale
    return s * c2 / (s + c2)


def _l2_d(s: Tensor, scale: float = 1.0) -> Tensor:
    return torch.ones_like(s)


def _huber_d(s: Tensor, scale: float = 1.0) -> Tensor:
    c2 = scale * scale
    return torch.where(s <= c2, torch.ones_like(s), scale / torch.sqrt(s.clamp(min=c2)))


def _cauchy_d(s: Tensor, scale: float = 1.0) -> Tensor:
    c2 = scale * scale
    return c2 / (s + c2)


def _geman_mcclure_d(s: Tensor, scale: float = 1.0) -> Tensor:
    c2 = scale * scale
    return (c2 / (s + c2)).square()


_LOSSES: dict[str, tuple[Loss, Loss]] = {
    "l2": (l2, _l2_d),
    "huber": (huber, _huber_d),
    "cauchy": (cauchy, _cauchy_d),
    "geman_mcclure": (geman_mcclure, _geman_mcclure_d),
}


def robust_loss(name: str) -> Loss:
    """The robust loss `rho(s, scale)` called `name` (l2, huber, cauchy, geman_mcclure)."""
    if name not in _LOSSES:
        raise InputError(f"unknown robust loss {name!r}; choose one of {sorted(_LOSSES)}")
    return _LOSSES[name][0]


def robust_loss_derivative(name: str) -> Loss:
    """d rho / d s of the loss called `name`: the IRLS weight of a residual group, in (0, 1]."""
    robust_loss(name)
    return _LOSSES[name][1]


# ---------------------------------------------------------------------------------------------
# Validation helpers (construction time only: they may sync).


def _float(name: str, x) -> Tensor:
    t = torch.as_tensor(x)
    return t if t.is_floating_point() else t.to(torch.get_default_dtype())


def _positive(name: str, value) -> None:
    t = torch.as_tensor(value, dtype=torch.float64)
    if not (torch.isfinite(t).all() and (t > 0).all()):
        raise InputError(f"{name} must be finite and > 0, got {value!r}")


def _shape(x: Tensor) -> tuple[int, ...]:
    return tuple(x.shape)


def _times(name: str, times) -> Tensor:
    t = torch.as_tensor(times)
    if t.ndim != 1 or t.is_floating_point() or t.dtype == torch.bool:
        raise InputError(f"{name}.times must be a 1-D integer tensor (F,), got {t.dtype} "
                         f"{_shape(t)}")
    if (t < 0).any():
        raise InputError(f"{name}.times must be >= 0, got {t.tolist()}")
    return t.long()


def _mask(name: str, mask, shape: tuple[int, ...]) -> Tensor:
    if mask is None:
        return torch.ones(shape, dtype=torch.bool)
    m = torch.as_tensor(mask)
    if m.dtype != torch.bool or _shape(m) != shape:
        raise InputError(f"{name} must be a bool tensor of shape {shape}, got {m.dtype} "
                         f"{_shape(m)}")
    return m


def _frame_count(name: str, x: Tensor, times_max: int, time_dim: int) -> None:
    if x.ndim < -time_dim or x.shape[time_dim] <= times_max:
        raise InputError(f"{name}: keyframe time {times_max} is outside a trajectory of shape "
                         f"{_shape(x)} (time axis {time_dim})")


# ---------------------------------------------------------------------------------------------
# Term plumbing.


class CostTerm(Protocol):
    """What an `Objective` needs from a term; every term below satisfies it."""

    def residual(self, ev: PoseEval) -> Tensor: ...

    def energy(self, ev: PoseEval) -> Tensor: ...

    def robust_weights(self, ev: PoseEval) -> Tensor: ...


class _LeastSquares:
    """Mixin: energy = 0.5 |r|^2 and IRLS weights all one."""

    def energy(self, ev: PoseEval) -> Tensor:
        """ev -> (...,) = 0.5 * sum of squared residual entries."""
        return 0.5 * self.residual(ev).square().sum(-1)

    def robust_weights(self, ev: PoseEval) -> Tensor:
        """ev -> (..., M) of ones (no robust loss)."""
        return torch.ones_like(self.residual(ev))


class _Robust:
    """Mixin: residual entries come in consecutive groups of `_group`; rho sees |r_group|^2."""

    _group: ClassVar[int]
    loss: str
    scale: float

    def _squared(self, ev: PoseEval) -> tuple[Tensor, Tensor]:
        r = self.residual(ev)
        return r, r.unflatten(-1, (-1, self._group)).square().sum(-1)

    def energy(self, ev: PoseEval) -> Tensor:
        """ev -> (...,) = 0.5 * sum over groups of rho(|r_group|^2, scale)."""
        _, s = self._squared(ev)
        return 0.5 * robust_loss(self.loss)(s, self.scale).sum(-1)

    def robust_weights(self, ev: PoseEval) -> Tensor:
        """ev -> (..., M): rho'(|r_group|^2) repeated over each group's entries (IRLS weights)."""
        r, s = self._squared(ev)
        w = robust_loss_derivative(self.loss)(s, self.scale)
        return w.unsqueeze(-1).expand(*w.shape, self._group).reshape(r.shape)


# ---------------------------------------------------------------------------------------------
# Terms.


@dataclass(frozen=True, eq=False)
class Reprojection(_Robust):
    """2D keypoint reprojection error, robust per keypoint.

    observed (*O, K, 2) pixels, confidence (*O, K) >= 0 (0 = missing; NaN observations allowed
    there); *O is () for one frame or (T,) for a trajectory. Reads ev.pixels (..., *O, K, 2).
    residual (..., |O|*K*2): r_k = sqrt(confidence_k) (pixels_k - observed_k) / sigma_px, the x, y
    of keypoint k adjacent; rho(s, scale) is applied to s_k = |r_k|^2 (both coordinates together),
    so `scale` is in units of sigma_px.
    """

    observed: Tensor
    confidence: Tensor
    sigma_px: float = 1.0
    loss: str = "cauchy"
    scale: float = 1.0
    _group: ClassVar[int] = 2
    _target: Tensor = field(init=False, repr=False)
    _sqrt_conf: Tensor = field(init=False, repr=False)

    def __post_init__(self) -> None:
        obs, conf = _float("observed", self.observed), _float("confidence", self.confidence)
        if obs.ndim < 2 or obs.shape[-1] != 2 or obs.shape[-2] == 0:
            raise InputError(f"Reprojection.observed must have shape (*O, K, 2) with K >= 1, "
                             f"got {_shape(obs)}")
        if conf.shape != obs.shape[:-1]:
            raise InputError(f"Reprojection.confidence must have shape {_shape(obs)[:-1]} to "
                             f"match observed {_shape(obs)}, got {_shape(conf)}")
        if not (torch.isfinite(conf).all() and (conf >= 0).all()):
            raise InputError("Reprojection.confidence must be finite and >= 0")
        valid = conf > 0
        bad = valid & ~torch.isfinite(obs).all(-1)
        if bad.any():
            raise InputError(f"Reprojection.observed has NaN/inf at keypoints with confidence > 0, "
                             f"indices {bad.nonzero().tolist()[:5]}")
        _positive("Reprojection.sigma_px", self.sigma_px)
        _positive("Reprojection.scale", self.scale)
        robust_loss(self.loss)
        object.__setattr__(self, "observed", obs)
        object.__setattr__(self, "confidence", conf)
        object.__setattr__(self, "_target", torch.where(valid[..., None], obs, 0.0))
        object.__setattr__(self, "_sqrt_conf", conf.sqrt() / self.sigma_px)

    def residual(self, ev: PoseEval) -> Tensor:
        """ev.pixels (..., *O, K, 2) -> (..., |O|*K*2) whitened pixel residuals."""
        p, n = ev.pixels, self.observed.ndim
        if p.ndim < n or p.shape[-n:] != self.observed.shape:
            raise InputError(f"Reprojection: ev.pixels {_shape(p)} must end in observed's shape "
                             f"{_shape(self.observed)}")
        r = (p - self._target.to(p)) * self._sqrt_conf.to(p)[..., None]
        return r.flatten(-n)


@dataclass(frozen=True, eq=False)
class JointLimits(_LeastSquares):
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
        lo, hi = _float("lower", self.lower), _float("upper", self.upper)
        if lo.ndim != 1 or lo.shape != hi.shape:
            raise InputError(f"JointLimits.lower and .upper must both have shape (D,), got "
                             f"{_shape(lo)} and {_shape(hi)}")
        if lo.isnan().any() or hi.isnan().any() or (lo > hi).any() or (lo == math.inf).any() \
                or (hi == -math.inf).any():
            raise InputError("JointLimits bounds must be non-NaN with lower <= upper, lower < inf "
                             "and upper > -inf")
        sigma = _float("sigma", self.sigma)
        if sigma.ndim > 1 or (sigma.ndim == 1 and sigma.shape != lo.shape):
            raise InputError(f"JointLimits.sigma must be a float or shape {_shape(lo)}, got "
                             f"{_shape(sigma)}")
        _positive("JointLimits.sigma", sigma)
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)
        object.__setattr__(self, "sigma", sigma)

    def residual(self, ev: PoseEval) -> Tensor:
        """ev.q (..., D) or (..., T, D) with time_axis -> (..., D) or (..., T*D)."""
        q = ev.q
        if q.ndim < 1 + self.time_axis or q.shape[-1] != self.lower.shape[0]:
            raise InputError(f"JointLimits: ev.q {_shape(q)} must be (..., {'T, ' * self.time_axis}"
                             f"{self.lower.shape[0]})")
        below = torch.clamp(q - self.lower.to(q), max=0.0)
        above = torch.clamp(q - self.upper.to(q), min=0.0)
        r = (below + above) / self.sigma.to(q)
        return r.flatten(-2) if self.time_axis else r


@dataclass(frozen=True, eq=False)
class Smoothness(_LeastSquares):
    """Finite-difference velocity and acceleration prior on a trajectory.

    on="q": x = ev.q (..., T, D), dof_scale (D,); on="joints": x = ev.joints (..., T, J, 3),
    dof_scale (J,). residual = concat of (x[t+1] - x[t]) / (dt sigma_velocity) over t < T-1 and
    (x[t+1] - 2x[t] + x[t-1]) / (dt^2 sigma_acceleration), each times dof_scale and flattened:
    (..., (T-1)*E + (T-2)*E) for E entries per frame. A None sigma drops that part.
    """

    dt: float
    sigma_velocity: float | None = None
    sigma_acceleration: float | None = None
    on: str = "q"
    dof_scale: Tensor | None = None

    def __post_init__(self) -> None:
        _positive("Smoothness.dt", self.dt)
        for name in ("sigma_velocity", "sigma_acceleration"):
            if getattr(self, name) is not None:
                _positive(f"Smoothness.{name}", getattr(self, name))
        if self.on not in ("q", "joints"):
            raise InputError(f"Smoothness.on must be 'q' or 'joints', got {self.on!r}")
        if self.dof_scale is not None:
            scale = _float("dof_scale", self.dof_scale)
            if scale.ndim != 1 or not (torch.isfinite(scale).all() and (scale >= 0).all()):
                raise InputError(f"Smoothness.dof_scale must be a finite, >= 0 vector, got "
                                 f"shape {_shape(scale)}")
            object.__setattr__(self, "dof_scale", scale)

    def residual(self, ev: PoseEval) -> Tensor:
        """ev.q (..., T, D) or ev.joints (..., T, J, 3) -> (..., M)."""
        x, n = (ev.q, 2) if self.on == "q" else (ev.joints, 3)
        if x.ndim < n or (n == 3 and x.shape[-1] != 3):
            raise InputError(f"Smoothness(on={self.on!r}) needs a trajectory (..., T, "
                             f"{'D' if n == 2 else 'J, 3'}), got {_shape(x)}")
        if self.dof_scale is not None:
            if self.dof_scale.shape[0] != x.shape[-n + 1]:
                raise InputError(f"Smoothness.dof_scale {_shape(self.dof_scale)} does not match "
                                 f"{self.on} of shape {_shape(x)}")
            x = x * (self.dof_scale.to(x) if n == 2 else self.dof_scale.to(x)[:, None])
        parts = []
        if self.sigma_velocity is not None:
            parts.append(torch.diff(x, n=1, dim=-n) / (self.dt * self.sigma_velocity))
        if self.sigma_acceleration is not None:
            parts.append(torch.diff(x, n=2, dim=-n) / (self.dt**2 * self.sigma_acceleration))
        if not parts:
            return x.new_zeros(x.shape[:-n] + (0,))
        return torch.cat([p.flatten(-n) for p in parts], dim=-1)


@dataclass(frozen=True, eq=False)
class Keyframe(_LeastSquares):
    """3D keyframe prior (DiFranco et al. eq. 4) on a trajectory ev.q (..., T, D).

    times (F,) frame indices; target (F, D); covariance (D, D) or (F, D, D) full, or (D,) / (F, D)
    variances (a 2-D covariance is ambiguous when F == D: then say `diagonal=`); mask (F, D) bool,
    True = dof set by the keyframe (None: all). Masked-out dofs have infinite variance: the residual
    whitens the kept entries with the Cholesky factor of their sub-covariance,
    r_j = L_S^{-1}(q[t_j] - f_j)_S, and is 0 for the masked ones, so |r_j|^2 is the Mahalanobis
    distance of the kept dofs. Diagonal variances may be inf (= masked); target may be NaN where
    masked. residual (..., F*D), energy (...,).
    """

    times: Tensor
    target: Tensor
    covariance: Tensor
    mask: Tensor | None = None
    diagonal: bool | None = None
    _whiten: Tensor = field(init=False, repr=False)
    _target: Tensor = field(init=False, repr=False)
    _last: int = field(init=False, repr=False)

    def __post_init__(self) -> None:
        times, target = _times("Keyframe", self.times), _float("target", self.target)
        if target.ndim != 2 or target.shape[0] != times.shape[0]:
            raise InputError(f"Keyframe.target must have shape (F={times.shape[0]}, D), got "
                             f"{_shape(target)}")
        n_f, d = target.shape
        mask = _mask("Keyframe.mask", self.mask, (n_f, d))
        if not torch.isfinite(target[mask]).all():
            raise InputError("Keyframe.target has NaN/inf at dofs the mask keeps")
        cov = _float("covariance", self.covariance).double()
        diagonal = self.diagonal
        if diagonal is None:
            if cov.ndim == 2 and n_f == d:
                raise InputError(f"Keyframe.covariance {_shape(cov)} is ambiguous with F == D == "
                                 f"{d}: pass diagonal=True (per-keyframe variances) or False")
            diagonal = cov.ndim == 1 or (cov.ndim == 2 and cov.shape == (n_f, d) and n_f != d)
        m = mask.double()
        if diagonal:
            if _shape(cov) not in ((d,), (n_f, d)):
                raise InputError(f"Keyframe.covariance (diagonal) must be (D,) or (F, D) = "
                                 f"({n_f}, {d}), got {_shape(cov)}")
            if cov.isnan().any() or (cov <= 0).any():
                raise InputError("Keyframe.covariance variances must be > 0 (inf = unset)")
            whiten = torch.diag_embed(m * cov.expand(n_f, d).rsqrt())
        else:
            if _shape(cov) not in ((d, d), (n_f, d, d)):
                raise InputError(f"Keyframe.covariance must be (D, D) or (F, D, D) with D={d}, "
                                 f"F={n_f}, got {_shape(cov)}")
            cov = cov.expand(n_f, d, d)
            if not torch.isfinite(cov).all() or not torch.allclose(cov, cov.mT, atol=1e-9):
                raise InputError("Keyframe.covariance must be finite and symmetric")
            keep = mask[:, :, None] & mask[:, None, :]
            eye = torch.eye(d, dtype=cov.dtype).expand_as(cov)
            chol, info = torch.linalg.cholesky_ex(torch.where(keep, cov, eye))
            if (info != 0).any():
                raise InputError(f"Keyframe.covariance of the kept dofs is not positive definite "
                                 f"for keyframes {(info != 0).nonzero().flatten().tolist()}")
            # Kept and masked dofs are uncoupled in the patched matrix, so its inverse factor is
            # L_S^{-1} on the kept block; zeroing the masked rows leaves exactly that.
            inv = torch.linalg.solve_triangular(chol, eye, upper=False)
            whiten = inv * m[:, :, None]
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "target", target)
        object.__setattr__(self, "mask", mask)
        object.__setattr__(self, "_whiten", whiten)
        object.__setattr__(self, "_target", torch.where(mask, target, 0.0))
        object.__setattr__(self, "_last", int(times.max()) if n_f else -1)

    def residual(self, ev: PoseEval) -> Tensor:
        """ev.q (..., T, D) -> (..., F*D) whitened keyframe residuals."""
        q = ev.q
        if q.ndim < 2 or q.shape[-1] != self.target.shape[1]:
            raise InputError(f"Keyframe: ev.q {_shape(q)} must be (..., T, {self.target.shape[1]})")
        _frame_count("Keyframe", q, self._last, -2)
        e = q.index_select(-2, self.times.to(q.device)) - self._target.to(q)
        return torch.einsum("fij,...fj->...fi", self._whiten.to(q), e).flatten(-2)


@dataclass(frozen=True, eq=False)
class JointKeyframe(_LeastSquares):
    """User-given 3D joint positions at some frames, on ev.joints (..., T, J, 3).

    times (F,), target_joints (F, J, 3) metres (NaN allowed where masked), mask (F, J) bool or
    None (all), sigma_m metres. residual = mask (joints[t_f] - target) / sigma_m, (..., F*J*3).
    """

    times: Tensor
    target_joints: Tensor
    mask: Tensor | None = None
    sigma_m: float = 0.05
    _target: Tensor = field(init=False, repr=False)
    _weight: Tensor = field(init=False, repr=False)
    _last: int = field(init=False, repr=False)

    def __post_init__(self) -> None:
        times = _times("JointKeyframe", self.times)
        target = _float("target_joints", self.target_joints)
        if target.ndim != 3 or target.shape[0] != times.shape[0] or target.shape[2] != 3:
            raise InputError(f"JointKeyframe.target_joints must have shape (F={times.shape[0]}, J, "
                             f"3), got {_shape(target)}")
        mask = _mask("JointKeyframe.mask", self.mask, _shape(target)[:2])
        if not torch.isfinite(target[mask]).all():
            raise InputError("JointKeyframe.target_joints has NaN/inf at joints the mask keeps")
        _positive("JointKeyframe.sigma_m", self.sigma_m)
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "target_joints", target)
        object.__setattr__(self, "mask", mask)
        object.__setattr__(self, "_target", torch.where(mask[..., None], target, 0.0))
        object.__setattr__(self, "_weight", mask[..., None].to(target.dtype) / self.sigma_m)
        object.__setattr__(self, "_last", int(times.max()) if times.numel() else -1)

    def residual(self, ev: PoseEval) -> Tensor:
        """ev.joints (..., T, J, 3) -> (..., F*J*3)."""
        x = ev.joints
        if x.ndim < 3 or x.shape[-2:] != self.target_joints.shape[1:]:
            raise InputError(f"JointKeyframe: ev.joints {_shape(x)} must be (..., T, "
                             f"{self.target_joints.shape[1]}, 3)")
        _frame_count("JointKeyframe", x, self._last, -3)
        e = x.index_select(-3, self.times.to(x.device)) - self._target.to(x)
        return (e * self._weight.to(x)).flatten(-3)


def distance_transform(mask: Tensor) -> Tensor:
    """Exact Euclidean distance in pixels from each pixel to the nearest True pixel.

    mask: (..., H, W) bool -> (..., H, W) float64; 0 on the mask, inf in an image with no True
    pixel. Separable: a 1-D pass down columns, then a lower envelope of parabolas along rows
    (brute force, chunked to bound memory). Construction-time helper, not differentiable.
    """
    mask = torch.as_tensor(mask, dtype=torch.bool)
    h, w = mask.shape[-2:]
    rows = torch.arange(h, dtype=torch.float64, device=mask.device)[:, None].expand(h, w)
    inf = torch.tensor(math.inf, dtype=torch.float64, device=mask.device)
    above = torch.where(mask, rows, -inf).cummax(-2).values
    below = torch.where(mask, rows, inf).flip(-2).cummin(-2).values.flip(-2)
    g = torch.minimum(rows - above, below - rows).square().reshape(-1, w)
    cols = torch.arange(w, dtype=torch.float64, device=mask.device)
    d2 = (cols[:, None] - cols[None, :]).square()
    chunk = max(1, 2**22 // (w * w))
    out = torch.cat([(c[:, None, :] + d2).amin(-1) for c in g.split(chunk)]) if g.numel() else g
    return out.sqrt().reshape(mask.shape)


@dataclass(frozen=True, eq=False)
class Silhouette(_Robust):
    """Keeps projected bones inside a foreground mask, on ev.joint_pixels (..., *O, J, 2).

    masks (*O, H, W) bool, *O = () or (T,); bones ((parent, child), ...) skeleton joint indices.
    Each bone is sampled at samples_per_bone points from parent to child (ends included); a
    sample's residual is DT(point) / sigma_px with DT the distance (pixels) to the nearest mask
    pixel, read by bilinear `grid_sample` (align_corners=True: pixel centres at integers). Points
    outside the image read DT at the nearest border point plus their distance to it. Frames with
    an empty mask count as missing (zero residual). residual (..., |O|*B*S), rho per sample.
    """

    masks: Tensor
    bones: tuple[tuple[int, int], ...]
    sigma_px: float = 1.0
    samples_per_bone: int = 8
    loss: str = "l2"
    scale: float = 1.0
    _group: ClassVar[int] = 1
    _dt: Tensor = field(init=False, repr=False)
    _present: Tensor = field(init=False, repr=False)
    _bones: Tensor = field(init=False, repr=False)

    def __post_init__(self) -> None:
        masks = torch.as_tensor(self.masks)
        if masks.dtype != torch.bool or masks.ndim < 2 or min(masks.shape[-2:]) < 2:
            raise InputError(f"Silhouette.masks must be a bool tensor (*O, H, W) with H, W >= 2, "
                             f"got {masks.dtype} {_shape(masks)}")
        bones = torch.as_tensor(self.bones)
        if bones.ndim != 2 or bones.shape[1] != 2 or bones.shape[0] == 0 \
                or bones.is_floating_point() or (bones < 0).any():
            raise InputError(f"Silhouette.bones must be non-empty (parent, child) pairs of joint "
                             f"indices >= 0, got {self.bones!r}")
        if int(self.samples_per_bone) != self.samples_per_bone or self.samples_per_bone < 2:
            raise InputError(f"Silhouette.samples_per_bone must be an integer >= 2, got "
                             f"{self.samples_per_bone!r}")
        _positive("Silhouette.sigma_px", self.sigma_px)
        _positive("Silhouette.scale", self.scale)
        robust_loss(self.loss)
        dt = distance_transform(masks)
        present = masks.flatten(-2).any(-1)
        if not present.all():
            log.warning("Silhouette: %d of %d masks are empty and count as missing",
                        int((~present).sum()), present.numel())
        object.__setattr__(self, "masks", masks)
        object.__setattr__(self, "_dt", torch.where(present[..., None, None], dt, 0.0))
        object.__setattr__(self, "_present", present)
        object.__setattr__(self, "_bones", bones.long())

    def residual(self, ev: PoseEval) -> Tensor:
        """ev.joint_pixels (..., *O, J, 2) -> (..., |O|*B*S): distance outside mask / sigma_px."""
        jp = ev.joint_pixels
        if jp is None:
            raise InputError("Silhouette needs PoseEval.joint_pixels (..., J, 2), the projected "
                             "pixels of all skeleton joints, but it is None")
        frames, (h, w) = self.masks.shape[:-2], self.masks.shape[-2:]
        n_o = len(frames)
        if jp.ndim < n_o + 2 or jp.shape[-1] != 2 or jp.shape[jp.ndim - n_o - 2:-2] != frames \
                or jp.shape[-2] <= int(self._bones.max()):
            raise InputError(f"Silhouette: ev.joint_pixels {_shape(jp)} must be (..., "
                             f"{', '.join(map(str, frames)) + ', ' if n_o else ''}J, 2) with J > "
                             f"{int(self._bones.max())}")
        bones = self._bones.to(jp.device)
        parent, child = jp.index_select(-2, bones[:, 0]), jp.index_select(-2, bones[:, 1])
        t = torch.linspace(0.0, 1.0, self.samples_per_bone, dtype=jp.dtype, device=jp.device)
        pts = parent[..., None, :] + t[:, None] * (child - parent)[..., None, :]
        batch, n_frames = jp.shape[:jp.ndim - n_o - 2], math.prod(frames)
        pts = pts.reshape(-1, n_frames, pts.shape[-3] * pts.shape[-2], 2).transpose(0, 1)
        u, v = pts.unbind(-1)
        uc, vc = u.clamp(0.0, w - 1.0), v.clamp(0.0, h - 1.0)
        off2 = (u - uc).square() + (v - vc).square()
        outside = torch.where(off2 > 0, torch.where(off2 > 0, off2, 1.0).sqrt(), 0.0)
        grid = torch.stack([2.0 * uc / (w - 1) - 1.0, 2.0 * vc / (h - 1) - 1.0], dim=-1)
        dt = self._dt.to(jp).reshape(n_frames, 1, h, w)
        d = F.grid_sample(dt, grid, mode="bilinear", padding_mode="border", align_corners=True)
        d = (d[:, 0] + outside) * self._present.to(jp).reshape(n_frames, 1, 1)
        return d.transpose(0, 1).reshape(*batch, -1) / self.sigma_px


# ---------------------------------------------------------------------------------------------
# Objective.


class ObjectiveValue(NamedTuple):
    """total (...,) weighted energy; terms: name -> weighted energy (...,), summing to total."""

    total: Tensor
    terms: dict[str, Tensor]


def _same_batch(what: str, shapes: Mapping[str, torch.Size]) -> None:
    if len(set(shapes.values())) > 1:
        got = {name: tuple(s) for name, s in shapes.items()}
        raise InputError(f"Objective terms disagree on the batch shape of their {what}: {got} "
                         f"(trajectory terms need JointLimits(time_axis=True))")


@dataclass(frozen=True, eq=False)
class Objective:
    """Weighted sum of named cost terms: E = sum_i w_i E_i (weights default to 1).

    Every term must give the same energy batch shape (...,) for the PoseEval it is called on.
    """

    terms: Mapping[str, CostTerm]
    weights: Mapping[str, float] | None = None

    def __post_init__(self) -> None:
        if not self.terms:
            raise InputError("Objective needs at least one term")
        for name, term in self.terms.items():
            if not all(callable(getattr(term, m, None))
                       for m in ("residual", "energy", "robust_weights")):
                raise InputError(f"Objective term {name!r} is not a cost term: "
                                 f"{type(term).__name__}")
        weights = dict(self.weights or {})
        unknown = sorted(set(weights) - set(self.terms))
        if unknown:
            raise InputError(f"Objective weights name unknown terms {unknown}; terms are "
                             f"{sorted(self.terms)}")
        for name, value in weights.items():
            if not (math.isfinite(float(value)) and float(value) >= 0):
                raise InputError(f"Objective weight {name!r} must be finite and >= 0, "
                                 f"got {value!r}")
        object.__setattr__(self, "terms", MappingProxyType(dict(self.terms)))
        object.__setattr__(self, "weights",
                           MappingProxyType({n: float(weights.get(n, 1.0)) for n in self.terms}))

    def __call__(self, ev: PoseEval) -> ObjectiveValue:
        """ev -> ObjectiveValue(total (...,), terms {name: w * energy (...,)})."""
        parts = {name: self.weights[name] * term.energy(ev) for name, term in self.terms.items()}
        _same_batch("energy", {name: e.shape for name, e in parts.items()})
        return ObjectiveValue(torch.stack(list(parts.values())).sum(0), parts)

    def residuals(self, ev: PoseEval) -> Tensor:
        """ev -> (..., M_total): each term's whitened residual times sqrt(weight), concatenated.

        For least-squares terms 0.5 |r|^2 is their share of the total. Robust terms return the plain
        whitened residual: a Gauss-Newton / IRLS step uses diag(robust_weights(ev)) as the per-row
        weight (J^T W J dq = -J^T W r), which matches the gradient of the robust total.
        """
        parts = {n: math.sqrt(self.weights[n]) * t.residual(ev) for n, t in self.terms.items()}
        _same_batch("residuals", {name: r.shape[:-1] for name, r in parts.items()})
        return torch.cat(list(parts.values()), dim=-1)

    def robust_weights(self, ev: PoseEval) -> Tensor:
        """ev -> (..., M_total) IRLS weights rho'(s) aligned with `residuals` (1 for l2 terms)."""
        parts = {name: term.robust_weights(ev) for name, term in self.terms.items()}
        _same_batch("robust weights", {name: w.shape[:-1] for name, w in parts.items()})
        return torch.cat(list(parts.values()), dim=-1)
