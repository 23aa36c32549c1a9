"""Inverse kinematics for interpretation-tree leaves: a chain's joint positions -> joint angles.

    plan = ik_plan(sk, chain)                     # "limb", "swing" or "iterative"
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
(as `ptrack.body.limits.wrap_to_limits`; unlimited angles in [-pi, pi)). Leaves whose angles still
break the limits are flagged for `mode="prune"`, or clamped into them and re-run through the
chain's forward kinematics for `mode="project"`. The chain's root must stay where q's forward
kinematics puts it; bone lengths are the model's (`sk.lengths`). Joints past the chain's end
(hand, foot) follow through q's own angles below it.

The iterative fallback ("iterative"): for chains with no closed form (URDF models, whose joints
are 1-dof revolutes; ASF chains that are neither limb nor swing; `ik_plan(..., closed_form=False)`
forces it) it minimises |FK(q)[chain joints] - positions|^2 over the plan's dofs -- those of the
path joints (and of the chain root when its bone end is on its pivot, as URDF links are) that
move the chain's joints -- with the shared batched Levenberg-Marquardt
(`ptrack.optim.solvers.levenberg_marquardt`) over hypotheses x leaves at once, from q's own angles,
with the geometric Jacobian (`ptrack.optim.jacobians`) restricted to the chain. "prune" solves
unbounded and flags leaves whose angles (wrapped into the limits' windows) break the limits;
"project" solves those leaves again within the limits (box constraints) from their clamped
angles. `ik_plan` raises `ClosedFormUnavailable` only when no dof moves the chain. Closed-form
leaves that miss their targets (`exact` False: numerical trouble, or targets that break the
model's bone lengths) are refined by the same fit from the closed form's angles
(`chain_ik(..., refine=True)`); when every leaf is exact this costs one host sync.

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

Layout: the solvers work on struct-of-arrays tensors (`ptrack.hypotheses.jumps`), hypotheses last; inputs and
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

from ptrack.body.kinematics import euler_zyx
from ptrack.body.limits import TAU
from ptrack.body.skeleton import Skeleton
from ptrack.errors import InputError
from ptrack.hypotheses.jumps import (
    Chain,
    Product,
    flatten_bits,
    path_below,
    sconst,
    scross,
    sdot,
    seye,
    smin_rotation,
    smm,
    smv,
    snorm,
    stranspose,
    sunit,
    to_aos,
    to_soa,
)
from ptrack.optim.solvers import levenberg_marquardt

MODES = ("prune", "project")


class ClosedFormUnavailable(InputError):
    """No inverse kinematics for the chain: no dof moves its joints with its root in place (chains
    without a closed form take the iterative fallback instead)."""


@dataclass(frozen=True, eq=False)
class ChainIK:
    """How to solve one chain: made by `ik_plan`.

    kind: "limb", "swing" or "iterative" (module docstring). ancestors: joints from the skeleton
    root to the chain root. path: joints below the chain root down to its end. balls: joints whose
    three angles are solved in closed form (none for iterative); hinge: the limb's hinge joint (-1
    otherwise) and hinge_slot its driven axis slot. dofs: (M,) q indices set: each ball's slots
    (z, y, x) then the hinge's; for iterative, the moving dofs in path order.
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
    return (
        bool(np.all(sk.axis_dof[j] >= 0))
        and _frame(sk, j) is not None
        and not np.any(sk.offset_parent[j])
        and sk.lengths[j] > 0
    )


def ik_plan(sk: Skeleton, chain: Chain, closed_form: bool = True) -> ChainIK:
    """How to solve `chain` on `sk`: a closed form ("limb" or "swing") where one applies, else
    (or with closed_form=False) "iterative" over the dofs of the chain root and path joints that
    move the chain's joints (`_moving_dofs`). Raises ClosedFormUnavailable (an InputError) naming
    the chain when no dof moves its joints (nothing to solve)."""
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
    if closed_form:
        if chain.num_links == 2 and path == list(chain.joints[1:]) and _is_ball(sk, path[0]):
            e = path[1]
            driven = np.flatnonzero(sk.axis_dof[e] >= 0)
            if len(driven) == 1 and not np.any(sk.offset_parent[e]) and sk.lengths[e] > 0:
                m = path[0]
                plan = ChainIK(
                    sk=sk,
                    chain=chain,
                    kind="limb",
                    ancestors=ancestors,
                    path=tuple(path),
                    balls=(m,),
                    hinge=e,
                    hinge_slot=int(driven[0]),
                    dofs=tuple(int(d) for d in sk.axis_dof[m]) + (int(sk.axis_dof[e, driven[0]]),),
                )
                if _limb_constants(plan)["rho"] >= 1e-6:  # else the hinge does not bend the limb
                    return plan
        if all(_is_ball(sk, j) for j in firsts):
            return ChainIK(
                sk=sk,
                chain=chain,
                kind="swing",
                ancestors=ancestors,
                path=tuple(path),
                balls=tuple(firsts),
                hinge=-1,
                hinge_slot=-1,
                dofs=tuple(int(d) for j in firsts for d in sk.axis_dof[j]),
            )
    dofs = _moving_dofs(sk, chain, path)
    if not dofs:
        raise ClosedFormUnavailable(
            f"chain {chain.name!r} on {sk.name!r}: no dof moves its joints {list(chain.joint_names[1:])} "
            f"while keeping its root {chain.joint_names[0]!r} in place; no inverse kinematics to solve"
        )
    return ChainIK(
        sk=sk,
        chain=chain,
        kind="iterative",
        ancestors=ancestors,
        path=tuple(path),
        balls=(),
        hinge=-1,
        hinge_slot=-1,
        dofs=dofs,
    )


def _moving_dofs(sk: Skeleton, chain: Chain, path: list[int]) -> tuple[int, ...]:
    """The dofs an iterative plan solves, in path order: those of each path joint that move a chain
    joint (one further down the path, or the joint itself when its bone end is off its pivot), and
    those of the chain root when its own bone end is on its pivot (URDF links: the root turns the
    chain without moving), so the root stays where q puts it."""
    targets = set(chain.joints[1:])
    walk = [chain.joints[0]] + path
    out: list[int] = []
    for i, j in enumerate(walk):
        off_pivot = bool(np.any(sk.offset_local[j])) and sk.lengths[j] > 0
        if i == 0 and off_pivot:
            continue  # an ASF bone end: turning its joint would move the chain's root
        if (j in targets and off_pivot) or targets & set(walk[i + 1 :]):
            out.extend(int(d) for d in sk.axis_dof[j] if d >= 0 and int(d) not in out)
    return tuple(out)


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
    assert c_m is not None  # the plan's ball joint has a frame (`_is_ball`)
    a = c_m.T @ sk.rest_rotation[m] @ sk.offset_local[m]
    p_rot = _slot_rotation(sk.axes[e, :k], sk.frozen_axes[e, :k])
    q_rot = _slot_rotation(sk.axes[e, k + 1 :], sk.frozen_axes[e, k + 1 :]) @ sk.rest_rotation[e]
    n = sk.axes[e, k] / np.linalg.norm(sk.axes[e, k])
    d = c_m.T @ sk.rest_rotation[m] @ p_rot
    c = q_rot @ sk.offset_local[e]
    a1 = d.T @ a
    alpha = a1 @ c - (a1 @ n) * (n @ c)
    beta = a1 @ np.cross(n, c)
    gamma = (a1 @ n) * (n @ c)
    rho, ac = math.hypot(alpha, beta), float(np.linalg.norm(a) * np.linalg.norm(c))
    return dict(
        a=a,
        d=d,
        n=n,
        c=c,
        alpha=alpha,
        beta=beta,
        gamma=gamma,
        rho=rho,
        ac=ac,
        delta=min(rho - (ac - gamma), 0.0),
        phi=math.atan2(beta, alpha),
    )


def _solved_slots(plan: ChainIK) -> dict[int, tuple[tuple[int, int], ...]]:
    """{joint: ((slot, column in plan.dofs), ...)} for the chain root and path joints whose slots
    drive a solved dof (the iterative solver's forward kinematics, `_walk_fk`)."""
    col = {d: m for m, d in enumerate(plan.dofs)}
    out = {}
    for j in (plan.chain.joints[0],) + plan.path:
        sl = tuple((s, col[int(d)]) for s, d in enumerate(plan.sk.axis_dof[j]) if int(d) in col)
        if sl:
            out[j] = sl
    return out


def _tensors(plan: ChainIK, dtype: torch.dtype, device: torch.device) -> dict:
    key = (dtype, str(device))
    out = plan._cache.get(key)
    if out is None:
        out = plan._cache[key] = _new_tensors(plan, dtype, device)
    return out


@torch.inference_mode(False)  # cached: ordinary tensors even when first built in a tracker's inference mode
def _new_tensors(plan: ChainIK, dtype: torch.dtype, device: torch.device) -> dict:
    sk = plan.sk

    def t(x):
        return torch.as_tensor(np.ascontiguousarray(x), dtype=dtype, device=device)

    joints = plan.ancestors + plan.path
    # the dofs IK reads, as rows of qs (the transposed q it works on)
    used = sorted(
        {int(d) for j in joints for d in sk.axis_dof[j] if d >= 0}
        | {int(d) for d in sk.translation_dof if d >= 0}
        | set(plan.dofs)
    )
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
            k1=t(k1),
            k2=t(k1 @ k1),
            rest=None if np.allclose(sk.rest_rotation[j], np.eye(3)) else t(sk.rest_rotation[j]),
            u=None if not np.any(sk.offset_parent[j]) else t(sk.offset_parent[j] * sk.lengths[j]),
            w=t(sk.offset_local[j] * sk.lengths[j]),
            axes=t(sk.axes[j]),
            # slots that turn (driven, or frozen at a nonzero angle); the others are the identity
            active=tuple(s for s in range(3) if sk.axis_dof[j, s] >= 0 or sk.frozen_axes[j, s] != 0.0),
        )
    lower, upper = sk.limits(dtype=dtype, device=device)
    dofs = torch.as_tensor(plan.dofs, device=device)
    out = dict(
        per=per,
        dofs=dofs,
        lower=lower[dofs],
        upper=upper[dofs],
        shift=_window_shift(lower[dofs], upper[dofs]),
        used=torch.as_tensor(used, device=device),
        hinge_row=row[plan.dofs[-1]],
        dof_rows=rows(plan.dofs),
        slots=_solved_slots(plan),
        root_position=t(sk.root_position)[:, None],
        trans_index=rows(sk.translation_dof),
        trans_mask=t(sk.translation_dof >= 0)[:, None],
    )
    if plan.kind == "limb":
        lc = _limb_constants(plan)
        lt = {k: (t(v) if isinstance(v, np.ndarray) else float(v)) for k, v in lc.items()}
        lt.update(
            ncross=torch.linalg.cross(lt["n"], lt["c"], dim=-1),
            nc=float(lc["n"] @ lc["c"]),
            a_unit=lt["a"] / torch.linalg.vector_norm(lt["a"]),
            length_m=float(sk.lengths[plan.balls[0]]),
            length_e=float(sk.lengths[plan.hinge]),
        )
        out["limb"] = lt
    return out


# ---------------------------------------------------------------- forward kinematics along a path
# Struct-of-arrays layout (see `ptrack.hypotheses.jumps`): angles (3, *M), rotations (3, 3, *M), positions
# (3, *M), with M = (L, B) or (B,): leaves, then hypotheses last.


def _slot_angles(pj: dict, qs: Tensor) -> Tensor:
    """Slot angles of one joint (frozen slots at their value): qs (D', B) -> (3, B)."""
    return qs.index_select(0, pj["index"]) * pj["mask"] + pj["frozen"]


def _seuler(theta: Tensor) -> Tensor:
    """Rz(z) Ry(y) Rx(x) for theta (3, *M) = (z, y, x) -> (3, 3, *M): `kinematics.euler_zyx` in this
    module's coordinates-first layout."""
    return euler_zyx(theta.movedim(0, -1)).movedim((-2, -1), (0, 1)).contiguous()


def _local(pj: dict, theta: Tensor) -> Tensor:
    """A joint's rotation relative to its parent for slot angles theta (3, *M) -> (3, 3, *M)."""
    nd = theta.ndim - 1
    if pj["c"] is not None:
        c = sconst(pj["c"], nd)
        r = smm(smm(c, _seuler(theta)), stranspose(c))
    else:
        eye = seye(theta, nd)
        rots = [
            eye + torch.sin(theta[s]) * sconst(pj["k1"][s], nd) + (1 - torch.cos(theta[s])) * sconst(pj["k2"][s], nd)
            for s in range(3)
        ]
        r = smm(smm(rots[0], rots[1]), rots[2])
    return r if pj["rest"] is None else smm(r, sconst(pj["rest"], nd))


def _step(pj: dict, g_par: Tensor, p_par: Tensor, theta: Tensor) -> tuple[Tensor, Tensor]:
    """One joint of forward kinematics: parent frame (3, 3, *M) and position (3, *M) -> this joint's."""
    g = smm(g_par, _local(pj, theta))
    nd = g.ndim - 2
    p = p_par + smv(g, sconst(pj["w"], nd))
    if pj["u"] is not None:
        p = p + smv(g_par, sconst(pj["u"], nd))
    return g, p


def _ancestors(plan: ChainIK, tc: dict, qs: Tensor) -> tuple[Tensor, Tensor]:
    """World rotation (3, 3, B) and position (3, B) of the chain's root joint for qs (D', B)."""
    per = tc["per"]
    root = plan.ancestors[0]
    g = _local(per[root], _slot_angles(per[root], qs))
    p = (
        qs.index_select(0, tc["trans_index"]) * tc["trans_mask"]
        + tc["root_position"]
        + smv(g, sconst(per[root]["w"], 1))
    )
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
    return torch.stack([torch.stack([z, z + math.pi]), torch.stack([y, math.pi - y]), torch.stack([x, x + math.pi])])


def euler_zyx_solutions(r: Tensor, x_lock: Tensor) -> Tensor:
    """Both (z, y, x) angle triples with Rz(z) Ry(y) Rx(x) = r: (..., 3, 3) -> (..., 2, 3); the
    first has |y| <= pi/2, the second is (z + pi, pi - y, x + pi) (not wrapped). At the gimbal lock
    (cos y = 0) x is taken from x_lock (...,) (e.g. the current angle) and z carries the rest.
    Day's extraction (as `ptrack.body.rotations.matrix_to_euler_np`): x from the last row, y and z given x."""
    out = _seuler_solutions(to_soa(r, 2), x_lock.expand(r.shape[:-2]))  # (3, 2, ...)
    return to_aos(out, 2).transpose(-1, -2)


def _window_shift(lower: Tensor, upper: Tensor) -> Tensor:
    """pi - centre of each dof's 2 pi window (M,): the arc's centre for two finite bounds, else 0;
    angle a is in its window as remainder(a + shift, 2 pi) - shift (`ptrack.body.limits.wrap_to_limits`)."""
    limited = torch.isfinite(lower) & torch.isfinite(upper)
    return math.pi - torch.where(limited, 0.5 * (lower + upper), torch.zeros_like(lower))


def _violation(theta: Tensor, tc: dict, sl: slice = slice(None)) -> tuple[Tensor, Tensor]:
    """Angles in their windows and their summed limit violation: theta (A, *M) (dofs tc[...][sl])
    -> (A, *M), (*M) radians."""
    nd = theta.ndim - 1
    shift = sconst(tc["shift"][sl], nd)
    w = torch.remainder(theta + shift, TAU) - shift
    viol = (sconst(tc["lower"][sl], nd) - w).clamp_min(0.0) + (w - sconst(tc["upper"][sl], nd)).clamp_min(0.0)
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


def _lower_bone(lc: dict, t: Tensor) -> Tensor:
    """The limb's lower bone v(t) = D Rot(n, t) c in the ball's axis frame: t (*M) -> (3, *M)."""
    nd = t.ndim
    ct, st = torch.cos(t), torch.sin(t)
    rot_c = sconst(lc["c"], nd) * ct + sconst(lc["ncross"], nd) * st + sconst(lc["n"] * lc["nc"], nd) * (1 - ct)
    return smv(sconst(lc["d"], nd), rot_c)


def _limb_fk(tc: dict, a_frame: Tensor, p_r: Tensor, theta: Tensor) -> Tensor:
    """Forward kinematics of a limb: positions (3, 3, L, B) of root, ball and hinge joints from the
    ball's parent axis frame a_frame = G_r C (3, 3, 1, B), root position p_r (3, 1, B) and angles
    theta (4, L, B). The ball joint's frame is G_r C Z C^T E (`ptrack.body.skeleton`), so its bone is
    G_r C Z a and the next one G_r C Z v(t)."""
    lc = tc["limb"]
    az = smm(a_frame, _seuler(theta[:3]))
    p_m = p_r + lc["length_m"] * smv(az, sconst(lc["a"], 2))
    p_e = p_m + lc["length_e"] * smv(az, _lower_bone(lc, theta[3]))
    return torch.stack(torch.broadcast_tensors(p_r, p_m, p_e))


def _limb(plan: ChainIK, tc: dict, a_frame: Tensor, qs: Tensor, x: Tensor, ctol: float) -> Tensor:
    """Limb angles (4, L, B) = ball (z, y, x), hinge, for targets x (3, 3, L, B) (joint, xyz, ...)."""
    lc = tc["limb"]
    cur_ball = _slot_angles(tc["per"][plan.balls[0]], qs)  # (3, B)
    cur = torch.cat([cur_ball, qs[tc["hinge_row"]][None]])  # (4, B)
    at = stranspose(a_frame)
    b1 = sunit(smv(at, x[1] - x[0]))  # (3, L, B) bone directions in the ball's parent axis frame
    b2 = sunit(smv(at, x[2] - x[1]))
    cos_k = sdot(b1, b2)
    # a . v(t) = rho cos(t - phi) + gamma must equal |a||c| cos_k. Not with acos (which loses half
    # the digits at a straight limb): with h-, h+ = |b1 -+ b2|^2 / 2 (exact near 0 and pi) and
    # delta = rho - (|a||c| - gamma) <= 0, rho cos(t - phi) = rho - delta - |a||c| h-, and
    # rho^2 sin^2(t - phi) = (delta + |a||c| h-) (delta - 2 gamma + |a||c| h+).
    dm, dp = b1 - b2, b1 + b2
    hm, hp = 0.5 * sdot(dm, dm), 0.5 * sdot(dp, dp)
    ac, delta, gamma = lc["ac"], lc["delta"], lc["gamma"]
    sin_part = torch.sqrt(((delta + ac * hm) * (delta - 2.0 * gamma + ac * hp)).clamp_min(0.0))
    half = torch.atan2(sin_part, lc["rho"] - delta - ac * hm)
    t = lc["phi"] + torch.stack([half, -half])  # (2, L, B) hinge candidates
    v = _lower_bone(lc, t)  # (3, 2, L, B)
    # Z takes the frame (a, v(t)) onto the frame (b1, b2): Z = sum_i g_i f_i^T
    f1 = sconst(lc["a_unit"], 3)
    f2 = sunit(v - sdot(v, f1) * f1)
    f3 = scross(f1, f2)
    g2 = sunit(b2 - cos_k * b1)
    g3 = scross(b1, g2)
    z = b1[:, None, None] * f1[None] + g2[:, None, None] * f2[None] + g3[:, None, None] * f3[None]
    # straight limb: keep the current twist (smallest turn of the current upper bone onto b1)
    straight = snorm(scross(b1, b2)) < ctol  # (L, B)
    if bool(straight.any()):  # one host sync; skips ~60 ops when no leaf is straight
        z_cur = _seuler(cur_ball)[:, :, None]  # (3, 3, 1, B)
        z_swing = smm(smin_rotation(smv(z_cur, sconst(lc["a"], 2)).expand_as(b1), b1), z_cur)
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
            g_p, link = smm(turn, g_p), smv(turn, link)
        target = x[k + 1] - x[k]
        delta = smin_rotation(link.expand_as(target), target)
        turn = delta if turn is None else smm(delta, turn)
        local = smm(stranspose(g_p), smm(turn, frames[ball][0][:, :, None]))
        if per[ball]["rest"] is not None:
            local = smm(local, sconst(per[ball]["rest"].T, 2))
        cb = sconst(per[ball]["c"], 2)
        zmat = smm(smm(stranspose(cb), local), cb)
        cur = _slot_angles(per[ball], qs)[:, None]  # (3, 1, B)
        sl = slice(3 * k, 3 * k + 3)
        out.append(_pick(_seuler_solutions(zmat, cur[2]), cur, tc, sl))
    return torch.cat(out)


def _solved(plan: ChainIK, tc: dict, theta: Tensor) -> dict[int, Tensor]:
    """Solved angles (M, L, B) -> slot angles {joint: (3, L, B)} for `_path_fk` (swing chains)."""
    return {b: theta[3 * i : 3 * i + 3] for i, b in enumerate(plan.balls)}


# ---------------------------------------------------------------- iterative fallback
# Flat problems: P = leaves x hypotheses (or the leaves being refined), last, as in the rest of the
# module; the solver sees them as its N problems, (P, M) angles.


def _root_parent(plan: ChainIK, tc: dict, qs: Tensor) -> tuple[Tensor, Tensor]:
    """World frame (3, 3, B) of the chain root's parent (identity for the skeleton root) and the
    root's pivot (3, B) (where its rotation turns about) for qs (D', B)."""
    per, anc = tc["per"], plan.ancestors
    pivot = qs.index_select(0, tc["trans_index"]) * tc["trans_mask"] + tc["root_position"]
    if len(anc) == 1:
        return seye(pivot, 1).expand(3, 3, *pivot.shape[1:]), pivot
    g = _local(per[anc[0]], _slot_angles(per[anc[0]], qs))
    p = pivot + smv(g, sconst(per[anc[0]]["w"], 1))
    for j in anc[1:-1]:
        g, p = _step(per[j], g, p, _slot_angles(per[j], qs))
    u = per[anc[-1]]["u"]
    return g, (p if u is None else p + smv(g, sconst(u, 1)))


def _turn_vector(pj: dict, s: int, angle: Tensor, v: Tensor) -> Tensor:
    """Rot(axes[s], angle) v (Rodrigues) for angle (P,), v (3, P) -> (3, P)."""
    kv = smv(sconst(pj["k1"][s], 1), v)
    return v + torch.sin(angle) * kv + (1 - torch.cos(angle)) * smv(sconst(pj["k1"][s], 1), kv)


def _walk_local(pj: dict, theta: Tensor) -> Tensor:
    """`_local` turning only the joint's active slots (URDF joints drive one slot of three, fixed
    joints none): theta (3, P) -> (3, 3, P), or (3, 3, 1) for a joint that does not turn."""
    if pj["c"] is not None and len(pj["active"]) == 3:
        return _local(pj, theta)
    r = None
    for s in pj["active"]:
        rs = (
            seye(theta, 1)
            + torch.sin(theta[s]) * sconst(pj["k1"][s], 1)
            + (1 - torch.cos(theta[s])) * sconst(pj["k2"][s], 1)
        )
        r = rs if r is None else smm(r, rs)
    if r is None:
        return seye(theta, 1) if pj["rest"] is None else sconst(pj["rest"], 1)
    return r if pj["rest"] is None else smm(r, sconst(pj["rest"], 1))


def _walk_fk(
    plan: ChainIK, tc: dict, g_par: Tensor, pivot: Tensor, qs: Tensor, theta: Tensor, jacobian: bool
) -> tuple[Tensor, Tensor | None]:
    """Forward kinematics from the chain root down its path with the solved dofs set, and the
    geometric Jacobian of the chain's joints w.r.t. them (`ptrack.optim.jacobians`, restricted to the
    chain: slot s of joint i turns the joints below about its world axis a through its pivot o_i,
    d p_y / d theta = a x (p_y - o_i)).

    g_par (3, 3, P), pivot (3, P) from `_root_parent`; qs (D', P) the other dofs; theta (M, P)
    -> positions (n+1, 3, P), jacobian (n, 3, M, P) of joints 1..n (None unless asked).
    """
    per, slots, chain = tc["per"], tc["slots"], plan.chain
    walk = (chain.joints[0],) + plan.path
    pos: dict[int, Tensor] = {}
    columns = []  # (column, walk index, world axis (3, P), pivot (3, P))
    g_p, p_p = g_par, pivot  # the parent frame and position (p_p unread at the chain root)
    for i, j in enumerate(walk):
        pj = per[j]
        th = _slot_angles(pj, qs)
        if j in slots:
            rows = list(th.unbind(0))
            for s, m in slots[j]:
                rows[s] = theta[m]
            th = torch.stack(rows)
        o = pivot if i == 0 else (p_p if pj["u"] is None else p_p + smv(g_p, sconst(pj["u"], 1)))
        if jacobian:
            for s, m in slots.get(j, ()):
                v = sconst(pj["axes"][s], 1)
                for r in reversed([r for r in pj["active"] if r < s]):  # a = G_parent Rot(a_0, th_0) ... a_s
                    v = _turn_vector(pj, r, th[r], v)
                columns.append((m, i, smv(g_p, v), o))
        g_p = smm(g_p, _walk_local(pj, th))
        p_p = o + smv(g_p, sconst(pj["w"], 1))
        pos[j] = p_p
    out = torch.stack(torch.broadcast_tensors(*(pos[j] for j in chain.joints)))
    if not jacobian:
        return out, None
    at = {j: i for i, j in enumerate(walk)}
    jac = theta.new_zeros(chain.num_links, 3, theta.shape[0], out.shape[-1])
    for m, i, a, o in columns:
        for k, y in enumerate(chain.joints[1:]):
            if at[y] >= i:
                jac[k, :, m] += scross(a, pos[y] - o)
    return out, jac


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
        pos, jac = _walk_fk(plan, tc, g_par, pivot, qs, th.T, True)
        assert jac is not None  # asked for
        r = torch.where(bad, 0.0, pos[1:] - target).permute(2, 0, 1).reshape(p, 3 * n)
        return r, torch.where(bad, 0.0, jac).permute(3, 0, 1, 2).reshape(p, 3 * n, m)

    return linearize


def _iterative(
    plan: ChainIK, tc: dict, qs: Tensor, x: Tensor, mode: str, tol: float, max_iter: int
) -> tuple[Tensor, ...]:
    """Iterative IK of every leaf from the hypothesis's own angles: qs (D', B), x (n+1, 3, L, B)
    -> theta (M, L, B), positions (n+1, 3, L, B), residual, exact, in_limits, keep, projected (L, B).
    Solved unbounded and wrapped into the limits' windows; in "project" mode the leaves outside
    the limits are solved again inside them (box constraints), from their clamped angles."""
    n1, _, leaves, b = x.shape
    g_par, pivot = _root_parent(plan, tc, qs)

    def tile(t: Tensor) -> Tensor:  # (..., B) -> (..., L B), leaf-major
        return t.unsqueeze(-2).expand(*t.shape[:-1], leaves, b).reshape(*t.shape[:-1], leaves * b)

    gp, pv, qp = tile(g_par), tile(pivot), tile(qs)
    xp = x.reshape(n1, 3, leaves * b)
    theta = _fit(plan, tc, gp, pv, qp, xp, tile(qs.index_select(0, tc["dof_rows"])), False, max_iter)
    theta, viol = _violation(theta, tc)
    pos, _ = _walk_fk(plan, tc, gp, pv, qp, theta, False)
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
            sub = _violation(sub, tc)[0]  # unlimited dofs back into [-pi, pi)
            theta[:, i] = sub
            pos[..., i] = _walk_fk(plan, tc, gp[..., i], pv[:, i], qp[:, i], sub, False)[0]
        keep = exact
    else:
        keep = exact & in_limits

    def lb(t: Tensor) -> Tensor:
        return t.unflatten(-1, (leaves, b))

    return (lb(theta), lb(pos), lb(residual), lb(exact), lb(in_limits), lb(keep), lb(projected))


def _refine(
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
    g_par, pivot = _root_parent(plan, tc, qs)
    g_par, pivot, qs_p, xp = g_par[..., bi], pivot[:, bi], qs[:, bi], x[:, :, li, bi]
    sub = _fit(plan, tc, g_par, pivot, qs_p, xp, theta[:, li, bi], False, max_iter)
    sub, sub_viol = _violation(sub, tc)
    sub_pos, _ = _walk_fk(plan, tc, g_par, pivot, qs_p, sub, False)
    diff = sub_pos - xp
    sub_res = torch.sqrt((diff * diff).sum(1)).amax(0)
    better = sub_res < residual[li, bi]
    theta[:, li, bi] = torch.where(better, sub, theta[:, li, bi])
    pos[:, :, li, bi] = torch.where(better, sub_pos, pos[:, :, li, bi])
    residual[li, bi] = torch.where(better, sub_res, residual[li, bi])
    viol[li, bi] = torch.where(better, sub_viol, viol[li, bi])


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
    tc = _tensors(plan, q.dtype, q.device)
    qf = q.reshape(-1, sk.num_dofs)
    qs = qf.index_select(1, tc["used"]).T.contiguous()  # (D', B): the dofs IK reads
    x = positions.to(q).reshape(-1, leaves, n1, 3).permute(2, 3, 1, 0).contiguous()  # (n+1, 3, L, B)
    if plan.kind == "iterative":
        theta, pos, residual, exact, in_limits, keep, projected = _iterative(plan, tc, qs, x, mode, tol, max_iter)
        return _result(q, plan.dofs, theta, pos, residual, exact, in_limits, keep, projected)
    ctol = 1000 * torch.finfo(q.dtype).eps if collinear_tol is None else collinear_tol
    g_r, p_r = _ancestors(plan, tc, qs)
    p_l = p_r[:, None]
    if plan.kind == "limb":
        a_frame = smm(g_r, sconst(tc["per"][plan.balls[0]]["c"], 1))[:, :, None]
        theta = _limb(plan, tc, a_frame, qs, x, ctol)

        def fk(th: Tensor) -> Tensor:
            return _limb_fk(tc, a_frame, p_l, th)
    else:
        theta = _swing(plan, tc, g_r, p_r, qs, x)
        g_l = g_r[:, :, None]

        def fk(th: Tensor) -> Tensor:
            return _path_fk(plan, tc, g_l, p_l, qs, _solved(plan, tc, th))

    theta, viol = _violation(theta, tc)  # in the limits' 2 pi windows
    pos = fk(theta)
    diff = pos - x
    residual = torch.sqrt((diff * diff).sum(1)).amax(0)
    if refine:
        miss = ~(residual <= tol) & torch.isfinite(x).all(0).all(0)
        if bool(miss.any()):  # one host sync
            _refine(plan, tc, qs, x, theta, pos, residual, viol, miss, max_iter)
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


__all__ = [
    "MODES",
    "ChainIK",
    "ClosedFormUnavailable",
    "IKResult",
    "chain_ik",
    "euler_zyx_solutions",
    "ik_plan",
    "product_ik",
]
