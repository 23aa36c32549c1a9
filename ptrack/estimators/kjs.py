"""`method: kjs` (kinematic jumps + covariance scaled diffusion), `css` and `ss`: mixture density
propagation trackers (Sminchisescu & Triggs 2003, figs. 4-5).

The posterior of each frame is a mixture of K modes (`ptrack.mixture.Modes`). One step of the tracker,
from frame t-1's modes to frame t's:

1. predict: each mode's centre is carried to frame t (constant position; its prior below is the
   dynamics' velocity noise, per dof from real motion, `kjs.dynamics`);
2. diffusion: samples around the modes, mode m getting a share of the budget by its weight, drawn
   from its covariance scaled by `kjs.scale` (CSS), or isotropically with the same volume (SS), with
   Gaussian, Student-t or Cauchy tails, then projected onto the joint limits;
3. jumps (kjs only): each sample picks a chain by the covariance vote of its mode (the chain holding
   most of the mode's uncertainty is flipped most often), the chain's interpretation tree is grown
   through the observed 2D joints of frame t (`ptrack.jumps`), and every leaf is turned back into
   angles by closed-form IK (`ptrack.ik`); leaves outside the limits are pruned or projected;
4. polishing: every hypothesis (the predicted modes, the samples, the leaves: `kjs.samples` in all,
   the same budget for kjs, css and ss) runs a batched Levenberg-Marquardt or L-BFGS
   (`ptrack.solvers`) on robust reprojection + joint limits + body non-self-intersection + the
   prior around its mode's prediction;
5. distinct minima (two hypotheses are one when no joint coordinate differs by more than
   `kjs.distinct_mm`; with distinct_mm 0, when no dof differs by more than `kjs.distinct_deg`),
   weights ∝ (weight of the mode they came from) ** `kjs.weight_memory` * exp(-cost / temperature), the K
   heaviest kept, each with the covariance scale * (Gauss-Newton Hessian)^-1 for the next frame's diffusion.

The polishing objective holds robust reprojection, joint limits, body non-self-intersection, the
dynamics (a prior around each mode's prediction, std per dof `kjs.dynamics` (or `kjs.prior_sigma`), widened by
`kjs.motion_scale` times the mode's last motion, Gaussian within `kjs.prior_tail_scale` std and
heavy-tailed beyond (`kjs.prior_tail`, cauchy: the paper's long-tailed components), so a limb
flipped far from the prediction remains a minimum of comparable cost) and a weak CMU pose prior
(`kjs.pose_prior_weight`, `ptrack.pose_prior`). Limits, priors and collision are folded into the
normal equations rather than stacked as residual rows (`ptrack.costs.Objective.linearize`).

Frame 0 starts from a 3D keyframe (`kjs.init: keyframe`), or, with no 3D input (`init: tree`), from
the rest pose placed in view under `kjs.init_yaws` headings (each also leaned forward and back),
fitted to frame 0's 2D rigidly and then in every dof under the pose prior; the `kjs.init_fits` best
fits that differ in 3D are expanded by every flip combination of the chains (the product of their
trees), the 4K of lowest frame-0 cost without the start prior refined, and the K best distinct minima
kept. A frame with no observed keypoint is carried by the dynamics. The output's `hypotheses` are the
K modes of each frame; `q`/`joints` are the best trajectory through them by Viterbi: each mode's own
frame cost (data, limits, collision, pose prior; `_evidence`) plus a velocity prior between
consecutive choices, on the joints' positions relative to the root (`kjs.viterbi_space: joints`, std
`kjs.viterbi_sigma_m` per frame) or on the dofs (`dofs`, `kjs.viterbi_sigma`).

A second pass runs backwards in time from the forward pass's last modes (`kjs.backward_pass: always`;
`tree`: after a tree start only). After a tree start it also starts from a tree start on the last frame
(`_backward_start`): without 3D input the forward pass can hold a limb's wrong branch, or the whole
body's, from frame 0 on, and the backward pass brings the later reading back. After a keyframe start each
backward step also starts from the forward pass's modes of the frame after (`_feed`): where a limb crosses
the image plane both passes lag on the side they came from, and the forward pass's true reading, found a
few frames after the crossing in a light mode, is carried back to the crossing; the backward pass keeps
the heaviest mode of each depth order of the limbs before any order's second (`_orders_first`), so that
such a light mode is not crowded out by many heavier copies of the other reading. Each frame's K
hypotheses are taken from both passes in turn (`_merge`): the forward trajectory's mode first, then each
pass's heaviest, each depth order of the limbs before any order twice. The best trajectory stays the
forward pass's: over the merged modes Viterbi took flipped backward modes where the forward pass had
been right (held-out 35_01, 02_03 and 118_01 at 1 px, seed 0: 36.1 against 29.2 mm; docs/results.md).
After a tree start the backward pass's own best trajectory replaces it when the two face directions more
than `HEADING_SPLIT_DEG` apart (two readings of the whole body) and it costs less (`_lead_pass`).

Then `kjs.smooth_sweeps` sweeps of a smoother (`_smooth`) re-polish every frame's hypotheses with the prior
around the mean of their nearest neighbours in the frames before and after. The passes are filters: each
mode holds its own frame's evidence and the past's (or the future's), so its depth jitters from frame to
frame where the 2D leaves it loose; the smoother brings in both sides. It keeps the weights and the best
trajectory's choice of mode per frame.

Last (`kjs.recombine`, `_recombine`) each frame gets one more hypothesis: the best trajectory's pose with
each chain's reading (which way each limb points in depth) chosen on its own, by a Viterbi pass per chain
over the modes' readings of it. The modes hold the readings in combinations, and often none holds the right
reading of every limb at once. It replaces a light mode and leaves the best trajectory as it was.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ptrack.banded import one_thread
from ptrack.costs import (
    CostTerm,
    HeavyTailedPrior,
    JointLimits,
    Objective,
    PosePrior,
    Reprojection,
    SelfIntersection,
)
from ptrack.errors import EstimationError, InputError
from ptrack.estimators.frame import rest_pose_in_view
from ptrack.ik import ChainIK, ClosedFormUnavailable, chain_ik, ik_plan, product_ik
from ptrack.jacobians import objective_linearization
from ptrack.jumps import (
    Chain,
    check_independent,
    default_chains,
    interpretation_tree,
    interpretation_trees,
    joint_observations,
    product,
)
from ptrack.limits import wrapped_difference
from ptrack.mixture import Modes, distinct_minima, posterior_weights, viterbi_with_cost
from ptrack.pose_prior import pose_prior, smoothing_prior
from ptrack.problem import Estimate, Problem, first_keyframe, pose_eval_from_joints
from ptrack.samplers import css_proposal, project_to_limits, scaled_covariance, spherical_proposal
from ptrack.solvers import lbfgs, levenberg_marquardt

if TYPE_CHECKING:
    from ptrack.config import RunConfig


@dataclass(frozen=True)
class Strategy:
    """What distinguishes the three trackers: the diffusion's core shape and whether to jump."""

    name: str
    spherical: bool
    jumps: bool


KJS = Strategy("kjs", spherical=False, jumps=True)
CSS = Strategy("css", spherical=False, jumps=False)
SS = Strategy("ss", spherical=True, jumps=False)


@dataclass(frozen=True, eq=False)
class Setup:
    """Everything fixed over the sequence: model, limits, cost terms without the frame's data,
    chains with their IK plans."""

    problem: Problem
    cfg: RunConfig
    lower: Tensor  # (D,)
    upper: Tensor  # (D,)
    angular: Tensor  # (D,) bool
    collision: SelfIntersection | None
    chains: tuple[Chain, ...]
    plans: tuple[ChainIK, ...]
    chain_dofs: Tensor  # (C, D) bool: dofs each chain's IK sets
    root: Tensor  # (D,) bool: the root joint's rotation and translation dofs
    prior: tuple[Tensor, Tensor, Tensor]  # CMU pose prior: mean (D,), std (D,), known (D,) bool (never the root)
    prior_sigma: Tensor  # (D,) the tracking term's std: the prior's spread (>= floor_deg), 1e6 where unknown
    dynamics_sigma: float | Tensor  # the dynamics' velocity std per frame before widening (`kjs.dynamics`)


def _setup(problem: Problem, cfg, strategy: Strategy) -> Setup:
    sk = problem.skeleton
    obs = problem.observations
    dtype, device = obs.keypoints.dtype, obs.keypoints.device
    k = cfg.kjs
    lower, upper = sk.limits(dtype=dtype, device=device)
    angular = torch.as_tensor(sk.angular_dofs(), device=device)
    collision = None
    if k.collision_weight > 0:
        collision = SelfIntersection.for_skeleton(sk)
    chains: tuple[Chain, ...] = ()
    plans: tuple[ChainIK, ...] = ()
    if strategy.jumps or k.init == "tree":
        try:
            chains = default_chains(sk, k.chains)
        except InputError as e:
            raise InputError(f"config key 'kjs.chains': {e}") from None
        check_independent(sk, chains)
        try:
            plans = tuple(ik_plan(sk, c) for c in chains)
        except ClosedFormUnavailable as e:
            raise InputError(f"config key 'kjs.chains': {e}") from None
    chain_dofs = torch.zeros(len(chains), sk.num_dofs, dtype=torch.bool, device=device)
    for c, plan in enumerate(plans):
        chain_dofs[c, list(plan.dofs)] = True
    root = torch.zeros(sk.num_dofs, dtype=torch.bool, device=device)
    root[[int(d) for d in (*sk.axis_dof[0], *sk.translation_dof) if d >= 0]] = True
    mean, std, known = pose_prior(sk, lower, upper, angular)
    known = known & ~root
    prior_sigma = torch.where(known, std.clamp_min(math.radians(k.floor_deg)), torch.full_like(std, 1e6))
    return Setup(
        problem,
        cfg,
        lower,
        upper,
        angular,
        collision,
        chains,
        plans,
        chain_dofs,
        root,
        (mean, std, known),
        prior_sigma,
        _dynamics_sigma(problem, k, dtype, device),
    )


def _dynamics_sigma(problem: Problem, k, dtype: torch.dtype, device: torch.device) -> float | Tensor:
    """The dynamics' velocity std per frame: with `kjs.dynamics` null the float `kjs.prior_sigma` for every
    dof; else a (D,) tensor: each CMU dof's RMS velocity in real motion from the table `kjs.dynamics`
    (`ptrack.pose_prior.SMOOTHING_TABLES`; the default "cmu-train" was fitted to clips of subjects with no
    dev clip) times the frame interval and `kjs.dynamics_scale`, at least `kjs.dynamics_floor`;
    `kjs.prior_sigma` for the dofs the table does not name (the root's position)."""
    if k.dynamics is None:
        return k.prior_sigma
    sk = problem.skeleton
    sigma = torch.full((sk.num_dofs,), k.prior_sigma, dtype=dtype, device=device)
    dt = problem.observations.frame_interval
    table = smoothing_prior(k.dynamics, "kjs.dynamics")["velocity"]
    for i, name in enumerate(sk.dof_names):
        if name in table:
            sigma[i] = max(table[name] * dt * k.dynamics_scale, k.dynamics_floor)
    return sigma


# ---------------------------------------------------------------- the frame's objective


def _objective(
    s: Setup, t: int | Tensor, mean: Tensor | None, sigma: float | Tensor | None = None, tracking: bool = False
) -> Objective:
    """Robust reprojection on frame t + limits + collision (+ the prior around `mean` (N, D), std `sigma`,
    by default the dynamics' `kjs.prior_sigma`; + with `tracking`, the CMU pose prior weighted by
    `kjs.pose_prior_weight`). t: one frame for every pose, or (N,) frame indices, one per pose."""
    cc, k = s.cfg.costs, s.cfg.kjs
    obs = s.problem.observations
    terms: dict[str, CostTerm] = {
        "reprojection": Reprojection(
            obs.keypoints[t],
            obs.confidence[t],
            sigma_px=cc.sigma_px,
            loss=cc.loss,
            scale=cc.robust_scale,
            per_problem=isinstance(t, Tensor),
        ),
        "limits": JointLimits(s.lower, s.upper, sigma=cc.limits_sigma),
    }
    weights = {"limits": cc.limits_weight}
    if s.collision is not None:
        terms["collision"] = s.collision
        weights["collision"] = k.collision_weight
    if mean is not None:
        sigma = k.prior_sigma if sigma is None else sigma
        if tracking and k.prior_tail != "gaussian":
            terms["prior"] = HeavyTailedPrior(mean, sigma, loss=k.prior_tail, scale=k.prior_tail_scale)
        else:
            terms["prior"] = PosePrior(mean, sigma)
    if tracking and k.pose_prior_weight > 0:
        terms["pose_prior"] = PosePrior(s.prior[0], s.prior_sigma)
        weights["pose_prior"] = k.pose_prior_weight
    return Objective(terms, weights)


def _polish(
    s: Setup,
    t: int | Tensor,
    q: Tensor,
    mean: Tensor | None,
    iterations: int,
    sigma: float | Tensor | None = None,
    tracking: bool = False,
) -> tuple[Tensor, Tensor, Tensor]:
    """Local optimisation of N hypotheses on frame t (or on frames t (N,), one per hypothesis). q, mean: (N, D)
    -> q (N, D), cost (N,), hessian (N, D, D)."""
    prob = s.problem
    sk, cam, kps = prob.skeleton, prob.observations.camera, prob.keypoints
    objective = _objective(s, t, mean, sigma, tracking)
    linearize = objective_linearization(sk, objective, cam, kps, fold=True)
    if s.cfg.kjs.polisher == "lbfgs" and iterations > 0:

        def energy(x: Tensor) -> Tensor:
            return objective(pose_eval_from_joints(cam, kps, x, sk.forward_kinematics(x))).total

        q, _ = lbfgs(energy, q, s.lower, s.upper, max_iter=iterations)
        iterations = 1  # one Gauss-Newton pass for the Hessian and the cost
    q, info = levenberg_marquardt(linearize, q, s.lower, s.upper, max_iter=max(iterations, 1), tol=1e-6)
    return q, info.cost, info.hessian


def _cholesky(s: Setup, hessian: Tensor) -> Tensor:
    k = s.cfg.kjs
    return scaled_covariance(
        hessian,
        k.scale,
        max_std=math.radians(k.ceiling_deg) / math.sqrt(k.scale),
        min_std=math.radians(k.floor_deg) / math.sqrt(k.scale),
    ).chol


# ---------------------------------------------------------------- sampling


def _allocate(weight: Tensor, total: int, even: float = 0.0) -> list[int]:
    """Split `total` samples over modes: a share `even` of them equally, the rest by weight, every mode
    at least one (if total allows)."""
    m = weight.shape[0]
    base = max(min(1, total // max(m, 1)), int(even * total) // max(m, 1))
    rest = total - base * m
    share = torch.floor(weight.double() * rest)
    left = rest - int(share.sum())
    order = torch.argsort(weight.double() * rest - share, descending=True)
    share[order[:left]] += 1
    return [base + int(x) for x in share.tolist()]


def _diffuse(s: Setup, modes: Modes, total: int, strategy: Strategy, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """Draw `total` diffusion samples: -> q (total, D), parent mode index (total,)."""
    k = s.cfg.kjs
    counts = _allocate(modes.weight, total, k.even_share)
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


# ---------------------------------------------------------------- one tracking step


def _select(s: Setup, q: Tensor, cost: Tensor, prior_weight: Tensor, count: int) -> tuple[Tensor, Tensor]:
    """Distinct minima among polished hypotheses, the `count` heaviest first: -> indices (M,) and their
    normalised weights (M,). prior_weight (N,): what each inherits from the mode it came from (that mode's
    weight to the power `kjs.weight_memory`)."""
    keep = _distinct(s, q, cost)
    w = posterior_weights(cost[keep] - cost[keep].min(), prior_weight[keep], s.cfg.kjs.temperature)
    order = torch.argsort(w, descending=True)[:count]
    return keep[order], w[order] / w[order].sum()


def _distinct(s: Setup, q: Tensor, rank: Tensor) -> Tensor:
    """Indices of the distinct poses among q (N, D), the lowest `rank` (N,) of each group first: apart in 3D
    (a joint coordinate `kjs.distinct_mm` or more apart) or, with distinct_mm 0, in a dof (`kjs.distinct_deg`)."""
    k = s.cfg.kjs
    if k.distinct_mm > 0:
        return distinct_minima(s.problem.skeleton.forward_kinematics(q).flatten(-2), rank, k.distinct_mm / 1000)
    return distinct_minima(q, rank, math.radians(k.distinct_deg))


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
    _, order = torch.unique(_depth_orders(s, q), dim=0, return_inverse=True)
    earliest = torch.full_like(rank, rank.numel()).scatter_reduce(0, order, rank, "amin")
    return rank + rank.numel() * (rank != earliest[order])


def _merge(s: Setup, forward: Modes, backward: Modes, lead: int) -> Modes:
    """One frame's modes from two mixtures (the forward and the backward pass; or, inside the backward
    pass, its own modes and the forward pass's): the first mixture's mode `lead` first (after both passes:
    the best trajectory's), then taken from each in turn, heaviest first, distinct (`_distinct`), at most K, with
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
    keep = _distinct(s, both.q, rank.to(both.q.dtype))
    keep = keep[torch.argsort(rank[keep])][: s.cfg.kjs.modes]
    weight = both.weight[keep]
    return Modes(both.q[keep], weight / weight.sum(), both.cost[keep], both.chol[keep], both.velocity[keep])


def _modes(s: Setup, q: Tensor, cost: Tensor, hessian: Tensor, weight: Tensor, origin: Tensor) -> Modes:
    """Modes from selected hypotheses; origin (M, D): the previous-frame pose each came from."""
    return Modes(q=q, weight=weight, cost=cost, chol=_cholesky(s, hessian), velocity=q - origin)


def _step(
    s: Setup, t: int, modes: Modes, strategy: Strategy, gen: torch.Generator, orders: bool = False
) -> tuple[Modes, Tensor]:
    """Frame t-1's modes -> frame t's, and the flipped leaves kept per chain (C,) (see the module docstring).
    With `orders` the K kept are the heaviest of each depth order of the limbs before any order's second
    (`_orders_first`), else the K heaviest."""
    k = s.cfg.kjs
    obs = s.problem.observations
    predicted = modes.q + k.momentum * modes.velocity  # (K, D): the dynamics' prediction of each mode
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
    q, cost, _ = _polish(s, t, q, predicted[parent], k.polish_iterations, sigma[parent], tracking=True)
    prior = modes.weight**k.weight_memory  # (K,) how much of the past evidence each mode carries forward
    best, _ = _select(s, q, cost, prior[parent], 4 * k.modes)
    q, parent = q[best], parent[best]
    q, cost, hessian = _polish(s, t, q, predicted[parent], k.refine_iterations, sigma[parent], tracking=True)
    keep, w = _select(s, q, cost, prior[parent], 4 * k.modes if orders else k.modes)
    if orders and keep.numel():
        pick = torch.argsort(_orders_first(s, q[keep], torch.arange(keep.numel(), device=keep.device)))[: k.modes]
        keep, w = keep[pick], w[pick] / w[pick].sum()
    if keep.numel() == 0:  # every hypothesis diverged (non-finite cost): the dynamics carry the modes
        return modes._replace(q=predicted), counts
    return _modes(s, q[keep], cost[keep], hessian[keep], w, modes.q[parent[keep]]), counts


# ---------------------------------------------------------------- initialisation


def _init_keyframe(s: Setup) -> Tensor:
    return first_keyframe(s.problem, "kjs.init", s.lower, s.upper)[None]


def _start_prior(s: Setup, q: Tensor) -> tuple[Tensor, Tensor]:
    """The prior of a start without 3D input. Each angle the CMU pose prior names (`ptrack.pose_prior`)
    is held near real people's mean angle with `kjs.start_prior_scale` times their spread; any other
    angle near 0 with std `kjs.rest_sigma`; the root's position near where the rigid fit of the body put
    it (std 0.1 m: monocular depth is otherwise traded for limbs tilted in depth); its rotation free.
    q (N, D) -> mean (N, D), sigma (D,)."""
    sk, k = s.problem.skeleton, s.cfg.kjs
    root = s.root
    trans = torch.zeros_like(root)
    trans[[int(d) for d in sk.translation_dof if d >= 0]] = True
    mean, std, known = s.prior
    mean = torch.where(root, q, torch.where(known, mean, torch.zeros_like(mean)).expand_as(q))
    floor = math.radians(k.floor_deg)
    sigma = torch.where(known, k.start_prior_scale * std.clamp_min(floor), torch.full_like(std, k.rest_sigma))
    sigma = torch.where(root, torch.full_like(sigma, 1e3), sigma)
    sigma = torch.where(trans, torch.full_like(sigma, 0.1), sigma)
    return mean, sigma


def _root_starts(s: Setup, q: Tensor, yaws: int, tilts: tuple[float, ...]) -> Tensor:
    """Start poses for the rigid fit: q (D,) with its root turned to `yaws` headings about the world's up
    axis (+Y) and leaned by each of `tilts` (radians) about the root's other horizontal axis. A pose
    fitted from one heading keeps that heading's depth order of the torso (which shoulder and hip is
    nearer the camera), so every heading is tried. -> (S, D); q[None] when the root cannot rotate."""
    sk = s.problem.skeleton
    driven = [k for k in range(3) if sk.axis_dof[0, k] >= 0]
    if not driven:
        return q[None]
    world = sk.rest_rotation[0] @ sk.axes[0].T  # (3, 3): columns = the root's axes in the world
    up = max(driven, key=lambda k: abs(world[1, k]))
    side = [k for k in driven if k != up]
    starts = []
    for i in range(yaws):
        for tilt in tilts if side else (0.0,):
            x = q.clone()
            x[int(sk.axis_dof[0, up])] += 2 * math.pi * i / yaws * (1.0 if world[1, up] >= 0 else -1.0)
            if side:
                x[int(sk.axis_dof[0, side[-1]])] += tilt
            starts.append(x)
    return torch.stack(starts)


def _init_tree(s: Setup, t: int = 0) -> Tensor:
    """No 3D input: the rest pose in view under every heading, each fitted rigidly to frame t's 2D
    (root dofs only), then in every dof with the rest prior; the distinct fits (by cost, at most
    `kjs.init_fits`) are expanded by every flip combination of the chains. -> candidates (N, D)."""
    prob = s.problem
    sk, obs = prob.skeleton, prob.observations
    k = s.cfg.kjs
    rest = torch.clamp(rest_pose_in_view(prob, s.lower.dtype, t), s.lower, s.upper)
    q = project_to_limits(
        _root_starts(s, rest, k.init_yaws, (0.0, 0.5, -0.5)), s.lower, s.upper, s.angular, mode="reflect"
    )
    lo = torch.where(s.root, s.lower, q[0])
    hi = torch.where(s.root, s.upper, q[0])
    q, _ = levenberg_marquardt(
        objective_linearization(sk, _objective(s, t, None), obs.camera, prob.keypoints, True), q, lo, hi, max_iter=30
    )
    mean, sigma = _start_prior(s, q)
    q, cost, _ = _polish(s, t, q, mean, 30, sigma)
    # distinct in 3D (no joint 5 cm apart): headings 2 pi apart, or the two Euler triples of one
    # rotation, are one fit
    joints = sk.forward_kinematics(q)
    pick = distinct_minima(joints.flatten(-2), cost, 0.05, limit=k.init_fits)
    fits = q[pick]
    px, conf = joint_observations(prob.keypoints, obs.keypoints[t], obs.confidence[t], sk.num_joints)
    trees = interpretation_trees(s.chains, joints[pick], obs.camera, px, conf)
    prod = product(trees)
    results = [chain_ik(plan, fits, tree.positions, mode="project") for plan, tree in zip(s.plans, trees)]
    ik = product_ik(fits, results, prod)
    keep = ik.keep & prod.unique
    keep[:, 0] = False  # leaf 0 is the fit itself, kept below whatever its IK flags say
    return torch.cat([fits, ik.q[keep]])


def _first_modes(s: Setup, strategy: Strategy, t: int = 0) -> Modes:
    """The modes of a start: frame 0's keyframe (`kjs.init: keyframe`), or a tree start on frame t."""
    k = s.cfg.kjs
    if k.init == "keyframe":  # the user's 3D pose, held by a tight prior (0.01 rad / m): it is their word
        q = _init_keyframe(s)
        q, cost, hessian = _polish(s, 0, q, q, 20, 0.01)
    else:
        q = _init_tree(s, t)  # many candidates: polish all briefly, the 4K most promising to convergence
        mean, sigma = _start_prior(s, q)
        q, cost, _ = _polish(s, t, q, mean, k.polish_iterations, sigma)
        # "most promising" by the frame's own cost (`_evidence`), not with the start prior: flip combinations
        # that reproject alike differ mostly in that prior, which is per dof around real people's mean pose
        # and so would drop a raised arm (49_18) before it is ever refined; the K kept below still weigh it
        best, _ = _select(s, q, _evidence(s, t, q), torch.ones_like(cost), 4 * k.modes)
        q, cost, hessian = _polish(s, t, q[best], mean[best], 20, sigma)
    keep, w = _select(s, q, cost, torch.ones_like(cost), k.modes)
    if keep.numel() == 0:
        raise EstimationError(f"method {strategy.name!r}: no start pose with a finite cost on frame {t}")
    return _modes(s, q[keep], cost[keep], hessian[keep], w, q[keep])


def _backward_start(s: Setup, last: Modes, strategy: Strategy) -> Modes:
    """The backward pass's first modes: the forward pass's last ones, moving the other way, and after a
    tree start also a tree start on the last frame, taken in turn (`_merge`, the forward pass's heaviest
    first). The forward pass may have lost the true reading of the whole body from frame 0 on (49_18 at
    2 px); the last frame's own tree start gives the backward pass a second chance at it."""
    last = last._replace(velocity=-last.velocity)
    t = s.problem.observations.num_frames - 1
    if s.cfg.kjs.init != "tree" or not bool((s.problem.observations.confidence[t] > 0).any()):
        return last
    return _merge(s, last, _first_modes(s, strategy, t), 0)


def _feed(s: Setup, backward: Modes, forward: Modes) -> Modes:
    """The backward pass's modes of frame t+1 joined by the forward pass's (`_merge`, its own heaviest
    first; the forward modes' velocity turned round), before the step to frame t. A limb crossing the
    image plane is read on the wrong side by both passes when each arrives from its own side of the
    crossing, lagging behind the motion (02_01, 1 px: the left thigh over frames 9-18). The forward pass finds
    the true side a few frames after the crossing, in a light mode, and carried backwards from there
    that reading stays on its side back to the crossing. Only after a keyframe start: after a tree start
    the forward pass may hold a wrong reading of the whole body, and fed to the backward pass it crowded
    out the last frame's own tree start (dev clips at 2 px, five seeds: best-of-K 32.2 -> 35.9 mm, 49_18
    38.0 -> 67.1)."""
    return _merge(s, backward, forward._replace(velocity=-forward.velocity), int(backward.weight.argmax()))


# ---------------------------------------------------------------- the estimator


def _evidence(s: Setup, t: int | Tensor, q: Tensor, joints: Tensor | None = None) -> Tensor:
    """Frame t's own cost of poses q (K, D) (joints (K, J, 3): their forward kinematics, if already at
    hand) -> (K,): robust reprojection, limits, collision and the pose
    prior, without the dynamics term. It is the unary term of the best-trajectory Viterbi pass, whose
    pairwise term is the dynamics: a mode's tracking cost and weight already hold the dynamics around the
    mode it came from (and, through the weights, every earlier frame), so using them there would count
    the dynamics twice and tie the best trajectory to the filter's earlier choices."""
    prob = s.problem
    sk = prob.skeleton
    with torch.no_grad():
        joints = sk.forward_kinematics(q) if joints is None else joints
        ev = pose_eval_from_joints(prob.observations.camera, prob.keypoints, q, joints)
        return _objective(s, t, None, tracking=True)(ev).total


def _pad(modes: Modes, k: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Modes (M) -> (K, D) q, (K,) weights, (K,) costs, (K, D, D) covariance factors, padding with copies
    of the best at weight 0."""
    m = modes.q.shape[0]
    if m >= k:
        return modes.q, modes.weight, modes.cost, modes.chol
    fill = k - m
    return (
        torch.cat([modes.q, modes.q[:1].expand(fill, -1)]),
        torch.cat([modes.weight, modes.weight.new_zeros(fill)]),
        torch.cat([modes.cost, modes.cost[:1].expand(fill)]),
        torch.cat([modes.chol, modes.chol[:1].expand(fill, -1, -1)]),
    )


def principal_directions(sk, q: Tensor, chol: Tensor, scale: float) -> Tensor:
    """Each mode's most uncertain direction, as 3D joint displacements: the top eigenvector of its
    covariance (chol chol^T / scale: the inverse Gauss-Newton Hessian, regularised, without the
    sampling scale), one standard deviation long, through forward kinematics. The sign is fixed so
    that the eigenvector's largest entry is positive. q (..., D), chol (..., D, D) -> (..., J, 3) metres."""
    cov = chol @ chol.transpose(-1, -2) / scale
    val, vec = torch.linalg.eigh(cov)
    v = vec[..., -1]  # (..., D)
    sign = torch.sign(v.gather(-1, v.abs().argmax(-1, keepdim=True)))
    dq = v * sign * val[..., -1:].clamp_min(0).sqrt()
    return sk.forward_kinematics(q + dq) - sk.forward_kinematics(q)


def _lattice(s: Setup, per_frame: list[Modes]) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Each frame's modes padded to K -> q (T, K, D), weights (T, K), costs (T, K), covariance factors
    (T, K, D, D) and joint positions (T, K, J, 3)."""
    padded = [_pad(m, s.cfg.kjs.modes) for m in per_frame]
    hq, hw, hc, hl = (torch.stack(x) for x in zip(*padded))
    with torch.no_grad():
        return hq, hw, hc, hl, s.problem.skeleton.forward_kinematics(hq)


def _best_path(s: Setup, hq: Tensor, hw: Tensor, joints: Tensor) -> tuple[Tensor, Tensor]:
    """Viterbi through the lattice q (T, K, D), weights (T, K), joints (T, K, J, 3): each mode's own frame
    cost (`_evidence`) plus a velocity prior between consecutive choices (`kjs.viterbi_space`); padding
    (weight 0) is never chosen. -> mode index per frame (T,), and the path's cost ()."""
    k = s.cfg.kjs
    T, K, D = hq.shape
    rows = torch.arange(T, device=hq.device).repeat_interleave(K)  # every mode with its own frame's 2D
    unary = _evidence(s, rows, hq.reshape(-1, D), joints.flatten(0, 1)).reshape(T, K)
    with torch.no_grad():
        if k.viterbi_space == "joints":  # the body's motion in metres: every joint relative to the root
            feats, sigma = (joints - joints[..., :1, :]).flatten(-2), k.viterbi_sigma_m
        else:
            feats, sigma = hq, k.viterbi_sigma
        return viterbi_with_cost(torch.where(hw > 0, unary, torch.full_like(unary, math.inf)), feats, sigma)


#: after a tree start, the passes' best trajectories whose bodies face directions this far apart (mean over
#: the frames, degrees) hold two readings of the whole body, and the cheaper one is taken (`_lead_pass`)
HEADING_SPLIT_DEG = 30.0


def _hips(s: Setup) -> tuple[int, int] | None:
    """The skeleton joints of the keypoints "l_hip" and "r_hip", or None when the keypoint set lacks one."""
    kp = s.problem.keypoints
    if "l_hip" not in kp.names or "r_hip" not in kp.names:
        return None
    return kp.joints[kp.names.index("l_hip")], kp.joints[kp.names.index("r_hip")]


def _heading(joints: Tensor, hips: tuple[int, int]) -> Tensor:
    """The direction of the hip line (left hip minus right hip, `_hips`) about the world's up axis (+Y):
    joints (T, J, 3) -> (T,) radians."""
    line = joints[:, hips[0]] - joints[:, hips[1]]
    return torch.atan2(line[:, 2], line[:, 0])


def _lead_pass(s: Setup, path: Tensor, cost: Tensor, joints: Tensor, backward: list[Modes]) -> tuple[bool, Tensor]:
    """After a tree start: does the backward pass's best trajectory replace the forward pass's? path (T,),
    cost () and joints (T, K, J, 3): the forward pass's best trajectory, its cost and its lattice's joints.
    -> (backward leads, the leading path).

    Each pass starts from its own tree start (frame 0, the last frame), and either can hold a wrong reading
    of the whole body throughout (49_18 and 49_19 at 2 px: the forward pass's body turned 48-58° from the
    truth, 240-260 mm MPJPE; the backward pass's 2-4°). Where the two trajectories face apart by more than
    `HEADING_SPLIT_DEG` on average the cheaper (frame costs plus the velocity prior, what Viterbi
    minimises) is taken: it was the right one on every such run measured. Where they face alike and differ
    limb by limb the cost does not tell them apart (the backward one was the cheaper on most held-out runs
    and worse in MPJPE on most of those), so the forward pass's stays (docs/results.md). Without hip
    keypoints the forward pass's stays."""
    hips = _hips(s)
    if hips is None:
        return False, path
    bq, bw, _, _, bj = _lattice(s, backward)
    back_path, back_cost = _best_path(s, bq, bw, bj)
    frames = torch.arange(path.shape[0], device=path.device)
    apart = _heading(joints[frames, path], hips) - _heading(bj[frames, back_path], hips)
    apart = torch.remainder(apart + math.pi, 2 * math.pi) - math.pi
    if float(apart.abs().mean()) > math.radians(HEADING_SPLIT_DEG) and bool(back_cost < cost):
        return True, back_path
    return False, path


#: Levenberg-Marquardt iterations of each graft in `_recombine` (a mode's chain on the best trajectory's pose)
#: and of the recombined pose: the chain moves little, the rest of the body settles around it
GRAFT_ITERATIONS, RECOMBINED_ITERATIONS = 3, 5
#: poses of many frames polished in one batched call (`_polish_rows`): one call per
#: frame costs a linearisation's overhead per frame; on the bundled clip 320 rows a call measured faster than
#: 1280 or 5920 (`_recombine` 1.5 s against 1.8 and 2.8 s), and memory stays bounded on long clips
POLISH_CHUNK = 320


def _polish_rows(
    s: Setup, t: Tensor, q: Tensor, mean: Tensor, iterations: int, sigma: float | Tensor, tracking: bool = False
) -> tuple[Tensor, Tensor, Tensor]:
    """`_polish` of poses from many frames, in calls of `POLISH_CHUNK` rows: t (N,) each pose's frame, q and
    mean (N, D), sigma a float, (D,) or (N, D) -> q (N, D), cost (N,), hessian (N, D, D)."""
    out = []
    for rows in torch.split(torch.arange(q.shape[0], device=q.device), POLISH_CHUNK):
        sig = sigma[rows] if isinstance(sigma, Tensor) and sigma.ndim == 2 else sigma
        out.append(_polish(s, t[rows], q[rows], mean[rows], iterations, sig, tracking))
    q_out, cost, hessian = (torch.cat(x) for x in zip(*out))
    return q_out, cost, hessian


def _recombine(
    s: Setup, hq: Tensor, hw: Tensor, hc: Tensor, hl: Tensor, joints: Tensor, path: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """One more hypothesis per frame: the best trajectory's pose with each chain's reading chosen on its own.

    The modes hold the chains' readings (which way each limb points in depth) in combinations: one mode
    may have the left arm right and the right leg wrong, another the reverse, and no mode both (49_18 at
    2 px after a tree start: the best trajectory's mode 99 mm off, each of two others right in one limb).
    The 2D cannot tell the combinations apart, but each chain's own reading can be followed in time. It runs
    after the smoother (`_smooth`), which then does not link the best trajectory's modes to it. For
    every frame t, chain c and mode m, the chain's dofs of mode m are grafted onto the best trajectory's
    pose and polished briefly around that graft; each chain then gets its own Viterbi pass over the modes:
    the graft's frame cost (`_evidence`) plus a velocity prior on the graft's joints relative to the root
    (std `kjs.recombine_sigma_m` per frame). The chosen readings of all chains on the best trajectory's pose,
    polished, replace frame t's padding or its lightest mode other than the best trajectory's, with that
    slot's weight (the lightest weight for padding), unless they are a mode already (`_distinct`). The
    best trajectory keeps its modes. Without chains (css and ss after a keyframe start) or with K = 1 nothing
    changes. hq (T, K, D), hw (T, K) (0: padding), hc (T, K), hl (T, K, D, D), joints (T, K, J, 3), path (T,)
    -> hq, hw, hc, hl, joints."""
    k = s.cfg.kjs
    sk = s.problem.skeleton
    T, K, D = hq.shape
    C = len(s.chains)
    if C == 0 or K < 2:
        return hq, hw, hc, hl, joints
    frames = torch.arange(T, device=hq.device)
    lead = hq[frames, path]  # (T, D)
    graft = torch.where(s.chain_dofs[None, :, None], hq[:, None], lead[:, None, None]).reshape(-1, D)  # (T C K, D)
    rows = frames.repeat_interleave(C * K)  # each graft with its own frame's 2D
    graft, _, _ = _polish_rows(s, rows, graft, graft, GRAFT_ITERATIONS, s.dynamics_sigma)
    with torch.no_grad():
        j = sk.forward_kinematics(graft)
    cost_tck = torch.where(hw[:, None] > 0, _evidence(s, rows, graft, j).reshape(T, C, K), math.inf)
    feats_tck = (j - j[:, :1]).reshape(T, C, K, -1)  # the grafts' joints relative to the root
    choice = torch.stack([viterbi_with_cost(cost_tck[:, c], feats_tck[:, c], k.recombine_sigma_m)[0] for c in range(C)])
    new = (choice != path[None]).any(0)  # (T,): some chain takes another mode's reading
    if not bool(new.any()):
        return hq, hw, hc, hl, joints
    picked = hq[frames[:, None], choice.T]  # (T, C, D)
    q = lead
    for c in range(C):
        q = torch.where(s.chain_dofs[c], picked[:, c], q)
    todo = frames[new]
    q, cost, hessian = _polish_rows(s, todo, q[new], q[new], RECOMBINED_ITERATIONS, s.dynamics_sigma)
    chol = _cholesky(s, hessian)
    with torch.no_grad():
        q_joints = sk.forward_kinematics(q)
    hq, hw, hc, hl, joints = hq.clone(), hw.clone(), hc.clone(), hl.clone(), joints.clone()
    for i, t in enumerate(todo.tolist()):
        real = hw[t] > 0
        pool = torch.cat([hq[t][real], q[i : i + 1]])
        rank = torch.arange(pool.shape[0], dtype=hq.dtype, device=hq.device)
        if int(_distinct(s, pool, rank).max()) < pool.shape[0] - 1:
            continue  # the recombined pose is one of the modes
        order = torch.where(real, hw[t], torch.full_like(hw[t], -1.0))
        order[path[t]] = math.inf
        slot = int(order.argmin())
        hq[t, slot], hc[t, slot], hl[t, slot], joints[t, slot] = q[i], cost[i], chol[i], q_joints[i]
        if not bool(real[slot]):  # padding (weight 0) takes the lightest mode's weight
            hw[t, slot] = hw[t][real].min()
            hw[t] = hw[t] / hw[t].sum()
    return hq, hw, hc, hl, joints


#: Levenberg-Marquardt iterations of each hypothesis in a smoothing sweep (`_smooth`): it starts at a
#: minimum of its own frame's objective and moves only as far as its neighbours pull it
SMOOTH_ITERATIONS = 5


def _smooth(
    s: Setup, hq: Tensor, hw: Tensor, hc: Tensor, hl: Tensor, joints: Tensor
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """`kjs.smooth_sweeps` sweeps of a smoother over the finished hypothesis lattice. Each tracked mode holds
    the evidence of its own frame and, through the dynamics, of the frames before (a filter): its depth
    jitters from frame to frame wherever the 2D leaves it loose. In a sweep each hypothesis of frame t is
    linked to the nearest hypothesis of frames t-1 and t+1 (mean distance of the joints relative to the root
    under `kjs.smooth_link_m`; none where the other frame holds no such pose, e.g. a limb's other branch)
    and polished again on frame t's objective with the tracking prior around the mean of its linked
    neighbours, std `kjs.smooth_scale` times the dynamics' (times sqrt 2 with one neighbour). A
    hypothesis with no linked neighbour, and padding, keep their pose. Each sweep uses the poses of the
    sweep before (Jacobi). hq (T, K, D), hw (T, K) weights (0: padding), hc (T, K) costs, hl (T, K, D, D)
    covariance factors, joints (T, K, J, 3) their forward kinematics -> hq, hc, hl, joints (the smoothed
    poses, their objective, covariance and joints)."""
    k = s.cfg.kjs
    sk = s.problem.skeleton
    T, K, D = hq.shape
    base = torch.as_tensor(s.dynamics_sigma, dtype=hq.dtype, device=hq.device).expand(D) * k.smooth_scale
    frames = torch.arange(T, device=hq.device)[:, None].expand(T, K)
    for _ in range(k.smooth_sweeps):
        rel = joints - joints[..., :1, :]  # (T, K, J, 3)
        pull = torch.zeros_like(hq)  # (T, K, D): sum of the wrapped steps to the linked neighbours
        count = torch.zeros(T, K, 1, dtype=hq.dtype, device=hq.device)
        for here, there in ((slice(1, None), slice(None, -1)), (slice(None, -1), slice(1, None))):  # t-1, t+1
            gap = (rel[here][:, :, None] - rel[there][:, None]).norm(dim=-1).mean(-1)  # (T-1, K, K)
            gap = torch.where(hw[there][:, None] > 0, gap, math.inf)
            near, j = gap.min(-1)  # (T-1, K)
            linked = (near < k.smooth_link_m).to(hq.dtype)[..., None]
            neighbour = torch.gather(hq[there], 1, j[..., None].expand(-1, -1, D))
            pull[here] += linked * wrapped_difference(neighbour - hq[here], s.angular)
            count[here] += linked
        move = (hw > 0) & (count[..., 0] > 0)  # (T, K)
        if not bool(move.any()):
            break
        n = count[move]  # (M, 1): 1 or 2 linked neighbours
        q, cost, hessian = _polish_rows(
            s, frames[move], hq[move], hq[move] + pull[move] / n, SMOOTH_ITERATIONS, base * torch.sqrt(2 / n), True
        )
        hq, hc, hl = hq.clone(), hc.clone(), hl.clone()
        hq[move], hc[move], hl[move] = q, cost, _cholesky(s, hessian)
        with torch.no_grad():
            joints = sk.forward_kinematics(hq)
    return hq, hc, hl, joints


def track(
    problem: Problem,
    cfg,
    generator: torch.Generator,
    strategy: Strategy,
    progress: Callable[[Iterable], Iterable] = lambda x: x,
) -> Estimate:
    """Run the tracker `strategy` over every frame of `problem` (see the module docstring), on one
    intra-op thread (`ptrack.banded.one_thread`): its products are small batched ones, and
    `scripts/bench_kjs.py` measured 6.1 fps on one thread and on two on an idle 2-core machine, but
    0.7 fps on two threads when another job held a core.

    With the Levenberg-Marquardt polisher nothing here needs autograd (the Jacobians are closed form), so
    the tracker runs in `torch.inference_mode`, which spares torch the view and version bookkeeping of each
    linearisation's ~650 small operations: the same results bit for bit, and `scripts/bench_kjs.py` 27.6 ->
    25.3 s (paired runs). The result's tensors are copied out of inference mode, so callers may use them
    freely; the caches it fills (FK plan, Jacobian and IK tables) are built outside it."""
    with one_thread(), torch.inference_mode(cfg.kjs.polisher == "lm"):  # lbfgs differentiates the cost
        est = _track(problem, cfg, generator, strategy, progress)
    return _ordinary(est)


def _ordinary(est: Estimate) -> Estimate:
    """Copies of an Estimate's tensors (also those in its dict fields) made outside inference mode:
    inference tensors cannot be modified in place or saved for backward outside it."""

    def copy(x):
        if isinstance(x, Tensor):
            return x.clone()
        if isinstance(x, dict):
            return {k: copy(v) for k, v in x.items()}
        return x

    return est._replace(**{k: copy(v) for k, v in est._asdict().items()})


def _track(
    problem: Problem, cfg, generator: torch.Generator, strategy: Strategy, progress: Callable[[Iterable], Iterable]
) -> Estimate:
    s = _setup(problem, cfg, strategy)
    sk, obs = problem.skeleton, problem.observations
    k = cfg.kjs
    steps = range(obs.num_frames)
    backward = k.backward_pass == "always" or (k.backward_pass == "tree" and k.init == "tree")
    schedule = [(t, False) for t in steps] + ([(t, True) for t in reversed(steps)] if backward else [])
    passes: list[list[tuple[Modes, Tensor]]] = [[], []]  # forward, backward (in reverse time order)
    modes = None
    for t, back in progress(schedule):
        if modes is None:
            modes, counts = _first_modes(s, strategy), torch.zeros(len(s.chains), dtype=torch.long)
        elif back and not passes[1]:  # the forward pass's last modes (and a tree start there: _backward_start)
            modes, counts = _backward_start(s, modes, strategy), torch.zeros_like(counts)
        elif back and k.init == "keyframe":  # from its own modes of frame t+1 and the forward pass's (`_feed`)
            modes, counts = _step(s, t, _feed(s, modes, passes[0][t + 1][0]), strategy, generator, orders=True)
        else:
            modes, counts = _step(s, t, modes, strategy, generator)
        passes[back].append((modes, counts.to(modes.q.device)))
    forward = [m for m, _ in passes[0]]
    jumps = [c for _, c in passes[0]]
    hq, hw, hc, hl, hyp_joints = _lattice(s, forward)
    path, cost = _best_path(s, hq, hw, hyp_joints)
    if backward:  # the hypotheses of both passes, the best trajectory's mode first in each frame (`_merge`)
        lead, other = forward, [m for m, _ in reversed(passes[1])]
        if k.init == "tree":
            swap, path = _lead_pass(s, path, cost, hyp_joints, other)
            lead, other = (other, lead) if swap else (lead, other)
        merged = [_merge(s, a, b, int(p)) for a, b, p in zip(lead, other, path)]
        hq, hw, hc, hl, hyp_joints = _lattice(s, merged)
        path = torch.zeros_like(path)
        jumps = [a + b for a, (_, b) in zip(jumps, reversed(passes[1]))]
    if k.smooth_sweeps > 0:  # every frame's hypotheses smoothed in time (`_smooth`); the choice of mode kept
        hq, hc, hl, hyp_joints = _smooth(s, hq, hw, hc, hl, hyp_joints)
    if k.recombine:  # each chain's reading chosen on its own, on the best trajectory's pose (`_recombine`); after
        # the smoother, so that the best trajectory is the same with it and without
        hq, hw, hc, hl, hyp_joints = _recombine(s, hq, hw, hc, hl, hyp_joints, path)
    with torch.no_grad():
        frames = torch.arange(hq.shape[0], device=hq.device)
        joints = hyp_joints[frames, path]
        directions = principal_directions(sk, hq, hl, k.scale)
    q = hq[frames, path]
    return Estimate(
        q=q,
        joints=joints,
        cost=hc[frames, path],
        terms={"mode_cost": hc[frames, path]},
        hypotheses=hyp_joints,
        hypothesis_weights=hw,
        hypothesis_costs=hc,
        hypothesis_directions=directions,
        jumps={c.name: x for c, x in zip(s.chains, torch.stack(jumps).T)} if strategy.jumps else None,
    )


def estimate_kjs(problem, cfg, generator, progress=lambda x: x) -> Estimate:
    """`method: kjs`: kinematic jump sampling with CSS diffusion."""
    return track(problem, cfg, generator, KJS, progress)


def estimate_css(problem, cfg, generator, progress=lambda x: x) -> Estimate:
    """`method: css`: covariance scaled sampling only, same hypothesis budget."""
    return track(problem, cfg, generator, CSS, progress)


def estimate_ss(problem, cfg, generator, progress=lambda x: x) -> Estimate:
    """`method: ss`: spherical sampling only, same hypothesis budget and core volume."""
    return track(problem, cfg, generator, SS, progress)
