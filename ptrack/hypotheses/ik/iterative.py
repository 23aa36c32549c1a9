"""The iterative IK fallback, and the refinement of closed-form leaves that miss their targets.

For chains with no closed form (URDF models, whose joints are 1-dof revolutes; ASF chains that are
neither limb nor swing; `ik_plan(..., closed_form=False)` forces it) `iterative_ik` minimises
|FK(q)[chain joints] - positions|^2 over the plan's dofs -- those of the path joints (and of the chain
root when its bone end is on its pivot, as URDF links are) that move the chain's joints -- with the
shared batched Levenberg-Marquardt (`ptrack.optim.solvers.levenberg_marquardt`) over hypotheses x
leaves at once, from q's own angles, with the geometric Jacobian (`ptrack.optim.jacobians`) restricted
to the chain (`kinematics.walk_fk`). "prune" solves unbounded and flags leaves whose angles (wrapped
into the limits' windows) break the limits; "project" solves those leaves again within the limits (box
constraints) from their clamped angles. Closed-form leaves that miss their targets (`exact` False:
numerical trouble, or targets that break the model's bone lengths) are refined by the same fit from the
closed form's angles (`refine_missed`, `chain_ik(..., refine=True)`); when every leaf is exact this
costs one host sync.

Measured 2026-11-23 (1 torch thread, shared loaded 2-core CPU; interleaved medians): on the
scripts/bench_jumps.py workload (4096 x 8 leaves, all exact) the closed-form path with refinement
on takes what it took before the fallback existed (28.8 vs 27.0 ms float32, 45.1 vs 45.8 ms
float64: noise). The fit lands every leaf of a 4-dof URDF arm's trees (tests/test_ik_iterative.py's
arm, 4096 x 4 leaves, from each hypothesis's own angles) within 1e-7 m (median 5e-12) in float64
and 6.6e-5 m (median 1.6e-7) in float32, in 0.4-1.0 s ("project": 0.9-1.7 s); from another random
pose, 3 of 4096 float32 fits stall near the shoulder's gimbal lock at ~1.5e-4 m (flagged not
`exact`). On CMU limbs it reaches the closed form's positions to within 1e-8 m. Most leaves converge
in under 8 iterations and a few take ~30; `_fit` therefore runs the solver in rounds over the
unconverged leaves only (400 vs 820 ms for one run over all of them, float64).

Flat problems: P = leaves x hypotheses (or the leaves being refined), last, as in the rest of the
package; the solver sees them as its N problems, (P, M) angles.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ptrack.hypotheses.ik.angles import window_violation
from ptrack.hypotheses.ik.kinematics import root_parent, walk_fk
from ptrack.hypotheses.ik.plan import ChainIK
from ptrack.hypotheses.jumps import sconst
from ptrack.optim.solvers import levenberg_marquardt


def iterative_ik(
    plan: ChainIK, tc: dict, qs: Tensor, x: Tensor, mode: str, tol: float, max_iter: int
) -> tuple[Tensor, ...]:
    """Iterative IK of every leaf from the hypothesis's own angles: qs (D', B), x (n+1, 3, L, B)
    -> theta (M, L, B), positions (n+1, 3, L, B), residual, exact, in_limits, keep, projected (L, B).
    Solved unbounded and wrapped into the limits' windows; in "project" mode the leaves outside
    the limits are solved again inside them (box constraints), from their clamped angles."""
    n1, _, leaves, b = x.shape
    g_par, pivot = root_parent(plan, tc, qs)

    def tile(t: Tensor) -> Tensor:  # (..., B) -> (..., L B), leaf-major
        return t.unsqueeze(-2).expand(*t.shape[:-1], leaves, b).reshape(*t.shape[:-1], leaves * b)

    gp, pv, qp = tile(g_par), tile(pivot), tile(qs)
    xp = x.reshape(n1, 3, leaves * b)
    theta = _fit(plan, tc, gp, pv, qp, xp, tile(qs.index_select(0, tc["dof_rows"])), False, max_iter)
    theta, viol = window_violation(theta, tc)
    pos, _ = walk_fk(plan, tc, gp, pv, qp, theta, False)
    diff = pos - xp
    residual = torch.sqrt((diff * diff).sum(1)).amax(0)
    exact, in_limits = residual <= tol, viol == 0
    projected = torch.zeros_like(in_limits)
    if mode == "project":
        projected = ~in_limits
        if bool(projected.any()):
            i = projected.nonzero()[:, 0]
            lo, hi = sconst(tc["lower"], 1), sconst(tc["upper"], 1)
            sub = _fit(
                plan, tc, gp[..., i], pv[:, i], qp[:, i], xp[..., i], torch.clamp(theta[:, i], lo, hi), True, max_iter
            )
            sub = window_violation(sub, tc)[0]  # unlimited dofs back into [-pi, pi)
            theta[:, i] = sub
            pos[..., i] = walk_fk(plan, tc, gp[..., i], pv[:, i], qp[:, i], sub, False)[0]
        keep = exact
    else:
        keep = exact & in_limits

    def lb(t: Tensor) -> Tensor:
        return t.unflatten(-1, (leaves, b))

    return (lb(theta), lb(pos), lb(residual), lb(exact), lb(in_limits), lb(keep), lb(projected))


def refine_missed(
    plan: ChainIK,
    tc: dict,
    qs: Tensor,
    x: Tensor,
    theta: Tensor,
    pos: Tensor,
    residual: Tensor,
    viol: Tensor,
    miss: Tensor,
    max_iter: int,
) -> None:
    """Refine the closed form's missed leaves miss (L, B) iteratively from its angles, in place:
    theta (M, L, B) (wrapped into the windows), pos (n+1, 3, L, B), residual and viol (L, B). A
    leaf keeps the closed form's answer if the fit does not lower its residual (e.g. targets that
    break the bone lengths, where the two answers are different compromises)."""
    li, bi = miss.nonzero(as_tuple=True)
    g_par, pivot = root_parent(plan, tc, qs)
    g_par, pivot, qs_p, xp = g_par[..., bi], pivot[:, bi], qs[:, bi], x[:, :, li, bi]
    sub = _fit(plan, tc, g_par, pivot, qs_p, xp, theta[:, li, bi], False, max_iter)
    sub, sub_viol = window_violation(sub, tc)
    sub_pos, _ = walk_fk(plan, tc, g_par, pivot, qs_p, sub, False)
    diff = sub_pos - xp
    sub_res = torch.sqrt((diff * diff).sum(1)).amax(0)
    better = sub_res < residual[li, bi]
    theta[:, li, bi] = torch.where(better, sub, theta[:, li, bi])
    pos[:, :, li, bi] = torch.where(better, sub_pos, pos[:, :, li, bi])
    residual[li, bi] = torch.where(better, sub_res, residual[li, bi])
    viol[li, bi] = torch.where(better, sub_viol, viol[li, bi])


def _fit(
    plan: ChainIK,
    tc: dict,
    g_par: Tensor,
    pivot: Tensor,
    qs: Tensor,
    x: Tensor,
    theta0: Tensor,
    bounded: bool,
    max_iter: int,
    first_round: int = 8,
) -> Tensor:
    """Least-squares fit of the chain's joints 1..n to targets x (n+1, 3, P) over the solved dofs,
    from theta0 (M, P), by `ptrack.optim.solvers.levenberg_marquardt` (all P problems at once), within
    the joint limits if bounded -> theta (M, P). Problems with non-finite targets stay at theta0.

    The solver runs the whole batch until its slowest problem is done; most leaves converge in
    a few iterations and a few take tens, so it runs in rounds, each on the problems not yet
    converged (restarting their damping), of `first_round` iterations, then twice as many as the
    round before: one host sync per round."""
    n = plan.chain.num_links
    bad = ~torch.isfinite(x[1:]).all(0).all(0)  # (P,)
    target = torch.where(bad, 0.0, x[1:])
    lo, hi = (tc["lower"], tc["upper"]) if bounded else (None, None)
    theta = torch.nan_to_num(theta0).T.contiguous()  # (P, M)
    idx: Tensor | None = None  # the problems still running (None: all)
    left, rounds = max_iter, first_round
    while left > 0:
        sub = (
            (g_par, pivot, qs, target, bad)
            if idx is None
            else (g_par[..., idx], pivot[:, idx], qs[:, idx], target[..., idx], bad[idx])
        )
        sol, info = levenberg_marquardt(
            _linearization(plan, tc, n, *sub), theta if idx is None else theta[idx], lo, hi, max_iter=min(rounds, left)
        )
        left, rounds = left - rounds, 2 * rounds
        if idx is None:
            theta, idx = sol, (~info.converged).nonzero()[:, 0]
        else:
            theta[idx] = sol
            idx = idx[~info.converged]
        if left <= 0 or idx.numel() == 0:  # one host sync per round
            break
    return theta.T


def _linearization(
    plan: ChainIK, tc: dict, n: int, g_par: Tensor, pivot: Tensor, qs: Tensor, target: Tensor, bad: Tensor
):
    """The solver's linearize for `_fit`: th (P, M) -> residuals (P, 3 n), jacobian (P, 3 n, M)."""

    def linearize(th: Tensor) -> tuple[Tensor, Tensor]:
        p, m = th.shape
        pos, jac = walk_fk(plan, tc, g_par, pivot, qs, th.T, True)
        assert jac is not None  # asked for
        r = torch.where(bad, 0.0, pos[1:] - target).permute(2, 0, 1).reshape(p, 3 * n)
        return r, torch.where(bad, 0.0, jac).permute(3, 0, 1, 2).reshape(p, 3 * n, m)

    return linearize
