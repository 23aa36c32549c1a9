"""What the batch solution leaves uncertain: `joint_std` from the marginal covariances of the Gauss-Newton
Hessian (the Laplace approximation), and the limbs' depth-flip branches (`flip_posterior`, in the posterior of
`ptrack.hypotheses.branches`), which add to it and whose lowest one restarts the solve (`lower_branch`);
`calibrate_std` widens the result by the calibration fitted on the dev clips (`ptrack/data/
batch_std_calibration.json`, made by `scripts/make_std_calibration.py`), partly in proportion to each joint's
travel from its nearest keyframe (`keyframe_travel`)."""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
import math
from typing import NamedTuple

import torch
from torch import Tensor

from ptrack.errors import InputError
from ptrack.estimators.batch.config import BatchMethodConfig
from ptrack.estimators.batch.objective import Trajectory, evaluate, total_energy
from ptrack.estimators.batch.solve import solve_trajectory
from ptrack.hypotheses.branches import SAME_M, BranchPosterior, branch_posterior, relax_branches
from ptrack.hypotheses.ik import ik_plan
from ptrack.hypotheses.jumps import check_independent, default_chains
from ptrack.optim.banded import BlockBanded, factorize, marginal_blocks
from ptrack.optim.jacobians import joint_jacobian
from ptrack.package_data import data_file

log = logging.getLogger(__name__)


def joint_std(obj: Trajectory, q: Tensor, hessian: BlockBanded, branches: BranchPosterior | None = None) -> Tensor:
    """Per-joint 3D standard deviation from the Gauss-Newton Hessian at the solution.

    q (B, T, D), hessian (diagonal (B, T, D, D)) -> (B, T, J) metres = sqrt(trace(G_t Sigma_t G_t^T))
    per joint, Sigma_t the marginal covariance of q_t (banded recursion). A tiny ridge (1e-9 of the
    largest diagonal entry) keeps directions no term constrains finite. With `branches`
    (`flip_posterior`), the flip branches' second moment about q is added to the variance:
    sqrt(trace(G Sigma G^T) + sum_c sum_l p_l |X_l - X|^2), each branch with q's curvature."""
    ridge = 1e-9 * hessian.diagonal.diagonal(dim1=-2, dim2=-1).amax((-2, -1)).clamp(min=1e-30)
    eye = torch.eye(q.shape[-1], dtype=q.dtype, device=q.device)
    factor, ok = factorize(BlockBanded(hessian.diagonal + ridge[:, None, None, None] * eye, hessian.lower))
    sigma = marginal_blocks(factor)  # (B, T, D, D)
    _, g = joint_jacobian(obj.problem.skeleton, q)  # (B, T, J, 3, D)
    var = torch.einsum("btjcd,btde,btjce->btj", g, sigma, g)
    if branches is not None:
        var = var + branches.variance
    std = var.clamp(min=0).sqrt()
    return torch.where(ok[:, None, None], std, torch.full_like(std, math.nan))


#: the shipped calibration of `joint_std` (`batch.std_calibration: true`)
CALIBRATION_FILE = "batch_std_calibration.json"


class StdCalibration(NamedTuple):
    """std' = sqrt((scale std)^2 + floor_m^2 + (travel m)^2): a variance factor, a floor (metres) and a share of
    the joint's travel from its nearest keyframe (m metres, `keyframe_travel`; dimensionless)."""

    scale: float
    floor_m: float
    travel: float = 0.0


@functools.cache
def std_calibration(mode: str = "branches") -> StdCalibration:
    """The calibration shipped in ptrack/data (`CALIBRATION_FILE`) for `batch.uncertainty` mode (branches,
    laplace): fitted on the dev clips' runs (configs/clips/dev.txt, keyframes every 1 s and first + last),
    the floor and the travel share by the lowest leave-one-clip-out interval score, the scale so that 0.95 of
    the joint-frames lie within 2 std (`scripts/make_std_calibration.py`)."""
    doc = json.loads(data_file(CALIBRATION_FILE).read_text(encoding="utf-8"))
    entry = doc[mode]
    return StdCalibration(float(entry["scale"]), float(entry["floor_m"]), float(entry["travel"]))


def keyframe_travel(joints: Tensor, frames: Tensor) -> Tensor:
    """How far each joint has moved from where it was at the nearest keyframe: joints (T, J, 3) metres (the
    solution), frames (F,) the keyframes' frames (any order, repeats allowed) -> (T, J) metres, the smaller of
    |X_t - X_k| for k the last keyframe at or before t and the first at or after it (0 at a keyframe). Without
    any keyframe, from frame 0 (the calibration was not fitted on such runs)."""
    t_len = joints.shape[0]
    frames = torch.unique(frames.to(device=joints.device, dtype=torch.long))  # sorted
    if frames.numel() == 0:
        frames = frames.new_zeros(1)
    t = torch.arange(t_len, device=joints.device)
    after = torch.searchsorted(frames, t).clamp(max=frames.numel() - 1)  # first keyframe >= t (or the last)
    before = (torch.searchsorted(frames, t, right=True) - 1).clamp(min=0)  # last keyframe <= t (or the first)
    d_before = (joints - joints[frames[before]]).norm(dim=-1)
    d_after = (joints - joints[frames[after]]).norm(dim=-1)
    return torch.minimum(d_before, d_after)


def calibrate_std(std: Tensor, calibration: StdCalibration, travel_m: Tensor) -> Tensor:
    """std (..., J) metres (`joint_std`), travel_m the same shape (`keyframe_travel`) -> sqrt((scale std)^2 +
    floor^2 + (travel travel_m)^2), the same shape. The raw std is the spread the objective's own model predicts
    (its 2D noise, smoothing scales and flip branches); the errors also hold what that model leaves out, mostly
    depth drift away from the keyframes, which grows with how far the joint has moved since (or before) the
    nearest one: on the dev clips the raw std holds 0.80 of joint-frames within 2 std."""
    c = calibration
    return ((c.scale * std).square() + c.floor_m**2 + (c.travel * travel_m).square()).sqrt()


def flip_posterior(
    obj: Trajectory, q: Tensor, bc: BatchMethodConfig, warm: tuple[BranchPosterior, Tensor] | None = None
) -> BranchPosterior | None:
    """The flip branches of the solution q (B, T, D) in the posterior (`ptrack.hypotheses.branches`): every limb's
    depth-labelled leaves (the default chains: arms, legs, head) through q's projections, each leaf's
    whole trajectory re-solved from there by `solve_trajectory` with the `batch.*` settings bc for
    `batch.branch_iterations` iterations (0: the rigid leaves), and their marginal
    probabilities per frame from the objective itself (per-frame terms, smoothing between
    consecutive frames' leaves; forward-backward). None (with a warning) for a model without the
    default chains. Costs one batched solve of 4 trajectories per chain (20 on CMU skeletons).

    warm (the posterior of an earlier solution q_0, q_0 (B, T, D)): after a restart from one of its
    branches, the objective is the same and q moved from q_0 on one limb; each leaf starts from its
    earlier re-solved trajectory moved by the same change (leaf + q - q_0), already near its minimum."""
    sk = obj.problem.skeleton
    try:
        chains = default_chains(sk)
        check_independent(sk, chains)
        plans = tuple(ik_plan(sk, c) for c in chains)
    except InputError as e:
        log.warning("batch: no flip chains on this model (%s): no flip restarts, the Laplace std only", e)
        return None

    def frame_energy(x: Tensor) -> Tensor:
        terms = evaluate(obj, x, with_jacobian=False).terms
        return terms["reprojection"] + terms["limits"] + terms["keyframes"] + terms["pose_prior"]

    short = dataclasses.replace(bc, iterations=bc.branch_iterations)

    def relax(starts: Tensor, at: Tensor) -> Tensor:
        if warm is None:
            return relax_branches(starts, lambda x: solve_trajectory(obj, x, short)[0], at)
        before, q0 = warm
        moved = before.branches.q + (at - q0)[:, None, None]
        return relax_branches(moved, lambda x: solve_trajectory(obj, x, short)[0])

    cam = obj.problem.observations.camera
    relaxed = relax if bc.branch_iterations > 0 else None
    smooth = [term for _, term in obj.smooth_terms]
    return branch_posterior(sk, cam, q, chains, plans, frame_energy, smooth, relaxed)


def lower_branch(obj: Trajectory, q: Tensor, branches: BranchPosterior) -> Tensor | None:
    """The re-solved flip branch (`flip_posterior`) of lowest whole energy, if it is lower than the
    solution q's and another trajectory (B = 1): -> (1, T, D), or None. A flipped limb's trajectory that
    the objective itself prefers means the solve stopped in a local minimum on the other branch. A branch
    whose joints all stay within `SAME_M` of q's at every frame is q's own minimum (its re-solve only went on
    where q's solve stopped at `batch.iterations`): not a restart."""
    cand = branches.branches.q[0].flatten(0, 1)  # (C L, T, D)
    energy = total_energy(obj, torch.cat([q, cand]))
    sk = obj.problem.skeleton
    moved = (sk.forward_kinematics(cand) - sk.forward_kinematics(q[0])).norm(dim=-1)  # (C L, T, J)
    other = moved.flatten(1).amax(-1) > SAME_M  # (C L,)
    lower = (energy[1:] < energy[0] - 1e-9 * energy[0].abs()) & other
    if not bool(lower.any()):
        return None
    best = int(torch.argmin(torch.where(lower, energy[1:], torch.inf)))
    return cand[best][None]
