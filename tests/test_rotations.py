"""ptrack.body.rotations: skew, Rodrigues, Euler composition and its inverse."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ptrack.body.rotations import axis_angle_matrix, elementary_matrix_np, euler_matrix_np, matrix_to_euler_np, skew


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


ORDERS = ["XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX"]


def _euler_stack(angles: np.ndarray, order: str) -> np.ndarray:
    """(N, 3) x, y, z angles -> (N, 3, 3) with `euler_matrix_np`."""
    return np.stack([euler_matrix_np(tuple(a), order) for a in angles])


def _middle(order: str) -> int:
    """Index (x=0, y=1, z=2) of the order's middle axis."""
    return "XYZ".index(order[1])


@pytest.mark.parametrize("order", ORDERS)
def test_matrix_to_euler_round_trip(order):
    """Away from the lock the angles come back themselves (first and last in (-pi, pi], middle in
    (-pi/2, pi/2)), batched over leading dims."""
    rng = np.random.default_rng(0)
    angles = rng.uniform(-np.pi, np.pi, size=(50, 3))
    angles[:, _middle(order)] = rng.uniform(-1.4, 1.4, size=50)
    mats = _euler_stack(angles, order)
    np.testing.assert_allclose(matrix_to_euler_np(mats, order), angles, rtol=0, atol=1e-9)
    assert matrix_to_euler_np(mats.reshape(5, 10, 3, 3), order).shape == (5, 10, 3)
    assert matrix_to_euler_np(mats[0], order).shape == (3,)


@pytest.mark.parametrize("order", ORDERS)
def test_matrix_to_euler_of_random_rotations(order):
    rng = np.random.default_rng(1)
    q, r = np.linalg.qr(rng.normal(size=(200, 3, 3)))
    mats = q * np.sign(np.diagonal(r, axis1=-2, axis2=-1))[:, None, :]
    mats[np.linalg.det(mats) < 0] *= -1
    angles = matrix_to_euler_np(mats, order)
    np.testing.assert_allclose(_euler_stack(angles, order), mats, rtol=0, atol=1e-12)
    assert np.all(np.abs(angles[:, _middle(order)]) <= np.pi / 2)


@pytest.mark.parametrize("order", ORDERS)
@pytest.mark.parametrize("distance", [0.0, 1e-12, 1e-9, 1e-6, -1e-9, -1e-6], ids=lambda d: f"{d:g}")
@pytest.mark.parametrize("sign", [1, -1], ids=["+90", "-90"])
def test_matrix_to_euler_at_and_near_gimbal_lock(order, distance, sign):
    """Middle angle +-90 degrees exactly and within 1e-12 .. 1e-6 of it (on either side): the
    rotation comes back exactly, whatever the split between first and last angle."""
    rng = np.random.default_rng(2)
    angles = rng.uniform(-np.pi, np.pi, size=(40, 3))
    angles[:, _middle(order)] = sign * (np.pi / 2 - distance)
    mats = _euler_stack(angles, order)
    back = matrix_to_euler_np(mats, order)
    assert np.all(np.isfinite(back))
    np.testing.assert_allclose(_euler_stack(back, order), mats, rtol=0, atol=1e-12)
    np.testing.assert_allclose(back[:, _middle(order)], sign * np.pi / 2, rtol=0, atol=2e-6)


@pytest.mark.parametrize("order", ORDERS)
def test_matrix_to_euler_exactly_singular_and_rounded_past_one(order):
    """At the lock itself (the element that is +-1 there is exactly +-1, or a rounding past it) the
    first angle is 0 and the last one carries the whole turn about the common axis."""
    i, k = "XYZ".index(order[0]), "XYZ".index(order[2])
    for sign in (1, -1):
        for last in (0.0, 0.7, -2.9, np.pi):
            angles = np.zeros(3)
            angles[_middle(order)] = sign * np.pi / 2
            angles[k] = last
            r = euler_matrix_np(tuple(angles), order)
            r[np.abs(r) < 1e-15] = 0.0  # exact zeros: cos(pi/2) is 6e-17 in floating point
            assert abs(r[k, i]) == 1.0
            for scale in (1.0, 1 + 4e-16, 1 + 1e-12):
                back = matrix_to_euler_np(r * scale, order)
                assert np.all(np.isfinite(back)) and back[i] == 0.0, (order, sign, last, scale, back)
                np.testing.assert_allclose(euler_matrix_np(tuple(back), order), r, rtol=0, atol=1e-11)


def test_matrix_to_euler_bad_input():
    with pytest.raises(ValueError, match="XYX"):
        matrix_to_euler_np(np.eye(3), "XYX")
    with pytest.raises(ValueError, match="xyz"):
        matrix_to_euler_np(np.eye(3), "xyz")
    with pytest.raises(ValueError, match=r"\(4, 3\)"):
        matrix_to_euler_np(np.zeros((4, 3)))
    with pytest.raises(ValueError):
        elementary_matrix_np("W", 0.1)
