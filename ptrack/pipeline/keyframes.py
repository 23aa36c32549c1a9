"""3D keyframes: read from a user's YAML/JSON file, or taken from the ground truth for synthetic
evaluation (DiFranco et al. §3.3, eq. 4: each a prior with its own standard deviation; what a
keyframe leaves out has no prior).

Keyframe file (`keyframes.file`; YAML, or JSON with the same keys):

    units: degrees            # angles in `dofs` and `q`: degrees (default) or radians
    keyframes:
      - frame: 0              # 0-based index into the reconstructed frames (after start/stride/upsample)
        q: [0.1, 0.9, ...]    # every dof, in the model's dof order (result.npz `dof_names`), or
        dofs:                 # some dofs by name (a partial keyframe): angles, root position in metres
          lfemur.rx: -20.0
          root.ty: 0.95
        sigma_deg: 2.0        # std of the given angles (default: config keyframes.sigma_deg)
        sigma_m: 0.02         # std of the given root coordinates (default: keyframes.sigma_m)
      - frame: 45
        joints:               # 3D joint positions, metres, world frame (Y up), by skeleton joint name
          lhand: [0.12, 1.31, 0.40]
          rfoot: [-0.2, 0.05, 0.3]
        sigma_m: 0.03         # std of each coordinate (default: keyframes.sigma_m)

An entry may give `q` or `dofs` (not both) and/or `joints`. Errors (`InputError`) name the file and
the entry: a frame outside the sequence, an unknown dof or joint, a zero or negative sigma, a value
that is not a number, malformed YAML/JSON.
"""

from __future__ import annotations

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
) -> Keyframes:
    """Ground-truth poses as keyframes: frame 0, then the first frame at or after each multiple of
    `every_s` seconds (None: none), and the last frame if `last`. Angles get Gaussian noise of std
    `noise_deg` (drawn from `generator`; the root position is kept). gt_q (T, D), times (T,) s."""
    t_len = gt_q.shape[0]
    frames = {0}
    if every_s is not None:
        rel = (times.double() - times[0].double()).cpu()
        k = 1
        while k * every_s <= float(rel[-1]) + 1e-9:
            frames.add(int(torch.searchsorted(rel, torch.tensor(k * every_s - 1e-9, dtype=rel.dtype))))
            k += 1
    if last:
        frames.add(t_len - 1)
    idx = torch.tensor(sorted(f for f in frames if f < t_len), dtype=torch.long)
    q = gt_q[idx.to(gt_q.device)].clone()
    angular = torch.as_tensor(skeleton.angular_dofs(), device=q.device)
    if noise_deg > 0:
        noise = torch.randn(q.shape, generator=generator, dtype=torch.float64).to(q) * math.radians(noise_deg)
        q = torch.where(angular, q + noise, q)
    sigma = torch.where(angular, math.radians(sigma_deg), sigma_m).to(q).expand(q.shape).clone()
    return Keyframes(frames=idx, q=q, sigma=sigma)


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


def read_keyframes(
    path: str | Path,
    skeleton: Skeleton,
    num_frames: int,
    sigma_deg: float,
    sigma_m: float,
    dtype: torch.dtype = torch.float32,
) -> tuple[Keyframes | None, JointKeyframes | None]:
    """Read a keyframe file (module docstring) for a model and a sequence of `num_frames` frames.
    -> angle keyframes (partial ones masked) and joint-position keyframes, either None if absent."""
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
    kf_rows: list[tuple[int, list[float], list[bool], list[float]]] = []
    jk_rows: list[tuple[int, list[list[float]], list[bool], float]] = []
    for n, entry in enumerate(raw["keyframes"]):
        where = f"keyframe file {p}, keyframe {n}"
        if not isinstance(entry, dict):
            raise InputError(f"{where} must be a mapping, got {entry!r}")
        bad = sorted(set(entry) - {"frame", "q", "dofs", "joints", "sigma_deg", "sigma_m"})
        if bad:
            raise InputError(f"{where}: unknown key {bad[0]!r} (known: frame, q, dofs, joints, sigma_deg, sigma_m)")
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
            for name, v in items:
                if name not in dofs:
                    raise InputError(
                        f"{where}: unknown dof {name!r} (the model's dofs: {', '.join(skeleton.dof_names[:8])}, ...)"
                    )
                i = dofs[name]
                values[i] = _number(v, f"{where}: {name}") * (1.0 if i in trans else scale)
                mask[i] = True
            kf_rows.append((frame, values, mask, [s_m if i in trans else s_ang for i in range(d)]))
        if "joints" in entry:
            js = entry["joints"]
            if not isinstance(js, dict) or not js:
                raise InputError(f"{where}: 'joints' must map joint names to [x, y, z]")
            pos, mask = [[0.0, 0.0, 0.0] for _ in range(j)], [False] * j
            for name, v in js.items():
                if name not in joints:
                    raise InputError(
                        f"{where}: unknown joint {name!r} (the skeleton's joints: "
                        f"{', '.join(skeleton.joint_names[:8])}, ...)"
                    )
                if not isinstance(v, list) or len(v) != 3:
                    raise InputError(f"{where}: joint {name} must be [x, y, z] in metres, got {v!r}")
                pos[joints[name]] = [_number(c, f"{where}: {name}") for c in v]
                mask[joints[name]] = True
            jk_rows.append((frame, pos, mask, s_m))
    kf = jk = None
    if kf_rows:
        kf = Keyframes(
            frames=torch.tensor([r[0] for r in kf_rows], dtype=torch.long),
            q=torch.tensor([r[1] for r in kf_rows], dtype=dtype),
            mask=torch.tensor([r[2] for r in kf_rows], dtype=torch.bool),
            sigma=torch.tensor([r[3] for r in kf_rows], dtype=dtype),
        )
    if jk_rows:
        jk = JointKeyframes(
            frames=torch.tensor([r[0] for r in jk_rows], dtype=torch.long),
            joints=torch.tensor([r[1] for r in jk_rows], dtype=dtype),
            mask=torch.tensor([r[2] for r in jk_rows], dtype=torch.bool),
            sigma=torch.tensor([r[3] for r in jk_rows], dtype=dtype),
        )
    return kf, jk
