"""BVH export: a small independent BVH reader must reproduce every FK joint position."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from ptrack.body.rotations import euler_matrix_np
from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.errors import InputError
from ptrack.io.export import bvh_text, write_bvh

DATA = Path(__file__).resolve().parents[1] / "ptrack" / "data"


def read_bvh(text: str):
    """-> (names: list[str | None] (None = End Site), parents, offsets (N, 3), channels {i: n},
    frame_time, values (T, C))."""
    tok = text.split()
    names: list[str | None] = []
    parents: list[int] = []
    offsets: list[list[float]] = []
    channels: dict[int, int] = {}
    stack: list[int] = []
    i = 0
    while tok[i] != "MOTION":
        t = tok[i]
        if t in ("ROOT", "JOINT"):
            names.append(tok[i + 1])
            parents.append(stack[-1] if stack else -1)
            i += 2
        elif t == "End":
            names.append(None)
            parents.append(stack[-1])
            i += 2
        elif t == "{":
            stack.append(len(names) - 1)
            i += 1
        elif t == "}":
            stack.pop()
            i += 1
        elif t == "OFFSET":
            offsets.append([float(x) for x in tok[i + 1 : i + 4]])
            i += 4
        elif t == "CHANNELS":
            channels[len(names) - 1] = int(tok[i + 1])
            i += 2 + int(tok[i + 1])
        else:
            i += 1
    frames = int(tok[tok.index("Frames:") + 1])
    frame_time = float(tok[tok.index("Time:") + 1])
    values = np.asarray(tok[tok.index("Time:") + 2 :], dtype=np.float64).reshape(frames, -1)
    return names, parents, np.asarray(offsets), channels, frame_time, values


def bvh_positions(text: str) -> tuple[list[str | None], list[int], np.ndarray]:
    """World position of every BVH joint and end site per frame: (T, N, 3)."""
    names, parents, offsets, channels, _, values = read_bvh(text)
    out = np.zeros((values.shape[0], len(names), 3))
    for f, row in enumerate(values):
        v = list(row)
        rot: dict[int, np.ndarray] = {}
        for j in range(len(names)):
            if names[j] is None:
                out[f, j] = out[f, parents[j]] + rot[parents[j]] @ offsets[j]
                continue
            if channels[j] == 6:
                x, y, z, rz, ry, rx = v[:6]
                v = v[6:]
                out[f, j] = np.array([x, y, z]) + offsets[j]
                parent_rot = np.eye(3)
            else:
                rz, ry, rx = v[:3]
                v = v[3:]
                out[f, j] = out[f, parents[j]] + rot[parents[j]] @ offsets[j]
                parent_rot = rot[parents[j]]
            rot[j] = parent_rot @ euler_matrix_np(tuple(np.radians([rx, ry, rz])), "XYZ")
    return names, parents, out


def _check_against_fk(sk: Skeleton, q: torch.Tensor, text: str) -> float:
    names, parents, pos = bvh_positions(text)
    joints, rot = sk.forward_kinematics(q.double(), rotations=True)
    fk = joints.numpy()
    # a BVH joint sits where its rotation turns: p_i - length_i G_i w_i (ASF: the parent bone's end)
    pivot = fk - sk.lengths[:, None] * np.einsum("tjab,jb->tja", rot.numpy(), sk.offset_local)
    err = 0.0
    for j, name in enumerate(names):
        # an end site (no name) sits at its joint's position
        ref = fk[:, sk.joint_index(names[parents[j]])] if name is None else pivot[:, sk.joint_index(name)]
        err = max(err, float(np.abs(pos[:, j] - ref).max()))
    return err


@pytest.fixture(scope="module")
def clip():
    sk = Skeleton.from_asf(DATA / "10.asf")
    return sk, load_amc(DATA / "10_02.amc", sk).q[::40]


def test_bvh_reproduces_fk(clip):
    sk, q = clip
    assert not np.any(sk.offset_parent)  # ASF: every bone starts at its parent's end
    text = bvh_text(sk, q, fps=30.0)
    assert _check_against_fk(sk, q, text) < 1e-6
    names, _, _, channels, frame_time, values = read_bvh(text)
    assert names[0] == "root" and channels[0] == 6 and values.shape == (q.shape[0], 6 + 3 * (sk.num_joints - 1))
    assert frame_time == pytest.approx(1 / 30, abs=1e-8)


def test_bvh_of_reduced_model_with_frozen_values(clip):
    sk, q = clip
    reduced = sk.freeze(["*fingers", "*thumb", "lfemur.rz"], value=0.3)
    qr = reduced.reduce(q, sk)
    assert _check_against_fk(reduced, qr, bvh_text(reduced, qr, fps=120.0)) < 1e-6


def test_bvh_of_urdf_model(tmp_path, clip):
    sk, q = clip
    # the root translation exports as prismatic joints below the file's base link, which BVH cannot hold
    (tmp_path / "m.urdf").write_text(sk.to_urdf())
    with pytest.raises(InputError, match="prismatic"):
        bvh_text(Skeleton.from_urdf(tmp_path / "m.urdf", collapse=False), q, fps=30.0)
    fixed = sk.freeze(["root.t*"])
    (tmp_path / "m.urdf").write_text(fixed.to_urdf())
    model = Skeleton.from_urdf(tmp_path / "m.urdf", floating_base=False, collapse=False)
    qm = q[:, [sk.dof_names.index(n) for n in model.dof_names]]
    assert _check_against_fk(model, qm, bvh_text(model, qm, fps=30.0)) < 1e-6


def test_write_bvh_and_bad_input(tmp_path, clip):
    sk, q = clip
    write_bvh(tmp_path / "m.bvh", sk, q, fps=30.0)
    assert (tmp_path / "m.bvh").read_text().startswith("HIERARCHY\nROOT root")
    with pytest.raises(InputError, match="shape"):
        bvh_text(sk, q[:, :10], fps=30.0)
    with pytest.raises(InputError, match="frame rate"):
        bvh_text(sk, q, fps=0.0)


def _pose_with_local_rotation(sk: Skeleton, q: torch.Tensor, joint: str, local: np.ndarray) -> torch.Tensor:
    """q with `joint`'s three ASF dofs set so that its rotation relative to its parent is `local`
    (the joint's parent rotation E is the identity and its axes the (z, y, x) columns of a frame C:
    local = C Rz Ry Rx C^T, solved for the angles with scipy)."""
    from scipy.spatial.transform import Rotation

    i = sk.joint_index(joint)
    c = np.stack([sk.axes[i, 2], sk.axes[i, 1], sk.axes[i, 0]], axis=-1)
    x, y, z = Rotation.from_matrix(c.T @ local @ c).as_euler("xyz")  # extrinsic xyz: Rz Ry Rx
    q = q.clone()
    for slot, angle in zip(range(3), (z, y, x)):
        q[int(sk.axis_dof[i, slot])] = angle
    return q


def test_bvh_at_gimbal_lock_reproduces_fk(clip):
    """Joints whose rotation relative to the parent has a middle (Y) Euler angle of exactly +-90
    degrees, or within 1e-7 rad of it, export to BVH channels that reproduce FK to 1e-6 m."""
    sk, q_clip = clip
    rng = np.random.default_rng(0)
    frames = []
    for middle in (np.pi / 2, -np.pi / 2, np.pi / 2 - 1e-7, -np.pi / 2 + 1e-9):
        q = q_clip[len(frames)].clone()
        q[sk.dof_names.index("root.ry")] = middle  # the root's axes are x, y, z: local = Rz Ry Rx
        for joint in ("lfemur", "rhumerus"):
            a, c = rng.uniform(-np.pi, np.pi, size=2)
            q = _pose_with_local_rotation(sk, q, joint, euler_matrix_np((c, middle, a), "XYZ"))
        frames.append(q)
    q = torch.stack(frames)
    text = bvh_text(sk, q, fps=30.0)
    names, _, _, channels, _, values = read_bvh(text)
    # the export really is at the lock: the Y channel of those joints is +-90 degrees
    col, start = {}, 0
    for k, name in enumerate(names):
        if name is not None:
            col[name] = start + channels[k] - 3  # the rotation channels come last
            start += channels[k]
    for joint in ("root", "lfemur", "rhumerus"):
        np.testing.assert_allclose(np.abs(values[:, col[joint] + 1]), 90.0, rtol=0, atol=1e-5, err_msg=joint)
    assert _check_against_fk(sk, q, text) < 1e-6


def test_bvh_of_skeleton_whose_joints_are_not_in_hierarchy_order(clip):
    """A footage run's model has its landmark joints appended last (children of the head and feet): the MOTION
    lines follow the hierarchy's order, not the joints' (this was 1.35 m off before)."""
    from ptrack.body.subject import add_landmark_joints

    sk, q = clip
    model = add_landmark_joints(sk, 1.7)
    # lm_nose, a child of the head, comes after the arms in the joints' order; in the hierarchy it follows the head
    assert model.joint_names[sk.num_joints] == "lm_nose" and model.parents[sk.num_joints] == sk.joint_index("head")
    assert _check_against_fk(model, q, bvh_text(model, q, fps=30.0)) < 1e-6
