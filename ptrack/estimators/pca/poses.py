"""Poses of the golf tracker's state (`method: pca`): the motion model's body poses and their closed-form
derivatives in the PCA weights and times, rotation vectors, and the root's rotation to and from its Euler angles.
Shapes: N states, f frames of a window, m PCA weights, D dofs."""

from __future__ import annotations

import torch
from torch import Tensor

from ptrack.body.rotations import matrix_to_euler_np, skew
from ptrack.estimators.pca.setup import Setup
from ptrack.motion.motion_model import MotionModel, decode


def decode_jacobian(model: MotionModel, alpha: Tensor, mu: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """`decode` and its derivatives in closed form: alpha (N, m), mu (N, f) -> q (N, f, Dm),
    dq/dalpha (N, f, Dm, m), dq/dmu (N, f, Dm). The decoder interpolates linearly between its N samples,
    so dq/dalpha is the interpolated components and dq/dmu the slope of the sample interval (0 outside
    [0, 1], where decode clamps); tests/test_pca.py checks both against `decode`."""
    n = model.num_samples
    mean, comp = model.mean.to(alpha), model.components.to(alpha)  # (N_s, Dm), (m, N_s, Dm)
    sm = mu.clamp(0.0, 1.0) * (n - 1)
    i0 = sm.floor().clamp(0, n - 2).long()
    w = (sm - i0.to(sm))[..., None]
    ca, cb = comp[:, i0].movedim(0, -1), comp[:, i0 + 1].movedim(0, -1)  # (N, f, Dm, m)
    dq_da = ca + w[..., None] * (cb - ca)
    ma, mb = mean[i0], mean[i0 + 1]
    q = ma + w * (mb - ma) + (dq_da @ alpha[:, None, :, None])[..., 0]
    inside = ((mu >= 0) & (mu <= 1)).to(alpha)[..., None]
    dq_dmu = (n - 1) * ((mb - ma) + ((cb - ca) @ alpha[:, None, :, None])[..., 0]) * inside
    return q, dq_da, dq_dmu


def body_poses(s: Setup, alpha: Tensor, mu: Tensor) -> tuple[Tensor, Tensor]:
    """Body poses (the root's dofs at zero) and their derivative: alpha (N, m), mu (N, f) -> q (N, f, D),
    dq/d(alpha, mu) (N, f, D, m + f) (each frame's q depends on its own mu only)."""
    n, f = mu.shape
    m = alpha.shape[-1]
    d = s.problem.skeleton.num_dofs
    qm, da, dmu = decode_jacobian(s.model, alpha, mu)
    q = alpha.new_zeros(n, f, d)
    q[..., s.model_dofs] = qm
    dq = alpha.new_zeros(n, f, d, m + f)
    dq[..., s.model_dofs, :m] = da
    fr = torch.arange(f, device=mu.device)
    dq[:, fr, :, m + fr] = dq.new_zeros(n, f, d).index_copy_(-1, s.model_dofs, dmu).transpose(0, 1)
    return q, dq


def rotation_exp(w: Tensor) -> tuple[Tensor, Tensor]:
    """Rotation vectors (..., 3) -> rotation matrices exp([w]x) (..., 3, 3) and the left Jacobians
    J_l(w) (..., 3, 3), with d/dw (exp(w) p) = -[exp(w) p]x J_l(w)."""
    t2 = w.square().sum(-1)[..., None, None]
    small = t2 < 1e-8
    t2s = torch.where(small, torch.ones_like(t2), t2)
    t = t2s.sqrt()
    a = torch.where(small, 1 - t2 / 6, torch.sin(t) / t)
    b = torch.where(small, 0.5 - t2 / 24, (1 - torch.cos(t)) / t2s)
    c = torch.where(small, 1.0 / 6 - t2 / 120, (t - torch.sin(t)) / (t2s * t))
    k = skew(w)
    kk = k @ k
    eye = torch.eye(3, dtype=w.dtype, device=w.device)
    return eye + a * k + b * kk, eye + b * k + c * kk


def orthonormal(r: Tensor) -> Tensor:
    """The nearest rotations (..., 3, 3) to near-rotations r: products of many rotations drift, and the
    constant-speed prediction R_{t-1} R_{t-2}^T R_{t-1} triples any drift each frame."""
    u, _, vt = torch.linalg.svd(r)
    return u @ vt


def root_angles(s: Setup, rot: Tensor) -> Tensor:
    """The root's Euler angles (..., 3), in the order of `s.root_dofs[3:]`, of world rotations (..., 3, 3)."""
    ang = torch.as_tensor(matrix_to_euler_np(rot.detach().cpu().double().numpy(), s.root_order))  # (..., 3) x, y, z
    return ang[..., list(s.root_xyz)].to(rot)


def rotation_of(s: Setup, angles: Tensor) -> Tensor:
    """World rotations (..., 3, 3) of the root's Euler angles (..., 3) (inverse of `root_angles`)."""
    q = angles.new_zeros(*angles.shape[:-1], s.problem.skeleton.num_dofs)
    q[..., s.root_dofs[3:]] = angles
    _, rot = s.problem.skeleton.forward_kinematics(q, rotations=True)
    return rot[..., 0, :, :] @ s.root_rest.to(angles).mT


def poses_of(s: Setup, alpha: Tensor, mu: Tensor, rot: Tensor, trans: Tensor) -> Tensor:
    """Full poses q (..., D) of PCA weights alpha (..., m), times mu (...), root rotations (..., 3, 3) and
    translations (..., 3)."""
    q = trans.new_zeros(*mu.shape, s.problem.skeleton.num_dofs)
    q[..., s.model_dofs] = decode(s.model, alpha, mu)
    q[..., s.root_dofs[:3]] = trans
    q[..., s.root_dofs[3:]] = root_angles(s, rot)
    return q
