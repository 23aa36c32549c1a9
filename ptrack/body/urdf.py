"""URDF <-> `Skeleton`: ptrack's own reader of a URDF file's kinematics, and a writer.

`parse_urdf` reads only what moves a model: links, joints (type, parent, child, origin, axis,
limits, mimic). Visual, collision, inertial, material, transmission, gazebo and any other elements
are skipped unread, so files other URDF readers accept (urdfdom, yourdfpy, pybullet) load here too:
an XML declaration after a comment, any `version`, several geometry children, unknown tags.

`skeleton_from_urdf` makes any URDF tree trackable: each link becomes a ptrack joint at the link's
frame; revolute and continuous joints become a rotation dof, prismatic joints a sliding dof (at any
depth), fixed joints no dof, and mimic joints follow their leader (multiplier * q + offset) without
a dof of their own. Floating and planar joints are refused. `skeleton_to_urdf` writes a ptrack
model as URDF (root translation as three prismatic joints, each rotation axis as a revolute or
continuous joint, with a link between each two, mimic joints as `<mimic>`). Reading such a file
merges the links it added back into their joints (`collapse`, see `Skeleton.from_urdf`), so that
the model comes back as it was; other readers see one link per axis, with the same kinematics.
"""

from __future__ import annotations

import logging
import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
import torch

from ptrack.body.rotations import axis_angle_matrix, euler_matrix_np, matrix_to_axis_angle_np, matrix_to_euler_np
from ptrack.body.skeleton import Skeleton
from ptrack.errors import InputError

_log = logging.getLogger(__name__)

#: joint types ptrack reads; floating and planar joints (and pybullet's spherical) are refused
JOINT_TYPES = ("revolute", "continuous", "prismatic", "fixed")
#: what `skeleton_to_urdf` writes as the limits of an unlimited prismatic joint (URDF has no such thing)
UNLIMITED_PRISMATIC = 1e6
#: attribute of <robot> by which `skeleton_to_urdf` records that the file moves its own base
_BASE_MARK = "ptrack_floating_base"


@dataclass(frozen=True)
class UrdfJoint:
    """One URDF joint's kinematics. Limits are +-inf where the joint has none (continuous joints,
    lower > upper as pybullet writes for 'unlimited', no <limit> element)."""

    name: str
    type: str
    parent: str
    child: str
    xyz: tuple[float, float, float]
    rpy: tuple[float, float, float]
    axis: tuple[float, float, float]  # unit
    lower: float
    upper: float
    mimic: tuple[str, float, float] | None  # (leader joint, multiplier, offset)


@dataclass(frozen=True)
class UrdfModel:
    """The kinematic tree of a URDF file: `links` in file order, `root` the one link no joint moves."""

    name: str
    links: tuple[str, ...]
    joints: tuple[UrdfJoint, ...]
    root: str
    floating_base: bool | None  # as recorded by `skeleton_to_urdf`, None for other files
    bare: frozenset[str] = frozenset()  # links without <visual>, <collision> or <inertial>


def _vector(text: str | None, default, what: str, where: str) -> tuple[float, float, float]:
    if text is None:
        return default
    parts = text.split()
    try:
        v = tuple(float(x) for x in parts)
    except ValueError:
        v = ()
    if len(v) != 3 or not all(math.isfinite(x) for x in v):
        raise InputError(f"{where}: {what}={text!r} is not three numbers")
    return v


def _number(el: ET.Element, key: str, default: float, where: str, infinite: bool = False) -> float:
    """Attribute `key` of `el` as a float (`default` if absent); +-inf only if `infinite`, never NaN."""
    text = el.get(key)
    if text is None:
        return default
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if math.isnan(v) or (math.isinf(v) and not infinite):
        raise InputError(f"{where}: {key}={text!r} is not a {'' if infinite else 'finite '}number")
    return v


_XML_DECLARATION = re.compile(r"<\?xml\s[^>]*\?>")


def parse_urdf(text: str, source: str = "<string>") -> UrdfModel:
    """The kinematic tree of URDF `text` (see the module docstring); `source` names it in errors."""
    text = _XML_DECLARATION.sub("", text.lstrip("\ufeff"))  # tolerated anywhere, as urdfdom does
    try:
        robot = ET.fromstring(text)
    except ET.ParseError as e:
        raise InputError(f"{source}: not a readable URDF (XML: {e})") from None
    if robot.tag != "robot":
        raise InputError(f"{source}: not a URDF: the top element is <{robot.tag}>, not <robot>")
    links: list[str] = []
    bare: set[str] = set()
    for el in robot.findall("link"):
        name = el.get("name")
        if not name:
            raise InputError(f"{source}: a <link> has no name")
        if name in links:
            raise InputError(f"{source}: link {name!r} is not unique")
        links.append(name)
        if all(el.find(tag) is None for tag in ("visual", "collision", "inertial")):
            bare.add(name)
    if not links:
        raise InputError(f"{source}: no <link> in <robot>")
    joints: list[UrdfJoint] = []
    child_of: dict[str, str] = {}
    for el in robot.findall("joint"):
        name = el.get("name")
        if not name:
            raise InputError(f"{source}: a <joint> has no name")
        where = f"{source}: joint {name!r}"
        if any(j.name == name for j in joints):
            raise InputError(f"{where} is not unique")
        kind = el.get("type")
        if kind not in JOINT_TYPES:
            extra = (
                " (a free base: from_urdf(..., floating_base=True) on the file without it)"
                if kind == "floating"
                else ""
            )
            raise InputError(f"{where} is of type {kind!r}; ptrack supports {', '.join(JOINT_TYPES)} joints{extra}")
        ends: list[str] = []
        for tag in ("parent", "child"):
            end = el.find(tag)
            link = end.get("link") if end is not None else None
            if not link:
                raise InputError(f"{where} has no <{tag} link=...>")
            if link not in links:
                raise InputError(f"{where}: its {tag} link {link!r} is not a <link> of the file")
            ends.append(link)
        parent, child = ends
        if child in child_of:
            raise InputError(f"{source}: link {child!r} is the child of two joints ({child_of[child]!r}, {name!r})")
        child_of[child] = name
        origin = el.find("origin")
        xyz = _vector(origin.get("xyz") if origin is not None else None, (0.0, 0.0, 0.0), "origin xyz", where)
        rpy = _vector(origin.get("rpy") if origin is not None else None, (0.0, 0.0, 0.0), "origin rpy", where)
        axis_el = el.find("axis")
        axis = _vector(axis_el.get("xyz") if axis_el is not None else None, (1.0, 0.0, 0.0), "axis xyz", where)
        lower, upper = -math.inf, math.inf
        if kind in ("revolute", "prismatic"):
            n = math.sqrt(sum(a * a for a in axis))
            if n == 0.0:
                raise InputError(f"{where}: its axis is zero")
            axis = (axis[0] / n, axis[1] / n, axis[2] / n)
            lim = el.find("limit")
            if lim is not None:
                lower, upper = _number(lim, "lower", 0.0, where, True), _number(lim, "upper", 0.0, where, True)
                if lower > upper:  # pybullet's way of writing an unlimited joint
                    lower, upper = -math.inf, math.inf
        elif kind == "continuous":
            n = math.sqrt(sum(a * a for a in axis))
            if n == 0.0:
                raise InputError(f"{where}: its axis is zero")
            axis = (axis[0] / n, axis[1] / n, axis[2] / n)
        mimic = None
        m = el.find("mimic")
        if m is not None and kind != "fixed":
            leader = m.get("joint")
            if not leader:
                raise InputError(f"{where}: <mimic> names no joint")
            mimic = (leader, _number(m, "multiplier", 1.0, where), _number(m, "offset", 0.0, where))
        joints.append(UrdfJoint(name, kind, parent, child, xyz, rpy, axis, lower, upper, mimic))
    roots = [ln for ln in links if ln not in child_of]
    if len(roots) != 1:
        raise InputError(
            f"{source}: the links must form one tree, found {len(roots)} root links (links no joint moves): {roots[:5]}"
        )
    mark = robot.get(_BASE_MARK)
    return UrdfModel(
        name=robot.get("name", ""),
        links=tuple(links),
        joints=tuple(joints),
        root=roots[0],
        floating_base=None if mark is None else mark.strip().lower() == "true",
        bare=frozenset(bare),
    )


def _frame_with_z(z: np.ndarray) -> np.ndarray:
    """Axis slots (z, y, x) of a right-handed orthonormal frame whose z column is the unit vector z."""
    z = z / np.linalg.norm(z)
    helper = np.eye(3)[0] if abs(z[0]) < 0.9 else np.eye(3)[1]
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([z, y, x])


def _mimic_source(model: UrdfModel, source: str) -> dict[str, tuple[str | None, float, float]]:
    """joint -> (independent joint, multiplier, offset) for every moving joint (chains of mimics
    resolved); a mimic of a joint the file does not have is held at its offset (leader None), as
    yourdfpy does, with a warning."""
    by_name = {j.name: j for j in model.joints}
    out: dict[str, tuple[str | None, float, float]] = {}
    for j in model.joints:
        if j.type == "fixed":
            continue
        name, mult, off, seen = j.name, 1.0, 0.0, [j.name]
        while (mimic := by_name[name].mimic) is not None:
            leader, m, o = mimic  # q_name = m q_leader + o
            if leader not in by_name:
                _log.warning(
                    "%s: joint %r mimics %r, which is not a joint of the file: held at its offset %g",
                    source,
                    name,
                    leader,
                    o,
                )
                out[j.name] = (None, 0.0, mult * o + off)
                break
            if by_name[leader].type == "fixed":
                raise InputError(f"{source}: joint {name!r} mimics {leader!r}, a fixed joint")
            if leader in seen:
                raise InputError(f"{source}: mimic joints form a loop: {' -> '.join(seen + [leader])}")
            mult, off = mult * m, mult * o + off
            name = leader
            seen.append(name)
        else:  # the chain ends at an independent joint
            out[j.name] = (name, mult, off)
    return out


def _moves_its_base(model: UrdfModel, children: dict[str, list[UrdfJoint]]) -> bool:
    """True if prismatic joints reached from the root through fixed and prismatic joints translate
    the root freely (along three independent directions), as `skeleton_to_urdf` writes a root's
    translation."""
    dirs = []
    stack = [(model.root, np.eye(3))]
    while stack:
        link, rot = stack.pop()
        for j in children.get(link, []):
            if j.type in ("fixed", "prismatic"):
                r = rot @ euler_matrix_np(j.rpy, "XYZ")
                if j.type == "prismatic" and j.mimic is None:
                    dirs.append(r @ np.asarray(j.axis))
                stack.append((j.child, r))
    return len(dirs) >= 3 and np.linalg.matrix_rank(np.asarray(dirs), tol=1e-6) == 3


def skeleton_from_urdf(path: str | Path, floating_base: bool | None = None, collapse: bool | None = None) -> Skeleton:
    """Build a Skeleton from a URDF file, or from URDF text such as `to_urdf`'s (a string that starts
    with '<'); see `Skeleton.from_urdf`."""
    if isinstance(path, str) and path.lstrip("\ufeff \t\r\n").startswith("<"):
        model = parse_urdf(path, "<URDF text>")
        return skeleton_from_model(model, floating_base=floating_base, source="<URDF text>", collapse=collapse)
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"URDF file not found: {p}")
    if p.is_dir():
        raise InputError(f"{p}: is a folder, not a URDF file")
    try:
        text = p.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise InputError(f"{p}: not a readable URDF (not UTF-8 text: {e})") from None
    return skeleton_from_model(
        parse_urdf(text, str(p)), floating_base=floating_base, name=p.stem, source=str(p), collapse=collapse
    )


@dataclass
class _Piece:
    """One ptrack joint made of a chain of URDF joints (see `_merge_chain`): its transform from the
    parent joint's frame is Trans(u) Rot(slot 1) Rot(slot 2) Rot(slot 3) E Trans(w + slide q)."""

    u: np.ndarray  # (3,) translation in the parent's frame (the root: its rest position)
    slots: list[tuple[np.ndarray, int, float, float]]  # (unit axis, dof or -1, scale, constant angle)
    rest: np.ndarray  # (3, 3) E
    w: np.ndarray  # (3,) translation in the joint's own frame
    slide: tuple[np.ndarray, int] | None  # (displacement per unit of q in the joint's frame, dof)
    translation: dict[int, int]  # the root: world axis (0, 1, 2) -> dof of a translation along it


def _merge_chain(chain: list[UrdfJoint], motion: dict[str, tuple[int, float, float]], is_root: bool) -> _Piece | int:
    """The chain of URDF joints from one kept link down to the next (the links between merged) as
    one ptrack joint, or the index of the first joint that this form cannot hold (a rotation after
    a translation or a slide, more than three rotations, two slides). `motion` maps each moving
    joint to (dof or -1 for one held at its offset, multiplier, offset). The first joint's origin is
    the offset u and
    the rest rotation; fixed rotations after it become slots held at their angle while slots are
    free, and translations after it are w. For the root, slides along the world axes before any
    rotation are its translation dofs.

    Kept as the transform Trans(u) S R Trans(w), S the slots so far, R the pending rest rotation and
    w in the current frame, so that a chain with nothing after its first joint is read exactly."""
    u = np.zeros(3)
    rest = np.eye(3)
    w = np.zeros(3)
    slots: list[tuple[np.ndarray, int, float, float]] = []
    slide: tuple[np.ndarray, int] | None = None
    translation: dict[int, int] = {}

    def may_rotate() -> bool:
        """Whether a slot can be added (moving w into u while there is no slot yet)."""
        nonlocal u, w
        if slide is not None or len(slots) == 3:
            return False
        if np.any(w):
            if slots:
                return False
            u, w = u + rest @ w, np.zeros(3)
        return True

    def turn(r: np.ndarray) -> None:
        """Fold a constant rotation into R: Trans(w) r = r Trans(r^T w)."""
        nonlocal rest, w, slide
        rest = rest @ r
        if np.any(w):
            w = r.T @ w
        if slide is not None:
            slide = (r.T @ slide[0], slide[1])

    for n, j in enumerate(chain):
        r_o = euler_matrix_np(j.rpy, "XYZ") if any(j.rpy) else None
        if n == 0:
            u = np.asarray(j.xyz, dtype=np.float64)
            rest = r_o if r_o is not None else np.eye(3)
        else:
            if any(j.xyz):
                w = w + np.asarray(j.xyz, dtype=np.float64)
            if r_o is not None:
                held = matrix_to_axis_angle_np(r_o) if j.type == "fixed" and not any(j.xyz) else None
                if held is not None and held[1] != 0.0 and may_rotate():
                    slots.append((rest @ held[0], -1, 1.0, held[1]))  # R Rot(b, a) = Rot(R b, a) R
                else:
                    turn(r_o)
        if j.type == "fixed":
            continue
        ax = np.asarray(j.axis, dtype=np.float64)
        d, mult, off = motion[j.name]
        if j.type == "prismatic":
            if np.any(off):
                w = w + off * ax
            if d < 0:
                continue
            world = rest @ ax
            k = int(np.argmax(np.abs(world)))
            if (
                is_root
                and not slots
                and mult == 1.0
                and k not in translation
                and np.allclose(world, np.eye(3)[k], rtol=0, atol=1e-12)
            ):
                translation[k] = d  # commutes with the rest of the root's chain
            elif slide is None:
                slide = (mult * ax, d)
            else:
                return n
        elif d < 0:  # a revolute held at its offset: a constant rotation
            if may_rotate():
                slots.append((rest @ ax, -1, 1.0, off))
            else:
                turn(axis_angle_matrix(torch.as_tensor(ax), torch.tensor(off, dtype=torch.float64)).numpy())
        elif may_rotate():
            slots.append((rest @ ax, d, mult, off))
        else:
            return n
    return _Piece(u, slots, rest, w, slide, translation)


def _slot_frame(slots: list[tuple[np.ndarray, int, float, float]]) -> np.ndarray:
    """Axes (3, 3) for slots 0..2 holding `slots`' axes in order, the free slots filled so that the
    three are the (z, y, x) columns of a right-handed frame when the given axes allow it (the closed
    form of `ptrack.body.kinematics`, as ASF skeletons have); of three, a held slot's axis is negated
    (its angle too, by the caller) where that makes the frame right-handed."""
    given = [a / np.linalg.norm(a) for a, *_ in slots]
    if len(given) == 0:
        return np.eye(3)[::-1].copy()
    if len(given) == 1:
        return _frame_with_z(given[0])
    if len(given) == 2:
        z, y = given
        return np.stack([z, y, np.cross(y, z)])
    axes = np.stack(given)
    held = [k for k, (_, d, _, _) in enumerate(slots) if d < 0]
    if held and np.linalg.det(axes[::-1].T) < 0:  # columns (x, y, z)
        axes[held[0]] = -axes[held[0]]
    return axes


def _merge_links(
    model: UrdfModel, children: dict[str, list[UrdfJoint]], floating_base: bool, collapse: bool | None
) -> set[str]:
    """The links to merge into the joint below them: each bare (no visual, collision or inertial)
    with one child joint, not the root link but `skeleton_to_urdf`'s base "world" where the base
    is not floating. collapse None: only the links `skeleton_to_urdf` adds (in files it wrote:
    "<joint>__link", "<joint>__link__<k>" above that joint, and that base); True: all such links
    of any file; False: none."""
    if collapse is False or (collapse is None and model.floating_base is None):
        return set()
    merge = {ln for ln in model.links if ln in model.bare and len(children.get(ln, ())) == 1}
    if floating_base or model.floating_base is None or not _BASE_LINK.fullmatch(model.root):
        merge.discard(model.root)
    if collapse:
        return merge
    merge = {ln for ln in merge if ln == model.root or _ADDED_LINK.fullmatch(ln)}
    while True:  # to_urdf's names: an added link is named after the joint below it
        bad = set()
        for ln in merge:
            end = ln
            while end in merge:
                end = children[end][0].child
            m = _ADDED_LINK.fullmatch(ln)
            if ln != model.root and (m is None or m[1] != end):
                bad.add(ln)
        if not bad:
            return merge
        merge -= bad


_ADDED_LINK = re.compile(r"(.+)__link(?:__\d+)?")
_BASE_LINK = re.compile(r"world(?:__\d+)?")


def skeleton_from_model(
    model: UrdfModel,
    floating_base: bool | None = None,
    name: str | None = None,
    source: str = "<urdf>",
    collapse: bool | None = None,
) -> Skeleton:
    """Build a Skeleton from a parsed URDF (see `Skeleton.from_urdf`)."""
    children: dict[str, list[UrdfJoint]] = {}
    incoming: dict[str, UrdfJoint] = {}
    for j in model.joints:
        children.setdefault(j.parent, []).append(j)
        incoming[j.child] = j
    if floating_base is None:
        floating_base = model.floating_base if model.floating_base is not None else not _moves_its_base(model, children)

    # links depth-first from the root, children in file order: parents precede children
    order: list[str] = []
    stack = [model.root]
    while stack:
        link = stack.pop()
        order.append(link)
        stack.extend(j.child for j in reversed(children.get(link, [])))
    if len(order) != len(model.links):
        missing = sorted(set(model.links) - set(order))
        raise InputError(f"{source}: links not connected to the root link {model.root!r}: {missing[:5]}")

    dof_names: list[str] = []
    lower: list[float] = []
    upper: list[float] = []
    if floating_base:
        dof_names.extend(["root.tx", "root.ty", "root.tz", "root.rx", "root.ry", "root.rz"])
        lower.extend([-math.inf] * 6)
        upper.extend([math.inf] * 6)
        clash = sorted(set(dof_names) & {j.name for j in model.joints})
        if clash:
            raise InputError(
                f"{source}: joint names {clash} are the floating base's dof names; "
                "use floating_base=False or rename them"
            )
    ours = model.floating_base is not None  # written by skeleton_to_urdf: +-UNLIMITED_PRISMATIC is no limit
    dof_of: dict[str, int] = {}
    for j in model.joints:  # independent moving joints get dofs in file order
        if j.type != "fixed" and j.mimic is None:
            dof_of[j.name] = len(dof_names)
            dof_names.append(j.name)
            wide = ours and j.type == "prismatic"
            lower.append(-math.inf if wide and j.lower <= -UNLIMITED_PRISMATIC else j.lower)
            upper.append(math.inf if wide and j.upper >= UNLIMITED_PRISMATIC else j.upper)
    motion = {
        jn: (-1 if leader is None else dof_of[leader], mult, off)
        for jn, (leader, mult, off) in _mimic_source(model, source).items()
    }

    # each kept link is a ptrack joint, with the chain of URDF joints from the kept link above
    merge = _merge_links(model, children, floating_base, collapse)
    while True:
        kept = [ln for ln in order if ln not in merge]
        pieces: dict[str, _Piece] = {}
        chains: dict[str, list[UrdfJoint]] = {}
        failed: set[str] = set()
        for ln in kept[1:] if model.root not in merge else kept:
            chain, up = [incoming[ln]], incoming[ln].parent
            while up in merge and up != model.root:
                chain.insert(0, incoming[up])
                up = incoming[up].parent
            piece = _merge_chain(chain, motion, is_root=up in merge)
            if isinstance(piece, int):  # keep the link above the joint that does not fit
                assert piece > 0  # a chain's first joint always fits
                failed.add(chain[piece].parent)
            else:
                pieces[ln], chains[ln] = piece, chain
        if not failed:
            break
        merge -= failed
    index = {ln: i for i, ln in enumerate(kept)}

    j_count = len(kept)
    axes = np.zeros((j_count, 3, 3))
    axes[:] = np.eye(3)[::-1]  # slots (z, y, x) of the identity frame
    axis_dof = -np.ones((j_count, 3), dtype=np.int64)
    axis_scale = np.ones((j_count, 3))
    frozen = np.zeros((j_count, 3))
    rest = np.broadcast_to(np.eye(3), (j_count, 3, 3)).copy()
    u = np.zeros((j_count, 3))
    w = np.zeros((j_count, 3))
    slide_axis = np.zeros((j_count, 3))
    slide_dof = -np.ones(j_count, dtype=np.int64)
    trans = -np.ones(3, dtype=np.int64)
    root_position = np.zeros(3)
    parents = [-1] * j_count
    if floating_base:
        trans[:] = [0, 1, 2]
        axis_dof[0] = [5, 4, 3]  # G_root = Rz Ry Rx
    for ln, p in pieces.items():
        i = index[ln]
        top = chains[ln][0].parent
        parents[i] = index.get(top, -1)
        if parents[i] < 0:  # the root, below merged links
            root_position = p.u
            for k, d in p.translation.items():
                trans[k] = d
        else:
            u[i] = p.u
        rest[i], w[i] = p.rest, p.w
        axes[i] = _slot_frame(p.slots)
        for k, (_, d, scale, angle) in enumerate(p.slots):
            sign = 1.0 if np.dot(axes[i, k], p.slots[k][0]) > 0 else -1.0  # a held slot's axis may be negated
            axis_dof[i, k], axis_scale[i, k], frozen[i, k] = d, scale, sign * angle
        if p.slide is not None:
            slide_axis[i], slide_dof[i] = p.slide
    lengths = np.where(np.any(u, axis=1), np.linalg.norm(u, axis=1), np.linalg.norm(w, axis=1))
    safe = np.where(lengths > 0, lengths, 1.0)[:, None]
    return Skeleton(
        name=name if name is not None else (model.name or "urdf"),
        joint_names=tuple(kept),
        parents=tuple(parents),
        axes=axes,
        axis_dof=axis_dof,
        rest_rotation=rest,
        offset_parent=u / safe,
        offset_local=w / safe,
        lengths=lengths,
        root_position=root_position,
        translation_dof=trans,
        dof_names=tuple(dof_names),
        lower=np.asarray(lower, dtype=np.float64),
        upper=np.asarray(upper, dtype=np.float64),
        frozen_axes=frozen,
        axis_scale=axis_scale,
        slide_axis=slide_axis,
        slide_dof=slide_dof,
    )


# ---------------------------------------------------------------- export


def _fmt(v) -> str:
    return " ".join(f"{float(x):.17g}" for x in v)


def _limit(v: float) -> float:
    return float(np.clip(v, -UNLIMITED_PRISMATIC, UNLIMITED_PRISMATIC))


def skeleton_to_urdf(sk: Skeleton) -> str:
    """URDF text of `sk`. Link `sk.joint_names[i]` is joint i's frame (position p_i, rotation G_i);
    URDF joints that move are named after the dofs. A dof driving several slots (a mimic joint of an
    imported URDF) is written once as the joint that slot has with multiplier 1 and offset 0, and
    `<mimic>` joints for the others. The base link is "world" (another name if the model uses it)."""
    used = set(sk.joint_names) | set(sk.dof_names)
    fresh_names: set[str] = set()

    def fresh(base: str) -> str:
        k, name = 0, base
        while name in used or name in fresh_names:
            k += 1
            name = f"{base}__{k}"
        fresh_names.add(name)
        return name

    # the slot (joint, k) or slide (joint, -1) that owns each dof; the others mimic it
    owner: dict[int, tuple[int, int]] = {}
    for i in range(sk.num_joints):
        if sk.slide_dof[i] >= 0 and np.isclose(np.linalg.norm(sk.slide_axis[i]), 1.0, rtol=0, atol=1e-12):
            owner.setdefault(int(sk.slide_dof[i]), (i, -1))
        for k in range(3):
            d = int(sk.axis_dof[i, k])
            if d >= 0 and sk.axis_scale[i, k] == 1.0 and sk.frozen_axes[i, k] == 0.0:
                owner.setdefault(d, (i, k))
    driven = {int(x) for x in sk.axis_dof[sk.axis_dof >= 0]} | {int(x) for x in sk.slide_dof[sk.slide_dof >= 0]}
    for d in sorted(driven):
        if d not in owner:
            raise InputError(
                f"skeleton {sk.name!r}: dof {sk.dof_names[d]!r} drives no joint directly "
                "(only through a multiplier or offset), which URDF cannot write"
            )

    world = fresh("world")
    links = [f"  <link name={quoteattr(world)}/>"]
    joints: list[tuple[int | None, str]] = []  # (dof of a joint that owns one, text)

    def link(name: str) -> None:
        links.append(f"  <link name={quoteattr(name)}/>")

    def joint(name, kind, parent, child, xyz=(0, 0, 0), rpy=(0, 0, 0), axis=None, lim=None, mimic=None):
        s = [
            f'  <joint name={quoteattr(name)} type="{kind}">',
            f"    <parent link={quoteattr(parent)}/>",
            f"    <child link={quoteattr(child)}/>",
            f'    <origin xyz="{_fmt(xyz)}" rpy="{_fmt(rpy)}"/>',
        ]
        if axis is not None:
            s.append(f'    <axis xyz="{_fmt(axis)}"/>')
        if lim is not None:
            s.append(
                f'    <limit lower="{_limit(lim[0]):.17g}" upper="{_limit(lim[1]):.17g}" effort="1" velocity="1"/>'
            )
        if mimic is not None:
            leader, mult, off = mimic
            s.append(f'    <mimic joint={quoteattr(leader)} multiplier="{mult:.17g}" offset="{off:.17g}"/>')
        s.append("  </joint>")
        joints.append((sk.dof_names.index(name) if mimic is None and kind != "fixed" else None, "\n".join(s)))

    def moving(d: int, here: tuple[int, int], scale: float, off: float) -> tuple[str, tuple | None]:
        """Name and <mimic> of the URDF joint of dof d at slot `here`."""
        if owner[d] == here:
            return sk.dof_names[d], None
        return fresh(f"{sk.dof_names[d]}__mimic"), (sk.dof_names[d], scale, off)

    def lim_of(d: int, kind: str, here: tuple[int, int]):
        if owner[d] != here:  # a mimic joint's range follows its leader's
            return (-UNLIMITED_PRISMATIC, UNLIMITED_PRISMATIC) if kind == "prismatic" else None
        return sk.lower[d], sk.upper[d]

    # joint i as a chain: origin (fixed: the offset u and the rest rotation E), then each slot about
    # E^T a (G_parent E Rot(E^T a) = G_parent Rot(a) E), the slide, the offset w; the last link is `name`
    for i, name in enumerate(sk.joint_names):
        e = sk.rest_rotation[i]
        steps: list[tuple] = []  # (joint name, kind, keyword arguments)
        if i == 0:
            steps.append(
                (fresh(f"{name}__origin"), "fixed", world, {"xyz": sk.root_position, "rpy": matrix_to_euler_np(e)})
            )
            for k in range(3):
                d = int(sk.translation_dof[k])
                if d >= 0:
                    steps.append(
                        (
                            sk.dof_names[d],
                            "prismatic",
                            None,
                            {"axis": e.T @ np.eye(3)[k], "lim": (sk.lower[d], sk.upper[d])},
                        )
                    )
        else:
            steps.append(
                (
                    fresh(f"{name}__offset"),
                    "fixed",
                    sk.joint_names[sk.parents[i]],
                    {"xyz": sk.lengths[i] * sk.offset_parent[i], "rpy": matrix_to_euler_np(e)},
                )
            )
        for k in range(3):
            d = int(sk.axis_dof[i, k])
            ax = e.T @ sk.axes[i, k]
            if d >= 0:
                jname, mimic = moving(d, (i, k), float(sk.axis_scale[i, k]), float(sk.frozen_axes[i, k]))
                lim = lim_of(d, "revolute", (i, k))
                kind = "revolute" if lim is not None and np.all(np.isfinite(lim)) else "continuous"
                steps.append(
                    (jname, kind, None, {"axis": ax, "lim": lim if kind == "revolute" else None, "mimic": mimic})
                )
            elif sk.frozen_axes[i, k] != 0.0:
                r = axis_angle_matrix(
                    torch.as_tensor(ax), torch.tensor(float(sk.frozen_axes[i, k]), dtype=torch.float64)
                ).numpy()
                steps.append((fresh(f"{name}__frozen{k}"), "fixed", None, {"rpy": matrix_to_euler_np(r)}))
        d = int(sk.slide_dof[i])
        if d >= 0:  # along G_i s
            s = sk.slide_axis[i]
            n = float(np.linalg.norm(s))
            jname, mimic = moving(d, (i, -1), n, 0.0)
            steps.append(
                (
                    jname,
                    "prismatic",
                    None,
                    {"axis": s / n if n > 0 else np.eye(3)[0], "lim": lim_of(d, "prismatic", (i, -1)), "mimic": mimic},
                )
            )
        if np.any(sk.offset_local[i]) and sk.lengths[i] != 0.0:
            steps.append((fresh(f"{name}__end"), "fixed", None, {"xyz": sk.lengths[i] * sk.offset_local[i]}))
        prev = steps[0][2]
        for n_step, (jname, kind, parent, kw) in enumerate(steps):
            child = name if n_step == len(steps) - 1 else fresh(f"{name}__link")
            link(child)
            joint(jname, kind, parent if parent is not None else prev, child, **kw)
            prev = child
    # the joints that own a dof in dof order (readers number dofs in file order), the others in place
    dof_at = {k: d for k, (d, _) in enumerate(joints) if d is not None}  # slot -> dof
    in_dof_order = [joints[k] for k in sorted(dof_at, key=dof_at.__getitem__)]
    for k, jt in zip(dof_at, in_dof_order):
        joints[k] = jt
    head = f'<?xml version="1.0"?>\n<robot name={quoteattr(sk.name or "ptrack")} {_BASE_MARK}="false">'
    return "\n".join([head, *links, *(text for _, text in joints), "</robot>\n"])
