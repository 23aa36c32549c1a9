"""Symmetric block-banded matrices over time: block LDL^T factor, solves, products and the diagonal
blocks of the inverse, without ever forming the dense (T*D) x (T*D) matrix.

A symmetric matrix A of T x T blocks of size D x D whose blocks vanish more than W block-rows off
the diagonal (W = 1: block-tridiagonal, a velocity prior; W = 2: block-pentadiagonal, an
acceleration prior) is held as a `BlockBanded`:

    diagonal (..., T, D, D)      A[t, t]
    lower    (..., T, W, D, D)   lower[..., t, k-1] = A[t, t-k] (ignored where t-k < 0), or
             (..., T, W, D)      the same blocks when they are diagonal matrices (a smoothness prior
                                 on each dof couples a dof only with itself), stored as vectors

with any leading batch dims (independent systems, solved at once). The factor is the block
LDL^T of A, A = L Dg L^T with L unit block-lower-triangular of the same band, kept as

    pivots_inv P (..., T, D, D) = Dg[t]^{-1}  and  U (..., T, W, D, D | D) = L[t, t-k] Dg[t-k],

computed one block row at a time (W is small, D x D products batched over the leading dims):

    U[t, k] = A[t, t-k] - sum_{j=k+1..W} U[t, j] P[t-j] U[t-k, j-k]^T
    Dg[t]   = A[t, t]   - sum_{k=1..W}   U[t, k] P[t-k] U[t, k]^T,   P[t] = Dg[t]^{-1} (Cholesky)

With diagonal couplings U[t, W] = A[t, t-W] stays diagonal and every product with it is a scaling,
which is what makes the smoother's pentadiagonal systems cheap (3 D x D products and one D x D
Cholesky + inverse per frame). Marginal covariances (diagonal blocks of S = A^{-1}) come from
S = Dg^{-1} L^{-1} + (I - L^T) S, run backwards in t over S's own band only (Takahashi):

    S[t, s] = delta_ts P[t] - sum_{k=1..W} P[t] U[t+k, k]^T S[t+k, s]      (s >= t)

    factorize(A) -> BandedFactor, ok (...,) bool
    solve(factor, b (..., T, D)) -> x (..., T, D)           A x = b
    matvec(A, x (..., T, D)) -> A x (..., T, D)
    marginal_blocks(factor) -> (..., T, D, D)               diagonal blocks of A^{-1}
    to_dense(A) -> (..., T*D, T*D); from_dense(M, T, W)     small problems and tests only

Work and memory are O(T W^2 D^3) and O(T W D^2). Everything follows the inputs' dtype and device.
"""

from __future__ import annotations

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
        return self.diagonal.shape[-3], self.lower.shape[-3 if not self.coupling_is_diagonal else -2], \
            self.diagonal.shape[-1]


class BandedFactor(NamedTuple):
    """Block LDL^T factor of a `BlockBanded`: pivots_inv (..., T, D, D) = P[t]; coupling
    (..., T, W, D, D) or (..., T, W, D) = U[t, k] (index k-1), zero where t-k < 0."""

    pivots_inv: Tensor
    coupling: Tensor


def _check(a: BlockBanded, who: str) -> tuple[int, int, int]:
    dg, lo = a.diagonal, a.lower
    ok = isinstance(dg, Tensor) and isinstance(lo, Tensor) and dg.ndim >= 3 and dg.shape[-1] == dg.shape[-2]
    if ok:
        t_len, d = dg.shape[-3], dg.shape[-1]
        ok = (lo.ndim == dg.ndim + 1 and lo.shape[-4] == t_len and lo.shape[-2:] == (d, d)) or \
            (lo.ndim == dg.ndim and lo.shape[-3] == t_len and lo.shape[-1] == d)
    if not ok:
        raise InputError(f"{who}: expected diagonal (..., T, D, D) and lower (..., T, W, D, D) or (..., T, W, D), "
                         f"got {tuple(getattr(dg, 'shape', ()))} and {tuple(getattr(lo, 'shape', ()))}")
    return a.shape


# products where either factor may be a diagonal matrix held as a vector (..., D)


def _is_vec(x: Tensor, mat: Tensor) -> bool:
    return x.ndim < mat.ndim


def _mm(a: Tensor, b: Tensor, like: Tensor) -> Tensor:
    """a @ b, each (..., D, D) or a diagonal (..., D); the result is a vector only if both are."""
    va, vb = _is_vec(a, like), _is_vec(b, like)
    if va and vb:
        return a * b
    if va:
        return a[..., :, None] * b
    if vb:
        return a * b[..., None, :]
    return a @ b


def _t(a: Tensor, like: Tensor) -> Tensor:
    return a if _is_vec(a, like) else a.mT


def _sandwich(u: Tensor, p: Tensor) -> Tensor:
    """u p u^T for p (..., D, D) and u dense or diagonal."""
    if _is_vec(u, p):
        return p * (u[..., :, None] * u[..., None, :])
    return u @ p @ u.mT


def _dense(x: Tensor, like: Tensor) -> Tensor:
    return torch.diag_embed(x) if _is_vec(x, like) else x


def factorize(a: BlockBanded) -> tuple[BandedFactor, Tensor]:
    """Block LDL^T of the symmetric positive definite `a` (see module docstring).

    -> BandedFactor, ok (...,) bool: False where a pivot was not positive definite (that system's
    factor is then meaningless but finite; the other systems are unaffected)."""
    t_len, w, d = _check(a, "factorize")
    dg = a.diagonal
    ref = dg[..., 0, :, :]  # a block: products below tell diagonal vectors from matrices by it
    batch = dg.shape[:-3]
    eye = torch.eye(d, dtype=dg.dtype, device=dg.device)
    vec = a.coupling_is_diagonal
    ok = torch.ones(batch, dtype=torch.bool, device=dg.device)
    p_list: list[Tensor] = []
    u_list: list[list[Tensor]] = []  # u_list[t][k-1] = U[t, k]
    zero_mat = dg.new_zeros(*batch, d, d)
    for t in range(t_len):
        row: list[Tensor] = []
        kmax = min(w, t)
        for k in range(w, 0, -1):
            if k > kmax:
                row.append(zero_mat if not vec or k < w else dg.new_zeros(*batch, d))
                continue
            u = a.lower[..., t, k - 1, :, :] if not vec else a.lower[..., t, k - 1, :]
            for j in range(k + 1, kmax + 1):  # - U[t, j] P[t-j] U[t-k, j-k]^T
                uj = row[w - j]
                u = _dense(u, ref) - _mm(uj, _mm(p_list[t - j], _t(u_list[t - k][j - k - 1], ref), ref), ref)
            if vec and k < w:
                u = _dense(u, ref)  # U[t, k] for k < W fills in (dense) once a farther coupling exists
            row.append(u)
        row.reverse()  # row[k-1] = U[t, k]
        pivot = dg[..., t, :, :]
        for k in range(1, kmax + 1):
            pivot = pivot - _sandwich(row[k - 1], p_list[t - k])
        chol, info = torch.linalg.cholesky_ex(pivot)
        good = info == 0
        ok &= good
        p_list.append(torch.cholesky_inverse(torch.where(good[..., None, None], chol, eye)))
        u_list.append(row)
    pivots_inv = torch.stack(p_list, dim=-3)
    if vec and w > 1:  # U[t, W] diagonal, U[t, k < W] dense: store all dense
        coupling = torch.stack([torch.stack([_dense(u, ref) for u in r], dim=-3) for r in u_list], dim=-4)
    elif vec:
        coupling = torch.stack([torch.stack(r, dim=-2) for r in u_list], dim=-3)
    else:
        coupling = torch.stack([torch.stack(r, dim=-3) for r in u_list], dim=-4)
    return BandedFactor(pivots_inv, coupling), ok


def _u(f: BandedFactor, t: int, k: int) -> Tensor:
    """U[t, k] as stored (matrix or diagonal vector)."""
    c = f.coupling
    return c[..., t, k - 1, :] if c.ndim == f.pivots_inv.ndim else c[..., t, k - 1, :, :]


def solve(f: BandedFactor, b: Tensor) -> Tensor:
    """Solve A x = b with `factorize`'s factor; b (..., T, D) -> x (..., T, D)."""
    p = f.pivots_inv
    ref = p[..., 0, :, :]
    t_len, d = p.shape[-3], p.shape[-1]
    w = f.coupling.shape[-2] if f.coupling.ndim == p.ndim else f.coupling.shape[-3]
    if b.shape[-2:] != (t_len, d):
        raise InputError(f"solve: b must have shape (..., {t_len}, {d}), got {tuple(b.shape)}")
    y: list[Tensor] = []  # y[t] = P[t] z[t], z = L^{-1} b
    for t in range(t_len):
        z = b[..., t, :]
        for k in range(1, min(w, t) + 1):  # z[t] = b[t] - sum_k U[t, k] P[t-k] z[t-k] = ... - U y[t-k]
            z = z - _mv(_u(f, t, k), y[t - k], ref)
        y.append((p[..., t, :, :] @ z[..., None])[..., 0])
    x: list[Tensor] = [y[0]] * t_len
    for t in range(t_len - 1, -1, -1):  # x[t] = y[t] - P[t] sum_k U[t+k, k]^T x[t+k]
        acc = None
        for k in range(1, min(w, t_len - 1 - t) + 1):
            v = _mv(_t(_u(f, t + k, k), ref), x[t + k], ref)
            acc = v if acc is None else acc + v
        x[t] = y[t] if acc is None else y[t] - (p[..., t, :, :] @ acc[..., None])[..., 0]
    return torch.stack(x, dim=-2)


def _mv(a: Tensor, v: Tensor, like: Tensor) -> Tensor:
    """a v for a (..., D, D) or a diagonal (..., D), v (..., D)."""
    return a * v if _is_vec(a, like) else (a @ v[..., None])[..., 0]


def matvec(a: BlockBanded, x: Tensor) -> Tensor:
    """A x; x (..., T, D) -> (..., T, D)."""
    t_len, w, d = _check(a, "matvec")
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


def marginal_blocks(f: BandedFactor) -> Tensor:
    """Diagonal blocks of A^{-1} from `factorize`'s factor -> (..., T, D, D): the marginal
    covariances of a Gaussian with precision A (module docstring; the inverse's band only)."""
    p = f.pivots_inv
    ref = p[..., 0, :, :]
    t_len = p.shape[-3]
    w = f.coupling.shape[-2] if f.coupling.ndim == p.ndim else f.coupling.shape[-3]
    sigma: list[list[Tensor] | None] = [None] * t_len  # sigma[t][j] = S[t, t+j], j = 0..W

    def s(i: int, j: int) -> Tensor:  # S[i, j] with |i - j| <= W, both already computed
        return sigma[i][j - i] if j >= i else sigma[j][i - j].mT

    for t in range(t_len - 1, -1, -1):
        ks = range(1, min(w, t_len - 1 - t) + 1)
        pt = p[..., t, :, :]
        row: list[Tensor] = [pt] * (len(ks) + 1)
        for j in ks:  # S[t, t+j] = -P[t] sum_k U[t+k, k]^T S[t+k, t+j]
            acc = sum(_mm(_t(_u(f, t + k, k), ref), s(t + k, t + j), ref) for k in ks)
            row[j] = -(pt @ acc)
        if len(ks):
            acc = sum(_mm(_t(_u(f, t + k, k), ref), row[k].mT, ref) for k in ks)
            diag = pt - pt @ acc
            row[0] = 0.5 * (diag + diag.mT)
        sigma[t] = row
    return torch.stack([r[0] for r in sigma], dim=-3)


def to_dense(a: BlockBanded) -> Tensor:
    """The whole symmetric matrix (..., T*D, T*D). Small problems and tests only."""
    t_len, w, d = _check(a, "to_dense")
    out = a.diagonal.new_zeros(*a.diagonal.shape[:-3], t_len * d, t_len * d)
    for t in range(t_len):
        out[..., t * d:(t + 1) * d, t * d:(t + 1) * d] = a.diagonal[..., t, :, :]
        for k in range(1, min(w, t) + 1):
            blk = a.lower[..., t, k - 1, :] if a.coupling_is_diagonal else a.lower[..., t, k - 1, :, :]
            blk = _dense(blk, a.diagonal[..., 0, :, :])
            out[..., t * d:(t + 1) * d, (t - k) * d:(t - k + 1) * d] = blk
            out[..., (t - k) * d:(t - k + 1) * d, t * d:(t + 1) * d] = blk.mT
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
