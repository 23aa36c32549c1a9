"""Closed-form residual Jacobians of the cost terms (`Objective.jacobian`, `PoseJacobian`) against
autograd through the whole pipeline (FK + projection + terms), on a real CMU pose, in float64."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from ptrack.body.keypoints import make_keypoints
from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.costs import (
    HeavyTailedPrior,
    JointLimits,
    Objective,
    PosePrior,
    Reprojection,
    SelfIntersection,
    SwapReprojection,
)
from ptrack.errors import InputError
from ptrack.observe.camera import camera_for_motion
from ptrack.optim.jacobians import objective_linearization
from ptrack.optim.solvers import _normal_equations
from ptrack.problem import evaluate_pose

DATA = Path(__file__).resolve().parents[1] / "ptrack" / "data"


@pytest.fixture(scope="module")
def scene():
    full = Skeleton.from_asf(DATA / "10.asf").with_limits("data")
    sk = full.freeze(["*fingers", "*thumb", "*hand", "*toes"])
    q = sk.reduce(load_amc(DATA / "10_02.amc", full).q[200:204], full)  # (4, D) float64
    kps = make_keypoints(sk)
    cam = camera_for_motion(sk.forward_kinematics(q), 6.0, 30.0, 10.0, 1000.0, 640, 480).to(dtype=torch.float64)
    return sk, q, kps, cam


def _autograd(sk, kps, cam, objective, q):
    """(N, M, D): autograd through FK, projection and the terms; problem i depends on q[i] only."""
    full = torch.autograd.functional.jacobian(lambda x: objective.residuals(evaluate_pose(sk, cam, kps, x)), q)
    return torch.stack([full[i, :, i] for i in range(q.shape[0])])


def test_camera_projection_jacobian(scene):
    sk, q, _kps, cam = scene
    X = sk.forward_kinematics(q)
    proj, d = cam.project_jacobian(X)
    torch.testing.assert_close(proj.pixels, cam.project(X).pixels)
    auto = torch.autograd.functional.jacobian(lambda x: cam.project(x).pixels, X[0])  # (J, 2, J, 3)
    auto = torch.stack([auto[j, :, j] for j in range(X.shape[1])])
    torch.testing.assert_close(d[0], auto, atol=1e-9, rtol=1e-9)


def test_objective_jacobian_matches_autograd(scene):
    """Reprojection (robust rows, a missing keypoint), limits (some dofs pushed outside), the pose
    prior and self-intersection (an arm pushed into the torso)."""
    sk, q, kps, cam = scene
    gen = torch.Generator().manual_seed(0)
    obs = cam.project(sk.forward_kinematics(q[0]).index_select(0, kps.index())).pixels
    obs = obs + torch.randn(obs.shape, generator=gen, dtype=torch.float64)
    conf = torch.ones(obs.shape[0], dtype=torch.float64)
    conf[3] = 0.0
    lower, upper = sk.limits(dtype=torch.float64)
    x = q + 0.05 * torch.randn(q.shape, generator=gen, dtype=torch.float64)
    x[1, sk.dof_names.index("lfemur.ry")] = upper[sk.dof_names.index("lfemur.ry")] + 0.3
    x[2, sk.dof_names.index("lhumerus.rz")] += 1.6  # swing the arm across the body
    collision = SelfIntersection.for_skeleton(sk)
    assert (collision.residual(evaluate_pose(sk, cam, kps, x)) > 0).any()
    objective = Objective(
        {
            "reprojection": Reprojection(obs, conf, sigma_px=2.0, loss="cauchy", scale=3.0),
            "limits": JointLimits(lower, upper, sigma=0.02),
            "prior": PosePrior(q, 0.1),
            "collision": collision,
        },
        {"limits": 2.0, "collision": 0.5},
    )
    lin = objective_linearization(sk, objective, cam, kps)(x)
    torch.testing.assert_close(lin.jacobian, _autograd(sk, kps, cam, objective, x), atol=1e-8, rtol=1e-7)
    torch.testing.assert_close(lin.residuals, objective.residuals(evaluate_pose(sk, cam, kps, x)))
    # limits, prior and collision folded into the normal equations: the same H, g and energy, fewer rows
    folded = objective_linearization(sk, objective, cam, kps, fold=True)(x)
    assert folded.residuals.shape[-1] == lin.residuals.shape[-1] - 2 * sk.num_dofs - collision.pairs.shape[0]
    for a, b in zip(_normal_equations(folded), _normal_equations(lin)):
        torch.testing.assert_close(a, b, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(folded.energy, lin.energy)


def test_forward_mode_fallback_for_terms_without_closed_form(scene):
    """A term with no `jacobian` method is differentiated by forward-mode autograd through its residual."""
    sk, q, kps, cam = scene

    class Height:  # a least-squares term of the joints only, with no closed form
        def residual(self, ev):
            return ev.joints[..., 1] * 3.0

        def energy(self, ev):
            return 0.5 * self.residual(ev).square().sum(-1)

        def robust_weights(self, ev):
            return torch.ones_like(self.residual(ev))

    objective = Objective({"height": Height(), "prior": PosePrior(q, 0.2)})
    lin = objective_linearization(sk, objective, cam, kps)(q)
    torch.testing.assert_close(lin.jacobian, _autograd(sk, kps, cam, objective, q), atol=1e-9, rtol=1e-9)


def test_pose_prior():
    mean = torch.zeros(3, 4)
    prior = PosePrior(mean, torch.tensor([1.0, 2.0, 4.0, 0.5]))
    from ptrack.costs import PoseEval

    ev = PoseEval(q=torch.ones(3, 4), joints=torch.zeros(3, 1, 3), pixels=torch.zeros(3, 1, 2), depth=torch.zeros(3, 1))
    torch.testing.assert_close(prior.residual(ev)[0], torch.tensor([1.0, 0.5, 0.25, 2.0]))
    assert prior.energy(ev).shape == (3,)
    with pytest.raises(InputError):
        PosePrior(mean, torch.tensor([1.0, -1.0, 1.0, 1.0]))
    with pytest.raises(InputError):
        PosePrior(mean, torch.ones(3))


def test_pose_prior_per_hypothesis_sigma(scene):
    """A std per hypothesis and dof (the trackers' motion-scaled dynamics): residuals and the closed-form
    Jacobian match autograd."""
    sk, q, kps, cam = scene
    sigma = 0.05 + torch.rand(q.shape, generator=torch.Generator().manual_seed(3), dtype=q.dtype)
    objective = Objective({"prior": PosePrior(q.flip(0), sigma)})
    lin = objective_linearization(sk, objective, cam, kps)(q)
    torch.testing.assert_close(lin.jacobian, _autograd(sk, kps, cam, objective, q), atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(objective.residuals(evaluate_pose(sk, cam, kps, q)), (q - q.flip(0)) / sigma)


def test_heavy_tailed_prior(scene):
    """Gaussian near the mean, logarithmic far from it (cauchy); its Jacobian matches autograd, and
    folded into the normal equations it gives the stacked rows' IRLS H, g and energy."""
    sk, q, kps, cam = scene
    sigma = torch.full(q.shape[-1:], 0.05, dtype=q.dtype)
    far = q.clone()
    far[:, sk.dof_names.index("lhumerus.rz")] += 1.0  # an arm 20 sigma off: a flip-sized jump
    heavy, gauss = HeavyTailedPrior(q, sigma, loss="cauchy", scale=3.0), PosePrior(q, sigma)
    near = q + 0.01
    for x, ratio in ((near, (0.9, 1.0)), (far, (0.0, 0.1))):
        ev = evaluate_pose(sk, cam, kps, x)
        r = heavy.energy(ev) / gauss.energy(ev)
        assert ((r > ratio[0]) & (r <= ratio[1] + 1e-12)).all(), r
    observed = cam.project(sk.forward_kinematics(q[0]).index_select(-2, kps.index())).pixels  # (K, 2)
    objective = Objective(
        {
            "prior": heavy,
            "reprojection": Reprojection(
                observed, torch.ones(observed.shape[0], dtype=q.dtype), loss="cauchy", scale=3.0
            ),
        }
    )
    lin = objective_linearization(sk, objective, cam, kps)(far)
    torch.testing.assert_close(lin.jacobian, _autograd(sk, kps, cam, objective, far), atol=1e-9, rtol=1e-9)
    folded = objective_linearization(sk, objective, cam, kps, fold=True)(far)
    for a, b in zip(_normal_equations(folded), _normal_equations(lin)):
        torch.testing.assert_close(a, b, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(folded.energy, lin.energy)
    with pytest.raises(InputError):
        HeavyTailedPrior(q, sigma, loss="nope")
    with pytest.raises(InputError):
        HeavyTailedPrior(q, -sigma)


def test_reprojection_pixel_jacobian_through_each_keypoints_point(scene):
    """`Reprojection.pixel_jacobian` on d pixels / d X (each keypoint's own 3D point, V = 3), taken on to the pose
    by `add_point_rows` (the joint Jacobian's pairs), gives the same normal equations J^T J, J^T r as the pose
    Jacobian `jacobian` (d pixels / d q) does, keypoint subset and a missing keypoint included."""
    from ptrack.optim.jacobians import pose_eval_and_jacobian
    from ptrack.optim.trajectory import add_point_rows

    sk, q, kps, cam = scene
    gen = torch.Generator().manual_seed(2)
    ev, jac = pose_eval_and_jacobian(sk, cam, kps, q)  # (N, ...) poses as frames of one trajectory
    keep = torch.arange(0, kps.index().numel(), 2)
    obs = ev.pixels[:, keep] + torch.randn(ev.pixels[:, keep].shape, generator=gen, dtype=torch.float64)
    conf = torch.rand(obs.shape[:-1], generator=gen, dtype=torch.float64)
    conf[1, 2] = 0.0
    term = Reprojection(obs, conf, sigma_px=2.0, keypoints=keep)
    n, k, d = q.shape[0], keep.numel(), q.shape[-1]
    r = term.residual(ev).reshape(n, 2 * k)
    rows = term.jacobian(ev, jac).reshape(n, 2 * k, d)
    _, dpix = cam.project_jacobian(ev.joints.index_select(-2, kps.index()))  # (N, K_all, 2, 3)
    per_point = term.pixel_jacobian(dpix).reshape(n, k, 2, 3)
    h = q.new_zeros(1, n, d, d)
    g = q.new_zeros(1, n, d)
    joints = [kps.joints[i] for i in keep.tolist()]
    add_point_rows(h, g, sk, q[None], joints, per_point[None], r[None, ..., None])
    torch.testing.assert_close(h[0], rows.mT @ rows, rtol=1e-10, atol=1e-8)
    torch.testing.assert_close(g[0], (rows.mT @ r[..., None])[..., 0], rtol=1e-10, atol=1e-8)


def test_swap_reprojection_reads_mirrored_labels(scene):
    """`SwapReprojection`: detections with every left/right label exchanged cost a pose what the true labels
    would, plus `swap_cost`; unexchanged detections cost what `Reprojection` says; the Jacobian is the chosen
    reading's (autograd), the marker rows zero."""
    sk, q, kps, cam = scene
    gen = torch.Generator().manual_seed(1)
    partners = kps.mirror_index()
    obs = cam.project(sk.forward_kinematics(q).index_select(-2, kps.index())).pixels  # (4, K, 2)
    obs = obs + torch.randn(obs.shape, generator=gen, dtype=torch.float64)
    conf = torch.rand(obs.shape[:-1], generator=gen, dtype=torch.float64) + 0.2
    conf[1, 5] = 0.0  # a missing keypoint (its partner's reading then has none either)
    mirrored = obs.index_select(-2, partners)
    mirrored_conf = conf.index_select(-1, partners)
    swapped_rows = torch.tensor([True, False, True, False])
    seen = torch.where(swapped_rows[:, None, None], mirrored, obs)
    seen_conf = torch.where(swapped_rows[:, None], mirrored_conf, conf)
    options = dict(sigma_px=2.0, loss="cauchy", scale=3.0, per_problem=True)
    term = SwapReprojection(seen, seen_conf, partners=partners, swap_cost=2.5, **options)
    plain = Reprojection(obs, conf, **options)
    ev = evaluate_pose(sk, cam, kps, q)
    assert term.swapped(ev).tolist() == swapped_rows.tolist()
    expected = plain.energy(ev) + 2.5 * swapped_rows.double()
    torch.testing.assert_close(term.energy(ev), expected, atol=1e-9, rtol=1e-9)
    r = term.residual(ev)
    assert r.shape == (4, 2 * len(kps.names) + 2)
    torch.testing.assert_close(r[:, :-2], plain.residual(ev), atol=1e-12, rtol=0)
    # the Jacobian of the chosen reading, in the objective's linearisation, against autograd
    x = q + 0.01 * torch.randn(q.shape, generator=gen, dtype=torch.float64)
    objective = Objective({"reprojection": term, "prior": PosePrior(q, 0.1)})
    assert term.swapped(evaluate_pose(sk, cam, kps, x)).tolist() == swapped_rows.tolist()
    lin = objective_linearization(sk, objective, cam, kps)(x)
    torch.testing.assert_close(lin.jacobian, _autograd(sk, kps, cam, objective, x), atol=1e-8, rtol=1e-7)
    torch.testing.assert_close(lin.energy, objective(evaluate_pose(sk, cam, kps, x)).total)
    marker = 2 * len(kps.names)
    assert bool((lin.jacobian[:, marker : marker + 2] == 0).all())
    # one frame for every pose: the same choice per pose
    one = SwapReprojection(mirrored[0], mirrored_conf[0], partners=partners, swap_cost=2.5, sigma_px=2.0)
    assert one.swapped(ev)[0]


def test_swap_reprojection_checks_its_inputs(scene):
    _sk, _q, kps, _cam = scene
    k = len(kps.names)
    obs, conf = torch.zeros(k, 2), torch.ones(k)
    partners = kps.mirror_index()
    with pytest.raises(InputError, match="involution"):
        SwapReprojection(obs, conf, partners=torch.zeros(k, dtype=torch.long))
    with pytest.raises(InputError, match="one frame per problem"):
        SwapReprojection(torch.zeros(3, k, 2), torch.ones(3, k), partners=partners)
    with pytest.raises(InputError, match="swap_cost"):
        SwapReprojection(obs, conf, partners=partners, swap_cost=0.0)
    with pytest.raises(InputError, match="partners"):
        SwapReprojection(obs, conf, partners=partners[:-1])
