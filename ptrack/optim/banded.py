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
factor keeps C_t^{-T} (one triangular inverse per frame) and each row's blocks side by side,
R_t = [B[t, W] .. B[t, 1]] (n x W n), so the pivot's update is one product R_t R_t^T and a solve is
two sweeps of two matrix-vector products per frame (the last W solutions read as one window).
Marginal covariances (diagonal blocks of S = A^{-1}) come from L^T S = L^{-1}, run
backwards in t over S's own band only (Takahashi):

    S[t, s] = C_t^{-T} (delta_ts C_t^{-1} - sum_{k=1..W} B[t+k, k]^T S[t+k, s])      (s >= t)

Two halves. The sweep is T sequential steps of small products, so its cost is mostly dispatch and
one core. `factorize` (T >= `HALVES_MIN_FRAMES`) orders the unknowns as the top frames 0..m-1, the
bottom frames m+W..T-1 and last the W separator frames m..m+W-1 between them (m = (T-W)/2): the top
and the bottom do not touch, so both are factored by the recursion above at once, the bottom
backwards in time (its own reversed system, couplings transposed), in T/2 steps over 2B systems
(half the dispatch of one sweep over T). Their Cholesky rows towards the separator,
Z_h = L_h^{-1} A[h, s], live on each half's last W frames only, and the separator's Schur
complement A_ss - Z_top^T Z_top - Z_bot^T Z_bot (W n x W n) is factored last. It is the same
factorisation of the reordered matrix (no extra fill, the same flops); solves are the two halves'
sweeps around the separator's, and the marginals add to each half's own (Takahashi) the part through
the separator, V_t S_ss V_t^T with V = A_hh^{-1} A_hs.

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

CPU fast path. The block Cholesky's T (or T/2) sequential steps and the solve's two sweeps are
small products whose cost on the CPU is mostly per-call overhead (~10-20 us a torch op of these sizes
against ~1-3 us a numpy call). For CPU float32/64 tensors without autograd they run on numpy and
LAPACK (`NUMPY_LOOPS`; the same recursion, in place in the factor's tensors: `_factor_dense_numpy`,
`_sweep_numpy`), and the decoupled dofs' scalar systems by LAPACK's banded Cholesky (pbtrf/pbtrs,
one call per system, `_band_lapack`) instead of the cyclic reduction's few hundred small ops; the
torch code is the reference and runs on every other device (tests compare the two).

Work and memory are O(T W^2 n^3) and O(T W n^2) for the coupled dofs. Everything follows the
inputs' dtype and device.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ptrack.errors import InputError
from ptrack.threads import one_thread

HALVES_MIN_FRAMES = 32  # `factorize` splits a system of this many frames or more into two halves
NUMPY_LOOPS = True  # the sequential loops on numpy/LAPACK for CPU tensors (`numpy_path`); False: torch's


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
    inv_chol_t (B, T, n, n) = C_t^{-T}; coupling (B, T, n, W n) = the rows R_t = [B[t, W] .. B[t, 1]]
    (B[t, k] at [:, t, :, (W-k) n:(W-k+1) n]), zero where t-k < 0. For n = 1 (decoupled dofs) both
    are held as (B, T) and (B, T, W)."""

    inv_chol_t: Tensor
    coupling: Tensor


class BandedFactor(NamedTuple):
    """Block Cholesky factor A = L L^T of a `BlockBanded` (module docstring). dense: the factor of
    the coupled dofs `coupled` (n,) (long), or None; scalar: the decoupled dofs `decoupled` (u,) as
    B * u independent systems of 1 x 1 blocks, or None; batch: the leading dims; size: D."""

    dense: _Chol | _Twisted | None
    scalar: _Reduction | _ScalarBand | None
    coupled: Tensor
    decoupled: Tensor
    batch: tuple
    size: int


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
    factor, ok (B,). One block row per step (module docstring), written in place into the row
    R_t = [B[t, W] .. B[t, 1]] so that the pivot's update is one product, C_t C_t^T = A[t, t] - R_t R_t^T.
    The loop is T sequential steps of ~6 small ops, so it is written for the fewest: per-frame views
    made once (unbind), products by bmm with out= into the factor (no cat, no copies), the pivot's
    upper factor U_t = C_t^T inverted straight into C_t^{-T} = U_t^{-1}."""
    if numpy_path(diag):
        return _factor_dense_numpy(diag, lower)
    b, t_len, n = diag.shape[0], diag.shape[1], diag.shape[-1]
    vec = lower.ndim == 4
    w = lower.shape[2]
    lower = lower.expand(b, *lower.shape[1:])
    eye = torch.eye(n, dtype=diag.dtype, device=diag.device).expand(b, n, n)
    # frame-major views, one per frame (unbind: one call instead of T integer indexings)
    far = (lower[:, :, w - 1, :, None] if vec else lower[:, :, w - 1]).transpose(0, 1).unbind(0)  # A[t, t-W]
    near = [
        (torch.diag_embed(lower[:, :, k]) if vec else lower[:, :, k]).transpose(0, 1).unbind(0) for k in range(w - 1)
    ]
    a_tt = diag.transpose(0, 1).unbind(0)
    # the factor is written in place, frame-major (frame t's C_t^{-T} and R_t contiguous, as the
    # sweeps read them); the blocks B[t, k] with t - k < 0 stay zero
    inv_fm = diag.new_empty(t_len, b, n, n)
    rows = diag.new_empty(t_len, b, n, w * n)  # R_t
    rows[:w].zero_()
    cit = inv_fm.unbind(0)  # C_t^{-T}
    blocks = [[r[..., (w - k) * n : (w - k + 1) * n] for k in range(1, w + 1)] for r in rows.unbind(0)]  # B[t, k]
    infos = []
    for t in range(t_len):
        blk = blocks[t]
        if t >= w:  # B[t, W] = A[t, t-W] C_{t-W}^{-T}
            (torch.mul if vec else torch.bmm)(far[t], cit[t - w], out=blk[w - 1])
        for k in range(min(w - 1, t), 0, -1):  # B[t, k] = (A[t, t-k] - sum_j B[t, j] B[t-k, j-k]^T) C_{t-k}^{-T}
            x = near[k - 1][t]
            for j in range(k + 1, min(w, t) + 1):
                x = torch.baddbmm(x, blk[j - 1], blocks[t - k][j - k - 1].mT, alpha=-1)
            torch.bmm(x, cit[t - k], out=blk[k - 1])
        row = rows[t]
        upper, info = torch.linalg.cholesky_ex(torch.baddbmm(a_tt[t], row, row.mT, alpha=-1), upper=True)
        infos.append(info)
        torch.linalg.solve_triangular(upper, eye, upper=True, out=cit[t])  # U_t^{-1} = C_t^{-T}
    ok = (torch.stack(infos, -1) == 0).all(-1) if infos else torch.ones(b, dtype=torch.bool, device=diag.device)
    inv_t, coupling = inv_fm.transpose(0, 1), rows.transpose(0, 1)  # (B, T, ...) views
    if not bool(ok.all()):  # a failed system's factor: finite stand-ins (identity pivots, no couplings)
        inv_t = torch.where(ok[:, None, None, None], inv_t, eye[:, None])
        coupling = torch.where(ok[:, None, None, None], coupling, 0.0)
    return _Chol(inv_t, coupling), ok


def numpy_path(x: Tensor) -> bool:
    """Whether the CPU fast paths on numpy/LAPACK apply to x (the sequential loops here, the batch
    linearisation's J^T J): CPU float32/64 tensors without autograd, unless `NUMPY_LOOPS` is off (the
    torch code is the reference)."""
    return NUMPY_LOOPS and x.device.type == "cpu" and x.dtype in (torch.float32, torch.float64) and not x.requires_grad


def _factor_dense_numpy(diag: Tensor, lower: Tensor) -> tuple[_Chol, Tensor]:
    """`_factor_dense` on the CPU by numpy and LAPACK (potrf, trtri), the same recursion step by step:
    a numpy call costs ~1-3 us against ~10-20 us for a torch op of these sizes, numpy turns R_t R_t^T
    into one syrk, and trtri inverts C_t in place (n^3 / 3 flops against a triangular solve of the
    identity's n^3). Each system of the batch is stepped by 2-D calls; C_t^{-T} is written straight
    into the factor: the pivot's Schur complement is formed in frame t's slot, factored and inverted
    there in place (the lower triangle of its column-major view holds C_t^{-1}, i.e. C_t^{-T} row-major)."""
    from scipy.linalg.lapack import get_lapack_funcs

    b, t_len, n = diag.shape[0], diag.shape[1], diag.shape[-1]
    vec = lower.ndim == 4
    w = lower.shape[2]
    dg = diag.numpy().transpose(1, 0, 2, 3)  # frame-major views (T, B, ...)
    lo = lower.expand(b, *lower.shape[1:]).numpy().swapaxes(0, 1)
    inv = np.empty((t_len, b, n, n), dtype=dg.dtype)
    rows = np.zeros((t_len, b, n, w * n), dtype=dg.dtype)  # R_t; B[t, k] with t - k < 0 stay zero
    potrf, trtri = get_lapack_funcs(("potrf", "trtri"), (inv,))
    failed = np.zeros(b, dtype=bool)
    ar = np.arange(n)
    for t in range(t_len):  # the products batched over the B systems (numpy loops over them in C)
        row = rows[t]
        if t >= w:  # B[t, W] = A[t, t-W] C_{t-W}^{-T}
            if vec:
                np.multiply(lo[t, :, w - 1, :, None], inv[t - w], out=row[..., :n])
            else:
                np.matmul(lo[t, :, w - 1], inv[t - w], out=row[..., :n])
        for k in range(min(w - 1, t), 0, -1):  # B[t, k] = (A[t, t-k] - sum_j B[t, j] B[t-k, j-k]^T) C_{t-k}^{-T}
            x = np.zeros((b, n, n), dtype=dg.dtype) if vec else lo[t, :, k - 1].copy()
            if vec:
                x[:, ar, ar] = lo[t, :, k - 1]
            for j in range(k + 1, min(w, t) + 1):
                prev = rows[t - k, :, :, (w - j + k) * n : (w - j + k + 1) * n]  # B[t-k, j-k]
                x -= row[..., (w - j) * n : (w - j + 1) * n] @ prev.swapaxes(-1, -2)
            np.matmul(x, inv[t - k], out=row[..., (w - k) * n : (w - k + 1) * n])
        s = inv[t]
        np.matmul(row, row.swapaxes(-1, -2), out=s)
        np.subtract(dg[t], s, out=s)  # C_t C_t^T = A[t, t] - R_t R_t^T
        for i in range(b):  # LAPACK in place on the column-major view: C_t, then C_t^{-1}, in its lower triangle
            si = s[i].T
            c, info = potrf(si, lower=1, clean=1, overwrite_a=1)
            if info == 0:
                c, info = trtri(c, lower=1, overwrite_c=1)
            if c is not si:  # not in place (f2py copied): write it back
                si[...] = c
            if info:
                failed[i] = True
    ok = torch.from_numpy(~failed).to(diag.device)
    eye = torch.eye(n, dtype=diag.dtype, device=diag.device).expand(b, n, n)
    inv_t, coupling = torch.from_numpy(inv).transpose(0, 1), torch.from_numpy(rows).transpose(0, 1)
    if bool(failed.any()):  # a failed system's factor: finite stand-ins (identity pivots, no couplings)
        inv_t = torch.where(ok[:, None, None, None], inv_t, eye[:, None])
        coupling = torch.where(ok[:, None, None, None], coupling, 0.0)
    return _Chol(inv_t, coupling), ok


class _Twisted(NamedTuple):
    """Block Cholesky of a system split at its middle (module docstring, "Two halves"), leading dims
    flattened to B: halves, the factor (2B, M, ...) of the top half (frames 0..m-1, preceded by
    M - m identity frames) stacked over the bottom half in reverse order (frames T-1 down to m+W);
    z (2B, W n, W n), Z = L_h^{-1} A[h, s] on each half's last W frames (the bottom half's separator
    columns in reverse frame order); sep_inv (B, W n, W n) = C_s^{-1}, the factor of the separator's
    Schur complement A_ss - Z_top^T Z_top - Z_bot^T Z_bot; top = m."""

    halves: _Chol
    z: Tensor
    sep_inv: Tensor
    top: int


def _gather(diag: Tensor, frames: Tensor, dofs: Tensor | None) -> Tensor:
    """diag (B, T, D, D) -> (B, *frames.shape, n, n): the blocks of the given frames, restricted to
    the dofs (None: all), by one flat index of each block's n^2 entries (on the bench's 300 x 62 x 62
    to 44 dofs 0.6 + 0.8 ms against 5.6 ms for one advanced index, whose gather along the last dim is
    slow) and the frames; the entries first when most frames are taken (no (B, T, D, D)-sized copy
    on the way: 3.3 -> 2.7 ms for the two halves' 298 of 300 frames)."""
    if dofs is None:
        picked = diag.index_select(1, frames.flatten())
    else:
        d, n = diag.shape[-1], dofs.numel()
        entries = (dofs[:, None] * d + dofs).flatten()  # (n^2,) row-major within a block
        if 2 * frames.numel() >= diag.shape[1]:
            picked = diag.flatten(-2).index_select(-1, entries).index_select(1, frames.flatten())
        else:
            picked = diag.index_select(1, frames.flatten()).flatten(-2).index_select(-1, entries)
        picked = picked.unflatten(-1, (n, n))
    return picked.reshape(diag.shape[0], *frames.shape, *picked.shape[-2:])


def _split_halves(diag: Tensor, lower: Tensor, m: int, dofs: Tensor | None) -> tuple[Tensor, Tensor]:
    """The two halves of `_Twisted` as one system of 2B: diag (B, T, D, D) (its dofs only, None: all),
    lower (B|1, T, W, n[, n]) -> (2B, M, n, n), (2B, M, W, n[, n]), M = T - W - m >= m; the top padded
    in front with identity frames, the bottom reversed (couplings transposed: A'[r, r-k] =
    A[T-1-r+k, T-1-r]^T)."""
    b, t_len = diag.shape[0], diag.shape[1]
    n = lower.shape[-1]
    w = lower.shape[2]
    vec = lower.ndim == 4
    big_m = t_len - w - m
    pad = big_m - m
    dev = diag.device
    frames = torch.stack(
        [torch.arange(-pad, m, device=dev).clamp(min=0), torch.arange(t_len - 1, m + w - 1, -1, device=dev)]
    )  # (2, M): top (pad frames read frame 0, then set to identity), bottom reversed
    d2 = _gather(diag, frames, dofs).transpose(0, 1).reshape(2 * b, big_m, n, n)
    if pad:
        d2[:b, :pad] = torch.eye(n, dtype=diag.dtype, device=dev)
    lower = lower.expand(b, *lower.shape[1:])
    ks = torch.arange(1, w + 1, device=dev)
    shape = (1, big_m, w) + (1,) * (lower.ndim - 3)
    keep = ((torch.arange(big_m, device=dev)[:, None] - pad) >= ks).reshape(shape)  # top: A[t, t-k] for t-k >= 0
    top_l = torch.where(keep, lower[:, frames[0]], 0.0)
    rev = lower[:, frames[1]]  # rev[r, k-1] = A[T-1-r, T-1-r-k]
    bot_l = []
    for k in range(1, w + 1):  # A'[r, r-k] = A[T-1-r+k, T-1-r]^T = rev[r-k, k-1]^T for r >= k
        blk = rev[:, : big_m - k, k - 1]
        bot_l.append(torch.cat([blk.new_zeros(b, k, *blk.shape[2:]), blk if vec else blk.mT], 1))
    return d2, torch.cat([top_l, torch.stack(bot_l, 2)])


def _block(diag: Tensor, lower: Tensor, t: int, s: int, dofs: Tensor | None) -> Tensor:
    """A[t, s] (B, n, n) for |t - s| <= W of a system diag (B, T, D, D) (its dofs only), lower
    (B, T, W, n[, n])."""
    if t == s:
        return _gather(diag, torch.tensor(t, device=diag.device), dofs)
    if t < s:
        return _block(diag, lower, s, t, dofs).mT
    blk = lower[:, t, t - s - 1]
    return torch.diag_embed(blk) if lower.ndim == 4 else blk


def _factor_twisted(diag: Tensor, lower: Tensor, dofs: Tensor | None) -> tuple[_Twisted, Tensor]:
    """diag (B, T, D, D) (its dofs only; None: all), lower (B|1, T, W, n[, n]) with T >= 4W ->
    `_Twisted`, ok (B,): both halves factored by one sweep of T/2 steps over the 2B systems, then
    the W-frame separator."""
    b, t_len = diag.shape[0], diag.shape[1]
    n = lower.shape[-1]
    w = lower.shape[2]
    m = (t_len - w) // 2
    big_m = t_len - w - m
    d2, l2 = _split_halves(diag, lower, m, dofs)
    halves, ok2 = _factor_dense(d2, l2)
    lower = lower.expand(b, *lower.shape[1:])
    # E = A[h, s] on each half's last W frames (n x W n each): top frame m-W+c against separator
    # frame m+i; bottom frame m+2W-1-c (reversed index M-W+c) against m+W-1-i (reversed M+i)
    e = d2.new_zeros(2 * b, w, n, w * n)
    for c in range(w):
        for i in range(w):
            if i <= c:  # |frame - separator frame| = W - c + i <= W
                e[:b, c, :, i * n : (i + 1) * n] = _block(diag, lower, m - w + c, m + i, dofs)
                e[b:, c, :, i * n : (i + 1) * n] = _block(diag, lower, m + 2 * w - 1 - c, m + w - 1 - i, dofs)
    # Z = L_h^{-1} E: the forward sweep from zeros, over the last W frames only (E vanishes before)
    cit, cpl = halves.inv_chol_t, halves.coupling
    z: list[Tensor] = []
    for c in range(w):
        t = big_m - w + c
        r = e[:, c]
        for k in range(1, c + 1):
            r = torch.baddbmm(r, cpl[:, t, :, (w - k) * n : (w - k + 1) * n], z[c - k], alpha=-1)
        z.append(cit[:, t].mT @ r)
    zz = torch.cat(z, 1)  # (2B, W n, W n)
    y = zz.mT @ zz
    # the bottom's separator columns run backwards in time: reverse their frame blocks
    rev = torch.arange(w - 1, -1, -1, device=diag.device)
    idx = (rev[:, None] * n + torch.arange(n, device=diag.device)).flatten()
    sep = torch.cat(
        [torch.cat([_block(diag, lower, m + i, m + j, dofs) for j in range(w)], -1) for i in range(w)], -2
    )  # (B, W n, W n)
    schur = sep - y[:b] - y[b:][:, idx][:, :, idx]
    chol, info = torch.linalg.cholesky_ex(schur)
    eye = torch.eye(w * n, dtype=d2.dtype, device=d2.device).expand(b, w * n, w * n)
    sep_inv = torch.linalg.solve_triangular(chol, eye, upper=False)
    ok = ok2[:b] & ok2[b:] & (info == 0)
    if not bool(ok.all()):
        sep_inv = torch.where(ok[:, None, None], sep_inv, eye)
    return _Twisted(halves, zz, sep_inv, m), ok


def _solve_twisted(f: _Twisted, b: Tensor) -> Tensor:
    """f's system, b (B, T, n) -> x (B, T, n): forward sweeps of the two halves at once, the
    separator, then their backward sweeps."""
    bsz, t_len, n = b.shape
    w = f.sep_inv.shape[-1] // n
    m = f.top
    big_m = t_len - w - m
    pad = big_m - m
    # the halves' right-hand sides after W zero frames (and the top's M - m padding frames)
    buf = torch.cat([torch.nn.functional.pad(b[:, :m], (0, 0, w + pad, 0)), _padded(b[:, m + w :].flip(1), w)])
    _sweep(f.halves, buf)  # buf[:, W:] = y (2B, M, n)
    last = buf[:, w + big_m - w :].reshape(2 * bsz, w * n, 1)
    zy = (f.z.mT @ last)[..., 0]  # (2B, W n): the bottom's in reversed frame order
    zy_bot = zy[bsz:].reshape(bsz, w, n).flip(1).reshape(bsz, w * n)
    y_sep = f.sep_inv @ (b[:, m : m + w].reshape(bsz, w * n) - zy[:bsz] - zy_bot)[..., None]
    x_sep = f.sep_inv.mT @ y_sep  # (B, W n, 1)
    x_rev = x_sep.reshape(bsz, w, n).flip(1).reshape(bsz, w * n, 1)
    buf[:, w + big_m - w :] -= (f.z @ torch.cat([x_sep, x_rev]))[..., 0].reshape(2 * bsz, w, n)
    x = b.new_empty(2 * bsz, big_m, n)
    _sweep(f.halves, buf, x)
    return torch.cat([x[:bsz, pad:], x_sep.reshape(bsz, w, n), x[bsz:].flip(1)], 1)


def _marginals_twisted(f: _Twisted) -> Tensor:
    """Diagonal blocks of the inverse of f's system -> (B, T, n, n). In the order (top, bottom,
    separator), A^{-1}'s half blocks are A_hh^{-1} + V S V^T with V = A_hh^{-1} A_hs = L_h^{-T} Z and
    S = (C_s C_s^T)^{-1} the separator's: Takahashi on each half plus, per frame, V_t S V_t^T (V by
    one backward sweep with W n columns)."""
    halves, z = f.halves, f.z
    b2, big_m, n = halves.inv_chol_t.shape[0], halves.inv_chol_t.shape[1], halves.inv_chol_t.shape[-1]
    bsz, w = b2 // 2, f.sep_inv.shape[-1] // n
    m = f.top
    pad = big_m - m
    own = _marginals(halves)  # (2B, M, n, n)
    # S = (C_s C_s^T)^{-1} = Q Q^T with Q = C_s^{-T}, so V_t S V_t^T = (V_t Q)(V_t Q)^T; the bottom
    # half's columns run backwards in time: its Q's rows reversed by frame block
    rev = torch.arange(w - 1, -1, -1, device=z.device)
    idx = (rev[:, None] * n + torch.arange(n, device=z.device)).flatten()
    q_both = torch.cat([f.sep_inv.mT, f.sep_inv.mT[:, idx]])  # (2B, W n, W n)
    # V = L_h^{-T} [0; Z]: a backward sweep with W n right-hand sides, keeping only its last W rows
    v_cols = _columns(halves.coupling, n)  # (2B, M, W n, n)
    zf = z.reshape(b2, w, n, w * n)
    win = [z.new_zeros(b2, n, w * n) for _ in range(w)]  # V_{t+1} .. V_{t+W}
    for t in range(big_m - 1, -1, -1):
        r = zf[:, t - (big_m - w)] if t >= big_m - w else z.new_zeros(b2, n, w * n)
        r = torch.baddbmm(r, v_cols[:, t].mT, torch.cat(win, 1), alpha=-1)
        x = halves.inv_chol_t[:, t] @ r  # V_t (2B, n, W n)
        vq = x @ q_both
        own[:, t] = torch.baddbmm(own[:, t], vq, vq.mT)
        win = [x] + win[:-1]
    s_sep = f.sep_inv.mT @ f.sep_inv  # (B, W n, W n)
    sep_blocks = torch.stack([s_sep[:, i * n : (i + 1) * n, i * n : (i + 1) * n] for i in range(w)], 1)
    return torch.cat([own[:bsz, pad:], sep_blocks, own[bsz:].flip(1)], 1)


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
    coupling = torch.stack([torch.stack(r[::-1], 1) for r in blk[w:]], 1) if t_len else diag.new_zeros(b, 0, w)
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


class _ScalarBand(NamedTuple):
    """B scalar W-banded systems factored by LAPACK's banded Cholesky (pbtrf; the CPU fast path of
    `_reduce`): chol (B, T, W + 1), row r the lower band storage of system r's factor (column-major
    (W + 1, T)); diag (B, T) and lower (B, T, W) the systems themselves (for the marginal variances)."""

    chol: Tensor
    diag: Tensor
    lower: Tensor


def _band_lapack(diag: Tensor, lower: Tensor) -> tuple[_ScalarBand, Tensor]:
    """`_reduce` on the CPU: one LAPACK pbtrf call per system (~10 us each; the cyclic reduction's
    ~370 small torch ops took ~4.5 ms for the bench's 18 decoupled dofs). diag (B, T), lower
    (B|1, T, W) -> _ScalarBand, ok (B,); a failed system's factor is the identity (finite solves)."""
    from scipy.linalg.lapack import get_lapack_funcs

    b, t_len = diag.shape
    w = lower.shape[-1]
    lower = lower.expand(b, t_len, w)
    band = diag.new_zeros(b, t_len, w + 1)  # band[r, j, k] = A[j + k, j] (LAPACK's lower storage, transposed)
    band[:, :, 0] = diag
    for k in range(1, min(w, t_len - 1) + 1):
        band[:, : t_len - k, k] = lower[:, k:, k - 1]
    arr = band.numpy()
    (pbtrf,) = get_lapack_funcs(("pbtrf",), (arr,))
    ok = torch.ones(b, dtype=torch.bool)
    for r in range(b):
        c, info = pbtrf(arr[r].T, lower=1, overwrite_ab=1)  # in place: arr[r].T is column-major
        if info != 0:
            ok[r] = False
            arr[r] = 0.0
            arr[r, :, 0] = 1.0
        elif not np.shares_memory(c, arr[r]):
            arr[r] = c.T
    return _ScalarBand(band, diag, lower), ok.to(diag.device)


def _solve_band_lapack(f: _ScalarBand, b: Tensor) -> Tensor:
    """b (B, T) -> x (B, T) with `_band_lapack`'s factor (LAPACK pbtrs per system)."""
    from scipy.linalg.lapack import get_lapack_funcs

    arr = f.chol.numpy()
    x = b.contiguous().clone()
    xs = x.numpy()
    (pbtrs,) = get_lapack_funcs(("pbtrs",), (arr,))
    for r in range(arr.shape[0]):
        xs[r], _ = pbtrs(arr[r].T, xs[r], lower=1, overwrite_b=1)
    return x


def _solve_reduced(f: _Reduction | _ScalarBand, b: Tensor) -> Tensor:
    """b (B, T) -> x (B, T) with `_reduce`'s (or `_band_lapack`'s) factor."""
    if isinstance(f, _ScalarBand):
        return _solve_band_lapack(f, b)
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
    # an entry is nonzero in some block iff its smallest or largest value over the blocks is (NaN
    # counts as nonzero, as in != 0): two fast reductions instead of a (..., T, D, D) mask
    blocks = a.diagonal.flatten(0, -3)
    off = (blocks.amin(0) != 0) | (blocks.amax(0) != 0)
    off.fill_diagonal_(False)
    return ~off.any(-1)


def factorize(a: BlockBanded, halves: bool | None = None) -> tuple[BandedFactor, Tensor]:
    """Block Cholesky of the symmetric positive definite `a` (see module docstring).

    halves: factor from both ends towards a W-frame separator in the middle (module docstring, "Two
    halves"); None = when T >= `HALVES_MIN_FRAMES`. -> BandedFactor, ok (...,) bool: False where a
    pivot was not positive definite (that system's factor is then meaningless but finite; the other
    systems are unaffected)."""
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
    dense: _Chol | _Twisted | None = None
    scalar: _Reduction | _ScalarBand | None = None
    if n:
        dofs = None if u == 0 else coupled
        sub_lo = lo if u == 0 else lo[..., coupled]
        if halves is None:
            halves = t_len >= HALVES_MIN_FRAMES
        with one_thread():
            if halves and t_len >= 4 * w:
                dense, good = _factor_twisted(dg, sub_lo, dofs)
            else:
                frames = torch.arange(t_len, device=dg.device)
                dense, good = _factor_dense(dg if dofs is None else _gather(dg, frames, dofs), sub_lo)
        ok &= good
    if u:
        sd = dg.diagonal(dim1=-2, dim2=-1)[..., decoupled]  # (B, T, u)
        sl = lo[..., decoupled]  # (B|1, T, W, u)
        scalar, good = (_band_lapack if numpy_path(dg) else _reduce)(
            sd.permute(0, 2, 1).reshape(b * u, t_len),
            sl.permute(0, 3, 1, 2).expand(b, u, t_len, w).reshape(b * u, t_len, w),
        )
        ok &= good.reshape(b, u).all(-1)
    return BandedFactor(dense, scalar, coupled, decoupled, tuple(batch), d), ok.reshape(batch)


def _columns(cpl: Tensor, n: int) -> Tensor:
    """The rows R_t (B, T, n, W n) -> V (B, T, W n, n) with V_t = [B[t+1, 1]; ..; B[t+W, W]] (zero past
    the end), so that the backward sweep's sum_k B[t+k, k]^T x_{t+k} is V_t^T [x_{t+1}; ..; x_{t+W}]."""
    t_len, w = cpl.shape[1], cpl.shape[-1] // max(n, 1)
    v = cpl.new_zeros(cpl.shape[0], t_len, w * n, n)
    for k in range(1, min(w, t_len - 1) + 1):
        v[:, : t_len - k, (k - 1) * n : k * n] = cpl[:, k:, :, (w - k) * n : (w - k + 1) * n]
    return v


def _sweep(f: _Chol, buf: Tensor, out: Tensor | None = None) -> None:
    """One triangular sweep in place over buf (B, T + W, n), whose first W frames are zeros.

    Forward (out None): buf[:, W:] holds b and becomes y = L^{-1} b, frame by frame
    y_t = C_t^{-1} (b_t - R_t [y_{t-W}; ..; y_{t-1}]) (the W frames before t are one contiguous window).
    Backward: buf[:, W:] holds y and out (B, T, n) receives x = L^{-T} y, from the last frame:
    x_t = C_t^{-T} y_t, then the window of the W frames before t loses R_t^T x_t (each x_t's share in
    its predecessors' equations), so no column of L is gathered. Two matrix-vector products per frame
    (for one system; batched products of one column for B)."""
    if numpy_path(buf) and buf.is_contiguous() and (out is None or out.is_contiguous()):
        _sweep_numpy(f, buf, out)
        return
    bsz, n = buf.shape[0], buf.shape[2]
    w = f.coupling.shape[-1] // max(n, 1)
    t_len = buf.shape[1] - w
    flat = buf.view(bsz, (t_len + w) * n)
    if bsz == 1:  # matrix-vector products (less dispatch than batched ones of one)
        cit, rows = f.inv_chol_t[0], f.coupling[0]
        frames, windows = buf[0], flat[0].unfold(0, w * n, n)
        if out is None:
            for t in range(t_len):
                torch.mv(cit[t].mT, torch.addmv(frames[t + w], rows[t], windows[t], alpha=-1), out=frames[t + w])
            return
        x = out[0]
        for t in range(t_len - 1, -1, -1):
            torch.mv(cit[t], frames[t + w], out=x[t])
            if t:
                windows[t].addmv_(rows[t].mT, x[t], alpha=-1)
        return
    cit, rows = f.inv_chol_t.transpose(0, 1), f.coupling.transpose(0, 1)  # frame-major
    frames = buf[..., None].transpose(0, 1)  # (T + W, B, n, 1)
    windows = flat.unfold(1, w * n, n)[..., None].transpose(0, 1)  # (T + 1, B, W n, 1)
    if out is None:
        for t in range(t_len):
            torch.bmm(cit[t].mT, torch.baddbmm(frames[t + w], rows[t], windows[t], alpha=-1), out=frames[t + w])
        return
    x = out[..., None].transpose(0, 1)
    for t in range(t_len - 1, -1, -1):
        torch.bmm(cit[t], frames[t + w], out=x[t])
        if t:
            windows[t].baddbmm_(rows[t].mT, x[t], alpha=-1)


def _sweep_numpy(f: _Chol, buf: Tensor, out: Tensor | None) -> None:
    """`_sweep` on the CPU by numpy matrix-vector products batched over the B systems (a numpy call
    ~1-3 us against ~7-14 us for a batched torch product of one column), in place through numpy views
    of buf and out."""
    cit, rows, y = f.inv_chol_t.numpy().swapaxes(0, 1), f.coupling.numpy().swapaxes(0, 1), buf.numpy()
    bsz, n = y.shape[0], y.shape[2]
    w = rows.shape[-1] // max(n, 1)
    t_len = y.shape[1] - w
    flat = y.reshape(bsz, (t_len + w) * n)  # a view: buf is contiguous
    v = np.empty((bsz, max(n, 1) * max(w, 1), 1), dtype=y.dtype)
    if out is None:  # y_t = C_t^{-1} (b_t - R_t [y_{t-W}; ..; y_{t-1}])
        vn = v[:, :n]
        for t in range(t_len):
            np.matmul(rows[t], flat[:, t * n : (t + w) * n, None], out=vn)
            np.subtract(y[:, t + w, :, None], vn, out=vn)
            np.matmul(cit[t].swapaxes(-1, -2), vn, out=y[:, t + w, :, None])
        return
    x = out.numpy()
    for t in range(t_len - 1, -1, -1):  # x_t = C_t^{-T} y_t; the W frames before t lose R_t^T x_t
        np.matmul(cit[t], y[:, t + w, :, None], out=x[:, t, :, None])
        if t:
            win = flat[:, t * n : (t + w) * n, None]
            np.matmul(rows[t].swapaxes(-1, -2), x[:, t, :, None], out=v)
            np.subtract(win, v, out=win)


def _padded(b: Tensor, w: int) -> Tensor:
    """b (B, T, n) -> (B, W + T, n) with W zero frames first: a buffer for `_sweep`."""
    return torch.nn.functional.pad(b, (0, 0, w, 0))


def _solve_dense(f: _Chol | _Twisted, b: Tensor) -> Tensor:
    """f's system, b (B, T, n) -> x (B, T, n): the two sweeps."""
    if isinstance(f, _Twisted):
        return _solve_twisted(f, b)
    buf = _padded(b, f.coupling.shape[-1] // max(b.shape[-1], 1))
    _sweep(f, buf)
    x = torch.empty_like(b)
    _sweep(f, buf, x)
    return x


def _frames(f: BandedFactor) -> int:
    """T of `factorize`'s factor."""
    if isinstance(f.dense, _Twisted):
        w = f.dense.sep_inv.shape[-1] // f.dense.halves.inv_chol_t.shape[-1]
        return f.dense.halves.inv_chol_t.shape[1] + w + f.dense.top
    if f.dense is not None:
        return f.dense.inv_chol_t.shape[1]
    assert f.scalar is not None  # factorize fills at least one of the two
    return f.scalar.diag.shape[1]


def solve(f: BandedFactor, b: Tensor) -> Tensor:
    """Solve A x = b with `factorize`'s factor; b (..., T, D) -> x (..., T, D): the coupled dofs by the
    dense factor's two sweeps, the decoupled ones by their scalar systems."""
    t_len = _frames(f)
    if not isinstance(b, Tensor) or b.shape != (*f.batch, t_len, f.size):
        raise InputError(f"solve: b must have shape {(*f.batch, t_len, f.size)}, got {tuple(getattr(b, 'shape', ()))}")
    flat = b.reshape(-1, t_len, f.size)
    x = torch.empty_like(flat)
    if f.dense is not None:
        with one_thread():
            x[..., f.coupled] = _solve_dense(f.dense, flat[..., f.coupled])
    if f.scalar is not None:
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
        cit, cpl = cit[..., None, None], cpl[..., None, :]
    bsz, t_len, n = cit.shape[0], cit.shape[1], cit.shape[-1]
    w = cpl.shape[-1] // n
    out = cit.new_empty(bsz, t_len, n, n)
    big = cit.new_zeros(bsz, w * n, w * n)  # S over frames t+1 .. t+W (zero past the end)
    for t in range(t_len - 1, -1, -1):
        g = torch.cat(
            [
                cpl[:, t + k, :, (w - k) * n : (w - k + 1) * n].mT if t + k < t_len else cit.new_zeros(bsz, n, n)
                for k in range(1, w + 1)
            ],
            dim=-1,
        )  # (B, n, W n)
        r = -(cit[:, t] @ (g @ big))  # S[t, t+1 .. t+W]
        s_tt = cit[:, t] @ (cit[:, t].mT - g @ r.mT)
        s_tt = 0.5 * (s_tt + s_tt.mT)
        full = torch.cat([torch.cat([s_tt, r], -1), torch.cat([r.mT, big], -1)], -2)
        big = full[:, : w * n, : w * n]
        out[:, t] = s_tt
    return out


def _marginals_any(f: _Chol | _Twisted) -> Tensor:
    return _marginals_twisted(f) if isinstance(f, _Twisted) else _marginals(f)


def marginal_blocks(f: BandedFactor) -> Tensor:
    """Diagonal blocks of A^{-1} from `factorize`'s factor -> (..., T, D, D): the marginal
    covariances of a Gaussian with precision A (module docstring; the inverse's band only): the
    coupled dofs' blocks from the dense factor, the decoupled dofs' variances from their scalar
    systems, zero between the two."""
    t_len = _frames(f)
    shape = (math.prod(f.batch), t_len, f.size, f.size)
    if f.dense is not None:
        with one_thread():
            dense = _marginals_any(f.dense)  # (B, T, n, n)
        out = dense.new_zeros(shape)
        out[:, :, f.coupled[:, None], f.coupled] = dense
    else:
        assert f.scalar is not None  # factorize fills at least one of the two
        out = f.scalar.diag.new_zeros(shape)
    if f.scalar is not None:
        chol, _ = _factor_scalar(f.scalar.diag, f.scalar.lower)  # sequential, once: the variances need L
        var = _marginals(chol)[..., 0, 0].reshape(out.shape[0], f.decoupled.numel(), t_len).permute(0, 2, 1)
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
