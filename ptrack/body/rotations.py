"""Rotation helpers (one convention: matrices act on column vectors, `x' = R @ x`).

`axis_angle_matrix(axis, angle)` is Rodrigues' formula for a fixed unit axis, exact and smooth at
angle 0. `euler_matrix(angles, order)` composes elementary rotations applied in `order`, first letter
first, i.e. for "XYZ": R = Rz @ Ry @ Rx (the Acclaim convention).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor


def skew(v: Tensor) -> Tensor:
    """Cross-product matrix. v: (..., 3) -> (..., 3, 3), skew(v) @ x = v x x."""
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).reshape(*v.shape[:-1], 3, 3)


def axis_angle_matrix(axis: Tensor, angle: Tensor) -> Tensor:
    """Rotation by `angle` about unit `axis`. axis: (..., 3), angle: (...) -> (..., 3, 3)."""
    k = skew(axis)
    s = torch.sin(angle)[..., None, None]
    c = torch.cos(angle)[..., None, None]
    eye = torch.eye(3, dtype=k.dtype, device=k.device)
    return eye + s * k + (1 - c) * (k @ k)


def elementary_matrix_np(axis: str, angle_rad: float) -> np.ndarray:
    """Rotation about a coordinate axis ("X", "Y" or "Z") by `angle_rad`: (3, 3) float64."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    if axis == "X":
        return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=np.float64)
    if axis == "Y":
        return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=np.float64)
    if axis == "Z":
        return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float64)
    raise ValueError(f"axis must be X, Y or Z, got {axis!r}")


def euler_matrix_np(angles_rad: Sequence[float], order: str = "XYZ") -> np.ndarray:
    """Euler angles (given as x, y, z values) applied in `order`, first letter first: (3, 3) float64."""
    by_axis = dict(zip("XYZ", angles_rad))
    r = np.eye(3)
    for a in order:
        r = elementary_matrix_np(a, by_axis[a]) @ r
    return r


def matrix_to_axis_angle_np(r: np.ndarray) -> tuple[np.ndarray, float]:
    """(unit axis, angle in [0, pi]) of the rotation matrix r (3, 3), accurate near 0 and pi."""
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])  # 2 sin(a) axis
    angle = math.atan2(0.5 * float(np.linalg.norm(v)), 0.5 * (float(np.trace(r)) - 1.0))
    if angle == 0.0:
        return np.eye(3)[0], 0.0
    if angle < 3.0:
        return v / np.linalg.norm(v), angle
    s = 0.5 * (r + r.T) - math.cos(angle) * np.eye(3)  # (1 - cos a) axis axis^T
    k = int(np.argmax(np.diag(s)))
    axis = s[k] / np.linalg.norm(s[k])
    if np.dot(axis, v) < 0:
        axis = -axis
    return axis, angle


def matrix_to_euler_np(r: np.ndarray, order: str = "XYZ") -> np.ndarray:
    """Inverse of `euler_matrix_np`: (..., 3, 3) -> (..., 3) float64 angles about x, y, z.

    `order` is any of the six orders of three distinct axes ("XYZ": R = Rz Ry Rx, "ZYX": Rx Ry Rz,
    ...). The first and last angles are in [-pi, pi], the middle one in [-pi/2, pi/2]. At the
    gimbal lock (middle angle +-pi/2, where only a combination of the other two is defined) the
    first angle is 0 and the last carries the whole turn; near it the last angle is solved from
    the first one actually chosen, so the matrix comes back to rounding error everywhere. No
    element needs to be within [-1, 1] (no arcsin): rounding past +-1 is harmless.
    """
    if sorted(order) != ["X", "Y", "Z"]:
        raise ValueError(f"Euler order must be three distinct axes of X, Y, Z (e.g. 'XYZ'), got {order!r}")
    r = np.asarray(r, dtype=np.float64)
    if r.shape[-2:] != (3, 3):
        raise ValueError(f"rotation matrices must have shape (..., 3, 3), got {r.shape}")
    # R = R_k(c) R_j(b) R_i(a) for order (i, j, k); s = +1 if (i, j, k) is a cyclic shift of (x, y, z).
    # Then R[k, i] = -s sin b, (R[k, j], R[k, k]) = cos b (s sin a, cos a), and with a known,
    # R R_i(a)^T = R_k(c) R_j(b) gives c from its (i, j) and (j, j) entries (Day's stable extraction).
    i, j, k = ("XYZ".index(a) for a in order)
    s = 1.0 if (j - i) % 3 == 1 else -1.0
    sa_cb, ca_cb = s * r[..., k, j], r[..., k, k]
    cb = np.hypot(sa_cb, ca_cb)
    lock = cb <= 64 * np.finfo(np.float64).eps  # first angle undefined: take 0
    a = np.where(lock, 0.0, np.arctan2(sa_cb, ca_cb))
    sa, ca = np.sin(a), np.cos(a)
    b = np.arctan2(-s * r[..., k, i], sa * sa_cb + ca * ca_cb)
    c = np.arctan2(sa * r[..., i, k] - s * ca * r[..., i, j], ca * r[..., j, j] - s * sa * r[..., j, k])
    out = np.empty(r.shape[:-2] + (3,))
    out[..., i], out[..., j], out[..., k] = a, b, c
    return out
