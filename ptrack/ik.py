"""Inverse kinematics for interpretation-tree leaves: a chain's joint positions -> joint angles.

    plan = ik_plan(sk, chain)                     # raises ClosedFormUnavailable if no closed form
    res = chain_ik(plan, q, tree.positions, mode="prune")   # q (N, D), positions (N, L, n+1, 3)
    res.angles, res.q                             # (N, L, M) solved dofs; (N, L, D) full poses

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
(as `ptrack.limits.wrap_to_limits`; unlimited angles in [-pi, pi)). Leaves whose angles still
break the limits are flagged for `mode="prune"`, or clamped into them and re-run through the
chain's forward kinematics for `mode="project"`. The chain's root must stay where q's forward
kinematics puts it; bone lengths are the model's (`sk.lengths`). Joints past the chain's end
(hand, foot) follow through q's own angles below it.

Not here yet: the iterative fallback for chains without a closed form (URDF models, other
structures) and for leaves whose closed form missed (`IKResult.exact` False: targets that break the
model's bone lengths). It is to minimise |FK(q)[chain joints] - positions|^2 over `dofs` with the
shared solver (`ptrack.solvers.levenberg_marquardt`, Jacobians from `ptrack.jacobians`), within
the limits, and return an `IKResult`; callers catch `ClosedFormUnavailable` from `ik_plan` (which
names the chain and the joint that breaks the closed form) to take that path.

Layout: the solvers work on struct-of-arrays tensors (`ptrack.jumps`), hypotheses last; inputs and
outputs are ordinary batch-first tensors. Shapes: `N` hypotheses (any leading batch dims), `L`
leaves, `D` dofs, `M` solved dofs, n links.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ptrack.errors import InputError
from ptrack.jumps import (Chain, Product, _aos, _flatten_bits, _sconst, _scross, _sdot, _seye, _smin_rotation,
                          _smm, _smv, _snorm, _soa, _st, _sunit, path_below)
from ptrack.limits import TAU
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
    names = chain.joint_names
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
    # the dofs IK reads, as rows of qs (the transposed q it works on)
    used = sorted({int(d) for j in joints for d in sk.axis_dof[j] if d >= 0}
                  | {int(d) for d in sk.translation_dof if d >= 0} | set(plan.dofs))
    row = {d: i for i, d in enumerate(used)}

    def rows(ds) -> Tensor:
        return torch.as_tensor([row.get(int(d), 0) for d in ds], device=device)

    per = {}
    for j in joints:
        c = _frame(sk, j)
        k1 = np.stack([np.cross(np.eye(3), a) for a in sk.axes[j]])  # k1[s] @ v = axes[s] x v
        per[j] = dict(
            index=rows(sk.axis_dof[j]),
            mask=t(sk.axis_dof[j] >= 0)[:, None],
            frozen=t(np.where(sk.axis_dof[j] >= 0, 0.0, sk.frozen_axes[j]))[:, None],
            c=None if c is None else t(c),
            k1=t(k1), k2=t(k1 @ k1),
            rest=None if np.allclose(sk.rest_rotation[j], np.eye(3)) else t(sk.rest_rotation[j]),
            u=None if not np.any(sk.offset_parent[j]) else t(sk.offset_parent[j] * sk.lengths[j]),
            w=t(sk.offset_local[j] * sk.lengths[j]),
        )
    lower, upper = sk.limits(dtype=dtype, device=device)
    dofs = torch.as_tensor(plan.dofs, device=device)
    out = dict(per=per, dofs=dofs, lower=lower[dofs], upper=upper[dofs],
               shift=_window_shift(lower[dofs], upper[dofs]),
               used=torch.as_tensor(used, device=device), hinge_row=row[plan.dofs[-1]],
               root_position=t(sk.root_position)[:, None],
               trans_index=rows(sk.translation_dof),
               trans_mask=t(sk.translation_dof >= 0)[:, None])
    if plan.kind == "limb":
        lc = _limb_constants(plan)
        lt = {k: (t(v) if isinstance(v, np.ndarray) else float(v)) for k, v in lc.items()}
        lt.update(ncross=torch.linalg.cross(lt["n"], lt["c"], dim=-1), nc=float(lc["n"] @ lc["c"]),
                  a_unit=lt["a"] / torch.linalg.vector_norm(lt["a"]),
                  length_m=float(sk.lengths[plan.balls[0]]), length_e=float(sk.lengths[plan.hinge]))
        out["limb"] = lt
    plan._cache[key] = out
    return out


# ---------------------------------------------------------------- forward kinematics along a path
# Struct-of-arrays layout (see `ptrack.jumps`): angles (3, *M), rotations (3, 3, *M), positions
# (3, *M), with M = (L, B) or (B,): leaves, then hypotheses last.


def _slot_angles(pj: dict, qs: Tensor) -> Tensor:
    """Slot angles of one joint (frozen slots at their value): qs (D', B) -> (3, B)."""
    return qs.index_select(0, pj["index"]) * pj["mask"] + pj["frozen"]


def _seuler(theta: Tensor) -> Tensor:
    """Rz(z) Ry(y) Rx(x) for theta (3, *M) = (z, y, x) -> (3, 3, *M) (as `kinematics.euler_zyx`)."""
    s, c = torch.sin(theta), torch.cos(theta)
    sz, sy, sx = s
    cz, cy, cx = c
    czsy, szsy = cz * sy, sz * sy
    return torch.stack([
        cz * cy, czsy * sx - sz * cx, czsy * cx + sz * sx,
        sz * cy, szsy * sx + cz * cx, szsy * cx - cz * sx,
        -sy, cy * sx, cy * cx,
    ]).unflatten(0, (3, 3))


def _local(pj: dict, theta: Tensor) -> Tensor:
    """A joint's rotation relative to its parent for slot angles theta (3, *M) -> (3, 3, *M)."""
    nd = theta.ndim - 1
    if pj["c"] is not None:
        c = _sconst(pj["c"], nd)
        r = _smm(_smm(c, _seuler(theta)), _st(c))
    else:
        eye = _seye(theta, nd)
        r = None
        for s in range(3):
            rs = eye + torch.sin(theta[s]) * _sconst(pj["k1"][s], nd) \
                + (1 - torch.cos(theta[s])) * _sconst(pj["k2"][s], nd)
            r = rs if r is None else _smm(r, rs)
    return r if pj["rest"] is None else _smm(r, _sconst(pj["rest"], nd))


def _step(pj: dict, g_par: Tensor, p_par: Tensor, theta: Tensor) -> tuple[Tensor, Tensor]:
    """One joint of forward kinematics: parent frame (3, 3, *M) and position (3, *M) -> this joint's."""
    g = _smm(g_par, _local(pj, theta))
    nd = g.ndim - 2
    p = p_par + _smv(g, _sconst(pj["w"], nd))
    if pj["u"] is not None:
        p = p + _smv(g_par, _sconst(pj["u"], nd))
    return g, p


def _ancestors(plan: ChainIK, tc: dict, qs: Tensor) -> tuple[Tensor, Tensor]:
    """World rotation (3, 3, B) and position (3, B) of the chain's root joint for qs (D', B)."""
    per = tc["per"]
    root = plan.ancestors[0]
    g = _local(per[root], _slot_angles(per[root], qs))
    p = qs.index_select(0, tc["trans_index"]) * tc["trans_mask"] + tc["root_position"] \
        + _smv(g, _sconst(per[root]["w"], 1))
    for j in plan.ancestors[1:]:
        g, p = _step(per[j], g, p, _slot_angles(per[j], qs))
    return g, p


def _path_fk(plan: ChainIK, tc: dict, g: Tensor, p: Tensor, qs: Tensor, solved: dict[int, Tensor]) -> Tensor:
    """Positions (n+1, 3, L, B) of the chain's joints from the root frame g (3, 3, 1, B), position
    p (3, 1, B), solved slot angles {joint: (3, L, B)} and qs (D', B) for the other path joints."""
    per = tc["per"]
    pos = {plan.chain.joints[0]: p}
    for j in plan.path:
        theta = solved[j] if j in solved else _slot_angles(per[j], qs)[:, None]
        g, p = _step(per[j], g, p, theta)
        pos[j] = p
    return torch.stack(torch.broadcast_tensors(*(pos[j] for j in plan.chain.joints)))


# ---------------------------------------------------------------- rotation -> angles


def _seuler_solutions(r: Tensor, x_lock: Tensor) -> Tensor:
    """`euler_zyx_solutions` on r (3, 3, *M), x_lock (*M) -> (3, 2, *M) (angle, solution)."""
    r20, r21, r22 = r[2, 0], r[2, 1], r[2, 2]
    lock = torch.hypot(r21, r22) <= 64 * torch.finfo(r.dtype).eps
    x = torch.where(lock, x_lock, torch.atan2(r21, r22))
    sx, cx = torch.sin(x), torch.cos(x)
    y = torch.atan2(-r20, sx * r21 + cx * r22)
    z = torch.atan2(sx * r[0, 2] - cx * r[0, 1], cx * r[1, 1] - sx * r[1, 2])
    return torch.stack([torch.stack([z, z + math.pi]), torch.stack([y, math.pi - y]),
                        torch.stack([x, x + math.pi])])


def euler_zyx_solutions(r: Tensor, x_lock: Tensor) -> Tensor:
    """Both (z, y, x) angle triples with Rz(z) Ry(y) Rx(x) = r: (..., 3, 3) -> (..., 2, 3); the
    first has |y| <= pi/2, the second is (z + pi, pi - y, x + pi) (not wrapped). At the gimbal lock
    (cos y = 0) x is taken from x_lock (...,) (e.g. the current angle) and z carries the rest.
    Day's extraction (as `ptrack.rotations.matrix_to_euler_np`): x from the last row, y and z given x."""
    out = _seuler_solutions(_soa(r, 2), x_lock.expand(r.shape[:-2]))  # (3, 2, ...)
    return _aos(out, 2).transpose(-1, -2)


def _window_shift(lower: Tensor, upper: Tensor) -> Tensor:
    """pi - centre of each dof's 2 pi window (M,): the arc's centre for two finite bounds, else 0;
    angle a is in its window as remainder(a + shift, 2 pi) - shift (`ptrack.limits.wrap_to_limits`)."""
    limited = torch.isfinite(lower) & torch.isfinite(upper)
    return math.pi - torch.where(limited, 0.5 * (lower + upper), torch.zeros_like(lower))


def _violation(theta: Tensor, tc: dict, sl: slice = slice(None)) -> tuple[Tensor, Tensor]:
    """Angles in their windows and their summed limit violation: theta (A, *M) (dofs tc[...][sl])
    -> (A, *M), (*M) radians."""
    nd = theta.ndim - 1
    shift = _sconst(tc["shift"][sl], nd)
    w = torch.remainder(theta + shift, TAU) - shift
    viol = (_sconst(tc["lower"][sl], nd) - w).clamp_min(0.0) + (w - _sconst(tc["upper"][sl], nd)).clamp_min(0.0)
    return w, viol.sum(0)


def _pick(cands: Tensor, current: Tensor, tc: dict, sl: slice = slice(None)) -> Tensor:
    """The candidate angle vector with least limit violation (radians, summed over dofs), ties
    within ~1e-6 going to the nearest to `current` (sum of 1 - cos of the differences):
    cands (A, K, *M), current (A, *M) broadcastable, limits of dofs tc[...][sl] -> (A, *M)."""
    _, viol = _violation(cands, tc, sl)  # (K, *M)
    near = (1.0 - torch.cos(cands - current.unsqueeze(1))).sum(0)
    score = viol + 1e-6 * near
    best, out = score[0], cands[:, 0]
    for k in range(1, cands.shape[1]):  # K is 2 or 4: cheaper than argmin + gather over dim 1
        better = score[k] < best
        best = torch.where(better, score[k], best)
        out = torch.where(better, cands[:, k], out)
    return out


# ---------------------------------------------------------------- solvers


class IKResult(NamedTuple):
    """IK of a chain (or of a product of chains) for L leaves per hypothesis.

    angles: (N, L, M) the solved dofs, in the limits' 2 pi window (clamped if projected).
    dofs: (M,) their q indices.
    start: (N, D) the poses IK started from; `q` (a property) writes the angles into them.
    positions: (N, L, n+1, 3) the chain's joints by forward kinematics of the solved pose (after
        projection; for a product, the chains' joints one chain after the other).
    residual: (N, L) metres, largest distance of the closed form's chain joints from the targets
        (before projection; ~0 unless the targets break the model's bone lengths).
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


def _lower_bone(lc: dict, t: Tensor) -> Tensor:
    """The limb's lower bone v(t) = D Rot(n, t) c in the ball's axis frame: t (*M) -> (3, *M)."""
    nd = t.ndim
    ct, st = torch.cos(t), torch.sin(t)
    rot_c = _sconst(lc["c"], nd) * ct + _sconst(lc["ncross"], nd) * st + _sconst(lc["n"] * lc["nc"], nd) * (1 - ct)
    return _smv(_sconst(lc["d"], nd), rot_c)


def _limb_fk(tc: dict, a_frame: Tensor, p_r: Tensor, theta: Tensor) -> Tensor:
    """Forward kinematics of a limb: positions (3, 3, L, B) of root, ball and hinge joints from the
    ball's parent axis frame a_frame = G_r C (3, 3, 1, B), root position p_r (3, 1, B) and angles
    theta (4, L, B). The ball joint's frame is G_r C Z C^T E (`ptrack.skeleton`), so its bone is
    G_r C Z a and the next one G_r C Z v(t)."""
    lc = tc["limb"]
    az = _smm(a_frame, _seuler(theta[:3]))
    p_m = p_r + lc["length_m"] * _smv(az, _sconst(lc["a"], 2))
    p_e = p_m + lc["length_e"] * _smv(az, _lower_bone(lc, theta[3]))
    return torch.stack(torch.broadcast_tensors(p_r, p_m, p_e))


def _limb(plan: ChainIK, tc: dict, a_frame: Tensor, qs: Tensor, x: Tensor, ctol: float) -> Tensor:
    """Limb angles (4, L, B) = ball (z, y, x), hinge, for targets x (3, 3, L, B) (joint, xyz, ...)."""
    lc = tc["limb"]
    cur_ball = _slot_angles(tc["per"][plan.balls[0]], qs)  # (3, B)
    cur = torch.cat([cur_ball, qs[tc["hinge_row"]][None]])  # (4, B)
    at = _st(a_frame)
    b1 = _sunit(_smv(at, x[1] - x[0]))  # (3, L, B) bone directions in the ball's parent axis frame
    b2 = _sunit(_smv(at, x[2] - x[1]))
    cos_k = _sdot(b1, b2)
    # a . v(t) = rho cos(t - phi) + gamma must equal |a||c| cos_k. Not with acos (which loses half
    # the digits at a straight limb): with h-, h+ = |b1 -+ b2|^2 / 2 (exact near 0 and pi) and
    # delta = rho - (|a||c| - gamma) <= 0, rho cos(t - phi) = rho - delta - |a||c| h-, and
    # rho^2 sin^2(t - phi) = (delta + |a||c| h-) (delta - 2 gamma + |a||c| h+).
    dm, dp = b1 - b2, b1 + b2
    hm, hp = 0.5 * _sdot(dm, dm), 0.5 * _sdot(dp, dp)
    ac, delta, gamma = lc["ac"], lc["delta"], lc["gamma"]
    sin_part = torch.sqrt(((delta + ac * hm) * (delta - 2.0 * gamma + ac * hp)).clamp_min(0.0))
    half = torch.atan2(sin_part, lc["rho"] - delta - ac * hm)
    t = lc["phi"] + torch.stack([half, -half])  # (2, L, B) hinge candidates
    v = _lower_bone(lc, t)  # (3, 2, L, B)
    # Z takes the frame (a, v(t)) onto the frame (b1, b2): Z = sum_i g_i f_i^T
    f1 = _sconst(lc["a_unit"], 3)
    f2 = _sunit(v - _sdot(v, f1) * f1)
    f3 = _scross(f1, f2)
    g2 = _sunit(b2 - cos_k * b1)
    g3 = _scross(b1, g2)
    z = b1[:, None, None] * f1[None] + g2[:, None, None] * f2[None] + g3[:, None, None] * f3[None]
    # straight limb: keep the current twist (smallest turn of the current upper bone onto b1)
    straight = _snorm(_scross(b1, b2)) < ctol  # (L, B)
    if bool(straight.any()):  # one host sync; skips ~60 ops when no leaf is straight
        z_cur = _seuler(cur_ball)[:, :, None]  # (3, 3, 1, B)
        z_swing = _smm(_smin_rotation(_smv(z_cur, _sconst(lc["a"], 2)).expand_as(b1), b1), z_cur)
        z = torch.where(straight, z_swing[:, :, None], z)  # (3, 3, 2, L, B)
    eul = _seuler_solutions(z, cur_ball[2])  # (3, 2 Euler, 2 hinge, L, B)
    cands = torch.cat([eul, t[None, None].expand(1, *eul.shape[1:])]).flatten(1, 2)  # (4, 4, L, B)
    return _pick(cands, cur[:, None], tc)


def _swing(plan: ChainIK, tc: dict, g_r: Tensor, p_r: Tensor, qs: Tensor, x: Tensor) -> Tensor:
    """Swing angles (3 n, L, B) (each ball's z, y, x) for targets x (n+1, 3, L, B)."""
    per = tc["per"]
    frames = {plan.chain.joints[0]: (g_r, p_r)}
    g, p = g_r, p_r
    for j in plan.path:  # current frames and positions along the path (per hypothesis)
        g, p = _step(per[j], g, p, _slot_angles(per[j], qs))
        frames[j] = (g, p)
    turn: Tensor | None = None
    out = []
    for k, ((pa, ch), ball) in enumerate(zip(plan.chain.links, plan.balls)):
        g_p = frames[pa][0][:, :, None]  # (3, 3, 1, B)
        link = (frames[ch][1] - frames[pa][1])[:, None]  # (3, 1, B)
        if turn is not None:
            g_p, link = _smm(turn, g_p), _smv(turn, link)
        target = x[k + 1] - x[k]
        delta = _smin_rotation(link.expand_as(target), target)
        turn = delta if turn is None else _smm(delta, turn)
        local = _smm(_st(g_p), _smm(turn, frames[ball][0][:, :, None]))
        if per[ball]["rest"] is not None:
            local = _smm(local, _sconst(per[ball]["rest"].T, 2))
        cb = _sconst(per[ball]["c"], 2)
        zmat = _smm(_smm(_st(cb), local), cb)
        cur = _slot_angles(per[ball], qs)[:, None]  # (3, 1, B)
        sl = slice(3 * k, 3 * k + 3)
        out.append(_pick(_seuler_solutions(zmat, cur[2]), cur, tc, sl))
    return torch.cat(out)


def _solved(plan: ChainIK, tc: dict, theta: Tensor) -> dict[int, Tensor]:
    """Solved angles (M, L, B) -> slot angles {joint: (3, L, B)} for `_path_fk` (swing chains)."""
    return {b: theta[3 * i:3 * i + 3] for i, b in enumerate(plan.balls)}


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
        `IKResult` (leading dims `...` in place of N); dtype and device follow q. Solved angles
        are in the limits' 2 pi window (unlimited ones in [-pi, pi)).
    """
    if mode not in MODES:
        raise InputError(f"chain_ik: mode must be one of {', '.join(MODES)}, got {mode!r}")
    sk, chain = plan.sk, plan.chain
    if not isinstance(q, Tensor) or not q.is_floating_point() or q.ndim < 1 or q.shape[-1] != sk.num_dofs:
        raise InputError(f"chain_ik: q must be a floating tensor (..., {sk.num_dofs}), got "
                         f"{tuple(getattr(q, 'shape', ()))}")
    n1 = chain.num_links + 1
    if not isinstance(positions, Tensor) or positions.ndim != q.ndim + 2 \
            or positions.shape[-2:] != (n1, 3) or positions.shape[:-3] != q.shape[:-1]:
        raise InputError(f"chain_ik: positions must be (..., L, {n1}, 3) with q's batch dims "
                         f"{tuple(q.shape[:-1])} for chain {chain.name!r}, got "
                         f"{tuple(getattr(positions, 'shape', ()))}")
    batch, leaves = q.shape[:-1], positions.shape[-3]
    tc = _tensors(plan, q.dtype, q.device)
    qf = q.reshape(-1, sk.num_dofs)
    qs = qf.index_select(1, tc["used"]).T.contiguous()  # (D', B): the dofs IK reads
    x = positions.to(q).reshape(-1, leaves, n1, 3).permute(2, 3, 1, 0).contiguous()  # (n+1, 3, L, B)
    ctol = 1000 * torch.finfo(q.dtype).eps if collinear_tol is None else collinear_tol
    g_r, p_r = _ancestors(plan, tc, qs)
    p_l = p_r[:, None]
    if plan.kind == "limb":
        a_frame = _smm(g_r, _sconst(tc["per"][plan.balls[0]]["c"], 1))[:, :, None]
        theta = _limb(plan, tc, a_frame, qs, x, ctol)

        def fk(th: Tensor) -> Tensor:
            return _limb_fk(tc, a_frame, p_l, th)
    else:
        theta = _swing(plan, tc, g_r, p_r, qs, x)
        g_l = g_r[:, :, None]

        def fk(th: Tensor) -> Tensor:
            return _path_fk(plan, tc, g_l, p_l, qs, _solved(plan, tc, th))

    theta, viol = _violation(theta, tc)  # in the limits' 2 pi windows
    in_limits = viol == 0  # (L, B)
    pos = fk(theta)
    diff = pos - x
    residual = torch.sqrt((diff * diff).sum(1)).amax(0)
    exact = residual <= tol
    projected = torch.zeros_like(in_limits)
    if mode == "project":
        projected = ~in_limits
        clamped = torch.clamp(theta, _sconst(tc["lower"], 2), _sconst(tc["upper"], 2))
        theta = torch.where(projected, clamped, theta)
        pos = torch.where(projected, fk(theta), pos)
        keep = exact
    else:
        keep = exact & in_limits
    lead = (*batch, leaves)

    def flags(f: Tensor) -> Tensor:
        return f.T.contiguous().reshape(lead)

    return IKResult(angles=theta.permute(2, 1, 0).contiguous().reshape(*lead, -1), dofs=plan.dofs, start=q,
                    positions=pos.permute(3, 2, 0, 1).contiguous().reshape(*lead, n1, 3),
                    residual=flags(residual), exact=flags(exact), in_limits=flags(in_limits),
                    keep=flags(keep), projected=flags(projected))


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
        angles[..., a_off:a_off + na] = prod.bits_view(c, r.angles, -2)
        positions[..., p_off:p_off + npos, :] = prod.bits_view(c, r.positions, -3)
        a_off, p_off = a_off + na, p_off + npos
    flags = {}
    for name, combine in (("keep", torch.logical_and), ("exact", torch.logical_and),
                          ("in_limits", torch.logical_and), ("projected", torch.logical_or),
                          ("residual", torch.maximum)):
        x = prod.bits_view(0, getattr(first, name), -1)
        for c, r in enumerate(results[1:], start=1):
            x = combine(x, prod.bits_view(c, getattr(r, name), -1))
        flags[name] = _flatten_bits(x, start, nb)
    return IKResult(angles=angles.flatten(start, start + nb - 1), dofs=tuple(d for r in results for d in r.dofs),
                    start=q, positions=positions.flatten(start, start + nb - 1), **flags)


__all__ = ["ChainIK", "ClosedFormUnavailable", "IKResult", "MODES", "chain_ik", "euler_zyx_solutions",
           "ik_plan", "product_ik"]
