"""Forward kinematics along a chain, in the struct-of-arrays layout (`ptrack.hypotheses.jumps`): angles
(3, *M), rotations (3, 3, *M), positions (3, *M), with M = (L, B) or (B,) (leaves, then hypotheses
last), or (P,) for the iterative fit's flat problems (P = leaves x hypotheses).

One joint's rotation (`local_rotation`) and step (`fk_step`); the chain root's frame from the skeleton
root (`root_frame`) and its parent's frame and pivot (`root_parent`); the chain's joints with some
joints' slot angles solved (`path_fk`, the closed forms); and the iterative fit's walk with the solved
dofs set and its geometric Jacobian (`walk_fk`). Constants come from `plan.plan_tensors`, the other
dofs from qs (D', B), the transposed q restricted to the dofs IK reads.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ptrack.body.kinematics import euler_zyx
from ptrack.hypotheses.ik.plan import ChainIK
from ptrack.hypotheses.jumps import sconst, scross, seye, smm, smv, stranspose


def slot_angles(pj: dict, qs: Tensor) -> Tensor:
    """Slot angles of one joint (frozen slots at their value): qs (D', B) -> (3, B)."""
    return qs.index_select(0, pj["index"]) * pj["mask"] + pj["frozen"]


def seuler(theta: Tensor) -> Tensor:
    """Rz(z) Ry(y) Rx(x) for theta (3, *M) = (z, y, x) -> (3, 3, *M): `ptrack.body.kinematics.euler_zyx`
    in the struct-of-arrays (coordinates-first) layout."""
    return euler_zyx(theta.movedim(0, -1)).movedim((-2, -1), (0, 1)).contiguous()


def local_rotation(pj: dict, theta: Tensor) -> Tensor:
    """A joint's rotation relative to its parent for slot angles theta (3, *M) -> (3, 3, *M)."""
    nd = theta.ndim - 1
    if pj["c"] is not None:
        c = sconst(pj["c"], nd)
        r = smm(smm(c, seuler(theta)), stranspose(c))
    else:
        eye = seye(theta, nd)
        rots = [
            eye + torch.sin(theta[s]) * sconst(pj["k1"][s], nd) + (1 - torch.cos(theta[s])) * sconst(pj["k2"][s], nd)
            for s in range(3)
        ]
        r = smm(smm(rots[0], rots[1]), rots[2])
    return r if pj["rest"] is None else smm(r, sconst(pj["rest"], nd))


def fk_step(pj: dict, g_par: Tensor, p_par: Tensor, theta: Tensor) -> tuple[Tensor, Tensor]:
    """One joint of forward kinematics: parent frame (3, 3, *M) and position (3, *M) -> this joint's."""
    g = smm(g_par, local_rotation(pj, theta))
    nd = g.ndim - 2
    p = p_par + smv(g, sconst(pj["w"], nd))
    if pj["u"] is not None:
        p = p + smv(g_par, sconst(pj["u"], nd))
    return g, p


def root_frame(plan: ChainIK, tc: dict, qs: Tensor) -> tuple[Tensor, Tensor]:
    """World rotation (3, 3, B) and position (3, B) of the chain's root joint for qs (D', B)."""
    per = tc["per"]
    root = plan.ancestors[0]
    g = local_rotation(per[root], slot_angles(per[root], qs))
    p = (
        qs.index_select(0, tc["trans_index"]) * tc["trans_mask"]
        + tc["root_position"]
        + smv(g, sconst(per[root]["w"], 1))
    )
    for j in plan.ancestors[1:]:
        g, p = fk_step(per[j], g, p, slot_angles(per[j], qs))
    return g, p


def path_fk(plan: ChainIK, tc: dict, g: Tensor, p: Tensor, qs: Tensor, solved: dict[int, Tensor]) -> Tensor:
    """Positions (n+1, 3, L, B) of the chain's joints from the root frame g (3, 3, 1, B), position
    p (3, 1, B), solved slot angles {joint: (3, L, B)} and qs (D', B) for the other path joints."""
    per = tc["per"]
    pos = {plan.chain.joints[0]: p}
    for j in plan.path:
        theta = solved[j] if j in solved else slot_angles(per[j], qs)[:, None]
        g, p = fk_step(per[j], g, p, theta)
        pos[j] = p
    return torch.stack(torch.broadcast_tensors(*(pos[j] for j in plan.chain.joints)))


def root_parent(plan: ChainIK, tc: dict, qs: Tensor) -> tuple[Tensor, Tensor]:
    """World frame (3, 3, B) of the chain root's parent (identity for the skeleton root) and the
    root's pivot (3, B) (where its rotation turns about) for qs (D', B)."""
    per, anc = tc["per"], plan.ancestors
    pivot = qs.index_select(0, tc["trans_index"]) * tc["trans_mask"] + tc["root_position"]
    if len(anc) == 1:
        return seye(pivot, 1).expand(3, 3, *pivot.shape[1:]), pivot
    g = local_rotation(per[anc[0]], slot_angles(per[anc[0]], qs))
    p = pivot + smv(g, sconst(per[anc[0]]["w"], 1))
    for j in anc[1:-1]:
        g, p = fk_step(per[j], g, p, slot_angles(per[j], qs))
    u = per[anc[-1]]["u"]
    return g, (p if u is None else p + smv(g, sconst(u, 1)))


def _turn_vector(pj: dict, s: int, angle: Tensor, v: Tensor) -> Tensor:
    """Rot(axes[s], angle) v (Rodrigues) for angle (P,), v (3, P) -> (3, P)."""
    kv = smv(sconst(pj["k1"][s], 1), v)
    return v + torch.sin(angle) * kv + (1 - torch.cos(angle)) * smv(sconst(pj["k1"][s], 1), kv)


def _walk_local(pj: dict, theta: Tensor) -> Tensor:
    """`local_rotation` turning only the joint's active slots (URDF joints drive one slot of three, fixed
    joints none): theta (3, P) -> (3, 3, P), or (3, 3, 1) for a joint that does not turn."""
    if pj["c"] is not None and len(pj["active"]) == 3:
        return local_rotation(pj, theta)
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


def walk_fk(
    plan: ChainIK, tc: dict, g_par: Tensor, pivot: Tensor, qs: Tensor, theta: Tensor, jacobian: bool
) -> tuple[Tensor, Tensor | None]:
    """Forward kinematics from the chain root down its path with the solved dofs set, and the
    geometric Jacobian of the chain's joints w.r.t. them (`ptrack.optim.jacobians`, restricted to the
    chain: slot s of joint i turns the joints below about its world axis a through its pivot o_i,
    d p_y / d theta = a x (p_y - o_i)).

    g_par (3, 3, P), pivot (3, P) from `root_parent`; qs (D', P) the other dofs; theta (M, P)
    -> positions (n+1, 3, P), jacobian (n, 3, M, P) of joints 1..n (None unless asked).
    """
    per, slots, chain = tc["per"], tc["slots"], plan.chain
    walk = (chain.joints[0],) + plan.path
    pos: dict[int, Tensor] = {}
    columns = []  # (column, walk index, world axis (3, P), pivot (3, P))
    g_p, p_p = g_par, pivot  # the parent frame and position (p_p unread at the chain root)
    for i, j in enumerate(walk):
        pj = per[j]
        th = slot_angles(pj, qs)
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
