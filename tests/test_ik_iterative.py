"""Tests for ptrack.hypotheses.ik's iterative fallback: chains with no closed form (a URDF arm of 1-dof
revolutes, written below) and closed-form leaves that miss their targets.

The reference is ptrack's forward kinematics: FK of the solved pose must land the chain's joints on
the targets (FK positions of other random poses, or interpretation-tree leaves).
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from ptrack.body.skeleton import Skeleton
from ptrack.hypotheses.ik import chain_ik, ik_plan, product_ik
from ptrack.hypotheses.jumps import default_chains, interpretation_trees, make_chain, product
from ptrack.observe.camera import camera_for_motion

DATA = Path(__file__).resolve().parents[1] / "ptrack" / "data"

# A human-like arm: a 3-revolute shoulder (pitch, roll, yaw about one point), an elbow with a small
# offset off the upper arm's axis, a wrist roll and a fixed palm.
ARM_URDF = """<?xml version="1.0"?>
<robot name="arm7">
  <link name="torso"/><link name="shoulder"/><link name="s1"/><link name="s2"/><link name="upper"/>
  <link name="fore"/><link name="hand"/><link name="tip"/>
  <joint name="mount" type="fixed"><parent link="torso"/><child link="shoulder"/>
    <origin xyz="0.05 0.35 0.4" rpy="0.1 0 0.2"/></joint>
  <joint name="shoulder_pitch" type="revolute"><parent link="shoulder"/><child link="s1"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 1 0"/><limit lower="-2.5" upper="2.5" effort="1" velocity="1"/></joint>
  <joint name="shoulder_roll" type="revolute"><parent link="s1"/><child link="s2"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="1 0 0"/><limit lower="-1.6" upper="1.6" effort="1" velocity="1"/></joint>
  <joint name="shoulder_yaw" type="revolute"><parent link="s2"/><child link="upper"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="0 0 1"/><limit lower="-2.0" upper="2.0" effort="1" velocity="1"/></joint>
  <joint name="elbow" type="revolute"><parent link="upper"/><child link="fore"/>
    <origin xyz="0.02 0 -0.3" rpy="0 0 0"/><axis xyz="0 1 0"/><limit lower="0.0" upper="2.6" effort="1" velocity="1"/></joint>
  <joint name="wrist" type="revolute"><parent link="fore"/><child link="hand"/>
    <origin xyz="0 0 -0.27" rpy="0 0 0"/><axis xyz="1 0 0"/><limit lower="-1.0" upper="1.0" effort="1" velocity="1"/></joint>
  <joint name="palm" type="fixed"><parent link="hand"/><child link="tip"/>
    <origin xyz="0 0 -0.08" rpy="0 0 0"/></joint>
</robot>
"""  # noqa: E501 (the URDF keeps one joint element per two lines)
ARM_CHAIN = ("shoulder", "fore", "hand")  # shoulder -> elbow -> wrist


@pytest.fixture(scope="module")
def arm(tmp_path_factory) -> Skeleton:
    """The arm on a floating base (root translation and rotation dofs above the chain)."""
    pytest.importorskip("pytorch_kinematics")
    path = tmp_path_factory.mktemp("urdf") / "arm7.urdf"
    path.write_text(ARM_URDF)
    return Skeleton.from_urdf(path, floating_base=True)


@pytest.fixture(scope="module")
def cmu() -> Skeleton:
    return Skeleton.from_asf(DATA / "10.asf").with_limits("data")


def _random_poses(sk: Skeleton, n: int, seed: int, dtype=torch.float64) -> torch.Tensor:
    """(n, D) poses uniform inside the limits (unlimited angles in [-pi, pi)), the root within 5 cm
    of the origin."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = sk.limits(torch.float64)
    lo = torch.where(torch.isfinite(lo), lo, torch.full_like(lo, -math.pi))
    hi = torch.where(torch.isfinite(hi), hi, torch.full_like(hi, math.pi))
    q = lo + (hi - lo) * torch.rand(n, sk.num_dofs, generator=g, dtype=torch.float64)
    trans = [int(d) for d in sk.translation_dof if d >= 0]
    q[:, trans] *= 0.05 / math.pi
    return q.to(dtype)


def _own_trees(sk, q, chains, distance=3.0):
    """Trees of each chain with every hypothesis observed through its own exact 2D joints."""
    joints = sk.forward_kinematics(q)
    cam = camera_for_motion(joints, distance, 30.0, 10.0, 1000.0, 640, 480).to(dtype=q.dtype)
    pixels = cam.project(joints).pixels
    conf = torch.ones(joints.shape[:-1], dtype=q.dtype)
    return cam, pixels, interpretation_trees(chains, joints, cam, pixels, conf)


# -- plans ------------------------------------------------------------------------------------


def test_plans_on_a_urdf_arm(arm):
    def dofs(names):
        plan = ik_plan(arm, make_chain(arm, names))
        assert plan.kind == "iterative" and plan.balls == () and plan.hinge == -1
        return [arm.dof_names[d] for d in plan.dofs]

    # the wrist roll turns the hand link about the wrist: it moves no joint of the chain
    assert dofs(ARM_CHAIN) == ["shoulder_pitch", "shoulder_roll", "shoulder_yaw", "elbow"]
    # a root whose link turns about its own origin brings its dof (the root itself stays put)
    assert dofs(("s1", "fore", "hand")) == ["shoulder_pitch", "shoulder_roll", "shoulder_yaw", "elbow"]
    assert dofs(("upper", "hand", "tip")) == ["shoulder_yaw", "elbow", "wrist"]
    # never the dofs above the chain root (the floating base, the shoulder above s2)
    assert dofs(("s2", "fore")) == ["shoulder_roll", "shoulder_yaw"]


def test_closed_form_can_be_declined(cmu):
    chain = default_chains(cmu, ["larm"])[0]
    closed, iterative = ik_plan(cmu, chain), ik_plan(cmu, chain, closed_form=False)
    assert (closed.kind, iterative.kind) == ("limb", "iterative")
    assert iterative.dofs == closed.dofs  # the humerus's ball and the radius's hinge
    head = default_chains(cmu, ["head"])[0]
    # the iterative head also turns the upper neck inside the thorax -> upper neck link
    assert [cmu.dof_names[d] for d in ik_plan(cmu, head, closed_form=False).dofs] == [
        f"{j}.{a}" for j in ("lowerneck", "upperneck", "head") for a in ("rz", "ry", "rx")
    ]


@pytest.mark.parametrize("model", ["arm", "cmu"])
def test_chain_jacobian_matches_joint_jacobian(model, arm, cmu):
    """The fit's forward kinematics and Jacobian along the chain equal the skeleton's
    (`forward_kinematics`, `ptrack.optim.jacobians.joint_jacobian`) restricted to the chain's dofs."""
    from ptrack.hypotheses.ik.kinematics import root_parent, walk_fk
    from ptrack.hypotheses.ik.plan import plan_tensors
    from ptrack.optim.jacobians import joint_jacobian

    sk, names = (arm, ARM_CHAIN) if model == "arm" else (cmu, ("lclavicle", "lhumerus", "lradius"))
    chain = make_chain(sk, names)
    plan = ik_plan(sk, chain, closed_form=False)
    q = _random_poses(sk, 16, 6)
    tc = plan_tensors(plan, q.dtype, q.device)
    qs = q.index_select(1, tc["used"]).T.contiguous()
    g_par, pivot = root_parent(plan, tc, qs)
    pos, jac = walk_fk(plan, tc, g_par, pivot, qs, q[:, list(plan.dofs)].T, True)
    joints, want = joint_jacobian(sk, q)
    idx = list(chain.joints)
    torch.testing.assert_close(pos.permute(2, 0, 1), joints[:, idx], atol=1e-12, rtol=0)
    torch.testing.assert_close(jac.permute(3, 0, 1, 2), want[:, idx[1:]][..., list(plan.dofs)], atol=1e-12, rtol=0)


# -- IK reproduces FK -------------------------------------------------------------------------


@pytest.mark.parametrize("dtype, tol, share", [(torch.float64, 1e-6, 1.0), (torch.float32, 1e-4, 0.99)])
def test_iterative_reproduces_fk_of_random_poses(arm, dtype, tol, share):
    """In float32 a few fits (0.07% of 4096) stall near the shoulder's gimbal lock (roll at
    +-pi/2: pitch and yaw turn about one axis) at ~1.5e-4 m: they are flagged not `exact`."""
    chain = make_chain(arm, ARM_CHAIN)
    plan = ik_plan(arm, chain)
    n, leaves = 64, 5
    start = _random_poses(arm, n, 0, dtype)
    truth = _random_poses(arm, n * leaves, 1, dtype).reshape(n, leaves, -1)
    truth[..., :6] = start[:, None, :6]  # the same base: the chain root stays where start puts it
    targets = arm.forward_kinematics(truth)[..., list(chain.joints), :]  # (N, L, 3, 3)
    res = chain_ik(plan, start, targets)
    assert res.angles.shape == (n, leaves, 4) and res.angles.dtype == dtype
    fk = arm.forward_kinematics(res.q)[..., list(chain.joints), :]
    err = (fk - targets).norm(dim=-1).amax(-1)
    assert float(res.exact.float().mean()) >= share and float(err.max()) < 10 * tol
    assert float(err[res.exact].max()) < tol and float(res.residual[res.exact].max()) < tol
    assert torch.equal(res.exact, res.residual <= 1e-4)
    torch.testing.assert_close(res.positions, fk, atol=tol, rtol=0)
    # only the plan's dofs move; angles are in the limits' window
    others = [d for d in range(arm.num_dofs) if d not in plan.dofs]
    assert torch.equal(res.q[..., others], start[:, None, others].expand(n, leaves, -1))
    lo, hi = arm.limits(dtype)
    d = list(plan.dofs)
    centre = (lo[d] + hi[d]) / 2
    assert bool(((res.angles - centre).abs() <= math.pi + 1e-5).all())
    # the start's leaves are not all near their targets: the fit travels
    far = (arm.forward_kinematics(start)[:, None, list(chain.joints)] - targets).norm(dim=-1).amax(-1)
    assert float(far.median()) > 0.1


def test_iterative_and_closed_form_reach_the_same_positions(cmu):
    q = cmu.load_amc(DATA / "10_02.amc").q[::10][:40]
    chains = default_chains(cmu, ["larm", "rarm", "lleg", "rleg"])
    _, _, trees = _own_trees(cmu, q, chains, distance=5.0)
    for chain, tree in zip(chains, trees):
        closed = chain_ik(ik_plan(cmu, chain), q, tree.positions)
        iterative = chain_ik(ik_plan(cmu, chain, closed_form=False), q, tree.positions)
        assert bool(closed.exact.all()) and bool(iterative.exact.all()), chain.name
        torch.testing.assert_close(iterative.positions, closed.positions, atol=1e-6, rtol=0)
        fk = cmu.forward_kinematics(iterative.q)[..., list(chain.joints), :]
        assert float((fk - tree.positions).norm(dim=-1).max()) < 1e-6


# -- interpretation trees on a URDF chain -----------------------------------------------------


def test_kept_leaves_of_urdf_trees_reproject(arm):
    chain = make_chain(arm, ARM_CHAIN)
    plan = ik_plan(arm, chain)
    q = _random_poses(arm, 200, 2)
    cam, pixels, (tree,) = _own_trees(arm, q, [chain])
    res = chain_ik(plan, q, tree.positions)
    kept = res.keep & tree.unique & ~tree.infeasible.any(-1)  # as the kjs tracker keeps leaves
    assert float(kept[:, 1:].float().mean()) > 0.3  # flipped interpretations survive
    fk = arm.forward_kinematics(res.q)
    px = cam.project(fk).pixels[..., list(chain.joints), :]  # (N, L, 3, 2)
    err = (px - pixels[:, None, list(chain.joints)]).norm(dim=-1).amax(-1)
    assert float(err[kept].max()) < 1e-3
    # leaf 0 is the hypothesis itself, and flipped leaves do move the chain
    torch.testing.assert_close(res.positions[:, 0], arm.forward_kinematics(q)[:, list(chain.joints)], atol=1e-6, rtol=0)
    moved = (res.positions[:, 1:] - res.positions[:, :1]).norm(dim=-1).amax(-1)
    assert float(moved[kept[:, 1:]].min()) > 1e-3
    # the leaves solved here combine with other chains' as a product, like closed-form ones
    prod = product([tree])
    combined = product_ik(q, [res], prod)
    assert torch.equal(combined.keep, res.keep)


def test_prune_and_project(arm):
    chain = make_chain(arm, ARM_CHAIN)
    plan = ik_plan(arm, chain)
    q = _random_poses(arm, 120, 3)
    _, _, (tree,) = _own_trees(arm, q, [chain])
    pruned = chain_ik(plan, q, tree.positions, mode="prune")
    projected = chain_ik(plan, q, tree.positions, mode="project")
    lo, hi = (t[list(plan.dofs)] for t in arm.limits(torch.float64))
    inside = ((pruned.angles >= lo) & (pruned.angles <= hi)).all(-1)
    assert torch.equal(pruned.in_limits, inside)
    assert torch.equal(pruned.keep, pruned.exact & pruned.in_limits)
    assert not pruned.projected.any()
    assert int((~inside).sum()) > 20  # flipped arms do break the limits
    # project: the same flags before projection; the leaves outside solved again within the limits
    assert torch.equal(projected.in_limits, pruned.in_limits)
    assert torch.equal(projected.projected, ~pruned.in_limits)
    assert torch.equal(projected.keep, projected.exact)
    assert bool(((projected.angles >= lo - 1e-12) & (projected.angles <= hi + 1e-12)).all())
    torch.testing.assert_close(projected.angles[inside], pruned.angles[inside])
    fk = arm.forward_kinematics(projected.q)[..., list(chain.joints), :]
    torch.testing.assert_close(projected.positions, fk, atol=1e-9, rtol=0)
    # the bounded fit is never worse than clamping the unbounded answer (it starts there)
    clamped = pruned.q.clone()
    clamped[..., list(plan.dofs)] = torch.clamp(pruned.angles, lo, hi)
    fk_clamped = arm.forward_kinematics(clamped)[..., list(chain.joints), :]

    def energy(x):
        return (x - tree.positions)[..., 1:, :].square().sum((-1, -2))

    out = ~inside
    assert bool((energy(fk)[out] <= energy(fk_clamped)[out] + 1e-12).all())
    assert float((energy(fk_clamped)[out] - energy(fk)[out]).max()) > 1e-4  # and usually better


def test_unreachable_and_non_finite_targets(arm):
    chain = make_chain(arm, ARM_CHAIN)
    plan = ik_plan(arm, chain)
    q = _random_poses(arm, 6, 4)
    joints = arm.forward_kinematics(q)[:, list(chain.joints)]
    targets = joints[:, None].repeat(1, 3, 1, 1)
    root = targets[:, 1, 0]
    targets[:, 1, 2] = root + 2.0 * (targets[:, 1, 2] - root) / (targets[:, 1, 2] - root).norm(dim=-1, keepdim=True)
    targets[:, 2, 1] = float("nan")
    res = chain_ik(plan, q, targets)
    assert bool(res.exact[:, 0].all()) and bool(res.keep[:, 0].all())
    # 2 m away: out of the arm's 0.57 m reach; the best fit stretches the arm towards it
    assert not res.exact[:, 1].any() and not res.keep[:, 1].any()
    assert bool((res.residual[:, 1] > 1.0).all())
    reach = (res.positions[:, 1, 2] - root).norm(dim=-1)
    assert bool((reach > 0.55).all())
    assert not res.exact[:, 2].any() and not res.keep[:, 2].any() and bool(res.angles[:, 2].isfinite().all())


def test_batched_shapes(arm):
    chain = make_chain(arm, ARM_CHAIN)
    plan = ik_plan(arm, chain)
    q = _random_poses(arm, 6, 5)
    _, _, (tree,) = _own_trees(arm, q, [chain])
    flat = chain_ik(plan, q, tree.positions)
    res = chain_ik(plan, q.reshape(2, 3, -1), tree.positions.reshape(2, 3, 4, 3, 3))
    assert res.angles.shape == (2, 3, 4, 4) and res.positions.shape == (2, 3, 4, 3, 3)
    for f in (res.residual, res.exact, res.in_limits, res.keep, res.projected):
        assert f.shape == (2, 3, 4)
    torch.testing.assert_close(res.angles.reshape(6, 4, 4), flat.angles)
    # no hypotheses at all (a tracker's empty selection): empty results of the right shapes
    for sk_plan in (plan, ik_plan(arm, make_chain(arm, ARM_CHAIN))):
        for mode in ("prune", "project"):
            empty = chain_ik(sk_plan, q[:0], tree.positions[:0], mode=mode)
            assert empty.angles.shape == (0, 4, 4) and empty.q.shape == (0, 4, arm.num_dofs)


# -- refining closed-form leaves that miss ----------------------------------------------------


def test_refinement_fixes_missed_closed_form_leaves(cmu):
    """collinear_tol=2 makes the limb closed form treat every limb as straight (twist kept, the
    lower bone left where that twist puts it): bent limbs miss; refinement brings them back."""
    q = cmu.load_amc(DATA / "10_02.amc").q[::10][:40]
    chains = default_chains(cmu, ["larm", "lleg"])
    _, _, trees = _own_trees(cmu, q, chains, distance=5.0)
    for chain, tree in zip(chains, trees):
        plan = ik_plan(cmu, chain)
        missed = chain_ik(plan, q, tree.positions, collinear_tol=2.0, refine=False)
        assert float(missed.exact.float().mean()) < 0.5
        fixed = chain_ik(plan, q, tree.positions, collinear_tol=2.0)
        assert bool(fixed.exact.all())
        refined = ~missed.exact
        assert float(fixed.residual[refined].max()) < 1e-6
        fk = cmu.forward_kinematics(fixed.q)[..., list(chain.joints), :]
        assert float((fk - tree.positions).norm(dim=-1)[refined].max()) < 1e-6
        # the leaves the closed form got within tol (some just) are untouched
        assert torch.equal(fixed.angles[missed.exact], missed.angles[missed.exact])
        assert torch.equal(fixed.residual[missed.exact], missed.residual[missed.exact])
        # the refined leaves land where the exact closed form puts the chain
        exact = chain_ik(plan, q, tree.positions)
        torch.testing.assert_close(fixed.positions[refined], exact.positions[refined], atol=1e-6, rtol=0)
        lo, hi = (t[list(plan.dofs)] for t in cmu.limits(torch.float64))
        assert torch.equal(fixed.in_limits, ((fixed.angles >= lo) & (fixed.angles <= hi)).all(-1))


def test_refinement_never_worsens_a_leaf(cmu):
    """Targets that break the bone lengths (the forearm 10% longer): neither answer is exact; the
    refined leaf is the closer of the closed form's and the fit's."""
    q = cmu.load_amc(DATA / "10_02.amc").q[::10][:20]
    chain = default_chains(cmu, ["larm"])[0]
    plan = ik_plan(cmu, chain)
    targets = cmu.forward_kinematics(q)[:, None, list(chain.joints)].clone()
    targets[:, 0, 2] = targets[:, 0, 1] + 1.1 * (targets[:, 0, 2] - targets[:, 0, 1])
    closed = chain_ik(plan, q, targets, refine=False)
    refined = chain_ik(plan, q, targets)
    assert not closed.exact.any() and not refined.exact.any()
    assert bool((refined.residual <= closed.residual).all())
    assert bool((refined.residual < closed.residual - 1e-4).any())  # the least-squares fit is closer
    fk = cmu.forward_kinematics(refined.q)[..., list(chain.joints), :]
    torch.testing.assert_close(refined.positions, fk, atol=1e-9, rtol=0)


def test_unlimited_dofs_stay_in_their_window(tmp_path):
    """A continuous shoulder yaw: its angle comes back in [-pi, pi), also after the bounded fit of
    "project" mode (which bounds only the limited dofs)."""
    pytest.importorskip("pytorch_kinematics")
    text = ARM_URDF.replace(
        '<joint name="shoulder_yaw" type="revolute">', '<joint name="shoulder_yaw" type="continuous">'
    )
    text = text.replace('<limit lower="-2.0" upper="2.0" effort="1" velocity="1"/>', "")  # the yaw's
    path = tmp_path / "continuous.urdf"
    path.write_text(text)
    sk = Skeleton.from_urdf(path, floating_base=True)
    assert math.isinf(sk.lower[sk.dof_names.index("shoulder_yaw")])
    chain = make_chain(sk, ARM_CHAIN)
    plan = ik_plan(sk, chain)
    yaw = list(plan.dofs).index(sk.dof_names.index("shoulder_yaw"))
    q = _random_poses(sk, 60, 7)
    _, _, (tree,) = _own_trees(sk, q, [chain])
    for mode in ("prune", "project"):
        res = chain_ik(plan, q, tree.positions, mode=mode)
        assert bool((res.angles[..., yaw].abs() <= math.pi).all())
        fk = sk.forward_kinematics(res.q)[..., list(chain.joints), :]
        torch.testing.assert_close(res.positions, fk, atol=1e-9, rtol=0)
    assert bool(res.projected.any())
