"""ptrack.rotations: skew, Rodrigues, Euler composition and its inverse."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ptrack.rotations import axis_angle_matrix, elementary_matrix_np, euler_matrix_np, matrix_to_euler_np, skew


def test_skew_is_cross_product():
    g = torch.Generator().manual_seed(0)
    v, x = torch.randn(4, 3, generator=g), torch.randn(4, 3, generator=g)
    torch.testing.assert_close((skew(v) @ x[..., None])[..., 0], torch.linalg.cross(v, x, dim=-1))


def test_axis_angle_matches_elementary_rotations_and_is_batched():
    angles = torch.tensor([0.0, 0.3, -1.2, 2.5], dtype=torch.float64)
    for k, name in enumerate("XYZ"):
        axis = torch.eye(3, dtype=torch.float64)[k].expand(4, 3)
        r = axis_angle_matrix(axis, angles)
        assert r.shape == (4, 3, 3)
        for i, a in enumerate(angles.tolist()):
            np.testing.assert_allclose(r[i].numpy(), elementary_matrix_np(name, a), atol=1e-12)


def test_axis_angle_gradcheck_near_zero():
    axis = torch.nn.functional.normalize(torch.tensor([[0.3, -0.5, 0.8]], dtype=torch.float64), dim=-1)
    angle = torch.tensor([1e-8], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a: axis_angle_matrix(axis, a), (angle,))


@pytest.mark.parametrize("order", ["XYZ", "ZYX", "YXZ"])
def test_euler_order_applies_first_letter_first(order):
    angles = (0.2, -0.4, 0.7)
    by_axis = dict(zip("XYZ", angles))
    expected = np.eye(3)
    for a in order:
        expected = elementary_matrix_np(a, by_axis[a]) @ expected
    np.testing.assert_allclose(euler_matrix_np(angles, order), expected, atol=1e-12)


def test_matrix_to_euler_round_trip():
    rng = np.random.default_rng(0)
    angles = rng.uniform([-np.pi, -1.4, -np.pi], [np.pi, 1.4, np.pi], size=(50, 3))
    mats = np.stack([euler_matrix_np(tuple(a), "XYZ") for a in angles])
    np.testing.assert_allclose(matrix_to_euler_np(mats), angles, atol=1e-9)
    with pytest.raises(ValueError):
        matrix_to_euler_np(mats, "ZYX")
    with pytest.raises(ValueError):
        elementary_matrix_np("W", 0.1)
