"""3D keyframes: read from a user's YAML/JSON file, or taken from the ground truth for synthetic
evaluation (DiFranco et al. §3.3, eq. 4: each a prior with its own standard deviation; what a
keyframe leaves out has no prior).

Keyframe file (`keyframes.file`; YAML, or JSON with the same keys):

    units: degrees            # angles in `dofs`, `q` and `covariance`: degrees (default) or radians
    keyframes:
      - frame: 0              # 0-based index into the reconstructed frames (after start/stride/upsample)
        q: [0.1, 0.9, ...]    # a full pose: every dof, in the model's dof order (result.npz `dof_names`)
      - frame: 30
        dofs:                 # some dofs by name (a partial keyframe): angles, root position in metres
          lfemur.rx: -20.0
          root.ty: 0.95
        sigma_deg: 2.0        # std of the given angles (default: config keyframes.sigma_deg)
        sigma_m: 0.02         # std of the given root coordinates (default: keyframes.sigma_m)
      - frame: 45
        joints:               # 3D joint positions, metres, world frame (Y up), by skeleton joint name
          lwrist: [0.12, 1.31, 0.40]
          rfoot: {position: [-0.2, 0.05, 0.3], sigma_m: 0.05}   # with its own std
        sigma_m: 0.03         # std of each coordinate of the others (default: keyframes.sigma_m)
      - frame: 60
        dofs: {lfemur.rx: -20.0, lfemur.ry: 5.0}
        covariance: [[9.0, 4.0], [4.0, 9.0]]      # full covariance of the given dofs, in their order
        joints: {root: [0.0, 0.9, 0.1]}
        joint_covariance: [[1e-4, 0, 0], [0, 1e-4, 0], [0, 0, 9e-4]]   # of the joints' x, y, z, m^2

An entry may give `q` or `dofs` (not both) and/or `joints`. `covariance` (a row and a column per given dof,
in the order of `dofs` or `q`; in the values' units: degrees^2 or radians^2 for angles, m^2 for the root's
position, their products across) replaces the entry's sigmas for its dofs; `joint_covariance` (a row and a
column per coordinate x, y, z of each given joint, in the order of `joints`; m^2) replaces them for its
joints. Both must be symmetric and positive definite. Errors (`InputError`) name the file and the entry: a
frame outside the sequence, an unknown dof or joint, a zero or negative sigma, a value that is not a
number (NaN, inf, text), a covariance of the wrong size, not symmetric or not positive definite, malformed
YAML/JSON.
"""

from __future__ import annotations

import fnmatch
import json
import math
from pathlib import Path

import torch
import yaml
from torch import Tensor

from ptrack.body.skeleton import Skeleton
from ptrack.errors import InputError
from ptrack.pipeline.config import load_yaml
from ptrack.problem import JointKeyframes, Keyframes


def keyframe_frames(times: Tensor, every_s: float | None, last: bool, first: bool = True) -> Tensor:
    """The ground-truth keyframes' frames: frame 0 if `first`, then the first frame at or after each multiple of
    `every_s` seconds (None: none), and the last frame if `last`. times (T,) s -> (F,) long, sorted (maybe empty)."""
    t_len = times.shape[0]
    frames = {0} if first else set()
    if every_s is not None:
        rel = (times.double() - times[0].double()).cpu()
        k = 1
        while k * every_s <= float(rel[-1]) + 1e-9:
            frames.add(int(torch.searchsorted(rel, torch.tensor(k * every_s - 1e-9, dtype=rel.dtype))))
            k += 1
    if last:
        frames.add(t_len - 1)
    return torch.tensor(sorted(f for f in frames if f < t_len), dtype=torch.long)


def ground_truth_keyframes(
    gt_q: Tensor,
    times: Tensor,
    skeleton: Skeleton,
    every_s: float | None,
    last: bool,
    noise_deg: float,
    sigma_deg: float,
    sigma_m: float,
    generator: torch.Generator,
    dofs: tuple[str, ...] | None = None,
    first: bool = True,
) -> Keyframes | None:
    """Ground-truth poses as keyframes at `keyframe_frames` (None when there are none: `first` false, no
    `every_s`, no `last`). Angles get Gaussian noise of std `noise_deg`
    (drawn from `generator`; the root position is kept). gt_q (T, D), times (T,) s. dofs: the keyframes
    after frame 0 give only the dofs matching these names or shell patterns (`keyframes.dofs`; () none of
    them: frame 0 alone), None every dof."""
    idx = keyframe_frames(times, every_s, last, first)
    if not idx.numel():
        return None
    q = gt_q[idx.to(gt_q.device)].clone()
    angular = torch.as_tensor(skeleton.angular_dofs(), device=q.device)
    if noise_deg > 0:
        noise = torch.randn(q.shape, generator=generator, dtype=torch.float64).to(q) * math.radians(noise_deg)
        q = torch.where(angular, q + noise, q)
    sigma = torch.where(angular, math.radians(sigma_deg), sigma_m).to(q).expand(q.shape).clone()
    if dofs is None:
        return Keyframes(frames=idx, q=q, sigma=sigma)
    given = torch.zeros(skeleton.num_dofs, dtype=torch.bool)
    for pattern in dofs:
        hits = [i for i, n in enumerate(skeleton.dof_names) if fnmatch.fnmatchcase(n, pattern)]
        if not hits:
            raise InputError(
                f"config key 'keyframes.dofs': {pattern!r} names no dof of the model "
                f"({', '.join(skeleton.dof_names[:8])}, ...)"
            )
        given[hits] = True
    mask = given.expand(len(idx), -1).clone()
    mask[idx == 0] = True  # frame 0 stays a full pose: the trackers start from it
    keep = mask.any(-1)
    return Keyframes(
        frames=idx[keep], q=q[keep.to(q.device)], mask=mask[keep].to(q.device), sigma=sigma[keep.to(q.device)]
    )


def ground_truth_joint_keyframes(
    gt_joints: Tensor,
    times: Tensor,
    skeleton: Skeleton,
    names: tuple[str, ...],
    every_s: float | None,
    last: bool,
    sigma_m: float,
    noise_m: float,
    depth_noise_m: float,
    camera_rotation: Tensor,
    full: bool,
    generator: torch.Generator,
) -> JointKeyframes | None:
    """Ground-truth positions of the joints `names` (`keyframes.joints`) at the keyframes after frame 0
    (`keyframe_frames`), as a user's joint keyframes: gt_joints (T, J, 3) m, times (T,) s. Each position gets
    Gaussian noise of std `noise_m` across the camera's view and `depth_noise_m` along its optical axis
    (camera_rotation (3, 3), world to camera: its rows are the camera's axes in the world), drawn from
    `generator`. The prior is that noise's covariance plus sigma_m^2 on each axis, R^T diag(s_a^2, s_a^2,
    s_d^2) R (`full`), or only its world-axis variances (not `full`). None where no keyframe follows frame 0."""
    joints = {n: i for i, n in enumerate(skeleton.joint_names)}
    bad = [n for n in names if n not in joints]
    if bad:
        raise InputError(
            f"config key 'keyframes.joints': unknown joint {bad[0]!r} (the skeleton's joints: "
            f"{', '.join(skeleton.joint_names[:8])}, ...)"
        )
    idx = keyframe_frames(times, every_s, last)
    idx = idx[idx > 0]
    if not idx.numel():
        return None
    f_len, j_len = len(idx), skeleton.num_joints
    sel = torch.tensor(sorted({joints[n] for n in names}), dtype=torch.long)
    rot = camera_rotation.detach().double().cpu()
    scale = torch.tensor([noise_m, noise_m, depth_noise_m], dtype=torch.float64)
    x = gt_joints[idx.to(gt_joints.device)].detach().double().cpu().clone()  # (F, J, 3)
    if noise_m > 0 or depth_noise_m > 0:
        e = torch.randn(f_len, len(sel), 3, generator=generator, dtype=torch.float64)
        x[:, sel] += (e * scale) @ rot  # camera-axis noise turned into the world: R^T (s e)
    block = rot.T @ torch.diag(scale.square() + sigma_m**2) @ rot  # (3, 3) the prior of each joint
    if not full:
        block = torch.diag(block.diagonal())
    mask = torch.zeros(f_len, j_len, dtype=torch.bool)
    mask[:, sel] = True
    covariance = torch.block_diag(*([block] * j_len)).expand(f_len, -1, -1).clone()
    return JointKeyframes(
        frames=idx,
        joints=x.to(gt_joints),
        mask=mask,
        sigma=torch.full((f_len, j_len), sigma_m, dtype=gt_joints.dtype),
        covariance=covariance,
    )


def _number(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(float(value)):
        raise InputError(f"{where} must be a finite number, got {value!r}")
    return float(value)


def _sigma(entry: dict, key: str, default: float, where: str) -> float:
    if key not in entry:
        return default
    s = _number(entry[key], f"{where}: {key}")
    if s <= 0:
        raise InputError(f"{where}: {key} must be > 0, got {entry[key]!r}")
    return s


def _covariance(value, n: int, what: str, where: str, key: str) -> Tensor:
    """A file's covariance matrix: n x n lists of finite numbers, symmetric, positive definite -> (n, n) float64."""
    rows = value if isinstance(value, list) else None
    if rows is None or len(rows) != n or not all(isinstance(r, list) and len(r) == n for r in rows):
        got = f"{len(rows)} rows" if rows is not None else repr(value)
        raise InputError(f"{where}: '{key}' must be a {n} x {n} matrix (a row and a column per {what}), got {got}")
    c = torch.tensor(
        [[_number(v, f"{where}: {key}[{i}][{j}]") for j, v in enumerate(r)] for i, r in enumerate(rows)],
        dtype=torch.float64,
    )
    if not torch.allclose(c, c.T, rtol=1e-9, atol=1e-12 * float(c.abs().max())):
        raise InputError(f"{where}: '{key}' must be symmetric")
    if int(torch.linalg.cholesky_ex(c).info) != 0:
        raise InputError(f"{where}: '{key}' must be positive definite (every variance > 0, correlations below 1)")
    return c


def _joint(value, where: str, name: str, sigma_m: float) -> tuple[list[float], float]:
    """A joint of a keyframe: [x, y, z] metres, or {position: [x, y, z], sigma_m: s} -> (position, sigma)."""
    if isinstance(value, dict):
        bad = sorted(set(value) - {"position", "sigma_m"})
        if bad or "position" not in value:
            raise InputError(f"{where}: joint {name} must be [x, y, z] or {{position: [x, y, z], sigma_m: s}}")
        sigma_m = _sigma(value, "sigma_m", sigma_m, f"{where}: joint {name}")
        value = value["position"]
    if not isinstance(value, list) or len(value) != 3:
        raise InputError(f"{where}: joint {name} must be [x, y, z] in metres, got {value!r}")
    return [_number(c, f"{where}: {name}") for c in value], sigma_m


_ENTRY_KEYS = ("frame", "q", "dofs", "joints", "sigma_deg", "sigma_m", "covariance", "joint_covariance")


def read_keyframes(
    path: str | Path,
    skeleton: Skeleton,
    num_frames: int,
    sigma_deg: float,
    sigma_m: float,
    dtype: torch.dtype = torch.float32,
) -> tuple[Keyframes | None, JointKeyframes | None]:
    """Read a keyframe file (module docstring) for a model and a sequence of `num_frames` frames.
    -> angle keyframes (partial ones masked; with a covariance where any entry gives one) and
    joint-position keyframes, either None if absent."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"keyframe file not found: {p}")
    text = p.read_text(encoding="utf-8", errors="replace")
    try:
        raw = json.loads(text) if p.suffix.lower() == ".json" else load_yaml(text)
    except json.JSONDecodeError as e:
        raise InputError(f"keyframe file {p} is not valid JSON: {e.msg} at line {e.lineno}, column {e.colno}") from None
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        raise InputError(f"keyframe file {p} is not valid YAML: {getattr(e, 'problem', None) or e}{where}") from None
    if not isinstance(raw, dict) or not isinstance(raw.get("keyframes"), list):
        raise InputError(f"keyframe file {p} must hold a mapping with a list 'keyframes'")
    unknown = sorted(set(raw) - {"keyframes", "units"})
    if unknown:
        raise InputError(f"keyframe file {p}: unknown key {unknown[0]!r} (known: keyframes, units)")
    units = raw.get("units", "degrees")
    if units not in ("degrees", "radians"):
        raise InputError(f"keyframe file {p}: units must be 'degrees' or 'radians', got {units!r}")
    scale = math.pi / 180 if units == "degrees" else 1.0
    dofs = {n: i for i, n in enumerate(skeleton.dof_names)}
    joints = {n: i for i, n in enumerate(skeleton.joint_names)}
    trans = set(int(i) for i in skeleton.translation_dof if i >= 0)
    d, j = skeleton.num_dofs, skeleton.num_joints
    # (frame, values, mask, std, covariance (D, D) or None)
    kf_rows: list[tuple[int, list[float], list[bool], list[float], Tensor | None]] = []
    # (frame, positions, mask, std per joint, covariance (3J, 3J) or None)
    jk_rows: list[tuple[int, list[list[float]], list[bool], list[float], Tensor | None]] = []
    for n, entry in enumerate(raw["keyframes"]):
        where = f"keyframe file {p}, keyframe {n}"
        if not isinstance(entry, dict):
            raise InputError(f"{where} must be a mapping, got {entry!r}")
        bad = sorted(set(entry) - set(_ENTRY_KEYS))
        if bad:
            raise InputError(f"{where}: unknown key {bad[0]!r} (known: {', '.join(_ENTRY_KEYS)})")
        frame = entry.get("frame")
        if isinstance(frame, bool) or not isinstance(frame, int):
            raise InputError(f"{where}: 'frame' must be an integer, got {frame!r}")
        if not 0 <= frame < num_frames:
            raise InputError(f"{where}: frame {frame} is outside the sequence (frames 0..{num_frames - 1})")
        where = f"{where} (frame {frame})"
        s_ang = math.radians(_sigma(entry, "sigma_deg", sigma_deg, where))
        s_m = _sigma(entry, "sigma_m", sigma_m, where)
        if "q" in entry and "dofs" in entry:
            raise InputError(f"{where}: give 'q' or 'dofs', not both")
        if not any(k in entry for k in ("q", "dofs", "joints")):
            raise InputError(f"{where}: gives nothing (add 'q', 'dofs' or 'joints')")
        if "covariance" in entry and not ("q" in entry or "dofs" in entry):
            raise InputError(f"{where}: 'covariance' is of the dofs given by 'q' or 'dofs', and it gives none")
        if "joint_covariance" in entry and "joints" not in entry:
            raise InputError(f"{where}: 'joint_covariance' is of the joints given by 'joints', and it gives none")
        if "q" in entry or "dofs" in entry:
            values, mask = [0.0] * d, [False] * d
            if "q" in entry:
                q = entry["q"]
                if not isinstance(q, list) or len(q) != d:
                    raise InputError(
                        f"{where}: 'q' must list all {d} dofs of the model, got "
                        f"{len(q) if isinstance(q, list) else q!r}"
                    )
                items = list(zip(skeleton.dof_names, q))
            else:
                if not isinstance(entry["dofs"], dict) or not entry["dofs"]:
                    raise InputError(f"{where}: 'dofs' must map dof names to values")
                items = list(entry["dofs"].items())
            order = []
            for name, v in items:
                if name not in dofs:
                    raise InputError(
                        f"{where}: unknown dof {name!r} (the model's dofs: {', '.join(skeleton.dof_names[:8])}, ...)"
                    )
                i = dofs[name]
                values[i] = _number(v, f"{where}: {name}") * (1.0 if i in trans else scale)
                mask[i] = True
                order.append(i)
            cov = None
            if "covariance" in entry:  # in the units of the values: (degrees or radians) and metres
                given = _covariance(entry["covariance"], len(order), "given dof", where, "covariance")
                unit = torch.tensor([1.0 if i in trans else scale for i in order], dtype=torch.float64)
                cov = torch.zeros(d, d, dtype=torch.float64)
                cov[torch.tensor(order)[:, None], torch.tensor(order)[None, :]] = given * unit[:, None] * unit[None, :]
            kf_rows.append((frame, values, mask, [s_m if i in trans else s_ang for i in range(d)], cov))
        if "joints" in entry:
            js = entry["joints"]
            if not isinstance(js, dict) or not js:
                raise InputError(f"{where}: 'joints' must map joint names to [x, y, z]")
            pos, mask, std = [[0.0, 0.0, 0.0] for _ in range(j)], [False] * j, [s_m] * j
            order = []
            for name, v in js.items():
                if name not in joints:
                    raise InputError(
                        f"{where}: unknown joint {name!r} (the skeleton's joints: "
                        f"{', '.join(skeleton.joint_names[:8])}, ...)"
                    )
                pos[joints[name]], std[joints[name]] = _joint(v, where, name, s_m)
                mask[joints[name]] = True
                order.append(joints[name])
            cov = None
            if "joint_covariance" in entry:  # m^2, x y z of each joint in the order given
                given = _covariance(
                    entry["joint_covariance"], 3 * len(order), "given joint's x, y, z", where, "joint_covariance"
                )
                idx = torch.tensor([3 * i + c for i in order for c in range(3)])
                cov = torch.zeros(3 * j, 3 * j, dtype=torch.float64)
                cov[idx[:, None], idx[None, :]] = given
            jk_rows.append((frame, pos, mask, std, cov))
    kf = jk = None
    if kf_rows:
        kf = Keyframes(
            frames=torch.tensor([r[0] for r in kf_rows], dtype=torch.long),
            q=torch.tensor([r[1] for r in kf_rows], dtype=dtype),
            mask=torch.tensor([r[2] for r in kf_rows], dtype=torch.bool),
            sigma=torch.tensor([r[3] for r in kf_rows], dtype=dtype),
            covariance=_covariances([(r[3], r[4]) for r in kf_rows], 1),
        )
    if jk_rows:
        jk = JointKeyframes(
            frames=torch.tensor([r[0] for r in jk_rows], dtype=torch.long),
            joints=torch.tensor([r[1] for r in jk_rows], dtype=dtype),
            mask=torch.tensor([r[2] for r in jk_rows], dtype=torch.bool),
            sigma=torch.tensor([r[3] for r in jk_rows], dtype=dtype),
            covariance=_covariances([(r[3], r[4]) for r in jk_rows], 3),
        )
    return kf, jk


def _covariances(rows: list[tuple[list[float], Tensor | None]], repeat: int) -> Tensor | None:
    """Each keyframe's covariance (N, N) where one was given, its stds' diagonal (each std `repeat` times) where
    not; None when no keyframe gave one. rows: (std, covariance or None) -> (F, N, N)."""
    if all(c is None for _, c in rows):
        return None
    out = [
        torch.diag_embed(torch.tensor(s, dtype=torch.float64).repeat_interleave(repeat).square()) if c is None else c
        for s, c in rows
    ]
    return torch.stack(out)  # float64: a covariance's factor wants the precision
