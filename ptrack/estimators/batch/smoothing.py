"""The smoothing prior of the batch objective (`method: batch`, DiFranco, Cham & Rehg 2001, eq. 3): one shared
`ptrack.costs.Smoothness` term per difference order (the trajectory's forward differences times a per-dof scale,
under the robust loss `batch.smooth_loss`), which gives its energy per frame, gradient and IRLS weights; their
band in the normal equations is assembled by `ptrack.optim.trajectory`. Shapes: T frames, D dofs, W the band's
width (the highest difference order)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ptrack.costs import PoseEval, Smoothness
from ptrack.optim.trajectory import weighted_band

if TYPE_CHECKING:
    from ptrack.estimators.batch.objective import Trajectory


def smoothing_terms(
    smooth: tuple[tuple[int, Tensor], ...], loss: str = "l2", scale: float = 1.0
) -> tuple[tuple[int, Smoothness], ...]:
    """The shared smoothness terms of smooth ((n, a_n (D,)), ...): (n, `Smoothness` whose residual is
    a_n * (n-th forward difference of q over time), (..., (T-n)*D), under the robust `loss` at `scale`), ..."""
    return tuple(
        (n, Smoothness(1.0, 1.0 if n == 1 else None, 1.0 if n == 2 else None, dof_scale=a, loss=loss, scale=scale))
        for n, a in smooth
    )


def smoothing_band(t_len: int, terms: tuple[tuple[int, Smoothness], ...], like: Tensor) -> Tensor:
    """Band of the least-squares smoothing's Hessian sum_n c_n^2 D_n^T D_n (D_n: n-th forward difference over T
    frames, c_n (D,) each term's `difference_scales`): -> (T, W+1, D) with W = the largest n (at least 1);
    entry [t, k] is the (t, t-k) block's diagonal."""
    weights = tuple(
        (n, c.square().expand(max(t_len - n, 0), like.shape[-1]))
        for _, term in terms
        for n, c in term.difference_scales(like)
    )
    return weighted_band(t_len, weights, like)


def robust_smoothing(
    obj: Trajectory, q: Tensor, derivatives: bool = True
) -> tuple[Tensor, Tensor | None, tuple[tuple[int, Tensor], ...]]:
    """The smoothing prior's terms summed (`Smoothness.banded_gauss_newton`): q (B, T, D) -> energy (B, T) (each
    residual at its middle frame), gradient (B, T, D), and the Gauss-Newton weights ((n, w c_n^2 (B, T-n, D)), ...)
    with w the IRLS weight of each residual; without `derivatives`, the energy only (gradient None, no weights)."""
    energy = q.new_zeros(q.shape[:-1])
    grad = torch.zeros_like(q) if derivatives else None
    weights: list[tuple[int, Tensor]] = []
    ev = PoseEval(q, q.new_zeros(0), q.new_zeros(0), q.new_zeros(0))
    for _, term in obj.smooth_terms:
        part = term.banded_gauss_newton(ev, derivatives)
        energy = energy + part.energy
        if grad is not None and part.gradient is not None:
            grad = grad + part.gradient
        weights += part.weights
    return energy, grad, tuple(weights)
