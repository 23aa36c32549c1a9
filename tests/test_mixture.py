"""Tests for ptrack.hypotheses.mixture: distinct minima, weights, nearest modes, Viterbi over a hypothesis lattice."""

from __future__ import annotations

import itertools
import math

import pytest
import torch

from ptrack.errors import InputError
from ptrack.hypotheses.mixture import (
    distinct_minima,
    forward_backward,
    nearest,
    posterior_weights,
    viterbi,
    viterbi_with_cost,
)


def test_distinct_minima_suppresses_duplicates_and_orders_by_cost():
    q = torch.tensor([[0.0, 0.0], [0.01, 0.0], [1.0, 1.0], [1.0, 1.02], [3.0, 0.0]])
    cost = torch.tensor([5.0, 1.0, 2.0, 0.5, 9.0])
    keep = distinct_minima(q, cost, min_distance=0.05)
    assert keep.tolist() == [3, 1, 4]  # 0 duplicates 1 (cheaper), 2 duplicates 3
    assert distinct_minima(q, cost, 0.05, limit=2).tolist() == [3, 1]
    assert distinct_minima(q, cost, 1e-6).tolist() == [3, 1, 2, 0, 4]


def test_distinct_minima_skips_non_finite():
    q = torch.tensor([[0.0], [1.0], [2.0]])
    cost = torch.tensor([float("nan"), 1.0, float("inf")])
    assert distinct_minima(q, cost, 0.1).tolist() == [1]
    assert distinct_minima(q, torch.full((3,), float("nan")), 0.1).numel() == 0
    with pytest.raises(InputError):
        distinct_minima(q[:, 0], cost, 0.1)


def test_posterior_weights():
    w = posterior_weights(torch.tensor([0.0, 1.0, 1.0]), torch.tensor([1.0, 1.0, 0.0]).log())
    assert torch.isclose(w.sum(), torch.tensor(1.0))
    assert torch.isclose(w[0] / w[1], torch.exp(torch.tensor(1.0)))
    assert w[2] < 1e-20


def test_nearest():
    centres = torch.tensor([[0.0, 0.0], [10.0, 0.0]])
    assert nearest(torch.tensor([[1.0, 1.0], [9.0, 0.0], [4.0, 0.0]]), centres).tolist() == [0, 1, 0]


def test_viterbi_matches_brute_force():
    gen = torch.Generator().manual_seed(0)
    T, K, D = 4, 3, 2
    unary = torch.rand(T, K, generator=gen, dtype=torch.float64) * 3
    q = torch.randn(T, K, D, generator=gen, dtype=torch.float64)
    sigma = 0.7

    def total(path):
        c = sum(float(unary[t, k]) for t, k in enumerate(path))
        return c + sum(
            0.5 * float((q[t, path[t]] - q[t - 1, path[t - 1]]).square().sum()) / sigma**2 for t in range(1, T)
        )

    best = min(itertools.product(range(K), repeat=T), key=total)
    assert viterbi(unary, q, sigma).tolist() == list(best)
    path, cost = viterbi_with_cost(unary, q, sigma)
    assert path.tolist() == list(best) and float(cost) == pytest.approx(total(best), rel=1e-12)


def test_forward_backward_matches_brute_force_marginals():
    """Each hypothesis's posterior is the summed exp(-energy) of every path through it (energy: viterbi's), over
    all paths; a non-finite unary entry gets 0; a frame with nothing finite counts as one without evidence."""
    gen = torch.Generator().manual_seed(1)
    T, K, D = 4, 3, 2
    unary = torch.rand(T, K, generator=gen, dtype=torch.float64) * 3
    unary[2, 1] = math.inf
    q = torch.randn(T, K, D, generator=gen, dtype=torch.float64)
    sigma = 0.7
    want = torch.zeros(T, K, dtype=torch.float64)
    for path in itertools.product(range(K), repeat=T):
        energy = sum(unary[t, k] for t, k in enumerate(path)) + sum(
            0.5 * (q[t, path[t]] - q[t - 1, path[t - 1]]).square().sum() / sigma**2 for t in range(1, T)
        )
        for t, k in enumerate(path):
            want[t, k] += torch.exp(-energy)
    want /= want.sum(-1, keepdim=True)
    got = forward_backward(unary, q, sigma)
    assert torch.allclose(got, want, atol=1e-12) and float(got[2, 1]) == 0.0
    # with a tight prior the whole chain follows the smooth track, however the single frames vote
    track = torch.tensor([[[0.0], [5.0]], [[0.1], [5.0]], [[0.2], [5.1]]], dtype=torch.float64)
    votes = torch.tensor([[0.0, 0.1], [0.5, 0.0], [0.0, 0.05]], dtype=torch.float64)
    assert (forward_backward(votes, track, 0.5)[:, 1] > 0.5).all()
    assert forward_backward(votes, track, 100.0).argmax(-1).tolist() == [0, 1, 0]
    blank = torch.full((3, 2), math.inf, dtype=torch.float64)
    assert torch.allclose(forward_backward(blank, track, 0.5), forward_backward(torch.zeros_like(blank), track, 0.5))


def test_viterbi_avoids_non_finite_and_prefers_smooth_paths():
    q = torch.tensor([[[0.0], [5.0]], [[0.1], [5.0]], [[0.2], [5.1]]])
    unary = torch.tensor([[0.0, 0.1], [0.5, 0.0], [float("nan"), 0.0]])
    path = viterbi(unary, q, sigma=0.5)
    assert path[2] == 1  # the NaN hypothesis is never taken
    unary = torch.tensor([[0.0, 0.1], [0.5, 0.0], [0.0, 0.05]])
    assert unary.argmin(-1).tolist() == [0, 1, 0]  # frame by frame it would jump back and forth
    assert viterbi(unary, q, sigma=0.5).tolist() == [1, 1, 1]  # a 5-unit jump costs 50: stay on one track
    assert viterbi(unary, q, sigma=100.0).tolist() == [0, 1, 0]  # with a loose prior the unaries decide
    with pytest.raises(InputError):
        viterbi(unary[0], q, 1.0)
