"""Motion export: BVH for animation tools (Blender, MotionBuilder, ...).

`write_bvh(path, skeleton, q, fps)` writes one BVH joint per skeleton joint, placed at the point its
rotation turns about (for ASF skeletons: the bone's start, i.e. the parent bone's end), with
channels `Zrotation Yrotation Xrotation` (R = Rz Ry Rx, degrees) holding the joint's rotation
relative to its parent, and the root's `Xposition Yposition Zposition` in metres (Y up, as the
mocap). Bones that end a chain get an `End Site` at their end point, so the BVH reproduces every
joint position of `Skeleton.forward_kinematics` (to ~1e-8 m: offsets and root positions in metres
with 9 decimals, angles with 6; rotations at the gimbal lock, Y = +-90 degrees, are exported exactly).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from torch import Tensor

from ptrack.body.kinematics import local_rotations, root_positions
from ptrack.body.rotations import matrix_to_euler_np
from ptrack.body.skeleton import Skeleton
from ptrack.errors import InputError


def bvh_text(skeleton: Skeleton, q: Tensor, fps: float) -> str:
    """BVH file contents for poses q (T, D) of `skeleton` sampled at `fps` frames per second."""
    if q.ndim != 2 or q.shape[-1] != skeleton.num_dofs:
        raise InputError(f"BVH export needs q of shape (T, {skeleton.num_dofs}), got {tuple(q.shape)}")
    if fps <= 0:
        raise InputError(f"BVH export needs a positive frame rate, got {fps}")
    if np.any(skeleton.slide_dof >= 0):
        sliding = [skeleton.joint_names[i] for i in np.flatnonzero(skeleton.slide_dof >= 0)]
        raise InputError(
            f"BVH export: {skeleton.name!r} has prismatic joints below its root (links {sliding[:3]}), "
            "which BVH cannot hold: only its root translates"
        )
    sk = skeleton
    children: dict[int, list[int]] = {i: [] for i in range(sk.num_joints)}
    for i, p in enumerate(sk.parents):
        if p >= 0:
            children[p].append(i)
    # offset of joint c's pivot from its parent i's pivot, in i's frame: len_i w_i + len_c u_c
    own = sk.lengths[:, None] * sk.offset_local  # (J, 3)
    lines = ["HIERARCHY"]

    def emit(i: int, depth: int) -> None:
        pad = "  " * depth
        if i == 0:
            lines.append(f"ROOT {sk.joint_names[0]}")
            offset = np.zeros(3)  # the position channels hold the root's absolute position
            channels = "CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation"
        else:
            p = sk.parents[i]
            offset = own[p] + sk.lengths[i] * sk.offset_parent[i]
            lines.append(f"{pad}JOINT {sk.joint_names[i]}")
            channels = "CHANNELS 3 Zrotation Yrotation Xrotation"
        lines.extend([f"{pad}{{", f"{pad}  OFFSET {_vec(offset)}", f"{pad}  {channels}"])
        for c in children[i]:
            emit(c, depth + 1)
        if not children[i]:
            lines.extend([f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {_vec(own[i])}", f"{pad}  }}"])
        lines.append(f"{pad}}}")

    emit(0, 0)
    local = local_rotations(sk, q.detach().double().cpu()).numpy()  # (T, J, 3, 3)
    euler = np.degrees(matrix_to_euler_np(local))[..., ::-1]  # (T, J, 3) as z, y, x
    root = root_positions(sk, q.detach().double().cpu()).numpy()  # (T, 3)
    lines += ["MOTION", f"Frames: {q.shape[0]}", f"Frame Time: {1.0 / fps:.8f}"]
    for t in range(q.shape[0]):
        lines.append(" ".join([*(f"{v:.9f}" for v in root[t]), *(f"{v:.6f}" for v in euler[t].reshape(-1))]))
    return "\n".join(lines) + "\n"


def _vec(v) -> str:
    return " ".join(f"{float(x):.9f}" for x in v)


def write_bvh(path: str | Path, skeleton: Skeleton, q: Tensor, fps: float) -> None:
    """Write poses q (T, D) of `skeleton` at `fps` as a BVH file (see module docstring)."""
    Path(path).write_text(bvh_text(skeleton, q, fps), encoding="utf-8")
