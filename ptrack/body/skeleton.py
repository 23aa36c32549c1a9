"""Articulated body models: a tree of joints driven by a pose vector `q: (D,)`.

A `Skeleton` is a tree of J joints (root first, parents before children). Joint i has a world
rotation G_i and a position p_i:

    G_i = G_parent @ Rot(a_i1, th_i1) @ Rot(a_i2, th_i2) @ Rot(a_i3, th_i3) @ E_i
    p_i = p_parent + length_i * (G_parent @ u_i + G_i @ w_i) + G_i @ s_i * q[slide_dof_i]

with up to three rotation axes a_ik (fixed, unit) per joint, each driven by one entry of q
(or none), a constant rotation E_i, and the offset split into a part fixed in the parent's frame
(u_i, URDF-style joint origins) and a part that turns with the joint (w_i, the Acclaim bone vector).
A slot's angle is th_ik = scale_ik * q[dof_ik] + frozen_ik (scale 1 and frozen 0 but for URDF mimic
joints and frozen slots). A URDF prismatic joint slides its frame along s_i by one entry of q.
The root adds a translation from q to its rest position. This one form covers Acclaim ASF
skeletons (a joint per bone, placed at the bone's end: "every bone's end point plus the root")
and URDF trees (`ptrack.body.urdf`), so every estimator works on both.

Units: metres and radians. The CMU world frame is Y up.
"""

from __future__ import annotations

import fnmatch
import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ptrack.body.acclaim import AsfFile, parse_amc, parse_asf
from ptrack.body.rotations import euler_matrix_np
from ptrack.errors import InputError

#: capture rate of CMU AMC files
CMU_FPS = 120.0

_EYE = np.eye(3)


@dataclass(frozen=True, eq=False)
class Skeleton:
    """A kinematic tree. All arrays are float64 numpy; `forward_kinematics` casts them as needed.

    Attributes (J joints, D dofs):
        name: model name.
        joint_names: (J,) root first; for ASF skeletons the bone names with "root" first.
        parents: (J,) parent index, -1 for the root; parents[i] < i.
        axes: (J, 3, 3) up to three unit rotation axes per joint (rows), applied left to right.
        axis_dof: (J, 3) int, index into q driving each axis, -1 for none.
        rest_rotation: (J, 3, 3) the constant E_i.
        offset_parent: (J, 3) unit-free direction u_i (parent frame) — see module docstring.
        offset_local: (J, 3) direction w_i (joint frame).
        lengths: (J,) metres; scales both offsets.
        root_position: (3,) rest position of the root, metres.
        translation_dof: (3,) int, q indices of the root translation (x, y, z), -1 for none.
        dof_names: (D,) e.g. "root.tx", "lfemur.rx".
        lower, upper: (D,) joint limits (metres for translations, radians for angles; +-inf = none).
        frozen_axes: (J, 3) constant angle added to each slot: the whole angle of slots whose dof was
            removed by `freeze`, a URDF mimic joint's offset, else 0.
        amc_layout: for ASF models, how AMC values map to dofs (None for URDF models).
        axis_scale: (J, 3) angle per unit of the driving dof (a URDF mimic joint's multiplier, else 1).
        slide_axis: (J, 3) displacement per unit of `slide_dof` in the joint's frame (URDF prismatic
            joints: the axis, times the multiplier for mimic joints); zeros for none.
        slide_dof: (J,) int, q index driving the joint's slide, -1 for none.
    """

    name: str
    joint_names: tuple[str, ...]
    parents: tuple[int, ...]
    axes: np.ndarray
    axis_dof: np.ndarray
    rest_rotation: np.ndarray
    offset_parent: np.ndarray
    offset_local: np.ndarray
    lengths: np.ndarray
    root_position: np.ndarray
    translation_dof: np.ndarray
    dof_names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    frozen_axes: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (J, 3) angle of frozen axes
    frozen: tuple[tuple[str, float], ...] = ()  # (dof name, value) removed by `freeze`
    amc_layout: AmcLayout | None = None
    axis_scale: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (J, 3), ones by default
    slide_axis: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # (J, 3), zeros by default
    slide_dof: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))  # (J,), -1 by default
    _cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        j = len(self.joint_names)
        if len(self.parents) != j or self.parents[0] != -1:
            raise InputError(f"skeleton {self.name!r}: parents must have {j} entries with -1 first")
        if any(not (0 <= p < i) for i, p in enumerate(self.parents) if i > 0):
            raise InputError(f"skeleton {self.name!r}: every parent must come before its child")
        if len(set(self.joint_names)) != j:
            raise InputError(f"skeleton {self.name!r}: joint names are not unique")
        if self.frozen_axes.shape != (j, 3):
            object.__setattr__(self, "frozen_axes", np.zeros((j, 3)))
        if self.axis_scale.shape != (j, 3):
            object.__setattr__(self, "axis_scale", np.ones((j, 3)))
        if self.slide_axis.shape != (j, 3):
            object.__setattr__(self, "slide_axis", np.zeros((j, 3)))
        if self.slide_dof.shape != (j,):
            object.__setattr__(self, "slide_dof", -np.ones(j, dtype=np.int64))

    # ---------------------------------------------------------------- sizes and names
    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def num_dofs(self) -> int:
        return len(self.dof_names)

    def joint_index(self, name: str) -> int:
        try:
            return self.joint_names.index(name)
        except ValueError:
            raise InputError(f"skeleton {self.name!r} has no joint {name!r}") from None

    def bones(self) -> list[tuple[int, int]]:
        """(parent, child) joint index pairs, one per non-root joint."""
        return [(p, i) for i, p in enumerate(self.parents) if p >= 0]

    def limits(self, dtype=torch.float32, device=None) -> tuple[Tensor, Tensor]:
        """Joint limits as tensors: lower (D,), upper (D,)."""
        return (
            torch.as_tensor(self.lower, dtype=dtype, device=device),
            torch.as_tensor(self.upper, dtype=dtype, device=device),
        )

    def with_limits(self, source: str, path: str | Path | None = None) -> Skeleton:
        """This model with the joint limits of `source`: "data" (measured on real CMU motion, the
        default of runs), "asf" (the model file's own) or "none". See `ptrack.body.limits`."""
        from ptrack.body.limits import with_limits

        return with_limits(self, source, path)

    def root_twin_dofs(self) -> tuple[int, int, int] | None:
        """The root's three rotation dofs (a, b, c) in the order their axes apply, when the root turns about three
        orthogonal axes, each by its own dof (scale 1, nothing frozen, no limits): then every orientation has two
        sets of angles, (a, b, c) and (a + pi, pi - b, c + pi) (`root_twin`). None otherwise."""
        dofs = self.axis_dof[0]
        if (dofs < 0).any() or len(set(dofs.tolist())) != 3 or not np.allclose(self.axis_scale[0], 1.0):
            return None
        if np.isfinite(self.lower[dofs]).any() or np.isfinite(self.upper[dofs]).any():
            return None  # the other set could lie outside the limits
        if not np.allclose(self.frozen_axes[0], 0.0):
            return None
        axes = self.axes[0]
        if not np.allclose(axes @ axes.T, np.eye(3), atol=1e-9):
            return None
        a, b, c = (int(d) for d in dofs)
        return a, b, c

    def root_twin(self, q: Tensor) -> Tensor:
        """q (..., D) -> the same poses with the root's other set of angles (`root_twin_dofs`): the same joints, the
        root's angles (a + pi, pi - b, c + pi). q itself where the root has no twin."""
        dofs = self.root_twin_dofs()
        if dofs is None:
            return q
        a, b, c = dofs
        twin = q.clone()
        twin[..., a] = q[..., a] + math.pi
        twin[..., b] = math.pi - q[..., b]
        twin[..., c] = q[..., c] + math.pi
        return twin

    def angular_dofs(self) -> np.ndarray:
        """(D,) bool: True for dofs that drive a rotation (periodic angles), False for translations."""
        mask = np.zeros(self.num_dofs, dtype=bool)
        mask[self.axis_dof[self.axis_dof >= 0]] = True
        return mask

    @property
    def has_slides_or_mimics(self) -> bool:
        """True if a URDF prismatic joint below the root or a mimic joint (a dof driving several
        slots, or a slot with a multiplier or offset) is in the model: FK handles them, code that
        works on `axes`/`axis_dof` alone does not."""
        driven = self.axis_dof[self.axis_dof >= 0]
        return bool(
            np.any(self.slide_dof >= 0)
            or len(set(driven.tolist())) < len(driven)
            or np.any((self.axis_scale != 1.0) & (self.axis_dof >= 0))
            or np.any((self.frozen_axes != 0.0) & (self.axis_dof >= 0))
        )

    def length_tensor(self, dtype=torch.float32, device=None) -> Tensor:
        """Bone lengths (J,) in metres, e.g. as a starting point for differentiable lengths."""
        return torch.as_tensor(self.lengths, dtype=dtype, device=device)

    # ---------------------------------------------------------------- constructors
    @staticmethod
    def from_asf(path: str | Path) -> Skeleton:
        """Read an Acclaim ASF skeleton (lengths converted to metres, limits to radians)."""
        return _from_asf(parse_asf(path))

    @staticmethod
    def from_urdf(path: str | Path, floating_base: bool | None = None, collapse: bool | None = None) -> Skeleton:
        """Any URDF articulated model (ptrack's own reader of the kinematic elements: `ptrack.body.urdf`),
        from a file path or from URDF text (a string starting with '<', e.g. `to_urdf()`'s).

        One joint per link, at the link's frame, in depth-first order from the root link. Revolute
        and continuous joints become rotation dofs, prismatic joints sliding dofs (anywhere in the
        tree), both named after the URDF joint (in the file's joint order) and with its limits
        (continuous joints, and pybullet's lower > upper, are unlimited); fixed joints carry no
        dof; a mimic joint follows its leader's dof (multiplier * q + offset). With
        `floating_base`, the base link gets a free translation and rotation (dofs "root.tx" ...
        "root.rz"), as a tracked human's pelvis has.
        None (default): a floating base unless the file moves its base itself (written by
        `to_urdf`, or three prismatic joints translating the root link).

        `collapse` merges links into the joint below them (bare links, no visual, collision or
        inertial, with one child joint, not the root link, where the merged chain fits one ptrack
        joint: an offset, up to three rotations, then a slide and an offset). None (default): only the links that
        `to_urdf` adds (its base link "world" and the "<joint>__link..." links between a joint's
        axes), in files `to_urdf` wrote, so that `Skeleton.from_urdf(sk.to_urdf())` gives `sk`
        back: the same joints, parents, offsets, rest rotations, dofs, axes in order and limits,
        and the same forward kinematics to rounding (undriven axis slots, which FK ignores, may
        differ; `freeze`'s record and ASF's `amc_layout` are not in the file). Other files come
        back one joint per link. True: every such link of any file. False: one joint per link
        always (for `to_urdf`'s files, a joint per axis, as other URDF readers see them).
        """
        from ptrack.body.urdf import skeleton_from_urdf

        return skeleton_from_urdf(path, floating_base=floating_base, collapse=collapse)

    def to_urdf(self) -> str:
        """A URDF string of this model (root translation as prismatic joints, see `ptrack.body.urdf`)."""
        from ptrack.body.urdf import skeleton_to_urdf

        return skeleton_to_urdf(self)

    # ---------------------------------------------------------------- reduced models
    def freeze(self, patterns: list[str] | tuple[str, ...], value: float = 0.0) -> Skeleton:
        """A reduced model: dofs matching any pattern are removed from q and held at `value`.

        A pattern matches a joint name (all its dofs: "lfingers", "*clavicle") or a dof name
        ("lfemur.rz", "root.t*"), shell-style. A pattern that matches nothing is an error.
        """
        drop: set[int] = set()
        for pat in patterns:
            hits = [
                i
                for i, n in enumerate(self.dof_names)
                if fnmatch.fnmatchcase(n, pat) or fnmatch.fnmatchcase(n.split(".")[0], pat)
            ]
            if not hits and not any(fnmatch.fnmatchcase(n, pat) for n in self.joint_names):
                raise InputError(f"freeze pattern {pat!r} matches no joint or dof of {self.name!r}")
            drop.update(hits)
        keep = [i for i in range(self.num_dofs) if i not in drop]
        remap = -np.ones(self.num_dofs + 1, dtype=np.int64)  # last entry maps -1 -> -1
        remap[keep] = np.arange(len(keep))
        axis_dof = remap[self.axis_dof]
        frozen_axes = self.frozen_axes.copy()
        gone = (self.axis_dof >= 0) & (axis_dof < 0)
        frozen_axes[gone] += self.axis_scale[gone] * value
        trans = remap[self.translation_dof]
        root_position = self.root_position.copy()
        root_position[(self.translation_dof >= 0) & (trans < 0)] += value
        slide_dof = remap[self.slide_dof]
        offset = self.lengths[:, None] * self.offset_parent
        held = (self.slide_dof >= 0) & (slide_dof < 0)  # a frozen slide becomes part of the joint's origin
        offset[held] += value * np.einsum("jab,jb->ja", self.rest_rotation[held], self.slide_axis[held])
        lengths = np.linalg.norm(offset, axis=1) if held.any() else self.lengths
        offset_parent = (
            np.divide(offset, lengths[:, None], out=np.zeros_like(offset), where=lengths[:, None] > 0)
            if held.any()
            else self.offset_parent
        )
        return replace(
            self,
            frozen=self.frozen + tuple((self.dof_names[i], float(value)) for i in sorted(drop)),
            axis_dof=axis_dof,
            translation_dof=trans,
            root_position=root_position,
            frozen_axes=frozen_axes,
            slide_dof=slide_dof,
            lengths=lengths,
            offset_parent=offset_parent,
            dof_names=tuple(self.dof_names[i] for i in keep),
            lower=self.lower[keep],
            upper=self.upper[keep],
        )

    def expand(self, q_reduced: Tensor, full: Skeleton) -> Tensor:
        """Map a pose of this (reduced) model into `full`'s dof layout: (..., D) -> (..., D_full).

        Frozen dofs get their frozen value (0 unless `freeze(value=...)` said otherwise).
        """
        idx = [full.dof_names.index(n) for n in self.dof_names]
        out = q_reduced.new_zeros(*q_reduced.shape[:-1], full.num_dofs)
        for name, value in self.frozen:
            if name in full.dof_names:
                out[..., full.dof_names.index(name)] = value
        out[..., idx] = q_reduced
        return out

    def reduce(self, q_full: Tensor, full: Skeleton) -> Tensor:
        """Select this model's dofs from a pose of `full`: (..., D_full) -> (..., D)."""
        idx = [full.dof_names.index(n) for n in self.dof_names]
        return q_full[..., idx]

    # ---------------------------------------------------------------- kinematics
    def forward_kinematics(self, q: Tensor, lengths: Tensor | None = None, rotations: bool = False):
        """Joint positions (..., J, 3) (and world rotations (..., J, 3, 3) if `rotations`).

        q: (..., D); lengths: optional (..., J) bone lengths in metres overriding the model's
        (differentiable). See `ptrack.body.kinematics.forward_kinematics`.
        """
        from ptrack.body.kinematics import forward_kinematics

        return forward_kinematics(self, q, lengths=lengths, rotations=rotations)

    def load_amc(self, path: str | Path) -> Motion:
        return load_amc(path, self)


@dataclass(frozen=True)
class Motion:
    """A motion capture clip: poses of one skeleton.

    q: (T, D) float64, root translation in metres, angles in radians; frames: (T,) AMC frame numbers
    (consecutive, or every stride-th after `slice`) counting at `frame_rate` per second.
    """

    q: Tensor
    frames: np.ndarray
    fps: float  # poses per second of this clip (120 / stride for CMU)
    path: str
    frame_rate: float = CMU_FPS  # rate at which the frame numbers count

    @property
    def times(self) -> np.ndarray:
        """(T,) seconds from the first frame."""
        return (self.frames - self.frames[0]) / self.frame_rate

    def slice(self, start: int = 0, stop: int | None = None, stride: int = 1) -> Motion:
        """Frames [start, stop) of the clip (indices, not AMC frame numbers) every `stride`."""
        t = self.q.shape[0]
        if stride < 1:
            raise InputError(f"stride must be >= 1, got {stride}")
        if not (0 <= start < t):
            raise InputError(f"start frame {start} outside the clip's {t} frames ({self.path})")
        if stop is not None and not (start < stop <= t):
            raise InputError(f"stop frame {stop} must be in ({start}, {t}] for {self.path}")
        sl = slice(start, stop, stride)
        return Motion(
            q=self.q[sl], frames=self.frames[sl], fps=self.fps / stride, path=self.path, frame_rate=self.frame_rate
        )


def load_amc(path: str | Path, skeleton: Skeleton) -> Motion:
    """Read an AMC motion for an ASF skeleton: q (T, D) at 120 fps.

    The skeleton must be one made by `Skeleton.from_asf` (possibly reduced by `freeze`: frozen dofs
    are dropped from q). Raises InputError if the AMC does not match the skeleton.
    """
    layout = skeleton.amc_layout
    if layout is None:
        raise InputError(f"load_amc needs an ASF skeleton; {skeleton.name!r} was not read from ASF")
    amc = parse_amc(path, dict(layout.dof_counts))
    q_full = np.concatenate([amc.values[bone] for bone, _ in layout.dof_counts], axis=1)
    q_full = q_full * np.asarray(layout.scale)
    keep = [layout.dof_names.index(n) for n in skeleton.dof_names]
    return Motion(q=torch.from_numpy(q_full[:, keep].copy()), frames=amc.frame_numbers, fps=CMU_FPS, path=str(path))


@dataclass(frozen=True)
class AmcLayout:
    """How an AMC file's values map to an ASF skeleton's full dof vector.

    dof_counts: ((bone, n values), ...) in dof order; dof_names: the full model's dof names;
    scale: (D_full,) file unit -> metres / radians per dof.
    """

    dof_counts: tuple[tuple[str, int], ...]
    dof_names: tuple[str, ...]
    scale: tuple[float, ...]


def _place_rotations(axes: np.ndarray, axis_dof: np.ndarray, c: np.ndarray, rots: list[tuple[str, int]]) -> None:
    """Fill one joint's three axis slots from Acclaim rotations `rots` [(axis letter, dof), ...] in
    file order (applied first to last, so M = R(last) ... R(first)) in the frame `c` (3, 3).

    When the letters come in X, Y, Z order (every CMU file), slots are (z, y, x) whatever subset is
    driven, so the joint's axes are the frame c's columns (z, y, x): forward kinematics then uses
    closed-form Euler matrices. Other orders keep the product order slot by slot.
    """
    letters = "".join(a for a, _ in rots)
    if letters == "".join(a for a in "XYZ" if a in letters):
        for a in "ZYX":
            axes["ZYX".index(a)] = c[:, "XYZ".index(a)]
        for a, d in rots:
            axis_dof["ZYX".index(a)] = d
    else:
        axes[:] = np.eye(3)[0]
        for k, (a, d) in enumerate(reversed(rots)):
            axes[k] = c[:, "XYZ".index(a)]
            axis_dof[k] = d


def _from_asf(asf: AsfFile) -> Skeleton:
    m = asf.metres_per_unit
    ang = math.pi / 180.0 if asf.angle_unit == "deg" else 1.0
    by_name = {b.name: b for b in asf.bones}
    children: dict[str, list[str]] = {}
    for parent, child in asf.hierarchy:
        children.setdefault(parent, []).append(child)
    # depth-first from the root, children in file order: parents precede children
    order: list[str] = ["root"]
    stack = list(reversed(children.get("root", [])))
    while stack:
        n = stack.pop()
        order.append(n)
        stack.extend(reversed(children.get(n, [])))
    unreachable = set(by_name) - set(order)
    if unreachable:
        raise InputError(f"{asf.path}: bones not connected to the root: {sorted(unreachable)}")
    parent_of = {c: p for p, c in asf.hierarchy}
    index = {n: i for i, n in enumerate(order)}
    j = len(order)

    axes = np.zeros((j, 3, 3))
    axis_dof = -np.ones((j, 3), dtype=np.int64)
    offset_local = np.zeros((j, 3))
    lengths = np.zeros(j)
    dof_names: list[str] = []
    lower: list[float] = []
    upper: list[float] = []
    dof_counts: dict[str, int] = {}
    scale: list[float] = []

    # root: translations then rotations, C M C^-1 with C from the root orientation
    trans = -np.ones(3, dtype=np.int64)
    c_root = euler_matrix_np(tuple(a * ang for a in asf.root_orientation), asf.root_axis)
    rot_order = []
    root_scale = []
    for token in asf.root_order:
        kind, ax = token[0], token[1]
        name = f"root.{token.lower()}"
        if kind == "T":
            trans["XYZ".index(ax)] = len(dof_names)
            root_scale.append(m)
            lower.append(-math.inf)
            upper.append(math.inf)
        else:
            rot_order.append((ax, len(dof_names)))
            root_scale.append(ang)
            lower.append(-math.inf)
            upper.append(math.inf)
        dof_names.append(name)
    dof_counts["root"] = len(asf.root_order)
    scale.extend(root_scale)
    if len(rot_order) > 3:
        raise InputError(f"{asf.path}: root order has more than three rotations")
    _place_rotations(axes[0], axis_dof[0], c_root, rot_order)

    for name in order[1:]:
        b = by_name[name]
        i = index[name]
        c = euler_matrix_np(tuple(a * ang for a in b.axis), b.axis_order)
        offset_local[i] = b.direction
        lengths[i] = b.length * m
        rots = []
        for dof, (lo, hi) in zip(b.dof, b.limits):
            if dof[0] != "r":
                raise InputError(
                    f"{asf.path}: bone {name!r} has dof {dof!r}; only rotational bone dofs (rx ry rz) are supported"
                )
            dname = f"{name}.{dof}"
            rots.append((dof[1].upper(), len(dof_names)))
            dof_names.append(dname)
            lower.append(lo * ang)
            upper.append(hi * ang)
        if b.dof:
            dof_counts[name] = len(b.dof)
            scale.extend([ang] * len(b.dof))
        _place_rotations(axes[i], axis_dof[i], c, rots)

    sk = Skeleton(
        name=asf.name,
        joint_names=tuple(order),
        parents=tuple(-1 if n == "root" else index[parent_of[n]] for n in order),
        axes=axes,
        axis_dof=axis_dof,
        rest_rotation=np.broadcast_to(_EYE, (j, 3, 3)).copy(),
        offset_parent=np.zeros((j, 3)),
        offset_local=offset_local,
        lengths=lengths,
        root_position=np.asarray(asf.root_position, dtype=np.float64) * m,
        translation_dof=trans,
        dof_names=tuple(dof_names),
        lower=np.asarray(lower),
        upper=np.asarray(upper),
        amc_layout=AmcLayout(tuple(dof_counts.items()), tuple(dof_names), tuple(scale)),
    )
    return sk
