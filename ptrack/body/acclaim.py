"""Acclaim ASF (skeleton) and AMC (motion) file parsing.

Only text -> plain records here; `ptrack.body.skeleton` turns an `AsfFile` into a kinematic model.
Both parsers accept CRLF or LF line endings and `#` comments; the ASF parser skips unknown `:`
sections (some CMU copies carry e.g. `:namespace`). Malformed input raises `InputError` naming the
file and line.

Units are left as in the file (ASF lengths in file units, angles in degrees); the `:units` section
is returned so the caller can convert (CMU: `length 0.45` means 1 unit = 1/0.45 inch = 0.056444 m).

Clip files: `skeleton_beside` (the .asf of an .amc), shared by the motion model (`ptrack.motion`) and the
evaluation harness (`ptrack.pipeline.evaluate`); clip lists are `ptrack.clips`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ptrack.errors import InputError

#: metres per inch; an ASF length unit is (1 / units.length) inches.
INCH_M = 0.0254


@dataclass(frozen=True)
class AsfBone:
    """One `begin ... end` block of `:bonedata`."""

    name: str
    direction: tuple[float, float, float]  # unit vector, world frame at rest
    length: float  # file units
    axis: tuple[float, float, float]  # degrees
    axis_order: str  # e.g. "XYZ": rotations applied X first
    dof: tuple[str, ...]  # subset of rx ry rz tx ty tz l, in file order
    limits: tuple[tuple[float, float], ...]  # one (lo, hi) per dof, degrees; +-inf if absent


@dataclass(frozen=True)
class AsfFile:
    """A parsed ASF file."""

    path: str
    name: str
    length_unit: float  # value of `:units length` (CMU: 0.45)
    angle_unit: str  # "deg" or "rad"
    root_order: tuple[str, ...]  # e.g. ("TX", "TY", "TZ", "RX", "RY", "RZ")
    root_axis: str  # e.g. "XYZ"
    root_position: tuple[float, float, float]
    root_orientation: tuple[float, float, float]
    bones: tuple[AsfBone, ...]
    hierarchy: tuple[tuple[str, str], ...]  # (parent, child) pairs in file order

    @property
    def metres_per_unit(self) -> float:
        """Scale from file length units to metres (CMU: 0.056444)."""
        return INCH_M / self.length_unit


def _read_lines(path: str | Path, kind: str) -> list[str]:
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{kind} file not found: {p}")
    if not p.is_file():
        raise InputError(f"{kind} path is not a file: {p}")
    try:
        text = p.read_text(encoding="utf-8", errors="strict")
    except UnicodeDecodeError as e:
        raise InputError(f"{kind} file {p} is not a text file ({e.reason} at byte {e.start})") from None
    return text.replace("\r\n", "\n").replace("\r", "\n").split("\n")


def _floats(tokens: list[str], n: int, where: str) -> tuple[float, ...]:
    if len(tokens) < n:
        raise InputError(f"{where}: expected {n} numbers, got {len(tokens)}")
    try:
        vals = tuple(float(t) for t in tokens[:n])
    except ValueError:
        raise InputError(f"{where}: expected numbers, got {' '.join(tokens[:n])!r}") from None
    if not all(np.isfinite(vals)):
        raise InputError(f"{where}: non-finite number in {' '.join(tokens[:n])!r}")
    return vals


def _vec3(tokens: list[str], where: str) -> tuple[float, float, float]:
    x, y, z = _floats(tokens, 3, where)
    return x, y, z


_DOF_NAMES = {"rx", "ry", "rz", "tx", "ty", "tz", "l"}


def parse_asf(path: str | Path) -> AsfFile:
    """Parse an Acclaim ASF skeleton file.

    Raises FileNotFoundError if the file is missing and InputError (naming file and line) if it is
    malformed: missing `:bonedata`/`:hierarchy`, bad numbers, limits that don't match the dofs, a
    hierarchy naming unknown bones.
    """
    lines = _read_lines(path, "ASF")
    sections: dict[str, list[tuple[int, str]]] = {}
    header: dict[str, str] = {}
    current = None
    for i, raw in enumerate(lines, start=1):
        line = raw.split("#", 1)[0].rstrip()
        if not line.strip():
            continue
        if line.lstrip().startswith(":"):
            tokens = line.strip().split(None, 1)
            current = tokens[0][1:].lower()
            if len(tokens) > 1:
                header[current] = tokens[1].strip()
            sections.setdefault(current, [])
            continue
        if current is None:
            raise InputError(f"{path}:{i}: content before the first ':' keyword: {line.strip()!r}")
        sections[current].append((i, line.strip()))

    for required in ("root", "bonedata", "hierarchy"):
        if required not in sections:
            raise InputError(f"{path}: not an ASF skeleton (no :{required} section)")

    length_unit, angle_unit = 1.0, "deg"
    for i, line in sections.get("units", []):
        tok = line.split()
        if len(tok) >= 2 and tok[0] == "length":
            length_unit = _floats(tok[1:], 1, f"{path}:{i}")[0]
            if length_unit <= 0:
                raise InputError(f"{path}:{i}: units length must be positive, got {length_unit}")
        elif len(tok) >= 2 and tok[0] == "angle":
            angle_unit = tok[1].lower()
            if angle_unit not in ("deg", "rad"):
                raise InputError(f"{path}:{i}: units angle must be deg or rad, got {tok[1]!r}")

    root_order: tuple[str, ...] = ("TX", "TY", "TZ", "RX", "RY", "RZ")
    root_axis = "XYZ"
    root_position = (0.0, 0.0, 0.0)
    root_orientation = (0.0, 0.0, 0.0)
    for i, line in sections["root"]:
        tok = line.split()
        key = tok[0].lower()
        if key == "order":
            root_order = tuple(t.upper() for t in tok[1:])
            if not root_order or any(t not in {"TX", "TY", "TZ", "RX", "RY", "RZ"} for t in root_order):
                raise InputError(f"{path}:{i}: bad root order {' '.join(tok[1:])!r}")
        elif key == "axis":
            root_axis = _axis_order(tok[1] if len(tok) > 1 else "", f"{path}:{i}")
        elif key == "position":
            root_position = _vec3(tok[1:], f"{path}:{i}")
        elif key == "orientation":
            root_orientation = _vec3(tok[1:], f"{path}:{i}")

    bones = _parse_bones(sections["bonedata"], str(path))
    names = {b.name for b in bones}
    hierarchy: list[tuple[str, str]] = []
    for i, line in sections["hierarchy"]:
        tok = line.split()
        if tok[0].lower() in ("begin", "end"):
            continue
        parent = tok[0]
        if parent != "root" and parent not in names:
            raise InputError(f"{path}:{i}: hierarchy names unknown bone {parent!r}")
        for child in tok[1:]:
            if child not in names:
                raise InputError(f"{path}:{i}: hierarchy names unknown bone {child!r}")
            hierarchy.append((parent, child))
    children = [c for _, c in hierarchy]
    dup = {c for c in children if children.count(c) > 1}
    if dup:
        raise InputError(f"{path}: bones with more than one parent in :hierarchy: {sorted(dup)}")
    orphans = [b.name for b in bones if b.name not in set(children)]
    if orphans:
        raise InputError(f"{path}: bones missing from :hierarchy: {orphans}")
    return AsfFile(
        path=str(path),
        name=header.get("name", Path(path).stem),
        length_unit=length_unit,
        angle_unit=angle_unit,
        root_order=root_order,
        root_axis=root_axis,
        root_position=root_position,
        root_orientation=root_orientation,
        bones=tuple(bones),
        hierarchy=tuple(hierarchy),
    )


def _axis_order(token: str, where: str) -> str:
    order = token.upper()
    if sorted(order) != ["X", "Y", "Z"]:
        raise InputError(f"{where}: axis order must be a permutation of XYZ, got {token!r}")
    return order


def _parse_bones(lines: list[tuple[int, str]], path: str) -> list[AsfBone]:
    bones: list[AsfBone] = []
    block: dict | None = None
    start = 0
    pending_limits = 0
    for i, line in lines:
        tok = line.split()
        key = tok[0].lower()
        where = f"{path}:{i}"
        if key == "begin":
            if block is not None:
                raise InputError(f"{where}: 'begin' inside the bone block opened at line {start}")
            block, start, pending_limits = {"limits": []}, i, 0
            continue
        if block is None:
            raise InputError(f"{where}: {tok[0]!r} outside a begin/end bone block")
        if key == "end":
            bones.append(_make_bone(block, f"{path}:{start}"))
            block = None
            continue
        if pending_limits and line.startswith("("):
            block["limits"].append(_limit(line, where))
            pending_limits -= 1
            continue
        if key == "name":
            block["name"] = tok[1] if len(tok) > 1 else ""
        elif key == "direction":
            block["direction"] = _floats(tok[1:], 3, where)
        elif key == "length":
            block["length"] = _floats(tok[1:], 1, where)[0]
        elif key == "axis":
            block["axis"] = _floats(tok[1:], 3, where)
            block["axis_order"] = _axis_order(tok[4] if len(tok) > 4 else "XYZ", where)
        elif key == "dof":
            dof = tuple(t.lower() for t in tok[1:])
            bad = [d for d in dof if d not in _DOF_NAMES]
            if bad:
                raise InputError(f"{where}: unknown dof {bad[0]!r} (expected rx ry rz tx ty tz l)")
            block["dof"] = dof
        elif key == "limits":
            n = len(block.get("dof", ()))
            rest = line[len(tok[0]) :].strip()
            block["limits"].append(_limit(rest, where))
            pending_limits = n - 1
        elif key in ("id", "bodymass", "cofmass"):
            pass
        else:
            raise InputError(f"{where}: unknown bone field {tok[0]!r}")
    if block is not None:
        raise InputError(f"{path}:{start}: bone block never closed with 'end'")
    return bones


def _limit(text: str, where: str) -> tuple[float, float]:
    inner = text.strip()
    if not (inner.startswith("(") and inner.endswith(")")):
        raise InputError(f"{where}: limits must look like (lo hi), got {text.strip()!r}")
    tok = inner[1:-1].replace(",", " ").split()
    if len(tok) != 2:
        raise InputError(f"{where}: limits must look like (lo hi), got {text.strip()!r}")
    vals = []
    for t in tok:
        t = t.lower()
        if t in ("inf", "+inf"):
            vals.append(float("inf"))
        elif t == "-inf":
            vals.append(float("-inf"))
        else:
            try:
                vals.append(float(t))
            except ValueError:
                raise InputError(f"{where}: bad limit value {t!r}") from None
    lo, hi = vals
    if lo > hi:
        raise InputError(f"{where}: lower limit {lo} above upper limit {hi}")
    return (lo, hi)


def _make_bone(block: dict, where: str) -> AsfBone:
    for field in ("name", "direction", "length"):
        if field not in block:
            raise InputError(f"{where}: bone block has no {field!r}")
    d = np.asarray(block["direction"], dtype=np.float64)
    norm = float(np.linalg.norm(d))
    length = float(block["length"])
    if length < 0:
        raise InputError(f"{where}: bone {block['name']!r} has negative length {length}")
    if norm < 1e-12 and length > 0:
        raise InputError(f"{where}: bone {block['name']!r} has a zero direction")
    dof = block.get("dof", ())
    limits = block["limits"]
    if limits and len(limits) != len(dof):
        raise InputError(f"{where}: bone {block['name']!r} has {len(dof)} dofs but {len(limits)} limits")
    if not limits:
        limits = [(float("-inf"), float("inf"))] * len(dof)
    dx, dy, dz = (float(x) for x in (d / norm if norm > 0 else d))
    return AsfBone(
        name=block["name"],
        direction=(dx, dy, dz),
        length=length,
        axis=tuple(block.get("axis", (0.0, 0.0, 0.0))),
        axis_order=block.get("axis_order", "XYZ"),
        dof=tuple(dof),
        limits=tuple(limits),
    )


@dataclass(frozen=True)
class AmcFile:
    """A parsed AMC motion: per frame, each bone's values in its ASF dof order (file units/degrees)."""

    path: str
    frame_numbers: np.ndarray  # (T,) int
    values: dict[str, np.ndarray]  # bone name -> (T, n_dof) float64


def parse_amc(path: str | Path, dof_counts: dict[str, int]) -> AmcFile:
    """Parse an AMC motion file.

    Args:
        dof_counts: bone name -> number of values expected per frame (root: 6 for TX..RZ). Every frame
            must give every bone in `dof_counts` exactly once with that many numbers.

    Raises InputError naming the file and line for unknown bones, wrong value counts, bad numbers,
    frames missing bones, or a file with no frames.
    """
    lines = _read_lines(path, "AMC")
    frames: list[int] = []
    rows: dict[str, list[list[float]]] = {name: [] for name in dof_counts}
    seen: set[str] = set()
    frame_line = 0

    def close_frame() -> None:
        if frames and seen != set(dof_counts):
            missing = sorted(set(dof_counts) - seen)
            raise InputError(
                f"{path}:{frame_line}: frame {frames[-1]} is missing bones {missing[:5]}"
                + (" ..." if len(missing) > 5 else "")
                + " (does this AMC belong to this ASF?)"
            )

    for i, raw in enumerate(lines, start=1):
        line = raw.split("#", 1)[0].strip()
        if not line or line.startswith(":"):
            continue
        tok = line.split()
        if len(tok) == 1 and tok[0].lstrip("-").isdigit():
            close_frame()
            frames.append(int(tok[0]))
            seen = set()
            frame_line = i
            continue
        if not frames:
            raise InputError(f"{path}:{i}: bone data before the first frame number: {line!r}")
        name = tok[0]
        if name not in dof_counts:
            raise InputError(
                f"{path}:{i}: bone {name!r} is not a bone with dofs in the ASF skeleton "
                "(does this AMC belong to this ASF?)"
            )
        if name in seen:
            raise InputError(f"{path}:{i}: bone {name!r} given twice in frame {frames[-1]}")
        n = dof_counts[name]
        if len(tok) - 1 != n:
            raise InputError(
                f"{path}:{i}: bone {name!r} has {len(tok) - 1} values, the ASF skeleton says {n} "
                "(does this AMC belong to this ASF?)"
            )
        rows[name].append(list(_floats(tok[1:], n, f"{path}:{i}")))
        seen.add(name)
    close_frame()
    if not frames:
        raise InputError(f"{path}: no frames found (is this an AMC motion file?)")
    return AmcFile(
        path=str(path),
        frame_numbers=np.asarray(frames, dtype=np.int64),
        values={k: np.asarray(v, dtype=np.float64).reshape(len(frames), dof_counts[k]) for k, v in rows.items()},
    )


# ---------------------------------------------------------------- clip files


def skeleton_beside(amc: str | Path) -> Path | None:
    """The skeleton of an AMC clip: `<subject>.asf` in its folder, else the only .asf there, else None."""
    amc = Path(amc)
    cand = amc.parent / f"{amc.stem.split('_')[0]}.asf"
    if cand.is_file():
        return cand
    found = sorted(amc.parent.glob("*.asf"))
    return found[0] if len(found) == 1 else None
