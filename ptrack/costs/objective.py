"""The objective: weighted sum of cost terms with a per-term breakdown."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import NamedTuple

import torch
from torch import Tensor

from ptrack.costs.base import CostTerm, LeastSquaresMixin, PoseEval, PoseJacobian, RobustMixin
from ptrack.errors import InputError

# ---------------------------------------------------------------------------------------------
# Objective.


class ObjectiveValue(NamedTuple):
    """total (...,) weighted energy; terms: name -> weighted energy (...,), summing to total."""

    total: Tensor
    terms: dict[str, Tensor]


def _same_batch(what: str, shapes: Mapping[str, torch.Size]) -> None:
    if len(set(shapes.values())) > 1:
        got = {name: tuple(s) for name, s in shapes.items()}
        raise InputError(
            f"Objective terms disagree on the batch shape of their {what}: {got} "
            f"(trajectory terms need JointLimits(time_axis=True))"
        )


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
            if not all(callable(getattr(term, m, None)) for m in ("residual", "energy", "robust_weights")):
                raise InputError(f"Objective term {name!r} is not a cost term: {type(term).__name__}")
        weights = dict(self.weights or {})
        unknown = sorted(set(weights) - set(self.terms))
        if unknown:
            raise InputError(f"Objective weights name unknown terms {unknown}; terms are {sorted(self.terms)}")
        for name, value in weights.items():
            if not (math.isfinite(float(value)) and float(value) >= 0):
                raise InputError(f"Objective weight {name!r} must be finite and >= 0, got {value!r}")
        object.__setattr__(self, "terms", MappingProxyType(dict(self.terms)))
        object.__setattr__(self, "weights", MappingProxyType({n: float(weights.get(n, 1.0)) for n in self.terms}))

    @property
    def _weights(self) -> Mapping[str, float]:
        """weights as `__post_init__` stored them: one per term."""
        assert self.weights is not None
        return self.weights

    def __call__(self, ev: PoseEval) -> ObjectiveValue:
        """ev -> ObjectiveValue(total (...,), terms {name: w * energy (...,)})."""
        parts = {name: self._weights[name] * term.energy(ev) for name, term in self.terms.items()}
        _same_batch("energy", {name: e.shape for name, e in parts.items()})
        return ObjectiveValue(torch.stack(list(parts.values())).sum(0), parts)

    def residuals(self, ev: PoseEval) -> Tensor:
        """ev -> (..., M_total): each term's whitened residual times sqrt(weight), concatenated.

        For least-squares terms 0.5 |r|^2 is their share of the total. Robust terms return the plain
        whitened residual: a Gauss-Newton / IRLS step uses diag(robust_weights(ev)) as the per-row
        weight (J^T W J dq = -J^T W r), which matches the gradient of the robust total.
        """
        parts = {n: math.sqrt(self._weights[n]) * t.residual(ev) for n, t in self.terms.items()}
        _same_batch("residuals", {name: r.shape[:-1] for name, r in parts.items()})
        return torch.cat(list(parts.values()), dim=-1)

    def jacobian(self, ev: PoseEval, jac: PoseJacobian) -> Tensor:
        """ev, jac (its fields' derivatives w.r.t. q, D last) -> (..., M_total, D): the Jacobian of
        `residuals`. Terms with a `jacobian` method give theirs in closed form; the others are
        differentiated by forward-mode autograd through their residual alone (no kinematics)."""
        return self._jacobian_of(list(self.terms), ev, jac)

    def _jacobian_of(
        self, names: list[str], ev: PoseEval, jac: PoseJacobian, given: Mapping[str, Tensor] | None = None
    ) -> Tensor:
        """The Jacobian rows of the terms `names`, in order; `given`: rows already made (times sqrt(weight))."""
        parts = []
        for name in names:
            if given is not None and name in given:
                parts.append(given[name])
                continue
            term = self.terms[name]
            closed = getattr(term, "jacobian", None)
            j = None
            if closed is not None:
                try:
                    j = closed(ev, jac)
                except NotImplementedError:
                    j = None
            if j is None:
                j = _forward_jacobian(term, ev, jac)
            parts.append(math.sqrt(self._weights[name]) * j)
        return torch.cat(parts, dim=-2)

    def linearize(
        self, ev: PoseEval, jac: PoseJacobian, fold: bool = False
    ) -> tuple[Tensor, Tensor, Tensor, Tensor] | tuple[Tensor, Tensor, Tensor, Tensor, Tensor | None, Tensor | None]:
        """`residuals`, `jacobian`, `robust_weights` and the total energy at once, each least-squares
        term's residual computed once: -> (..., M), (..., M, D), (..., M), (...,).

        With `fold`, least-squares terms whose Jacobian is mostly zeros are not stacked as rows but
        folded into the Gauss-Newton normal equations (`ptrack.optim.solvers.Linearization`): terms with a
        `diagonal_jacobian` (joint limits, pose priors: one row per dof) and terms with a
        `gauss_newton(ev, jac) -> (energy, J^T J, J^T r)` (body collision: pairs apart give nothing).
        Their share comes back as two more outputs, fold_h (..., D, D) and fold_g (..., D); the
        stacked rows hold the other terms only. A least-squares term with a `residual_jacobian(ev, jac) ->
        (residual, jacobian)` (its two from shared work, e.g. one ray-to-model distance) gives both at once."""
        rs, ws, es, stacked = [], [], [], []
        given: dict[str, Tensor] = {}  # Jacobians that came with their residual
        diag_h: list[Tensor] = []  # folded terms' shares: J^T J diagonals (..., D), full (..., D, D), J^T r
        full_h: list[Tensor] = []
        fold_gs: list[Tensor] = []
        for name, term in self.terms.items():
            w = self._weights[name]
            if fold:
                part = _folded(term, ev, jac)
                if part is not None:
                    energy, h, g, diagonal = part
                    es.append(w * energy)
                    (diag_h if diagonal else full_h).append(w * h)
                    fold_gs.append(w * g)
                    continue
            stacked.append(name)
            r = None
            both = getattr(term, "residual_jacobian", None)
            if both is not None:
                try:
                    r, j = both(ev, jac)
                    given[name] = math.sqrt(w) * j
                except NotImplementedError:
                    r = None
            if r is None:
                r = term.residual(ev)
            rs.append(math.sqrt(w) * r)
            if isinstance(term, LeastSquaresMixin):
                ws.append(torch.ones_like(r))
                es.append(w * term.energy_of(r))
            elif isinstance(term, RobustMixin):  # weights and energy from the residual just made
                weights, energy_ = term.weights_and_energy(r)
                ws.append(weights)
                es.append(w * energy_)
            else:
                ws.append(term.robust_weights(ev))
                es.append(w * term.energy(ev))
        _same_batch("residuals", {name: r.shape[:-1] for name, r in zip(stacked, rs)})
        energy = torch.stack(es).sum(0)
        if not fold:
            return torch.cat(rs, -1), self._jacobian_of(stacked, ev, jac, given), torch.cat(ws, -1), energy
        fold_h = _fold_sum(diag_h, full_h)
        fold_g = _sum(fold_gs) if fold_gs else None
        if not rs:  # every term folded: no stacked rows at all
            empty = ev.q.new_zeros(*ev.q.shape[:-1], 0)
            return empty, empty[..., None].expand(*empty.shape, ev.q.shape[-1]), empty, energy, fold_h, fold_g
        jacobian = self._jacobian_of(stacked, ev, jac, given)
        return torch.cat(rs, -1), jacobian, torch.cat(ws, -1), energy, fold_h, fold_g

    def robust_weights(self, ev: PoseEval) -> Tensor:
        """ev -> (..., M_total) IRLS weights rho'(s) aligned with `residuals` (1 for l2 terms)."""
        parts = {name: term.robust_weights(ev) for name, term in self.terms.items()}
        _same_batch("robust weights", {name: w.shape[:-1] for name, w in parts.items()})
        return torch.cat(list(parts.values()), dim=-1)


def _sum(parts: list[Tensor]) -> Tensor:
    """The sum of equally shaped tensors (at least one), added in list order into a new tensor."""
    out = parts[0].clone()
    for p in parts[1:]:
        out += p
    return out


def _fold_sum(diagonals: list[Tensor], fulls: list[Tensor]) -> Tensor | None:
    """Folded terms' J^T J shares -> their sum (..., D, D), None if there are none: diagonals (..., D) are
    added onto the diagonal of the full ones (..., D, D) in place, without a D x D matrix each."""
    if not fulls:
        return torch.diag_embed(_sum(diagonals)) if diagonals else None
    h = _sum(fulls)
    if diagonals:
        h.diagonal(dim1=-2, dim2=-1).add_(_sum(diagonals))
    return h


def _folded(term, ev: PoseEval, jac: PoseJacobian) -> tuple[Tensor, Tensor, Tensor, bool] | None:
    """A term's share of the (IRLS) normal equations, if it can give it without stacking rows:
    -> (energy (...,), h, g (..., D), diagonal) with h (..., D) (the diagonal of J^T W J) when
    `diagonal`, else (..., D, D); None when the term must be stacked."""
    least_squares = isinstance(term, LeastSquaresMixin)
    diagonal = getattr(term, "diagonal_jacobian", None)
    if diagonal is not None:
        try:
            jd = diagonal(ev)
        except NotImplementedError:
            jd = None
        if jd is not None:
            r = term.residual(ev)
            if least_squares:
                return term.energy_of(r), jd.square(), jd * r, True
            w = term.robust_weights(ev)
            return term.energy(ev), w * jd.square(), w * jd * r, True
    gauss_newton = getattr(term, "gauss_newton", None)
    if gauss_newton is not None and least_squares:
        return (*gauss_newton(ev, jac), False)
    return None


def _forward_jacobian(term: CostTerm, ev: PoseEval, jac: PoseJacobian) -> Tensor:
    """d term.residual / d q by `torch.func.jvp` over the D columns (e_d, jac[..., d]) of ev's fields."""
    q = ev.q
    d = q.shape[-1]
    eye = torch.eye(d, dtype=q.dtype, device=q.device).reshape(d, *([1] * (q.ndim - 1)), d).expand(d, *q.shape)
    tangents = (eye, jac.joints.movedim(-1, 0), jac.pixels.movedim(-1, 0), jac.depth.movedim(-1, 0))

    def f(q_, joints, pixels, depth):
        return term.residual(PoseEval(q_, joints, pixels, depth, ev.joint_pixels))

    def column(tq, tj, tp, td):
        return torch.func.jvp(f, (q, ev.joints, ev.pixels, ev.depth), (tq, tj, tp, td))[1]

    return torch.func.vmap(column)(*tangents).movedim(0, -1)
