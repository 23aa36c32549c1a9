"""Batched forward kinematics for `Skeleton` models.

    forward_kinematics(skeleton, q (..., D)) -> joints (..., J, 3) [, rotations (..., J, 3, 3)]

One pure function, differentiable w.r.t. q and bone lengths, any leading batch dims, float32 or
float64, CPU or CUDA. Speed comes from two things: all per-joint local rotations are built at once
(closed-form Rodrigues for every axis of every joint), and the tree is composed level by level
(joints at the same depth in one batched 3x3 product), so a CMU skeleton takes ~10 sequential
steps whatever the batch size. Rotations are 3x3 and positions 3-vectors, never 4x4 homogeneous
matrices.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ptrack.errors import InputError
from ptrack.skeleton import Skeleton


@dataclass(frozen=True)
class _Level:
    nodes: Tensor  # (n,) joint indices at this depth
    parent_slot: Tensor  # (n,) position of each node's parent in the previous level
    nodes_list: tuple[int, ...]


@dataclass(frozen=True)
class _Plan:
    """Skeleton constants as tensors of one dtype/device, plus the level schedule."""

    dof_index: Tensor  # (J*3,) long, clamped q index per axis slot
    dof_mask: Tensor  # (J, 3) 1 where the slot is driven by q
    frozen: Tensor  # (J, 3) constant angle for undriven slots
    k1: Tensor  # (J, 3, 3, 3) skew(axis) per slot
    k2: Tensor  # (J, 3, 3, 3) skew(axis)^2 per slot
    rest: Tensor | None  # (J, 3, 3) or None if all identity
    offset_parent: Tensor | None  # (J, 3) or None if all zero
    offset_local: Tensor | None  # (J, 3) or None if all zero
    lengths: Tensor  # (J,)
    root_position: Tensor  # (3,)
    trans_index: Tensor  # (3,) long clamped
    trans_mask: Tensor  # (3,)
    levels: tuple[_Level, ...]
    order: Tensor  # (J,) position of each joint in the level-concatenated output
    identity_order: bool


def _skew_np(a):
    import numpy as np

    x, y, z = a[..., 0], a[..., 1], a[..., 2]
    o = np.zeros_like(x)
    return np.stack([o, -z, y, z, o, -x, -y, x, o], axis=-1).reshape(*a.shape[:-1], 3, 3)


def _plan(sk: Skeleton, dtype: torch.dtype, device: torch.device) -> _Plan:
    key = ("plan", dtype, str(device))
    plan = sk._cache.get(key)
    if plan is not None:
        return plan
    import numpy as np

    def t(x):
        return torch.as_tensor(np.ascontiguousarray(x), dtype=dtype, device=device)

    k1 = _skew_np(sk.axes)
    k2 = k1 @ k1
    driven = sk.axis_dof >= 0
    depth = [0] * sk.num_joints
    for i, p in enumerate(sk.parents):
        if p >= 0:
            depth[i] = depth[p] + 1
    levels: list[_Level] = []
    prev: list[int] = []
    for d in range(max(depth) + 1):
        nodes = [i for i in range(sk.num_joints) if depth[i] == d]
        slots = [prev.index(sk.parents[i]) for i in nodes] if d > 0 else [0] * len(nodes)
        levels.append(_Level(torch.as_tensor(nodes, device=device), torch.as_tensor(slots, device=device),
                             tuple(nodes)))
        prev = nodes
    concat = [i for lv in levels for i in lv.nodes_list]
    order = [concat.index(i) for i in range(sk.num_joints)]
    rest_is_eye = np.allclose(sk.rest_rotation, np.eye(3))
    plan = _Plan(
        dof_index=torch.as_tensor(np.clip(sk.axis_dof, 0, None).reshape(-1), device=device),
        dof_mask=t(driven.astype(np.float64)),
        frozen=t(np.where(driven, 0.0, sk.frozen_axes)),
        k1=t(k1),
        k2=t(k2),
        rest=None if rest_is_eye else t(sk.rest_rotation),
        offset_parent=t(sk.offset_parent) if np.any(sk.offset_parent) else None,
        offset_local=t(sk.offset_local) if np.any(sk.offset_local) else None,
        lengths=t(sk.lengths),
        root_position=t(sk.root_position),
        trans_index=torch.as_tensor(np.clip(sk.translation_dof, 0, None), device=device),
        trans_mask=t((sk.translation_dof >= 0).astype(np.float64)),
        levels=tuple(levels),
        order=torch.as_tensor(order, device=device),
        identity_order=order == list(range(sk.num_joints)),
    )
    sk._cache[key] = plan
    return plan


@dataclass(frozen=True)
class _FramePlan:
    """Constants of the closed-form path, all in level order (joints of depth 0, 1, 2, ...).

    Every joint's three axes are the (z, y, x) columns of a fixed frame C_i, so its local rotation
    is C_i Rz Ry Rx C_i^T E_i. The tree is composed on H_i = G_i C_i:
    H_i = H_parent D_i M_i F_i with D_i = C_parent^T C_i and F_i = C_i^T E_i C_i, which needs no
    per-joint conjugation; positions use offsets pre-rotated into the C frames.
    """

    dof_index: Tensor  # (J*3,) clamped q index per slot (level order)
    dof_mask: Tensor  # (J, 3)
    frozen: Tensor  # (J, 3)
    d: Tensor  # (J, 3, 3)
    f: Tensor | None  # (J, 3, 3)
    c_t: Tensor  # (J, 3, 3) C^T, to recover world rotations G = H C^T
    u: Tensor | None  # (J, 3) C_parent^T u
    w: Tensor | None  # (J, 3) C^T w
    lengths_lv: Tensor  # (J,)
    level_index: Tensor  # (J,) joint index of each level-order slot
    bounds: tuple[tuple[int, int], ...]  # (offset, count) per level
    parent_slot: tuple[Tensor, ...]  # per level > 0: parent position within the previous level
    identity_parent: tuple[bool, ...]  # parent_slot is 0..n-1 (no gather needed)


def _frames_of(sk: Skeleton):
    """C (J, 3, 3) with columns (x, y, z) = (axes[2], axes[1], axes[0]), or None if some joint's
    axes are not a right-handed orthonormal frame."""
    import numpy as np

    c = np.stack([sk.axes[:, 2], sk.axes[:, 1], sk.axes[:, 0]], axis=-1)
    ok = np.allclose(np.einsum("jab,jac->jbc", c, c), np.eye(3), atol=1e-9) and np.allclose(
        np.linalg.det(c), 1.0, atol=1e-9)
    return c if ok else None


def _frame_plan(sk: Skeleton, dtype: torch.dtype, device: torch.device) -> _FramePlan | None:
    key = ("frame_plan", dtype, str(device))
    if key in sk._cache:
        return sk._cache[key]
    import numpy as np

    c = _frames_of(sk)
    if c is None:
        sk._cache[key] = None
        return None
    base = _plan(sk, dtype, device)
    lv = [i for level in base.levels for i in level.nodes_list]
    par = [sk.parents[i] for i in lv]
    c_par = np.stack([c[p] if p >= 0 else np.eye(3) for p in par])
    c_lv = c[lv]
    d = np.einsum("jba,jbc->jac", c_par, c_lv)
    e = sk.rest_rotation[lv]
    f = np.einsum("jba,jbc,jcd->jad", c_lv, e, c_lv)
    u = np.einsum("jba,jb->ja", c_par, sk.offset_parent[lv])
    w = np.einsum("jba,jb->ja", c_lv, sk.offset_local[lv])

    def t(x):
        return torch.as_tensor(np.ascontiguousarray(x), dtype=dtype, device=device)

    bounds, off = [], 0
    for level in base.levels:
        bounds.append((off, len(level.nodes_list)))
        off += len(level.nodes_list)
    driven = sk.axis_dof[lv] >= 0
    plan = _FramePlan(
        dof_index=torch.as_tensor(np.clip(sk.axis_dof[lv], 0, None).reshape(-1), device=device),
        dof_mask=t(driven.astype(np.float64)),
        frozen=t(np.where(driven, 0.0, sk.frozen_axes[lv])),
        d=t(d),
        f=None if np.allclose(f, np.eye(3)) else t(f),
        c_t=t(np.swapaxes(c_lv, -1, -2)),
        u=t(u) if np.any(u) else None,
        w=t(w) if np.any(w) else None,
        lengths_lv=t(sk.lengths[lv]),
        level_index=torch.as_tensor(lv, device=device),
        bounds=tuple(bounds),
        parent_slot=tuple(level.parent_slot for level in base.levels),
        identity_parent=tuple(level.parent_slot.tolist() == list(range(len(level.nodes_list)))
                              for level in base.levels),
    )
    sk._cache[key] = plan
    return plan


def _euler_zyx(theta: Tensor) -> Tensor:
    """Rz(a) Ry(b) Rx(c) for theta (..., 3) = (a, b, c) -> (..., 3, 3), closed form."""
    s, c = torch.sin(theta), torch.cos(theta)
    sz, sy, sx = s.unbind(-1)
    cz, cy, cx = c.unbind(-1)
    czsy, szsy = cz * sy, sz * sy
    m = torch.stack([
        cz * cy, czsy * sx - sz * cx, czsy * cx + sz * sx,
        sz * cy, szsy * sx + cz * cx, szsy * cx - cz * sx,
        -sy, cy * sx, cy * cx,
    ], dim=-1)
    return m.unflatten(-1, (3, 3))


def _fk_frames(fp: _FramePlan, p: "_Plan", q: Tensor, lens: Tensor, rotations: bool):
    """Closed-form path (see `_FramePlan`). Returns joints (..., J, 3) and optionally G (..., J, 3, 3)."""
    batch = q.shape[:-1]
    j = fp.dof_mask.shape[0]
    theta = q.index_select(-1, fp.dof_index).unflatten(-1, (j, 3)) * fp.dof_mask + fp.frozen
    local = _mm(fp.d, _euler_zyx(theta))  # (..., J, 3, 3) = D M
    if fp.f is not None:
        local = _mm(local, fp.f)
    lens = lens.index_select(-1, fp.level_index)
    root_t = q.index_select(-1, p.trans_index) * p.trans_mask + p.root_position  # (..., 3)
    hs: list[Tensor] = []
    ps: list[Tensor] = []
    for lvl, (off, n) in enumerate(fp.bounds):
        loc = local.narrow(-3, off, n)
        ln = lens.narrow(-1, off, n)[..., None]
        if lvl == 0:
            h = loc
            pos = root_t[..., None, :].expand(*batch, n, 3)
            if fp.w is not None:
                pos = pos + ln * _mv(h, fp.w[off:off + n])
        else:
            hp, pp = hs[-1], ps[-1]
            if not fp.identity_parent[lvl]:
                hp = hp.index_select(-3, fp.parent_slot[lvl])
                pp = pp.index_select(-2, fp.parent_slot[lvl])
            h = _mm(hp, loc)
            off_v = 0
            if fp.u is not None:
                off_v = _mv(hp, fp.u[off:off + n])
            if fp.w is not None:
                off_v = off_v + _mv(h, fp.w[off:off + n])
            pos = pp + ln * off_v
        hs.append(h)
        ps.append(pos)
    joints = torch.cat(ps, dim=-2)
    if not p.identity_order:
        joints = joints.index_select(-2, p.order)
    if not rotations:
        return joints
    g = _mm(torch.cat(hs, dim=-3), fp.c_t)
    if not p.identity_order:
        g = g.index_select(-3, p.order)
    return joints, g


def local_rotations(sk: Skeleton, q: Tensor) -> Tensor:
    """Per-joint rotation relative to the parent. q: (..., D) -> (..., J, 3, 3)."""
    p = _plan(sk, q.dtype, q.device)
    j = sk.num_joints
    theta = q.index_select(-1, p.dof_index).reshape(*q.shape[:-1], j, 3) * p.dof_mask + p.frozen
    s = torch.sin(theta)[..., None, None]
    c = torch.cos(theta)[..., None, None]
    r = p.k1 * s + p.k2 * (1 - c)  # (..., J, 3, 3, 3) without the identity
    eye = torch.eye(3, dtype=q.dtype, device=q.device)
    r0, r1, r2 = (r[..., k, :, :] + eye for k in range(3))
    local = _mm(_mm(r0, r1), r2)
    if p.rest is not None:
        local = _mm(local, p.rest)
    return local


def _mm(a: Tensor, b: Tensor) -> Tensor:
    """Batched 3x3 product. On CPU einsum's flattened GEMM beats `@` on tiny matrices ~5x."""
    return torch.einsum("...ij,...jk->...ik", a, b)


def _mv(a: Tensor, v: Tensor) -> Tensor:
    """Batched matrix-vector product: (..., 3, 3), (..., 3) -> (..., 3)."""
    return (a * v[..., None, :]).sum(-1)


def forward_kinematics(sk: Skeleton, q: Tensor, lengths: Tensor | None = None, rotations: bool = False,
                       generic: bool = False):
    """Forward kinematics.

    Args:
        sk: the model.
        q: (..., D) pose: root translation (metres) and joint angles (radians), any leading dims.
        lengths: optional (..., J) or (J,) bone lengths in metres replacing `sk.lengths`
            (differentiable, e.g. to fit a subject's proportions).
        rotations: also return world rotations.
        generic: force the Rodrigues path (used to cross-check the closed-form path, which is
            taken whenever every joint's axes form a right-handed frame, as in all ASF files).

    Returns:
        joints (..., J, 3) world positions in metres (for ASF models: the root, then each bone's
        end point, in `sk.joint_names` order); with `rotations`, also (..., J, 3, 3) world
        rotations of each joint frame.
    """
    if q.shape[-1] != sk.num_dofs:
        raise InputError(f"pose q has {q.shape[-1]} dofs in its last dim (shape {tuple(q.shape)}); "
                         f"skeleton {sk.name!r} has {sk.num_dofs}")
    p = _plan(sk, q.dtype, q.device)
    batch = q.shape[:-1]
    if lengths is None:
        lens = p.lengths
    else:
        if lengths.shape[-1] != sk.num_joints:
            raise InputError(f"lengths must have {sk.num_joints} entries in the last dim, got {tuple(lengths.shape)}")
        lens = lengths.to(q.dtype)
    fp = None if generic else _frame_plan(sk, q.dtype, q.device)
    if fp is not None:
        return _fk_frames(fp, p, q, lens, rotations)
    root_t = q.index_select(-1, p.trans_index) * p.trans_mask + p.root_position  # (..., 3)

    local = local_rotations(sk, q)
    rots: list[Tensor] = []
    poss: list[Tensor] = []
    for d, lv in enumerate(p.levels):
        loc = local.index_select(-3, lv.nodes)  # (..., n, 3, 3)
        ln = lens.index_select(-1, lv.nodes)[..., None]  # (..., n, 1) or (n, 1)
        if d == 0:
            g = loc
            pos = root_t[..., None, :].expand(*batch, len(lv.nodes_list), 3)
            if p.offset_local is not None:
                pos = pos + ln * _mv(g, p.offset_local[lv.nodes])
        else:
            gp = rots[-1].index_select(-3, lv.parent_slot)
            pp = poss[-1].index_select(-2, lv.parent_slot)
            g = _mm(gp, loc)
            off = 0
            if p.offset_parent is not None:
                off = _mv(gp, p.offset_parent[lv.nodes])
            if p.offset_local is not None:
                off = off + _mv(g, p.offset_local[lv.nodes])
            pos = pp + ln * off
        rots.append(g)
        poss.append(pos)
    joints = torch.cat(poss, dim=-2)
    if not p.identity_order:
        joints = joints.index_select(-2, p.order)
    if not rotations:
        return joints
    world = torch.cat(rots, dim=-3)
    if not p.identity_order:
        world = world.index_select(-3, p.order)
    return joints, world
