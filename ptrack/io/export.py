"""Motion export: BVH for animation tools (Blender, MotionBuilder, game engines, retargeting rigs).

`write_bvh(path, skeleton, q, fps, rest=..., names=..., floor_m=...)` writes one BVH joint per skeleton joint,
placed at the point its rotation turns about (for ASF skeletons: the bone's start, i.e. the parent bone's
end), with channels `Zrotation Yrotation Xrotation` (R = Rz Ry Rx, degrees) and the root's
`Xposition Yposition Zposition` in metres (Y up, as the mocap; right-handed). So ptrack's `joints[:, i]`
(the END of bone i) is where BVH joint i's children sit (for ASF skeletons: BVH joint c with parents[c] = i),
or BVH joint i's `End Site` when bone i ends a chain; BVH joint i itself sits at `joints[:, parents[i]]`.
Every joint position of `Skeleton.forward_kinematics` comes back (to ~1e-8 m: offsets and root positions in
metres with 9 decimals, angles with 6; rotations at the gimbal lock, Y = +-90 degrees, are exported exactly).

Options:
- `rest`: the pose the OFFSETs describe (all channels zero). "asf": the skeleton's own rest pose (q = 0; for
  CMU skeletons the ASF's: arms out sideways, legs 20 degrees apart, facing +Z). "tpose": a T-pose built
  from it (`tpose_rotations`): every moving bone nearest the vertical made vertical (legs down, spine and
  neck up), every one nearest the sideways axis made sideways (clavicles and arms out along +-X), bones
  pointing forward (feet) and joints without dofs (hips, hands, toes, landmarks) keep their angle to their
  parent; facing +Z (the skeleton's own facing: CMU's is +Z). The channels change with the rest pose so
  that every frame's joint positions are the same.
- `names`: a joint name map for retargeting rigs (`NAME_MAPS`, e.g. "mixamo"); unmapped joints keep their names.
- `floor_m`: the floor's height along +Y; the BVH is moved down by it so that the floor is at Y = 0.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from ptrack.body.kinematics import forward_kinematics, local_rotations, root_positions
from ptrack.body.rotations import matrix_to_euler_np
from ptrack.body.skeleton import Skeleton
from ptrack.errors import InputError

if TYPE_CHECKING:
    from ptrack.io.exporters import ExportOptions
    from ptrack.io.run_folder import RunFolder

#: the rest poses a BVH can be written in (see the module docstring)
REST_POSES = ("asf", "tpose")

#: CMU/ASF bone name -> Mixamo rig joint at the same point. A BVH joint sits at its bone's START, so e.g.
#: `lfemur` (the thigh, starting at the hip) is Mixamo's LeftUpLeg. Not mapped (they keep their names):
#: `lhipjoint`/`rhipjoint` (pelvis to hip, Mixamo has no such bone), `upperneck` (mid-neck), `lhand`/`rhand`
#: (mid-palm) and the landmark joints `lm_*` of footage runs.
MIXAMO: dict[str, str] = {
    "root": "mixamorig:Hips",
    "lowerback": "mixamorig:Spine",
    "upperback": "mixamorig:Spine1",
    "thorax": "mixamorig:Spine2",
    "lowerneck": "mixamorig:Neck",
    "head": "mixamorig:Head",
    **{
        f"{s}{bone}": f"mixamorig:{side}{rig}"
        for s, side in (("l", "Left"), ("r", "Right"))
        for bone, rig in (
            ("femur", "UpLeg"),
            ("tibia", "Leg"),
            ("foot", "Foot"),
            ("toes", "ToeBase"),
            ("clavicle", "Shoulder"),
            ("humerus", "Arm"),
            ("radius", "ForeArm"),
            ("wrist", "Hand"),
            ("fingers", "HandIndex1"),
            ("thumb", "HandThumb1"),
        )
    },
}

#: name map -> {ptrack joint name: BVH joint name}
NAME_MAPS: dict[str, dict[str, str]] = {"mixamo": MIXAMO}


def name_map(name: str | None) -> dict[str, str]:
    """The joint name map called `name` (a `NAME_MAPS` key; None: no renaming). InputError for an unknown one."""
    if name is None:
        return {}
    if name not in NAME_MAPS:
        raise InputError(f"unknown BVH name map {name!r}: one of {', '.join(sorted(NAME_MAPS))}")
    return NAME_MAPS[name]


def _child_offsets(sk: Skeleton) -> tuple[dict[int, list[int]], np.ndarray]:
    """Children of each joint, and each joint's offset from its parent's pivot in the parent's frame (J, 3):
    len_p w_p + len_c u_c (the root's: zero)."""
    children: dict[int, list[int]] = {i: [] for i in range(sk.num_joints)}
    offsets = np.zeros((sk.num_joints, 3))
    own = sk.lengths[:, None] * sk.offset_local  # (J, 3) each bone's own vector in its frame
    for c, p in enumerate(sk.parents):
        if p >= 0:
            children[p].append(c)
            offsets[c] = own[p] + sk.lengths[c] * sk.offset_parent[c]
    return children, offsets


def _swing(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation (3, 3) turning unit vector a (3,) onto unit vector b (3,) (not opposite)."""
    v, c = np.cross(a, b), float(np.dot(a, b))
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def rest_rotations(skeleton: Skeleton, rest: str = "asf") -> np.ndarray:
    """Each joint's world rotation in the BVH's rest pose, (J, 3, 3): its offsets are the skeleton's turned by
    them. "asf": the skeleton's rotations at q = 0; "tpose": `tpose_rotations`."""
    if rest not in REST_POSES:
        raise InputError(f"unknown BVH rest pose {rest!r}: one of {', '.join(REST_POSES)}")
    q0 = torch.zeros(skeleton.num_dofs, dtype=torch.float64)
    _, g0 = forward_kinematics(skeleton, q0, rotations=True)
    return g0.numpy() if rest == "asf" else tpose_rotations(skeleton)


def tpose_rotations(skeleton: Skeleton) -> np.ndarray:
    """World rotations (J, 3, 3) of each joint in a T-pose made from the skeleton's rest pose (q = 0), parents
    first: a joint with dofs whose bone (towards its children or its end) points nearest +-Y or +-X is swung
    onto that axis (legs down, spine up, arms out); other joints (feet pointing forward, joints without dofs)
    keep their rest rotation relative to their parent."""
    sk = skeleton
    q0 = torch.zeros(sk.num_dofs, dtype=torch.float64)
    _, g0t = forward_kinematics(sk, q0, rotations=True)
    g0 = g0t.numpy()
    children, offsets = _child_offsets(sk)
    own = sk.lengths[:, None] * sk.offset_local
    moving = np.any(sk.axis_dof >= 0, axis=1)
    out = np.empty_like(g0)
    for i, p in enumerate(sk.parents):
        parent = out[p] @ g0[p].T if p >= 0 else np.eye(3)  # how the T-pose turned the parent
        out[i] = parent @ g0[i]  # keeps the rest relation to the parent
        bone = sum((offsets[c] for c in children[i]), np.zeros(3)) if children[i] else own[i]
        n = float(np.linalg.norm(bone))
        if not moving[i] or n < 1e-9:
            continue
        d = out[i] @ (bone / n)  # the bone's world direction so far
        k = int(np.argmax(np.abs(d)))
        if k == 2:  # pointing forward or back (a foot): keep it
            continue
        target = np.zeros(3)
        target[k] = np.sign(d[k])
        out[i] = _swing(d, target) @ out[i]
    return out


def bvh_text(
    skeleton: Skeleton,
    q: Tensor,
    fps: float,
    rest: str = "asf",
    names: dict[str, str] | None = None,
    floor_m: float | None = None,
) -> str:
    """BVH file contents for poses q (T, D) of `skeleton` sampled at `fps` frames per second (module docstring:
    `rest` a `REST_POSES` name, `names` {joint: BVH name}, `floor_m` the floor's height along +Y or None)."""
    if q.ndim != 2 or q.shape[-1] != skeleton.num_dofs:
        raise InputError(f"BVH export needs q of shape (T, {skeleton.num_dofs}), got {tuple(q.shape)}")
    if not fps > 0 or not np.isfinite(fps):
        raise InputError(f"BVH export needs a positive frame rate, got {fps}")
    if np.any(skeleton.slide_dof >= 0):
        sliding = [skeleton.joint_names[i] for i in np.flatnonzero(skeleton.slide_dof >= 0)]
        raise InputError(
            f"BVH export: {skeleton.name!r} has prismatic joints below its root (links {sliding[:3]}), "
            "which BVH cannot hold: only its root translates"
        )
    sk = skeleton
    names = names or {}
    bvh_names = [names.get(n, n) for n in sk.joint_names]
    if len(set(bvh_names)) != len(bvh_names):
        raise InputError(f"BVH export: the name map gives two joints of {sk.name!r} the same name")
    a = rest_rotations(sk, rest)  # (J, 3, 3) each joint's world rotation at rest
    children, offsets = _child_offsets(sk)
    own = sk.lengths[:, None] * sk.offset_local
    lines = ["HIERARCHY"]
    order: list[int] = []  # joints in the hierarchy's order, which the MOTION lines' channels follow

    def emit(i: int, depth: int) -> None:
        order.append(i)
        pad = "  " * depth
        if i == 0:
            lines.append(f"ROOT {bvh_names[0]}")
            offset = np.zeros(3)  # the position channels hold the root's absolute position
            channels = "CHANNELS 6 Xposition Yposition Zposition Zrotation Yrotation Xrotation"
        else:
            offset = a[sk.parents[i]] @ offsets[i]
            lines.append(f"{pad}JOINT {bvh_names[i]}")
            channels = "CHANNELS 3 Zrotation Yrotation Xrotation"
        lines.extend([f"{pad}{{", f"{pad}  OFFSET {_vec(offset)}", f"{pad}  {channels}"])
        for c in children[i]:
            emit(c, depth + 1)
        if not children[i]:
            lines.extend([f"{pad}  End Site", f"{pad}  {{", f"{pad}    OFFSET {_vec(a[i] @ own[i])}", f"{pad}  }}"])
        lines.append(f"{pad}}}")

    emit(0, 0)
    q64 = q.detach().double().cpu()
    local = local_rotations(sk, q64).numpy()  # (T, J, 3, 3) G_parent^T G_i
    # BVH world rotation W_i = G_i A_i^T, so its channels hold W_parent^T W_i = A_parent local_i A_i^T
    a_parent = np.stack([a[p] if p >= 0 else np.eye(3) for p in sk.parents])
    bvh_local = a_parent @ local @ np.swapaxes(a, -1, -2)
    euler = np.degrees(matrix_to_euler_np(bvh_local))[:, order, ::-1]  # (T, J, 3) as z, y, x, hierarchy order
    root = root_positions(sk, q64).numpy()  # (T, 3)
    if floor_m is not None:
        root[:, 1] -= floor_m
    lines += ["MOTION", f"Frames: {q.shape[0]}", f"Frame Time: {1.0 / fps:.10f}"]
    for t in range(q.shape[0]):
        lines.append(" ".join([*(f"{v:.9f}" for v in root[t]), *(f"{v:.6f}" for v in euler[t].reshape(-1))]))
    return "\n".join(lines) + "\n"


def _vec(v) -> str:
    return " ".join(f"{float(x):.9f}" for x in v)


def write_bvh(
    path: str | Path,
    skeleton: Skeleton,
    q: Tensor,
    fps: float,
    rest: str = "asf",
    names: dict[str, str] | None = None,
    floor_m: float | None = None,
) -> None:
    """Write poses q (T, D) of `skeleton` at `fps` as a BVH file (see `bvh_text` and the module docstring)."""
    Path(path).write_text(bvh_text(skeleton, q, fps, rest, names, floor_m), encoding="utf-8")


def export_bvh(run: RunFolder, out_dir: Path, options: ExportOptions) -> list[Path]:
    """`ptrack export --format bvh`: result.bvh of the run's estimate in `options.rest` with `options.names`,
    the floor at Y = 0 when the run knew it (`RunFolder.floor_m`; CMU runs: the mocap floor is Y = 0 already)."""
    options.refuse("bvh", accepted=("names", "rest"), up=("y",))
    names = name_map(options.names)
    q = torch.as_tensor(run.arrays["q"], dtype=torch.float64)
    path = out_dir / "result.bvh"
    write_bvh(path, run.skeleton, q, run.fps, rest=options.rest or "asf", names=names, floor_m=run.floor_m)
    return [path]
