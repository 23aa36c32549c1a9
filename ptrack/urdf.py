"""URDF <-> `Skeleton`, through pytorch-kinematics.

`skeleton_from_urdf` makes any URDF articulated model trackable: each URDF joint becomes a ptrack
joint (revolute/continuous joints become dofs, fixed joints carry no dof). `skeleton_to_urdf`
writes a ptrack model as URDF (root translation as three prismatic joints, each rotation axis as a
revolute joint), which is also how ptrack's FK is checked against pytorch-kinematics.
"""

from __future__ import annotations

import math
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
import torch

from ptrack.errors import InputError
from ptrack.rotations import axis_angle_matrix, matrix_to_euler_np
from ptrack.skeleton import Skeleton


def _fmt(v) -> str:
    return " ".join(f"{float(x):.17g}" for x in v)



def skeleton_to_urdf(sk: Skeleton) -> str:
    """URDF text of `sk`. Link `sk.joint_names[i]` is joint i's frame (position p_i, rotation G_i);
    URDF joint names are the dof names, so pytorch-kinematics' joint order maps back by name."""
    out = [f'<?xml version="1.0"?>\n<robot name={quoteattr(sk.name or "ptrack")}>', '  <link name="world"/>']
    counter = [0]

    def link(name: str) -> None:
        out.append(f"  <link name={quoteattr(name)}/>")

    def joint(name, kind, parent, child, xyz=(0, 0, 0), rpy=(0, 0, 0), axis=None, lim=None):
        s = [f"  <joint name={quoteattr(name)} type=\"{kind}\">",
             f"    <parent link={quoteattr(parent)}/>", f"    <child link={quoteattr(child)}/>",
             f'    <origin xyz="{_fmt(xyz)}" rpy="{_fmt(rpy)}"/>']
        if axis is not None:
            s.append(f'    <axis xyz="{_fmt(axis)}"/>')
        if lim is not None:
            lo, hi = lim
            s.append(f'    <limit lower="{max(lo, -1e6):.17g}" upper="{min(hi, 1e6):.17g}" effort="1" velocity="1"/>')
        s.append("  </joint>")
        out.append("\n".join(s))

    def tmp(base: str) -> str:
        counter[0] += 1
        name = f"{base}__{counter[0]}"
        link(name)
        return name

    for i, name in enumerate(sk.joint_names):
        if i == 0:
            prev = tmp(name)
            joint(f"{name}__origin", "fixed", "world", prev, xyz=sk.root_position)
            for k, ax in enumerate("xyz"):
                d = int(sk.translation_dof[k])
                if d >= 0:
                    nxt = tmp(name)
                    joint(sk.dof_names[d], "prismatic", prev, nxt, axis=np.eye(3)[k], lim=(-1e6, 1e6))
                    prev = nxt
        else:
            prev = tmp(name)
            parent = sk.joint_names[sk.parents[i]]
            joint(f"{name}__offset", "fixed", parent, prev, xyz=sk.lengths[i] * sk.offset_parent[i])
        for k in range(3):
            d = int(sk.axis_dof[i, k])
            ax = sk.axes[i, k]
            if d >= 0:
                nxt = tmp(name)
                lim = (sk.lower[d], sk.upper[d])
                kind = "continuous" if not np.all(np.isfinite(lim)) else "revolute"
                joint(sk.dof_names[d], kind, prev, nxt, axis=ax, lim=None if kind == "continuous" else lim)
                prev = nxt
            elif sk.frozen_axes[i, k] != 0.0:
                nxt = tmp(name)
                r = axis_angle_matrix(torch.as_tensor(ax), torch.tensor(float(sk.frozen_axes[i, k]),
                                                                         dtype=torch.float64)).numpy()
                joint(f"{name}__frozen{k}", "fixed", prev, nxt, rpy=matrix_to_euler_np(r))
                prev = nxt
        e = sk.rest_rotation[i]
        link(name)
        joint(f"{name}__end", "fixed", prev, name, xyz=sk.lengths[i] * (e @ sk.offset_local[i]),
              rpy=matrix_to_euler_np(e))
    out.append("</robot>\n")
    return "\n".join(out)


def _nearest_rotation(m: np.ndarray) -> np.ndarray:
    """The rotation closest to m (3, 3) in Frobenius norm."""
    u, _, vt = np.linalg.svd(m)
    r = u @ vt
    if np.linalg.det(r) < 0:
        r = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    return r


def _frame_with_z(z: np.ndarray) -> np.ndarray:
    """Axis slots (z, y, x) of a right-handed orthonormal frame whose z column is the unit vector z."""
    z = z / np.linalg.norm(z)
    helper = np.eye(3)[0] if abs(z[0]) < 0.9 else np.eye(3)[1]
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([z, y, x])


def skeleton_from_urdf(path: str | Path, floating_base: bool | None = None) -> Skeleton:
    """Build a Skeleton from a URDF file (see `Skeleton.from_urdf`)."""
    import pytorch_kinematics as pk

    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"URDF file not found: {p}")
    try:
        chain = pk.build_chain_from_urdf(p.read_bytes())
    except Exception as e:  # the URDF parser raises assorted exception types on bad XML
        raise InputError(f"{p}: not a readable URDF ({type(e).__name__}: {e})") from None

    names: list[str] = []
    parents: list[int] = []
    axes, axis_dof, rest, off_dir, lengths = [], [], [], [], []
    dof_names: list[str] = []
    lower: list[float] = []
    upper: list[float] = []

    root = chain._root
    if floating_base is None:  # a base the file already moves (prismatic joints, as to_urdf writes) floats as it is
        frames, prismatic = list(root.children), False
        while frames and not prismatic:
            f = frames.pop()
            prismatic = f.joint.joint_type == "prismatic"
            frames.extend(f.children)
        floating_base = not prismatic
    names.append(root.link.name)
    parents.append(-1)
    rest.append(np.eye(3))
    off_dir.append(np.zeros(3))
    lengths.append(0.0)
    root_axes = np.eye(3)[::-1].copy()  # slots (z, y, x)
    root_dof = -np.ones(3, dtype=np.int64)
    trans = -np.ones(3, dtype=np.int64)
    if floating_base:
        for k, a in enumerate("xyz"):
            trans[k] = len(dof_names)
            dof_names.append(f"root.t{a}")
            lower.append(-math.inf)
            upper.append(math.inf)
        for k in range(3):  # G_root = Rz Ry Rx
            root_dof[k] = len(dof_names) + 2 - k
        for a in "xyz":
            dof_names.append(f"root.r{a}")
            lower.append(-math.inf)
            upper.append(math.inf)
    axes.append(root_axes)
    axis_dof.append(root_dof)

    world_rot = {0: np.eye(3)}  # rest world rotation of each joint made so far
    base_chain = {0}  # joints reached from the base through fixed/prismatic joints only
    stack = [(c, 0) for c in reversed(root.children)]
    while stack:
        frame, parent = stack.pop()
        j = frame.joint
        m = j.offset.get_matrix()[0].double().numpy() if j.offset is not None else np.eye(4)
        r0, t0 = _nearest_rotation(m[:3, :3]), m[:3, 3]  # pytorch-kinematics parses in float32
        lo = frame.link.offset
        if lo is not None and not np.allclose(lo.get_matrix()[0].double().numpy(), np.eye(4)):
            raise InputError(f"{p}: link {frame.link.name!r} has a non-identity link offset, which ptrack does not support")
        idx = len(names)
        names.append(frame.link.name)
        parents.append(parent)
        rest.append(r0)
        n = float(np.linalg.norm(t0))
        off_dir.append(t0 / n if n > 0 else np.zeros(3))
        lengths.append(n)
        world_rot[idx] = world_rot[parent] @ r0
        a = np.eye(3)[::-1].copy()  # slots (z, y, x) of the identity frame
        d = -np.ones(3, dtype=np.int64)
        if j.joint_type in ("fixed", "prismatic") and parent in base_chain:
            base_chain.add(idx)
        if j.joint_type == "prismatic":
            # only as a root translation: at the base, along a world axis
            ax = world_rot[parent] @ r0 @ np.asarray(j.axis.double().numpy(), dtype=np.float64)
            k = int(np.argmax(np.abs(ax)))
            if floating_base:
                raise InputError(f"{p}: prismatic joint {j.name!r} moves the base, which floating_base=True "
                                 "already does; use floating_base=False for this model")
            if parent not in base_chain or not np.allclose(ax, np.eye(3)[k], atol=1e-9) or trans[k] >= 0:
                raise InputError(f"{p}: prismatic joint {j.name!r} is not a base translation along +x, +y or +z; "
                                 "ptrack supports prismatic joints only as the root's translation")
            trans[k] = len(dof_names)
            dof_names.append(j.name)
            lower.append(-math.inf)
            upper.append(math.inf)
        elif j.joint_type == "revolute":
            ax = np.asarray(j.axis.double().numpy(), dtype=np.float64)
            a[:] = _frame_with_z(r0 @ (ax / np.linalg.norm(ax)))  # R0 Rot(ax) = Rot(R0 ax) R0
            d[0] = len(dof_names)
            dof_names.append(j.name)
            lim = getattr(j, "limits", None)
            lo_, hi_ = (lim if lim is not None else (-math.inf, math.inf))
            lower.append(float(lo_) if lo_ is not None else -math.inf)
            upper.append(float(hi_) if hi_ is not None else math.inf)
        elif j.joint_type not in ("fixed", "prismatic"):
            raise InputError(f"{p}: joint {j.name!r} is {j.joint_type}; ptrack supports revolute, continuous and fixed joints")
        axes.append(a)
        axis_dof.append(d)
        stack.extend((c, idx) for c in reversed(frame.children))

    return Skeleton(
        name=p.stem,
        joint_names=tuple(names),
        parents=tuple(parents),
        axes=np.asarray(axes),
        axis_dof=np.asarray(axis_dof),
        rest_rotation=np.asarray(rest),
        offset_parent=np.asarray(off_dir),
        offset_local=np.zeros((len(names), 3)),
        lengths=np.asarray(lengths),
        root_position=np.zeros(3),
        translation_dof=trans,
        dof_names=tuple(dof_names),
        lower=np.asarray(lower),
        upper=np.asarray(upper),
    )
