"""Joint limits: which box each dof lives in, where it comes from, and how angles wrap into it.

Three sources (config `model.limits`):

    data  per-dof bounds measured on real CMU motion (`ptrack/data/cmu_limits.json`, made by
          `scripts/make_limits.py`): the smallest arc of the circle that holds every captured value of
          the dof, widened by a margin. The CMU ASF files' own limits are contradicted by the very
          motions recorded with them (on the 36 CMU clips in ../shared the ground truth lies outside
          them in 0.9-11.1% of the reduced model's limited dof-frames, by up to 105 degrees), so
          these are the default. Dofs the file does not name keep the model's limits.
    asf   the model file's own limits (ASF `limits`, URDF `<limit>`).
    none  no limits at all.

A rotational dof is periodic: q and q + 2 pi give the same pose. An angular limit [lower, upper]
is therefore an arc (upper - lower < 2 pi), and a pose is inside it when some 2 pi shift of the
angle is; `wrap_to_limits` picks that representative without changing the pose. Units: radians
(metres for translations, which are never limited by the data file).
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from ptrack.errors import InputError
from ptrack.package_data import data_file

if TYPE_CHECKING:
    from ptrack.body.skeleton import Skeleton

log = logging.getLogger(__name__)

SOURCES = ("data", "asf", "none")
TAU = 2.0 * math.pi


def data_limits_path() -> Path:
    """The shipped file of CMU data-derived limits."""
    return data_file("cmu_limits.json")


def read_limits_file(path: str | Path | None = None) -> dict[str, tuple[float, float]]:
    """{dof name: (lower, upper) radians} from a limits JSON file (`null` bounds = unlimited: +-inf).

    Layout: {"limits_deg": {"lfemur.rx": [lower, upper] | null, ...}, ...provenance keys}."""
    p = Path(path) if path is not None else data_limits_path()
    if not p.is_file():
        raise FileNotFoundError(f"joint limits file not found: {p}")
    try:
        raw = json.loads(p.read_text(encoding="utf-8"))
        table = raw["limits_deg"]
    except (json.JSONDecodeError, KeyError, TypeError) as e:
        raise InputError(f"joint limits file {p} must be JSON with a 'limits_deg' mapping ({e})") from None
    out: dict[str, tuple[float, float]] = {}
    for name, bounds in table.items():
        if bounds is None:
            out[name] = (-math.inf, math.inf)
            continue
        if (
            not isinstance(bounds, list)
            or len(bounds) != 2
            or not all(isinstance(b, (int, float)) for b in bounds)
            or not bounds[0] <= bounds[1]
        ):
            raise InputError(f"joint limits file {p}: {name!r} must be [lower, upper] degrees or null, got {bounds!r}")
        out[name] = (math.radians(bounds[0]), math.radians(bounds[1]))
    return out


def with_limits(sk: Skeleton, source: str, path: str | Path | None = None) -> Skeleton:
    """`sk` with the joint limits of `source` ("data", "asf" or "none"); see the module docstring.

    For "data", dofs named in the file get its bounds and the others keep `sk`'s own; `path`
    replaces the shipped file.
    """
    if source not in SOURCES:
        raise InputError(f"joint limits source must be one of {', '.join(SOURCES)}, got {source!r}")
    if source == "asf":
        return sk
    if source == "none":
        return replace(sk, lower=np.full(sk.num_dofs, -math.inf), upper=np.full(sk.num_dofs, math.inf))
    table = read_limits_file(path)
    lower, upper = sk.lower.copy(), sk.upper.copy()
    hits = 0
    for i, name in enumerate(sk.dof_names):
        if name in table:
            lower[i], upper[i] = table[name]
            hits += 1
    if hits == 0:
        log.warning("no data-derived joint limits name a dof of %r; it keeps its own limits", sk.name)
    return replace(sk, lower=lower, upper=upper)


def wrap_to_limits(q: Tensor, lower: Tensor, upper: Tensor, angular: Tensor) -> Tensor:
    """The same pose with each limited angle shifted by a multiple of 2 pi to lie nearest its arc
    (within pi of the arc's centre, so inside an arc that spans 2 pi or more).

    q: (..., D); lower, upper: (D,); angular: (D,) bool (periodic dofs). Angles without two finite
    bounds and translations are returned unchanged. -> (..., D)
    """
    lower, upper = lower.to(q), upper.to(q)
    angular = angular.to(device=q.device)
    limited = angular & torch.isfinite(lower) & torch.isfinite(upper)
    centre = torch.where(limited, 0.5 * (lower + upper), torch.zeros_like(lower))
    shifted = centre + torch.remainder(q - centre + math.pi, TAU) - math.pi
    return torch.where(limited, shifted, q)


def wrapped_difference(diff: Tensor, angular: Tensor) -> Tensor:
    """Differences of poses, each angle's brought into [-pi, pi) (translations' unchanged).
    diff: (..., D); angular: (D,) bool (periodic dofs). -> (..., D)"""
    return torch.where(angular, torch.remainder(diff + math.pi, TAU) - math.pi, diff)


def outside_limits(q: Tensor, lower: Tensor, upper: Tensor, angular: Tensor | None = None) -> Tensor:
    """How far each entry lies outside its limits (0 inside; radians or metres).

    Angular dofs are measured on the circle (the nearest 2 pi shift counts). Infinite bounds never
    violate; NaN stays NaN. q: (..., D); lower, upper, angular: (D,) -> (..., D)
    """
    if angular is not None:
        q = wrap_to_limits(q, lower, upper, angular)
    lower, upper = lower.to(q), upper.to(q)
    return torch.maximum(lower - q, q - upper).clamp_min(0.0)


def limited_dofs(lower: Tensor, upper: Tensor) -> Tensor:
    """(D,) bool: dofs with at least one finite bound."""
    return torch.isfinite(lower) | torch.isfinite(upper)


def arc_bounds(values: np.ndarray, margin: float) -> tuple[float, float]:
    """The smallest arc of the circle holding every angle in `values` (N,) radians, widened by
    `margin` on each side, as (lower, upper) with lower <= upper, the representative whose centre is
    nearest 0. (-inf, inf) when the widened arc covers the whole circle."""
    a = np.sort(np.mod(np.asarray(values, dtype=np.float64), TAU))
    if a.size == 0:
        raise InputError("arc_bounds needs at least one value")
    gaps = np.diff(np.concatenate([a, [a[0] + TAU]]))
    i = int(np.argmax(gaps))  # the largest empty gap runs from a[i] to a[i + 1]
    lo = a[(i + 1) % a.size]
    width = TAU - gaps[i] + 2.0 * margin
    if width >= TAU:
        return -math.inf, math.inf
    lo -= margin
    centre = lo + 0.5 * width
    lo -= TAU * round(centre / TAU)
    return float(lo), float(lo + width)
