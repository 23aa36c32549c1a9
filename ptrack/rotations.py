"""Rotation helpers (one convention: matrices act on column vectors, `x' = R @ x`).

`axis_angle_matrix(axis, angle)` is Rodrigues' formula for a fixed unit axis, exact and smooth at
angle 0. `euler_matrix(angles, order)` composes elementary rotations applied in `order`, first letter
first, i.e. for "XYZ": R = Rz @ Ry @ Rx (the Acclaim convention).
"""

from __future__ import annotations

import math

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


def euler_matrix_np(angles_rad: tuple[float, float, float], order: str = "XYZ") -> np.ndarray:
    """Euler angles (given as x, y, z values) applied in `order`, first letter first: (3, 3) float64."""
    by_axis = dict(zip("XYZ", angles_rad))
    r = np.eye(3)
    for a in order:
        r = elementary_matrix_np(a, by_axis[a]) @ r
    return r


def matrix_to_euler_np(r: np.ndarray, order: str = "XYZ") -> np.ndarray:
    """Inverse of `euler_matrix_np` for order "XYZ" (R = Rz Ry Rx): (..., 3, 3) -> (..., 3) x, y, z angles."""
    if order != "XYZ":
        raise ValueError("only XYZ order is implemented")
    sy = np.clip(-r[..., 2, 0], -1.0, 1.0)
    y = np.arcsin(sy)
    x = np.arctan2(r[..., 2, 1], r[..., 2, 2])
    z = np.arctan2(r[..., 1, 0], r[..., 0, 0])
    return np.stack([x, y, z], axis=-1)
