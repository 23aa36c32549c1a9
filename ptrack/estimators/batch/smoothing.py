"""The smoothing prior of the batch objective (`method: batch`, DiFranco, Cham & Rehg 2001, eq. 3): forward
differences of the trajectory over time, the band of their Gauss-Newton Hessian, and the residuals under a
robust loss (IRLS weights). Shapes: T frames, D dofs, W the band's width (the highest difference order)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ptrack.costs import robust_loss, robust_loss_derivative

if TYPE_CHECKING:
    from ptrack.estimators.batch.objective import Trajectory


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


def band_matvec(band: Tensor, q: Tensor) -> Tensor:
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
