"""Forward kinematics on arbitrary tree shapes, against a plain per-joint recursive reference.

The CMU skeletons are one family of trees; URDF robots and hand-written ASFs give others (levels
longer than the next one, children of the first few joints of a level, deep chains, stars). Here
`Skeleton`s are built directly with random parents, axes, driven slots, rest rotations and offsets,
and every FK path (closed form without grad, the analytical backward, autograd through the closed
form and through the Rodrigues path) is compared with a recursive implementation written below
from the model equations in `ptrack.body.skeleton`'s docstring, values and gradients w.r.t. q.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import torch

from ptrack.body.acclaim import INCH_M
from ptrack.body.kinematics import _plan, forward_kinematics
from ptrack.body.skeleton import Skeleton

# -- the reference: per joint, recursive from the root, torch float64 scalars (so autograd works) --


def _rodrigues(axis: torch.Tensor, angle: torch.Tensor) -> torch.Tensor:
    """Rotation by `angle` about unit `axis` (3,): (3, 3)."""
    x, y, z = axis
    k = torch.stack([torch.stack([0 * x, -z, y]), torch.stack([z, 0 * x, -x]), torch.stack([-y, x, 0 * x])])
    return torch.eye(3, dtype=torch.float64) + torch.sin(angle) * k + (1 - torch.cos(angle)) * (k @ k)


def reference_fk(sk: Skeleton, q: torch.Tensor, lengths: torch.Tensor | None = None):
    """q (D,) float64 -> joints (J, 3), world rotations (J, 3, 3):
    G_i = G_parent R(a_i1, th_i1) R(a_i2, th_i2) R(a_i3, th_i3) E_i,
    p_i = p_parent + length_i (G_parent u_i + G_i w_i); the root's parent frame is the identity and
    its parent position the rest position plus the translation dofs."""
    f64 = dict(dtype=torch.float64)
    lens = torch.as_tensor(sk.lengths, **f64) if lengths is None else lengths
    children: dict[int, list[int]] = {i: [] for i in range(sk.num_joints)}
    for i, p in enumerate(sk.parents):
        if p >= 0:
            children[p].append(i)
    pos: dict[int, torch.Tensor] = {}
    rot: dict[int, torch.Tensor] = {}

    def visit(i: int, g_parent: torch.Tensor, p_parent: torch.Tensor) -> None:
        local = torch.eye(3, **f64)
        for k in range(3):
            d = int(sk.axis_dof[i, k])
            angle = q[d] if d >= 0 else torch.tensor(float(sk.frozen_axes[i, k]), **f64)
            local = local @ _rodrigues(torch.as_tensor(sk.axes[i, k], **f64), angle)
        g = g_parent @ local @ torch.as_tensor(sk.rest_rotation[i], **f64)
        u = torch.as_tensor(sk.offset_parent[i], **f64)
        w = torch.as_tensor(sk.offset_local[i], **f64)
        rot[i] = g
        pos[i] = p_parent + lens[i] * (g_parent @ u + g @ w)
        for c in children[i]:
            visit(c, g, pos[i])

    root = torch.as_tensor(sk.root_position, **f64)
    trans = [q[d] if d >= 0 else torch.zeros((), **f64) for d in sk.translation_dof.tolist()]
    visit(0, torch.eye(3, **f64), root + torch.stack(trans))
    return torch.stack([pos[i] for i in range(sk.num_joints)]), torch.stack([rot[i] for i in range(sk.num_joints)])


# -- random trees ------------------------------------------------------------------------------


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    m, r = np.linalg.qr(rng.normal(size=(3, 3)))
    m = m * np.sign(np.diag(r))
    return m if np.linalg.det(m) > 0 else -m


def random_parents(rng: np.random.Generator, j: int, style: str) -> list[int]:
    """Parents (J,) with parents[i] < i, of a given shape."""
    parents = [-1]
    for i in range(1, j):
        if style == "chain":  # mostly a long chain with the odd branch
            p = i - 1 if rng.random() < 0.8 else int(rng.integers(0, i))
        elif style == "star":  # wide and shallow
            p = int(rng.integers(0, min(i, 3)))
        elif style == "early":  # children of the first joints of each level
            p = int(rng.integers(0, i)) // 2 if i > 1 else 0
        else:  # uniform
            p = int(rng.integers(0, i))
        parents.append(p)
    return parents


def random_skeleton(seed: int, j: int, style: str, frames: bool, parents: list[int] | None = None) -> Skeleton:
    """A random model. `frames`: every joint's axes are the (z, y, x) columns of a rotation (the
    closed-form FK path); otherwise arbitrary unit axes (the Rodrigues path)."""
    rng = np.random.default_rng(seed)
    parents = random_parents(rng, j, style) if parents is None else parents
    j = len(parents)
    axes = np.zeros((j, 3, 3))
    for i in range(j):
        if frames:
            c = _random_rotation(rng)
            axes[i] = np.stack([c[:, 2], c[:, 1], c[:, 0]])
        else:
            a = rng.normal(size=(3, 3))
            axes[i] = a / np.linalg.norm(a, axis=-1, keepdims=True)
    driven = rng.random((j, 3)) < 0.7
    translation_dof = np.where(rng.random(3) < 0.7, 0, -1)
    n_trans = int((translation_dof == 0).sum())
    translation_dof[translation_dof == 0] = np.arange(n_trans)
    axis_dof = -np.ones((j, 3), dtype=np.int64)
    axis_dof[driven] = n_trans + np.arange(int(driven.sum()))
    d = n_trans + int(driven.sum())
    rest = np.stack([_random_rotation(rng) if rng.random() < 0.4 else np.eye(3) for _ in range(j)])
    offset_parent = rng.normal(size=(j, 3)) * (rng.random((j, 1)) < 0.5)
    offset_parent[0] = 0.0  # the root is placed by root_position (FK and URDF export ignore its u)
    offset_local = rng.normal(size=(j, 3)) * (rng.random((j, 1)) < 0.8)
    return Skeleton(
        name=f"tree{seed}",
        joint_names=tuple(f"j{i}" for i in range(j)),
        parents=tuple(parents),
        axes=axes,
        axis_dof=axis_dof,
        rest_rotation=rest,
        offset_parent=offset_parent,
        offset_local=offset_local,
        lengths=rng.uniform(0.2, 1.5, size=j),
        root_position=rng.normal(size=3),
        translation_dof=translation_dof,
        dof_names=tuple(f"q{k}" for k in range(d)),
        lower=np.full(d, -math.inf),
        upper=np.full(d, math.inf),
        frozen_axes=np.where(driven, 0.0, rng.uniform(-1, 1, size=(j, 3))),
    )


# hand-picked shapes that broke the level plan: a level whose parents are the first n joints of a
# longer previous level, for n = 1 and n > 1, not in level order and in level order
SHAPES = {
    "review_asf": [-1, 0, 1, 2, 0],  # root a c d b
    "first_two_of_three": [-1, 0, 0, 0, 1, 2],
    "first_two_dfs": [-1, 0, 1, 0, 3, 0],  # root a c b f e
    "first_of_each_level": [-1, 0, 0, 1, 1, 3, 3, 5],
    "chain": [-1, 0, 1, 2, 3],
    "star": [-1, 0, 0, 0, 0],
}
RANDOM_TREES = [
    (seed, j, style)
    for seed, (j, style) in enumerate(
        [(n, s) for s in ("uniform", "chain", "star", "early") for n in (2, 3, 6, 12, 25)]
    )
]


def _trees(frames: bool):
    for name, parents in SHAPES.items():
        yield name, random_skeleton(100 + len(name), len(parents), "", frames, parents=parents)
    for seed, j, style in RANDOM_TREES:
        yield f"{style}{j}-{seed}", random_skeleton(seed, j, style, frames)


def _reference_batch(sk: Skeleton, q: torch.Tensor):
    outs = [reference_fk(sk, x) for x in q.reshape(-1, sk.num_dofs)]
    joints = torch.stack([o[0] for o in outs]).reshape(*q.shape[:-1], sk.num_joints, 3)
    rots = torch.stack([o[1] for o in outs]).reshape(*q.shape[:-1], sk.num_joints, 3, 3)
    return joints, rots


@pytest.mark.parametrize("frames", [True, False], ids=["frames", "free_axes"])
def test_fk_of_random_trees_matches_recursive_reference(frames):
    for name, sk in _trees(frames):
        assert _plan(sk, torch.float64, torch.device("cpu")).closed_form == frames, name
        g = torch.Generator().manual_seed(len(name))
        q = torch.randn(2, 3, sk.num_dofs, generator=g, dtype=torch.float64)
        ref_j, ref_r = _reference_batch(sk, q)
        for generic in (False, True):
            joints, rots = forward_kinematics(sk, q, rotations=True, generic=generic)
            torch.testing.assert_close(joints, ref_j, rtol=0, atol=1e-12, msg=lambda m: f"{name} {generic}: {m}")
            torch.testing.assert_close(rots, ref_r, rtol=0, atol=1e-12, msg=lambda m: f"{name} {generic}: {m}")
            torch.testing.assert_close(
                forward_kinematics(sk, q, generic=generic),
                ref_j,
                rtol=0,
                atol=1e-12,
                msg=lambda m: f"{name} {generic} positions only: {m}",
            )


@pytest.mark.parametrize("frames", [True, False], ids=["frames", "free_axes"])
def test_fk_gradients_of_random_trees_match_autograd_through_reference(frames):
    """Gradient w.r.t. q of a random linear function of the joints, on every path: the analytical
    backward (closed form, positions only), autograd through the closed form (with rotations) and
    through the Rodrigues path; and the gradient w.r.t. lengths."""
    for name, sk in _trees(frames):
        g = torch.Generator().manual_seed(7 + len(name))
        q = torch.randn(3, sk.num_dofs, generator=g, dtype=torch.float64)
        upstream = torch.randn(3, sk.num_joints, 3, generator=g, dtype=torch.float64)
        x = q.clone().requires_grad_(True)
        (_reference_batch(sk, x)[0] * upstream).sum().backward()
        expected = x.grad
        for generic in (False, True):
            for rotations in (False, True):
                x = q.clone().requires_grad_(True)
                out = forward_kinematics(sk, x, rotations=rotations, generic=generic)
                joints = out[0] if rotations else out
                (joints * upstream).sum().backward()
                torch.testing.assert_close(
                    x.grad,
                    expected,
                    rtol=0,
                    atol=1e-10,
                    msg=lambda m: f"{name} generic={generic} rotations={rotations}: {m}",
                )
        lengths = torch.as_tensor(sk.lengths).clone().requires_grad_(True)
        (forward_kinematics(sk, q[0], lengths=lengths) * upstream[0]).sum().backward()
        ln_ref = torch.as_tensor(sk.lengths).clone().requires_grad_(True)
        (reference_fk(sk, q[0], lengths=ln_ref)[0] * upstream[0]).sum().backward()
        torch.testing.assert_close(lengths.grad, ln_ref.grad, rtol=0, atol=1e-10, msg=lambda m: f"{name}: {m}")


@pytest.mark.parametrize("frames", [True, False], ids=["frames", "free_axes"])
@pytest.mark.parametrize("shape", ["review_asf", "first_two_of_three", "first_of_each_level"])
def test_gradcheck_and_gradgradcheck_on_small_trees(shape, frames):
    parents = SHAPES[shape]
    sk = random_skeleton(3, len(parents), "", frames, parents=parents)
    q = torch.randn(2, sk.num_dofs, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    q.requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: forward_kinematics(sk, x), (q,))
    assert torch.autograd.gradgradcheck(lambda x: forward_kinematics(sk, x), (q,))


# -- the review's ASF --------------------------------------------------------------------------


def _asf_text(hierarchy: list[str], bones: dict[str, tuple[str, float]]) -> str:
    blocks = []
    for k, (name, (direction, length)) in enumerate(bones.items(), start=1):
        blocks.append(f"""\
  begin
     id {k}
     name {name}
     direction {direction}
     length {length}
     axis 0 0 0 XYZ
    dof rx ry rz
    limits (-180.0 180.0)
           (-180.0 180.0)
           (-180.0 180.0)
  end""")
    body = "\n".join(blocks)
    lines = "\n".join(f"    {h}" for h in hierarchy)
    return f"""\
:version 1.10
:name fork
:units
  mass 1.0
  length 1.0
  angle deg
:root
   order TX TY TZ RX RY RZ
   axis XYZ
   position 0 0 0
   orientation 0 0 0
:bonedata
{body}
:hierarchy
  begin
{lines}
  end
"""


ASF_CASES = {
    # the review's file: level 2 (c) hangs from the first joint of level 1 (a, b)
    "n1": (
        ["root a b", "a c", "c d"],
        {"a": ("0 1 0", 1.0), "b": ("1 0 0", 5.0), "c": ("0 1 0", 1.0), "d": ("0 1 0", 1.0)},
        {"a": (0, 1, 0), "b": (5, 0, 0), "c": (0, 2, 0), "d": (0, 3, 0)},
    ),
    # level 2 (c, f) hangs from the first two joints of level 1 (a, b, e)
    "n2": (
        ["root a b e", "a c", "b f", "c d"],
        {
            "a": ("0 1 0", 1.0),
            "b": ("1 0 0", 5.0),
            "e": ("0 0 1", 2.0),
            "c": ("0 1 0", 1.0),
            "f": ("0 0 1", 1.0),
            "d": ("0 1 0", 1.0),
        },
        {"a": (0, 1, 0), "b": (5, 0, 0), "e": (0, 0, 2), "c": (0, 2, 0), "f": (5, 0, 1), "d": (0, 3, 0)},
    ),
}


@pytest.mark.parametrize("case", ASF_CASES)
def test_asf_whose_level_hangs_from_the_first_joints_of_a_longer_level(tmp_path: Path, case):
    hierarchy, bones, rest = ASF_CASES[case]
    path = tmp_path / "fork.asf"
    path.write_text(_asf_text(hierarchy, bones))
    sk = Skeleton.from_asf(path)
    zero = torch.zeros(sk.num_dofs, dtype=torch.float64)
    for generic in (False, True):
        joints = forward_kinematics(sk, zero, generic=generic)
        for name, expected in rest.items():
            np.testing.assert_allclose(
                joints[sk.joint_index(name)].numpy(),
                np.asarray(expected) * INCH_M,
                rtol=0,
                atol=1e-12,
                err_msg=f"{name} generic={generic}",
            )
    q = torch.randn(4, sk.num_dofs, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    ref = _reference_batch(sk, q)
    for generic in (False, True):
        got = forward_kinematics(sk, q, rotations=True, generic=generic)
        for a, b in zip(got, ref):
            torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    x = q.clone().requires_grad_(True)
    forward_kinematics(sk, x).square().sum().backward()
    y = q.clone().requires_grad_(True)
    _reference_batch(sk, y)[0].square().sum().backward()
    torch.testing.assert_close(x.grad, y.grad, rtol=0, atol=1e-10)
