"""Random proposals around the modes of a pose posterior: Covariance Scaled Sampling (CSS) and its
Spherical Sampling (SS) baseline (Sminchisescu & Triggs 2003, section 5.1, Table 1, fig. 6), and the
projection of proposals onto the joint limits.

CSS scatters samples around each mode with a covariance adapted to the local cost surface: `scale`
times the inverse Gauss-Newton Hessian at the mode, so samples go far along the directions the
image constrains little (depth, the monocular ambiguities) and stay close along the well-measured
ones. Directions the Hessian does not constrain at all get a bounded standard deviation instead of
an infinite one (`scaled_covariance`). SS is the cost-insensitive baseline: isotropic, with the same
core volume as the CSS ellipsoid, as the paper does for its comparison (std = det(Sigma)^(1/(2D))).
Both come with Gaussian or heavy tails: a multivariate Student-t with `dof` degrees of freedom
(scale matrix Sigma, covariance dof / (dof - 2) Sigma for dof > 2), or Cauchy (Student-t with one
degree of freedom, the paper's "HT"), drawn as the Gaussian scale mixture x = mean + L z / sqrt(w),
z ~ N(0, I), w ~ chi2(dof) / dof.

Like blackjax proposals, every sampler is a pure function that takes an explicit `torch.Generator`
and returns the samples with their log-density under the component they were drawn from (for
importance weights; `proposal_log_density` evaluates any points under every component, for
mixture densities). The random numbers are drawn in float64 on the generator's device, in a fixed
order (all normals, then the chi-square variates), and only then moved to the inputs' device and
dtype: one seed gives the same samples in float32 and float64, on CPU and CUDA, and CSS and SS
called with the same seed share their underlying draws (common random numbers).

Shapes: `M` modes (mixture components), `S` samples per mode, `N` samples in all, `D` dofs.
Units follow the pose: radians for angles, metres for translations.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ptrack.body.limits import wrap_to_limits
from ptrack.errors import InputError

TAILS = ("gaussian", "student", "cauchy")
PROJECTIONS = ("clamp", "reflect")


class ScaledCovariance(NamedTuple):
    """A CSS covariance and its Cholesky factor.

    covariance: (..., D, D) symmetric positive definite.
    chol: (..., D, D) lower triangular with a positive diagonal, chol @ chol.mT == covariance.
    """

    covariance: Tensor
    chol: Tensor


class Draws(NamedTuple):
    """Samples from a proposal.

    samples: (M, S, D) with an int sample count, (N, D) with per-mode counts (mode-major order).
    log_density: (M, S) or (N,), log-density of each raw sample (before any projection onto the
        limits) under the component it was drawn from, in the samples' units (radians, metres).
    component: (M, S) or (N,) long, the index of the mode each sample was drawn around.
    """

    samples: Tensor
    log_density: Tensor
    component: Tensor


# ---------------------------------------------------------------- covariance


def scaled_covariance(
    hessian: Tensor, scale: float | Tensor = 1.0, *, max_std: float = 1.0, min_std: float = 0.0
) -> ScaledCovariance:
    """The CSS covariance `scale * H^-1`, with H the Gauss-Newton Hessian at a mode, regularised so
    that it is finite and positive definite.

    H (the Gauss-Newton J^T J of a cost 0.5 |r|^2, i.e. the precision of the local Gaussian) is
    symmetrised and eigen-decomposed; its eigenvalues are clamped into [1 / max_std^2, 1 / min_std^2]
    before inversion. So before scaling, a direction H does not constrain (eigenvalue ~0, or
    negative from round-off) gets standard deviation `max_std` (radians / metres) rather than an
    infinite one, and no direction is narrower than `min_std` (0: no lower bound). Directions H
    constrains well are untouched: there the result is exactly scale * H^-1. After scaling, stds
    are sqrt(scale) times those. The eigen-decomposition and the Cholesky factor (from a QR of the
    square root V diag(std), which keeps the factor accurate for ill-conditioned covariances) are
    computed in float64 and returned in the Hessian's dtype.

    hessian: (..., D, D); scale: float or (...) tensor broadcastable to the batch dims, > 0
    (the paper's scaling factors are 4, 8, 16 for Gaussian tails, 1 for Cauchy tails);
    max_std > 0 finite; 0 <= min_std <= max_std.
    -> ScaledCovariance(covariance (..., D, D), chol (..., D, D)).
    """
    if (
        not isinstance(hessian, Tensor)
        or hessian.ndim < 2
        or hessian.shape[-1] != hessian.shape[-2]
        or hessian.shape[-1] == 0
    ):
        raise InputError(
            f"hessian must be a (..., D, D) tensor with D >= 1, got "
            f"{tuple(hessian.shape) if isinstance(hessian, Tensor) else type(hessian).__name__}"
        )
    if not hessian.is_floating_point():
        raise InputError(f"hessian must be a floating-point tensor, got {hessian.dtype}")
    if not (isinstance(max_std, (int, float)) and math.isfinite(max_std) and max_std > 0):
        raise InputError(f"max_std must be a finite number > 0, got {max_std!r}")
    if not (isinstance(min_std, (int, float)) and 0 <= min_std <= max_std):
        raise InputError(f"min_std must be a number in [0, max_std={max_std}], got {min_std!r}")
    batch = hessian.shape[:-2]
    work = _work_dtype(hessian.device)
    s = _positive("scale", scale, batch, hessian.device, work)
    h = hessian.to(work)
    if not bool(torch.isfinite(h).all()):
        raise InputError("hessian has non-finite entries (NaN or inf)")
    h = 0.5 * (h + h.mT)
    lam, vec = torch.linalg.eigh(h)
    hi = 1.0 / min_std**2 if min_std > 0 else math.inf
    var = s[..., None] / lam.clamp(min=1.0 / max_std**2, max=hi)  # (..., D)
    root = vec * var.sqrt()[..., None, :]  # root @ root.mT = V diag(var) V^T
    covariance = (vec * var[..., None, :]) @ vec.mT
    covariance = 0.5 * (covariance + covariance.mT)
    r = torch.linalg.qr(root.mT).R  # root.mT = Q R  =>  covariance = R^T R
    sign = torch.where(torch.diagonal(r, dim1=-2, dim2=-1) < 0, -1.0, 1.0).to(work)
    chol = (r * sign[..., :, None]).mT  # rows of R flipped so the diagonal is positive
    return ScaledCovariance(covariance.to(hessian.dtype), chol.to(hessian.dtype))


def spherical_std(chol: Tensor) -> Tensor:
    """The std of the sphere with the same core volume as the ellipsoid of covariance
    chol @ chol.mT: det(Sigma)^(1/(2D)), the paper's SS radius. chol: (..., D, D) -> (...)"""
    _check_square("chol", chol)
    return torch.exp(_log_det_chol(chol) / chol.shape[-1])


def spherical_chol(chol: Tensor) -> Tensor:
    """spherical_std(chol) times the identity: the SS counterpart of a CSS Cholesky factor, e.g. for
    `proposal_log_density` of an SS mixture. chol: (..., D, D) -> (..., D, D)"""
    eye = torch.eye(chol.shape[-1], dtype=chol.dtype, device=chol.device)
    return spherical_std(chol)[..., None, None] * eye


# ---------------------------------------------------------------- proposals


def css_proposal(
    mean: Tensor,
    chol: Tensor,
    n: int | Sequence[int] | Tensor,
    generator: torch.Generator,
    *,
    tail: str = "gaussian",
    dof: float | None = None,
) -> Draws:
    """Covariance Scaled Sampling: samples around each mode, x = mean_m + chol_m u, u a standard
    Gaussian, Student-t or Cauchy vector (see the module docstring).

    mean: (M, D) modes; chol: (M, D, D) lower-triangular factors of the modes' covariances (scale
    matrices for heavy tails), e.g. `scaled_covariance(H, scale).chol`; n: int S (S samples per mode)
    or (M,) non-negative counts; generator: any device; tail: "gaussian", "student" (needs `dof` > 0)
    or "cauchy"; `dof` is only read for "student".
    -> Draws with samples (M, S, D) or (N, D), in mean's dtype and on its device.
    """
    mean, chol = _check_modes(mean, chol)
    counts, per_mode = _counts(n, mean.shape[0])
    u, base = _whitened(mean, counts, per_mode, generator, tail, dof)
    return _draws(mean, u @ chol.mT, base - _log_det_chol(chol)[:, None], counts, per_mode)


def spherical_proposal(
    mean: Tensor,
    chol: Tensor,
    n: int | Sequence[int] | Tensor,
    generator: torch.Generator,
    *,
    tail: str = "gaussian",
    dof: float | None = None,
) -> Draws:
    """Spherical Sampling, the paper's baseline: like `css_proposal` with the same arguments, but each
    mode's covariance replaced by the isotropic one of the same core volume, std = det(Sigma)^(1/(2D))
    (`spherical_std`). Since the volumes agree, so do the log-densities of corresponding draws.

    mean: (M, D); chol: (M, D, D); n: int S or (M,) counts -> Draws (M, S, D) or (N, D).
    """
    mean, chol = _check_modes(mean, chol)
    counts, per_mode = _counts(n, mean.shape[0])
    u, base = _whitened(mean, counts, per_mode, generator, tail, dof)
    log_det = _log_det_chol(chol)
    std = torch.exp(log_det / chol.shape[-1])
    return _draws(mean, u * std[:, None, None], base - log_det[:, None], counts, per_mode)


def proposal_log_density(
    x: Tensor, mean: Tensor, chol: Tensor, *, tail: str = "gaussian", dof: float | None = None
) -> Tensor:
    """Log-density of points under each mode's component (before projection onto the limits).

    For a mixture with log-weights log_w (M,): torch.logsumexp(log_w + proposal_log_density(...), -1).
    Use `spherical_chol(chol)` for SS components.
    x: (..., D); mean: (M, D); chol: (M, D, D) -> (..., M)
    """
    mean, chol = _check_modes(mean, chol)
    nu = _check_tail(tail, dof)
    M, D = mean.shape
    if x.ndim < 1 or x.shape[-1] != D:
        raise InputError(f"x must be (..., D={D}) like mean (M, D)={tuple(mean.shape)}, got {tuple(x.shape)}")
    x = x.to(mean)
    diff = x.reshape(-1, 1, D) - mean  # (B, M, D)
    u = torch.linalg.solve_triangular(chol, diff.permute(1, 2, 0), upper=False)  # (M, D, B)
    sq = u.square().sum(-2).mT  # (B, M)
    out = _log_density_std(sq, D, nu) - _log_det_chol(chol)
    return out.reshape(*x.shape[:-1], M)


# ---------------------------------------------------------------- limits


def project_to_limits(
    q: Tensor, lower: Tensor, upper: Tensor, angular: Tensor | None = None, *, mode: str = "clamp"
) -> Tensor:
    """Samples moved into the joint-limit box [lower, upper] (bounds may be -inf / inf).

    Angular dofs (`angular` True) are first written in their limits' 2 pi window
    (`ptrack.body.limits.wrap_to_limits`: the same pose, the angle within pi of the arc's centre), so an
    angle just past +pi of an arc around pi is inside, and one outside its arc is brought to the
    bound nearest on the circle. Then each entry outside its bounds is
      "clamp":   set to the nearest bound (the paper's "projected back onto the feasible
                 constraint surface"); a share of the samples lands exactly on the boundary.
      "reflect": mirrored back in at the bound it crossed (folded again, as often as needed, when
                 it overshoots a two-sided box by more than its width), so the density stays
                 continuous at the boundary instead of piling up a mass on it. A zero-width box
                 gives its bound, an infinite entry is clamped.
    Entries inside their limits are returned unchanged (angles up to the 2 pi window, same pose);
    NaN stays NaN. The log-density of a `Draws` is that of the raw samples, not of the projected
    ones. q: (..., D); lower, upper: (D,) with lower <= upper; angular: (D,) bool or None
    -> (..., D), q's dtype and device.
    """
    if mode not in PROJECTIONS:
        raise InputError(f"projection mode must be one of {', '.join(PROJECTIONS)}, got {mode!r}")
    if not isinstance(q, Tensor) or q.ndim < 1 or not q.is_floating_point():
        raise InputError(
            f"q must be a floating-point (..., D) tensor, got "
            f"{tuple(q.shape) if isinstance(q, Tensor) else type(q).__name__}"
        )
    D = q.shape[-1]
    lower, upper = torch.as_tensor(lower).to(q), torch.as_tensor(upper).to(q)
    for name, b in (("lower", lower), ("upper", upper)):
        if b.shape != (D,):
            raise InputError(f"{name} must be (D,) = ({D},) like q's last dim, got {tuple(b.shape)}")
    if angular is not None:
        angular = torch.as_tensor(angular)
        if angular.shape != (D,) or angular.dtype != torch.bool:
            raise InputError(f"angular must be a ({D},) bool tensor, got {tuple(angular.shape)} {angular.dtype}")
    if bool((lower > upper).any()):
        bad = torch.nonzero(lower > upper).flatten().tolist()
        raise InputError(f"lower must be <= upper; dofs {bad} are not")
    if angular is not None:
        q = wrap_to_limits(q, lower, upper, angular)
    keep = (q >= lower) & (q <= upper) | torch.isnan(q)
    clamped = torch.minimum(torch.maximum(q, lower), upper)
    if mode == "clamp":
        return torch.where(keep, q, clamped)
    has_lo, has_hi = torch.isfinite(lower), torch.isfinite(upper)
    lo = torch.where(has_lo, lower, torch.zeros_like(lower))  # finite stand-ins keep unused branches finite
    hi = torch.where(has_hi, upper, torch.zeros_like(upper))
    width = hi - lo
    both = has_lo & has_hi
    period = torch.where(both & (width > 0), 2.0 * width, torch.ones_like(width))
    t = torch.remainder(q - lo, period)
    folded = torch.where(width > 0, lo + torch.where(t <= width, t, period - t), lo)
    out = torch.where(
        both, folded, torch.where(has_lo, lo + (q - lo).abs(), torch.where(has_hi, hi - (hi - q).abs(), q))
    )
    return torch.where(keep, q, torch.where(torch.isinf(q), clamped, out))


# ---------------------------------------------------------------- internals


def _work_dtype(device: torch.device) -> torch.dtype:
    """float64 for the linear algebra, except where the device has none (MPS)."""
    return torch.float32 if device.type == "mps" else torch.float64


def _positive(name: str, value: float | Tensor, batch: torch.Size, device: torch.device, dtype: torch.dtype) -> Tensor:
    """`value` as a tensor broadcast to `batch`, checked finite and > 0."""
    if isinstance(value, bool) or not isinstance(value, (int, float, Tensor)):
        raise InputError(f"{name} must be a number or a tensor, got {type(value).__name__}")
    t = torch.as_tensor(value).to(device=device, dtype=dtype)
    try:  # numpy's shape arithmetic: torch.broadcast_shapes costs milliseconds per call here
        if np.broadcast_shapes(tuple(t.shape), tuple(batch)) != tuple(batch):
            raise ValueError
    except ValueError:
        raise InputError(f"{name} must broadcast to the batch dims {tuple(batch)}, got {tuple(t.shape)}") from None
    if not bool((torch.isfinite(t) & (t > 0)).all()):
        raise InputError(f"{name} must be finite and > 0, got {value!r}")
    return t.expand(batch)


def _check_square(name: str, m: Tensor) -> None:
    if not isinstance(m, Tensor) or m.ndim < 2 or m.shape[-1] != m.shape[-2]:
        raise InputError(
            f"{name} must be a (..., D, D) tensor, got {tuple(m.shape) if isinstance(m, Tensor) else type(m).__name__}"
        )


def _check_modes(mean: Tensor, chol: Tensor) -> tuple[Tensor, Tensor]:
    """mean (M, D) and chol (M, D, D), chol in mean's dtype and on its device."""
    if not isinstance(mean, Tensor) or mean.ndim != 2 or not mean.is_floating_point():
        raise InputError(
            f"mean must be a floating-point (M, D) tensor, got "
            f"{tuple(mean.shape) if isinstance(mean, Tensor) else type(mean).__name__}"
        )
    M, D = mean.shape
    if not isinstance(chol, Tensor) or chol.shape != (M, D, D):
        raise InputError(
            f"chol must be (M, D, D) = ({M}, {D}, {D}) to match mean (M, D), got "
            f"{tuple(chol.shape) if isinstance(chol, Tensor) else type(chol).__name__}"
        )
    return mean, chol.to(mean)


def _check_tail(tail: str, dof: float | None) -> float | None:
    """Degrees of freedom of the tail: None for Gaussian, 1 for Cauchy, `dof` for Student-t."""
    if tail not in TAILS:
        raise InputError(f"tail must be one of {', '.join(TAILS)}, got {tail!r}")
    if dof is not None and (
        isinstance(dof, bool) or not isinstance(dof, (int, float)) or not math.isfinite(dof) or dof <= 0
    ):
        raise InputError(f"dof must be a finite number > 0, got {dof!r}")
    if tail == "student":
        if dof is None:
            raise InputError("tail='student' needs dof (degrees of freedom > 0)")
        return float(dof)
    return 1.0 if tail == "cauchy" else None


def _counts(n: int | Sequence[int] | Tensor, M: int) -> tuple[Tensor | None, int]:
    """(counts (M,) long on CPU or None, samples per mode S if uniform else the largest count)."""
    if isinstance(n, bool):
        raise InputError(f"n must be an int or (M,) counts, got {n!r}")
    if isinstance(n, int):
        if n < 0:
            raise InputError(f"n (samples per mode) must be >= 0, got {n}")
        return None, n
    c = torch.as_tensor(n)
    if c.is_floating_point() or c.is_complex() or c.dtype == torch.bool or c.shape != (M,):
        raise InputError(f"counts must be (M,) = ({M},) integers, one per mode, got {tuple(c.shape)} {c.dtype}")
    c = c.to(device="cpu", dtype=torch.long)
    if bool((c < 0).any()):
        raise InputError(f"counts must be >= 0, got {c.tolist()}")
    return c, int(c.max()) if M else 0


def _whitened(
    mean: Tensor, counts: Tensor | None, per_mode: int, generator: torch.Generator, tail: str, dof: float | None
) -> tuple[Tensor, Tensor]:
    """Standard (Gaussian / t / Cauchy) vectors padded to (M, S, D) in mean's dtype and device, and
    their log-density under the standard distribution (M, S). Padding rows (counts < S) are zeros."""
    nu = _check_tail(tail, dof)
    if not isinstance(generator, torch.Generator):
        raise InputError(f"generator must be a torch.Generator, got {type(generator).__name__}")
    M, D = mean.shape
    N = M * per_mode if counts is None else int(counts.sum())
    gdev = generator.device
    z = torch.randn((N, D), generator=generator, device=gdev, dtype=torch.float64)
    if nu is not None:  # chi2(nu) / nu = Gamma(nu / 2, rate nu / 2)
        w = torch._standard_gamma(torch.full((N,), 0.5 * nu, device=gdev, dtype=torch.float64), generator=generator) / (
            0.5 * nu
        )
        z = z * w.rsqrt()[:, None]
    sq = z.square().sum(-1)
    base = _log_density_std(sq, D, nu)
    z, base = z.to(device=mean.device, dtype=mean.dtype), base.to(device=mean.device, dtype=mean.dtype)
    if counts is None:
        return z.reshape(M, per_mode, D), base.reshape(M, per_mode)
    comp, pos = _layout(counts, mean.device)
    u = torch.zeros((M, per_mode, D), dtype=mean.dtype, device=mean.device)
    b = torch.zeros((M, per_mode), dtype=mean.dtype, device=mean.device)
    u[comp, pos] = z
    b[comp, pos] = base
    return u, b


def _layout(counts: Tensor, device: torch.device) -> tuple[Tensor, Tensor]:
    """(component (N,), position within its mode (N,)) of the mode-major flat layout."""
    M = counts.shape[0]
    comp = torch.repeat_interleave(torch.arange(M), counts)
    start = torch.cumsum(counts, 0) - counts
    pos = torch.arange(comp.shape[0]) - start[comp]
    return comp.to(device), pos.to(device)


def _draws(mean: Tensor, offsets: Tensor, log_density: Tensor, counts: Tensor | None, per_mode: int) -> Draws:
    """Draws from padded offsets (M, S, D) and log-densities (M, S), flattened with counts."""
    M = mean.shape[0]
    samples = mean[:, None, :] + offsets
    if counts is None:
        comp = torch.arange(M, device=mean.device)[:, None].expand(M, per_mode)
        return Draws(samples, log_density, comp)
    comp, pos = _layout(counts, mean.device)
    return Draws(samples[comp, pos], log_density[comp, pos], comp)


def _log_det_chol(chol: Tensor) -> Tensor:
    """log det(chol @ chol.mT) / 2 = sum log diag(chol). (..., D, D) -> (...)"""
    return torch.diagonal(chol, dim1=-2, dim2=-1).log().sum(-1)


def _log_density_std(sq: Tensor, D: int, nu: float | None) -> Tensor:
    """Log-density of a standard D-variate Gaussian (nu None) or Student-t (scale matrix I) at
    points with squared norm `sq`."""
    if nu is None:
        return -0.5 * sq - 0.5 * D * math.log(2.0 * math.pi)
    const = math.lgamma(0.5 * (nu + D)) - math.lgamma(0.5 * nu) - 0.5 * D * math.log(nu * math.pi)
    return const - 0.5 * (nu + D) * torch.log1p(sq / nu)
