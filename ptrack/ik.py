"""Inverse kinematics for interpretation-tree leaves: a chain's joint positions -> joint angles.

    plan = ik_plan(sk, chain)                     # raises ClosedFormUnavailable if no closed form
    res = chain_ik(plan, q, tree.positions, mode="prune")   # q (N, D), positions (N, L, n+1, 3)
    res.q                                         # (N, L, D): q with the chain's dofs solved

Closed forms (Sminchisescu & Triggs 2003, section 3.1), chosen by `ik_plan` from the skeleton:

- "limb": root -> ball -> hinge, e.g. CMU shoulder (`lclavicle`) -> elbow (`lhumerus`, a 3-dof
  ball: the humerus's rx ry rz in its ASF `axis` frame) -> wrist (`lradius`, a 1-dof hinge: the
  radius's rx); likewise hip -> knee -> ankle. The hinge angle comes from the angle between the
  two links (two candidates, t and its mirror); the ball's rotation Z is the one taking the
  upper bone and the lower bone (for that hinge angle) onto the target directions, so the
  upper bone's twist is recovered from the next joint. When the limb is straight (the targets
  collinear to `collinear_tol`) the twist is undetermined and the current one is kept: Z is the
  smallest rotation from the current upper bone direction to the target, applied to the current Z.
- "swing": every link's first joint is a 3-dof ball (e.g. thorax -> upper neck -> head: the lower
  neck turns the neck link, the head joint the head link). A single point per link fixes only
  the swing, so each ball turns by the smallest rotation taking its link onto the target and
  keeps its current twist; joints inside a link keep their angles.

Each ball's rotation has two Euler solutions (y and pi - y) and a limb's hinge two candidates, all
reproducing the same positions; the one inside the joint limits is chosen (least violation),
ties going to the nearest to the current angles. Angles are returned in the limits' 2 pi window
(`ptrack.limits.wrap_to_limits`). Leaves whose angles still break the limits are flagged for
`mode="prune"`, or clamped into them and re-run through the chain's forward kinematics for
`mode="project"`. The chain's root must stay where q's forward kinematics puts it; bone lengths
are the model's (`sk.lengths`).

The iterative fallback (any chain, URDF models, and leaves whose closed form is not `exact`) is to
run the shared solver `ptrack.solvers` on the chain's dofs; it is not here yet. Where to plug it in:
`ik_plan` raises `ClosedFormUnavailable` for chains without a closed form, and `IKResult.exact`
marks leaves where the closed form missed its targets (bone lengths inconsistent with the model).

Shapes: `N` hypotheses (any leading batch dims), `L` leaves, `D` dofs, n links.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ptrack.errors import InputError
from ptrack.jumps import Chain, Product, _mm, _mv, _unit, min_rotation, path_below
from ptrack.kinematics import euler_zyx
from ptrack.limits import TAU, outside_limits, wrap_to_limits
from ptrack.skeleton import Skeleton

MODES = ("prune", "project")


class ClosedFormUnavailable(InputError):
    """The chain has no closed-form IK here (not a ball + hinge limb nor a chain of balls): use the
    iterative fallback."""


@dataclass(frozen=True, eq=False)
class ChainIK:
    """How to solve one chain: made by `ik_plan`.

    kind: "limb" or "swing" (module docstring). ancestors: joints from the skeleton root to the
    chain root. path: joints below the chain root down to its end. balls: joints whose three angles
    are solved; hinge: the limb's hinge joint (-1 for swing) and hinge_slot its driven axis slot.
    dofs: (M,) q indices set, each ball's slots (z, y, x) then the hinge's.
    """

    sk: Skeleton
    chain: Chain
    kind: str
    ancestors: tuple[int, ...]
    path: tuple[int, ...]
    balls: tuple[int, ...]
    hinge: int
    hinge_slot: int
    dofs: tuple[int, ...]
    _cache: dict = field(default_factory=dict, repr=False)


def _frame(sk: Skeleton, j: int) -> np.ndarray | None:
    """C (3, 3) with columns (axes[2], axes[1], axes[0]) if a right-handed orthonormal frame."""
    c = np.stack([sk.axes[j, 2], sk.axes[j, 1], sk.axes[j, 0]], axis=-1)
    if np.allclose(c.T @ c, np.eye(3), atol=1e-9) and abs(np.linalg.det(c) - 1.0) < 1e-9:
        return c
    return None


def _is_ball(sk: Skeleton, j: int) -> bool:
    return bool(np.all(sk.axis_dof[j] >= 0)) and _frame(sk, j) is not None \
        and not np.any(sk.offset_parent[j]) and sk.lengths[j] > 0


def ik_plan(sk: Skeleton, chain: Chain) -> ChainIK:
    """The closed-form IK plan of `chain` on `sk`; raises ClosedFormUnavailable (an InputError)
    naming the chain and the reason when neither closed form applies."""
    if max(chain.joints) >= sk.num_joints:
        raise InputError(f"chain {chain.name!r} does not belong to skeleton {sk.name!r}")
    anc = [chain.joints[0]]
    while sk.parents[anc[-1]] >= 0:
        anc.append(sk.parents[anc[-1]])
    ancestors = tuple(reversed(anc))
    path: list[int] = []
    firsts: list[int] = []
    for p, c in chain.links:
        seg = path_below(sk, p, c)
        firsts.append(seg[0])
        path.extend(seg)
    r, names = chain.joints[0], chain.joint_names
    if chain.num_links == 2 and path == list(chain.joints[1:]) and _is_ball(sk, path[0]):
        e = path[1]
        driven = np.flatnonzero(sk.axis_dof[e] >= 0)
        if len(driven) == 1 and not np.any(sk.offset_parent[e]) and sk.lengths[e] > 0:
            m = path[0]
            plan = ChainIK(sk=sk, chain=chain, kind="limb", ancestors=ancestors, path=tuple(path),
                           balls=(m,), hinge=e, hinge_slot=int(driven[0]),
                           dofs=tuple(int(d) for d in sk.axis_dof[m]) + (int(sk.axis_dof[e, driven[0]]),))
            if _limb_constants(plan)["rho"] < 1e-6:
                raise ClosedFormUnavailable(
                    f"chain {chain.name!r}: the hinge {names[2]!r} does not change the angle between "
                    "its bone and the bone above it; no closed-form limb IK")
            return plan
    not_ball = [sk.joint_names[j] for j in firsts if not _is_ball(sk, j)]
    if not not_ball:
        return ChainIK(sk=sk, chain=chain, kind="swing", ancestors=ancestors, path=tuple(path),
                       balls=tuple(firsts), hinge=-1, hinge_slot=-1,
                       dofs=tuple(int(d) for j in firsts for d in sk.axis_dof[j]))
    raise ClosedFormUnavailable(
        f"chain {chain.name!r} on {sk.name!r}: no closed-form IK (needs root -> 3-dof ball -> 1-dof "
        f"hinge, or a 3-dof ball at the start of every link; {not_ball[0]!r} is not a 3-dof ball "
        f"joint with an axis frame); use the iterative fallback")


# ---------------------------------------------------------------- constants


def _slot_rotation(axes: np.ndarray, angles: np.ndarray) -> np.ndarray:
    """Rot(axes[0], a0) Rot(axes[1], a1) ... for constant angles (numpy)."""
    out = np.eye(3)
    for a, t in zip(axes, angles):
        k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        out = out @ (np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * k @ k)
    return out


def _limb_constants(plan: ChainIK) -> dict:
    """Limb geometry in the ball's axis frame (numpy): the upper bone a = C^T E_m w_m, the lower
    bone v(t) = D Rot(n, t) c for hinge angle t, and a . v(t) = alpha cos t + beta sin t + gamma."""
    sk, m, e, k = plan.sk, plan.balls[0], plan.hinge, plan.hinge_slot
    c_m = _frame(sk, m)
    a = c_m.T @ sk.rest_rotation[m] @ sk.offset_local[m]
    p_rot = _slot_rotation(sk.axes[e, :k], sk.frozen_axes[e, :k])
    q_rot = _slot_rotation(sk.axes[e, k + 1:], sk.frozen_axes[e, k + 1:]) @ sk.rest_rotation[e]
    n = sk.axes[e, k] / np.linalg.norm(sk.axes[e, k])
    d = c_m.T @ sk.rest_rotation[m] @ p_rot
    c = q_rot @ sk.offset_local[e]
    a1 = d.T @ a
    alpha = a1 @ c - (a1 @ n) * (n @ c)
    beta = a1 @ np.cross(n, c)
    gamma = (a1 @ n) * (n @ c)
    rho, ac = math.hypot(alpha, beta), float(np.linalg.norm(a) * np.linalg.norm(c))
    return dict(a=a, d=d, n=n, c=c, alpha=alpha, beta=beta, gamma=gamma, rho=rho, ac=ac,
                delta=min(rho - (ac - gamma), 0.0), phi=math.atan2(beta, alpha))


def _tensors(plan: ChainIK, dtype: torch.dtype, device: torch.device) -> dict:
    key = (dtype, str(device))
    out = plan._cache.get(key)
    if out is not None:
        return out
    sk = plan.sk

    def t(x):
        return torch.as_tensor(np.ascontiguousarray(x), dtype=dtype, device=device)

    joints = plan.ancestors + plan.path
    per = {}
    for j in joints:
        c = _frame(sk, j)
        per[j] = dict(
            index=torch.as_tensor(np.clip(sk.axis_dof[j], 0, None), device=device),
            mask=t(sk.axis_dof[j] >= 0),
            frozen=t(np.where(sk.axis_dof[j] >= 0, 0.0, sk.frozen_axes[j])),
            c=None if c is None else t(c),
            axes=t(sk.axes[j]),
            rest=None if np.allclose(sk.rest_rotation[j], np.eye(3)) else t(sk.rest_rotation[j]),
            u=None if not np.any(sk.offset_parent[j]) else t(sk.offset_parent[j] * sk.lengths[j]),
            w=t(sk.offset_local[j] * sk.lengths[j]),
        )
    lower, upper = sk.limits(dtype=dtype, device=device)
    dofs = torch.as_tensor(plan.dofs, device=device)
    out = dict(per=per, dofs=dofs, lower=lower[dofs], upper=upper[dofs],
               angular=torch.ones(len(plan.dofs), dtype=torch.bool, device=device),
               root_position=t(sk.root_position),
               trans_index=torch.as_tensor(np.clip(sk.translation_dof, 0, None), device=device),
               trans_mask=t(sk.translation_dof >= 0))
    if plan.kind == "limb":
        lc = _limb_constants(plan)
        out["limb"] = {k: (t(v) if isinstance(v, np.ndarray) else float(v)) for k, v in lc.items()}
        out["ball_c"] = per[plan.balls[0]]["c"]
    plan._cache[key] = out
    return out


# ---------------------------------------------------------------- forward kinematics along a path


def _slot_angles(pj: dict, q: Tensor) -> Tensor:
    """(..., D) -> (..., 3) angles of one joint's axis slots (frozen slots at their value)."""
    return q.index_select(-1, pj["index"]) * pj["mask"] + pj["frozen"]


def _rodrigues(axis: Tensor, angle: Tensor) -> Tensor:
    k = torch.zeros(*angle.shape, 3, 3, dtype=angle.dtype, device=angle.device) + _skew(axis)
    s, c = torch.sin(angle)[..., None, None], torch.cos(angle)[..., None, None]
    return torch.eye(3, dtype=angle.dtype, device=angle.device) + s * k + (1 - c) * _mm(k, k)


def _skew(v: Tensor) -> Tensor:
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack([o, -z, y, z, o, -x, -y, x, o], dim=-1).unflatten(-1, (3, 3))


def _local(pj: dict, theta: Tensor) -> Tensor:
    """A joint's rotation relative to its parent for slot angles theta (..., 3) -> (..., 3, 3)."""
    if pj["c"] is not None:
        c = pj["c"]
        r = _mm(_mm(c, euler_zyx(theta)), c.transpose(-1, -2))
    else:
        r = _rodrigues(pj["axes"][0], theta[..., 0])
        r = _mm(_mm(r, _rodrigues(pj["axes"][1], theta[..., 1])), _rodrigues(pj["axes"][2], theta[..., 2]))
    return r if pj["rest"] is None else _mm(r, pj["rest"])


def _step(pj: dict, g_par: Tensor, p_par: Tensor, theta: Tensor) -> tuple[Tensor, Tensor]:
    """One joint of forward kinematics: parent frame and position -> this joint's."""
    g = _mm(g_par, _local(pj, theta))
    p = p_par + _mv(g, pj["w"])
    if pj["u"] is not None:
        p = p + _mv(g_par, pj["u"])
    return g, p


def _ancestors(plan: ChainIK, tc: dict, q: Tensor) -> tuple[Tensor, Tensor]:
    """World rotation (..., 3, 3) and position (..., 3) of the chain's root joint for q (..., D)."""
    per = tc["per"]
    root = plan.ancestors[0]
    g = _local(per[root], _slot_angles(per[root], q))
    p = q.index_select(-1, tc["trans_index"]) * tc["trans_mask"] + tc["root_position"] + _mv(g, per[root]["w"])
    for j in plan.ancestors[1:]:
        g, p = _step(per[j], g, p, _slot_angles(per[j], q))
    return g, p


def _path_fk(plan: ChainIK, tc: dict, g: Tensor, p: Tensor, q: Tensor, solved: dict[int, Tensor]) -> Tensor:
    """Positions (..., n+1, 3) of the chain's joints from the root frame g (..., 3, 3), position
    p (..., 3), slot angles `solved` {joint: (..., 3)} and q (..., D) for the other path joints."""
    per = tc["per"]
    pos = {plan.chain.joints[0]: p}
    for j in plan.path:
        theta = solved[j] if j in solved else _slot_angles(per[j], q)
        g, p = _step(per[j], g, p, theta)
        pos[j] = p
    return torch.stack(torch.broadcast_tensors(*(pos[j] for j in plan.chain.joints)), dim=-2)


# ---------------------------------------------------------------- rotation -> angles


def euler_zyx_solutions(r: Tensor, x_lock: Tensor) -> Tensor:
    """Both (z, y, x) angle triples with Rz(z) Ry(y) Rx(x) = r: (..., 3, 3) -> (..., 2, 3); the
    first has |y| <= pi/2, the second is (z + pi, pi - y, x + pi). At the gimbal lock (cos y = 0)
    x is taken from x_lock (...,) (e.g. the current angle) and z carries the rest."""
    r20, r21, r22 = r[..., 2, 0], r[..., 2, 1], r[..., 2, 2]
    lock = torch.hypot(r21, r22) <= 64 * torch.finfo(r.dtype).eps
    x = torch.stack([torch.where(lock, x_lock, torch.atan2(r21, r22)),
                     torch.where(lock, x_lock, torch.atan2(-r21, -r22))], dim=-1)
    sx, cx = torch.sin(x), torch.cos(x)
    y = torch.atan2(-r20[..., None], sx * r21[..., None] + cx * r22[..., None])
    z = torch.atan2(sx * r[..., 0, 2, None] - cx * r[..., 0, 1, None],
                    cx * r[..., 1, 1, None] - sx * r[..., 1, 2, None])
    return torch.stack([z, y, x], dim=-1)


def _pick(cands: Tensor, current: Tensor, lower: Tensor, upper: Tensor, angular: Tensor) -> Tensor:
    """The candidate angle vector with least limit violation, ties (1e-9) to the nearest to
    `current` on the circle: cands (..., C, M), current (..., M) broadcastable -> (..., M)."""
    viol = outside_limits(cands, lower, upper, angular).sum(-1)  # (..., C)
    diff = torch.remainder(cands - current[..., None, :] + math.pi, TAU) - math.pi
    dist = (diff * diff).sum(-1)
    best = viol.amin(-1, keepdim=True)
    dist = torch.where(viol <= best + 1e-9, dist, torch.full_like(dist, math.inf))
    i = dist.argmin(-1, keepdim=True)
    return torch.gather(cands, -2, i[..., None].expand(*i.shape[:-1], 1, cands.shape[-1])).squeeze(-2)


# ---------------------------------------------------------------- solvers


class IKResult(NamedTuple):
    """IK of a chain for L leaves per hypothesis.

    q: (N, L, D) q with the chain's dofs set (in the limits' 2 pi window; clamped if projected).
    positions: (N, L, n+1, 3) the chain's joints by forward kinematics of q (after projection).
    residual: (N, L) metres, largest distance of the closed form's chain joints from the targets
        (before projection; ~0 unless the targets break the model's bone lengths).
    exact: (N, L) bool, residual <= tol.
    in_limits: (N, L) bool, the chain's angles were inside the joint limits before projection.
    keep: (N, L) bool, "prune": exact & in_limits; "project": exact.
    projected: (N, L) bool, angles were clamped into the limits (project mode only).
    dofs: (M,) q indices the chain sets.
    """

    q: Tensor
    positions: Tensor
    residual: Tensor
    exact: Tensor
    in_limits: Tensor
    keep: Tensor
    projected: Tensor
    dofs: tuple[int, ...]


def _limb(plan: ChainIK, tc: dict, g_r: Tensor, q: Tensor, x: Tensor, ctol: float) -> Tensor:
    """Limb angles (B, L, 4) = ball (z, y, x), hinge, for targets x (B, L, 3, 3)."""
    lc = tc["limb"]
    ball = tc["per"][plan.balls[0]]
    cur_ball = _slot_angles(ball, q)  # (B, 3)
    cur = torch.cat([cur_ball, q[..., plan.dofs[3], None]], -1)  # (B, 4)
    a_frame = _mm(g_r, tc["ball_c"])[:, None]  # (B, 1, 3, 3): world <- ball axis frame
    b1 = _unit(_mv(a_frame.transpose(-1, -2), x[:, :, 1] - x[:, :, 0]))  # (B, L, 3)
    b2 = _unit(_mv(a_frame.transpose(-1, -2), x[:, :, 2] - x[:, :, 1]))
    cos_k = _dot(b1, b2)
    a, d, n, c = lc["a"], lc["d"], lc["n"], lc["c"]
    # a . v(t) = rho cos(t - phi) + gamma must equal |a||c| cos_k. Not with acos (which loses half
    # the digits at a straight limb): with h-, h+ = |b1 -+ b2|^2 / 2 (exact near 0 and pi) and
    # delta = rho - (|a||c| - gamma) <= 0, rho cos(t - phi) = rho - delta - |a||c| h-, and
    # rho^2 sin^2(t - phi) = (delta + |a||c| h-) (delta - 2 gamma + |a||c| h+).
    hm = 0.5 * _dot(b1 - b2, b1 - b2)
    hp = 0.5 * _dot(b1 + b2, b1 + b2)
    ac, delta, gamma = lc["ac"], lc["delta"], lc["gamma"]
    sin_part = torch.sqrt(((delta + ac * hm) * (delta - 2.0 * gamma + ac * hp)).clamp_min(0.0))
    half = torch.atan2(sin_part, lc["rho"] - delta - ac * hm)
    t = lc["phi"] + torch.stack([half, -half], -1)  # (B, L, 2) hinge candidates
    ct, st = torch.cos(t)[..., None], torch.sin(t)[..., None]
    v = _mv(d, c * ct + torch.linalg.cross(n, c, dim=-1) * st + n * (n @ c) * (1 - ct))  # (B, L, 2, 3)
    f1 = _unit(a).expand_as(v)
    f2 = _unit(v - _dot(v, f1)[..., None] * f1)
    frame_f = torch.stack([f1, f2, torch.linalg.cross(f1, f2, dim=-1)], -1)  # columns
    g2 = _unit(b2 - cos_k[..., None] * b1)
    frame_g = torch.stack([b1, g2, torch.linalg.cross(b1, g2, dim=-1)], -1)[:, :, None]
    z = _mm(frame_g, frame_f.transpose(-1, -2))  # (B, L, 2, 3, 3)
    # straight limb: keep the current twist (smallest turn of the current upper bone onto b1)
    z_cur = euler_zyx(cur_ball)[:, None]  # (B, 1, 3, 3)
    z_swing = _mm(min_rotation(_mv(z_cur, a).expand_as(b1), b1), z_cur)
    straight = torch.linalg.vector_norm(torch.linalg.cross(b1, b2, dim=-1), dim=-1) < ctol
    z = torch.where(straight[..., None, None, None], z_swing[:, :, None], z)
    eul = euler_zyx_solutions(z, cur_ball[:, None, None, 0])  # (B, L, 2 hinge, 2 euler, 3)
    cands = torch.cat([eul, t[..., None, None].expand(*t.shape, 2, 1)], -1).flatten(-3, -2)  # (B, L, 4, 4)
    return _pick(cands, cur[:, None], tc["lower"], tc["upper"], tc["angular"])


def _swing(plan: ChainIK, tc: dict, g_r: Tensor, p_r: Tensor, q: Tensor, x: Tensor) -> Tensor:
    """Swing angles (B, L, 3 * n) (each ball's z, y, x) for targets x (B, L, n+1, 3)."""
    per = tc["per"]
    frames = {plan.chain.joints[0]: (g_r, p_r)}
    g, p = g_r, p_r
    for j in plan.path:  # current frames and positions along the path (per hypothesis)
        g, p = _step(per[j], g, p, _slot_angles(per[j], q))
        frames[j] = (g, p)
    turn: Tensor | None = None
    out = []
    for k, ((pa, ch), ball) in enumerate(zip(plan.chain.links, plan.balls)):
        g_p = frames[pa][0][:, None]
        link = (frames[ch][1] - frames[pa][1])[:, None]  # (B, 1, 3)
        if turn is not None:
            g_p, link = _mm(turn, g_p), _mv(turn, link)
        delta = min_rotation(link.expand_as(x[:, :, k]), x[:, :, k + 1] - x[:, :, k])
        turn = delta if turn is None else _mm(delta, turn)
        g_j = _mm(turn, frames[ball][0][:, None])
        local = _mm(g_p.transpose(-1, -2), g_j)
        if per[ball]["rest"] is not None:
            local = _mm(local, per[ball]["rest"].transpose(-1, -2))
        cb = per[ball]["c"]
        zmat = _mm(_mm(cb.transpose(-1, -2), local), cb)
        cur = _slot_angles(per[ball], q)[:, None]  # (B, 1, 3)
        sl = slice(3 * k, 3 * k + 3)
        out.append(_pick(euler_zyx_solutions(zmat, cur[..., 2].expand(zmat.shape[:-2])), cur,
                         tc["lower"][sl], tc["upper"][sl], tc["angular"][sl]))
    return torch.cat(out, -1)


def _dot(a: Tensor, b: Tensor) -> Tensor:
    return (a * b).sum(-1)


def chain_ik(plan: ChainIK, q: Tensor, positions: Tensor, mode: str = "prune", tol: float = 1e-4,
             collinear_tol: float | None = None) -> IKResult:
    """Closed-form IK of a chain for every leaf of every hypothesis.

    Args:
        plan: from `ik_plan`.
        q: (..., D) current poses (every dof outside the chain is kept).
        positions: (..., L, n+1, 3) target world positions of the chain's joints (root first; the
            root must be q's own), e.g. `Tree.positions`.
        mode: "prune" (flag leaves outside the limits) or "project" (clamp them into the limits).
        tol: metres; `exact` when the closed form lands every chain joint within tol of its target.
        collinear_tol: sine of the angle between a limb's two links below which it counts as
            straight (twist kept); default 1000 x the dtype's epsilon.

    Returns:
        `IKResult` (leading dims `...` in place of N); dtype and device follow q.
    """
    if mode not in MODES:
        raise InputError(f"chain_ik: mode must be one of {', '.join(MODES)}, got {mode!r}")
    sk, chain = plan.sk, plan.chain
    if not isinstance(q, Tensor) or not q.is_floating_point() or q.ndim < 1 or q.shape[-1] != sk.num_dofs:
        raise InputError(f"chain_ik: q must be a floating tensor (..., {sk.num_dofs}), got "
                         f"{tuple(getattr(q, 'shape', ()))}")
    n1 = chain.num_links + 1
    if not isinstance(positions, Tensor) or positions.shape[-2:] != (n1, 3) \
            or positions.shape[:-3] != q.shape[:-1]:
        raise InputError(f"chain_ik: positions must be (..., L, {n1}, 3) with q's batch dims "
                         f"{tuple(q.shape[:-1])} for chain {chain.name!r}, got "
                         f"{tuple(getattr(positions, 'shape', ()))}")
    batch, leaves = q.shape[:-1], positions.shape[-3]
    tc = _tensors(plan, q.dtype, q.device)
    qf = q.reshape(-1, sk.num_dofs)
    x = positions.to(q).reshape(-1, leaves, n1, 3)
    ctol = 1000 * torch.finfo(q.dtype).eps if collinear_tol is None else collinear_tol
    g_r, p_r = _ancestors(plan, tc, qf)
    if plan.kind == "limb":
        theta = _limb(plan, tc, g_r, qf, x, ctol)
    else:
        theta = _swing(plan, tc, g_r, p_r, qf, x)
    lower, upper, angular = tc["lower"], tc["upper"], tc["angular"]
    theta = wrap_to_limits(theta, lower, upper, angular)
    in_limits = (outside_limits(theta, lower, upper) == 0).all(-1)
    g_l, p_l = g_r[:, None], p_r[:, None]

    def fk(th: Tensor) -> Tensor:
        return _path_fk(plan, tc, g_l, p_l, qf[:, None], _solved(plan, tc, th))

    pos = fk(theta)
    residual = torch.linalg.vector_norm(pos - x, dim=-1).amax(-1)
    exact = residual <= tol
    projected = torch.zeros_like(in_limits)
    if mode == "project":
        clamped = torch.clamp(theta, lower, upper)
        projected = ~in_limits
        theta = torch.where(projected[..., None], clamped, theta)
        pos = torch.where(projected[..., None, None], fk(theta), pos)
        keep = exact
    else:
        keep = exact & in_limits
    out_q = qf[:, None].expand(-1, leaves, -1).clone()
    out_q.index_copy_(-1, tc["dofs"], theta)
    lead = (*batch, leaves)
    return IKResult(q=out_q.reshape(*lead, sk.num_dofs), positions=pos.reshape(*lead, n1, 3),
                    residual=residual.reshape(lead), exact=exact.reshape(lead),
                    in_limits=in_limits.reshape(lead), keep=keep.reshape(lead),
                    projected=projected.reshape(lead), dofs=plan.dofs)


def _solved(plan: ChainIK, tc: dict, theta: Tensor) -> dict[int, Tensor]:
    """Solved angle vector (..., M) -> slot angles {joint: (..., 3)} for `_path_fk`."""
    out = {b: theta[..., 3 * i:3 * i + 3] for i, b in enumerate(plan.balls)}
    if plan.kind == "limb":
        hinge = tc["per"][plan.hinge]
        slots = hinge["frozen"].expand(*theta.shape[:-1], 3)
        out[plan.hinge] = slots.index_copy(-1, torch.as_tensor([plan.hinge_slot], device=theta.device),
                                           theta[..., 3:4])
    return out


def product_ik(q: Tensor, results: list[IKResult], prod: Product) -> IKResult:
    """Combine per-chain IK over a product of trees: q (..., D) and each chain's result over its own
    leaves -> one result over the combined leaves (..., L): each chain's dofs from its leaf, flags
    AND-ed (`positions` stacks the chains' joints in chain order, (..., L, sum(n_c + 1), 3);
    `residual` is the largest). The chains must be independent (`jumps.check_independent`)."""
    if len(results) != len(prod.chains):
        raise InputError(f"product_ik: {len(results)} results for {len(prod.chains)} chains")
    total = prod.flips.shape[0]
    out_q = q[..., None, :].expand(*q.shape[:-1], total, q.shape[-1]).clone()
    pos, res = [], []
    keep = exact = in_limits = projected = None
    for c, r in enumerate(results):
        sel = prod.leaf[:, c]
        dofs = torch.as_tensor(r.dofs, device=q.device)
        out_q.index_copy_(-1, dofs, r.q.index_select(-2, sel).index_select(-1, dofs))
        pos.append(r.positions.index_select(-3, sel))
        res.append(r.residual.index_select(-1, sel))
        flags = [f.index_select(-1, sel) for f in (r.keep, r.exact, r.in_limits, r.projected)]
        if keep is None:
            keep, exact, in_limits, projected = flags
        else:
            keep, exact, in_limits = keep & flags[0], exact & flags[1], in_limits & flags[2]
            projected = projected | flags[3]
    return IKResult(q=out_q, positions=torch.cat(pos, -2), residual=torch.stack(res, -1).amax(-1),
                    exact=exact, in_limits=in_limits, keep=keep, projected=projected,
                    dofs=tuple(d for r in results for d in r.dofs))


__all__ = ["ChainIK", "ClosedFormUnavailable", "IKResult", "MODES", "chain_ik", "euler_zyx_solutions",
           "ik_plan", "product_ik"]
