"""Mixture bookkeeping for the sampling trackers: distinct minima, weights, pruning to K modes, and the
best trajectory through the per-frame hypothesis lattice.

A frame's posterior is a mixture of K modes: poses q (K, D), weights (K,) summing to 1, costs (K,)
(negative log posterior up to a constant) and scale factors (K, D, D) (Cholesky factors of the
sampling covariance). Everything here is pure and batched over candidates; no randomness.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from ptrack.errors import InputError


class Modes(NamedTuple):
    """K weighted modes of one frame: q (K, D), weight (K,) summing to 1, cost (K,), chol (K, D, D),
    velocity (K, D) per frame (the change from the mode it came from; zeros at the start)."""

    q: Tensor
    weight: Tensor
    cost: Tensor
    chol: Tensor
    velocity: Tensor


#: elements of the pairwise differences `distinct_minima` holds at once (a block of rows against all)
PAIRWISE_BLOCK = 1 << 22


def distinct_minima(q: Tensor, cost: Tensor, min_distance: float, limit: int | None = None) -> Tensor:
    """Indices of the distinct minima among N optimised candidates, best (lowest cost) first.

    Greedy non-maximum suppression: candidates are visited by increasing cost and kept unless a kept one
    lies within `min_distance` (max-norm over the dofs, i.e. no dof differs by more) of it. Non-finite
    costs are never kept. q: (N, D); cost: (N,) -> (M,) int64 with M <= limit.
    """
    if q.ndim != 2 or cost.shape != q.shape[:1]:
        raise InputError(
            f"distinct_minima: q (N, D) and cost (N,) expected, got {tuple(q.shape)} and {tuple(cost.shape)}"
        )
    order = torch.argsort(torch.where(torch.isfinite(cost), cost, torch.full_like(cost, float("inf"))))
    order = order[torch.isfinite(cost[order])]
    if order.numel() == 0:
        return order
    qs = q[order]
    n = qs.shape[0]
    # the (n, n) table of close pairs, built a block of rows at a time: the (rows, n, D) differences stay
    # near PAIRWISE_BLOCK elements (2000 candidates of 51 coordinates at once: 1.6 GB in float64)
    rows = max(1, PAIRWISE_BLOCK // max(n * qs.shape[1], 1))
    close = torch.cat(
        [(block[:, None, :] - qs[None, :, :]).abs().amax(-1) < min_distance for block in qs.split(rows)]
    )  # (n, n)
    keep = torch.zeros(order.numel(), dtype=torch.bool, device=q.device)
    suppressed = torch.zeros_like(keep)
    # a loop over candidates in cost order; each step is O(n) on the precomputed (n, n) table
    for i in range(order.numel()):
        if suppressed[i]:
            continue
        keep[i] = True
        suppressed |= close[i]
        if limit is not None and int(keep.sum()) >= limit:
            break
    return order[keep]


def posterior_weights(cost: Tensor, log_prior: Tensor, temperature: float = 1.0) -> Tensor:
    """Normalised weights w_i ∝ exp(log_prior_i) * exp(-cost_i / temperature), 0 where that is not finite (a
    NaN cost, a prior of weight 0). (M,), (M,) log prior weights -> (M,)."""
    logw = log_prior - cost / temperature
    return torch.softmax(torch.where(torch.isfinite(logw), logw, torch.full_like(logw, -math.inf)), dim=0)


def nearest(q: Tensor, centres: Tensor) -> Tensor:
    """Index of the nearest centre (Euclidean in q) for each row of q. (M, D), (K, D) -> (M,) int64."""
    return torch.cdist(q, centres).argmin(-1)


def forward_backward(unary: Tensor, q: Tensor, sigma: float) -> Tensor:
    """Posterior marginals of every hypothesis of a (T, K) lattice under the chain whose energy `viterbi`
    minimises: p(k_0 .. k_T-1) ∝ exp(-sum_t unary[t, k_t] - 0.5 * sum_t |q[t, k_t] - q[t-1, k_t-1]|^2 / sigma^2),
    summed over every path through each hypothesis (forward-backward in log space). Non-finite unary entries get
    probability 0 (a frame with nothing finite is taken as one without evidence: unary 0). The Viterbi path is
    this chain's MAP path. unary: (T, K); q: (T, K, D) -> (T, K), each row summing to 1."""
    _check_lattice(unary, q)
    logu = torch.where(torch.isfinite(unary), -unary, torch.full_like(unary, -math.inf))
    logu = torch.where(torch.isfinite(logu).any(-1, keepdim=True), logu, torch.zeros_like(logu))
    T = logu.shape[0]
    pair = [-0.5 * torch.cdist(q[t - 1], q[t]).square() / sigma**2 for t in range(1, T)]  # (K_prev, K) each
    alpha = [logu[0]]
    for t in range(1, T):
        alpha.append(logu[t] + torch.logsumexp(alpha[-1][:, None] + pair[t - 1], 0))
    beta = [torch.zeros_like(logu[0])]
    for t in range(T - 1, 0, -1):
        beta.append(torch.logsumexp(pair[t - 1] + (logu[t] + beta[-1])[None, :], 1))
    return torch.softmax(torch.stack(alpha) + torch.stack(beta[::-1]), -1)


def _check_lattice(unary: Tensor, q: Tensor) -> None:
    if unary.ndim != 2 or q.shape[:2] != unary.shape:
        raise InputError(
            f"viterbi: unary (T, K) and q (T, K, D) expected, got {tuple(unary.shape)} and {tuple(q.shape)}"
        )


def viterbi(unary: Tensor, q: Tensor, sigma: float) -> Tensor:
    """The best path through a (T, K) lattice of hypotheses.

    Minimises sum_t unary[t, k_t] + 0.5 * sum_t |q[t, k_t] - q[t-1, k_{t-1}]|^2 / sigma^2: the per-frame
    costs plus a temporal smoothness (velocity) prior between consecutive chosen hypotheses. Non-finite
    unary entries are never chosen (unless a frame has nothing else).
    unary: (T, K); q: (T, K, D) -> (T,) int64 hypothesis index per frame.
    """
    return viterbi_with_cost(unary, q, sigma)[0]


def viterbi_with_cost(unary: Tensor, q: Tensor, sigma: float) -> tuple[Tensor, Tensor]:
    """`viterbi` and the minimised sum along its path: unary (T, K), q (T, K, D) -> path (T,) int64,
    cost () (a huge finite number where the path has to take a non-finite unary entry)."""
    _check_lattice(unary, q)
    big = torch.finfo(unary.dtype).max / 4
    u = torch.where(torch.isfinite(unary), unary, torch.full_like(unary, big))
    T = u.shape[0]
    score = u[0]
    back = []
    for t in range(1, T):
        pair = 0.5 * torch.cdist(q[t - 1], q[t]).square() / sigma**2  # (K_prev, K)
        total = score[:, None] + pair
        best, arg = total.min(0)
        back.append(arg)
        score = best + u[t]
    path = [int(score.argmin())]
    for arg in reversed(back):
        path.append(int(arg[path[-1]]))
    return torch.as_tensor(path[::-1], dtype=torch.long, device=unary.device), score.min()
