"""The smoothing prior of the batch objective (`method: batch`, DiFranco, Cham & Rehg 2001, eq. 3): the shared
`ptrack.costs.Smoothness` residuals (forward differences of the trajectory over time, per-dof scales) under a
robust loss (IRLS weights), and the band of their Gauss-Newton Hessian (`ptrack.optim.trajectory`). Shapes: T
frames, D dofs, W the band's width (the highest difference order)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ptrack.costs import PoseEval, Smoothness, robust_loss, robust_loss_derivative
from ptrack.optim.trajectory import band_matvec, difference_transpose, weighted_band

if TYPE_CHECKING:
    from ptrack.estimators.batch.objective import Trajectory

__all__ = ["band_matvec", "robust_smoothing", "smoothing_band", "smoothing_terms", "weighted_band"]


def smoothing_terms(smooth: tuple[tuple[int, Tensor], ...]) -> tuple[tuple[int, Smoothness], ...]:
    """The shared smoothness terms of smooth ((n, a_n (D,)), ...): (n, `Smoothness` whose residual is
    a_n * (n-th forward difference of q over time), (..., (T-n)*D)), ...)."""
    return tuple((n, Smoothness(1.0, 1.0 if n == 1 else None, 1.0 if n == 2 else None, dof_scale=a)) for n, a in smooth)


def smoothing_band(t_len: int, smooth: tuple[tuple[int, Tensor], ...], like: Tensor) -> Tensor:
    """Band of sum_n a_n^2 D_n^T D_n (D_n: n-th forward difference over T frames, per dof).
    -> (T, W+1, D) with W = the largest n (at least 1); entry [t, k] is the (t, t-k) block's diagonal."""
    return weighted_band(t_len, tuple((n, a.square().expand(max(t_len - n, 0), -1)) for n, a in smooth), like)


def robust_smoothing(
    obj: Trajectory, q: Tensor, derivatives: bool = True
) -> tuple[Tensor, Tensor | None, tuple[tuple[int, Tensor], ...]]:
    """The smoothing prior under the robust loss `obj.smooth_loss` (scale `obj.smooth_scale` prior std):
    q (B, T, D) -> energy (B, T) (each residual at its middle frame), gradient (B, T, D), and the
    Gauss-Newton weights ((n, w a_n^2 (B, T-n, D)), ...) with w the IRLS weight of each residual;
    without `derivatives`, the energy only (gradient None, no weights)."""
    rho, drho = robust_loss(obj.smooth_loss), robust_loss_derivative(obj.smooth_loss)
    b_len, t_len, d = q.shape
    energy = q.new_zeros(b_len, t_len)
    grad = torch.zeros_like(q) if derivatives else None
    weights = []
    ev = PoseEval(q, q.new_zeros(0), q.new_zeros(0), q.new_zeros(0))
    for (n, a), (_, term) in zip(obj.smooth, obj.smooth_terms):
        if t_len <= n:
            continue
        r = term.residual(ev).unflatten(-1, (t_len - n, d))  # (B, T-n, D) in prior std units
        s = r.square()
        e = 0.5 * rho(s, obj.smooth_scale).sum(-1)
        energy = energy + torch.nn.functional.pad(e, ((n + 1) // 2, n - (n + 1) // 2))
        if grad is None:
            continue
        c = drho(s, obj.smooth_scale) * a.square()
        grad = grad + difference_transpose(n, c * torch.diff(q, n=n, dim=-2))
        weights.append((n, c))
    return energy, grad, tuple(weights)
