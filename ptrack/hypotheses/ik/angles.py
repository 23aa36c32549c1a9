"""Rotations back to angles, and the choice among equivalent angles: both Euler solutions of a rotation
(`euler_zyx_solutions`; `seuler_solutions` in the struct-of-arrays layout), angles wrapped into the
limits' 2 pi windows with their limit violation (`window_violation`), and the candidate inside the
limits nearest to the current angles (`pick_candidate`).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ptrack.body.limits import TAU
from ptrack.hypotheses.jumps import sconst, to_aos, to_soa


def seuler_solutions(r: Tensor, x_lock: Tensor) -> Tensor:
    """`euler_zyx_solutions` on r (3, 3, *M), x_lock (*M) -> (3, 2, *M) (angle, solution)."""
    r20, r21, r22 = r[2, 0], r[2, 1], r[2, 2]
    lock = torch.hypot(r21, r22) <= 64 * torch.finfo(r.dtype).eps
    x = torch.where(lock, x_lock, torch.atan2(r21, r22))
    sx, cx = torch.sin(x), torch.cos(x)
    y = torch.atan2(-r20, sx * r21 + cx * r22)
    z = torch.atan2(sx * r[0, 2] - cx * r[0, 1], cx * r[1, 1] - sx * r[1, 2])
    return torch.stack([torch.stack([z, z + math.pi]), torch.stack([y, math.pi - y]), torch.stack([x, x + math.pi])])


def euler_zyx_solutions(r: Tensor, x_lock: Tensor) -> Tensor:
    """Both (z, y, x) angle triples with Rz(z) Ry(y) Rx(x) = r: (..., 3, 3) -> (..., 2, 3); the
    first has |y| <= pi/2, the second is (z + pi, pi - y, x + pi) (not wrapped). At the gimbal lock
    (cos y = 0) x is taken from x_lock (...,) (e.g. the current angle) and z carries the rest.
    Day's extraction (as `ptrack.body.rotations.matrix_to_euler_np`): x from the last row, y and z given x."""
    out = seuler_solutions(to_soa(r, 2), x_lock.expand(r.shape[:-2]))  # (3, 2, ...)
    return to_aos(out, 2).transpose(-1, -2)


def window_violation(theta: Tensor, tc: dict, sl: slice = slice(None)) -> tuple[Tensor, Tensor]:
    """Angles in their windows and their summed limit violation: theta (A, *M) (dofs tc[...][sl])
    -> (A, *M), (*M) radians."""
    nd = theta.ndim - 1
    shift = sconst(tc["shift"][sl], nd)
    w = torch.remainder(theta + shift, TAU) - shift
    viol = (sconst(tc["lower"][sl], nd) - w).clamp_min(0.0) + (w - sconst(tc["upper"][sl], nd)).clamp_min(0.0)
    return w, viol.sum(0)


def pick_candidate(cands: Tensor, current: Tensor, tc: dict, sl: slice = slice(None)) -> Tensor:
    """The candidate angle vector with least limit violation (radians, summed over dofs), ties
    within ~1e-6 going to the nearest to `current` (sum of 1 - cos of the differences):
    cands (A, K, *M), current (A, *M) broadcastable, limits of dofs tc[...][sl] -> (A, *M)."""
    _, viol = window_violation(cands, tc, sl)  # (K, *M)
    near = (1.0 - torch.cos(cands - current.unsqueeze(1))).sum(0)
    score = viol + 1e-6 * near
    best, out = score[0], cands[:, 0]
    for k in range(1, cands.shape[1]):  # K is 2 or 4: cheaper than argmin + gather over dim 1
        better = score[k] < best
        best = torch.where(better, score[k], best)
        out = torch.where(better, cands[:, k], out)
    return out
