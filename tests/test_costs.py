import math

import pytest
import torch
from torch.autograd import gradcheck

from ptrack.costs import (
    JointKeyframe,
    JointLimits,
    Keyframe,
    Objective,
    ObjectiveValue,
    PoseEval,
    PosePrior,
    Reprojection,
    Silhouette,
    Smoothness,
    cauchy,
    distance_transform,
    geman_mcclure,
    huber,
    l2,
    robust_loss,
    robust_loss_derivative,
)
from ptrack.errors import InputError

LOSSES = ["l2", "huber", "cauchy", "geman_mcclure"]
D64 = torch.float64


def gen(seed=0):
    return torch.Generator().manual_seed(seed)


def ev(q=None, joints=None, pixels=None, joint_pixels=None, dtype=D64):
    """A PoseEval with only the fields a test needs; the rest are small dummies."""
    z = torch.zeros(1, dtype=dtype)
    return PoseEval(
        q=z if q is None else q,
        joints=z if joints is None else joints,
        pixels=z if pixels is None else pixels,
        depth=z,
        joint_pixels=joint_pixels,
    )


# ---------------------------------------------------------------- robust losses


@pytest.mark.parametrize("name", LOSSES)
def test_loss_equals_s_near_zero(name):
    s = torch.tensor([0.0, 1e-8, 1e-6, 1e-4], dtype=D64)
    rho = robust_loss(name)(s, 1.0)
    torch.testing.assert_close(rho, s, rtol=2e-4, atol=0.0)


@pytest.mark.parametrize("name", ["huber", "cauchy", "geman_mcclure"])
def test_robust_losses_grow_subquadratically(name):
    r = torch.tensor([2.0, 4.0, 8.0, 16.0], dtype=D64)
    rho = robust_loss(name)(r.square(), 1.0)
    assert (rho < r.square()).all()
    ratio = rho / r.square()
    assert (ratio[1:] < ratio[:-1]).all()  # rho(r^2) / r^2 keeps falling


def test_loss_closed_forms_and_scale():
    s = torch.tensor([0.25, 9.0, 100.0], dtype=D64)
    torch.testing.assert_close(l2(s), s)
    huber_expected = torch.tensor([0.25, 2 * 2 * 3.0 - 4, 2 * 2 * 10.0 - 4], dtype=D64)
    torch.testing.assert_close(huber(s, 2.0), huber_expected)
    torch.testing.assert_close(cauchy(s, 2.0), 4 * torch.log1p(s / 4))
    torch.testing.assert_close(geman_mcclure(s, 2.0), 4 * s / (s + 4))
    assert (geman_mcclure(torch.tensor([1e12], dtype=D64), 2.0) <= 4.0).all()


@pytest.mark.parametrize("name", LOSSES)
def test_loss_derivative_matches_autograd(name):
    s = torch.tensor([0.0, 0.3, 1.7, 40.0], dtype=D64, requires_grad=True)
    (g,) = torch.autograd.grad(robust_loss(name)(s, 1.3).sum(), s)
    assert torch.isfinite(g).all()
    torch.testing.assert_close(robust_loss_derivative(name)(s.detach(), 1.3), g)


def test_unknown_loss_raises():
    with pytest.raises(InputError, match="tukey"):
        robust_loss("tukey")
    with pytest.raises(InputError, match="tukey"):
        Reprojection(torch.zeros(2, 2), torch.ones(2), loss="tukey")


# ---------------------------------------------------------------- reprojection


def test_reprojection_zero_at_observation():
    obs = torch.rand(5, 2, generator=gen(), dtype=D64) * 100
    term = Reprojection(obs, torch.ones(5), sigma_px=3.0)
    e = ev(pixels=obs.clone())
    assert term.residual(e).abs().max() == 0
    assert term.energy(e) == 0


def test_reprojection_hand_computed():
    obs = torch.tensor([[10.0, 20.0], [30.0, 40.0], [50.0, 60.0]], dtype=D64)
    conf = torch.tensor([1.0, 0.25, 0.0], dtype=D64)
    pix = obs + torch.tensor([[2.0, 0.0], [4.0, -4.0], [7.0, 7.0]], dtype=D64)
    term = Reprojection(obs, conf, sigma_px=2.0, loss="cauchy", scale=1.0)
    r = term.residual(ev(pixels=pix))
    torch.testing.assert_close(r, torch.tensor([1.0, 0.0, 1.0, -1.0, 0.0, 0.0], dtype=D64))
    expected = 0.5 * (math.log1p(1.0) + math.log1p(2.0) + 0.0)
    torch.testing.assert_close(term.energy(ev(pixels=pix)), torch.tensor(expected, dtype=D64))
    w = term.robust_weights(ev(pixels=pix))
    torch.testing.assert_close(w, torch.tensor([0.5, 0.5, 1 / 3, 1 / 3, 1.0, 1.0], dtype=D64))
    l2_term = Reprojection(obs, conf, sigma_px=2.0, loss="l2")
    torch.testing.assert_close(l2_term.energy(ev(pixels=pix)), torch.tensor(1.5, dtype=D64))


def test_reprojection_ignores_missing_nan_keypoints():
    obs = torch.tensor([[1.0, 2.0], [float("nan"), float("nan")]], dtype=D64)
    term = Reprojection(obs, torch.tensor([1.0, 0.0]))
    pix = torch.tensor([[2.0, 2.0], [5.0, 5.0]], dtype=D64, requires_grad=True)
    energy = term.energy(ev(pixels=pix))
    (g,) = torch.autograd.grad(energy, pix)
    assert torch.isfinite(energy) and torch.isfinite(g).all()
    assert (g[1] == 0).all() and g[0, 0] > 0
    torch.testing.assert_close(energy, 0.5 * torch.log1p(torch.tensor(1.0, dtype=D64)))


def test_reprojection_batched_particles_match_loop():
    obs = torch.rand(4, 2, generator=gen(1), dtype=D64) * 50
    conf = torch.tensor([1.0, 0.5, 0.0, 2.0], dtype=D64)
    term = Reprojection(obs, conf, sigma_px=1.5, loss="huber")
    pix = obs + torch.randn(6, 4, 2, generator=gen(2), dtype=D64) * 3
    assert term.residual(ev(pixels=pix)).shape == (6, 8)
    energy = term.energy(ev(pixels=pix))
    assert energy.shape == (6,)
    loop = torch.stack([term.energy(ev(pixels=p)) for p in pix])
    torch.testing.assert_close(energy, loop)


def test_reprojection_trajectory_shapes():
    obs = torch.rand(3, 4, 2, generator=gen(3), dtype=D64)
    term = Reprojection(obs, torch.ones(3, 4))
    pix = torch.rand(5, 3, 4, 2, generator=gen(4), dtype=D64)
    assert term.residual(ev(pixels=pix)).shape == (5, 24)
    assert term.energy(ev(pixels=pix)).shape == (5,)
    assert term.robust_weights(ev(pixels=pix)).shape == (5, 24)
    per_frame = sum(Reprojection(obs[t], torch.ones(4)).energy(ev(pixels=pix[:, t])) for t in range(3))
    torch.testing.assert_close(term.energy(ev(pixels=pix)), per_frame)


def test_reprojection_per_problem():
    """per_problem: observed (N, K, 2) holds each pose's own frame, and the residual stays per pose (N, K*2),
    equal to N one-frame terms; without it the same observed is one trajectory's (N*K*2)."""
    obs = torch.rand(3, 4, 2, generator=gen(8), dtype=D64) * 50
    conf = torch.rand(3, 4, generator=gen(9), dtype=D64)
    pix = obs + torch.randn(3, 4, 2, generator=gen(10), dtype=D64)
    term = Reprojection(obs, conf, loss="cauchy", per_problem=True)
    assert term.residual(ev(pixels=pix)).shape == (3, 8)
    loop = torch.stack([Reprojection(obs[i], conf[i], loss="cauchy").energy(ev(pixels=pix[i])) for i in range(3)])
    torch.testing.assert_close(term.energy(ev(pixels=pix)), loop)
    assert Reprojection(obs, conf).residual(ev(pixels=pix)).shape == (24,)
    with pytest.raises(InputError, match="per_problem"):
        Reprojection(obs[0], conf[0], per_problem=True)


def test_reprojection_keypoints_and_pose_prior_dofs():
    """`Reprojection.keypoints` reads some of ev.pixels' keypoints, `PosePrior.dofs` some entries of ev.q (as the
    golf tracker's window does: its tracked joints and pairs' points side by side, priors on parts of its state);
    both equal the term on the selection alone, with closed-form Jacobian rows."""
    from ptrack.costs.base import PoseJacobian

    obs = torch.rand(2, 3, 2, generator=gen(1), dtype=D64) * 50
    conf = torch.rand(2, 3, generator=gen(2), dtype=D64)
    pix = torch.rand(4, 2, 5, 2, generator=gen(3), dtype=D64) * 50  # N = 4, T = 2, 5 projected points
    keep = torch.tensor([4, 0, 2])
    sub = Reprojection(obs, conf, loss="cauchy", keypoints=keep)
    alone = Reprojection(obs, conf, loss="cauchy")
    torch.testing.assert_close(sub.energy(ev(pixels=pix)), alone.energy(ev(pixels=pix[..., keep, :])))
    dpix = torch.rand(4, 2, 5, 2, 7, generator=gen(4), dtype=D64)
    jac = PoseJacobian(joints=dpix, pixels=dpix, depth=dpix[..., 0, :])
    torch.testing.assert_close(
        sub.jacobian(ev(pixels=pix), jac), alone.jacobian(ev(pixels=pix), jac._replace(pixels=dpix[..., keep, :, :]))
    )
    with pytest.raises(InputError, match="keypoints"):
        Reprojection(obs, conf, keypoints=torch.tensor([0, 1]))
    q = torch.randn(4, 6, generator=gen(5), dtype=D64)
    dofs = torch.tensor([5, 1])
    prior = PosePrior(torch.tensor([0.5, -0.2], dtype=D64), torch.tensor([0.1, 0.3], dtype=D64), dofs=dofs)
    torch.testing.assert_close(
        prior.residual(ev(q=q)),
        (q[:, dofs] - torch.tensor([0.5, -0.2], dtype=D64)) / torch.tensor([0.1, 0.3], dtype=D64),
    )
    rows = prior.jacobian(ev(q=q), jac)
    assert rows.shape == (4, 2, 6)
    torch.testing.assert_close(rows[0], torch.eye(6, dtype=D64)[dofs] / torch.tensor([[0.1], [0.3]], dtype=D64))
    with pytest.raises(InputError, match="dofs"):
        PosePrior(torch.zeros(2, dtype=D64), dofs=torch.tensor([0, 1, 2]))


def test_robust_wraps_a_least_squares_term():
    """`Robust(term, loss, scale)`: the term's residual and Jacobian, energy 0.5 sum rho(r_i^2), IRLS weights
    rho'(r_i^2) entry by entry; with l2 the term itself."""
    from ptrack.costs import Robust
    from ptrack.costs.base import PoseJacobian

    q = torch.randn(3, 4, generator=gen(6), dtype=D64) * 3
    prior = PosePrior(torch.zeros(4, dtype=D64), 0.5)
    robust = Robust(prior, "cauchy", 2.0)
    r = prior.residual(ev(q=q))
    jac = PoseJacobian(joints=q[..., None], pixels=q[..., None], depth=q)
    torch.testing.assert_close(robust.residual(ev(q=q)), r)
    torch.testing.assert_close(robust.jacobian(ev(q=q), jac), prior.jacobian(ev(q=q), jac))
    torch.testing.assert_close(robust.energy(ev(q=q)), 0.5 * cauchy(r.square(), 2.0).sum(-1))
    torch.testing.assert_close(robust.robust_weights(ev(q=q)), robust_loss_derivative("cauchy")(r.square(), 2.0))
    torch.testing.assert_close(Robust(prior, "l2").energy(ev(q=q)), prior.energy(ev(q=q)))
    with pytest.raises(InputError, match="robust loss"):
        Robust(prior, "nope")


def test_reprojection_float32():
    obs = torch.rand(4, 2, generator=gen(5), dtype=D64)
    term = Reprojection(obs, torch.ones(4))
    pix = torch.rand(2, 4, 2, generator=gen(6))
    assert term.energy(ev(pixels=pix, dtype=torch.float32)).dtype == torch.float32


@pytest.mark.parametrize("loss", LOSSES)
def test_reprojection_gradcheck(loss):
    obs = torch.rand(3, 2, generator=gen(7), dtype=D64)
    term = Reprojection(obs, torch.tensor([1.0, 0.3, 2.0]), sigma_px=0.5, loss=loss, scale=0.7)
    pix = (obs + torch.randn(2, 3, 2, generator=gen(8), dtype=D64)).requires_grad_()
    assert gradcheck(lambda p: term.energy(ev(pixels=p)), (pix,))


def test_reprojection_input_errors():
    with pytest.raises(InputError, match="NaN"):
        Reprojection(torch.tensor([[float("nan"), 1.0]]), torch.ones(1))
    with pytest.raises(InputError, match="confidence"):
        Reprojection(torch.zeros(3, 2), torch.ones(4))
    with pytest.raises(InputError, match="confidence"):
        Reprojection(torch.zeros(3, 2), -torch.ones(3))
    with pytest.raises(InputError, match="observed"):
        Reprojection(torch.zeros(3, 3), torch.ones(3))
    with pytest.raises(InputError, match="sigma_px"):
        Reprojection(torch.zeros(3, 2), torch.ones(3), sigma_px=-1.0)
    term = Reprojection(torch.zeros(3, 2), torch.ones(3))
    with pytest.raises(InputError, match=r"\(5, 2\)"):
        term.energy(ev(pixels=torch.zeros(5, 2)))


# ---------------------------------------------------------------- joint limits


def test_joint_limits_zero_inside_quadratic_outside():
    term = JointLimits(torch.tensor([-1.0, 0.0]), torch.tensor([1.0, 2.0]), sigma=0.1)
    inside = torch.tensor([[0.5, 1.0], [-1.0, 2.0]], dtype=D64)
    assert (term.energy(ev(q=inside)) == 0).all()
    for delta in (0.1, 0.2):
        above = torch.tensor([1.0 + delta, 1.0], dtype=D64)
        below = torch.tensor([0.0, -delta], dtype=D64)
        expected = torch.tensor(0.5 * (delta / 0.1) ** 2, dtype=D64)
        torch.testing.assert_close(term.energy(ev(q=above)), expected)
        torch.testing.assert_close(term.energy(ev(q=below)), expected)
    torch.testing.assert_close(
        term.residual(ev(q=torch.tensor([1.3, -0.5], dtype=D64))), torch.tensor([3.0, -5.0], dtype=D64)
    )


def test_joint_limits_infinite_bounds():
    inf = math.inf
    term = JointLimits(torch.tensor([-inf, 0.0, -inf]), torch.tensor([inf, inf, 1.0]))
    q = torch.tensor([1e6, 1e6, -1e6], dtype=D64, requires_grad=True)
    energy = term.energy(ev(q=q))
    (g,) = torch.autograd.grad(energy, q)
    assert energy == 0 and (g == 0).all()
    q2 = torch.tensor([0.0, -0.1, 1.1], dtype=D64)
    torch.testing.assert_close(term.residual(ev(q=q2)), torch.tensor([0.0, -2.0, 2.0], dtype=D64))


def test_joint_limits_batched_and_time_axis():
    lo, hi = -torch.ones(3), torch.ones(3)
    q = torch.randn(4, 5, 3, generator=gen(9), dtype=D64) * 2
    frame = JointLimits(lo, hi)
    traj = JointLimits(lo, hi, time_axis=True)
    assert frame.energy(ev(q=q)).shape == (4, 5)
    assert traj.residual(ev(q=q)).shape == (4, 15)
    torch.testing.assert_close(traj.energy(ev(q=q)), frame.energy(ev(q=q)).sum(-1))
    per_dof = JointLimits(lo, hi, sigma=torch.tensor([0.1, 0.2, 0.4]))
    torch.testing.assert_close(
        per_dof.residual(ev(q=torch.tensor([2.0, 2.0, 2.0], dtype=D64))), torch.tensor([10.0, 5.0, 2.5], dtype=D64)
    )


def test_joint_limits_gradcheck():
    term = JointLimits(torch.tensor([-1.0, 0.0, -math.inf]), torch.tensor([1.0, 0.5, 0.0]), sigma=0.3, time_axis=True)
    q = torch.tensor([[[1.4, -0.3, 0.7], [0.2, 0.9, -2.0]]], dtype=D64, requires_grad=True)
    assert gradcheck(lambda x: term.energy(ev(q=x)), (q,))


def test_joint_limits_input_errors():
    with pytest.raises(InputError, match="lower <= upper"):
        JointLimits(torch.tensor([1.0]), torch.tensor([0.0]))
    with pytest.raises(InputError, match=r"\(2,\) and \(3,\)"):
        JointLimits(torch.zeros(2), torch.ones(3))
    with pytest.raises(InputError, match="sigma"):
        JointLimits(torch.zeros(2), torch.ones(2), sigma=-0.1)
    with pytest.raises(InputError, match=r"ev\.q"):
        JointLimits(torch.zeros(2), torch.ones(2)).energy(ev(q=torch.zeros(4, 3)))


# ---------------------------------------------------------------- smoothness


def test_smoothness_constant_and_linear():
    term = Smoothness(dt=0.1, sigma_velocity=2.0, sigma_acceleration=5.0)
    const = torch.ones(6, 3, dtype=D64) * 0.7
    assert term.energy(ev(q=const)) == 0
    slope = torch.tensor([1.0, -2.0, 0.5], dtype=D64)
    linear = torch.arange(6, dtype=D64)[:, None] * slope
    accel_only = Smoothness(dt=0.1, sigma_acceleration=5.0)
    vel_only = Smoothness(dt=0.1, sigma_velocity=2.0)
    torch.testing.assert_close(accel_only.energy(ev(q=linear)), torch.tensor(0.0, dtype=D64))
    expected = 0.5 * 5 * ((slope / 0.1 / 2.0) ** 2).sum()
    torch.testing.assert_close(vel_only.energy(ev(q=linear)), expected)
    torch.testing.assert_close(term.energy(ev(q=linear)), expected)


def test_smoothness_hand_computed_acceleration_and_shapes():
    q = torch.tensor([[0.0], [1.0], [4.0], [9.0]], dtype=D64)
    term = Smoothness(dt=0.5, sigma_velocity=1.0, sigma_acceleration=4.0)
    r = term.residual(ev(q=q))
    torch.testing.assert_close(r, torch.tensor([2.0, 6.0, 10.0, 2.0, 2.0], dtype=D64))
    batch = torch.randn(3, 7, 4, generator=gen(10), dtype=D64)
    assert term.residual(ev(q=batch)).shape == (3, 6 * 4 + 5 * 4)
    assert term.energy(ev(q=batch)).shape == (3,)


def test_smoothness_none_sigmas_and_dof_scale():
    q = torch.randn(2, 5, 3, generator=gen(11), dtype=D64)
    nothing = Smoothness(dt=0.1)
    assert nothing.residual(ev(q=q)).shape == (2, 0)
    assert (nothing.energy(ev(q=q)) == 0).all()
    scaled = Smoothness(dt=0.1, sigma_velocity=1.0, dof_scale=torch.tensor([0.0, 2.0, 0.0]))
    plain = Smoothness(dt=0.1, sigma_velocity=1.0)
    torch.testing.assert_close(scaled.energy(ev(q=q)), 4 * plain.energy(ev(q=q[..., 1:2])))


def test_smoothness_on_joints():
    joints = torch.randn(2, 4, 5, 3, generator=gen(12), dtype=D64)
    term = Smoothness(dt=1 / 30, sigma_velocity=1.0, sigma_acceleration=1.0, on="joints", dof_scale=torch.ones(5))
    assert term.energy(ev(joints=joints)).shape == (2,)
    still = joints[:, :1].expand(2, 4, 5, 3)
    assert (term.energy(ev(joints=still)) == 0).all()


def test_smoothness_gradcheck():
    term = Smoothness(dt=0.2, sigma_velocity=0.5, sigma_acceleration=2.0, dof_scale=torch.tensor([1.0, 0.3]))
    q = torch.randn(2, 5, 2, generator=gen(13), dtype=D64, requires_grad=True)
    assert gradcheck(lambda x: term.energy(ev(q=x)), (q,))


@pytest.mark.parametrize("loss", LOSSES)
@pytest.mark.parametrize("on", ["q", "joints"])
def test_robust_smoothness_gradient_and_band_weights_are_autograds(loss, on):
    """`Smoothness.banded_gauss_newton` under a robust loss: its gradient equals autograd's of the term's energy,
    its per-frame energies sum to that energy, and its band weights are the Gauss-Newton Hessian J^T W J with the
    IRLS weights rho'(r^2) of `robust_weights` (J from autograd of the residual), per order."""
    torch.manual_seed(0)
    shape, scale = ((2, 7, 3), torch.tensor([1.0, 0.3, 2.0])) if on == "q" else ((2, 7, 2, 3), torch.tensor([0.5, 2.0]))
    term = Smoothness(0.1, 0.5, 2.0, on=on, dof_scale=scale, loss=loss, scale=1.5)
    x = 0.2 * torch.randn(shape, generator=gen(14), dtype=D64)
    x[:, 4] += 1.0  # a jump: some residuals far into the loss's tails

    def make(x_):
        return ev(q=x_) if on == "q" else ev(joints=x_)

    xg = x.clone().requires_grad_()
    (grad,) = torch.autograd.grad(term.energy(make(xg)).sum(), xg)
    out = term.banded_gauss_newton(make(x))
    torch.testing.assert_close(out.gradient, grad, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out.energy.sum(-1), term.energy(make(x)), rtol=1e-12, atol=0.0)
    assert out.energy.shape == x.shape[:2]
    if loss != "l2":
        assert not torch.equal(term.robust_weights(make(x)), torch.ones_like(term.residual(make(x))))
    no_derivatives = term.banded_gauss_newton(make(x), derivatives=False)
    assert no_derivatives.gradient is None and no_derivatives.weights == ()
    torch.testing.assert_close(no_derivatives.energy, out.energy, rtol=0.0, atol=0.0)
    t_len = x.shape[1]
    for (n, part), (m, c) in zip(term.orders(), out.weights):
        assert n == m and c.shape == (2, t_len - n, *x.shape[2:])
        jac = torch.autograd.functional.jacobian(lambda y: part.residual(make(y)), x[0]).flatten(1)  # (M, T E)
        w = part.robust_weights(make(x[0]))  # (M,)
        want = jac.T @ (w[:, None] * jac)  # (T E, T E)
        entries = jac.shape[1] // t_len
        for k in range(entries):  # each entry's coupling over time: D_n^T diag(c[:, k]) D_n
            dn = torch.zeros(t_len - n, t_len, dtype=D64)
            for j in range(n + 1):
                dn[torch.arange(t_len - n), torch.arange(t_len - n) + j] = (-1.0) ** (n - j) * math.comb(n, j)
            got = dn.T @ (c[0].flatten(1)[:, k, None] * dn)
            torch.testing.assert_close(got, want[k::entries, k::entries], rtol=1e-12, atol=1e-12)


def test_smoothness_orders_and_select():
    """`orders` splits the prior into its velocity and acceleration parts (energies adding up to the term's);
    `select` keeps the scales of some dofs, for a trajectory of just those."""
    term = Smoothness(0.1, 2.0, 5.0, dof_scale=torch.tensor([1.0, 0.5, 3.0]), loss="cauchy", scale=2.0)
    q = torch.randn(2, 6, 3, generator=gen(15), dtype=D64)
    parts = term.orders()
    assert [n for n, _ in parts] == [1, 2]
    assert parts[0][1].sigma_acceleration is None and parts[1][1].sigma_velocity is None
    torch.testing.assert_close(sum(p.energy(ev(q=q)) for _, p in parts), term.energy(ev(q=q)))
    idx = torch.tensor([2, 0])
    sub = Smoothness(0.1, 2.0, 5.0, dof_scale=torch.tensor([3.0, 1.0]), loss="cauchy", scale=2.0)
    torch.testing.assert_close(term.select(idx).energy(ev(q=q[..., idx])), sub.energy(ev(q=q[..., idx])))
    with pytest.raises(InputError, match="loss"):
        Smoothness(0.1, 1.0, loss="tukey")


def test_smoothness_input_errors():
    with pytest.raises(InputError, match="dt"):
        Smoothness(dt=0.0, sigma_velocity=1.0)
    with pytest.raises(InputError, match="sigma_acceleration"):
        Smoothness(dt=0.1, sigma_acceleration=-1.0)
    with pytest.raises(InputError, match="on"):
        Smoothness(dt=0.1, on="pixels")
    with pytest.raises(InputError, match="dof_scale"):
        term = Smoothness(dt=0.1, sigma_velocity=1.0, dof_scale=torch.ones(4))
        term.energy(ev(q=torch.zeros(3, 2)))


# ---------------------------------------------------------------- keyframes


def spd(d, seed):
    a = torch.randn(d, d, generator=gen(seed), dtype=D64)
    return a @ a.T + d * torch.eye(d, dtype=D64)


def test_keyframe_full_covariance_matches_mahalanobis():
    cov = spd(3, 14)
    target = torch.randn(2, 3, generator=gen(15), dtype=D64)
    q = torch.randn(5, 3, generator=gen(16), dtype=D64)
    term = Keyframe(torch.tensor([1, 4]), target, cov)
    e = q[[1, 4]] - target
    expected = 0.5 * torch.einsum("fi,ij,fj->", e, torch.linalg.inv(cov), e)
    torch.testing.assert_close(term.energy(ev(q=q)), expected)


def test_keyframe_partial_full_covariance_uses_sub_block():
    covs = torch.stack([spd(4, 17), spd(4, 18)])
    target = torch.randn(2, 4, generator=gen(19), dtype=D64)
    mask = torch.tensor([[True, False, True, True], [False, True, False, False]])
    target[~mask] = float("nan")
    q = torch.randn(3, 6, 4, generator=gen(20), dtype=D64)
    term = Keyframe(torch.tensor([0, 5]), target, covs, mask=mask)
    r = term.residual(ev(q=q))
    assert r.shape == (3, 8)
    expected = torch.zeros(3, dtype=D64)
    for j, t in enumerate((0, 5)):
        keep = mask[j]
        e = q[:, t, keep] - target[j, keep]
        sub = covs[j][keep][:, keep]
        expected += 0.5 * torch.einsum("ni,ij,nj->n", e, torch.linalg.inv(sub), e)
    torch.testing.assert_close(term.energy(ev(q=q)), expected)
    assert (r.reshape(3, 2, 4)[:, ~mask] == 0).all()


def test_keyframe_partial_diagonal_and_forms_agree():
    var = torch.tensor([0.5, 2.0, 0.1], dtype=D64)
    target = torch.tensor([[1.0, float("nan"), 3.0], [0.0, 1.0, 0.0]], dtype=D64)
    mask = torch.tensor([[True, False, True], [True, True, True]])
    q = torch.randn(4, 3, generator=gen(21), dtype=D64)
    e = q[[0, 2]] - torch.nan_to_num(target)
    expected = 0.5 * ((e**2 / var) * mask).sum()
    forms = [var, var.expand(2, 3).clone(), torch.diag(var), torch.diag_embed(var.expand(2, 3))]
    for cov in forms:
        term = Keyframe(torch.tensor([0, 2]), target, cov, mask=mask)
        torch.testing.assert_close(term.energy(ev(q=q)), expected)
    inf_var = torch.tensor([[0.5, math.inf, 0.1], [0.5, 2.0, 0.1]], dtype=D64)
    term = Keyframe(torch.tensor([0, 2]), torch.nan_to_num(target), inf_var)
    torch.testing.assert_close(term.energy(ev(q=q)), expected)


def test_keyframe_ambiguous_square_covariance():
    target = torch.zeros(2, 2)
    with pytest.raises(InputError, match="ambiguous"):
        Keyframe(torch.tensor([0, 1]), target, torch.eye(2))
    q = torch.tensor([[1.0, 0.0], [0.0, 1.0]], dtype=D64)
    var = torch.tensor([[4.0, 1.0], [1.0, 1.0]])
    diag = Keyframe(torch.tensor([0, 1]), target, var, diagonal=True)
    torch.testing.assert_close(diag.energy(ev(q=q)), torch.tensor(0.5 * (0.25 + 1.0), dtype=D64))


def test_keyframe_gradcheck_and_batch():
    cov = spd(3, 22)
    mask = torch.tensor([[True, True, False], [True, True, True]])
    term = Keyframe(torch.tensor([2, 0]), torch.randn(2, 3, generator=gen(23)), cov, mask=mask)
    q = torch.randn(2, 4, 3, generator=gen(24), dtype=D64, requires_grad=True)
    assert term.energy(ev(q=q)).shape == (2,)
    assert gradcheck(lambda x: term.energy(ev(q=x)), (q,))


def test_keyframe_input_errors():
    with pytest.raises(InputError, match="positive definite"):
        Keyframe(torch.tensor([0]), torch.zeros(1, 2), torch.tensor([[1.0, 2.0], [2.0, 1.0]]))
    with pytest.raises(InputError, match="times"):
        Keyframe(torch.tensor([-1]), torch.zeros(1, 2), torch.ones(2))
    with pytest.raises(InputError, match="times"):
        Keyframe(torch.tensor([0.5]), torch.zeros(1, 2), torch.ones(2))
    with pytest.raises(InputError, match="NaN"):
        Keyframe(torch.tensor([0]), torch.full((1, 2), float("nan")), torch.ones(2))
    with pytest.raises(InputError, match="covariance"):
        Keyframe(torch.tensor([0]), torch.zeros(1, 2), torch.ones(3))
    with pytest.raises(InputError, match="mask"):
        Keyframe(torch.tensor([0]), torch.zeros(1, 2), torch.ones(2), mask=torch.ones(1, 3, dtype=torch.bool))
    term = Keyframe(torch.tensor([7]), torch.zeros(1, 2), torch.ones(2))
    with pytest.raises(InputError, match="keyframe time 7"):
        term.energy(ev(q=torch.zeros(5, 2)))


def test_joint_keyframe_hand_computed_and_gradcheck():
    target = torch.zeros(2, 3, 3, dtype=D64)
    target[0, 1] = float("nan")
    mask = torch.tensor([[True, False, True], [True, True, True]])
    term = JointKeyframe(torch.tensor([1, 3]), target, mask, sigma_m=0.1)
    joints = torch.randn(2, 4, 3, 3, generator=gen(25), dtype=D64, requires_grad=True)
    energy = term.energy(ev(joints=joints))
    expected = 0.5 * ((joints[:, 1, [0, 2]] / 0.1) ** 2).sum((-1, -2)) + 0.5 * ((joints[:, 3] / 0.1) ** 2).sum((-1, -2))
    torch.testing.assert_close(energy, expected)
    assert term.residual(ev(joints=joints)).shape == (2, 18)
    assert gradcheck(lambda x: term.energy(ev(joints=x)), (joints,))
    with pytest.raises(InputError, match="target_joints"):
        JointKeyframe(torch.tensor([0]), torch.zeros(1, 3, 2))
    with pytest.raises(InputError, match="sigma_m"):
        JointKeyframe(torch.tensor([0]), torch.zeros(1, 3, 3), sigma_m=0.0)


# ---------------------------------------------------------------- silhouette


def box_mask(h=20, w=24):
    m = torch.zeros(h, w, dtype=torch.bool)
    m[5:15, 6:14] = True
    return m


def brute_force_edt(mask):
    """Exact EDT by brute force: mask (..., H, W) bool -> (..., H, W) float64, the Euclidean
    distance from each pixel to the nearest True pixel; hypot(H, W) where there is none."""
    h, w = mask.shape[-2:]
    v, u = torch.meshgrid(torch.arange(h, dtype=D64), torch.arange(w, dtype=D64), indexing="ij")
    pix = torch.stack([v, u], dim=-1).reshape(-1, 2)
    d = (pix[:, None] - pix[None]).square().sum(-1).sqrt()  # (HW, HW) pixel to pixel
    flat = mask.reshape(-1, 1, h * w)
    out = torch.where(flat, d, math.inf).amin(-1)
    out = torch.where(flat.any(-1), out, math.hypot(h, w))
    return out.reshape(mask.shape)


@pytest.mark.parametrize("shape", [(17, 23), (2, 3, 9, 14), (1, 31), (12, 1), (5, 2, 2)])
def test_distance_transform_matches_brute_force(shape):
    g = gen(26)
    masks = torch.rand(shape, generator=g) > torch.rand(shape[:-2] + (1, 1), generator=g)
    flat = masks.reshape(-1, *shape[-2:])
    flat[0] = False  # an empty mask
    if flat.shape[0] > 1:
        flat[1] = True  # a full mask
    if flat.shape[0] > 2:
        flat[2] = False
        flat[2, -1, 0] = True  # one pixel in a corner
    got = distance_transform(masks)
    assert got.shape == masks.shape and got.dtype == D64 and got.device == masks.device
    torch.testing.assert_close(got, brute_force_edt(masks), rtol=0.0, atol=1e-9)
    assert torch.isfinite(got).all()


def test_distance_transform_edge_cases():
    assert distance_transform(torch.zeros(0, 4, 5, dtype=torch.bool)).shape == (0, 4, 5)
    assert distance_transform(torch.zeros(3, 0, 5, dtype=torch.bool)).shape == (3, 0, 5)
    empty = distance_transform(torch.zeros(4, 5, dtype=torch.bool))
    assert (empty == math.hypot(4, 5)).all()  # finite, above any distance inside a 4 x 5 image
    assert (distance_transform(torch.ones(4, 5, dtype=torch.bool)) == 0).all()
    with pytest.raises(InputError, match="mask"):
        distance_transform(torch.ones(5, dtype=torch.bool))


def test_distance_transform_far_corner_of_a_full_size_image():
    # speed is measured by scripts/bench_silhouette.py, not asserted here
    masks = torch.zeros(4, 480, 640, dtype=torch.bool)
    masks[:, 200:330, 300:360] = True
    d = distance_transform(masks)
    assert d[0, 0, 0] == math.hypot(200, 300)


def test_silhouette_zero_inside():
    term = Silhouette(box_mask(), bones=((0, 1), (1, 2)), sigma_px=2.0)
    jp = torch.tensor([[7.0, 6.0], [10.0, 10.0], [12.5, 13.0]], dtype=D64)
    assert term.residual(ev(joint_pixels=jp)).shape == (16,)
    assert term.energy(ev(joint_pixels=jp)) == 0


def test_silhouette_outside_positive_and_pulls_inward():
    term = Silhouette(box_mask(), bones=((0, 1),), sigma_px=2.0, samples_per_bone=5)
    jp = torch.tensor([[17.0, 8.0], [19.0, 12.0]], dtype=D64, requires_grad=True)
    energy = term.energy(ev(joint_pixels=jp))
    (g,) = torch.autograd.grad(energy, jp)
    assert energy > 0
    assert (g[:, 0] > 0).all()  # descent (-g) moves both joints left, towards the box
    assert g[:, 1].abs().max() < 1e-9
    # a sample at the parent joint (17, 8) is 3.5 px right of the centre of the box's last
    # column 13 (13.5): residual 3.5 / sigma_px
    torch.testing.assert_close(term.residual(ev(joint_pixels=jp))[0], torch.tensor(1.75, dtype=D64))


def test_silhouette_outside_image_still_pulls_inward():
    term = Silhouette(box_mask(), bones=((0, 1),))
    jp = torch.tensor([[-10.0, 10.0], [-30.0, 10.0]], dtype=D64, requires_grad=True)
    energy = term.energy(ev(joint_pixels=jp))
    (g,) = torch.autograd.grad(energy, jp)
    assert torch.isfinite(energy) and energy > 0
    assert (g[:, 0] < 0).all()
    # (-10, 10) is 16.5 px left of the centre of the box's first column 6 (6.5)
    torch.testing.assert_close(term.residual(ev(joint_pixels=jp))[0], torch.tensor(16.5, dtype=D64))


def one_pixel_mask(u, v, h=24, w=32):
    m = torch.zeros(h, w, dtype=torch.bool)
    m[v, u] = True
    return m


def read(term, points):
    """The term's residual (sigma_px = 1: the distance read) at points (N, 2), as (N,)."""
    return term.residual(ev(joint_pixels=torch.stack([points, points], dim=-2)))[..., 0]


def test_silhouette_pixel_centres_follow_the_camera():
    # pixel (u, v) covers [u, u+1) x [v, v+1), centre (u + 0.5, v + 0.5), as in Camera and
    # render_silhouettes: a one-pixel mask reads 0 at its centre, 1 one pixel to the right, ...
    term = Silhouette(one_pixel_mask(20, 10), bones=((0, 1),), samples_per_bone=2)
    pts = torch.tensor(
        [[20.5, 10.5], [21.5, 10.5], [19.5, 10.5], [20.5, 11.5], [20.5, 12.5], [23.5, 14.5], [17.5, 6.5], [21.5, 11.5]],
        dtype=D64,
    )
    expected = torch.tensor([0.0, 1.0, 1.0, 1.0, 2.0, 5.0, 5.0, math.sqrt(2.0)], dtype=D64)
    torch.testing.assert_close(read(term, pts), expected, rtol=0.0, atol=1e-9)
    # at every pixel centre of a random mask the term reads its distance transform exactly
    masks = torch.rand(13, 17, generator=gen(29)) > 0.9
    term = Silhouette(masks, bones=((0, 1),), samples_per_bone=2)
    v, u = torch.meshgrid(torch.arange(13, dtype=D64), torch.arange(17, dtype=D64), indexing="ij")
    centres = torch.stack([u, v], dim=-1).reshape(-1, 2) + 0.5
    torch.testing.assert_close(read(term, centres), distance_transform(masks).flatten(), rtol=0.0, atol=1e-9)


def test_silhouette_outside_image_reads_border_plus_distance():
    # outside the pixel centres' hull [0.5, W - 0.5] x [0.5, H - 0.5] a point reads DT at the
    # nearest hull point plus its distance to it (the exact distance when that hull point is
    # a mask pixel's centre)
    corner = Silhouette(one_pixel_mask(0, 0), bones=((0, 1),), samples_per_bone=2)
    edge = Silhouette(one_pixel_mask(31, 5), bones=((0, 1),), samples_per_bone=2)
    pts = torch.tensor([[-2.5, -3.5], [0.2, 0.5], [0.5, -0.5]], dtype=D64)
    torch.testing.assert_close(read(corner, pts), torch.tensor([5.0, 0.3, 1.0], dtype=D64), rtol=0.0, atol=1e-9)
    pts = torch.tensor([[35.5, 5.5], [34.5, 9.5], [32.0, 5.5]], dtype=D64)
    torch.testing.assert_close(read(edge, pts), torch.tensor([4.0, 4.0 + 3.0, 0.5], dtype=D64), rtol=0.0, atol=1e-9)
    box = Silhouette(box_mask(), bones=((0, 1),), samples_per_bone=2)  # columns 6..13, rows 5..14
    pts = torch.tensor([[-10.0, 10.5], [30.0, 10.0], [10.0, -4.5]], dtype=D64)
    torch.testing.assert_close(read(box, pts), torch.tensor([16.5, 16.5, 10.0], dtype=D64), rtol=0.0, atol=1e-9)


def test_silhouette_trajectory_batch_and_empty_frame():
    masks = torch.stack([box_mask(), torch.zeros(20, 24, dtype=torch.bool), box_mask()])
    term = Silhouette(masks, bones=((0, 1), (0, 2)), samples_per_bone=4, loss="cauchy")
    size = torch.tensor([24.0, 20.0], dtype=D64)
    jp = torch.rand(5, 3, 3, 2, generator=gen(27), dtype=D64) * size
    r = term.residual(ev(joint_pixels=jp))
    assert r.shape == (5, 3 * 2 * 4)
    assert term.energy(ev(joint_pixels=jp)).shape == (5,)
    assert (r.reshape(5, 3, 8)[:, 1] == 0).all()
    single = Silhouette(box_mask(), bones=((0, 1), (0, 2)), samples_per_bone=4, loss="cauchy")
    torch.testing.assert_close(r.reshape(5, 3, 8)[:, 2], single.residual(ev(joint_pixels=jp[:, 2])))


def test_silhouette_gradcheck():
    term = Silhouette(box_mask(), bones=((0, 1), (1, 2)), samples_per_bone=3, loss="huber", scale=2.0)
    jp = torch.tensor([[[18.3, 7.7], [9.2, 3.1]], [[-2.6, 8.4], [11.1, 17.8]]], dtype=D64)
    third = torch.tensor([[[20.45, 16.2]], [[4.15, 9.35]]], dtype=D64)
    jp = torch.cat([jp, third], dim=1).requires_grad_()
    assert gradcheck(lambda x: term.energy(ev(joint_pixels=x)), (jp,))


def test_silhouette_input_errors():
    with pytest.raises(InputError, match="joint_pixels"):
        Silhouette(box_mask(), bones=((0, 1),)).energy(ev())
    with pytest.raises(InputError, match="masks"):
        Silhouette(box_mask().float(), bones=((0, 1),))
    with pytest.raises(InputError, match="bones"):
        Silhouette(box_mask(), bones=())
    with pytest.raises(InputError, match="samples_per_bone"):
        Silhouette(box_mask(), bones=((0, 1),), samples_per_bone=1)
    with pytest.raises(InputError, match="J >"):
        Silhouette(box_mask(), bones=((0, 4),)).energy(ev(joint_pixels=torch.zeros(3, 2)))


# ---------------------------------------------------------------- objective


def trajectory_objective(weights=None):
    obs = torch.rand(4, 3, 2, generator=gen(28), dtype=D64) * 10
    terms = {
        "reprojection": Reprojection(obs, torch.ones(4, 3), sigma_px=2.0, loss="cauchy"),
        "limits": JointLimits(-torch.ones(2), torch.ones(2), sigma=0.5, time_axis=True),
        "smooth": Smoothness(dt=0.1, sigma_velocity=5.0, sigma_acceleration=50.0),
        "keyframe": Keyframe(torch.tensor([0]), torch.zeros(1, 2), torch.tensor([0.1, 0.2])),
    }
    return Objective(terms, weights)


def trajectory_eval(n=3, requires_grad=False):
    q = torch.randn(n, 4, 2, generator=gen(29), dtype=D64) * 1.5
    pix = torch.rand(n, 4, 3, 2, generator=gen(30), dtype=D64) * 10
    return q.requires_grad_(requires_grad), pix.requires_grad_(requires_grad)


def test_objective_breakdown_sums_to_total_and_applies_weights():
    q, pix = trajectory_eval()
    plain = trajectory_objective()
    weighted = trajectory_objective({"limits": 3.0, "smooth": 0.0})
    e = ev(q=q, pixels=pix)
    value = weighted(e)
    assert isinstance(value, ObjectiveValue) and value.total.shape == (3,)
    assert set(value.terms) == {"reprojection", "limits", "smooth", "keyframe"}
    torch.testing.assert_close(sum(value.terms.values()), value.total)
    base = plain(e).terms
    torch.testing.assert_close(value.terms["limits"], 3.0 * base["limits"])
    assert (value.terms["smooth"] == 0).all()
    torch.testing.assert_close(value.terms["reprojection"], plain.terms["reprojection"].energy(e))


def test_objective_residuals_and_robust_weights():
    q, pix = trajectory_eval()
    obj = trajectory_objective({"keyframe": 4.0})
    e = ev(q=q, pixels=pix)
    r, w = obj.residuals(e), obj.robust_weights(e)
    assert r.shape == w.shape == (3, 24 + 8 + 6 + 4 + 2)
    assert ((w > 0) & (w <= 1)).all()
    # least-squares terms: 0.5 |sqrt(w) r|^2 is their weighted energy
    priors = {k: v for k, v in obj.terms.items() if k != "reprojection"}
    least_squares = Objective(priors, {"keyframe": 4.0})
    half_square = 0.5 * least_squares.residuals(e).square().sum(-1)
    torch.testing.assert_close(half_square, least_squares(e).total)
    # IRLS weights give the exact gradient of the robust total: J^T W r
    q2, pix2 = trajectory_eval(requires_grad=True)
    e2 = ev(q=q2, pixels=pix2)
    (g,) = torch.autograd.grad(obj(e2).total.sum(), pix2)
    rr = obj.residuals(e2)
    irls = (rr * obj.robust_weights(e2).detach() * rr.detach()).sum()
    (g_irls,) = torch.autograd.grad(irls, pix2)
    torch.testing.assert_close(g, g_irls)


def test_objective_gradcheck():
    obj = trajectory_objective({"limits": 2.0})
    q, pix = trajectory_eval(n=2, requires_grad=True)
    assert gradcheck(lambda a, b: obj(ev(q=a, pixels=b)).total, (q, pix))


def test_objective_input_errors():
    with pytest.raises(InputError, match="bogus"):
        trajectory_objective({"bogus": 1.0})
    with pytest.raises(InputError, match="limits"):
        trajectory_objective({"limits": -1.0})
    with pytest.raises(InputError, match="at least one"):
        Objective({})
    with pytest.raises(InputError, match="not a cost term"):
        Objective({"x": 3.0})
    mixed = Objective(
        {"frame_limits": JointLimits(-torch.ones(2), torch.ones(2)), "smooth": Smoothness(dt=0.1, sigma_velocity=1.0)}
    )
    with pytest.raises(InputError, match="batch shape"):
        mixed(ev(q=torch.zeros(3, 4, 2, dtype=D64)))
