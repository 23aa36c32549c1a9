"""The batch solve: the whole objective's Gauss-Newton linearisation on its block-banded normal equations, and
Levenberg-Marquardt over the trajectory (inside the joint-limit box with `batch.hard_limits`;
`ptrack.optim.solvers`)."""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import Tensor

from ptrack.estimators.batch.config import BatchMethodConfig
from ptrack.estimators.batch.objective import Trajectory, evaluate
from ptrack.optim.banded import BlockBanded
from ptrack.optim.solvers import BandedLinearization, BandedLMInfo, banded_levenberg_marquardt
from ptrack.optim.trajectory import weighted_band


def linearization(obj: Trajectory) -> Callable[[Tensor], BandedLinearization]:
    """q (B, T, D) -> `BandedLinearization` of the whole objective (smoothing on the band; with a
    robust smoothing loss, the band of its IRLS weights at q)."""
    band = obj.band[None]  # (1, T, W+1, D)

    def linearize(q: Tensor) -> BandedLinearization:
        terms, h, g, weights = evaluate(obj, q)
        assert h is not None and g is not None  # with_jacobian
        b = weighted_band(q.shape[1], weights, q) if weights else band  # robust: the IRLS weights' band
        lower = b[:, :, 1:]  # (B|1, T, W, D): [t, k-1] = block (t, t-k)
        h.diagonal(dim1=-2, dim2=-1).add_(b[:, :, 0])
        energy = torch.stack(list(terms.values())).sum(0).sum(-1)
        return BandedLinearization(BlockBanded(h, lower.to(q)), g, energy)

    return linearize


def solve_trajectory(
    obj: Trajectory, start: Tensor, bc: BatchMethodConfig, callback: Callable[[int, Tensor, Tensor], None] | None = None
) -> tuple[Tensor, BandedLMInfo]:
    """The whole objective's Levenberg-Marquardt from start (B, T, D), inside the joint-limit box where
    `obj.hard_limits` (`Trajectory.box`), with the `batch.*` settings bc (iterations, tol, damping)
    -> q (B, T, D), `BandedLMInfo`. The B starts share the objective: a trajectory that has stopped is
    not linearised again while the others go on."""
    lower, upper = obj.box()
    return banded_levenberg_marquardt(
        linearization(obj),
        start,
        lower,
        upper,
        max_iter=bc.iterations,
        tol=bc.tol,
        gtol=bc.tol * 1e-2,
        damping=bc.damping,
        callback=callback,
        shared=True,
    )
