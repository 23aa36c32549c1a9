"""The floor contact term (`ptrack.costs.floor`) and the skeleton's floor points (`ptrack.body.subject`)."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from ptrack.body.skeleton import Skeleton
from ptrack.body.subject import ANKLE_HEIGHT, add_landmark_joints, floor_points, scale_to_height
from ptrack.costs import FloorContact, PoseEval
from ptrack.costs.base import PoseJacobian
from ptrack.errors import InputError
from ptrack.package_data import data_file

D64 = torch.float64


def _ev(joints: torch.Tensor) -> PoseEval:
    z = torch.zeros(1, dtype=D64)
    return PoseEval(q=z, joints=joints, pixels=z, depth=z)


def _joints(heights: list[list[float]]) -> torch.Tensor:
    """heights (N, J) -> joints (N, J, 3) with those Y and arbitrary X, Z."""
    h = torch.tensor(heights, dtype=D64)
    return torch.stack([torch.randn(h.shape, dtype=D64), h, torch.randn(h.shape, dtype=D64)], -1)


def test_the_lowest_foot_point_is_pulled_to_the_floor():
    term = FloorContact(joints=(1, 2), height_m=0.1, clearance_m=0.02, sigma_m=0.05)
    # joint 0 is not a foot point: its height never counts
    joints = _joints([[-5.0, 0.12, 0.5], [-5.0, 0.4, 0.3], [-5.0, 0.0, 0.9]])
    r = term.residual(_ev(joints))
    assert r.shape == (3, 1)
    assert torch.allclose(r[:, 0], torch.tensor([0.0, 3.6, -2.4], dtype=D64), atol=1e-12)
    e = term.energy(_ev(joints))
    assert float(e[0]) == pytest.approx(0.0, abs=1e-20)
    assert e[2] == pytest.approx(0.5 * 2.4**2)  # below the floor: quadratic
    assert e[1] == pytest.approx(0.5 * (2 * 3.6 - 1))  # above: Huber's, linear beyond one sigma


def test_above_the_floor_the_cost_grows_slower_than_below():
    term = FloorContact(joints=(0,), sigma_m=0.03)
    up, down = (term.energy(_ev(_joints([[h]]))) for h in (0.3, -0.3))
    assert float(up) < 0.25 * float(down)


def test_irls_weights_match_the_gradient_of_the_energy():
    """d energy / d r = w r: the weights a Gauss-Newton solver reads reproduce the term's gradient."""
    term = FloorContact(joints=(0, 1), height_m=0.0, clearance_m=0.01, sigma_m=0.03)
    joints = _joints([[0.5, 0.2], [0.05, 0.3], [-0.04, 0.1]]).requires_grad_(True)
    ev = _ev(joints)
    term.energy(ev).sum().backward()
    r = term.residual(ev).detach()
    w = term.robust_weights(ev).detach()
    low = joints.detach()[..., 1].argmin(-1)
    for n in range(3):
        expected = float(w[n, 0] * r[n, 0] / term.sigma_m)
        assert float(joints.grad[n, low[n], 1]) == pytest.approx(expected, rel=1e-9)


def test_a_trajectory_has_one_residual_per_frame():
    term = FloorContact(joints=(0, 1), time_axis=True)
    joints = _joints([[0.1, 0.2], [0.0, 0.3], [0.05, -0.1], [0.2, 0.2]]).reshape(1, 4, 2, 3)
    r = term.residual(_ev(joints))
    assert r.shape == (1, 4)
    assert term.energy(_ev(joints)).shape == (1,)


def test_bad_floor_terms_are_input_errors():
    with pytest.raises(InputError):
        FloorContact(joints=())
    with pytest.raises(InputError):
        FloorContact(joints=(0,), sigma_m=0.0)
    with pytest.raises(InputError):
        FloorContact(joints=(0,), loss="fuzzy")
    with pytest.raises(InputError, match="J > 4"):
        FloorContact(joints=(4,)).residual(_ev(_joints([[0.0, 1.0]])))


def test_floor_points_of_the_scaled_template():
    height = 1.72
    sk = add_landmark_joints(scale_to_height(Skeleton.from_asf(data_file("10.asf")), height), height)
    joints, clearance = floor_points(sk, height)
    names = {sk.joint_names[j] for j in joints}
    assert names == {"ltoes", "rtoes", "lm_l_heel", "lm_r_heel", "lm_l_small_toe", "lm_r_small_toe"}
    # the heel landmark sits 0.009 H above the floor (ankle 0.039 H, heel 0.03 H below it): the lowest point
    assert 0.0 <= clearance <= ANKLE_HEIGHT * height
    assert clearance == pytest.approx(0.009 * height, abs=0.01)
    with pytest.raises(InputError, match="foot points"):
        floor_points(_no_feet(), height)


def _no_feet() -> Skeleton:
    """The CMU template with no foot point: its toes renamed, no landmark joints."""
    sk = Skeleton.from_asf(data_file("10.asf"))
    return dataclasses.replace(sk, joint_names=tuple(n.replace("toes", "digits") for n in sk.joint_names))


def test_closed_form_jacobian_matches_autograd():
    """The term's Jacobian through the skeleton's forward kinematics equals autograd's."""
    from ptrack.optim.jacobians import joint_jacobian

    height = 1.72
    sk = add_landmark_joints(scale_to_height(Skeleton.from_asf(data_file("10.asf")), height), height)
    joints, clearance = floor_points(sk, height)
    term = FloorContact(joints, height_m=-1.0, clearance_m=clearance)
    q = 0.3 * torch.randn(4, sk.num_dofs, dtype=D64, generator=torch.Generator().manual_seed(0))
    x, dx = joint_jacobian(sk, q)
    z = torch.zeros(1, dtype=D64)
    closed = term.jacobian(PoseEval(q=q, joints=x, pixels=z, depth=z), PoseJacobian(joints=dx, pixels=z, depth=z))
    auto = torch.autograd.functional.jacobian(lambda p: term.residual(_ev(sk.forward_kinematics(p))).sum(0), q)
    assert closed.shape == (4, 1, sk.num_dofs)
    assert torch.allclose(closed[:, 0], auto[0], atol=1e-9)
