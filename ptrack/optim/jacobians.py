"""Jacobians w.r.t. the pose q: of the joint positions (geometric, one FK pass) and of an
objective's stacked residuals (chain rule through the joints, FK still once).

    joint_jacobian(sk, q (..., D)) -> joints (..., J, 3), jac (..., J, 3, D)
    joint_jacobian(sk, q, joints (Y,)) -> joints (..., J, 3), jac (..., Y, 3, D): only those joints' rows
    joint_jacobian_product(sk, q, joints (Y,), left (..., Y, R, 3)) -> left @ those rows (..., Y, R, D)
    point_jacobian(sk, q (..., D), joint (..., P), local (..., P, 3)) -> points (..., P, 3), jac (..., P, 3, D)
    joint_and_point_jacobian(sk, q, joint, local) -> both of the above, FK once
    residual_jacobian(sk, residual_fn, q (..., D)) -> r (..., M), jac (..., M, D)
    objective_linearization(sk, objective, camera, keypoints) -> q (N, D) -> Linearization

The geometric Jacobian. In the model of `ptrack.body.skeleton`,

    G_i = G_parent R(a_i1, th_i1) R(a_i2, th_i2) R(a_i3, th_i3) E_i
    p_i = o_i + length_i G_i w_i,   o_i = p_parent + length_i G_parent u_i,

slot k of joint i turns G_i, and with it p_i and the whole subtree below i, rigidly about the
world axis  a = G_parent R(a_i1, th_i1) ... R(a_i(k-1), th_i(k-1)) a_ik  through the pivot o_i
(the joint's origin: for ASF bones the parent bone's end point, for the root its translated rest
position). The part of the offset fixed in the parent's frame (u_i) puts o_i, not p_i, on the axis.
So for every joint y in the subtree of i (i included), d p_y / d th_ik = a x (p_y - o_i), and a
root translation dof moves every joint by its unit vector. A URDF prismatic joint i (p_i gains
G_i s_i q_slide) moves its whole subtree by G_i s_i per unit of its dof; a mimic slot turns by
its multiplier per unit of its leader's dof, so its column is scaled by it. Everything comes from one FK pass with
world rotations: the pivots are o_i = p_i - length_i G_i w_i.

Residual Jacobians. A one-frame objective is r(q) = f(q, X(q)) with X the joints; its Jacobian is
df/dq + df/dX . dX/dq. `residual_jacobian` pushes the D columns (e_d, dX/dq_d) through f in one
`torch.func.vmap` of `torch.func.jvp` (forward mode over f only: projection and cost terms, no FK).

Measured by scripts/bench_solver.py (N=256 poses of CMU subject 10 without fingers, thumbs, hands
and toes: J=31, D=50; 17 keypoints + limits: M=84; float64, 1 thread on a shared, loaded 2-core
CPU, so absolute times are noisy; ratios are from the same run):

    joint positions    geometric 43 ms | torch.func.jacfwd 489 ms (11.5x) | autograd 555 ms (13.1x)
    residuals          chain rule 76 ms | torch.func.jacfwd 594 ms (7.8x) | autograd 437 ms (5.8x)

all equal to autograd within 4e-14 (float64). torch.func.jacrev does not run through the FK (its
analytical backward is an autograd.Function without functorch support), and
torch.autograd.functional.jacobian(vectorize=True) fails on it for the same reason; the autograd
column is one backward pass per output row.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch
from torch import Tensor

from ptrack.body.keypoints import KeypointSet
from ptrack.body.skeleton import Skeleton
from ptrack.costs import Objective, PoseEval
from ptrack.costs.base import PoseJacobian
from ptrack.errors import InputError
from ptrack.observe.camera import Camera
from ptrack.optim.solvers import Linearization

ResidualFn = Callable[[Tensor, Tensor], Tensor]


def _pair_tables(sk: Skeleton, anc: Tensor, dtype: torch.dtype) -> dict[str, Tensor]:
    """The (row, slot) pairs of a Jacobian whose rows are Y joints, from anc (Y, J) (anc[r, i]: joint i is
    row r's joint or one of its ancestors), on the CPU: each pair's row, slot, dof and mimic scale, and
    where its three entries go in a flattened (Y, 3, D) Jacobian ((r * 3 + k) * D + dof); likewise the
    (row, prismatic slider) pairs of URDF models (joint i slides its subtree along G_i s_i, one dof)."""
    j, d = sk.num_joints, sk.num_dofs
    slot_dof = torch.as_tensor(sk.axis_dof, dtype=torch.long)  # (J, 3)
    driven = slot_dof >= 0
    joint_of = torch.arange(j)[:, None].expand(j, 3)[driven]  # (S,) joint of each driven slot
    pair_row, pair_slot = torch.nonzero(anc[:, joint_of], as_tuple=True)  # (P,) each
    pair_dof = slot_dof[driven][pair_slot]
    scale = torch.as_tensor(sk.axis_scale, dtype=dtype)  # (J, 3) a mimic slot's multiplier, else 1
    sliders = torch.as_tensor(np.flatnonzero(sk.slide_dof >= 0), dtype=torch.long)
    slide_row, slide_src = torch.nonzero(anc[:, sliders], as_tuple=True)
    slide_src = sliders[slide_src]
    slide_dof = torch.as_tensor(sk.slide_dof, dtype=torch.long)[slide_src]
    return {
        "pair_row": pair_row,
        "pair_slot": pair_slot,
        "pair_dof": pair_dof,
        "pair_index": ((pair_row[:, None] * 3 + torch.arange(3)) * d + pair_dof[:, None]).flatten(),
        "pair_scale": scale[driven][pair_slot],
        "slide_row": slide_row,
        "slide_src": slide_src,
        "slide_dof": slide_dof,
        "slide_index": ((slide_row[:, None] * 3 + torch.arange(3)) * d + slide_dof[:, None]).flatten(),
    }


def _constants(sk: Skeleton, dtype: torch.dtype, device: torch.device) -> dict:
    """Per-skeleton constants, cached like the FK plan: slot axes, which slots are driven, the dof
    each slot drives, and the (joint, slot) pairs where the slot's joint is the joint or one of its
    ancestors, with where their three entries go in a flattened (J, 3, D) Jacobian."""
    key = ("jacobian", dtype, str(device))
    c = sk._cache.get(key)
    if c is None:
        c = sk._cache[key] = _new_constants(sk, dtype, device)
    return c


@torch.inference_mode(False)  # cached: ordinary tensors even when first built in a tracker's inference mode
def _new_constants(sk: Skeleton, dtype: torch.dtype, device: torch.device) -> dict:
    j = sk.num_joints
    anc = torch.zeros(j, j, dtype=torch.bool)  # anc[y, i]: i is y or an ancestor of y
    for y in range(j):
        i = y
        while i >= 0:
            anc[y, i] = True
            i = sk.parents[i]
    slot_dof = torch.as_tensor(sk.axis_dof, dtype=torch.long)  # (J, 3)
    driven = slot_dof >= 0
    joint_of = torch.arange(j)[:, None].expand(j, 3)[driven]  # (S,) joint of each driven slot
    trans = torch.as_tensor(sk.translation_dof, dtype=torch.long)
    scale = torch.as_tensor(sk.axis_scale, dtype=dtype)  # (J, 3) a mimic slot's multiplier, else 1
    pt = _pair_tables(sk, anc, dtype)
    c = {
        "axes": torch.as_tensor(sk.axes, dtype=dtype, device=device),  # (J, 3, 3)
        "slot_index": torch.as_tensor(sk.axis_dof.clip(0), dtype=torch.long, device=device),  # (J, 3)
        "driven": driven.to(device),
        "frozen": torch.as_tensor(sk.frozen_axes, dtype=dtype, device=device),
        "parents": torch.as_tensor([max(p, 0) for p in sk.parents], dtype=torch.long, device=device),
        "is_root": torch.as_tensor([p < 0 for p in sk.parents], device=device),
        "w": torch.as_tensor(sk.offset_local * sk.lengths[:, None], dtype=dtype, device=device),
        "slot_flat": (torch.arange(j)[:, None] * 3 + torch.arange(3))[driven].to(device),  # (S,)
        "slot_joint": joint_of.to(device),
        "injective": len(set(slot_dof[driven].tolist())) == int(driven.sum()),
        "ancestors": anc,  # on the CPU: `_row_constants` builds its tables from it
        "pair_joint": pt["pair_row"].to(device),
        "pair_slot": pt["pair_slot"].to(device),
        "pair_index": pt["pair_index"].to(device),  # (3 P,)
        "trans_axis": torch.nonzero(trans >= 0).flatten().to(device),  # world axes with a dof
        "trans_dof": trans[trans >= 0].to(device),
        # angle per unit of the slot's dof (0 for undriven slots): theta = mask * q + frozen, as in FK
        "mask": torch.where(driven, scale, torch.zeros_like(scale)).to(device),
        "pair_scale": pt["pair_scale"].to(device),  # (P,)
        "plain": bool((scale[driven] == 1).all()),
        "slide_src": pt["slide_src"].to(device),  # (Q,) the prismatic joint of each (joint, slider) pair
        "slide_axis": torch.as_tensor(sk.slide_axis, dtype=dtype, device=device),  # (J, 3) in G_i's frame
        "slide_index": pt["slide_index"].to(device),  # (3 Q,)
    }
    return c


def _cross(a: Tensor, b: Tensor) -> Tensor:
    """a x b with broadcasting: (..., 3), (..., 3) -> (..., 3)."""
    a0, a1, a2 = a.unbind(-1)
    b0, b1, b2 = b.unbind(-1)
    return torch.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], dim=-1)


def _turn(axis: Tensor, angle: Tensor, v: Tensor) -> Tensor:
    """Rodrigues on vectors: R(axis, angle) v. axis, v (..., 3), angle (...) -> (..., 3)."""
    s, co = torch.sin(angle)[..., None], torch.cos(angle)[..., None]
    return v * co + _cross(axis, v) * s + axis * ((axis * v).sum(-1, keepdim=True) * (1 - co))


def _slot_axes(c: dict, q: Tensor, joints: Tensor, rot: Tensor) -> tuple[Tensor, Tensor]:
    """World axis a_s (..., S, 3) and pivot o_s (..., S, 3) of every driven slot s, from one FK pass's
    joints (..., J, 3) and world rotations (..., J, 3, 3) of q (..., D); c: `_constants`."""
    # slot angles (..., J, 3): mask * q + frozen (driven: q, or a mimic's multiplier * q + offset)
    theta = q.index_select(-1, c["slot_index"].flatten()).unflatten(-1, (-1, 3)) * c["mask"] + c["frozen"]
    a1, a2, a3 = c["axes"].unbind(-2)  # (J, 3) each: the slots' axes in the parent frame
    v2 = _turn(a1, theta[..., 0], a2)
    v3 = _turn(a1, theta[..., 0], _turn(a2, theta[..., 1], a3))
    local_axes = torch.stack([a1.expand_as(v2), v2, v3], dim=-2)  # (..., J, 3 slots, 3)
    eye = torch.eye(3, dtype=q.dtype, device=q.device)
    g_parent = torch.where(c["is_root"][:, None, None], eye, rot.index_select(-3, c["parents"]))
    world_axes = torch.einsum("...jab,...jsb->...jsa", g_parent, local_axes)  # (..., J, 3, 3)
    pivots = joints - torch.einsum("...jab,jb->...ja", rot, c["w"])  # o_i = p_i - l_i G_i w_i
    a = world_axes.flatten(-3, -2).index_select(-2, c["slot_flat"])  # (..., S, 3)
    o = pivots.index_select(-2, c["slot_joint"])  # (..., S, 3)
    return a, o


def joint_jacobian(sk: Skeleton, q: Tensor, joints: Sequence[int] | Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Joint positions and their geometric Jacobian w.r.t. the pose, from one FK pass.

    q: (..., D) -> joints (..., J, 3) metres, jac (..., J, 3, D) with jac[..., y, :, d] = d p_y / d q_d
    (see the module docstring). joints: the rows wanted, Y joint indices (any order, repeats allowed;
    a sequence or a 1-D long tensor): jac is then (..., Y, 3, D) with jac[..., r] = the full
    Jacobian's row joints[r], built from the (joint, ancestor slot) pairs of those joints only (the
    positions stay all J: FK computes them anyway). Follows q's dtype and device. Not differentiable
    itself (it is a first derivative; use autograd through `forward_kinematics` for second derivatives).
    """
    positions, rot = sk.forward_kinematics(q, rotations=True)
    c = _constants(sk, q.dtype, q.device)
    a, o = _slot_axes(c, q, positions, rot)
    rows = None if joints is None else _row_constants(sk, c, joints, q.dtype, q.device)
    return positions, _joint_rows(sk, c, q, positions, rot, a, o, rows)


def point_jacobian(sk: Skeleton, q: Tensor, joint: Tensor, local: Tensor) -> tuple[Tensor, Tensor]:
    """Points rigidly attached to joints' frames and their geometric Jacobian w.r.t. the pose, one FK pass.

    q (..., D); joint (..., P) long: the skeleton joint y whose frame carries each point; local (..., P, 3):
    the point in that frame (origin p_y, axes y's world rotation G_y). joint and local broadcast against
    q's batch dims. -> points x = p_y + G_y local (..., P, 3) metres and jac (..., P, 3, D) = d x / d q.

    The point moves with y's body: every slot s of y or of an ancestor turns it about the slot's world
    axis a_s through the pivot o_s (d x / d th_s = a_s x (x - o_s), as for the joints; mimic slots
    scaled by their multiplier), a prismatic ancestor slides it along G_i s_i, a root translation dof
    moves it by its unit vector. Follows q's dtype and device.
    """
    joints, rot = sk.forward_kinematics(q, rotations=True)
    c = _constants(sk, q.dtype, q.device)
    a, o = _slot_axes(c, q, joints, rot)
    return _point_rows(sk, c, q, joints, rot, a, o, joint, local)


def _pair_values(c: dict, t: dict, positions: Tensor, a: Tensor, o: Tensor) -> Tensor:
    """Each (joint y, slot s) pair's column entries a_s x (p_y - o_s) (times a mimic slot's multiplier),
    for the pair tables t (`_constants` or `_row_constants`): -> (..., P, 3)."""
    lever = positions.index_select(-2, t["pair_joint"]) - o.index_select(-2, t["pair_slot"])
    vals = _cross(a.index_select(-2, t["pair_slot"]), lever)  # (..., P, 3)
    if not c["plain"]:  # mimic slots turn by their multiplier per unit of the leader's dof
        vals = vals * t["pair_scale"][:, None]
    return vals


def _slide_directions(c: dict, t: dict, rot: Tensor) -> Tensor:
    """Each (joint, prismatic slider i) pair's direction G_i s_i in the world, for the pair tables t:
    rot (..., J, 3, 3) -> (..., Q, 3)."""
    src = t["slide_src"]
    return torch.einsum("...qab,qb->...qa", rot.index_select(-3, src), c["slide_axis"].index_select(0, src))


def joint_jacobian_product(
    sk: Skeleton,
    q: Tensor,
    joints: Sequence[int] | Tensor,
    left: Tensor,
    fk: tuple[Tensor, Tensor] | None = None,
) -> Tensor:
    """left @ the joint Jacobian rows of Y chosen joints, without forming those rows.

    q (..., D), joints (Y,) as in `joint_jacobian`, left (..., Y, R, 3) (a derivative w.r.t. each
    chosen joint's position, e.g. of its R = 2 pixel coordinates) -> (..., Y, R, D) = left[..., y]
    @ jac[..., y] with jac = `joint_jacobian(sk, q, joints)[1]`. Each (joint, ancestor slot) pair
    contributes left_y (a_s x (p_y - o_s)) to its dof's column (R values instead of 3, and no
    (Y, 3, D) buffer); a slider its left_y G_i s_i, a root translation dof left_y's column of its
    axis. For one slot per dof (no mimics), equal to the product of the two to the last bit: its
    entries are the same products summed in the same order (x0 y0 + x1 y1, + x2 y2), where the
    product adds exact zeros. fk: `sk.forward_kinematics(q, rotations=True)` if already computed.
    Follows q's dtype and device.
    """
    positions, rot = sk.forward_kinematics(q, rotations=True) if fk is None else fk
    c = _constants(sk, q.dtype, q.device)
    a, o = _slot_axes(c, q, positions, rot)
    rc = _row_constants(sk, c, joints, q.dtype, q.device)
    y_len, r_len, d = rc["rows"], left.shape[-2], sk.num_dofs
    batch = torch.broadcast_shapes(q.shape[:-1], left.shape[:-3])
    left = left.expand(*batch, y_len, r_len, 3)
    vals = _pair_values(c, rc, positions, a, o)  # (..., P, 3)
    lp = left.index_select(-3, rc["pair_row"])  # (..., P, R, 3)
    entries = _chain_rule(lp, vals[..., None])[..., 0]  # (..., P, R), as the product's x0 y0 + x1 y1 + x2 y2
    r = torch.arange(r_len, device=q.device)
    index = ((rc["pair_row"][:, None] * r_len + r) * d + rc["pair_dof"][:, None]).flatten()
    out = q.new_zeros(*batch, y_len * r_len * d)
    if c["injective"]:
        out.index_copy_(-1, index, entries.flatten(-2))
    else:
        out.index_add_(-1, index, entries.flatten(-2))
    if rc["slide_src"].numel():
        direction = _slide_directions(c, rc, rot)  # (..., Q, 3)
        slide = (left.index_select(-3, rc["slide_row"]) * direction[..., None, :]).sum(-1)  # (..., Q, R)
        index = ((rc["slide_row"][:, None] * r_len + r) * d + rc["slide_dof"][:, None]).flatten()
        out.index_add_(-1, index, slide.flatten(-2))
    out = out.unflatten(-1, (y_len, r_len, d))
    if c["trans_dof"].numel():  # no slot drives a translation dof: these columns are zero so far
        out[..., c["trans_dof"]] += left[..., c["trans_axis"]]
    return out


def joint_and_point_jacobian(
    sk: Skeleton, q: Tensor, joint: Tensor, local: Tensor, fk: tuple[Tensor, Tensor] | None = None
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """`joint_jacobian` and `point_jacobian` of the same poses from one FK pass (and one set of slot axes):
    q (..., D), joint (..., P), local (..., P, 3) as in `point_jacobian` -> joints (..., J, 3), their
    jac (..., J, 3, D), points (..., P, 3) and theirs (..., P, 3, D) (broadcast batch dims), each equal to
    what the two functions return. fk: `sk.forward_kinematics(q, rotations=True)` (joints (..., J, 3),
    world rotations (..., J, 3, 3)) if already computed."""
    joints, rot = sk.forward_kinematics(q, rotations=True) if fk is None else fk
    c = _constants(sk, q.dtype, q.device)
    a, o = _slot_axes(c, q, joints, rot)
    points, point_jac = _point_rows(sk, c, q, joints, rot, a, o, joint, local)
    return joints, _joint_rows(sk, c, q, joints, rot, a, o), points, point_jac


def _row_constants(
    sk: Skeleton, c: dict, joints: Sequence[int] | Tensor, dtype: torch.dtype, device: torch.device
) -> dict:
    """`_constants`' pair tables for the Jacobian rows of Y chosen joints (cached per choice): the
    (row r, slot s) pairs where s's joint is joints[r] or one of its ancestors, in the full table's
    order (row-major, then slot), with where their entries go in a flattened (Y, 3, D) Jacobian;
    likewise for prismatic sliders."""
    rows = tuple(int(y) for y in (joints.tolist() if isinstance(joints, Tensor) else joints))
    key = ("jacobian rows", dtype, str(device), rows)
    rc = sk._cache.get(key)
    if rc is None:
        rc = sk._cache[key] = _new_row_constants(sk, c, rows, dtype, device)
    return rc


@torch.inference_mode(False)  # cached: ordinary tensors even when first built in a tracker's inference mode
def _new_row_constants(sk: Skeleton, c: dict, rows: tuple[int, ...], dtype: torch.dtype, device: torch.device) -> dict:
    j = sk.num_joints
    if any(not -j <= y < j for y in rows):
        raise ValueError(f"joint_jacobian: joints {list(rows)} outside the skeleton's {j} joints")
    rows = tuple(y % j for y in rows)
    sel = torch.as_tensor(rows, dtype=torch.long)
    pt = _pair_tables(sk, c["ancestors"][sel], dtype)
    rc: dict = {name: x.to(device) for name, x in pt.items()}  # for `joint_jacobian_product`: pair_row, pair_dof, ...
    rc["rows"] = len(rows)
    rc["pair_joint"] = sel[pt["pair_row"]].to(device)
    return rc


def _joint_rows(
    sk: Skeleton, c: dict, q: Tensor, joints: Tensor, rot: Tensor, a: Tensor, o: Tensor, rows: dict | None = None
) -> Tensor:
    """`joint_jacobian`'s jac (..., J, 3, D) from an FK pass of q (..., D) (joints (..., J, 3), world
    rotations (..., J, 3, 3)) and its slot axes and pivots a, o (..., S, 3) (`_slot_axes`); with rows
    (`_row_constants` of Y joints) only those rows, (..., Y, 3, D)."""
    batch = q.shape[:-1]
    t = c if rows is None else rows  # the pair tables: all joints, or the chosen rows
    n_rows = joints.shape[-2] if rows is None else rows["rows"]
    # for each (joint y, slot s) pair with y in the subtree of s's joint: a_s x (p_y - o_s)
    vals = _pair_values(c, t, joints, a, o).flatten(-2)  # (..., 3 P), entries (p, k)
    jac = q.new_zeros(*batch, n_rows * 3 * sk.num_dofs)
    if c["injective"]:
        jac.index_copy_(-1, t["pair_index"], vals)
    else:
        jac.index_add_(-1, t["pair_index"], vals)
    if t["slide_src"].numel():  # a prismatic joint i moves every joint of its subtree by G_i s_i
        jac.index_add_(-1, t["slide_index"], _slide_directions(c, t, rot).flatten(-2))
    jac = jac.unflatten(-1, (n_rows, 3, sk.num_dofs))
    if c["trans_dof"].numel():
        jac[..., c["trans_axis"], c["trans_dof"]] = 1.0
    return jac


def _point_rows(
    sk: Skeleton,
    c: dict,
    q: Tensor,
    joints: Tensor,
    rot: Tensor,
    a: Tensor,
    o: Tensor,
    joint: Tensor,
    local: Tensor,
) -> tuple[Tensor, Tensor]:
    """`point_jacobian`'s points (..., P, 3) and jac (..., P, 3, D) from an FK pass of q (..., D) (joints
    (..., J, 3), world rotations (..., J, 3, 3)) and its slot axes and pivots a, o (..., S, 3)."""
    key = ("point_jacobian", q.dtype, str(q.device))
    pc = sk._cache.get(key)
    if pc is None:
        pc = sk._cache[key] = _point_constants(sk, c, q.dtype, q.device)
    batch = torch.broadcast_shapes(q.shape[:-1], joint.shape[:-1], local.shape[:-2])
    n_pts = joint.shape[-1]
    joint = joint.to(q.device).expand(*batch, n_pts)
    joints = joints.expand(*batch, *joints.shape[-2:])
    rot = rot.expand(*batch, *rot.shape[-3:])
    p_y = joints.gather(-2, joint[..., None].expand(*batch, n_pts, 3))
    g_y = rot.gather(-3, joint[..., None, None].expand(*batch, n_pts, 3, 3))
    points = p_y + (g_y @ local.to(q)[..., None])[..., 0]
    a, o = a[..., None, :, :], o[..., None, :, :]  # (..., 1, S, 3)
    vals = _cross(a, points[..., None, :] - o) * pc["anc"][joint][..., None]  # (..., P, S, 3)
    jac = vals.mT @ pc["select"]  # (..., P, 3, D)
    if pc["sliders"].numel():
        src = pc["sliders"]
        direction = torch.einsum("...qab,qb->...qa", rot.index_select(-3, src), c["slide_axis"].index_select(0, src))
        slide = direction[..., None, :, :] * pc["slide_anc"][joint][..., None]  # (..., P, Q, 3)
        jac = jac + slide.mT @ pc["slide_select"]
    if c["trans_dof"].numel():
        jac[..., c["trans_axis"], c["trans_dof"]] = 1.0
    return points, jac


@torch.inference_mode(False)  # cached: ordinary tensors even when first built in a tracker's inference mode
def _point_constants(sk: Skeleton, c: dict, dtype: torch.dtype, device: torch.device) -> dict:
    """`_point_rows`' cached tables: (J, S) slot s turns joint y's body; (S, D) each slot's dof with its
    multiplier; the same for prismatic sliders."""
    d = sk.num_dofs
    n_slot = int(c["slot_joint"].numel())
    anc = c["ancestors"][:, c["slot_joint"].cpu()].to(device)  # (J, S): slot s's joint is y or above it
    slot_dof = c["slot_index"].flatten()[c["slot_flat"]]
    select = torch.zeros(n_slot, d, dtype=dtype, device=device)
    select[torch.arange(n_slot, device=device), slot_dof] = c["mask"].flatten()[c["slot_flat"]]
    sliders = torch.as_tensor(np.flatnonzero(sk.slide_dof >= 0), dtype=torch.long)
    slide_anc = c["ancestors"][:, sliders].to(device)  # (J, Q): slider i is y or above it
    sliders = sliders.to(device)
    slide_select = torch.zeros(sliders.numel(), d, dtype=dtype, device=device)
    slide_dof = torch.as_tensor(sk.slide_dof, dtype=torch.long, device=device)
    slide_select[torch.arange(sliders.numel(), device=device), slide_dof[sliders]] = 1.0
    return {"anc": anc, "select": select, "sliders": sliders, "slide_anc": slide_anc, "slide_select": slide_select}


def residual_jacobian(
    sk: Skeleton, residual_fn: ResidualFn, q: Tensor, joints_and_jacobian: tuple[Tensor, Tensor] | None = None
) -> tuple[Tensor, Tensor]:
    """Residuals r(q) = f(q, joints(q)) and their Jacobian w.r.t. q, with FK run once.

    residual_fn(q (..., D), joints (..., J, 3)) -> (..., M) must be written in torch ops that
    `torch.func.jvp` and `vmap` support (`Camera.project`, `Reprojection` and `JointLimits` are:
    tests/test_jacobians.py).
    joints_and_jacobian: `joint_jacobian(sk, q)` if already computed.
    q: (..., D) -> r (..., M), jac (..., M, D) = df/dq + df/dX dX/dq.
    """
    joints, dx = joint_jacobian(sk, q) if joints_and_jacobian is None else joints_and_jacobian
    d = q.shape[-1]
    eye = torch.eye(d, dtype=q.dtype, device=q.device).reshape(d, *([1] * (q.ndim - 1)), d).expand(d, *q.shape)
    tangent_x = dx.movedim(-1, 0)  # (D, ..., J, 3)

    def column(tq: Tensor, tx: Tensor) -> tuple[Tensor, Tensor]:
        out = torch.func.jvp(residual_fn, (q, joints), (tq, tx))  # (primal, tangent): no has_aux
        return out[0], out[1]

    # torch's stub types out_dims without the None that vmap accepts per output
    r, cols = torch.func.vmap(column, out_dims=(None, 0))(eye, tangent_x)  # type: ignore[arg-type]
    return r, cols.movedim(0, -1)


def objective_linearization(
    sk: Skeleton, objective: Objective, camera: Camera, keypoints: KeypointSet, fold: bool = False
) -> Callable[[Tensor], Linearization]:
    """The one-frame objective as the solvers read it: q (N, D) -> Linearization(residuals (N, M),
    jacobian (N, M, D), weights (N, M) IRLS, energy (N,) the robust total), one FK per call.

    The objective's terms must read only q, joints and keypoint pixels/depth (Reprojection,
    JointLimits, JointKeyframe on one frame, ...), not joint_pixels. With `fold` the terms whose
    Jacobian is mostly zeros (limits, priors, body collision) come folded into
    `Linearization.fold_h`/`fold_g` instead of stacked rows (`Objective.linearize`): the same steps,
    cheaper normal equations.
    """
    if camera is None or keypoints is None:
        raise InputError("objective_linearization needs a camera and a keypoint set")

    def linearize(q: Tensor) -> Linearization:
        ev, jac = pose_eval_and_jacobian(sk, camera, keypoints, q)
        return Linearization(*objective.linearize(ev, jac, fold))

    return linearize


def pose_eval_and_jacobian(
    sk: Skeleton, camera: Camera, keypoints: KeypointSet, q: Tensor
) -> tuple[PoseEval, PoseJacobian]:
    """`ptrack.problem.evaluate_pose` and the derivatives of its fields w.r.t. q, from one FK pass:
    q (..., D) -> PoseEval (joints (..., J, 3), pixels (..., K, 2), depth (..., K)) and PoseJacobian
    (joints (..., J, 3, D), pixels (..., K, 2, D), depth (..., K, D)). Cost terms turn these into
    their residual Jacobians (`Objective.jacobian`), in closed form where they can."""
    joints, dx = joint_jacobian(sk, q)
    idx = keypoints.index(q.device)
    dkp = dx.index_select(-3, idx)  # (..., K, 3, D)
    proj, dpix = camera.project_jacobian(joints.index_select(-2, idx))
    _, R, _ = camera._params_like(joints)
    ev = PoseEval(q=q, joints=joints, pixels=proj.pixels, depth=proj.depth)
    jac = PoseJacobian(joints=dx, pixels=_chain_rule(dpix, dkp), depth=torch.einsum("c,...kcd->...kd", R[2], dkp))
    return ev, jac


def _chain_rule(outer: Tensor, inner: Tensor) -> Tensor:
    """outer @ inner for many tiny matrices, outer (..., R, 3), inner (..., 3, D) -> (..., R, D), as three
    broadcast multiply-adds in the order x0 y0 + x1 y1 + x2 y2: on CPU 3.5x faster than the batched matmul
    for (128 x 17) pixel Jacobians (2 x 3 by 3 x 50), whose per-matrix overhead is most of its time."""
    out = outer[..., 0, None] * inner[..., None, 0, :]
    out.addcmul_(outer[..., 1, None], inner[..., None, 1, :])
    return out.addcmul_(outer[..., 2, None], inner[..., None, 2, :])
