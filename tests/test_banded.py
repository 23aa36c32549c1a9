"""Tests for ptrack.optim.banded (block-banded LDL^T, solves, marginal covariances) and the banded
Levenberg-Marquardt of ptrack.optim.solvers, each against dense linear algebra on small problems."""

from __future__ import annotations

import pytest
import torch

from ptrack.errors import InputError
from ptrack.optim import banded as bd
from ptrack.optim.solvers import BandedLinearization, banded_levenberg_marquardt

F64 = torch.float64


def random_banded(b: int, t_len: int, d: int, w: int, diagonal_coupling: bool, seed: int = 0) -> bd.BlockBanded:
    """An SPD block-banded matrix: per-frame J^T J blocks plus a per-dof smoothness band (or dense couplings)."""
    g = torch.Generator().manual_seed(seed)
    jac = torch.randn(b, t_len, d + 2, d, generator=g, dtype=F64)
    diag = jac.mT @ jac + 0.1 * torch.eye(d, dtype=F64)
    if diagonal_coupling:
        lower = 0.5 * torch.randn(b, t_len, w, d, generator=g, dtype=F64)
        diag = diag + torch.diag_embed(lower.abs().sum(-2) * 2 + 0.5)  # keep it diagonally dominant enough
    else:
        m = torch.randn(b, t_len * d, t_len * d, generator=g, dtype=F64)
        dense = bd.to_dense(bd.from_dense(m @ m.mT, t_len, w))
        full = bd.from_dense(dense + t_len * d * torch.eye(t_len * d, dtype=F64), t_len, w)
        return full
    return bd.BlockBanded(diag, lower)


def diagonal_blocks(m: torch.Tensor, t_len: int, d: int) -> torch.Tensor:
    return torch.stack([m[..., t * d : (t + 1) * d, t * d : (t + 1) * d] for t in range(t_len)], dim=-3)


@pytest.mark.parametrize("w", [1, 2, 3])
@pytest.mark.parametrize("diagonal_coupling", [True, False])
@pytest.mark.parametrize(("t_len", "halves"), [(9, False), (12, True), (13, True)])
@pytest.mark.parametrize("numpy_loops", [True, False])
def test_solve_and_marginals_equal_dense(w, diagonal_coupling, t_len, halves, numpy_loops, monkeypatch):
    """One sweep over the frames, or two halves from both ends and a W-frame separator in the
    middle (odd and even T - W: the top half padded or not); the sequential loops on numpy/LAPACK
    (CPU) or torch (any device)."""
    monkeypatch.setattr(bd, "NUMPY_LOOPS", numpy_loops)
    d = 4
    a = random_banded(2, t_len, d, w, diagonal_coupling)
    dense = bd.to_dense(a)
    assert torch.allclose(dense, dense.mT)
    assert bool((torch.linalg.eigvalsh(dense) > 0).all())
    factor, ok = bd.factorize(a, halves=halves)
    assert isinstance(factor.dense, bd._Twisted) == halves
    assert ok.all()
    b = torch.randn(2, t_len, d, dtype=F64, generator=torch.Generator().manual_seed(1))
    x = bd.solve(factor, b)
    x_dense = torch.linalg.solve(dense, b.flatten(-2)).unflatten(-1, (t_len, d))
    assert torch.allclose(x, x_dense, atol=1e-12, rtol=1e-10)
    assert torch.allclose(bd.matvec(a, x), b, atol=1e-11)
    marg = bd.marginal_blocks(factor)
    assert torch.allclose(marg, diagonal_blocks(torch.linalg.inv(dense), t_len, d), atol=1e-12, rtol=1e-10)


@pytest.mark.parametrize("w", [1, 2, 3])
@pytest.mark.parametrize("t_len", [1, 2, 7, 16])
@pytest.mark.parametrize("alone", [[1, 3], [0, 1, 2, 3, 4]])
@pytest.mark.parametrize("halves", [False, True])
@pytest.mark.parametrize("numpy_loops", [True, False])
def test_decoupled_dofs_reduced_in_parallel_equal_dense(w, t_len, alone, halves, numpy_loops, monkeypatch):
    """Dofs no per-frame block couples to another (unobserved ones: only priors act on them) are
    split off and solved by cyclic reduction (torch) or LAPACK's banded Cholesky (CPU fast path);
    the result is still the dense solve and inverse."""
    monkeypatch.setattr(bd, "NUMPY_LOOPS", numpy_loops)
    b, d = 2, 5
    g = torch.Generator().manual_seed(t_len * 10 + w)
    jac = torch.randn(b, t_len, d + 2, d, generator=g, dtype=F64)
    diag = jac.mT @ jac + 0.1 * torch.eye(d, dtype=F64)
    for i in alone:
        v = diag[..., i, i].clone()
        diag[..., i, :] = 0
        diag[..., :, i] = 0
        diag[..., i, i] = v
    lower = 0.5 * torch.randn(b, t_len, w, d, generator=g, dtype=F64)
    a = bd.BlockBanded(diag + torch.diag_embed(lower.abs().sum(-2) * 2 + 0.5), lower)
    factor, ok = bd.factorize(a, halves=halves)
    assert ok.all() and factor.decoupled.tolist() == alone
    dense = bd.to_dense(a)
    rhs = torch.randn(b, t_len, d, dtype=F64, generator=g)
    x_dense = torch.linalg.solve(dense, rhs.flatten(-2)).unflatten(-1, (t_len, d))
    assert torch.allclose(bd.solve(factor, rhs), x_dense, atol=1e-12, rtol=1e-10)
    marg = bd.marginal_blocks(factor)
    assert torch.allclose(marg, diagonal_blocks(torch.linalg.inv(dense), t_len, d), atol=1e-12, rtol=1e-10)
    bad = a.diagonal.clone()
    bad[1, t_len // 2, alone[0], alone[0]] = -1.0  # an indefinite pivot among the decoupled dofs of system 1
    factor, ok = bd.factorize(bd.BlockBanded(bad, a.lower), halves=halves)
    assert ok.tolist() == [True, False] and torch.isfinite(bd.solve(factor, rhs)).all()


@pytest.mark.parametrize(
    ("t_len", "bad_frames", "halves"), [(6, [3], False), (11, [1], True), (11, [5], True), (11, [9], True)]
)
@pytest.mark.parametrize("numpy_loops", [True, False])
def test_batched_systems_are_independent_and_failures_flagged(t_len, bad_frames, halves, numpy_loops, monkeypatch):
    """An indefinite frame in the top half, the separator or the bottom half of system 1 fails that
    system only (numpy/LAPACK loops or torch's)."""
    monkeypatch.setattr(bd, "NUMPY_LOOPS", numpy_loops)
    d = 3
    a = random_banded(3, t_len, d, 2, True)
    bad_diag = a.diagonal.clone()
    bad_diag[1, bad_frames] = -torch.eye(d, dtype=F64)  # system 1 is indefinite
    factor, ok = bd.factorize(bd.BlockBanded(bad_diag, a.lower), halves=halves)
    assert ok.tolist() == [True, False, True]
    b = torch.randn(3, t_len, d, dtype=F64)
    x = bd.solve(factor, b)
    assert torch.isfinite(x).all() and torch.isfinite(bd.marginal_blocks(factor)).all()
    for i in (0, 2):
        single, _ = bd.factorize(bd.BlockBanded(a.diagonal[i], a.lower[i]), halves=False)
        assert torch.allclose(x[i], bd.solve(single, b[i]), atol=1e-13)


@pytest.mark.parametrize("w", [1, 2, 3])
@pytest.mark.parametrize("diagonal_coupling", [True, False])
def test_numpy_loops_equal_torch_loops(w, diagonal_coupling, monkeypatch):
    """The CPU fast path (factor and sweeps on numpy/LAPACK) gives torch's factor and solve."""
    a = random_banded(2, 40, 5, w, diagonal_coupling)
    b = torch.randn(2, 40, 5, dtype=F64, generator=torch.Generator().manual_seed(2))
    out = {}
    for flag in (True, False):
        monkeypatch.setattr(bd, "NUMPY_LOOPS", flag)
        factor, ok = bd.factorize(a)
        assert ok.all() and isinstance(factor.dense, bd._Twisted)
        out[flag] = factor.dense.halves, bd.solve(factor, b)
    (fn, xn), (ft, xt) = out[True], out[False]
    assert torch.allclose(fn.inv_chol_t, ft.inv_chol_t, atol=1e-13, rtol=1e-11)
    assert torch.allclose(fn.coupling, ft.coupling, atol=1e-13, rtol=1e-11)
    assert torch.allclose(xn, xt, atol=1e-13, rtol=1e-11)


def test_float32_and_shapes_follow_inputs():
    a = random_banded(1, 5, 3, 2, True)
    a32 = bd.BlockBanded(a.diagonal.float(), a.lower.float())
    factor, ok = bd.factorize(a32)
    x = bd.solve(factor, torch.ones(1, 5, 3))
    assert x.dtype == torch.float32 and x.shape == (1, 5, 3) and ok.all()
    assert bd.marginal_blocks(factor).shape == (1, 5, 3, 3)
    with pytest.raises(InputError):
        bd.factorize(bd.BlockBanded(torch.zeros(5, 3, 3), torch.zeros(4, 2, 3)))
    with pytest.raises(InputError):
        bd.solve(factor, torch.ones(1, 4, 3))


def test_single_frame_and_short_sequences():
    for t_len in (1, 2):
        a = random_banded(1, t_len, 3, 2, True)
        factor, _ok = bd.factorize(a)
        b = torch.randn(1, t_len, 3, dtype=F64)
        x = bd.solve(factor, b)
        assert torch.allclose(bd.to_dense(a) @ x.flatten(-2)[..., None], b.flatten(-2)[..., None], atol=1e-12)


# -- the banded Levenberg-Marquardt -------------------------------------------------------------------


def curve_problem(b: int, t_len: int, seed: int = 0):
    """B trajectories of 2-D points observed through a nonlinear map (polar to Cartesian) with an
    acceleration prior: a small nonlinear least-squares problem whose normal equations are
    block-pentadiagonal. -> truth (B, T, 2), linearize(q, obs) -> (BandedLinearization, dense H), obs."""
    g = torch.Generator().manual_seed(seed)
    truth = torch.stack(
        [
            torch.linspace(0, 2, t_len, dtype=F64).expand(b, t_len),
            1.0 + 0.3 * torch.rand(b, t_len, generator=g, dtype=F64),
        ],
        -1,
    )
    obs = measure(truth) + 0.01 * torch.randn(b, t_len, 2, generator=g, dtype=F64)
    a = torch.tensor([3.0, 5.0], dtype=F64)  # acceleration weights per dof

    def residuals(q, o):  # q (T, 2), o (T, 2) -> (M,)
        return torch.cat([(measure(q) - o).flatten(), (a * torch.diff(q, n=2, dim=0)).flatten()])

    def linearize(q, o):
        rs, hs, gs = [], [], []
        for qi, oi in zip(q, o):
            r = residuals(qi, oi)
            jac = torch.autograd.functional.jacobian(lambda x: residuals(x, oi), qi).flatten(-2)  # (M, T*2)
            rs.append(r)
            hs.append(jac.mT @ jac)
            gs.append((jac.mT @ r).unflatten(-1, (t_len, 2)))
        h = torch.stack(hs)
        energy = 0.5 * torch.stack(rs).square().sum(-1)
        return BandedLinearization(bd.from_dense(h, t_len, 2), torch.stack(gs), energy), h

    return truth, obs, linearize


def measure(q):
    return torch.stack([q[..., 1] * torch.cos(q[..., 0]), q[..., 1] * torch.sin(q[..., 0])], -1)


def test_banded_lm_matches_dense_gauss_newton_and_batching():
    t_len = 8
    truth, obs, linearize = curve_problem(2, t_len)
    q0 = truth + 0.2
    tight = dict(max_iter=50, tol=1e-14, gtol=1e-12)
    q, info = banded_levenberg_marquardt(lambda x: linearize(x, obs)[0], q0, **tight)
    assert info.converged.all()
    x = q0.clone()  # a dense Gauss-Newton from the same start reaches the same minimum
    for _ in range(30):
        lin, h = linearize(x, obs)
        x = x - torch.linalg.solve(h, lin.gradient.flatten(-2)).unflatten(-1, (t_len, 2))
    assert torch.allclose(q, x, atol=1e-9)
    assert info.history.shape[1] == 2 and bool((info.history[1:] <= info.history[:-1] + 1e-15).all())
    q1, _ = banded_levenberg_marquardt(lambda x: linearize(x, obs[1:])[0], q0[1:], **tight)
    assert torch.allclose(q1[0], q[1], atol=1e-9)  # the same alone as in the batch


def test_banded_lm_on_a_shared_objective_steps_only_the_trajectories_not_done():
    """shared=True: starts of one objective; once some have stopped only the others are linearised, and each
    ends where it does alone, after as many iterations."""
    truth, obs, linearize = curve_problem(1, 8)
    starts = truth + torch.tensor([0.01, 0.2, 0.5], dtype=F64)[:, None, None]
    tight = dict(max_iter=50, tol=1e-14, gtol=1e-12)
    rows: list[int] = []

    def lin(x):
        rows.append(x.shape[0])
        return linearize(x, obs.expand(x.shape[0], -1, -1))[0]

    q, info = banded_levenberg_marquardt(lin, starts, shared=True, **tight)
    assert info.converged.all() and min(rows) < 3
    for i in range(3):
        alone, alone_info = banded_levenberg_marquardt(lambda x: linearize(x, obs)[0], starts[i : i + 1], **tight)
        assert torch.allclose(q[i], alone[0], atol=1e-9)
        assert int(info.iterations[i]) == int(alone_info.iterations[0])
        assert float(info.cost[i]) == pytest.approx(float(alone_info.cost[0]), rel=1e-12)


def test_banded_lm_respects_bounds():
    truth, obs, linearize = curve_problem(1, 6)
    upper = torch.tensor([1.0, 10.0], dtype=F64)
    start = truth.clamp(max=0.9)
    q, info = banded_levenberg_marquardt(lambda x: linearize(x, obs)[0], start, upper=upper, max_iter=40)
    assert bool((q[..., 0] <= 1.0).all()) and float(q[..., 0].max()) == pytest.approx(1.0)
    assert info.cost[0] < linearize(start, obs)[0].energy[0]
