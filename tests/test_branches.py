"""Tests for ptrack.hypotheses.branches: the exact second-order forward-backward, the depth-labelled leaves
of every limb at a pose, and the branch posterior on synthetic cases (equal-cost flips share the
probability and the std grows to cover them; a costly frame pins its branch)."""

from __future__ import annotations

import itertools
from pathlib import Path

import pytest
import torch

from ptrack.costs import PoseEval, Smoothness
from ptrack.errors import InputError
from ptrack.hypotheses.branches import (
    Branches,
    branch_marginals,
    branch_poses,
    branch_posterior,
    forward_backward,
    mixture_variance,
    smoothing_factors,
)
from ptrack.hypotheses.ik import ik_plan
from ptrack.hypotheses.jumps import default_chains
from ptrack.pipeline.config import load_config
from ptrack.pipeline.run import prepare

REPO = Path(__file__).resolve().parents[1]
BATCH = REPO / "configs" / "batch.yaml"


def test_forward_backward_matches_enumeration():
    """Marginals of a second-order chain (unary, pair and triple energies) equal brute force over
    all L^T paths, batched, with an impossible state (inf) included."""
    gen = torch.Generator().manual_seed(0)
    t_len, n = 5, 3
    unary = torch.rand(2, t_len, n, generator=gen, dtype=torch.float64) * 3
    unary[0, 2, 1] = torch.inf
    pair = torch.rand(2, t_len - 1, n, n, generator=gen, dtype=torch.float64) * 3
    triple = torch.rand(2, t_len - 2, n, n, n, generator=gen, dtype=torch.float64) * 3
    got = forward_backward(unary, pair, triple)
    for b in range(2):
        want = torch.zeros(t_len, n, dtype=torch.float64)
        for path in itertools.product(range(n), repeat=t_len):
            e = sum(unary[b, t, s] for t, s in enumerate(path))
            e = e + sum(pair[b, t, path[t], path[t + 1]] for t in range(t_len - 1))
            e = e + sum(triple[b, t, path[t], path[t + 1], path[t + 2]] for t in range(t_len - 2))
            for t, s in enumerate(path):
                want[t, s] += torch.exp(-e)
        want = want / want.sum(-1, keepdim=True)
        torch.testing.assert_close(got[b], want)
    assert float(got[0, 2, 1]) == 0.0
    # no pair or triple: each frame on its own
    torch.testing.assert_close(forward_backward(unary), torch.softmax(-unary, -1))


def _mirror(t_len: int = 12) -> tuple[Branches, torch.Tensor]:
    """Two one-dof trajectories mirrored about 0 between frames 3 and 8 (equal everywhere else),
    i.e. two branches of equal energy under any smoothing prior; the dof is the x of one point."""
    bump = torch.zeros(t_len, dtype=torch.float64)
    bump[3:9] = torch.tensor([0.1, 0.3, 0.4, 0.4, 0.3, 0.1], dtype=torch.float64)
    q = torch.stack([bump, -bump])[None, None, :, :, None]  # (B 1, C 1, L 2, T, D 1)
    valid = torch.ones(1, 1, 2, t_len, dtype=torch.bool)
    return Branches(chains=(), q=q, valid=valid, dofs=torch.ones(1, 1, dtype=torch.bool)), bump


def _smoothness(n: int, a: float) -> Smoothness:
    """The prior 1/2 |a diff_n(q)|^2 on one dof."""
    sigma = {"sigma_velocity" if n == 1 else "sigma_acceleration": 1.0}
    return Smoothness(1.0, **sigma, dof_scale=torch.tensor([a], dtype=torch.float64))


def test_smoothing_factors_are_the_terms_energy_of_each_stitched_path():
    """Pair and triple factors summed along any path of states equal the shared `Smoothness` terms' energy of
    the trajectory that path stitches together (robust loss, per-dof scales, the chain's dofs only)."""
    gen = torch.Generator().manual_seed(3)
    x = torch.randn(3, 5, 4, generator=gen, dtype=torch.float64)  # (S, T, D)
    idx = torch.tensor([0, 2, 3])
    vel = Smoothness(1.0, 1.0, dof_scale=torch.tensor([2.0, 9.0, 0.5, 1.0]), loss="cauchy", scale=1.5)
    acc = Smoothness(1.0, None, 1.0, dof_scale=torch.tensor([1.0, 7.0, 3.0, 0.2]), loss="cauchy", scale=1.5)
    pair, triple = smoothing_factors(x[..., idx], [t.select(idx) for t in (vel, acc)])
    assert pair is not None and triple is not None
    for path in itertools.product(range(3), repeat=5):
        stitched = x[list(path), torch.arange(5)][:, idx]  # (T, 3)
        want = sum(t.select(idx).energy(PoseEval(stitched, *[stitched.new_zeros(0)] * 3)) for t in (vel, acc))
        got = sum(pair[t, path[t], path[t + 1]] for t in range(4))
        got = got + sum(triple[t, path[t], path[t + 1], path[t + 2]] for t in range(3))
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)


def test_equal_cost_flip_has_probability_one_half_and_the_std_covers_both():
    br, bump = _mirror()
    smooth = [_smoothness(1, 5.0), _smoothness(2, 3.0)]
    prob = branch_marginals(br, torch.zeros(1, 1, 2, bump.shape[0], dtype=torch.float64), smooth)
    torch.testing.assert_close(prob, torch.full_like(prob, 0.5))
    # the point at x = the dof, reported on branch 0: its std about it is sqrt(0.5) * |2 bump|
    joints = torch.nn.functional.pad(br.q[..., None], (0, 2))  # (1, 1, 2, T, 1 joint, 3)
    var = mixture_variance(joints[:, 0, 0], joints, prob)  # (1, T, 1)
    std = var[0, :, 0].sqrt()
    torch.testing.assert_close(std, (0.5 * (2 * bump).square()).sqrt())
    assert bool((2 * bump <= 2 * std + 1e-12).all())  # the other branch lies within 2 std


def test_a_costly_frame_pins_its_branch_and_smoothing_carries_it():
    """Branch 1 costs 20 more at frame 5 only (a keyframe on branch 0): it is pinned there, and the
    smoothing prior (switching costs nothing only where the branches meet) carries that to the
    neighbouring frames of the stretch; outside the stretch the branches are one pose."""
    br, bump = _mirror()
    smooth = [_smoothness(1, 5.0)]
    unary = torch.zeros(1, 1, 2, bump.shape[0], dtype=torch.float64)
    unary[0, 0, 1, 5] = 20.0
    prob = branch_marginals(br, unary, smooth)[0, 0, 1]
    assert float(prob[5]) < 1e-8
    assert float(prob[4]) < 0.05 and float(prob[6]) < 0.05
    assert float(prob[0]) == pytest.approx(0.5) and float(prob[-1]) == pytest.approx(0.5)


def test_leaves_at_a_real_pose_equal_cost_share_probability():
    """The bundled clip's ground truth, every limb's depth flips through its own projections: one
    leaf is the pose itself at every frame, the leaves reproject the chain's joints where the pose
    does, with no cost and no smoothing every distinct leaf is equally probable, and every leaf's
    joints lie within 2 std (the mixture's, about the pose) of the pose's."""
    cfg = load_config(BATCH, ["data.stop=24", "progress=false"])
    prep = prepare(cfg)
    sk, cam = prep.problem.skeleton, prep.problem.observations.camera
    q = prep.gt_q.to(torch.float64)[None]  # (1, T, D)
    chains = default_chains(sk)
    plans = tuple(ik_plan(sk, c) for c in chains)
    br = branch_poses(sk, cam, q, chains, plans)
    joints = sk.forward_kinematics(q)  # (1, T, J, 3)
    leaf_joints = sk.forward_kinematics(br.q)  # (1, C, L, T, J, 3)
    gap = (leaf_joints - joints[:, None, None]).norm(dim=-1).amax(-1)  # (1, C, L, T)
    assert bool((gap.amin(2) < 1e-6).all())  # the pose is one of the leaves at every frame
    cam64 = cam.to(dtype=torch.float64)
    same, count = 0, 0
    for c, chain in enumerate(chains):
        idx = list(chain.joints)
        px = cam64.project(leaf_joints[0, c][..., idx, :]).pixels  # (L, T, n+1, 2)
        want = cam64.project(joints[0][..., idx, :]).pixels.expand_as(px)
        exact = (px - want).abs().amax((-1, -2)) < 1e-3  # same image (IK to 1e-4 m)
        same += int((exact & br.valid[0, c]).sum())
        count += int(br.valid[0, c].sum())
    # the rest were clamped into the joint limits by IK ("project") and pay their image error
    assert same > 0.5 * count, (same, count)
    post = branch_posterior(sk, cam, q, chains, plans, lambda x: x.new_zeros(x.shape[:-1]), ())
    valid = post.branches.valid
    n = valid.sum(2, keepdim=True)
    torch.testing.assert_close(post.prob, torch.where(valid, 1.0 / n, 0.0).to(post.prob))
    assert bool((n > 1).any())  # some limb has a second branch
    std = post.variance.sqrt()  # (1, T, J): the branches' spread alone
    far = (post.joints - joints[:, None, None]).norm(dim=-1)  # (1, C, L, T, J)
    assert bool(((far <= 2 * std[:, None, None] + 1e-9) | ~valid[..., None]).all())


def test_bad_uncertainty_value():
    with pytest.raises(InputError, match=r"batch\.uncertainty"):
        load_config(BATCH, ["batch.uncertainty=gaussian"])
