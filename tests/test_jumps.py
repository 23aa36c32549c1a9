"""Tests for ptrack.hypotheses.jumps: interpretation trees of kinematic sub-chains.

Real CMU poses (the bundled 10_02 clip) seen by a virtual camera; observations are the exact
projections of the pose, so every leaf must reproject onto them and keep the bone lengths, and
a pose flipped analytically in depth must lead back to the truth.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch

from ptrack.body.keypoints import make_keypoints
from ptrack.body.skeleton import Skeleton
from ptrack.errors import InputError
from ptrack.hypotheses.jumps import (
    CMU_CHAINS,
    check_independent,
    default_chains,
    flip_names,
    interpretation_tree,
    interpretation_trees,
    joint_observations,
    make_chain,
    min_rotation,
    product,
    product_joints,
)
from ptrack.observe.camera import camera_for_motion

DATA = Path(__file__).resolve().parents[1] / "ptrack" / "data"


@pytest.fixture(scope="module")
def sk() -> Skeleton:
    return Skeleton.from_asf(DATA / "10.asf")


@pytest.fixture(scope="module")
def scene(sk):
    """40 real poses of 10_02 (float64), their joints, a camera and the exact projections."""
    q = sk.load_amc(DATA / "10_02.amc").q[::12][:40]
    joints = sk.forward_kinematics(q)
    cam = camera_for_motion(joints, 5.0, 30.0, 10.0, 1000.0, 640, 480).to(dtype=torch.float64)
    pixels = cam.project(joints).pixels
    conf = torch.ones(joints.shape[:-1], dtype=torch.float64)
    return q, joints, cam, pixels, conf


def _lengths(p: torch.Tensor) -> torch.Tensor:
    """Link lengths of chain positions (..., n+1, 3) -> (..., n)."""
    return torch.linalg.vector_norm(p[..., 1:, :] - p[..., :-1, :], dim=-1)


# -- chains -----------------------------------------------------------------------------------


def test_default_chains_cmu(sk):
    chains = default_chains(sk)
    assert [c.name for c in chains] == list(CMU_CHAINS)
    larm = chains[0]
    assert larm.joint_names == ("lclavicle", "lhumerus", "lradius")
    assert larm.joints == tuple(sk.joint_index(n) for n in larm.joint_names)
    assert (larm.num_links, larm.num_leaves) == (2, 4)
    assert [c.name for c in default_chains(sk, ["head", "lleg"])] == ["head", "lleg"]
    check_independent(sk, chains)  # the five defaults combine as a product


def test_chain_validation_names_the_chain(sk):
    with pytest.raises(InputError, match=r"'bad'.*'rradius' is not below 'lradius'"):
        make_chain(sk, ("lhumerus", "lradius", "rradius"), name="bad")
    with pytest.raises(InputError, match=r"'up'.*'lclavicle' is not below 'lhumerus'"):
        make_chain(sk, ("lhumerus", "lclavicle"), name="up")
    with pytest.raises(InputError, match=r"'one'.*at least two joints"):
        make_chain(sk, ("lhumerus",), name="one")
    with pytest.raises(InputError, match=r"'rep'.*repeats"):
        make_chain(sk, ("lhumerus", "lradius", "lhumerus"), name="rep")
    with pytest.raises(InputError, match=r"'ghost'.*no joint 'lelbow'"):
        make_chain(sk, ("lhumerus", "lelbow"), name="ghost")
    with pytest.raises(InputError, match="unknown default chain 'tail'"):
        default_chains(sk, ["tail"])
    # a multi-bone link is a path: thorax -> upper neck skips the lower neck
    assert make_chain(sk, ("thorax", "upperneck")).num_links == 1


def test_default_chains_need_cmu_names(sk):
    renamed = replace(sk, joint_names=tuple(f"j{i}" for i in range(sk.num_joints)))
    with pytest.raises(InputError, match=r"'larm'.*no joint 'lclavicle'"):
        default_chains(renamed)


def test_check_independent(sk):
    larm = make_chain(sk, CMU_CHAINS["larm"], "larm")
    shoulder = make_chain(sk, ("thorax", "lclavicle", "lhumerus"), "shoulder")
    with pytest.raises(
        InputError, match="'shoulder' and 'larm' are not independent: 'shoulder' moves 'larm''s root 'lclavicle'"
    ):
        check_independent(sk, [larm, shoulder])
    with pytest.raises(InputError, match="'larm' and 'larm' are not independent: both move 'lhumerus'"):
        check_independent(sk, [larm, larm])
    check_independent(sk, [larm, make_chain(sk, CMU_CHAINS["rarm"], "rarm")])


# -- trees ------------------------------------------------------------------------------------


def test_every_leaf_reprojects_and_keeps_lengths(sk, scene):
    q, joints, cam, pixels, conf = scene
    for chain in default_chains(sk):
        tree = interpretation_tree(chain, joints, cam, pixels, conf)
        idx = list(chain.joints)
        n, leaves = chain.num_links, chain.num_leaves
        assert tree.positions.shape == (q.shape[0], leaves, n + 1, 3)
        assert torch.equal(tree.flips, torch.arange(leaves))
        # bone lengths of the hypothesis, on every leaf (infeasible ones too: nearest sphere point)
        torch.testing.assert_close(
            _lengths(tree.positions), _lengths(joints[:, None, idx]).expand(-1, leaves, -1), atol=1e-6, rtol=0
        )
        # feasible links reproject onto the observations
        err = (cam.project(tree.positions[..., 1:, :]).pixels - pixels[:, None, idx[1:]]).norm(dim=-1)
        assert float(err[~tree.infeasible].max()) < 1e-4
        # leaf 0 is the hypothesis itself; the root never moves
        torch.testing.assert_close(tree.positions[:, 0], joints[:, idx], atol=1e-9, rtol=0)
        torch.testing.assert_close(
            tree.positions[:, :, 0], joints[:, None, idx[0]].expand(-1, leaves, -1), atol=0, rtol=0
        )
        # a unique flipped leaf really moved the flipped joints
        moved = (tree.positions[:, 1:] - tree.positions[:, :1]).norm(dim=-1).amax(-1)
        assert bool((moved[tree.unique[:, 1:]] > 1e-3).all())
        assert float(tree.penalty[~tree.infeasible.any(-1)].abs().max()) == 0.0


def test_infeasible_only_below_a_flip(sk, scene):
    """With the pose's own projections, every link of the unflipped path has the true joint as a
    solution; a ray can miss its sphere only after a flip above it moved the sphere."""
    _, joints, cam, pixels, conf = scene
    for chain in default_chains(sk):
        tree = interpretation_tree(chain, joints, cam, pixels, conf)
        assert not tree.infeasible[:, :, 0].any() and not tree.tangent[:, :, 0].any()
        assert not tree.infeasible[:, 0].any() and tree.unique[:, :2].all()
        flips_above = (tree.flips[:, None] & ((1 << torch.arange(chain.num_links)) - 1)) != 0  # (L, n)
        assert not (tree.infeasible & ~flips_above).any()


def _other_intersection(point: torch.Tensor, centre: torch.Tensor, cam) -> torch.Tensor:
    """The second point where the camera ray through `point` pierces the sphere about `centre`
    through `point`: (..., 3). The ray is o + t d; the two roots are symmetric about m = (c - o).d."""
    o = cam.center.to(point)
    d = torch.nn.functional.normalize(point - o, dim=-1)
    m = ((centre - o) * d).sum(-1, keepdim=True)
    t = ((point - o) * d).sum(-1, keepdim=True)
    return o + (2 * m - t) * d


def _ray_sphere(pixel_point: torch.Tensor, centre: torch.Tensor, radius: torch.Tensor, cam):
    """Both intersections (..., 2, 3) of the ray through `pixel_point` with a sphere, and whether
    they exist (...,)."""
    o = cam.center.to(centre)
    d = torch.nn.functional.normalize(pixel_point - o, dim=-1)
    m = ((centre - o) * d).sum(-1)
    h2 = ((centre - o) ** 2).sum(-1) - m * m
    disc = radius**2 - h2
    s = disc.clamp_min(0).sqrt()
    ts = torch.stack([m - s, m + s], -1)
    return o + ts[..., None] * d[..., None, :], disc > 0


def test_known_flip_is_found(sk, scene):
    """Flip the left elbow in depth (and put the wrist back on its ray), run the tree from that
    wrong hypothesis: one leaf is the true arm."""
    _q, joints, cam, pixels, conf = scene
    chain = default_chains(sk, ["larm"])[0]
    s_i, e_i, w_i = chain.joints
    shoulder, elbow, wrist = joints[:, s_i], joints[:, e_i], joints[:, w_i]
    elbow_f = _other_intersection(elbow, shoulder, cam)
    torch.testing.assert_close((elbow_f - shoulder).norm(dim=-1), (elbow - shoulder).norm(dim=-1))
    assert float((elbow_f - elbow).norm(dim=-1).min()) > 0.01  # a real flip, in depth
    both, ok = _ray_sphere(wrist, elbow_f, (wrist - elbow).norm(dim=-1), cam)
    assert int(ok.sum()) >= 10
    flipped = joints.clone()
    flipped[:, e_i] = elbow_f
    flipped[:, w_i] = both[:, 0]
    tree = interpretation_tree(chain, flipped[ok], cam, pixels[ok], conf[ok])
    # the flipped hypothesis is leaf 0; the truth is among the leaves
    dist = (tree.positions - joints[ok][:, None, list(chain.joints)]).norm(dim=-1).amax(-1)  # (N, L)
    assert float(dist.amin(-1).max()) < 1e-3
    best = dist.argmin(-1)
    assert bool((best & 1).all())  # found with the elbow link flipped
    assert flip_names([chain], 1) == ["larm:lhumerus"]


def test_missing_observation_makes_link_unflippable(sk, scene):
    _, joints, cam, pixels, conf = scene
    chain = default_chains(sk, ["larm"])[0]
    s_i, e_i, w_i = chain.joints
    full = interpretation_tree(chain, joints, cam, pixels, conf)
    # missing wrist: leaves with the wrist bit set repeat the ones without
    c = conf.clone()
    c[:, w_i] = 0.0
    tree = interpretation_tree(chain, joints, cam, pixels, c)
    assert tree.unique.tolist() == [[True, True, False, False]] * joints.shape[0]
    torch.testing.assert_close(tree.positions[:, 2:], tree.positions[:, :2])
    torch.testing.assert_close(tree.positions[:, :2, :2], full.positions[:, :2, :2])
    torch.testing.assert_close(tree.positions[:, 0], joints[:, list(chain.joints)])
    # with the elbow flipped, the forearm follows the upper arm rigidly: same elbow angle, length
    p = tree.positions[:, 1]
    upper, fore = p[:, 1] - p[:, 0], p[:, 2] - p[:, 1]
    upper0, fore0 = joints[:, e_i] - joints[:, s_i], joints[:, w_i] - joints[:, e_i]
    cos = (upper * fore).sum(-1) / (upper.norm(dim=-1) * fore.norm(dim=-1))
    cos0 = (upper0 * fore0).sum(-1) / (upper0.norm(dim=-1) * fore0.norm(dim=-1))
    torch.testing.assert_close(cos, cos0)
    torch.testing.assert_close(fore.norm(dim=-1), fore0.norm(dim=-1))
    assert tree.observed[:, 1].logical_not().all() and tree.observed[:, 0].all()
    # missing elbow (a NaN pixel counts as missing): the elbow stays, the wrist still flips
    px = pixels.clone()
    px[:, e_i] = float("nan")
    tree = interpretation_tree(chain, joints, cam, px, conf)
    assert tree.unique.tolist() == [[True, False, True, False]] * joints.shape[0]
    torch.testing.assert_close(tree.positions[:, :, 1], joints[:, None, e_i].expand(-1, 4, -1))
    assert torch.isfinite(tree.positions).all()


def _tangent_pixel(centre, radius, cam):
    """A world point on the sphere where the camera ray touches it."""
    o = cam.center.to(centre)
    w = centre - o
    dist = w.norm()
    w_hat = w / dist
    perp = torch.nn.functional.normalize(torch.linalg.cross(w_hat, torch.tensor([0.0, 1.0, 0.0]).to(w)), dim=0)
    return centre + radius * (-(radius / dist) * w_hat + (1 - (radius / dist) ** 2).sqrt() * perp)


def test_tangent_and_no_solution_are_flagged(sk, scene):
    _, joints, cam, pixels, conf = scene
    chain = make_chain(sk, ("lclavicle", "lhumerus"))
    s_i, e_i = chain.joints
    j0 = joints[:1]
    radius = (j0[0, e_i] - j0[0, s_i]).norm()
    touch = _tangent_pixel(j0[0, s_i], radius, cam)
    px = pixels[:1].clone()
    px[0, e_i] = cam.project(touch).pixels
    tree = interpretation_tree(chain, j0, cam, px, conf[:1])
    assert tree.tangent.tolist() == [[[True], [True]]]
    assert tree.unique.tolist() == [[True, False]] and not tree.infeasible.any()
    torch.testing.assert_close(tree.positions[0, :, 1], touch.expand(2, 3), atol=1e-3 * radius, rtol=0)
    torch.testing.assert_close(_lengths(tree.positions), radius.expand(1, 2, 1))
    # move the observation 100 px away from the sphere's image: no intersection
    px[0, e_i] = cam.project(j0[0, s_i]).pixels + torch.tensor([0.0, -(100 + 1000 * radius.item() / 4)]).double()
    tree = interpretation_tree(chain, j0, cam, px, conf[:1])
    assert tree.infeasible.all() and not tree.tangent.any() and tree.unique.tolist() == [[True, False]]
    o, d = cam.rays(px[0, e_i])
    centre = j0[0, s_i]
    w = centre - o
    h = (w - (w @ d) * d).norm()
    assert float(h) > float(radius)
    torch.testing.assert_close(tree.penalty, (h - radius).expand(1, 2))
    # the point used is on the sphere and as close to the ray as the sphere gets
    p = tree.positions[0, 0, 1]
    torch.testing.assert_close((p - centre).norm(), radius)
    v = p - o
    torch.testing.assert_close((v - (v @ d) * d).norm(), h - radius)


def test_observation_inputs(sk, scene):
    _, joints, cam, pixels, conf = scene
    chain = default_chains(sk, ["larm"])[0]
    with pytest.raises(InputError, match="pixels must be"):
        interpretation_tree(chain, joints, cam, pixels[..., :5, :], conf)
    with pytest.raises(InputError, match="joints must be"):
        interpretation_tree(chain, joints[..., :2], cam, pixels, conf)
    with pytest.raises(InputError, match="uses joint"):
        interpretation_tree(chain, joints[..., :5, :], cam, pixels[..., :5, :], conf[..., :5])
    # keypoints -> per-joint arrays
    kp = make_keypoints(sk)
    kpx = pixels[:, list(kp.joints)]
    kconf = torch.ones(kpx.shape[:-1], dtype=kpx.dtype)
    jpx, jconf = joint_observations(kp, kpx, kconf, sk.num_joints)
    assert jpx.shape == pixels.shape and jconf.shape == conf.shape
    torch.testing.assert_close(jpx[:, list(kp.joints)], kpx)
    assert float(jconf.sum()) == kconf.numel()
    a = interpretation_tree(chain, joints, cam, jpx, jconf)
    b = interpretation_tree(chain, joints, cam, pixels, conf)
    torch.testing.assert_close(a.positions, b.positions)
    with pytest.raises(InputError, match="joint_observations"):
        joint_observations(kp, kpx[..., :3, :], kconf, sk.num_joints)


def test_batched_shapes_and_shared_observations(sk, scene):
    _, joints, cam, pixels, conf = scene
    chain = default_chains(sk, ["head"])[0]
    j = joints[:6].reshape(2, 3, *joints.shape[1:])
    # hypotheses of one frame share its observations (J, 2)
    tree = interpretation_tree(chain, j, cam, pixels[0], conf[0])
    assert tree.positions.shape == (2, 3, 4, 3, 3)
    assert tree.unique.shape == tree.penalty.shape == (2, 3, 4)
    assert tree.tangent.shape == tree.infeasible.shape == (2, 3, 4, 2)
    assert tree.observed.shape == (2, 3, 2)
    flat = interpretation_tree(chain, joints[:6], cam, pixels[0], conf[0])
    torch.testing.assert_close(tree.positions.reshape(flat.positions.shape), flat.positions)
    err = (cam.project(tree.positions[..., 1:, :]).pixels - pixels[0, list(chain.joints[1:])]).norm(dim=-1)
    assert float(err[~tree.infeasible].max()) < 1e-4


@pytest.mark.parametrize("dtype, px_tol, m_tol", [(torch.float32, 0.05, 1e-5), (torch.float64, 1e-4, 1e-9)])
def test_dtypes(sk, scene, dtype, px_tol, m_tol):
    _, joints, cam, pixels, conf = scene
    chain = default_chains(sk, ["rleg"])[0]
    tree = interpretation_tree(chain, joints.to(dtype), cam.to(dtype=dtype), pixels.to(dtype), conf.to(dtype))
    assert tree.positions.dtype == tree.penalty.dtype == dtype
    err = cam.project(tree.positions.double()[..., 1:, :]).pixels - pixels[:, None, list(chain.joints[1:])]
    assert float(err.norm(dim=-1)[~tree.infeasible].max()) < px_tol
    ref = interpretation_tree(chain, joints, cam, pixels, conf)
    both = ~tree.infeasible.any(-1) & ~ref.infeasible.any(-1)
    assert float(both.float().mean()) > 0.5
    dist = (tree.positions.double() - ref.positions).norm(dim=-1).amax(-1)
    assert float(dist[both].max()) < m_tol * 100


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_device_follows_inputs(sk, scene):
    _, joints, cam, pixels, conf = scene
    chain = default_chains(sk, ["larm"])[0]
    tree = interpretation_tree(chain, joints.cuda(), cam.to("cuda"), pixels.cuda(), conf.cuda())
    assert tree.positions.device.type == tree.unique.device.type == "cuda"
    ref = interpretation_tree(chain, joints, cam, pixels, conf)
    torch.testing.assert_close(tree.positions.cpu(), ref.positions)


def test_outputs_on_input_device(sk, scene):
    _, joints, cam, pixels, conf = scene
    tree = interpretation_tree(default_chains(sk, ["larm"])[0], joints, cam, pixels, conf)
    for t in (tree.positions, tree.flips, tree.unique, tree.penalty, tree.tangent):
        assert t.device == joints.device


# -- product of trees -------------------------------------------------------------------------


def test_product_of_trees(sk, scene):
    _, joints, cam, pixels, conf = scene
    chains = default_chains(sk, ["larm", "head", "rleg"])
    trees = interpretation_trees(chains, joints, cam, pixels, conf)
    prod = product(trees)
    assert prod.leaf.shape == (64, 3) and prod.offsets == (0, 2, 4)
    assert torch.equal(prod.flips, torch.arange(64))
    # the combined index is the bitmask: chain c's leaf is its bits
    assert prod.leaf[0b10_01_11].tolist() == [0b11, 0b01, 0b10]
    assert flip_names(prod, 0b10_01_11) == ["larm:lhumerus", "larm:lradius", "head:upperneck", "rleg:rtibia"]
    unique = (
        trees[0].unique[:, prod.leaf[:, 0]] & trees[1].unique[:, prod.leaf[:, 1]] & trees[2].unique[:, prod.leaf[:, 2]]
    )
    assert torch.equal(prod.unique, unique)
    penalty = sum(t.penalty[:, prod.leaf[:, c]] for c, t in enumerate(trees))
    torch.testing.assert_close(prod.penalty, penalty)
    infeasible = [t.infeasible.any(-1)[:, prod.leaf[:, c]] for c, t in enumerate(trees)]
    assert torch.equal(prod.infeasible, infeasible[0] | infeasible[1] | infeasible[2])
    joints_l = product_joints(joints, trees, prod)
    assert joints_l.shape == (joints.shape[0], 64, sk.num_joints, 3)
    for c, t in enumerate(trees):
        torch.testing.assert_close(joints_l[:, :, list(t.chain.joints)], t.positions[:, prod.leaf[:, c]])
    others = [j for j in range(sk.num_joints) if all(j not in c.joints for c in chains)]
    torch.testing.assert_close(joints_l[:, :, others], joints[:, None, others].expand(-1, 64, -1, -1))
    with pytest.raises(InputError, match="share hypotheses"):
        product([trees[0], interpretation_tree(chains[1], joints[:3], cam, pixels[:3], conf[:3])])
    with pytest.raises(InputError, match="at least one"):
        product([])


# -- rotations --------------------------------------------------------------------------------


def test_min_rotation():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(200, 3, dtype=torch.float64, generator=g)
    y = torch.randn(200, 3, dtype=torch.float64, generator=g)
    y[:20] = -x[:20] * 2.0  # opposite
    y[20:40] = -x[20:40] + 1e-9 * torch.randn(20, 3, dtype=torch.float64, generator=g)  # nearly opposite
    y[40:60] = x[40:60] * 3.0  # same direction
    r = min_rotation(x, y)
    eye = torch.eye(3, dtype=torch.float64)
    torch.testing.assert_close(r @ r.transpose(-1, -2), eye.expand(200, 3, 3))
    torch.testing.assert_close(torch.linalg.det(r), torch.ones(200, dtype=torch.float64))
    xu, yu = torch.nn.functional.normalize(x, dim=-1), torch.nn.functional.normalize(y, dim=-1)
    torch.testing.assert_close((r @ xu[..., None])[..., 0], yu)
    torch.testing.assert_close(r[40:60], eye.expand(20, 3, 3))
    # the smallest: the turn angle equals the angle between x and y
    angle = torch.arccos(((r.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1))
    torch.testing.assert_close(angle[60:], torch.arccos((xu * yu).sum(-1).clamp(-1, 1))[60:])
    assert min_rotation(x[0], y[0]).shape == (3, 3)
