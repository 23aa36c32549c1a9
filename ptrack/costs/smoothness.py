"""The smoothing prior on a trajectory (DiFranco, Cham & Rehg 2001, eq. 3): `Smoothness`, scaled finite differences
of the poses (or joint positions) over time under a robust loss, with what a trajectory solver needs of it beside
the residual: each frame's energy, the gradient, and the IRLS weights of its banded Gauss-Newton Hessian
(`Smoothness.banded_gauss_newton`); and the forward-difference operator's coefficients and transpose.

Shapes: T frames; E entries per frame (D dofs, or J joints x 3); n the difference order (1 velocity, 2
acceleration). D_n is the n-th forward difference over time: (D_n x)[i] = sum_j coef_n[j] x[i + j], i < T - n.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import ClassVar, NamedTuple

import torch
from torch import Tensor

from ptrack.checks import as_float_tensor
from ptrack.costs.base import PoseEval, RobustMixin, check_positive, robust_loss, shape_of
from ptrack.errors import InputError


def difference_coefficients(n: int) -> list[float]:
    """The n-th forward difference's coefficients: (D_n x)[i] = sum_j coef[j] x[i + j]. -> n+1 floats."""
    return [float((-1) ** (n - j) * math.comb(n, j)) for j in range(n + 1)]


def difference_transpose(n: int, v: Tensor, dim: int = -2) -> Tensor:
    """D_n^T v over the time axis `dim` (negative): v (..., T-n, ...) -> (..., T, ...)."""
    coef = difference_coefficients(n)
    tail = [0, 0] * (-dim - 1)  # `pad` counts from the last axis
    return sum(
        (coef[j] * torch.nn.functional.pad(v, (*tail, j, n - j)) for j in range(n + 1)),
        torch.zeros((), dtype=v.dtype, device=v.device),
    )


class BandedGaussNewton(NamedTuple):
    """`Smoothness.banded_gauss_newton`'s result, x the trajectory the term reads ((..., T, D) or (..., T, J, 3)).

    energy (..., T): each residual's energy at its middle frame (residual i of order n at frame i + ceil(n/2));
    summed, the term's `energy`. gradient: d energy / d x, x's shape (None without derivatives). weights ((n,
    c_n^2 w_n (..., T-n, E...)), ...): the Gauss-Newton Hessian J^T W J = sum_n D_n^T diag(weights_n) D_n, c_n the
    order's scale (`Smoothness.difference_scales`) and w_n = rho'(r^2) its IRLS weights; it couples each entry
    only with itself over time, a band (`ptrack.optim.trajectory.weighted_band`). Empty without derivatives."""

    energy: Tensor
    gradient: Tensor | None
    weights: tuple[tuple[int, Tensor], ...]


@dataclass(frozen=True, eq=False)
class Smoothness(RobustMixin):
    """Finite-difference velocity and acceleration prior on a trajectory, each residual entry under the robust
    `loss` at `scale` (its own units: prior standard deviations; l2, the default, is the plain Gaussian prior).

    on="q": x = ev.q (..., T, D), dof_scale (D,); on="joints": x = ev.joints (..., T, J, 3),
    dof_scale (J,). residual = concat of (x[t+1] - x[t]) / (dt sigma_velocity) over t < T-1 and
    (x[t+1] - 2x[t] + x[t-1]) / (dt^2 sigma_acceleration), each times dof_scale and flattened:
    (..., (T-1)*E + (T-2)*E) for E entries per frame. A None sigma drops that part. energy (...,) =
    0.5 sum rho(r_i^2, scale). The residual is linear in x (no offset): each part's Jacobian is c_n D_n,
    c_n = dof_scale / (dt^n sigma_n) (`difference_scales`), whose normal equations are banded
    (`banded_gauss_newton`); under l2 they are constant and the gradient is that Hessian times x.
    """

    dt: float
    sigma_velocity: float | None = None
    sigma_acceleration: float | None = None
    on: str = "q"
    dof_scale: Tensor | None = None
    loss: str = "l2"
    scale: float = 1.0
    _group: ClassVar[int] = 1

    def __post_init__(self) -> None:
        check_positive("Smoothness.dt", self.dt)
        for name in ("sigma_velocity", "sigma_acceleration"):
            if getattr(self, name) is not None:
                check_positive(f"Smoothness.{name}", getattr(self, name))
        if self.on not in ("q", "joints"):
            raise InputError(f"Smoothness.on must be 'q' or 'joints', got {self.on!r}")
        if self.dof_scale is not None:
            scale = as_float_tensor(self.dof_scale, "dof_scale")
            if scale.ndim != 1 or not (torch.isfinite(scale).all() and (scale >= 0).all()):
                raise InputError(f"Smoothness.dof_scale must be a finite, >= 0 vector, got shape {shape_of(scale)}")
            object.__setattr__(self, "dof_scale", scale)
        robust_loss(self.loss)
        check_positive("Smoothness.scale", self.scale)

    def _orders(self) -> list[tuple[int, float]]:
        """[(n, sigma_n), ...] of the parts kept, velocity first."""
        both = ((1, self.sigma_velocity), (2, self.sigma_acceleration))
        return [(n, sigma) for n, sigma in both if sigma is not None]

    def _trajectory(self, ev: PoseEval) -> tuple[Tensor, int]:
        """The trajectory the term reads, checked: -> x and its per-frame ndim plus one (the time axis is -that)."""
        x, n = (ev.q, 2) if self.on == "q" else (ev.joints, 3)
        if x.ndim < n or (n == 3 and x.shape[-1] != 3):
            raise InputError(
                f"Smoothness(on={self.on!r}) needs a trajectory (..., T, {'D' if n == 2 else 'J, 3'}), "
                f"got {shape_of(x)}"
            )
        if self.dof_scale is not None and self.dof_scale.shape[0] != x.shape[-n + 1]:
            raise InputError(
                f"Smoothness.dof_scale {shape_of(self.dof_scale)} does not match {self.on} of shape {shape_of(x)}"
            )
        return x, n

    def residual(self, ev: PoseEval) -> Tensor:
        """ev.q (..., T, D) or ev.joints (..., T, J, 3) -> (..., M)."""
        x, n = self._trajectory(ev)
        parts = [c * torch.diff(x, n=order, dim=-n) for order, c in self.difference_scales(x)]
        if not parts:
            return x.new_zeros(x.shape[:-n] + (0,))
        return torch.cat([p.flatten(-n) for p in parts], dim=-1)

    def difference_scales(self, like: Tensor) -> tuple[tuple[int, Tensor], ...]:
        """((n, c_n), ...) per order kept: its residual is c_n D_n x, c_n = dof_scale / (dt^n sigma_n) broadcast
        against one frame of x ((D,) or (J, 1); a 0-d tensor without dof_scale), in like's dtype and device."""
        scale = like.new_ones(()) if self.dof_scale is None else self.dof_scale.to(like)
        if self.on == "joints" and self.dof_scale is not None:
            scale = scale[:, None]
        return tuple((n, scale / (self.dt**n * sigma)) for n, sigma in self._orders())

    def banded_gauss_newton(self, ev: PoseEval, derivatives: bool = True) -> BandedGaussNewton:
        """Each frame's energy, the gradient and the Gauss-Newton weights of the band (`BandedGaussNewton`) at
        the trajectory ev reads; without `derivatives` the energy only."""
        x, n_ax = self._trajectory(ev)
        t_len = x.shape[-n_ax]
        energy = x.new_zeros(x.shape[: x.ndim - n_ax + 1])  # (..., T)
        grad = torch.zeros_like(x) if derivatives else None
        weights = []
        for order, c in self.difference_scales(x):
            if t_len <= order:
                continue
            diff = torch.diff(x, n=order, dim=-n_ax)
            r = c * diff  # (..., T-n, E...)
            flat = r.flatten(-n_ax + 1) if n_ax == 3 else r  # (..., T-n, E): one residual frame per row
            if grad is None:
                e = self.energy_of(flat)
            else:
                w, e = self.weights_and_energy(flat)
                cw = w.reshape(r.shape) * c.square()  # c_n^2 w_n
                grad = grad + difference_transpose(order, cw * diff, dim=-n_ax)  # J^T W r = D_n^T c_n^2 w_n D_n x
                weights.append((order, cw))
            energy = energy + torch.nn.functional.pad(e, ((order + 1) // 2, order - (order + 1) // 2))
        return BandedGaussNewton(energy, grad, tuple(weights))

    def orders(self) -> tuple[tuple[int, Smoothness], ...]:
        """((n, this prior with its order-n part only), ...), velocity first: the energy is their sum."""
        return tuple(
            (
                n,
                dataclasses.replace(self, sigma_acceleration=None)
                if n == 1
                else dataclasses.replace(self, sigma_velocity=None),
            )
            for n, _ in self._orders()
        )

    def select(self, entries: Tensor) -> Smoothness:
        """This prior on the entries `entries` (E',) long of each frame only (dofs on "q", joints on "joints"):
        the same scales, read from an x holding just those entries."""
        if self.dof_scale is None:
            return self
        return dataclasses.replace(self, dof_scale=self.dof_scale.index_select(0, entries.to(self.dof_scale.device)))
