"""Cost-term plumbing: the `PoseEval` record terms read, robust losses, construction-time checks,
and the least-squares / robust mixins."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar, NamedTuple, Protocol

import torch
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


class PoseJacobian(NamedTuple):
    """Derivatives of a `PoseEval`'s fields w.r.t. the pose q, the dof axis last: joints (..., J, 3, D),
    pixels (..., K, 2, D), depth (..., K, D) (d q / d q is the identity). Terms with a `jacobian(ev,
    jac) -> (..., M, D)` method use it to give the Jacobian of their residual in closed form;
    `Objective.jacobian` pushes it through the others by forward-mode autograd."""

    joints: Tensor
    pixels: Tensor
    depth: Tensor


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

ROBUST_LOSSES: tuple[str, ...] = tuple(_LOSSES)  # the names `robust_loss` knows


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


def check_positive(name: str, value) -> None:
    t = torch.as_tensor(value, dtype=torch.float64)
    if not (torch.isfinite(t).all() and (t > 0).all()):
        raise InputError(f"{name} must be finite and > 0, got {value!r}")


def shape_of(x: Tensor) -> tuple[int, ...]:
    return tuple(x.shape)


def check_index(name: str, index, size: int, of: str) -> Tensor:
    """`index` as a 1-D long tensor of `size` entries (an index into another axis; `of` says what it must match
    in the message); InputError otherwise."""
    k = torch.as_tensor(index)
    if k.ndim != 1 or k.is_floating_point() or k.shape[0] != size:
        raise InputError(f"{name} must be ({size},) indices to match {of}, got {shape_of(k)}")
    return k.long()


def check_times(name: str, times) -> Tensor:
    t = torch.as_tensor(times)
    if t.ndim != 1 or t.is_floating_point() or t.dtype == torch.bool:
        raise InputError(f"{name}.times must be a 1-D integer tensor (F,), got {t.dtype} {shape_of(t)}")
    if (t < 0).any():
        raise InputError(f"{name}.times must be >= 0, got {t.tolist()}")
    return t.long()


def check_mask(name: str, mask, shape: tuple[int, ...]) -> Tensor:
    if mask is None:
        return torch.ones(shape, dtype=torch.bool)
    m = torch.as_tensor(mask)
    if m.dtype != torch.bool or shape_of(m) != shape:
        raise InputError(f"{name} must be a bool tensor of shape {shape}, got {m.dtype} {shape_of(m)}")
    return m


def check_frame_count(name: str, x: Tensor, times_max: int, time_dim: int) -> None:
    if x.ndim < -time_dim or x.shape[time_dim] <= times_max:
        raise InputError(
            f"{name}: keyframe time {times_max} is outside a trajectory of shape {shape_of(x)} (time axis {time_dim})"
        )


# ---------------------------------------------------------------------------------------------
# Term plumbing.


class CostTerm(Protocol):
    """What an `Objective` needs from a term; every term below satisfies it."""

    def residual(self, ev: PoseEval) -> Tensor: ...

    def energy(self, ev: PoseEval) -> Tensor: ...

    def robust_weights(self, ev: PoseEval) -> Tensor: ...


class LeastSquaresMixin:
    """Mixin: energy = 0.5 |r|^2 and IRLS weights all one."""

    if TYPE_CHECKING:  # provided by the term that mixes this in

        def residual(self, ev: PoseEval) -> Tensor: ...

    def energy(self, ev: PoseEval) -> Tensor:
        """ev -> (...,) = 0.5 * sum of squared residual entries."""
        return self.energy_of(self.residual(ev))

    def energy_of(self, r: Tensor) -> Tensor:
        """`energy` (...,) of the residual r (..., M) already computed (e.g. one frame's rows per leading index)."""
        return 0.5 * r.square().sum(-1)

    def robust_weights(self, ev: PoseEval) -> Tensor:
        """ev -> (..., M) of ones (no robust loss)."""
        return torch.ones_like(self.residual(ev))


class RobustMixin:
    """Mixin: residual entries come in consecutive groups of `_group`; rho sees |r_group|^2."""

    _group: ClassVar[int]
    loss: str
    scale: float

    if TYPE_CHECKING:  # provided by the term that mixes this in

        def residual(self, ev: PoseEval) -> Tensor: ...

    def _squared_of(self, r: Tensor) -> Tensor:
        return r.unflatten(-1, (-1, self._group)).square().sum(-1)

    def _weights_of(self, r: Tensor, s: Tensor) -> Tensor:
        w = robust_loss_derivative(self.loss)(s, self.scale)
        return w.unsqueeze(-1).expand(*w.shape, self._group).reshape(r.shape)

    def _energy_of(self, s: Tensor) -> Tensor:
        return 0.5 * robust_loss(self.loss)(s, self.scale).sum(-1)

    def energy(self, ev: PoseEval) -> Tensor:
        """ev -> (...,) = 0.5 * sum over groups of rho(|r_group|^2, scale)."""
        return self.energy_of(self.residual(ev))

    def energy_of(self, r: Tensor) -> Tensor:
        """`energy` (...,) of the residual r (..., M) already computed (any leading dims: e.g. (..., T, M / T)
        a trajectory's residual split by frame gives each frame's energy)."""
        return self._energy_of(self._squared_of(r))

    def robust_weights(self, ev: PoseEval) -> Tensor:
        """ev -> (..., M): rho'(|r_group|^2) repeated over each group's entries (IRLS weights)."""
        r = self.residual(ev)
        return self._weights_of(r, self._squared_of(r))

    def weights_and_energy(self, r: Tensor) -> tuple[Tensor, Tensor]:
        """`robust_weights` (..., M) and `energy` (...,) of the residual r (..., M) already computed."""
        s = self._squared_of(r)
        return self._weights_of(r, s), self._energy_of(s)


@dataclass(frozen=True, eq=False)
class Robust(RobustMixin):
    """A least-squares term under a robust loss, entry by entry (theseus' residual, weight and loss as three
    pieces): the same residual (..., M) and Jacobian, energy 0.5 sum_i rho(r_i^2, scale), IRLS weights
    rho'(r_i^2). For a term whose residual entries are each one measurement (`RaySilhouette`'s samples)."""

    term: CostTerm
    loss: str = "cauchy"
    scale: float = 1.0
    _group: ClassVar[int] = 1

    def __post_init__(self) -> None:
        robust_loss(self.loss)
        check_positive("Robust.scale", self.scale)

    def residual(self, ev: PoseEval) -> Tensor:
        """The term's residual (..., M)."""
        return self.term.residual(ev)

    def jacobian(self, ev: PoseEval, jac: PoseJacobian) -> Tensor:
        """The term's closed-form Jacobian (..., M, D); NotImplementedError where it has none (the `Objective`
        then differentiates the residual)."""
        closed = getattr(self.term, "jacobian", None)
        if closed is None:
            raise NotImplementedError(f"{type(self.term).__name__} has no closed-form Jacobian")
        return closed(ev, jac)

    def residual_jacobian(self, ev: PoseEval, jac: PoseJacobian) -> tuple[Tensor, Tensor]:
        """The term's `residual_jacobian`; NotImplementedError where it has none."""
        both = getattr(self.term, "residual_jacobian", None)
        if both is None:
            raise NotImplementedError(f"{type(self.term).__name__} has no residual_jacobian")
        return both(ev, jac)
