"""IK of a chain for every leaf of every hypothesis (`chain_ik`: the plan's closed form or iterative fit,
then the limits: "prune" flags, "project" clamps or re-solves) and of a product of chains
(`product_ik`), returning an `IKResult`. Inputs and outputs are batch-first; the solvers work on the
struct-of-arrays layout (`ptrack.hypotheses.jumps`), hypotheses last.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from ptrack.errors import InputError
from ptrack.hypotheses.ik.angles import window_violation
from ptrack.hypotheses.ik.closed_form import limb_angles, limb_fk, swing_angles, swing_slots
from ptrack.hypotheses.ik.iterative import iterative_ik, refine_missed
from ptrack.hypotheses.ik.kinematics import path_fk, root_frame
from ptrack.hypotheses.ik.plan import ChainIK, plan_tensors
from ptrack.hypotheses.jumps import Product, flatten_bits, sconst, smm

MODES = ("prune", "project")


class IKResult(NamedTuple):
    """IK of a chain (or of a product of chains) for L leaves per hypothesis.

    angles: (N, L, M) the solved dofs, in the limits' 2 pi window (clamped if projected).
    dofs: (M,) their q indices.
    start: (N, D) the poses IK started from; `q` (a property) writes the angles into them.
    positions: (N, L, n+1, 3) the chain's joints by forward kinematics of the solved pose (after
        projection; for a product, the chains' joints one chain after the other).
    residual: (N, L) metres, largest distance of the solved chain joints from the targets (before
        projection; ~0 unless the targets break the model's bone lengths or the fit stalled).
    exact: (N, L) bool, residual <= tol.
    in_limits: (N, L) bool, the solved angles were inside the joint limits before projection.
    keep: (N, L) bool, "prune": exact & in_limits; "project": exact.
    projected: (N, L) bool, angles were clamped into the limits (project mode only).
    """

    angles: Tensor
    dofs: tuple[int, ...]
    start: Tensor
    positions: Tensor
    residual: Tensor
    exact: Tensor
    in_limits: Tensor
    keep: Tensor
    projected: Tensor

    @property
    def q(self) -> Tensor:
        """(N, L, D) full poses per leaf: `start` with the solved dofs set. Built on each access
        (a copy of N x L x D numbers): index `angles` instead where that is enough."""
        q, leaves = self.start, self.angles.shape[-2]
        out = q[..., None, :].expand(*q.shape[:-1], leaves, q.shape[-1]).clone()
        return out.index_copy_(-1, torch.as_tensor(self.dofs, device=q.device), self.angles.to(q))


def chain_ik(
    plan: ChainIK,
    q: Tensor,
    positions: Tensor,
    mode: str = "prune",
    tol: float = 1e-4,
    collinear_tol: float | None = None,
    refine: bool = True,
    max_iter: int = 50,
) -> IKResult:
    """Inverse kinematics of a chain for every leaf of every hypothesis.

    Args:
        plan: from `ik_plan`.
        q: (..., D) current poses (every dof outside the chain is kept).
        positions: (..., L, n+1, 3) target world positions of the chain's joints (root first; the
            root must be q's own), e.g. `Tree.positions`.
        mode: "prune" (flag leaves outside the limits) or "project" (bring them into the limits:
            closed forms clamp the angles, the iterative fit solves again within the limits).
        tol: metres; `exact` when the solution lands every chain joint within tol of its target.
        collinear_tol: sine of the angle between a limb's two links below which it counts as
            straight (twist kept); default 1000 x the dtype's epsilon.
        refine: closed forms only: refine the leaves the closed form missed (not `exact`, finite
            targets) by the iterative fit from the closed form's angles. Costs one host sync
            (whether any leaf missed) when none did.
        max_iter: Levenberg-Marquardt iterations of the iterative fit.

    Returns:
        `IKResult` (leading dims `...` in place of N); dtype and device follow q. Solved angles
        are in the limits' 2 pi window (unlimited ones in [-pi, pi)).
    """
    if mode not in MODES:
        raise InputError(f"chain_ik: mode must be one of {', '.join(MODES)}, got {mode!r}")
    sk, chain = plan.sk, plan.chain
    if not isinstance(q, Tensor) or not q.is_floating_point() or q.ndim < 1 or q.shape[-1] != sk.num_dofs:
        raise InputError(
            f"chain_ik: q must be a floating tensor (..., {sk.num_dofs}), got {tuple(getattr(q, 'shape', ()))}"
        )
    n1 = chain.num_links + 1
    if (
        not isinstance(positions, Tensor)
        or positions.ndim != q.ndim + 2
        or positions.shape[-2:] != (n1, 3)
        or positions.shape[:-3] != q.shape[:-1]
    ):
        raise InputError(
            f"chain_ik: positions must be (..., L, {n1}, 3) with q's batch dims "
            f"{tuple(q.shape[:-1])} for chain {chain.name!r}, got "
            f"{tuple(getattr(positions, 'shape', ()))}"
        )
    leaves = positions.shape[-3]
    tc = plan_tensors(plan, q.dtype, q.device)
    qf = q.reshape(-1, sk.num_dofs)
    qs = qf.index_select(1, tc["used"]).T.contiguous()  # (D', B): the dofs IK reads
    x = positions.to(q).reshape(-1, leaves, n1, 3).permute(2, 3, 1, 0).contiguous()  # (n+1, 3, L, B)
    if plan.kind == "iterative":
        theta, pos, residual, exact, in_limits, keep, projected = iterative_ik(plan, tc, qs, x, mode, tol, max_iter)
        return _result(q, plan.dofs, theta, pos, residual, exact, in_limits, keep, projected)
    ctol = 1000 * torch.finfo(q.dtype).eps if collinear_tol is None else collinear_tol
    g_r, p_r = root_frame(plan, tc, qs)
    p_l = p_r[:, None]
    if plan.kind == "limb":
        a_frame = smm(g_r, sconst(tc["per"][plan.balls[0]]["c"], 1))[:, :, None]
        theta = limb_angles(plan, tc, a_frame, qs, x, ctol)

        def fk(th: Tensor) -> Tensor:
            return limb_fk(tc, a_frame, p_l, th)
    else:
        theta = swing_angles(plan, tc, g_r, p_r, qs, x)
        g_l = g_r[:, :, None]

        def fk(th: Tensor) -> Tensor:
            return path_fk(plan, tc, g_l, p_l, qs, swing_slots(plan, tc, th))

    theta, viol = window_violation(theta, tc)  # in the limits' 2 pi windows
    pos = fk(theta)
    diff = pos - x
    residual = torch.sqrt((diff * diff).sum(1)).amax(0)
    if refine:
        miss = ~(residual <= tol) & torch.isfinite(x).all(0).all(0)
        if bool(miss.any()):  # one host sync
            refine_missed(plan, tc, qs, x, theta, pos, residual, viol, miss, max_iter)
    exact = residual <= tol
    in_limits = viol == 0  # (L, B)
    projected = torch.zeros_like(in_limits)
    if mode == "project":
        projected = ~in_limits
        clamped = torch.clamp(theta, sconst(tc["lower"], 2), sconst(tc["upper"], 2))
        theta = torch.where(projected, clamped, theta)
        pos = torch.where(projected, fk(theta), pos)
        keep = exact
    else:
        keep = exact & in_limits
    return _result(q, plan.dofs, theta, pos, residual, exact, in_limits, keep, projected)


def _result(
    q: Tensor,
    dofs: tuple[int, ...],
    theta: Tensor,
    pos: Tensor,
    residual: Tensor,
    exact: Tensor,
    in_limits: Tensor,
    keep: Tensor,
    projected: Tensor,
) -> IKResult:
    """Struct-of-arrays solution -> `IKResult`: theta (M, L, B), pos (n+1, 3, L, B), flags (L, B)."""
    n1, _, leaves, _ = pos.shape
    lead = (*q.shape[:-1], leaves)

    def flags(f: Tensor) -> Tensor:
        return f.T.contiguous().reshape(lead)

    return IKResult(
        angles=theta.permute(2, 1, 0).contiguous().reshape(*lead, theta.shape[0]),
        dofs=dofs,
        start=q,
        positions=pos.permute(3, 2, 0, 1).contiguous().reshape(*lead, n1, 3),
        residual=flags(residual),
        exact=flags(exact),
        in_limits=flags(in_limits),
        keep=flags(keep),
        projected=flags(projected),
    )


def product_ik(q: Tensor, results: list[IKResult], prod: Product) -> IKResult:
    """Combine per-chain IK over a product of trees: q (..., D) the hypotheses and each chain's
    result over its own leaves -> one result over the combined leaves (..., L): each chain's angles
    from its leaf, `dofs` and `positions` concatenated in chain order, flags AND-ed (`projected`
    OR-ed), `residual` the largest. The chains must be independent (`jumps.check_independent`)."""
    if len(results) != len(prod.chains):
        raise InputError(f"product_ik: {len(results)} results for {len(prod.chains)} chains")
    first = results[0]
    batch = first.residual.shape[:-1]
    nb, start = prod.num_bits, len(batch)
    bit_shape = (*batch, *([2] * nb))
    m = sum(r.angles.shape[-1] for r in results)
    joints = sum(r.positions.shape[-2] for r in results)
    angles = first.angles.new_empty(*bit_shape, m)
    positions = first.positions.new_empty(*bit_shape, joints, 3)
    a_off = p_off = 0
    for c, r in enumerate(results):  # each chain's leaves into its slice, by broadcasting
        na, npos = r.angles.shape[-1], r.positions.shape[-2]
        angles[..., a_off : a_off + na] = prod.bits_view(c, r.angles, -2)
        positions[..., p_off : p_off + npos, :] = prod.bits_view(c, r.positions, -3)
        a_off, p_off = a_off + na, p_off + npos
    flags = {}
    for name, combine in (
        ("keep", torch.logical_and),
        ("exact", torch.logical_and),
        ("in_limits", torch.logical_and),
        ("projected", torch.logical_or),
        ("residual", torch.maximum),
    ):
        x = prod.bits_view(0, getattr(first, name), -1)
        for c, r in enumerate(results[1:], start=1):
            x = combine(x, prod.bits_view(c, getattr(r, name), -1))
        flags[name] = flatten_bits(x, start, nb)
    return IKResult(
        angles=angles.flatten(start, start + nb - 1),
        dofs=tuple(d for r in results for d in r.dofs),
        start=q,
        positions=positions.flatten(start, start + nb - 1),
        **flags,
    )
