import dataclasses
from pathlib import Path

import pytest
import torch
from torch.autograd import gradcheck

from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.costs import Objective, PoseEval, SelfIntersection
from ptrack.costs.collision import DEFAULT_SKIP, segment_distance
from ptrack.errors import InputError

D64 = torch.float64
DATA = Path(__file__).resolve().parents[1] / "ptrack" / "data"


def ev(joints):
    z = torch.zeros(1, dtype=joints.dtype)
    return PoseEval(q=z, joints=joints, pixels=z, depth=z)


@pytest.fixture(scope="module")
def sk10():
    return Skeleton.from_asf(DATA / "10.asf")


@pytest.fixture(scope="module")
def joints_10_02(sk10):
    """Ground truth of the bundled kick 10_02: (590, 31, 3) float64."""
    motion = load_amc(DATA / "10_02.amc", sk10)
    return sk10.forward_kinematics(torch.as_tensor(motion.q, dtype=D64))


# ---------------------------------------------------------------- segment distance


def _point_segment(x, a, b):
    ab = b - a
    u = (((x - a) * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-300)).clamp(0, 1)
    return (x - a - u[..., None] * ab).norm(dim=-1)


def _reference(p0, p1, q0, q1):
    """Independent exact distance: the minimum of a convex quadratic over the unit square is at its
    interior critical point or on an edge (a point-to-segment distance)."""
    edges = torch.stack(
        [_point_segment(p0, q0, q1), _point_segment(p1, q0, q1), _point_segment(q0, p0, p1), _point_segment(q1, p0, p1)]
    ).amin(0)
    u, v, w = p1 - p0, q1 - q0, p0 - q0
    m = torch.stack(
        [torch.stack([(u * u).sum(-1), -(u * v).sum(-1)], -1), torch.stack([-(u * v).sum(-1), (v * v).sum(-1)], -1)], -2
    )
    rhs = torch.stack([-(u * w).sum(-1), (v * w).sum(-1)], -1)
    ok = torch.linalg.det(m).abs() > 1e-9 * (u * u).sum(-1) * (v * v).sum(-1)
    st = torch.linalg.solve(torch.where(ok[..., None, None], m, torch.eye(2, dtype=m.dtype)), rhs)
    inside = ok & (st >= 0).all(-1) & (st <= 1).all(-1)
    interior = (w + st[..., :1] * u - st[..., 1:] * v).norm(dim=-1)
    return torch.where(inside, torch.minimum(interior, edges), edges)


def _segments(n=4000, seed=0, dtype=D64):
    """(n, 4, 3): general position, plus parallel, collinear, point and crossing cases."""
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 4, 3, generator=g, dtype=dtype)
    k = n // 10
    x[:k, 3] = x[:k, 2] + 0.7 * (x[:k, 1] - x[:k, 0])  # parallel
    x[k : 2 * k, 2] = x[k : 2 * k, 0] + 0.3 * (x[k : 2 * k, 1] - x[k : 2 * k, 0])  # collinear, overlapping
    x[k : 2 * k, 3] = x[k : 2 * k, 0] + 1.6 * (x[k : 2 * k, 1] - x[k : 2 * k, 0])
    x[2 * k : 3 * k, 1] = x[2 * k : 3 * k, 0]  # p is a point
    x[3 * k : 4 * k, 3] = x[3 * k : 4 * k, 2]  # q is a point
    x[4 * k : 5 * k, 1] = x[4 * k : 5 * k, 0]  # both points
    x[4 * k : 5 * k, 3] = x[4 * k : 5 * k, 2]
    mid = 0.5 * (x[5 * k : 6 * k, 0] + x[5 * k : 6 * k, 1])  # crossing: q passes through p's middle
    x[5 * k : 6 * k, 3] = 2 * mid - x[5 * k : 6 * k, 2]
    x[6 * k : 7 * k, 3] = (
        x[6 * k : 7 * k, 2]
        + (x[6 * k : 7 * k, 1] - x[6 * k : 7 * k, 0])
        + 1e-4 * torch.randn(k, 3, generator=g, dtype=dtype)
    )  # nearly parallel
    return x


def test_segment_distance_is_exact():
    x = _segments()
    d = segment_distance(*x.unbind(1), eps=0.0)
    torch.testing.assert_close(d, _reference(*x.unbind(1)), atol=1e-9, rtol=0)


def test_segment_distance_against_brute_force_sampling():
    x = _segments(n=600, seed=1)
    d = segment_distance(*x.unbind(1), eps=0.0)
    s = torch.linspace(0, 1, 401, dtype=D64)
    p = x[:, None, 0] + s[:, None] * (x[:, 1] - x[:, 0])[:, None]  # (n, 401, 3)
    q = x[:, None, 2] + s[:, None] * (x[:, 3] - x[:, 2])[:, None]
    brute = torch.cdist(p, q, compute_mode="donot_use_mm_for_euclid_dist").flatten(1).amin(1)
    step = ((x[:, 1] - x[:, 0]).norm(dim=-1) + (x[:, 3] - x[:, 2]).norm(dim=-1)) / 400
    assert (brute >= d - 1e-12).all()  # sampled points never beat the exact minimum
    assert (brute <= d + step + 1e-12).all()  # and come within one grid step of it


def test_segment_distance_float32_and_broadcasting():
    x = _segments(seed=2)
    d64 = segment_distance(*x.unbind(1), eps=0.0)
    d32 = segment_distance(*x.float().unbind(1), eps=0.0)
    assert d32.dtype == torch.float32
    torch.testing.assert_close(d32.double(), d64, atol=2e-4, rtol=1e-4)
    # one segment against a batch of segments
    d = segment_distance(x[:5, 0], x[:5, 1], x[:1, 2], x[:1, 3])
    assert d.shape == (5,)


def test_segment_distance_gradcheck():
    x = _segments(n=60, seed=3)
    # general position: unique closest points, so d is differentiable there (crossing, parallel
    # overlapping and point segments are kinks of d: their gradients are only checked finite)
    x = x[42:].clone().requires_grad_()
    assert gradcheck(lambda y: segment_distance(*y.unbind(1), eps=1e-6), (x,))
    # a point (one tensor for both ends) against a segment
    assert gradcheck(lambda y: segment_distance(y[:, 0], y[:, 0], y[:, 2], y[:, 3]), (x,))


def test_segment_distance_gradient_finite_at_contact_and_degenerate():
    x = _segments(n=100, seed=4).requires_grad_()
    d = segment_distance(*x.unbind(1))
    d.sum().backward()
    assert torch.isfinite(x.grad).all()
    crossing = torch.tensor([[-1.0, 0, 0], [1, 0, 0], [0, -1, 0], [0, 1, 0]], requires_grad=True)
    segment_distance(*crossing).backward()
    assert torch.isfinite(crossing.grad).all()


# ---------------------------------------------------------------- the cost term


def _two_capsules(gap, dtype=D64):
    """Capsules along x and along y (radius 0.05 each), `gap` apart in z: joints (4, 3)."""
    return torch.tensor([[-0.3, 0, 0], [0.3, 0, 0], [0, -0.3, gap], [0, 0.3, gap]], dtype=dtype)


TWO = dict(segments=[[0, 1], [2, 3]], radii=[0.05, 0.05], pairs=[[0, 1]])


def test_crossing_capsules_cost_more_than_apart_and_gradient_separates():
    term = SelfIntersection(**TWO, sigma=0.01)
    crossing, apart = _two_capsules(0.02), _two_capsules(0.3)
    assert term.energy(ev(apart)) == 0
    assert term.energy(ev(crossing)) > 1.0  # 8 cm deep: r = 8, energy 32
    torch.testing.assert_close(term.penetration(crossing), torch.tensor([0.08], dtype=D64))
    j = crossing.clone().requires_grad_()
    term.energy(ev(j)).backward()
    stepped = crossing - 1e-4 * j.grad
    d0 = segment_distance(*crossing)
    d1 = segment_distance(*stepped)
    assert d1 > d0 + 1e-3
    assert term.energy(ev(stepped)) < term.energy(ev(crossing))
    # the push is along the z gap: capsule a goes down, capsule b up
    assert (j.grad[:2, 2] > 0).all() and (j.grad[2:, 2] < 0).all()


def test_exact_contact_has_finite_gradient():
    term = SelfIntersection(**TWO)
    j = _two_capsules(0.0).requires_grad_()
    term.energy(ev(j)).backward()
    assert torch.isfinite(j.grad).all()


def test_margin_and_residual():
    term = SelfIntersection(**TWO, sigma=0.02, margin=0.03)
    r = term.residual(ev(_two_capsules(0.05)))  # penetration 0.05, 0.02 beyond the margin
    torch.testing.assert_close(r, torch.tensor([1.0], dtype=D64))
    torch.testing.assert_close(term.energy(ev(_two_capsules(0.05))), torch.tensor(0.5, dtype=D64))
    assert term.residual(ev(_two_capsules(0.08))) == 0


def test_term_gradcheck(sk10, joints_10_02):
    term = SelfIntersection.for_skeleton(sk10, radius_scale=1.5)  # fat: many pairs penetrate
    j = joints_10_02[::150].clone()
    assert (term.residual(ev(j)) > 0).sum() > 10
    assert gradcheck(lambda x: term.energy(ev(x)), (j.requires_grad_(),))
    assert gradcheck(lambda x: term.residual(ev(x)), (j,))


def test_batched_shapes_match_per_element(sk10, joints_10_02):
    term = SelfIntersection.for_skeleton(sk10, radius_scale=1.5)
    p = term.pairs.shape[0]
    j = joints_10_02[:24].reshape(4, 6, 31, 3)
    assert term.residual(ev(j)).shape == (4, 6, p)
    assert term.energy(ev(j)).shape == (4, 6)
    assert term.energy(ev(j[:, 0])).shape == (4,)
    assert term.residual(ev(j[0, 0])).shape == (p,)
    loop = torch.stack([torch.stack([term.energy(ev(j[a, b])) for b in range(6)]) for a in range(4)])
    torch.testing.assert_close(term.energy(ev(j)), loop)
    e32 = term.energy(ev(j.float()))
    assert e32.dtype == torch.float32
    torch.testing.assert_close(e32.double(), loop, rtol=1e-4, atol=1e-3)
    assert term.robust_weights(ev(j)).shape == (4, 6, p)


def test_gauss_newton_share_skips_far_pairs_only(sk10, joints_10_02):
    """`gauss_newton` (what the trackers fold into their normal equations) equals stacking `residual`
    and `jacobian`, though its cheap bound leaves out most pairs; on fat capsules that penetrate."""
    from ptrack.costs.base import PoseJacobian

    term = SelfIntersection.for_skeleton(sk10, radius_scale=1.5)
    x = joints_10_02[::100].clone()  # (6, J, 3); the joints themselves as 3 * J "dofs"
    jx = torch.eye(x.shape[-2] * 3, dtype=D64).reshape(x.shape[-2], 3, -1).expand(x.shape[0], -1, -1, -1)
    e, jac = ev(x), PoseJacobian(joints=jx, pixels=None, depth=None)
    r, rows = term.residual(e), term.jacobian(e, jac)
    assert (r > 0).sum() > 10
    assert term._maybe(x)[0].numel() < x.shape[0] * term.pairs.shape[0] // 2
    energy, h, g = term.gauss_newton(e, jac)
    torch.testing.assert_close(energy, term.energy(e))
    torch.testing.assert_close(h, rows.mT @ rows)
    torch.testing.assert_close(g, (rows.mT @ r[..., None])[..., 0])


def test_in_objective(sk10, joints_10_02):
    obj = Objective({"self": SelfIntersection.for_skeleton(sk10)}, {"self": 2.0})
    assert obj(ev(joints_10_02[:3])).total.shape == (3,)


# ---------------------------------------------------------------- pairs from a skeleton


def test_for_skeleton_pairs(sk10):
    term = SelfIntersection.for_skeleton(sk10)
    pairs = {frozenset(p) for p in term.pair_names}
    assert len(pairs) == term.pairs.shape[0]
    bones = {sk10.joint_names[c]: (p, c) for p, c in sk10.bones()}
    for a, b in term.pair_names:  # never two bones sharing a joint
        assert not set(bones[a]) & set(bones[b])
    assert frozenset(("lradius", "upperback")) in pairs  # forearm vs torso
    assert frozenset(("lfemur", "rfemur")) in pairs  # thigh vs thigh
    assert frozenset(("lhumerus", "upperback")) in pairs  # 3 hops
    assert frozenset(("lhumerus", "thorax")) not in pairs  # 2 hops: via the clavicle
    assert frozenset(("lfemur", "rhipjoint")) not in pairs  # 2 hops: pelvis
    assert frozenset(("lowerback", "thorax")) not in pairs  # 2 hops: spine
    assert not {n for n in term.names if any(s.strip("*") in n for s in DEFAULT_SKIP)}
    one = {frozenset(p) for p in SelfIntersection.for_skeleton(sk10, min_hops=1).pair_names}
    assert frozenset(("lhumerus", "thorax")) in one and frozenset(("lowerback", "thorax")) in one
    assert frozenset(("lhumerus", "lclavicle")) not in one  # sharing a joint: always out
    fewer = SelfIntersection.for_skeleton(sk10, exclude=[("rfemur", "lfemur")])
    assert frozenset(("lfemur", "rfemur")) not in {frozenset(p) for p in fewer.pair_names}
    assert fewer.pairs.shape[0] == term.pairs.shape[0] - 1
    every = SelfIntersection.for_skeleton(sk10, skip=())
    assert "lhand" in every.names and len(every.names) == 30


def test_for_skeleton_radii(sk10):
    term = SelfIntersection.for_skeleton(sk10)
    i = term.names.index("upperback")
    assert term.radii[i].item() == pytest.approx(0.07)  # half the 0.14 m flesh radius
    custom = SelfIntersection.for_skeleton(sk10, radii={"upperback": 0.2}, radius_scale=1.0)
    assert custom.radii[i].item() == pytest.approx(0.2)
    flat = SelfIntersection.for_skeleton(sk10, radii=torch.full((30,), 0.1), radius_scale=1.0)
    torch.testing.assert_close(flat.radii, torch.full((20,), 0.1))


def test_zero_length_bone_merges_its_joints(sk10):
    lengths = sk10.lengths.copy()
    lengths[sk10.joint_index("lowerneck")] = 0.0
    sk = dataclasses.replace(sk10, lengths=lengths)
    term = SelfIntersection.for_skeleton(sk)
    pairs = {frozenset(p) for p in term.pair_names}
    assert "lowerneck" not in term.names
    before = {frozenset(p) for p in SelfIntersection.for_skeleton(sk10).pair_names}
    assert frozenset(("upperneck", "lhumerus")) in before  # 3 hops via lowerneck
    assert frozenset(("upperneck", "lhumerus")) not in pairs  # 2 hops once lowerneck is a point


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(min_hops=0),
        dict(min_hops=1.5),
        dict(radius_scale=0.0),
        dict(sigma=-1.0),
        dict(radii={"nobone": 0.1}),
        dict(radii=torch.ones(3)),
        dict(exclude=[("lfemur", "nobone")]),
        dict(skip="*hand"),
        dict(margin=float("nan")),
    ],
)
def test_for_skeleton_errors(sk10, kwargs):
    with pytest.raises(InputError):
        SelfIntersection.for_skeleton(sk10, **kwargs)


def test_construction_and_input_errors():
    with pytest.raises(InputError, match="segments"):
        SelfIntersection(segments=[[0.0, 1.0]], radii=[0.1], pairs=torch.zeros(0, 2, dtype=torch.long))
    with pytest.raises(InputError, match="radii"):
        SelfIntersection(segments=[[0, 1], [2, 3]], radii=[0.1], pairs=[[0, 1]])
    with pytest.raises(InputError, match="pairs"):
        SelfIntersection(segments=[[0, 1], [2, 3]], radii=[0.1, 0.1], pairs=[[0, 2]])
    with pytest.raises(InputError, match="margin"):
        SelfIntersection(**TWO, margin="deep")
    none = SelfIntersection(segments=[[0, 1]], radii=[0.1], pairs=torch.zeros(0, 2, dtype=torch.long))
    assert none.residual(ev(torch.randn(5, 2, 3))).shape == (5, 0)
    assert (none.energy(ev(torch.randn(5, 2, 3))) == 0).all()
    term = SelfIntersection(**TWO)
    with pytest.raises(InputError, match="joints"):
        term.energy(ev(torch.zeros(4, 2)))
    with pytest.raises(InputError, match="J=3"):
        term.energy(ev(torch.zeros(3, 3)))


# ---------------------------------------------------------------- real motion


CLIPS = ["02_01", "05_02", "64_01", "10_01", "16_01", "49_18", "124_01"]


def _gt_energy_per_frame(sk, amc):
    motion = load_amc(amc, sk)
    joints = sk.forward_kinematics(torch.as_tensor(motion.q, dtype=torch.float32))
    return SelfIntersection.for_skeleton(sk).energy(ev(joints))


# Measured with the defaults (radius_scale 0.5, min_hops 2, DEFAULT_SKIP, margin 0): no frame of
# these eight clips penetrates (energy exactly 0; the closest approach leaves 7 mm on 124_01 and
# 12-74 mm on the others). With the flesh radii and only the adjacency rules, 100% of their frames
# penetrate, up to 8.3 cm. The threshold leaves room for other skeletons' rounding, not for misses.
def test_ground_truth_bundled_clip_costs_nothing(sk10):
    e = _gt_energy_per_frame(sk10, DATA / "10_02.amc")
    assert e.mean() < 1e-3


@pytest.mark.parametrize("clip", CLIPS)
def test_ground_truth_cmu_clips_cost_nothing(cmu_file, clip):
    sk = Skeleton.from_asf(cmu_file(clip.split("_")[0] + ".asf"))
    e = _gt_energy_per_frame(sk, cmu_file(clip + ".amc"))
    assert e.mean() < 1e-3


def _subtree(sk, root):
    out = [root]
    for i, p in enumerate(sk.parents):
        if p in out:
            out.append(i)
    return out


def _rotation_taking(a, b):
    a, b = a / a.norm(), b / b.norm()
    v, c = torch.linalg.cross(a, b), (a * b).sum()
    k = torch.zeros(3, 3, dtype=a.dtype)
    k[0, 1], k[0, 2], k[1, 2] = -v[2], v[1], -v[0]
    k = k - k.T
    return torch.eye(3, dtype=a.dtype) + k + k @ k / (1 + c)


def test_arm_through_torso_costs_clearly_more(sk10, joints_10_02):
    """Swing the left arm about the shoulder (a shoulder rotation: bone lengths kept) until the
    forearm's middle lies on the line from the shoulder through the spine."""
    term = SelfIntersection.for_skeleton(sk10)
    shoulder = sk10.joint_index("lclavicle")
    arm = _subtree(sk10, sk10.joint_index("lhumerus"))
    elbow, wrist = sk10.joint_index("lhumerus"), sk10.joint_index("lradius")
    torso = {"lowerback", "upperback", "thorax"}
    for f in range(0, 590, 50):
        x = joints_10_02[f].clone()
        mid = 0.5 * (x[elbow] + x[wrist])
        r = _rotation_taking(mid - x[shoulder], x[sk10.joint_index("upperback")] - x[shoulder])
        x[arm] = (x[arm] - x[shoulder]) @ r.T + x[shoulder]
        torch.testing.assert_close(
            (x[arm] - x[shoulder]).norm(dim=-1), (joints_10_02[f, arm] - joints_10_02[f, shoulder]).norm(dim=-1)
        )
        assert term.energy(ev(joints_10_02[f])) == 0
        assert term.energy(ev(x)) > 10.0  # measured 38-48: 6.7-6.9 cm deep at sigma 1 cm
        pen = term.penetration(x)
        a, b = term.pair_names[int(pen.argmax())]
        assert {a, b} & torso and {a, b} & {"lhumerus", "lradius"}
