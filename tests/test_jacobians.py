"""Tests for ptrack.optim.jacobians: the geometric joint Jacobian and residual Jacobians, against autograd
(float64) on the bundled CMU skeleton with real poses, reduced models and random trees."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from ptrack.body.keypoints import make_keypoints
from ptrack.body.limits import wrap_to_limits
from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.costs import JointLimits, Objective, PoseEval, Reprojection
from ptrack.errors import InputError
from ptrack.observe.camera import camera_for_motion
from ptrack.optim.jacobians import (
    joint_and_point_jacobian,
    joint_jacobian,
    joint_jacobian_product,
    objective_linearization,
    point_jacobian,
    residual_jacobian,
)
from ptrack.problem import evaluate_pose

DATA = Path(__file__).resolve().parents[1] / "ptrack" / "data"
F64 = torch.float64
# the same float64 quantity by two code paths (batch layout, rows chosen or not, FK given or not): equal
# up to rounding, not bit for bit, since BLAS/SIMD kernels and FMA contraction depend on the shapes, the
# CPU and the torch build. Coordinates and Jacobian entries are a few metres (per radian) at most and
# come out of FK chains ~10 rotations deep, a few ulps (2.2e-16 of 3 m) each: ~1e-14; 1e-13 allows 10x
SAME = {"rtol": 0, "atol": 1e-13}
REDUCE = ["*fingers", "*thumb", "*hand", "*toes"]


@pytest.fixture(scope="module")
def cmu() -> Skeleton:
    return Skeleton.from_asf(DATA / "10.asf")


def _poses(sk: Skeleton, n: int = 5) -> torch.Tensor:
    """n real poses of 10_02 (every 100th frame) in sk's dof layout, float64 (n, D)."""
    return load_amc(DATA / "10_02.amc", sk).q[::100][:n].to(F64)


def _autograd_joint_jacobian(sk: Skeleton, q: torch.Tensor) -> torch.Tensor:
    """q (N, D) -> (N, J, 3, D) through the FK's own backward (problems are independent)."""
    jac = torch.autograd.functional.jacobian(lambda x: sk.forward_kinematics(x).sum(0), q)  # (J, 3, N, D)
    return jac.permute(2, 0, 1, 3)


def _random_tree(seed: int, j: int = 9) -> Skeleton:
    """A URDF-ish random tree: free unit axes (the Rodrigues FK path), rest rotations, offsets
    fixed in the parent frame and turning with the joint, frozen slots at nonzero angles, a
    partial root translation."""
    rng = np.random.default_rng(seed)
    parents = [-1] + [int(rng.integers(0, i)) for i in range(1, j)]
    axes = rng.normal(size=(j, 3, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    driven = rng.random((j, 3)) < 0.7
    translation_dof = np.array([0, -1, 1])
    axis_dof = -np.ones((j, 3), dtype=np.int64)
    axis_dof[driven] = 2 + np.arange(int(driven.sum()))
    d = 2 + int(driven.sum())
    rest = np.stack([np.linalg.qr(rng.normal(size=(3, 3)))[0] for _ in range(j)])
    rest *= np.sign(np.linalg.det(rest))[:, None, None]
    offset_parent = rng.normal(size=(j, 3))
    offset_parent[0] = 0.0
    return Skeleton(
        name=f"tree{seed}",
        joint_names=tuple(f"j{i}" for i in range(j)),
        parents=tuple(parents),
        axes=axes,
        axis_dof=axis_dof,
        rest_rotation=rest,
        offset_parent=offset_parent,
        offset_local=rng.normal(size=(j, 3)),
        lengths=rng.uniform(0.2, 1.5, size=j),
        root_position=rng.normal(size=3),
        translation_dof=translation_dof,
        dof_names=tuple(f"q{k}" for k in range(d)),
        lower=np.full(d, -math.inf),
        upper=np.full(d, math.inf),
        frozen_axes=np.where(driven, 0.0, rng.uniform(-1, 1, size=(j, 3))),
    )


def test_joint_jacobian_matches_autograd_on_real_cmu_poses(cmu):
    q = _poses(cmu)
    joints, jac = joint_jacobian(cmu, q)
    assert joints.shape == (5, cmu.num_joints, 3) and jac.shape == (5, cmu.num_joints, 3, cmu.num_dofs)
    torch.testing.assert_close(joints, cmu.forward_kinematics(q), rtol=0, atol=1e-12)
    torch.testing.assert_close(jac, _autograd_joint_jacobian(cmu, q), rtol=0, atol=1e-10)


@pytest.mark.parametrize(
    "patterns,value", [(REDUCE, 0.0), (["*clavicle", "lfemur.rz", "root.t*"], 0.3)], ids=["no_hands", "frozen_at_0.3"]
)
def test_joint_jacobian_on_reduced_models(cmu, patterns, value):
    sk = cmu.freeze(patterns, value=value)
    q = _poses(sk)
    joints, jac = joint_jacobian(sk, q)
    assert jac.shape[-1] == sk.num_dofs < cmu.num_dofs
    torch.testing.assert_close(joints, sk.forward_kinematics(q), rtol=0, atol=1e-12)
    torch.testing.assert_close(jac, _autograd_joint_jacobian(sk, q), rtol=0, atol=1e-10)


@pytest.mark.parametrize("seed", range(4))
def test_joint_jacobian_on_random_urdf_like_trees(seed):
    sk = _random_tree(seed)
    q = torch.randn(4, sk.num_dofs, generator=torch.Generator().manual_seed(seed), dtype=F64)
    joints, jac = joint_jacobian(sk, q)
    torch.testing.assert_close(joints, sk.forward_kinematics(q), rtol=0, atol=1e-12)
    torch.testing.assert_close(jac, _autograd_joint_jacobian(sk, q), rtol=0, atol=1e-10)


def test_joint_jacobian_any_leading_dims_and_dtype(cmu):
    q = _poses(cmu, 4)
    _, flat = joint_jacobian(cmu, q)
    joints, jac = joint_jacobian(cmu, q.reshape(2, 2, -1))
    assert joints.shape == (2, 2, cmu.num_joints, 3)
    torch.testing.assert_close(jac.reshape(flat.shape), flat, **SAME)
    _, single = joint_jacobian(cmu, q[0])
    torch.testing.assert_close(single, flat[0], rtol=0, atol=1e-14)
    j32, jac32 = joint_jacobian(cmu, q.float())
    assert j32.dtype == jac32.dtype == torch.float32
    torch.testing.assert_close(jac32.double(), flat, rtol=0, atol=1e-4)


def _chosen_joints_case(cmu, model: str, gen: torch.Generator):
    """A model, 3 poses and a choice of joints for the chosen-rows tests: CMU and a reduced CMU (the
    keypoints' 17 joints), a random tree (repeats, any order) or the panda URDF (sliders, mimics)."""
    if model in ("cmu", "reduced"):
        sk = cmu if model == "cmu" else cmu.freeze(REDUCE)
        return sk, _poses(sk, 3), [0, 6, 7, 8, 1, 2, 3, 12, 13, 15, 16, 17, 18, 19, 24, 25, 26]
    if model == "panda":
        sk = Skeleton.from_urdf(Path(__file__).parent / "data/urdf/example_robot_data/panda_description/panda.urdf")
        assert sk.has_slides_or_mimics
        return sk, 0.5 * torch.randn(3, sk.num_dofs, generator=gen, dtype=F64), list(range(sk.num_joints))[::-2]
    sk = _random_tree(int(model[-1]))
    return sk, torch.randn(3, sk.num_dofs, generator=gen, dtype=F64), [4, 0, 7, 4]


@pytest.mark.parametrize("model", ["cmu", "reduced", "tree1", "panda"])
def test_joint_jacobian_of_chosen_joints_equals_the_full_rows(cmu, model):
    """joint_jacobian(sk, q, joints): the full Jacobian's rows of those joints, to rounding (`SAME`; any
    order, repeats, a tensor or a sequence, none), on CMU, a reduced model, a random tree and a URDF with
    sliders and mimics; and so equal to autograd through FK (float64)."""
    gen = torch.Generator().manual_seed(5)
    sk, q, chosen = _chosen_joints_case(cmu, model, gen)
    joints, full = joint_jacobian(sk, q)
    for rows in (chosen, torch.tensor(chosen[:2]), [sk.num_joints - 1], list(range(sk.num_joints)), []):
        got_joints, jac = joint_jacobian(sk, q.reshape(1, 3, -1), rows)
        assert jac.shape == (1, 3, len(rows), 3, sk.num_dofs)
        torch.testing.assert_close(got_joints[0], joints, **SAME)
        torch.testing.assert_close(jac[0], full[:, torch.as_tensor(rows, dtype=torch.long)], **SAME)
    want = _autograd_joint_jacobian(sk, q)[:, chosen]
    torch.testing.assert_close(joint_jacobian(sk, q, chosen)[1], want, rtol=0, atol=1e-10)
    with pytest.raises(ValueError, match="outside the skeleton"):
        joint_jacobian(sk, q, [sk.num_joints])


@pytest.mark.parametrize("model", ["cmu", "reduced", "tree2", "panda"])
def test_joint_jacobian_product_equals_left_times_the_rows(cmu, model):
    """joint_jacobian_product(sk, q, joints, left) = left @ joint_jacobian(sk, q, joints)[1] per joint
    (float64; on CMU, whose dofs each drive one slot, the sum x0 y0 + x1 y1 + x2 y2 to rounding, `SAME`),
    left broadcast over q's batch dims and the FK given or not, on CMU, a reduced model, a random tree
    and a URDF with sliders and mimics."""
    gen = torch.Generator().manual_seed(7)
    sk, q, chosen = _chosen_joints_case(cmu, model, gen)
    _, rows = joint_jacobian(sk, q, chosen)  # (3, Y, 3, D)
    for r_len in (2, 1):
        left = torch.randn(3, len(chosen), r_len, 3, generator=gen, dtype=F64)
        got = joint_jacobian_product(sk, q, chosen, left)
        assert got.shape == (3, len(chosen), r_len, sk.num_dofs)
        torch.testing.assert_close(got, left @ rows, rtol=0, atol=1e-12)
        if model == "cmu":
            want = left[..., 0, None] * rows[..., None, 0, :]
            for c in (1, 2):
                want.addcmul_(left[..., c, None], rows[..., None, c, :])
            torch.testing.assert_close(got, want, **SAME)
        fk = sk.forward_kinematics(q, rotations=True)
        torch.testing.assert_close(joint_jacobian_product(sk, q, chosen, left, fk), got, **SAME)
        shared = joint_jacobian_product(sk, q, chosen, left[0])  # one left for every pose
        torch.testing.assert_close(shared, left[0] @ rows, rtol=0, atol=1e-12)


def _autograd_point_jacobian(sk: Skeleton, q: torch.Tensor, joint: torch.Tensor, local: torch.Tensor) -> torch.Tensor:
    """q (N, D), joint (N, P), local (N, P, 3) -> d (p_joint + G_joint local) / d q (N, P, 3, D) through FK."""

    def points(x: torch.Tensor) -> torch.Tensor:
        joints, rot = sk.forward_kinematics(x, rotations=True)
        rows = torch.arange(x.shape[0])[:, None]
        return joints[rows, joint] + (rot[rows, joint] @ local[..., None])[..., 0]

    jac = torch.autograd.functional.jacobian(lambda x: points(x).sum(0), q)  # (P, 3, N, D) summed over N
    return jac.permute(2, 0, 1, 3)


@pytest.mark.parametrize("model", ["cmu", "reduced", "tree0", "tree3", "panda"])
def test_point_jacobian_matches_autograd(cmu, model):
    """Points rigidly attached to joint frames: positions and geometric Jacobian equal FK and autograd through
    it (float64), on CMU (all dofs, reduced), random URDF-like trees and a URDF with sliders and mimics."""
    gen = torch.Generator().manual_seed(3)
    if model in ("cmu", "reduced"):
        sk = cmu if model == "cmu" else cmu.freeze(REDUCE)
        q = _poses(sk, 3)
    elif model == "panda":
        sk = Skeleton.from_urdf(Path(__file__).parent / "data/urdf/example_robot_data/panda_description/panda.urdf")
        assert sk.has_slides_or_mimics
        q = 0.5 * torch.randn(3, sk.num_dofs, generator=gen, dtype=F64)
    else:
        sk = _random_tree(int(model[-1]))
        q = torch.randn(3, sk.num_dofs, generator=gen, dtype=F64)
    joint = torch.randint(0, sk.num_joints, (3, 7), generator=gen)
    local = 0.2 * torch.randn(3, 7, 3, generator=gen, dtype=F64)
    points, jac = point_jacobian(sk, q, joint, local)
    assert points.shape == (3, 7, 3) and jac.shape == (3, 7, 3, sk.num_dofs)
    joints, rot = sk.forward_kinematics(q, rotations=True)
    rows = torch.arange(3)[:, None]
    torch.testing.assert_close(points, joints[rows, joint] + (rot[rows, joint] @ local[..., None])[..., 0])
    torch.testing.assert_close(jac, _autograd_point_jacobian(sk, q, joint, local), rtol=0, atol=1e-10)
    # at local 0 the points are the joints themselves: the joint Jacobian's rows
    _, at_joint = point_jacobian(sk, q, joint, torch.zeros_like(local))
    torch.testing.assert_close(at_joint, joint_jacobian(sk, q)[1][rows, joint], rtol=0, atol=1e-12)
    # joint and local broadcast against q's batch dims
    _, shared = point_jacobian(sk, q, joint[0], local[0])
    torch.testing.assert_close(shared[0], jac[0], **SAME)
    # both from one FK pass (given or not): exactly what the two functions return
    for fk in (None, (joints, rot)):
        both = joint_and_point_jacobian(sk, q, joint, local, fk)
        for got, want in zip(both, (*joint_jacobian(sk, q), points, jac)):
            torch.testing.assert_close(got, want, **SAME)


def test_root_translation_columns_are_unit_vectors(cmu):
    _, jac = joint_jacobian(cmu, _poses(cmu, 2))
    for axis, name in enumerate(("root.tx", "root.ty", "root.tz")):
        col = jac[..., cmu.dof_names.index(name)]  # (N, J, 3)
        torch.testing.assert_close(col, torch.eye(3, dtype=F64)[axis].expand_as(col), rtol=0, atol=0)


# -- residual Jacobians -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def pose_problem(cmu):
    """Reduced model with data limits, a camera on the clip, noisy keypoints of one frame, the
    reprojection (Cauchy) + limits objective, and 6 poses near the true one (some outside limits)."""
    sk = cmu.freeze(REDUCE).with_limits("data")
    lo, hi = sk.limits(dtype=F64)
    q_all = wrap_to_limits(load_amc(DATA / "10_02.amc", sk).q.to(F64), lo, hi, torch.as_tensor(sk.angular_dofs()))
    joints = sk.forward_kinematics(q_all)
    cam = camera_for_motion(joints, 6.0, 30.0, 10.0, 1000.0, 640, 480).to(dtype=F64)
    kps = make_keypoints(sk)
    g = torch.Generator().manual_seed(3)
    obs = cam.project(joints[200, kps.index()]).pixels + 2.0 * torch.randn(kps.num_keypoints, 2, generator=g, dtype=F64)
    conf = torch.rand(kps.num_keypoints, generator=g, dtype=F64) + 0.5
    obj = Objective(
        {
            "reprojection": Reprojection(obs, conf, sigma_px=2.0, loss="cauchy", scale=2.0),
            "limits": JointLimits(lo, hi, sigma=0.05),
        },
        weights={"limits": 3.0},
    )
    q = q_all[200] + 0.2 * torch.randn(6, sk.num_dofs, generator=g, dtype=F64)
    return sk, cam, kps, obj, q


def _pipeline_residuals(sk, cam, kps, obj):
    return lambda q: obj.residuals(evaluate_pose(sk, cam, kps, q))


def test_residual_jacobian_matches_autograd_through_the_pipeline(pose_problem):
    sk, cam, kps, obj, q = pose_problem

    def f(q, joints):
        proj = cam.project(joints.index_select(-2, kps.index()))
        return obj.residuals(PoseEval(q=q, joints=joints, pixels=proj.pixels, depth=proj.depth))

    r, jac = residual_jacobian(sk, f, q)
    full = _pipeline_residuals(sk, cam, kps, obj)
    torch.testing.assert_close(r, full(q), rtol=0, atol=1e-12)
    ref = torch.autograd.functional.jacobian(lambda x: full(x).sum(0), q).permute(1, 0, 2)  # (N, M, D)
    assert jac.shape == (6, r.shape[-1], sk.num_dofs)
    assert (q < torch.as_tensor(sk.lower)).any() or (q > torch.as_tensor(sk.upper)).any()  # limit rows live
    torch.testing.assert_close(jac, ref, rtol=0, atol=1e-6 * ref.abs().max())
    torch.testing.assert_close(jac, ref, rtol=0, atol=1e-9)


def test_objective_linearization_gives_the_objectives_weights_and_energy(pose_problem):
    sk, cam, kps, obj, q = pose_problem
    lin = objective_linearization(sk, obj, cam, kps)(q)
    ev = evaluate_pose(sk, cam, kps, q)
    torch.testing.assert_close(lin.residuals, obj.residuals(ev), rtol=0, atol=1e-12)
    torch.testing.assert_close(lin.weights, obj.robust_weights(ev), rtol=0, atol=1e-12)
    torch.testing.assert_close(lin.energy, obj(ev).total, rtol=0, atol=1e-12)
    # J^T W r is the gradient of the robust energy
    x = q.clone().requires_grad_(True)
    obj(evaluate_pose(sk, cam, kps, x)).total.sum().backward()
    grad = (lin.jacobian.mT @ (lin.weights * lin.residuals)[..., None])[..., 0]
    torch.testing.assert_close(grad, x.grad, rtol=0, atol=1e-8)


def test_objective_linearization_needs_camera_and_keypoints(pose_problem):
    sk, _cam, kps, obj, _ = pose_problem
    with pytest.raises(InputError, match="camera"):
        objective_linearization(sk, obj, None, kps)
