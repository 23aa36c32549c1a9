"""Symmetric block-banded matrices over time: block Cholesky factor, solves, products and the diagonal
blocks of the inverse, without ever forming the dense (T*D) x (T*D) matrix.

A symmetric matrix A of T x T blocks of size D x D whose blocks vanish more than W block-rows off
the diagonal (W = 1: block-tridiagonal, a velocity prior; W = 2: block-pentadiagonal, an
acceleration prior) is held as a `BlockBanded`:

    diagonal (..., T, D, D)      A[t, t]
    lower    (..., T, W, D, D)   lower[..., t, k-1] = A[t, t-k] (ignored where t-k < 0), or
             (..., T, W, D)      the same blocks when they are diagonal matrices (a smoothness prior
                                 on each dof couples a dof only with itself), stored as vectors

with any leading batch dims (independent systems, solved at once). The factor is the block
Cholesky A = L L^T, L block-lower-triangular of the same band with L[t, t] = C_t (lower triangular)
and L[t, t-k] = B[t, k], computed one block row at a time (W is small, products batched over the
leading dims):

    B[t, k] = (A[t, t-k] - sum_{j=k+1..W} B[t, j] B[t-k, j-k]^T) C_{t-k}^{-T}
    C_t C_t^T = A[t, t] - sum_{k=1..W} B[t, k] B[t, k]^T

With diagonal couplings B[t, W] = A[t, t-W] C_{t-W}^{-T} is a row scaling (no product). The
factor keeps C_t^{-T} (one triangular inverse per frame), so a solve is two sweeps of block
products. Marginal covariances (diagonal blocks of S = A^{-1}) come from L^T S = L^{-1}, run
backwards in t over S's own band only (Takahashi):

    S[t, s] = C_t^{-T} (delta_ts C_t^{-1} - sum_{k=1..W} B[t+k, k]^T S[t+k, s])      (s >= t)

Decoupled dofs. With diagonal couplings, a dof whose rows of every diagonal block are diagonal (a
dof no observation moves: only per-dof priors, limits and keyframes act on it, e.g. fingers and
toes under 17 keypoints) is coupled to nothing but itself over time: each such dof is a scalar
W-banded T x T system. `factorize` splits them off, so the sequential sweep runs on the n coupled
dofs only (work n^3 instead of D^3 per frame), and solves the scalar systems all at once by
parallel cyclic reduction (block-tridiagonal with W x W blocks; log2(T/W) vectorised levels; its
multipliers take O(T log T) memory per dof).

    factorize(A) -> BandedFactor, ok (...,) bool
    solve(factor, b (..., T, D)) -> x (..., T, D)           A x = b
    matvec(A, x (..., T, D)) -> A x (..., T, D)
    marginal_blocks(factor) -> (..., T, D, D)               diagonal blocks of A^{-1}
    to_dense(A) -> (..., T*D, T*D); from_dense(M, T, W)     small problems and tests only

Work and memory are O(T W^2 n^3) and O(T W n^2) for the coupled dofs. Everything follows the
inputs' dtype and device.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import NamedTuple

import torch
from torch import Tensor

from ptrack.errors import InputError


class BlockBanded(NamedTuple):
    """Symmetric block-banded matrix: diagonal (..., T, D, D); lower (..., T, W, D, D) dense or
    (..., T, W, D) diagonal couplings, lower[..., t, k-1] = A[t, t-k] (see module docstring)."""

    diagonal: Tensor
    lower: Tensor

    @property
    def coupling_is_diagonal(self) -> bool:
        return self.lower.ndim == self.diagonal.ndim

    @property
    def shape(self) -> tuple[int, int, int]:
        """(T, W, D)."""
        return (
            self.diagonal.shape[-3],
            self.lower.shape[-3 if not self.coupling_is_diagonal else -2],
            self.diagonal.shape[-1],
        )


class _Chol(NamedTuple):
    """Block Cholesky factor of one group of n dofs, leading dims flattened to B (module docstring):
    inv_chol_t (B, T, n, n) = C_t^{-T}; coupling (B, T, W, n, n) = B[t, k] at [:, t, k-1], zero
    where t-k < 0. For n = 1 (decoupled dofs) both are held as (B, T) and (B, T, W)."""

    inv_chol_t: Tensor
    coupling: Tensor


class BandedFactor(NamedTuple):
    """Block Cholesky factor A = L L^T of a `BlockBanded` (module docstring). dense: the factor of
    the coupled dofs `coupled` (n,) (long), or None; scalar: the decoupled dofs `decoupled` (u,) as
    B * u independent systems of 1 x 1 blocks, or None; batch: the leading dims; size: D."""

    dense: _Chol | None
    scalar: _Reduction | None
    coupled: Tensor
    decoupled: Tensor
    batch: tuple
    size: int


@contextmanager
def one_thread() -> Iterator[None]:
    """Run torch on one intra-op thread inside the block (restored after). The sequential sweeps
    run on it: their products are small (n x n per frame), multithreaded BLAS gains nothing on them
    and, on a loaded machine, its spinning threads made a 40-frame sweep 370x slower (2.3 s against
    6 ms, measured on 2 shared cores); `method: batch` runs its whole solve inside it."""
    n = torch.get_num_threads()
    if n == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def _check(a: BlockBanded, who: str) -> tuple[int, int, int]:
    dg, lo = a.diagonal, a.lower
    ok = isinstance(dg, Tensor) and isinstance(lo, Tensor) and dg.ndim >= 3 and dg.shape[-1] == dg.shape[-2]
    if ok:
        t_len, d = dg.shape[-3], dg.shape[-1]
        ok = (lo.ndim == dg.ndim + 1 and lo.shape[-4] == t_len and lo.shape[-2:] == (d, d)) or (
            lo.ndim == dg.ndim and lo.shape[-3] == t_len and lo.shape[-1] == d
        )
    if not ok:
        raise InputError(
            f"{who}: expected diagonal (..., T, D, D) and lower (..., T, W, D, D) or (..., T, W, D), "
            f"got {tuple(getattr(dg, 'shape', ()))} and {tuple(getattr(lo, 'shape', ()))}"
        )
    return a.shape


def _factor_dense(diag: Tensor, lower: Tensor) -> tuple[_Chol, Tensor]:
    """diag (B, T, n, n), lower (B|1, T, W, n) diagonal or (B|1, T, W, n, n) dense couplings ->
    factor, ok (B,). One block row per step; per-frame tensors are kept in lists (no copies)."""
    b, t_len, n = diag.shape[0], diag.shape[1], diag.shape[-1]
    vec = lower.ndim == 4
    w = lower.shape[2]
    lower = lower.expand(b, *lower.shape[1:])
    eye = torch.eye(n, dtype=diag.dtype, device=diag.device).expand(b, n, n)
    zero = diag.new_zeros(b, n, n)
    a_tt = diag.unbind(1)
    a_k = [lower[:, :, k].unbind(1) for k in range(w)]  # a_k[k-1][t] = A[t, t-k]
    if vec and w > 1:  # dense A[t, t-k] for k < W (the k = W block stays a row scaling)
        a_k[: w - 1] = [torch.diag_embed(lower[:, :, k]).unbind(1) for k in range(w - 1)]
    cit: list[Tensor] = [zero] * w  # cit[t + W] = C_t^{-T}
    blk: list[list[Tensor]] = [[zero] * w for _ in range(w)]  # blk[t + W][k-1] = B[t, k]
    infos = []
    for t in range(t_len):
        row: list[Tensor] = [zero] * w
        if vec:
            row[w - 1] = a_k[w - 1][t][:, :, None] * cit[t]
        else:
            row[w - 1] = a_k[w - 1][t] @ cit[t]
        for k in range(w - 1, 0, -1):
            x = a_k[k - 1][t]
            for j in range(k + 1, w + 1):  # - B[t, j] B[t-k, j-k]^T
                x = torch.baddbmm(x, row[j - 1], blk[t - k + w][j - k - 1].mT, alpha=-1)
            row[k - 1] = x @ cit[t - k + w]
        s = a_tt[t]
        for k in range(w):
            s = torch.baddbmm(s, row[k], row[k].mT, alpha=-1)
        chol, info = torch.linalg.cholesky_ex(s)
        infos.append(info)
        # C_t^{-1} comes out column-major: its transpose is a contiguous C_t^{-T}
        cit.append(torch.linalg.solve_triangular(chol, eye, upper=False).mT)
        blk.append(row)
    ok = (torch.stack(infos, -1) == 0).all(-1) if infos else torch.ones(b, dtype=torch.bool, device=diag.device)
    inv_t = torch.stack(cit[w:], 1)
    coupling = torch.stack([torch.stack(r, 1) for r in blk[w:]], 1)
    if not bool(ok.all()):  # a failed system's factor: finite stand-ins (identity pivots, no couplings)
        inv_t = torch.where(ok[:, None, None, None], inv_t, eye[:, None])
        coupling = torch.where(ok[:, None, None, None, None], coupling, 0.0)
    return _Chol(inv_t, coupling), ok


def _factor_scalar(diag: Tensor, lower: Tensor) -> tuple[_Chol, Tensor]:
    """1 x 1 blocks, elementwise: diag (B, T), lower (B|1, T, W) -> factor, ok (B,)."""
    b, t_len = diag.shape
    w = lower.shape[-1]
    lower = lower.expand(b, t_len, w)
    zero = diag.new_zeros(b)
    a_tt = diag.unbind(1)
    a_k = [lower[:, :, k].unbind(1) for k in range(w)]
    ci: list[Tensor] = [zero] * w  # 1 / C_t
    blk: list[list[Tensor]] = [[zero] * w for _ in range(w)]
    for t in range(t_len):
        row: list[Tensor] = [zero] * w
        for k in range(w, 0, -1):
            x = a_k[k - 1][t]
            for j in range(k + 1, w + 1):
                x = torch.addcmul(x, row[j - 1], blk[t - k + w][j - k - 1], value=-1)
            row[k - 1] = x * ci[t - k + w]
        s = a_tt[t]
        for k in range(w):
            s = torch.addcmul(s, row[k], row[k], value=-1)
        ci.append(s.rsqrt())  # NaN for a failed pivot, flagged and replaced below
        blk.append(row)
    inv = torch.stack(ci[w:], 1) if t_len else diag.new_zeros(b, 0)
    coupling = torch.stack([torch.stack(r, 1) for r in blk[w:]], 1) if t_len else diag.new_zeros(b, 0, w)
    ok = torch.isfinite(inv).all(-1) & torch.isfinite(coupling).flatten(1).all(-1)
    if not bool(ok.all()):
        inv = torch.where(ok[:, None], inv, 1.0)
        coupling = torch.where(ok[:, None, None], coupling, 0.0)
    return _Chol(inv, coupling), ok


class _Reduction(NamedTuple):
    """Parallel cyclic reduction of B independent scalar systems with W-banded T x T matrices, seen as
    block-tridiagonal with W x W blocks (N = ceil(T / W) of them), blocks held entry-major
    (W, W, B, N) so that a block product is two vectorised ops: per level l (stride 2^l) the
    multipliers alpha, beta that fold each block row's neighbours at distance 2^l into it, and after
    the last level the inverse diagonal blocks inv. diag (B, T) and lower (B, T, W) are the system
    itself (for the marginal variances)."""

    alpha: tuple
    beta: tuple
    inv: Tensor
    diag: Tensor
    lower: Tensor


def _shift(x: Tensor, s: int) -> Tensor:
    """x (..., N) moved s places along N (s > 0: entry i holds x[i - s]), zero-filled."""
    n = x.shape[-1]
    s = max(min(s, n), -n)
    if s >= 0:
        return torch.nn.functional.pad(x[..., : n - s], (s, 0))
    return torch.nn.functional.pad(x[..., -s:], (0, -s))


def _bmm(a: Tensor, b: Tensor) -> Tensor:
    """Block products, entry-major: a (W, V, ...) @ b (V, U, ...) -> (W, U, ...)."""
    return (a[:, :, None] * b[None]).sum(1)


def _spd_inverse(m: Tensor) -> tuple[Tensor, Tensor]:
    """Inverse of SPD blocks, entry-major m (W, W, ...), and (...) bool positive definite; W <= 2
    in closed form (batched LAPACK calls on many tiny matrices cost more than the arithmetic)."""
    w = m.shape[0]
    if w == 1:
        return 1.0 / m, m[0, 0] > 0
    if w == 2:
        a, b, c = m[0, 0], m[0, 1], m[1, 1]
        det = a * c - b * b
        good = (a > 0) & (det > 0)
        return torch.stack([torch.stack([c, -b]), torch.stack([-b, a])]) / det, good
    chol, info = torch.linalg.cholesky_ex(m.movedim((0, 1), (-2, -1)))
    return torch.cholesky_inverse(chol).movedim((-2, -1), (0, 1)), info == 0


def _reduce(diag: Tensor, lower: Tensor) -> tuple[_Reduction, Tensor]:
    """Factor B scalar banded systems by parallel cyclic reduction: log2(N) levels of vectorised
    W x W block products over all blocks at once, instead of T sequential steps. diag (B, T),
    lower (B|1, T, W) -> _Reduction, ok (B,)."""
    b, t_len = diag.shape
    w = lower.shape[-1]
    lower = lower.expand(b, t_len, w)
    n = -(-t_len // w)
    pad = n * w - t_len
    d_pad = torch.nn.functional.pad(diag, (0, pad), value=1.0).reshape(b, n, w)
    frame = torch.arange(n * w, device=diag.device)
    k_idx = torch.arange(1, w + 1, device=diag.device)
    c_pad = torch.nn.functional.pad(lower, (0, 0, 0, pad))
    c_pad = torch.where(frame[:, None] >= k_idx, c_pad, 0.0).reshape(b, n, w, w)  # [i, r, k-1] = A[iW+r, iW+r-k]
    zero = diag.new_zeros(b, n)
    rows_d = [[zero] * w for _ in range(w)]
    rows_l = [[zero] * w for _ in range(w)]
    for r in range(w):
        rows_d[r][r] = d_pad[:, :, r]
        for r2 in range(r):  # inside the block
            rows_d[r][r2] = rows_d[r2][r] = c_pad[:, :, r, r - r2 - 1]
        for r2 in range(r, w):  # block i row r, block i-1 column r2: k = W + r - r2 <= W
            rows_l[r][r2] = c_pad[:, :, r, w + r - r2 - 1]
    big_d = torch.stack([torch.stack(row) for row in rows_d])  # (W, W, B, N)
    big_l = torch.stack([torch.stack(row) for row in rows_l])
    big_u = _shift(big_l, -1).transpose(0, 1)  # U_i = L_{i+1}^T
    ok = torch.ones(b, dtype=torch.bool, device=diag.device)
    alphas, betas = [], []
    s = 1
    while True:
        inv, good = _spd_inverse(big_d)
        ok &= good.all(-1)
        if s >= n:
            break
        alpha = -_bmm(big_l, _shift(inv, s))
        beta = -_bmm(big_u, _shift(inv, -s))
        big_d = big_d + _bmm(alpha, _shift(big_u, s)) + _bmm(beta, _shift(big_l, -s))
        big_l, big_u = _bmm(alpha, _shift(big_l, s)), _bmm(beta, _shift(big_u, -s))
        alphas.append(alpha)
        betas.append(beta)
        s *= 2
    if not bool(ok.all()):
        inv = torch.where(ok[:, None], inv, torch.eye(w, dtype=diag.dtype, device=diag.device)[:, :, None, None])
        alphas = [torch.where(ok[:, None], a, 0.0) for a in alphas]
        betas = [torch.where(ok[:, None], a, 0.0) for a in betas]
    return _Reduction(tuple(alphas), tuple(betas), inv, diag, lower), ok


def _solve_reduced(f: _Reduction, b: Tensor) -> Tensor:
    """b (B, T) -> x (B, T) with `_reduce`'s factor."""
    bsz, t_len = b.shape
    w, n = f.inv.shape[0], f.inv.shape[-1]
    x = torch.nn.functional.pad(b, (0, n * w - t_len)).reshape(bsz, n, w).permute(2, 0, 1)[:, None]  # (W, 1, B, N)
    s = 1
    for alpha, beta in zip(f.alpha, f.beta):
        x = x + _bmm(alpha, _shift(x, s)) + _bmm(beta, _shift(x, -s))
        s *= 2
    return _bmm(f.inv, x)[:, 0].permute(1, 2, 0).reshape(bsz, n * w)[:, :t_len]


def _split(a: BlockBanded) -> Tensor:
    """(D,) bool: dofs whose rows of every diagonal block are diagonal (decoupled from the others;
    only meaningful with diagonal couplings, which couple a dof only with itself)."""
    off = a.diagonal.ne(0)
    off.diagonal(dim1=-2, dim2=-1).fill_(False)
    return ~off.flatten(0, -3).any(0).any(-1)


def factorize(a: BlockBanded) -> tuple[BandedFactor, Tensor]:
    """Block Cholesky of the symmetric positive definite `a` (see module docstring).

    -> BandedFactor, ok (...,) bool: False where a pivot was not positive definite (that system's
    factor is then meaningless but finite; the other systems are unaffected)."""
    t_len, w, d = _check(a, "factorize")
    batch = a.diagonal.shape[:-3]
    dg = a.diagonal.reshape(-1, t_len, d, d)
    vec = a.coupling_is_diagonal
    lo = a.lower.reshape(-1, *a.lower.shape[-3 if vec else -4 :])
    b = dg.shape[0]
    alone = _split(a) if vec and d > 1 else torch.zeros(d, dtype=torch.bool, device=dg.device)
    decoupled = torch.nonzero(alone).flatten()
    coupled = torch.nonzero(~alone).flatten()
    u, n = decoupled.numel(), coupled.numel()
    ok = torch.ones(b, dtype=torch.bool, device=dg.device)
    dense = scalar = None
    if n:
        sub_dg = dg if u == 0 else dg[:, :, coupled][:, :, :, coupled]
        sub_lo = lo if u == 0 else lo[..., coupled]
        with one_thread():
            dense, good = _factor_dense(sub_dg, sub_lo)
        ok &= good
    if u:
        sd = dg.diagonal(dim1=-2, dim2=-1)[..., decoupled]  # (B, T, u)
        sl = lo[..., decoupled]  # (B|1, T, W, u)
        scalar, good = _reduce(
            sd.permute(0, 2, 1).reshape(b * u, t_len),
            sl.permute(0, 3, 1, 2).expand(b, u, t_len, w).reshape(b * u, t_len, w),
        )
        ok &= good.reshape(b, u).all(-1)
    return BandedFactor(dense, scalar, coupled, decoupled, tuple(batch), d), ok.reshape(batch)


def _solve_dense(f: _Chol, b: Tensor) -> Tensor:
    """f's system, b (B, T, n) -> x (B, T, n)."""
    bsz, t_len, n = b.shape
    w = f.coupling.shape[2]
    zero = b.new_zeros(bsz, n, 1)
    cit = f.inv_chol_t.unbind(1)
    blk = [c.unbind(1) for c in f.coupling.unbind(1)]  # blk[t][k-1] = B[t, k]
    rhs = b[..., None].unbind(1)
    y: list[Tensor] = [zero] * w
    for t in range(t_len):  # y_t = C_t^{-1} (b_t - sum_k B[t, k] y_{t-k})
        r = rhs[t]
        for k in range(1, min(w, t) + 1):
            r = torch.baddbmm(r, blk[t][k - 1], y[t - k + w], alpha=-1)
        y.append(cit[t].mT @ r)
    x: list[Tensor] = [zero] * (t_len + w)
    for t in range(t_len - 1, -1, -1):  # x_t = C_t^{-T} (y_t - sum_k B[t+k, k]^T x_{t+k})
        r = y[t + w]
        for k in range(1, min(w, t_len - 1 - t) + 1):
            r = torch.baddbmm(r, blk[t + k][k - 1].mT, x[t + k], alpha=-1)
        x[t] = cit[t] @ r
    return torch.stack(x[:t_len], 1)[..., 0]


def solve(f: BandedFactor, b: Tensor) -> Tensor:
    """Solve A x = b with `factorize`'s factor; b (..., T, D) -> x (..., T, D)."""
    if f.dense is not None:
        t_len = f.dense.inv_chol_t.shape[1]
    else:
        assert f.scalar is not None  # factorize fills at least one of the two
        t_len = f.scalar.diag.shape[1]
    if not isinstance(b, Tensor) or b.shape != (*f.batch, t_len, f.size):
        raise InputError(f"solve: b must have shape {(*f.batch, t_len, f.size)}, got {tuple(getattr(b, 'shape', ()))}")
    flat = b.reshape(-1, t_len, f.size)
    if f.scalar is None:
        assert f.dense is not None
        with one_thread():
            return _solve_dense(f.dense, flat).reshape(b.shape)
    x = torch.empty_like(flat)
    if f.dense is not None:
        with one_thread():
            x[..., f.coupled] = _solve_dense(f.dense, flat[..., f.coupled])
    u = f.decoupled.numel()
    xs = _solve_reduced(f.scalar, flat[..., f.decoupled].permute(0, 2, 1).reshape(-1, t_len))
    x[..., f.decoupled] = xs.reshape(-1, u, t_len).permute(0, 2, 1)
    return x.reshape(b.shape)


def _marginals(f: _Chol) -> Tensor:
    """Diagonal blocks of the inverse of f's system -> (B, T, n, n): Takahashi's recursion backwards
    over the inverse's band, S[t, t+1..t+W] = -C_t^{-T} G_t S[t+1..t+W, t+1..t+W] with
    G_t = [B[t+1, 1]^T .. B[t+W, W]^T], S[t, t] = C_t^{-T} (C_t^{-1} - G_t S[t+1..t+W, t])."""
    cit, cpl = f.inv_chol_t, f.coupling
    if cit.ndim == 2:  # 1 x 1 blocks
        cit, cpl = cit[..., None, None], cpl[..., None, None]
    bsz, t_len, n = cit.shape[0], cit.shape[1], cit.shape[-1]
    w = cpl.shape[2]
    out = cit.new_empty(bsz, t_len, n, n)
    big = cit.new_zeros(bsz, w * n, w * n)  # S over frames t+1 .. t+W (zero past the end)
    for t in range(t_len - 1, -1, -1):
        g = torch.cat(
            [cpl[:, t + k, k - 1].mT if t + k < t_len else cit.new_zeros(bsz, n, n) for k in range(1, w + 1)], dim=-1
        )  # (B, n, W n)
        r = -(cit[:, t] @ (g @ big))  # S[t, t+1 .. t+W]
        s_tt = cit[:, t] @ (cit[:, t].mT - g @ r.mT)
        s_tt = 0.5 * (s_tt + s_tt.mT)
        full = torch.cat([torch.cat([s_tt, r], -1), torch.cat([r.mT, big], -1)], -2)
        big = full[:, : w * n, : w * n]
        out[:, t] = s_tt
    return out


def marginal_blocks(f: BandedFactor) -> Tensor:
    """Diagonal blocks of A^{-1} from `factorize`'s factor -> (..., T, D, D): the marginal
    covariances of a Gaussian with precision A (module docstring; the inverse's band only)."""
    if f.scalar is None:
        assert f.dense is not None
        with one_thread():
            return _marginals(f.dense).reshape(*f.batch, f.dense.inv_chol_t.shape[1], f.size, f.size)
    u = f.decoupled.numel()
    bsz, t_len = f.scalar.diag.shape[0] // u, f.scalar.diag.shape[1]
    out = f.scalar.diag.new_zeros(bsz, t_len, f.size, f.size)
    if f.dense is not None:
        with one_thread():
            out[:, :, f.coupled[:, None], f.coupled] = _marginals(f.dense)
    chol, _ = _factor_scalar(f.scalar.diag, f.scalar.lower)  # sequential, once: the variances need L
    var = _marginals(chol)[..., 0, 0].reshape(bsz, u, t_len).permute(0, 2, 1)
    out[:, :, f.decoupled, f.decoupled] = var
    return out.reshape(*f.batch, t_len, f.size, f.size)


def matvec(a: BlockBanded, x: Tensor) -> Tensor:
    """A x; x (..., T, D) -> (..., T, D)."""
    t_len, w, _ = _check(a, "matvec")
    pad = torch.nn.functional.pad
    out = (a.diagonal @ x[..., None])[..., 0]
    for k in range(1, min(w, t_len - 1) + 1):
        if a.coupling_is_diagonal:
            blk = a.lower[..., k:, k - 1, :]
            below, above = blk * x[..., :-k, :], blk * x[..., k:, :]
        else:
            blk = a.lower[..., k:, k - 1, :, :]  # A[t, t-k] for t >= k
            below = (blk @ x[..., :-k, :, None])[..., 0]  # into row t
            above = (blk.mT @ x[..., k:, :, None])[..., 0]  # A[t-k, t] x[t] into row t-k
        out = out + pad(below, (0, 0, k, 0)) + pad(above, (0, 0, 0, k))
    return out


def to_dense(a: BlockBanded) -> Tensor:
    """The whole symmetric matrix (..., T*D, T*D). Small problems and tests only."""
    t_len, w, d = _check(a, "to_dense")
    out = a.diagonal.new_zeros(*a.diagonal.shape[:-3], t_len * d, t_len * d)
    for t in range(t_len):
        out[..., t * d : (t + 1) * d, t * d : (t + 1) * d] = a.diagonal[..., t, :, :]
        for k in range(1, min(w, t) + 1):
            blk = a.lower[..., t, k - 1, :] if a.coupling_is_diagonal else a.lower[..., t, k - 1, :, :]
            blk = torch.diag_embed(blk) if a.coupling_is_diagonal else blk
            out[..., t * d : (t + 1) * d, (t - k) * d : (t - k + 1) * d] = blk
            out[..., (t - k) * d : (t - k + 1) * d, t * d : (t + 1) * d] = blk.mT
    return out


def from_dense(matrix: Tensor, t_len: int, w: int) -> BlockBanded:
    """The `BlockBanded` (dense couplings) of a symmetric (..., T*D, T*D) matrix; entries more than W
    blocks off the diagonal are dropped."""
    d = matrix.shape[-1] // max(t_len, 1)
    if matrix.shape[-2:] != (t_len * d, t_len * d) or w < 1:
        raise InputError(f"from_dense: matrix {tuple(matrix.shape)} is not (..., T*D, T*D) with T={t_len}, W >= 1")
    blocks = matrix.unflatten(-1, (t_len, d)).unflatten(-3, (t_len, d))  # (..., T, D, T, D)
    diagonal = torch.stack([blocks[..., t, :, t, :] for t in range(t_len)], dim=-3)
    lower = matrix.new_zeros(*matrix.shape[:-2], t_len, w, d, d)
    for t in range(t_len):
        for k in range(1, min(w, t) + 1):
            lower[..., t, k - 1, :, :] = blocks[..., t, :, t - k, :]
    return BlockBanded(diagonal, lower)
