"""How to solve one chain: `ik_plan` picks a closed form ("limb" or "swing", `closed_form`) where the
skeleton allows one, else the iterative fit (`iterative`), and `plan_tensors` holds the plan's constants
(per-joint axes, rest rotations, bone vectors, limits, the limb's geometry) as tensors, built once per
dtype and device.

A "limb" is root -> ball -> hinge (a 3-dof ball joint whose axes form a frame, then a 1-dof hinge
that bends the limb); a "swing" chain has a 3-dof ball as every link's first joint. An iterative plan
solves the dofs of the path joints (and of the chain root when its bone end is on its pivot, as URDF
links are) that move the chain's joints.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from ptrack.body.skeleton import Skeleton
from ptrack.errors import InputError
from ptrack.hypotheses.jumps import Chain, path_below


class ClosedFormUnavailable(InputError):
    """No inverse kinematics for the chain: no dof moves its joints with its root in place (chains
    without a closed form take the iterative fallback instead)."""


@dataclass(frozen=True, eq=False)
class ChainIK:
    """How to solve one chain: made by `ik_plan`.

    kind: "limb", "swing" or "iterative" (`closed_form`, `iterative`). ancestors: joints from the skeleton
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
    drive a solved dof (the iterative solver's forward kinematics, `kinematics.walk_fk`)."""
    col = {d: m for m, d in enumerate(plan.dofs)}
    out = {}
    for j in (plan.chain.joints[0],) + plan.path:
        sl = tuple((s, col[int(d)]) for s, d in enumerate(plan.sk.axis_dof[j]) if int(d) in col)
        if sl:
            out[j] = sl
    return out


def _window_shift(lower: Tensor, upper: Tensor) -> Tensor:
    """pi - centre of each dof's 2 pi window (M,): the arc's centre for two finite bounds, else 0;
    angle a is in its window as remainder(a + shift, 2 pi) - shift (`ptrack.body.limits.wrap_to_limits`)."""
    limited = torch.isfinite(lower) & torch.isfinite(upper)
    return math.pi - torch.where(limited, 0.5 * (lower + upper), torch.zeros_like(lower))


def plan_tensors(plan: ChainIK, dtype: torch.dtype, device: torch.device) -> dict:
    """The plan's constants as tensors of `dtype` on `device`, built once and cached on the plan: per
    joint ("per": axes, Rodrigues matrices, rest rotation, bone vectors, rows of qs), the solved dofs and
    their limits and windows, the dofs IK reads ("used": the rows of qs (D', B)), and the limb's
    geometry ("limb")."""
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
