"""A Gaussian mixture over the body's joint angles, measured on real CMU motion: a pose prior that knows which
angles go together.

The per-dof prior (`ptrack.body.pose_prior`) says how far each angle strays from its mean, one angle at a time.
It cannot say that a thigh raised behind goes with a trunk leaning forward, or that a knee bent far goes with a
raised thigh, and on real footage one view leaves exactly such readings open: a thigh's depth branch, the trunk's
lean along the camera ray. The two readings reproject alike, and the per-dof prior often prefers the one people
do not take (docs/notes/footage-history.md). A full-covariance mixture holds the correlations.

It ranks hypotheses; it does not move them: the kjs tracker adds its negative log-density, weighted by
`kjs.pose_mixture_weight`, to each mode's own frame cost (`ptrack.estimators.kjs.model.frame_evidence`), the
unary term of the best trajectory and of the modes' posterior weights.

`ptrack/data/cmu_pose_mixture.json` is made by `scripts/make_pose_mixture.py` from CMU clips, less the held-out
clips (`configs/clips/heldout_batch.txt`) and the check clips of `scripts/eval_synthetic_footage.py`. For a
skeleton with fewer dofs than the file (frozen hands, toes, wrists) each component is marginalised onto the dofs
the skeleton has (for a Gaussian: the covariance's rows and columns of those dofs).

    mix = pose_mixture(skeleton, dtype, device)   # None when the skeleton names none of the file's dofs
    nll = mix.nll(q)                              # q (..., D) radians -> (...,)

Shapes: C components, D the skeleton's dofs, M of them in the mixture."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ptrack.errors import InputError
from ptrack.package_data import data_file

if TYPE_CHECKING:
    from ptrack.body.skeleton import Skeleton


def pose_mixture_path() -> Path:
    """The shipped CMU pose mixture file."""
    return data_file("cmu_pose_mixture.json")


@dataclass(frozen=True)
class MixtureTable:
    """A mixture as its file holds it: dofs (M,) names, weights (C,), means (C, M) radians, covariances (C, M, M)
    radians squared."""

    dofs: tuple[str, ...]
    weights: Tensor
    means: Tensor
    covariances: Tensor


def read_pose_mixture(path: str | Path | None = None) -> MixtureTable:
    """A pose mixture JSON file -> its table (float64).

    Layout: {"dofs": [M names], "weights": [C], "means": [C][M], "covariances": [C][M (M + 1) / 2] (each lower
    triangle row by row), ...provenance keys}."""
    p = Path(path) if path is not None else pose_mixture_path()
    if not p.is_file():
        raise FileNotFoundError(f"pose mixture file not found: {p}")
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
        dofs = tuple(str(n) for n in doc["dofs"])
        weights = torch.tensor(doc["weights"], dtype=torch.float64)
        means = torch.tensor(doc["means"], dtype=torch.float64)
        tril = torch.tensor(doc["covariances"], dtype=torch.float64)
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as e:
        raise InputError(f"pose mixture file {p} must be JSON with dofs, weights, means, covariances ({e})") from None
    m, c = len(dofs), weights.shape[0]
    if weights.ndim != 1 or means.shape != (c, m) or tril.shape != (c, m * (m + 1) // 2):
        raise InputError(f"pose mixture file {p}: {c} weights, means (C, M) and lower triangles (C, M(M+1)/2) expected")
    rows, cols = torch.tril_indices(m, m)
    cov = torch.zeros(c, m, m, dtype=torch.float64)
    cov[:, rows, cols] = tril
    cov[:, cols, rows] = tril
    if not (torch.isfinite(weights).all() and torch.isfinite(means).all() and (weights > 0).all()):
        raise InputError(f"pose mixture file {p}: weights must be positive and every number finite")
    return MixtureTable(dofs, weights / weights.sum(), means, cov)


@dataclass(frozen=True)
class PoseMixture:
    """A mixture on some of a skeleton's dofs: index (M,) the dofs it covers, log_weight (C,) with each
    component's log normaliser folded in, mean (C, M), chol (C, M, M) Cholesky factors of the covariances."""

    index: Tensor
    log_weight: Tensor
    mean: Tensor
    chol: Tensor

    def nll(self, q: Tensor) -> Tensor:
        """Negative log-density of poses q (..., D) radians -> (...,). Each angle's difference from a
        component's mean is wrapped into [-pi, pi), so q and q + 2 pi cost the same."""
        x = q.index_select(-1, self.index)[..., None, :]  # (..., 1, M)
        d = torch.remainder(x - self.mean + math.pi, 2 * math.pi) - math.pi  # (..., C, M)
        z = torch.linalg.solve_triangular(self.chol, d[..., None], upper=False)[..., 0]  # (..., C, M)
        return -torch.logsumexp(self.log_weight - 0.5 * z.square().sum(-1), -1)


def pose_mixture(
    sk: Skeleton, dtype: torch.dtype, device: torch.device, path: str | Path | None = None
) -> PoseMixture | None:
    """The mixture of `path` (default: the shipped CMU one) on `sk`'s dofs of the same names, marginalised onto
    them; None when `sk` names none of them (a skeleton that is not CMU's)."""
    table = read_pose_mixture(path)
    have = [(i, table.dofs.index(n)) for i, n in enumerate(sk.dof_names) if n in table.dofs]
    if not have:
        return None
    ours, theirs = (torch.tensor(x) for x in zip(*have))
    cov = table.covariances[:, theirs][:, :, theirs]
    chol = torch.linalg.cholesky(cov)
    m = len(have)
    log_norm = torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1) + 0.5 * m * math.log(2 * math.pi)
    return PoseMixture(
        ours.to(device),
        (torch.log(table.weights) - log_norm).to(dtype=dtype, device=device),
        table.means[:, theirs].to(dtype=dtype, device=device),
        chol.to(dtype=dtype, device=device),
    )


__all__ = ["MixtureTable", "PoseMixture", "pose_mixture", "pose_mixture_path", "read_pose_mixture"]
