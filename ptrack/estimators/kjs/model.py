"""What the kjs, css and ss trackers hold fixed over a sequence (`Setup`), each frame's objective and its
batched polishing, and the choice of distinct, weighted minima among polished hypotheses.

Shapes: N hypotheses, D dofs, K modes (`kjs.modes`)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ptrack.body.pose_mixture import PoseMixture, pose_mixture
from ptrack.body.pose_prior import held_sigma, pose_prior, smoothing_prior
from ptrack.costs import (
    CostTerm,
    HeavyTailedPrior,
    JointLimits,
    Objective,
    PosePrior,
    Reprojection,
    SelfIntersection,
    SwapReprojection,
)
from ptrack.errors import InputError
from ptrack.estimators.kjs.config import KjsRunConfig
from ptrack.hypotheses.ik import ChainIK, ClosedFormUnavailable, ik_plan
from ptrack.hypotheses.jumps import Chain, check_independent, default_chains
from ptrack.hypotheses.mixture import Modes, distinct_minima, posterior_weights
from ptrack.hypotheses.samplers import scaled_covariance
from ptrack.optim.jacobians import objective_linearization
from ptrack.optim.solvers import lbfgs, levenberg_marquardt
from ptrack.problem import Problem, first_keyframe, pose_eval_from_joints
from ptrack.threads import in_two_processes, parallel_processes


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
    cfg: KjsRunConfig  # the run's config (a `ptrack.pipeline.config.RunConfig`)
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
    mixture: PoseMixture | None = None  # the CMU pose mixture that ranks modes (`kjs.pose_mixture_weight` > 0)
    partners: Tensor | None = None  # (K,) each keypoint's left/right partner, with `costs.swap_cost` > 0


def make_setup(problem: Problem, cfg: KjsRunConfig, strategy: Strategy) -> Setup:
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
    prior_sigma = held_sigma(std, known, math.radians(k.floor_deg))
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
        _mixture(sk, k.pose_mixture_weight, dtype, device),
        _partners(problem, cfg.costs.swap_cost),
    )


def _partners(problem: Problem, swap_cost: float | None) -> Tensor | None:
    """(K,) each keypoint's left/right partner (itself when unpaired) when `costs.swap_cost` > 0 and the keypoint
    set pairs any, else None (also for null, which the pipeline resolves before a run: `run.with_swap_cost`)."""
    if not swap_cost or not problem.keypoints.swap_pairs:
        return None
    return problem.keypoints.mirror_index(problem.observations.keypoints.device)


def _mixture(sk, weight: float, dtype: torch.dtype, device: torch.device) -> PoseMixture | None:
    """The CMU pose mixture on `sk`'s dofs when `kjs.pose_mixture_weight` > 0, else None; an InputError for a
    skeleton that names none of its dofs."""
    if weight == 0:
        return None
    mix = pose_mixture(sk, dtype, device)
    if mix is None:
        raise InputError("config key 'kjs.pose_mixture_weight' needs a skeleton with CMU dof names (lfemur.rx, ...)")
    return mix


def _dynamics_sigma(problem: Problem, k, dtype: torch.dtype, device: torch.device) -> float | Tensor:
    """The dynamics' velocity std per frame: with `kjs.dynamics` null the float `kjs.prior_sigma` for every
    dof; else a (D,) tensor: each CMU dof's RMS velocity in real motion from the table `kjs.dynamics`
    (`ptrack.body.pose_prior.SMOOTHING_TABLES`; the default "cmu-train" was fitted to clips of subjects with no
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


def frame_objective(
    s: Setup, t: int | Tensor, mean: Tensor | None, sigma: float | Tensor | None = None, tracking: bool = False
) -> Objective:
    """Robust reprojection on frame t + limits + collision (+ the floor contact when the problem has a floor)
    (+ the prior around `mean` (N, D), std `sigma`,
    by default the dynamics' `kjs.prior_sigma`; + with `tracking`, the CMU pose prior weighted by
    `kjs.pose_prior_weight`). t: one frame for every pose, or (N,) frame indices, one per pose."""
    cc, k = s.cfg.costs, s.cfg.kjs
    obs = s.problem.observations
    observed, confidence, per_problem = obs.keypoints[t], obs.confidence[t], isinstance(t, Tensor)
    reprojection: Reprojection
    if s.partners is not None:  # the detector's mirrored labels read too, at `costs.swap_cost`
        assert cc.swap_cost  # `_partners`: a positive price
        reprojection = SwapReprojection(
            observed,
            confidence,
            sigma_px=cc.sigma_px,
            loss=cc.loss,
            scale=cc.robust_scale,
            per_problem=per_problem,
            partners=s.partners,
            swap_cost=cc.swap_cost,
        )
    else:
        reprojection = Reprojection(
            observed, confidence, sigma_px=cc.sigma_px, loss=cc.loss, scale=cc.robust_scale, per_problem=per_problem
        )
    terms: dict[str, CostTerm] = {
        "reprojection": reprojection,
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
    floor = s.problem.floor
    if floor is not None and cc.floor_weight > 0:
        terms["floor"] = floor.term(cc.floor_sigma_m)
        weights["floor"] = cc.floor_weight
    if tracking and k.pose_prior_weight > 0:
        terms["pose_prior"] = PosePrior(s.prior[0], s.prior_sigma)
        weights["pose_prior"] = k.pose_prior_weight
    return Objective(terms, weights)


def polish(
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
    objective = frame_objective(s, t, mean, sigma, tracking)
    linearize = objective_linearization(sk, objective, cam, kps, fold=True)
    if s.cfg.kjs.polisher == "lbfgs" and iterations > 0:

        def energy(x: Tensor) -> Tensor:
            return objective(pose_eval_from_joints(cam, kps, x, sk.forward_kinematics(x))).total

        q, _ = lbfgs(energy, q, s.lower, s.upper, max_iter=iterations)
        iterations = 1  # one Gauss-Newton pass for the Hessian and the cost
    q, info = levenberg_marquardt(linearize, q, s.lower, s.upper, max_iter=max(iterations, 1), tol=1e-6)
    return q, info.cost, info.hessian


#: the widest sampling std of a direction, after scaling: half a turn (radians; metres for the root's position).
#: Only directions the frame's Hessian hardly constrains reach it; a 30-degree cap (`kjs.ceiling_deg` until
#: 2026-11-29) measured the same within the seed spread on the held-out and the dev clips (docs/results.md).
WIDEST_STD = math.pi


def mode_cholesky(s: Setup, hessian: Tensor) -> Tensor:
    """A mode's CSS factor: `kjs.scale` times the inverse Hessian (D, D), each direction's std between
    `kjs.floor_deg` and `WIDEST_STD` after scaling -> the Cholesky factor (D, D)."""
    k = s.cfg.kjs
    return scaled_covariance(
        hessian,
        k.scale,
        max_std=WIDEST_STD / math.sqrt(k.scale),
        min_std=math.radians(k.floor_deg) / math.sqrt(k.scale),
    ).chol


# ---------------------------------------------------------------- distinct minima, their weights, the modes


def select_modes(s: Setup, q: Tensor, cost: Tensor, log_prior: Tensor, count: int) -> tuple[Tensor, Tensor]:
    """Distinct minima among polished hypotheses (N), the `count` heaviest first: -> indices (M,) and their
    normalised weights (M,) ∝ exp(log_prior - cost / `kjs.temperature`). log_prior (N,): each hypothesis's prior
    weight, logarithm (`prior_weights`)."""
    keep = distinct_poses(s, q, cost)
    w = posterior_weights(cost[keep] - cost[keep].min(), log_prior[keep], s.cfg.kjs.temperature)
    order = torch.argsort(w, descending=True)[:count]
    return keep[order], w[order] / w[order].sum()


def distinct_poses(s: Setup, q: Tensor, rank: Tensor) -> Tensor:
    """Indices of the distinct poses among q (N, D), the lowest `rank` (N,) of each group first: apart in 3D
    (a joint coordinate `kjs.distinct_mm` or more apart) or, with distinct_mm 0, in a dof (`kjs.distinct_deg`)."""
    k = s.cfg.kjs
    if k.distinct_mm > 0:
        return distinct_minima(s.problem.skeleton.forward_kinematics(q).flatten(-2), rank, k.distinct_mm / 1000)
    return distinct_minima(q, rank, math.radians(k.distinct_deg))


def make_modes(s: Setup, q: Tensor, cost: Tensor, hessian: Tensor, weight: Tensor, origin: Tensor) -> Modes:
    """Modes from selected hypotheses; origin (M, D): the previous-frame pose each came from."""
    return Modes(q=q, weight=weight, cost=cost, chol=mode_cholesky(s, hessian), velocity=q - origin)


# ---------------------------------------------------------------- a frame's own cost; many frames at once


def frame_evidence(s: Setup, t: int | Tensor, q: Tensor, joints: Tensor | None = None) -> Tensor:
    """Frame t's own cost of poses q (K, D) (joints (K, J, 3): their forward kinematics, if already at
    hand) -> (K,): robust reprojection, limits, collision, the floor, the pose prior and, with
    `kjs.pose_mixture_weight` > 0, the weighted negative log-density of the CMU pose mixture
    (`ptrack.body.pose_mixture`), without the dynamics term. It is the unary term of the best-trajectory
    Viterbi pass, whose pairwise term is the dynamics: a mode's tracking cost and weight already hold the
    dynamics around the mode it came from (and, through the weights, every earlier frame), so using them
    there would count the dynamics twice and tie the best trajectory to the filter's earlier choices."""
    prob = s.problem
    sk = prob.skeleton
    with torch.no_grad():
        joints = sk.forward_kinematics(q) if joints is None else joints
        ev = pose_eval_from_joints(prob.observations.camera, prob.keypoints, q, joints)
        cost = frame_objective(s, t, None, tracking=True)(ev).total
        if s.mixture is not None:
            cost = cost + s.cfg.kjs.pose_mixture_weight * s.mixture.nll(q)
        return cost


#: the std (radians, metres) of the prior that holds frame 0's modes to the user's keyframe (`kjs.init: keyframe`):
#: the 3D pose is their word
KEYFRAME_SIGMA = 0.01


def keyframe_cost(s: Setup, q: Tensor) -> Tensor:
    """How far poses q (N, D) of frame 0 lie from the user's keyframe, as the start's prior holds them (std
    `KEYFRAME_SIGMA`; `ptrack.problem.first_keyframe`) -> (N,); zeros after a tree start (no 3D input)."""
    if s.cfg.kjs.init != "keyframe":
        return q.new_zeros(q.shape[0])
    key = first_keyframe(s.problem, "kjs.init", s.lower, s.upper)
    return 0.5 * ((q - key) / KEYFRAME_SIGMA).square().sum(-1)


#: poses of many frames polished in one batched call (`polish_rows`): one call per
#: frame costs a linearisation's overhead per frame; on the bundled clip 320 rows a call measured faster than
#: 1280 or 5920 (`recombine` 1.5 s against 1.8 and 2.8 s), and memory stays bounded on long clips
POLISH_CHUNK = 320
#: `polish_rows` splits more rows than this into an even number of calls (at most `POLISH_CHUNK` rows each), so
#: that two processes can take half each; fewer go in one call (a second call's overhead would outweigh it)
SPLIT_ROWS = 64


def polish_chunks(n: int) -> list[Tensor]:
    """The calls `polish_rows` makes for n rows: (n,) split into consecutive chunks of sizes differing by at most
    one; one chunk up to `SPLIT_ROWS` rows, else an even number of them, each at most `POLISH_CHUNK`. The chunks
    depend on n alone, not on how many processes run them, so the result is the same either way."""
    count = 1 if n <= SPLIT_ROWS else 2 * math.ceil(n / (2 * POLISH_CHUNK))
    return list(torch.tensor_split(torch.arange(n), count))


def polish_rows(
    s: Setup, t: Tensor, q: Tensor, mean: Tensor, iterations: int, sigma: float | Tensor, tracking: bool = False
) -> tuple[Tensor, Tensor, Tensor]:
    """`polish` of poses from many frames, in the calls `polish_chunks` makes: t (N,) each pose's frame, q and
    mean (N, D), sigma a float, (D,) or (N, D) -> q (N, D), cost (N,), hessian (N, D, D). With two or more
    calls and a thread budget of 2 or more (`ptrack.threads.parallel_processes`), the second half of the calls
    runs at once in a second process (`in_two_processes`), with the same result bit for bit."""

    def run(chunks: list[Tensor]) -> list[tuple[Tensor, Tensor, Tensor]]:
        out = []
        for rows in chunks:
            rows = rows.to(q.device)
            sig = sigma[rows] if isinstance(sigma, Tensor) and sigma.ndim == 2 else sigma
            out.append(polish(s, t[rows], q[rows], mean[rows], iterations, sig, tracking))
        return out

    chunks = polish_chunks(q.shape[0])
    half = len(chunks) // 2
    if half and parallel_processes(q.device):
        later, first = in_two_processes(lambda: run(chunks[half:]), lambda: run(chunks[:half]))
        parts = first + later
    else:
        parts = run(chunks)
    q_out, cost, hessian = (torch.cat(x) for x in zip(*parts))
    return q_out, cost, hessian
