"""`estimate_batch`: the MAP trajectory (`ptrack.estimators.batch`) from its start, with the flip restarts and
the uncertainty, as an `Estimate`."""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Iterable
from typing import Any

import torch
from torch import Tensor

from ptrack.body.limits import wrap_to_limits
from ptrack.estimators.batch.objective import evaluate, trajectory_objective
from ptrack.estimators.batch.solve import solve_trajectory
from ptrack.estimators.batch.start import (
    has_full_first_keyframe,
    has_full_keyframe,
    interpolate_keyframes,
    load_init,
    warp_to_keyframes,
)
from ptrack.estimators.batch.uncertainty import (
    calibrate_std,
    flip_posterior,
    joint_std,
    keyframe_travel,
    lower_branch,
    std_calibration,
)
from ptrack.hypotheses.branches import BranchPosterior
from ptrack.optim.solvers import BandedLMInfo
from ptrack.problem import Estimate, Problem
from ptrack.threads import one_thread

log = logging.getLogger(__name__)

#: (problem, cfg, generator, progress) -> Estimate: an estimator whose per-frame fits start the batch solve
PerFrame = Callable[[Problem, Any, torch.Generator, Callable[[Iterable], Iterable]], Estimate]


def estimate_batch(
    problem: Problem,
    cfg,
    generator: torch.Generator,
    progress: Callable[[Iterable], Iterable] = lambda x: x,
    callback: Callable[[int, Tensor, Tensor], None] | None = None,
    per_frame: PerFrame | None = None,
    tracker: PerFrame | None = None,
) -> Estimate:
    """The MAP trajectory (`ptrack.estimators.batch`). Deterministic given its start (uses no randomness).
    Solved in float64 on the observations' device; the Estimate is in the observations' dtype.

    per_frame(problem, cfg, generator, progress) -> Estimate: the per-frame fits the start comes from when
    neither `init_from` nor the keyframes give it (`ptrack.estimators.estimate_batch` passes
    `estimate_frames`; no estimator imports another). Needed then, and None, it raises ValueError.
    tracker, the same signature: the start with `batch.init: kjs` (`estimate_kjs`: its best trajectory; the
    tracker's tree start where frame 0 has no full keyframe, whatever `kjs.init` says).

    callback(iteration, q (1, T, D), cost (1,)) is called after every solver iteration. Runs on one
    intra-op thread (`ptrack.threads.one_thread`: small per-frame products, shared cores); with torch
    allowed 2 or more threads, the linearisation's per-frame work runs on the sequence's two halves on
    two threads (`evaluate`)."""
    with one_thread():
        return _estimate(problem, cfg, generator, progress, callback, per_frame, tracker)


def _estimate(
    problem: Problem,
    cfg,
    generator: torch.Generator,
    progress: Callable[[Iterable], Iterable],
    callback: Callable[[int, Tensor, Tensor], None] | None,
    per_frame: PerFrame | None,
    tracker: PerFrame | None = None,
) -> Estimate:
    bc = cfg.batch
    obs = problem.observations
    out_dtype, device = obs.keypoints.dtype, obs.keypoints.device
    dtype = torch.float64  # the whole-sequence normal equations are solved in double precision
    obj = trajectory_objective(problem, cfg, dtype, device)
    lower, upper = obj.lower, obj.upper
    if cfg.init_from:
        q0 = warp_to_keyframes(load_init(cfg.init_from, problem, dtype, device), obj)
    elif bc.init == "keyframes" and has_full_keyframe(problem):
        q0 = interpolate_keyframes(problem, lower, upper)
    elif bc.init == "kjs":
        if tracker is None:
            raise ValueError("estimate_batch: batch.init is kjs; pass tracker (estimate_kjs)")
        kjs_cfg = dataclasses.replace(cfg.kjs, init="keyframe" if has_full_first_keyframe(problem) else "tree")
        q0 = tracker(problem, dataclasses.replace(cfg, kjs=kjs_cfg), generator, progress).q
    else:
        if bc.init == "keyframes":
            log.info("batch: no keyframe gives every dof, so the start is the per-frame fits (as batch.init=frame)")
        if per_frame is None:
            raise ValueError("estimate_batch: the start is the per-frame fit here; pass per_frame (estimate_frames)")
        full0 = has_full_first_keyframe(problem)
        frame_cfg = cfg if full0 else dataclasses.replace(cfg, frame=dataclasses.replace(cfg.frame, init="rest"))
        q0 = per_frame(problem, frame_cfg, generator, progress).q
    q0 = wrap_to_limits(q0.detach().to(dtype), lower, upper, obj.angular)
    done = 0  # iterations so far: a restart's costs follow the first solve's on the logged timeline

    def solve(start: Tensor) -> tuple[Tensor, BandedLMInfo]:
        def logged(it: int, x: Tensor, cost: Tensor) -> None:
            if callback is not None:
                callback(done + it, x, cost)

        return solve_trajectory(obj, start, bc, logged)

    q, info = solve(q0[None])
    history = info.history
    log.info(
        "batch: %d iterations, cost %.6g -> %.6g", int(info.iterations[0]), float(history[0, 0]), float(info.cost[0])
    )
    branches: BranchPosterior | None = None
    warm: tuple[BranchPosterior, Tensor] | None = None  # the posterior of the trajectory a restart replaced
    for _ in range(bc.flip_restarts):
        with torch.no_grad():
            branches = flip_posterior(obj, q, bc, warm)
            start = None if branches is None else lower_branch(obj, q, branches)
        if start is None or branches is None:
            break
        done = history.shape[0] - 1
        warm = (branches, q)
        q, info = solve(start)
        history = torch.cat([history, info.history[1:]])
        branches = None  # the posterior of the trajectory it replaced
        log.info("batch: restarted from a flip branch, cost -> %.6g", float(info.cost[0]))
    with torch.no_grad():
        terms = evaluate(obj, q, with_jacobian=False).terms
        joints = problem.skeleton.forward_kinematics(q[0])
        std = None
        if bc.uncertainty:
            mode = "branches" if bc.uncertainty is True else bc.uncertainty
            if mode == "branches" and branches is None:
                branches = flip_posterior(obj, q, bc, warm)
            std = joint_std(obj, q, info.hessian, branches if mode == "branches" else None)[0]
            if bc.std_calibration:
                travel = keyframe_travel(joints, torch.cat([obj.kf_frames, obj.jk_frames]))
                std = calibrate_std(std, std_calibration(mode), travel)
    terms = {name: v[0].to(out_dtype) for name, v in terms.items()}
    return Estimate(
        q=q[0].to(out_dtype),
        joints=joints.to(out_dtype),
        cost=torch.stack(list(terms.values())).sum(0),
        terms=terms,
        joint_std=None if std is None else std.to(out_dtype),
        solver_cost=history[:, 0].to(out_dtype),
    )
