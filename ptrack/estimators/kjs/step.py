"""One step of the mixture trackers, frame t-1's modes to frame t's: prediction, covariance scaled (or
spherical) diffusion, kinematic jumps, batched polishing and the K distinct modes kept (the package
docstring, steps 1-5); and `merge_mixtures`, which joins two mixtures of one frame with each depth order of the
limbs served first.

Shapes: S samples, L leaves, D dofs, C chains, K modes (`kjs.modes`)."""

from __future__ import annotations

import torch
from torch import Tensor

from ptrack.costs import HeavyTailedPrior, PoseEval, PosePrior
from ptrack.estimators.kjs.model import Setup, Strategy, distinct_poses, make_modes, polish, select_modes
from ptrack.hypotheses.ik import chain_ik
from ptrack.hypotheses.jumps import interpretation_tree, joint_observations
from ptrack.hypotheses.mixture import Modes
from ptrack.hypotheses.samplers import css_proposal, project_to_limits, spherical_proposal

# ---------------------------------------------------------------- sampling


def _allocate(weight: Tensor, total: int) -> list[int]:
    """Split `total` samples over modes by weight, every mode at least one (if total allows)."""
    m = weight.shape[0]
    base = min(1, total // max(m, 1))
    rest = total - base * m
    share = torch.floor(weight.double() * rest)
    left = rest - int(share.sum())
    order = torch.argsort(weight.double() * rest - share, descending=True)
    share[order[:left]] += 1
    return [base + int(x) for x in share.tolist()]


def _diffuse(s: Setup, modes: Modes, total: int, strategy: Strategy, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """Draw `total` diffusion samples: -> q (total, D), parent mode index (total,)."""
    k = s.cfg.kjs
    counts = _allocate(modes.weight, total)
    dof = k.tail_dof if k.tail == "student" else None
    propose = spherical_proposal if strategy.spherical else css_proposal
    draws = propose(modes.q, modes.chol, counts, gen, tail=k.tail, dof=dof)
    q = project_to_limits(draws.samples, s.lower, s.upper, s.angular, mode="reflect")
    return q, draws.component


def _chain_votes(s: Setup, chol: Tensor) -> Tensor:
    """(M, D, D) scale factors -> (M, C) probability of flipping each chain: the share of each mode's
    covariance (trace over the chain's dofs) that the chain holds."""
    var = chol.square().sum(-1)  # (M, D) marginal variances = diag(L L^T)
    votes = (var[:, None, :] * s.chain_dofs.to(var)).sum(-1)  # (M, C)
    return votes / votes.sum(-1, keepdim=True).clamp_min(torch.finfo(var.dtype).tiny)


def _jump(
    s: Setup, t: int, q: Tensor, parent: Tensor, modes: Modes, gen: torch.Generator, per_sample: int
) -> tuple[Tensor, Tensor, Tensor]:
    """Kinematic jumps of samples q (S, D) on frame t: each flips `per_sample` chains chosen by its mode's
    covariance vote. -> leaves q (L_all, D) (the samples' own leaf 0 included), parent mode (L_all,),
    flipped leaves kept per chain (C,)."""
    prob = s.problem
    sk, obs = prob.skeleton, prob.observations
    counts = torch.zeros(len(s.chains), dtype=torch.long, device=q.device)
    if per_sample == 0 or not s.chains:
        return q, parent, counts
    px, conf = joint_observations(prob.keypoints, obs.keypoints[t], obs.confidence[t], sk.num_joints)
    probs = _chain_votes(s, modes.chol)[parent]  # (S, C)
    picks = torch.multinomial(
        probs.double().cpu(), min(per_sample, len(s.chains)), replacement=False, generator=gen
    ).to(q.device)  # (S, c)
    out_q, out_parent = [q], [parent]
    joints = sk.forward_kinematics(q)
    for c, (chain, plan) in enumerate(zip(s.chains, s.plans)):
        rows = (picks == c).any(-1).nonzero()[:, 0]
        if rows.numel() == 0:
            continue
        tree = interpretation_tree(chain, joints[rows], obs.camera, px, conf)
        ik = chain_ik(plan, q[rows], tree.positions, mode=s.cfg.kjs.limits_mode)
        keep = ik.keep & tree.unique & ~tree.infeasible.any(-1)
        keep[:, 0] = False  # leaf 0 keeps the sample's own interpretation: already in out_q
        idx = keep.nonzero()
        out_q.append(ik.q[idx[:, 0], idx[:, 1]])
        out_parent.append(parent[rows][idx[:, 0]])
        counts[c] = idx.shape[0]
    return torch.cat(out_q), torch.cat(out_parent), counts


# ---------------------------------------------------------------- depth orders of the limbs, and two mixtures merged


#: a limb whose ends lie nearer than this in depth (metres) has no depth order in `_depth_orders`
DEPTH_ORDER_MARGIN_M = 0.05


def _depth_orders(s: Setup, q: Tensor) -> Tensor:
    """Which end of each limb of the keypoint set (`KeypointSet.limbs`, the flip metric's) is nearer the
    camera, for poses q (N, D): -> (N, L) in {-1, 0, 1}, 0 where the ends are within
    `DEPTH_ORDER_MARGIN_M` of each other in depth (near the image plane, where 2D barely tells)."""
    kp, cam = s.problem.keypoints, s.problem.observations.camera
    if not kp.limbs:
        return torch.zeros(q.shape[0], 0, dtype=torch.long, device=q.device)
    with torch.no_grad():
        joints = s.problem.skeleton.forward_kinematics(q).index_select(-2, kp.index(q.device))
        depth = cam.world_to_camera(joints)[..., 2]  # (N, P)
        limbs = torch.as_tensor(kp.limbs, device=q.device)
        gap = depth[:, limbs[:, 1]] - depth[:, limbs[:, 0]]
        return (gap > DEPTH_ORDER_MARGIN_M).long() - (gap < -DEPTH_ORDER_MARGIN_M).long()


def _orders_first(s: Setup, q: Tensor, rank: Tensor) -> Tensor:
    """Poses q (N, D) in the order `rank` (N,) (distinct integers, lowest first) -> a new rank (N,) that keeps
    the first pose of each depth order of the limbs (`_depth_orders`) where it was and puts every repeat of
    a depth order after all of them (in their old order)."""
    orders = _depth_orders(s, q)
    if orders.shape[1] == 0:  # a keypoint set without limbs: every pose has the same (empty) depth order
        return rank
    _, order = torch.unique(orders, dim=0, return_inverse=True)
    earliest = torch.full_like(rank, rank.numel()).scatter_reduce(0, order, rank, "amin")
    return rank + rank.numel() * (rank != earliest[order])


def merge_mixtures(s: Setup, forward: Modes, backward: Modes, lead: int) -> Modes:
    """One frame's modes from two mixtures (the forward and the backward pass; or, inside the backward
    pass, its own modes and the forward pass's): the first mixture's mode `lead` first (after both passes:
    the best trajectory's), then taken from each in turn, heaviest first, distinct (`distinct_poses`), at most K, with
    each depth order of the limbs (`_depth_orders`) served before any order is served twice: the
    two mixtures often hold the same reading many times over and the other reading of a limb near the
    image plane only in a light mode, which K slots would otherwise leave out. Each keeps its cost,
    covariance and velocity, and its weight is the mean of its weights in the two mixtures (0 in the one
    that lacks it), renormalised. (M1), (M2) modes -> (<= K) modes, `lead` at index 0."""
    n = min(forward.q.shape[0], backward.q.shape[0])
    lead = lead if lead < forward.q.shape[0] else 0  # a padding slot (`_pad`) is a copy of mode 0
    first = torch.argsort(forward.weight, descending=True)
    first = torch.cat([first.new_tensor([lead]), first[first != lead]])
    second = torch.argsort(backward.weight, descending=True) + forward.q.shape[0]
    turns = torch.cat([torch.stack([first[:n], second[:n]], 1).flatten(), first[n:], second[n:]])
    rank = torch.empty_like(turns)
    rank[turns] = torch.arange(turns.numel(), device=turns.device)
    both = Modes(*(torch.cat([a, b]) for a, b in zip(forward, backward)))
    rank = _orders_first(s, both.q, rank)
    keep = distinct_poses(s, both.q, rank.to(both.q.dtype))
    keep = keep[torch.argsort(rank[keep])][: s.cfg.kjs.modes]
    weight = both.weight[keep]
    return Modes(both.q[keep], weight / weight.sum(), both.cost[keep], both.chol[keep], both.velocity[keep])


# ---------------------------------------------------------------- the prior weight of a new minimum


def prior_weights(s: Setup, q: Tensor, parent: Tensor, weight: Tensor, predicted: Tensor, sigma: Tensor) -> Tensor:
    """The log prior weight of each new minimum q (N, D) of frame t, whose polishing cost holds the dynamics
    around its parent mode's prediction (parent (N,) into the previous modes' weight (K,), predicted (K, D) and
    dynamics std sigma (K, D)) -> (N,).

    `kjs.reweight: mixture` (Sminchisescu & Triggs 2003, sec. 3): the prior is the predicted mixture
    sum_j w_j p_j(q), p_j the dynamics' density around mode j's prediction (the heavy-tailed prior of the
    polishing, normalised as a Gaussian of std sigma_j); its parent's own term is already in the cost, so it is
    taken back out here, and the weight prior x likelihood follows in `select_modes`. `memory`: the parent's
    weight to the power `kjs.weight_memory` (the dynamics counted once, around the parent)."""
    k = s.cfg.kjs
    if k.reweight == "memory":
        return k.weight_memory * torch.log(weight.clamp_min(torch.finfo(weight.dtype).tiny))[parent]
    term: HeavyTailedPrior | PosePrior = (
        PosePrior(predicted, sigma)
        if k.prior_tail == "gaussian"
        else HeavyTailedPrior(predicted, sigma, loss=k.prior_tail, scale=k.prior_tail_scale)
    )
    empty = q.new_zeros(q.shape[0], 1, 0, 3)
    energy = term.energy(PoseEval(q[:, None, :], empty, empty[..., :2], empty[..., 0]))  # (N, K)
    log_density = torch.log(weight.clamp_min(torch.finfo(weight.dtype).tiny)) - energy - torch.log(sigma).sum(-1)
    own = energy.gather(1, parent[:, None])[:, 0]  # the parent's dynamics, already in the polishing cost
    return torch.logsumexp(log_density, 1) + own


# ---------------------------------------------------------------- one tracking step


def track_step(
    s: Setup, t: int, modes: Modes, strategy: Strategy, gen: torch.Generator, orders: bool = False
) -> tuple[Modes, Tensor]:
    """Frame t-1's modes -> frame t's, and the flipped leaves kept per chain (C,) (`ptrack.estimators.kjs`' docstring).
    With `orders` the K kept are the heaviest of each depth order of the limbs before any order's second
    (`_orders_first`), else the K heaviest."""
    k = s.cfg.kjs
    obs = s.problem.observations
    predicted = modes.q  # (K, D): the dynamics' prediction of each mode (constant position)
    counts = torch.zeros(len(s.chains), dtype=torch.long, device=predicted.device)
    if not bool((obs.confidence[t] > 0).any()):  # nothing seen: the dynamics carry the modes
        return modes._replace(q=predicted), counts
    centres = modes._replace(q=predicted)
    budget = k.samples - modes.q.shape[0]
    if strategy.jumps and s.chains and k.jumps_per_sample > 0:
        # each diffusion sample brings up to 2^n - 1 flipped leaves per chain it jumps
        leaves = max(2 ** max(c.num_links for c in s.chains) - 1, 1) * min(k.jumps_per_sample, len(s.chains))
        n_diffuse = max(budget // (1 + leaves), 1)
    else:
        n_diffuse = budget
    q, parent = _diffuse(s, centres, n_diffuse, strategy, gen)
    if strategy.jumps:
        q, parent, counts = _jump(s, t, q, parent, centres, gen, k.jumps_per_sample)
        q, parent = q[:budget], parent[:budget]
    idx = torch.arange(modes.q.shape[0], device=q.device)
    q = torch.cat([predicted, q])
    parent = torch.cat([idx, parent])
    # the dynamics' spread widens with each mode's own last motion: a fast limb may move as far again
    sigma = torch.sqrt(s.dynamics_sigma**2 + (k.motion_scale * modes.velocity) ** 2)  # (K, D)
    # polish everything briefly, then the most promising distinct minima to convergence
    q, cost, _ = polish(s, t, q, predicted[parent], k.polish_iterations, sigma[parent], tracking=True)
    best, _ = select_modes(s, q, cost, prior_weights(s, q, parent, modes.weight, predicted, sigma), 4 * k.modes)
    q, parent = q[best], parent[best]
    q, cost, hessian = polish(s, t, q, predicted[parent], k.refine_iterations, sigma[parent], tracking=True)
    log_prior = prior_weights(s, q, parent, modes.weight, predicted, sigma)
    keep, w = select_modes(s, q, cost, log_prior, 4 * k.modes if orders else k.modes)
    if orders and keep.numel():
        pick = torch.argsort(_orders_first(s, q[keep], torch.arange(keep.numel(), device=keep.device)))[: k.modes]
        keep, w = keep[pick], w[pick] / w[pick].sum()
    if keep.numel() == 0:  # every hypothesis diverged (non-finite cost): the dynamics carry the modes
        return modes._replace(q=predicted), counts
    return make_modes(s, q[keep], cost[keep], hessian[keep], w, modes.q[parent[keep]]), counts
