"""The banded trajectory assembler: the Gauss-Newton normal equations of a trajectory objective, summed from
the shared cost terms' residuals, Jacobians and IRLS weights (`ptrack.costs`) into the blocks of a block-banded
system (`ptrack.optim.banded`): each frame's diagonal block, and the band of diagonal couplings between frames
that the smoothing prior gives.

A per-frame term's residual rows each depend on one frame's pose q_t (D,). Its share of the Gauss-Newton
Hessian and gradient is J_t^T W_t J_t and J_t^T W_t r_t on the diagonal block of that frame (W_t its IRLS
weights, one for least squares). Rows come in four forms:

    FrameRows(frames (F,), residual (B, F, M), jacobian (B|1, F, M, D), weight (B, F, M) | None)
        rows at some frames, their Jacobian w.r.t. their frame's pose:   add_frame_rows(h, g, rows)
    every frame's rows, jacobian (B, T, M, D), residual (B, T, M, 1) (weights folded in: sqrt(W) J, sqrt(W) r):
                                                                         add_all_frames(h, g, jacobian, residual)
    every frame's rows, each reading one joint's position: d rows / d that position (B, T, Y, R, 3) (the
    reprojection's, `Reprojection.pixel_jacobian` on d pixels / d X), on to the pose without (Y, 3, D) rows:
                                                                         add_point_rows(h, g, sk, q, joints, ...)
    one row per dof with a diagonal Jacobian (joint limits, pose priors), residual and diagonal (B, T, D):
                                                                         add_diagonal_rows(h, g, residual, diagonal)

Rows given against joint positions (joint keyframes) reach the pose through the geometric joint Jacobian
(`joint_rows`). h (B, T, D, D) and g (B, T, D) are added to in place.

Terms that couple frames: rows that are the n-th forward differences D_n of a dof over time (the smoothing prior,
`ptrack.costs.Smoothness`, which gives its energy, gradient and weights c_n (..., T-n, D) per residual: its
squared scale times its IRLS weight, `Smoothness.banded_gauss_newton`) give the band sum_n D_n^T diag(c_n) D_n of
the normal equations, which couples each dof only with itself:

    weighted_band(T, ((n, c_n (..., T-n, D)), ...), like) -> (..., T, W+1, D)   [t, k]: block (t, t-k)'s diagonal
    band_matvec(band (T, W+1, D), q (B, T, D)) -> (B, T, D)                   the band times q
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ptrack.body.skeleton import Skeleton
from ptrack.costs.smoothness import difference_coefficients
from ptrack.optim.banded import numpy_path
from ptrack.optim.jacobians import joint_jacobian, joint_jacobian_product


class FrameRows(NamedTuple):
    """Residual rows of a per-frame term at some frames: frames (F,) long (repeats allowed); residual (B, F, M)
    whitened; jacobian (B|1, F, M, D) = d residual / d q[frames]; weight (B, F, M) IRLS weights, None for
    least squares."""

    frames: Tensor
    residual: Tensor
    jacobian: Tensor
    weight: Tensor | None = None


def add_frame_rows(h: Tensor, g: Tensor, rows: FrameRows) -> None:
    """h (B, T, D, D) += J^T W J and g (B, T, D) += J^T W r of `rows` at their frames, in place."""
    if rows.frames.numel() == 0:
        return
    j, r = rows.jacobian, rows.residual
    wj = j if rows.weight is None else j * rows.weight[..., None]
    h.index_add_(1, rows.frames, (wj.mT @ j).expand(h.shape[0], -1, -1, -1))
    g.index_add_(1, rows.frames, (wj.mT @ r[..., None])[..., 0])


def add_all_frames(h: Tensor, g: Tensor, jacobian: Tensor, residual: Tensor) -> None:
    """Every frame's rows: h (B, T, D, D) = J^T J and g (B, T, D) = J^T r, written in place (not added: the
    first term of a linearisation), from jacobian (B, T, M, D) and residual (B, T, M, 1) with the IRLS
    weights' square roots already in both. h and g may be slices of the frames (a part of the sequence). On
    the CPU numpy's batched product (BLAS per frame, less overhead than torch's)."""
    if numpy_path(jacobian):
        np.matmul(jacobian.numpy().swapaxes(-1, -2), jacobian.numpy(), out=h.numpy())
    else:
        torch.matmul(jacobian.mT, jacobian, out=h)  # one batched product per frame, in place
    torch.matmul(jacobian.mT, residual, out=g[..., None])


def add_point_rows(
    h: Tensor,
    g: Tensor,
    sk: Skeleton,
    q: Tensor,
    joints: Sequence[int],
    d_points: Tensor,
    residual: Tensor,
    fk: tuple[Tensor, Tensor] | None = None,
) -> None:
    """Every frame's rows, each reading the position of one of the joints (Y,): h (B, T, D, D) = J^T J and g
    (B, T, D) = J^T r written in place (`add_all_frames`), from q (B, T, D), d_points (B, T, Y, R, 3) the R rows
    of each joint y by its position and residual (B, T, Y*R, 1), the IRLS weights' square roots in both. J =
    d_points @ d X_y / d q by `joint_jacobian_product` (never the (Y, 3, D) rows). h, g, q, d_points and residual
    may be the same slice of the frames; fk: `sk.forward_kinematics(q, rotations=True)` if already computed."""
    jw = joint_jacobian_product(sk, q, joints, d_points, fk)  # (B, T, Y, R, D)
    add_all_frames(h, g, jw.flatten(-3, -2), residual)


def add_diagonal_rows(h: Tensor, g: Tensor, residual: Tensor, diagonal: Tensor) -> Tensor:
    """One row per dof and frame with a diagonal Jacobian: residual, diagonal (B, T, D). Adds diagonal^2 to
    h's diagonal (in place: no (D, D) matrix per frame) and returns g + diagonal * residual (a new tensor)."""
    h.diagonal(dim1=-2, dim2=-1).add_(diagonal.square())
    return g + diagonal * residual


def joint_rows(sk: Skeleton, q: Tensor, joints: Sequence[int], d_joints: Tensor) -> Tensor:
    """Rows given against joint positions, against the pose: q (B, F, D) the rows' frames' poses, joints (Y,)
    the joints they read, d_joints (B|1, F, M, Y, 3) = d residual / d those joints' positions ->
    (B, F, M, D) = sum_y d_joints[..., y, :] @ d X_y / d q (the geometric joint Jacobian)."""
    _, dx = joint_jacobian(sk, q, list(joints))  # (B, F, Y, 3, D)
    return torch.einsum("bfmyc,bfycd->bfmd", d_joints.expand(q.shape[0], -1, -1, -1, -1), dx)


def weighted_band(t_len: int, smooth: tuple[tuple[int, Tensor], ...], like: Tensor) -> Tensor:
    """Band of sum_n D_n^T diag(c_n) D_n with a weight per residual: smooth ((n, c_n (..., T-n, D)), ...)
    -> (..., T, W+1, D), W the largest n (at least 1); entry [t, k] is the (t, t-k) block's diagonal."""
    d = like.shape[-1]
    w = max([n for n, _ in smooth] + [1])
    lead = torch.broadcast_shapes(*[c.shape[:-2] for _, c in smooth]) if smooth else ()
    band = like.new_zeros(*lead, t_len, w + 1, d)
    for n, c in smooth:
        if t_len <= n:
            continue
        coef = difference_coefficients(n)
        rows = t_len - n  # residual i covers frames i .. i+n
        for j in range(n + 1):
            for k in range(j + 1):
                band[..., j : rows + j, j - k, :] += coef[j] * coef[k] * c
    return band


def band_matvec(band: Tensor, q: Tensor) -> Tensor:
    """The band's symmetric matrix times q: band (T, W+1, D), q (B, T, D) -> (B, T, D)."""
    out = band[:, 0] * q
    t_len = q.shape[-2]
    for k in range(1, min(band.shape[1] - 1, t_len - 1) + 1):
        c = band[k:, k]
        out = (
            out
            + torch.nn.functional.pad(c * q[:, :-k], (0, 0, k, 0))
            + torch.nn.functional.pad(c * q[:, k:], (0, 0, 0, k))
        )
    return out
