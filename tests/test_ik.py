"""Tests for ptrack.hypotheses.ik: closed-form inverse kinematics of interpretation-tree leaves.

The reference is ptrack's forward kinematics (itself checked against an independent Acclaim
implementation): FK of the solved pose must land the chain's joints on the targets, on real CMU
poses (the bundled 10_02 and clips of other subjects in ../shared/data/cmu) and on every leaf of
their interpretation trees.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from ptrack.body.kinematics import euler_zyx
from ptrack.body.skeleton import Skeleton
from ptrack.errors import InputError
from ptrack.hypotheses.ik import ClosedFormUnavailable, chain_ik, euler_zyx_solutions, ik_plan, product_ik
from ptrack.hypotheses.jumps import default_chains, interpretation_trees, make_chain, product, product_joints
from ptrack.observe.camera import camera_for_motion

DATA = Path(__file__).resolve().parents[1] / "ptrack" / "data"
CLIPS = [("02", "02_01"), ("05", "05_02"), ("64", "64_01"), ("131", "131_03")]


@pytest.fixture(scope="module")
def sk() -> Skeleton:
    return Skeleton.from_asf(DATA / "10.asf").with_limits("data")


@pytest.fixture(scope="module")
def poses(sk) -> torch.Tensor:
    """60 real poses of 10_02, float64."""
    return sk.load_amc(DATA / "10_02.amc").q[::10][:60]


def _trees(sk, q, chains):
    joints = sk.forward_kinematics(q)
    cam = camera_for_motion(joints, 5.0, 30.0, 10.0, 1000.0, 640, 480).to(dtype=q.dtype)
    pixels = cam.project(joints).pixels
    return joints, interpretation_trees(chains, joints, cam, pixels, torch.ones(joints.shape[:-1], dtype=q.dtype))


def _perturbed(q: torch.Tensor, dofs, scale: float, seed: int) -> torch.Tensor:
    """q with the given dofs moved by uniform noise in [-scale, scale]."""
    g = torch.Generator().manual_seed(seed)
    out = q.clone()
    out[:, list(dofs)] += scale * (2 * torch.rand(q.shape[0], len(dofs), generator=g, dtype=q.dtype) - 1)
    return out


def _wrapped(a: torch.Tensor) -> torch.Tensor:
    return torch.remainder(a + math.pi, 2 * math.pi) - math.pi


# -- plans ------------------------------------------------------------------------------------


def test_plans_of_cmu_chains(sk):
    kinds = {c.name: ik_plan(sk, c) for c in default_chains(sk)}
    assert {k: p.kind for k, p in kinds.items()} == {
        "larm": "limb",
        "rarm": "limb",
        "lleg": "limb",
        "rleg": "limb",
        "head": "swing",
    }
    names = [sk.dof_names[d] for d in kinds["larm"].dofs]
    assert names == ["lhumerus.rz", "lhumerus.ry", "lhumerus.rx", "lradius.rx"]
    assert [sk.dof_names[d] for d in kinds["lleg"].dofs] == ["lfemur.rz", "lfemur.ry", "lfemur.rx", "ltibia.rx"]
    head = kinds["head"]
    assert [sk.joint_names[j] for j in head.balls] == ["lowerneck", "head"]
    assert [sk.joint_names[j] for j in head.path] == ["lowerneck", "upperneck", "head"]


def test_no_closed_form_falls_back_to_iterative(sk):
    # a chain past the wrist: the radius has one dof, the wrist one
    forearm = ik_plan(sk, make_chain(sk, ("lhumerus", "lradius", "lwrist"), name="forearm"))
    assert forearm.kind == "iterative"
    assert [sk.dof_names[d] for d in forearm.dofs] == ["lradius.rx", "lwrist.ry"]
    # a reduced model without the humerus twist
    reduced = sk.freeze(["lhumerus.ry"])
    plan = ik_plan(reduced, default_chains(reduced, ["larm"])[0])
    assert plan.kind == "iterative"
    assert [reduced.dof_names[d] for d in plan.dofs] == ["lhumerus.rz", "lhumerus.rx", "lradius.rx"]
    # nothing moves the chain: still an error, naming the chain
    frozen = sk.freeze(["lhumerus.*", "lradius.*"])
    with pytest.raises(ClosedFormUnavailable, match=r"'larm'.*no dof moves its joints"):
        ik_plan(frozen, default_chains(frozen, ["larm"])[0])
    assert issubclass(ClosedFormUnavailable, InputError)
    # freezing other dofs (fingers, clavicles) keeps the closed form, with the dofs renumbered
    light = sk.freeze(["*fingers", "*thumb", "*clavicle"])
    plan = ik_plan(light, default_chains(light, ["larm"])[0])
    assert plan.kind == "limb"
    assert [light.dof_names[d] for d in plan.dofs] == ["lhumerus.rz", "lhumerus.ry", "lhumerus.rx", "lradius.rx"]


def test_urdf_models_take_the_iterative_path(sk, tmp_path):
    pytest.importorskip("pytorch_kinematics")
    path = tmp_path / "cmu.urdf"
    path.write_text(sk.to_urdf())
    urdf = Skeleton.from_urdf(path, floating_base=False, collapse=False)  # a link per axis
    chain = default_chains(urdf, ["larm"])[0]  # the same joint names: trees work on any model
    plan = ik_plan(urdf, chain)
    assert plan.kind == "iterative"
    assert [urdf.dof_names[d] for d in plan.dofs] == ["lhumerus.rz", "lhumerus.ry", "lhumerus.rx", "lradius.rx"]


# -- IK reproduces FK -------------------------------------------------------------------------


def _check_reproduces_fk(sk, q, seed=0, tol=1e-6):
    joints = sk.forward_kinematics(q)
    for chain in default_chains(sk):
        plan = ik_plan(sk, chain)
        start = _perturbed(q, plan.dofs, 0.3, seed)  # IK must not just copy the current angles
        res = chain_ik(plan, start, joints[:, None, list(chain.joints)])
        solved = res.q[:, 0]
        fk = sk.forward_kinematics(solved)
        err = (fk[:, list(chain.joints)] - joints[:, list(chain.joints)]).norm(dim=-1)
        assert float(err.max()) < tol, chain.name
        assert bool(res.exact.all()) and float(res.residual.max()) < tol
        torch.testing.assert_close(res.positions[:, 0], fk[:, list(chain.joints)], atol=1e-9, rtol=0)
        if plan.kind == "limb":
            # twist recovered: the truth's angles (inside the limits, and nearest to the start), and
            # so every joint past the chain (hand, foot) lands where it was -- unless the limb is
            # straight (mocap has exactly straight knees), where the twist is the start's
            bent = torch.sin(q[:, plan.dofs[3]]).abs() > 1e-3
            assert float(bent.float().mean()) > 0.5
            torch.testing.assert_close(
                _wrapped(solved[bent][:, list(plan.dofs)] - q[bent][:, list(plan.dofs)]),
                torch.zeros(int(bent.sum()), 4, dtype=q.dtype),
                atol=1e-6,
                rtol=0,
            )
            assert float((fk - joints)[bent].norm(dim=-1).max()) < tol
        # dofs outside the chain are untouched
        others = [d for d in range(sk.num_dofs) if d not in plan.dofs]
        assert torch.equal(solved[:, others], start[:, others])


def test_ik_reproduces_fk_bundled_clip(sk, poses):
    _check_reproduces_fk(sk, poses)


@pytest.mark.parametrize("subject, clip", CLIPS)
def test_ik_reproduces_fk_cmu_clips(cmu_file, subject, clip):
    sk = Skeleton.from_asf(cmu_file(f"{subject}.asf")).with_limits("data")
    q = sk.load_amc(cmu_file(f"{clip}.amc")).q
    _check_reproduces_fk(sk, q[:: max(1, q.shape[0] // 50)], seed=int(subject))


@pytest.mark.parametrize("subject, clip", [("10", "10_02")] + CLIPS)
def test_ik_of_every_leaf(cmu_file, subject, clip):
    """FK(IK(leaf)) == leaf on every leaf of every default chain (flipped poses included)."""
    if subject == "10":
        sk = Skeleton.from_asf(DATA / "10.asf").with_limits("data")
        q = sk.load_amc(DATA / "10_02.amc").q
    else:
        sk = Skeleton.from_asf(cmu_file(f"{subject}.asf")).with_limits("data")
        q = sk.load_amc(cmu_file(f"{clip}.amc")).q
    q = q[:: max(1, q.shape[0] // 40)]
    chains = default_chains(sk)
    _, trees = _trees(sk, q, chains)
    for chain, tree in zip(chains, trees):
        res = chain_ik(ik_plan(sk, chain), q, tree.positions)
        fk = sk.forward_kinematics(res.q)[..., list(chain.joints), :]
        err = (fk - tree.positions).norm(dim=-1).amax(-1)  # (N, L)
        assert float(err.max()) < 1e-6, chain.name
        assert bool(res.exact.all())


def test_straight_limb_keeps_the_current_twist(sk, poses):
    chain = default_chains(sk, ["lleg"])[0]
    plan = ik_plan(sk, chain)
    knee = sk.dof_names.index("ltibia.rx")
    femur = list(plan.dofs[:3])
    q = poses[:20].clone()
    q[:, knee] = 0.0  # a straight leg: the femur's twist is not seen by the hip, knee, ankle
    joints = sk.forward_kinematics(q)
    targets = joints[:, None, list(chain.joints)]
    # from the pose itself: the same angles come back (the general formula would invent a twist)
    res = chain_ik(plan, q, targets)
    torch.testing.assert_close(
        _wrapped(res.angles[:, 0] - q[:, list(plan.dofs)]), torch.zeros(20, 4, dtype=q.dtype), atol=1e-9, rtol=0
    )
    # from a start with other femur angles: the smallest turn of the start's femur onto the target
    start = _perturbed(q, femur, 0.4, 1)
    res = chain_ik(plan, start, targets)
    fk_start, rot_start = sk.forward_kinematics(start, rotations=True)
    fk_new, rot_new = sk.forward_kinematics(res.q[:, 0], rotations=True)
    torch.testing.assert_close(fk_new[:, list(chain.joints)], joints[:, list(chain.joints)], atol=1e-9, rtol=0)
    m = chain.joints[1]
    turn = rot_new[:, m] @ rot_start[:, m].transpose(-1, -2)  # world rotation applied to the femur
    d_start = fk_start[:, m] - fk_start[:, chain.joints[0]]
    d_new = fk_new[:, m] - fk_new[:, chain.joints[0]]
    axis = torch.stack(
        [turn[:, 2, 1] - turn[:, 1, 2], turn[:, 0, 2] - turn[:, 2, 0], turn[:, 1, 0] - turn[:, 0, 1]], -1
    )
    # a smallest rotation turns about d_start x d_new: its axis is normal to both directions
    torch.testing.assert_close((axis * d_start).sum(-1), torch.zeros(20, dtype=q.dtype), atol=1e-9, rtol=0)
    torch.testing.assert_close((axis * d_new).sum(-1), torch.zeros(20, dtype=q.dtype), atol=1e-9, rtol=0)
    assert float(res.angles[:, 0, 3].abs().max()) < 1e-6


def test_head_swing_keeps_twists_and_inner_joints(sk, poses):
    chain = default_chains(sk, ["head"])[0]
    plan = ik_plan(sk, chain)
    joints = sk.forward_kinematics(poses)
    res = chain_ik(plan, poses, joints[:, None, list(chain.joints)])
    # targets are the pose's own joints: nothing turns
    torch.testing.assert_close(
        _wrapped(res.angles[:, 0] - poses[:, list(plan.dofs)]),
        torch.zeros(poses.shape[0], 6, dtype=poses.dtype),
        atol=1e-9,
        rtol=0,
    )
    upper = sk.dof_names.index("upperneck.rx")
    assert upper not in plan.dofs  # the joint inside the thorax -> upper neck link keeps its angles


# -- joint limits -----------------------------------------------------------------------------


def test_limits_prune_and_project(sk, poses):
    chains = default_chains(sk, ["lleg", "rleg", "larm"])
    _, trees = _trees(sk, poses, chains)
    lower, upper = sk.limits(torch.float64)
    seen_out = 0
    for chain, tree in zip(chains, trees):
        plan = ik_plan(sk, chain)
        pruned = chain_ik(plan, poses, tree.positions, mode="prune")
        projected = chain_ik(plan, poses, tree.positions, mode="project")
        d = list(plan.dofs)
        lo, hi = lower[d], upper[d]
        # angles in the limits' 2 pi window
        centre = torch.where(torch.isfinite(lo) & torch.isfinite(hi), (lo + hi) / 2, torch.zeros_like(lo))
        assert bool(((pruned.angles - centre).abs() <= math.pi + 1e-12).all())
        inside = ((pruned.angles >= lo) & (pruned.angles <= hi)).all(-1)
        assert torch.equal(pruned.in_limits, inside)
        assert torch.equal(pruned.keep, pruned.exact & pruned.in_limits)
        assert not pruned.projected.any()
        seen_out += int((~inside).sum())
        # project: clamped into the limits, FK re-run; leaves inside are as in prune mode
        assert torch.equal(projected.in_limits, pruned.in_limits)
        assert torch.equal(projected.projected, ~pruned.in_limits)
        assert torch.equal(projected.keep, projected.exact)
        assert bool(((projected.angles >= lo - 1e-12) & (projected.angles <= hi + 1e-12)).all())
        torch.testing.assert_close(projected.angles[inside], pruned.angles[inside])
        torch.testing.assert_close(projected.angles[~inside], torch.clamp(pruned.angles[~inside], lo, hi))
        fk = sk.forward_kinematics(projected.q)[..., list(chain.joints), :]
        torch.testing.assert_close(projected.positions, fk, atol=1e-9, rtol=0)
        moved = (projected.positions - tree.positions).norm(dim=-1).amax(-1)
        assert bool((moved[~inside] > 1e-6).all()) and float(moved[inside].max()) < 1e-6
    assert seen_out > 10  # flipped legs and arms do break the data limits
    with pytest.raises(InputError, match="mode must be one of prune, project"):
        chain_ik(ik_plan(sk, chains[0]), poses, trees[0].positions, mode="clamp")


def test_one_sided_limit(sk, poses):
    """A dof bounded on one side only is still checked and clamped on that side."""
    chain = default_chains(sk, ["lleg"])[0]
    knee = sk.dof_names.index("ltibia.rx")
    lower, upper = sk.lower.copy(), sk.upper.copy()
    lower[knee], upper[knee] = -math.inf, 1.0
    one_sided = replace(sk, lower=lower, upper=upper)
    _, (tree,) = _trees(one_sided, poses, [chain])
    plan = ik_plan(one_sided, chain)
    pruned = chain_ik(plan, poses, tree.positions)
    bent = pruned.angles[..., 3] > 1.0
    assert bool(bent.any()) and bool((~pruned.in_limits[bent]).all())
    projected = chain_ik(plan, poses, tree.positions, mode="project")
    assert float(projected.angles[..., 3].max()) <= 1.0


def test_limits_choose_among_equivalent_solutions(sk, poses):
    """The elbow angle t and its mirror (with the humerus twisted by pi) give the same positions; the
    one inside the limits is returned even when the start is nearer the other."""
    chain = default_chains(sk, ["larm"])[0]
    plan = ik_plan(sk, chain)
    joints = sk.forward_kinematics(poses)
    bent = poses[:, plan.dofs[3]].abs() > 0.5
    start = poses.clone()
    start[:, plan.dofs[3]] = -poses[:, plan.dofs[3]]  # the mirror elbow angle, outside (-10, 170) deg
    res = chain_ik(plan, start, joints[:, None, list(chain.joints)])
    torch.testing.assert_close(res.angles[bent, 0, 3], poses[bent, plan.dofs[3]])
    assert bool(res.in_limits[bent].all())


# -- shapes, dtypes, devices, inputs ----------------------------------------------------------


def test_batched_shapes(sk, poses):
    chain = default_chains(sk, ["rarm"])[0]
    plan = ik_plan(sk, chain)
    _, (tree,) = _trees(sk, poses[:6], [chain])
    q = poses[:6].reshape(2, 3, -1)
    res = chain_ik(plan, q, tree.positions.reshape(2, 3, 4, 3, 3))
    assert res.angles.shape == (2, 3, 4, 4) and res.positions.shape == (2, 3, 4, 3, 3)
    for f in (res.residual, res.exact, res.in_limits, res.keep, res.projected):
        assert f.shape == (2, 3, 4)
    assert res.q.shape == (2, 3, 4, sk.num_dofs)
    flat = chain_ik(plan, poses[:6], tree.positions)
    torch.testing.assert_close(res.angles.reshape(6, 4, 4), flat.angles)
    with pytest.raises(InputError, match="positions must be"):
        chain_ik(plan, q, tree.positions)
    with pytest.raises(InputError, match="q must be"):
        chain_ik(plan, poses[:6, :10], tree.positions)


def test_float32(sk, poses):
    chains = default_chains(sk)
    _, trees = _trees(sk, poses.float(), chains)
    for chain, tree in zip(chains, trees):
        res = chain_ik(ik_plan(sk, chain), poses.float(), tree.positions)
        assert res.angles.dtype == res.positions.dtype == torch.float32
        fk = sk.forward_kinematics(res.q)[..., list(chain.joints), :]
        assert float((fk - tree.positions).norm(dim=-1).max()) < 2e-5
        assert bool(res.exact.all())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_device_follows_inputs(sk, poses):
    chain = default_chains(sk, ["larm"])[0]
    plan = ik_plan(sk, chain)
    _, (tree,) = _trees(sk, poses, [chain])
    res = chain_ik(plan, poses.cuda(), tree.positions.cuda())
    assert res.angles.device.type == res.keep.device.type == "cuda"
    torch.testing.assert_close(res.angles.cpu(), chain_ik(plan, poses, tree.positions).angles)


def test_product_ik(sk, poses):
    chains = default_chains(sk, ["larm", "rleg", "head"])
    joints, trees = _trees(sk, poses, chains)
    prod = product(trees)
    results = [chain_ik(ik_plan(sk, c), poses, t.positions) for c, t in zip(chains, trees)]
    res = product_ik(poses, results, prod)
    assert res.angles.shape == (poses.shape[0], 64, 4 + 4 + 6)
    assert res.dofs == results[0].dofs + results[1].dofs + results[2].dofs
    fk = sk.forward_kinematics(res.q)
    want = product_joints(joints, trees, prod)
    idx = [j for c in chains for j in c.joints]
    torch.testing.assert_close(fk[..., idx, :], want[..., idx, :], atol=1e-9, rtol=0)
    torch.testing.assert_close(res.positions, want[..., idx, :], atol=1e-9, rtol=0)
    keep = (
        results[0].keep[:, prod.leaf[:, 0]] & results[1].keep[:, prod.leaf[:, 1]] & results[2].keep[:, prod.leaf[:, 2]]
    )
    assert torch.equal(res.keep, keep)
    with pytest.raises(InputError, match="2 results for 3 chains"):
        product_ik(poses, results[:2], prod)


def test_generic_axes_path_matches_frames(sk, poses):
    """Joints whose axes are not a frame go through Rodrigues products: same rotations as C Z C^T."""
    from ptrack.hypotheses.ik.kinematics import local_rotation, slot_angles  # the two paths of one joint's rotation
    from ptrack.hypotheses.ik.plan import plan_tensors

    plan = ik_plan(sk, default_chains(sk, ["larm"])[0])
    tc = plan_tensors(plan, torch.float64, torch.device("cpu"))
    qs = poses.index_select(1, tc["used"]).T.contiguous()
    for j in plan.ancestors + plan.path:
        pj = tc["per"][j]
        theta = slot_angles(pj, qs)
        torch.testing.assert_close(local_rotation(dict(pj, c=None), theta), local_rotation(pj, theta))


def test_euler_zyx_solutions():
    g = torch.Generator().manual_seed(3)
    theta = (torch.rand(300, 3, generator=g, dtype=torch.float64) * 2 - 1) * math.pi
    theta[:50, 1] = math.pi / 2  # at the gimbal lock
    theta[50:100, 1] = -math.pi / 2 + 1e-9  # next to it
    r = euler_zyx(theta)
    sols = euler_zyx_solutions(r, theta[:, 2])
    assert sols.shape == (300, 2, 3)
    for k in range(2):
        torch.testing.assert_close(euler_zyx(sols[:, k]), r, atol=1e-9, rtol=0)
    assert bool((sols[:, 0, 1].abs() <= math.pi / 2 + 1e-12).all())
    # at the lock, x is the one given
    torch.testing.assert_close(sols[:50, 0, 2], theta[:50, 2])
