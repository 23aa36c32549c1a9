"""Tests for ptrack.optim.solvers: batched Levenberg-Marquardt and L-BFGS against scipy on small problems,
per-problem independence, box constraints, IRLS, info records, and a real pose fit."""

from __future__ import annotations

from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
import scipy.optimize as so
import torch

from ptrack.body.keypoints import make_keypoints
from ptrack.body.limits import wrap_to_limits
from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.costs import JointLimits, Objective, Reprojection, cauchy, robust_loss_derivative
from ptrack.errors import InputError
from ptrack.observe.camera import camera_for_motion
from ptrack.optim.jacobians import objective_linearization
from ptrack.optim.solvers import Linearization, lbfgs, levenberg_marquardt
from ptrack.problem import evaluate_pose

DATA = Path(__file__).resolve().parents[1] / "ptrack" / "data"
F64 = torch.float64
TIGHT = dict(tol=1e-15, gtol=1e-13, max_iter=200)
SCIPY_TIGHT = dict(xtol=1e-15, ftol=1e-15, gtol=1e-15)

# -- a batch of 3-link planar arms reaching for targets with their elbow and hand -------------------

LINKS = torch.tensor([1.0, 0.8, 0.5], dtype=F64)


def _arm_points(q: torch.Tensor) -> torch.Tensor:
    """q (N, 3) joint angles -> (N, 3, 2) ends of the three links."""
    a = torch.cumsum(q, -1)
    steps = LINKS[:, None] * torch.stack([torch.cos(a), torch.sin(a)], -1)
    return torch.cumsum(steps, -2)


class Arms:
    """N arm problems: r = [elbow - t_elbow, hand - t_hand, 0.1 q] (N, 6), targets made from random
    poses plus noise (so the minimum has a nonzero residual), starts 0.3 rad away."""

    def __init__(self, n: int = 5, seed: int = 0, scale: torch.Tensor | None = None):
        g = torch.Generator().manual_seed(seed)
        self.q_true = torch.rand(n, 3, generator=g, dtype=F64) * 2 - 1
        pts = _arm_points(self.q_true)[:, [1, 2]]
        self.targets = pts + 0.05 * torch.randn(pts.shape, generator=g, dtype=F64)
        self.q0 = self.q_true + 0.3 * torch.randn(n, 3, generator=g, dtype=F64)

    def residuals(self, q: torch.Tensor) -> torch.Tensor:
        """q (N, 3) -> (N, 6)."""
        return torch.cat([(_arm_points(q)[:, [1, 2]] - self.targets).flatten(1), 0.1 * q], -1)

    def linearize(self, q: torch.Tensor):
        jac = torch.autograd.functional.jacobian(lambda x: self.residuals(x).sum(0), q)  # (M, N, D)
        return self.residuals(q), jac.permute(1, 0, 2)

    def energy(self, q: torch.Tensor) -> torch.Tensor:
        return 0.5 * self.residuals(q).square().sum(-1)

    def subset(self, idx) -> Arms:
        out = Arms.__new__(Arms)
        out.q_true, out.targets, out.q0 = self.q_true[idx], self.targets[idx], self.q0[idx]
        return out

    def scipy_problem(self, i: int):
        sub = self.subset([i])
        fun = lambda x: sub.residuals(torch.as_tensor(x)[None])[0].numpy()  # noqa: E731
        jac = lambda x: sub.linearize(torch.as_tensor(x)[None])[1][0].numpy()  # noqa: E731
        return fun, jac


@pytest.fixture(scope="module")
def arms() -> Arms:
    return Arms()


def test_lm_matches_scipy_least_squares(arms):
    q, info = levenberg_marquardt(arms.linearize, arms.q0, **TIGHT)
    assert info.converged.all()
    for i in range(5):
        fun, jac = arms.scipy_problem(i)
        ref = so.least_squares(fun, arms.q0[i].numpy(), jac=jac, method="lm", **SCIPY_TIGHT)
        np.testing.assert_allclose(q[i].numpy(), ref.x, rtol=0, atol=1e-6)
        np.testing.assert_allclose(info.cost[i].item(), ref.cost, rtol=1e-10)
    assert (info.cost > 1e-5).all()  # nonzero residual at the minimum: not a trivial fit


def _box(arms: Arms) -> tuple[torch.Tensor, torch.Tensor]:
    """Bounds 0.5 around the truth, the middle joint's upper one 0.1 below its unbounded optimum."""
    q_free, _ = levenberg_marquardt(arms.linearize, arms.q0, **TIGHT)
    lower, upper = arms.q_true - 0.5, arms.q_true + 0.5
    upper[:, 1] = q_free[:, 1] - 0.1
    return lower, upper


def test_lm_box_constraints_match_scipy_with_bounds(arms):
    lower, upper = _box(arms)
    q, info = levenberg_marquardt(arms.linearize, arms.q0, lower, upper, **TIGHT)
    assert info.converged.all()
    assert ((q >= lower) & (q <= upper)).all()
    assert (q[:, 1] == upper[:, 1]).all()
    for i in range(5):
        fun, jac = arms.scipy_problem(i)
        start = np.clip(arms.q0[i].numpy(), lower[i].numpy(), upper[i].numpy())
        ref = so.least_squares(
            fun, start, jac=jac, bounds=(lower[i].numpy(), upper[i].numpy()), method="trf", **SCIPY_TIGHT
        )
        np.testing.assert_allclose(q[i].numpy(), ref.x, rtol=0, atol=1e-6)
    # KKT: the free dofs' gradient vanishes, the bound dof's pushes outward
    assert info.gradient[:, [0, 2]].abs().max() < 1e-8
    assert (info.gradient[:, 1] < 0).all()


def test_lm_problems_are_independent(arms):
    q, info = levenberg_marquardt(arms.linearize, arms.q0, max_iter=50)
    for i in range(5):
        one = arms.subset([i])
        qi, ii = levenberg_marquardt(one.linearize, one.q0, max_iter=50)
        torch.testing.assert_close(qi[0], q[i], rtol=0, atol=1e-12)
        assert ii.iterations[0] == info.iterations[i]
        assert ii.converged[0] == info.converged[i]
    assert len(set(info.iterations.tolist())) > 1  # problems stop at their own iteration


def test_lm_converged_flags_and_iterations(arms):
    _, short = levenberg_marquardt(arms.linearize, arms.q0, max_iter=2)
    assert not short.converged.any() and (short.iterations == 2).all() and short.evaluations == 3
    q, info = levenberg_marquardt(arms.linearize, arms.q0, **TIGHT)
    assert info.converged.all() and (info.iterations < 200).all()
    # started at its solution a problem converges at once, beside others that keep going
    start = arms.q0.clone()
    start[2] = q[2]
    _, mixed = levenberg_marquardt(arms.linearize, start, gtol=1e-9)
    assert mixed.converged.all() and mixed.iterations[2] == 0 and (mixed.iterations[[0, 1, 3, 4]] > 3).all()


def test_callbacks_see_every_iteration(arms):
    seen = []
    record = lambda it, q, c: seen.append((it, c.clone()))  # noqa: E731
    _q, info = levenberg_marquardt(arms.linearize, arms.q0, max_iter=7, callback=record)
    assert [it for it, _ in seen] == list(range(7))
    torch.testing.assert_close(seen[-1][1], info.cost, rtol=0, atol=0)
    assert all((b <= a).all() for (_, a), (_, b) in pairwise(seen))  # LM never raises a cost
    seen.clear()
    _, info = lbfgs(arms.energy, arms.q0, max_iter=5, callback=record)
    assert [it for it, _ in seen] == list(range(5))
    assert all((b <= a).all() for (_, a), (_, b) in pairwise(seen))


def test_lm_hessian_is_gauss_newton_at_the_solution(arms):
    q, info = levenberg_marquardt(arms.linearize, arms.q0, **TIGHT)
    r, jac = arms.linearize(q)
    torch.testing.assert_close(info.hessian, jac.mT @ jac, rtol=0, atol=1e-12)
    torch.testing.assert_close(info.gradient, (jac.mT @ r[..., None])[..., 0], rtol=0, atol=1e-12)
    torch.testing.assert_close(info.cost, arms.energy(q), rtol=0, atol=1e-14)
    assert info.hessian.shape == (5, 3, 3) and info.damping.shape == (5,)


def test_lm_irls_matches_scipy_robust_least_squares():
    """Exponential curve fits with 20% gross outliers, Cauchy loss: IRLS weights + robust energy."""
    g = torch.Generator().manual_seed(1)
    n, m, c = 3, 30, 0.5
    x = torch.linspace(0, 2, m, dtype=F64)
    truth = torch.tensor([[1.0, 0.7, 0.2], [2.0, -0.5, 0.0], [0.5, 1.2, -0.3]], dtype=F64)

    def model(p):
        return p[:, :1] * torch.exp(p[:, 1:2] * x) + p[:, 2:]

    y = model(truth) + 0.05 * torch.randn(n, m, generator=g, dtype=F64)
    y[:, ::5] += 3.0
    w_of = robust_loss_derivative("cauchy")

    def linearize(p):
        r = model(p) - y
        jac = torch.stack([torch.exp(p[:, 1:2] * x), p[:, :1] * x * torch.exp(p[:, 1:2] * x), torch.ones_like(r)], -1)
        return Linearization(r, jac, w_of(r.square(), c), 0.5 * cauchy(r.square(), c).sum(-1))

    p0 = torch.tensor([[1.0, 0.0, 0.0]], dtype=F64).expand(n, 3)
    p, info = levenberg_marquardt(linearize, p0, **TIGHT)
    assert info.converged.all()
    for i in range(n):
        ref = so.least_squares(
            lambda a: (model(torch.as_tensor(a)[None]) - y[i]).numpy()[0],
            p0[i].numpy(),
            loss="cauchy",
            f_scale=c,
            method="trf",
            **SCIPY_TIGHT,
        )
        np.testing.assert_allclose(p[i].numpy(), ref.x, rtol=0, atol=1e-6)
        np.testing.assert_allclose(info.cost[i].item(), ref.cost, rtol=1e-9)
    # and the same through weights_fn / energy_fn instead of a Linearization
    p2, _ = levenberg_marquardt(
        lambda a: linearize(a)[:2],
        p0,
        **TIGHT,
        weights_fn=lambda a: linearize(a).weights,
        energy_fn=lambda a: linearize(a).energy,
    )
    torch.testing.assert_close(p2, p, rtol=0, atol=1e-12)


def test_lm_input_errors(arms):
    with pytest.raises(InputError, match="q0"):
        levenberg_marquardt(arms.linearize, arms.q0[0])
    with pytest.raises(InputError, match="lower"):
        levenberg_marquardt(arms.linearize, arms.q0, torch.zeros(4))
    with pytest.raises(InputError, match="lower <= upper"):
        levenberg_marquardt(arms.linearize, arms.q0, torch.ones(3), torch.zeros(3))
    with pytest.raises(InputError, match="jacobian"):
        levenberg_marquardt(lambda q: (arms.residuals(q), arms.linearize(q)[1][:, :, :2]), arms.q0)
    with pytest.raises(InputError, match="energy"):
        levenberg_marquardt(arms.linearize, arms.q0, weights_fn=lambda q: torch.ones(5, 6, dtype=F64))


def test_lm_keeps_dtype_and_device(arms):
    q, info = levenberg_marquardt(
        lambda x: tuple(t.float() for t in arms.linearize(x.double())), arms.q0.float(), max_iter=5
    )
    assert q.dtype == info.cost.dtype == info.hessian.dtype == torch.float32


# -- L-BFGS ----------------------------------------------------------------------------------------


def test_lbfgs_reaches_the_lm_minimum(arms):
    q_lm, _ = levenberg_marquardt(arms.linearize, arms.q0, **TIGHT)
    q, info = lbfgs(arms.energy, arms.q0, max_iter=200, gtol=1e-11)
    assert info.converged.all()
    torch.testing.assert_close(q, q_lm, rtol=0, atol=1e-6)
    torch.testing.assert_close(info.cost, arms.energy(q_lm), rtol=1e-10, atol=0)


def test_lbfgs_box_matches_scipy_minimize(arms):
    lower, upper = _box(arms)
    q, info = lbfgs(arms.energy, arms.q0, lower, upper, max_iter=200, gtol=1e-11)
    assert info.converged.all() and ((q >= lower) & (q <= upper)).all()
    for i in range(5):
        sub = arms.subset([i])

        def fg(x):
            t = torch.as_tensor(x)[None].requires_grad_(True)
            e = sub.energy(t)[0]
            e.backward()
            return e.item(), t.grad[0].numpy()

        start = np.clip(arms.q0[i].numpy(), lower[i].numpy(), upper[i].numpy())
        ref = so.minimize(
            fg,
            start,
            jac=True,
            method="L-BFGS-B",
            bounds=list(zip(lower[i].numpy(), upper[i].numpy())),
            options=dict(ftol=1e-15, gtol=1e-12, maxiter=500),
        )
        np.testing.assert_allclose(q[i].numpy(), ref.x, rtol=0, atol=1e-6)


def test_lbfgs_line_search_is_per_problem(arms):
    """A batch with one badly scaled problem (energy x 1e6, coordinates x 100: the unit first step
    overshoots by far and its line search backtracks many times): the other problems take exactly
    the steps they take alone, and the bad one still converges."""
    good = arms.subset([0, 1, 2, 3])
    bad = arms.subset([4])

    def energy(q):
        e_good = good.energy(q[:4])
        e_bad = 1e6 * bad.energy(q[4:] / 100.0)
        return torch.cat([e_good, e_bad])

    q0 = torch.cat([good.q0, 100.0 * bad.q0])
    q, info = lbfgs(energy, q0, max_iter=300, gtol=1e-9)
    q_alone, alone = lbfgs(good.energy, good.q0, max_iter=300, gtol=1e-9)
    torch.testing.assert_close(q[:4], q_alone, rtol=0, atol=1e-12)
    assert info.iterations[:4].tolist() == alone.iterations.tolist()
    assert info.converged.all()
    q_bad, _ = levenberg_marquardt(bad.linearize, bad.q0, **TIGHT)
    torch.testing.assert_close(q[4] / 100.0, q_bad[0], rtol=0, atol=1e-6)


def test_lbfgs_input_errors(arms):
    with pytest.raises(InputError, match="history"):
        lbfgs(arms.energy, arms.q0, history=0)
    with pytest.raises(InputError, match="shape"):
        lbfgs(lambda q: arms.energy(q).sum(), arms.q0)


# -- a real pose fit ---------------------------------------------------------------------------------


def test_lm_fits_cmu_pose_to_noiseless_keypoints():
    """Reduced CMU model (50 dofs) with data limits, a real frame of 10_02 seen by a virtual camera,
    its 17 noiseless keypoints; 16 starts perturbed by 0.1 rad per angle (5 cm on the root)."""
    sk = Skeleton.from_asf(DATA / "10.asf").freeze(["*fingers", "*thumb", "*hand", "*toes"]).with_limits("data")
    lo, hi = sk.limits(dtype=F64)
    q_all = wrap_to_limits(load_amc(DATA / "10_02.amc", sk).q.to(F64), lo, hi, torch.as_tensor(sk.angular_dofs()))
    joints = sk.forward_kinematics(q_all)
    cam = camera_for_motion(joints, 6.0, 30.0, 10.0, 1000.0, 640, 480).to(dtype=F64)
    kps = make_keypoints(sk)
    observed = cam.project(joints[300, kps.index()]).pixels
    obj = Objective(
        {
            "reprojection": Reprojection(
                observed, torch.ones(kps.num_keypoints, dtype=F64), sigma_px=1.0, loss="cauchy", scale=5.0
            ),
            "limits": JointLimits(lo, hi, sigma=0.05),
        }
    )
    g = torch.Generator().manual_seed(0)
    noise = 0.1 * torch.randn(16, sk.num_dofs, generator=g, dtype=F64)
    noise[:, :3] *= 0.5
    q0 = q_all[300] + noise
    start_px = (evaluate_pose(sk, cam, kps, q0.clamp(lo, hi)).pixels - observed).norm(dim=-1).amax(-1)
    assert (start_px > 10).all()
    linearize = objective_linearization(sk, obj, cam, kps)
    q, info = levenberg_marquardt(linearize, q0, lo, hi, max_iter=60)
    px = (evaluate_pose(sk, cam, kps, q).pixels - observed).norm(dim=-1).amax(-1)
    assert (px < 0.1).all(), px
    assert info.converged.all() and ((q >= lo) & (q <= hi)).all()
    lin = linearize(q)
    gauss_newton = lin.jacobian.mT @ (lin.weights[..., None] * lin.jacobian)
    torch.testing.assert_close(info.hessian, gauss_newton, rtol=1e-10, atol=1e-8)
