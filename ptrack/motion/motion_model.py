"""Time-warped PCA motion model of one motion type (Urtasun, Fleet & Fua 2004, section 3).

Fitting (`fit_motion_model`): in each training clip the key postures are found (`ptrack.motion.key_postures`);
the clip is time-warped piecewise-linearly so that every key posture falls at the same normalised
time (`key_times`: the clips' mean relative positions of the postures between the first and the last,
which sit at 0 and 1), and resampled at N normalised times mu_i = i / (N - 1). A swing is then an
angular motion vector Psi (N * D,) of the D modelled dofs (every dof of the skeleton but the root's
six, which the tracker estimates itself, and those matching `motion.exclude`: by default fingers, thumbs,
hands and toes, which the trackers hold at zero and whose CMU angles jump by whole turns). PCA over the clips
gives the mean motion Theta_0 and m eigen-motions Theta_i: Psi ~ Theta_0 + sum_i alpha_i Theta_i (eq. 2).

Resampling between two captured frames interpolates each 3-dof joint's rotation by quaternion slerp
(kornia) and reads the angles back in the joint's own Euler order (the branch and 2 pi turn nearest
the angles' linear interpolation, so angles stay continuous). Joints with one or two dofs take linear
interpolation of their angles: for one dof it is the same path as slerp, and slerp between two
2-dof rotations leaves the joint's two-axis manifold, so its angles could not be read back exactly.

Decoding (`decode`) is linear interpolation between the N samples in mu, differentiable in both the
PCA weights alpha and the normalised time mu (eqs. 3-4). Angles are radians, in skeleton dof order.

File format (`save_motion_model`): one compressed .npz with float64 arrays `mean` (N, D), `components`
(m, N, D), `explained` (m,), `sigma` (m,), `key_times` (P,) and `meta`, a JSON string: format version,
dof_names, skeleton_dof_names, key_names, skeleton name, training clips and their key frames.
"""

from __future__ import annotations

import fnmatch
import json
import logging
import math
import os
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ptrack.body.acclaim import skeleton_beside
from ptrack.body.rotations import matrix_to_euler_np
from ptrack.body.skeleton import Skeleton
from ptrack.clips import parse_clips
from ptrack.errors import InputError
from ptrack.motion.key_postures import detect_key_postures

log = logging.getLogger(__name__)

FORMAT = "ptrack-motion-model"
VERSION = 1


@dataclass(frozen=True)
class MotionModel:
    """A PCA motion model. N samples in normalised time, D modelled dofs, m components, P key postures.

    dof_names: (D,) modelled dofs (the skeleton's dofs but the root's and `motion.exclude`), in skeleton order.
    skeleton_dof_names: every dof of the training skeleton (to refuse another skeleton).
    mean: (N, D) mean motion Theta_0, radians. components: (m, N, D) orthonormal eigen-motions Theta_i.
    explained: (m,) share of the training variance along each component.
    key_names: (P,) key postures; key_times: (P,) their normalised times in [0, 1].
    sigma: (m,) std of the training clips' PCA coefficients (a prior on alpha).
    """

    dof_names: tuple[str, ...]
    skeleton_dof_names: tuple[str, ...]
    mean: Tensor
    components: Tensor
    explained: Tensor
    key_names: tuple[str, ...]
    key_times: Tensor
    sigma: Tensor
    info: dict | None = None  # provenance: skeleton name, clips, their key frames

    @property
    def num_samples(self) -> int:
        return self.mean.shape[0]

    @property
    def num_components(self) -> int:
        return self.components.shape[0]


def decode(model: MotionModel, alpha: Tensor, mu: Tensor) -> Tensor:
    """Joint angles of the model's dofs: alpha (..., m), mu (...) -> (..., D), radians.

    Linear interpolation between the N samples of Theta_0 + sum_i alpha_i Theta_i at normalised time
    mu, clamped to [0, 1] (zero gradient in mu outside). Differentiable in alpha and mu; computes in
    alpha's dtype and device; alpha and mu broadcast over their leading dims.
    """
    n = model.num_samples
    mean = model.mean.to(alpha)
    comp = model.components.to(alpha)
    mu = torch.as_tensor(mu).to(alpha).clamp(0.0, 1.0)
    s = mu * (n - 1)
    i0 = s.detach().floor().clamp(0, n - 2).long()
    w = (s - i0.to(s))[..., None]
    a = mean[i0] + torch.einsum("...k,k...d->...d", alpha, comp[:, i0])
    b = mean[i0 + 1] + torch.einsum("...k,k...d->...d", alpha, comp[:, i0 + 1])
    return a + w * (b - a)


def encode(model: MotionModel, motion: Tensor) -> Tensor:
    """PCA weights of a resampled motion: motion (N, D) radians -> alpha (m,) (least squares projection)."""
    if motion.shape != model.mean.shape:
        raise InputError(f"motion must have shape {tuple(model.mean.shape)} (samples, dofs), got {tuple(motion.shape)}")
    comp = model.components.to(motion)
    return comp.flatten(1) @ (motion - model.mean.to(motion)).flatten()


def motion_vector(model: MotionModel, alpha: Tensor) -> Tensor:
    """The whole motion of weights alpha: (..., m) -> (..., N, D)."""
    return model.mean.to(alpha) + torch.einsum("...k,knd->...nd", alpha, model.components.to(alpha))


def dof_index(model: MotionModel, skeleton: Skeleton) -> Tensor:
    """Positions of the model's dofs in `skeleton`'s pose vector q: LongTensor (D,).

    InputError if the skeleton lacks some (e.g. dofs removed by `Skeleton.freeze`: index the full
    skeleton's q and `reduce` it, or keep those dofs).
    """
    missing = [d for d in model.dof_names if d not in skeleton.dof_names]
    if missing:
        raise InputError(
            f"skeleton {skeleton.name!r} has no dof {missing[0]!r} of the motion model ({len(missing)} missing)"
        )
    return torch.as_tensor([skeleton.dof_names.index(d) for d in model.dof_names], dtype=torch.long)


# ---------------------------------------------------------------- resampling


def modelled_dofs(skeleton: Skeleton, exclude: Sequence[str] = ()) -> list[int]:
    """Indices of the dofs a motion model holds: every dof not driving the root joint nor matching an
    `exclude` pattern (shell-style, on the dof name or its joint's name, as `Skeleton.freeze`)."""
    root = {int(i) for i in skeleton.axis_dof[0] if i >= 0} | {int(i) for i in skeleton.translation_dof if i >= 0}
    return [
        i
        for i, name in enumerate(skeleton.dof_names)
        if i not in root
        and not any(
            fnmatch.fnmatchcase(name, pat) or fnmatch.fnmatchcase(name.rsplit(".", 1)[0], pat) for pat in exclude
        )
    ]


def _euler_branches(m: np.ndarray) -> np.ndarray:
    """Both Euler solutions (x, y, z) of R = Rz Ry Rx: (..., 3, 3) -> (2, ..., 3)."""
    a = matrix_to_euler_np(m, "XYZ")
    b = np.stack([a[..., 0] + math.pi, math.pi - a[..., 1], a[..., 2] + math.pi], axis=-1)
    return np.stack([a, b])


def resample(skeleton: Skeleton, q: Tensor, times: np.ndarray) -> np.ndarray:
    """Poses at fractional frame indices: q (T, D_sk), times (N,) in [0, T-1] -> (N, D_sk).

    3-dof joints whose axes form a frame (every ASF joint) by quaternion slerp, the rest linearly;
    see the module docstring.
    """
    from kornia.geometry.conversions import quaternion_to_rotation_matrix, rotation_matrix_to_quaternion
    from kornia.geometry.quaternion import Quaternion

    from ptrack.body.kinematics import euler_zyx

    q = q.detach().cpu().double()
    t = q.shape[0]
    times = np.clip(np.asarray(times, dtype=np.float64), 0, t - 1)
    i0 = np.minimum(np.floor(times).astype(np.int64), max(t - 2, 0))
    i1 = np.minimum(i0 + 1, t - 1)
    w = times - i0
    qn = q.numpy()
    out = qn[i0] * (1 - w[:, None]) + qn[i1] * w[:, None]  # linear, replaced below for ball joints
    c = np.stack([skeleton.axes[:, 2], skeleton.axes[:, 1], skeleton.axes[:, 0]], axis=-1)
    frames_ok = np.isclose(np.linalg.det(c), 1.0, atol=1e-9) & np.all(
        np.isclose(np.einsum("jab,jac->jbc", c, c), np.eye(3), atol=1e-9), axis=(1, 2)
    )
    ball = [j for j in range(1, skeleton.num_joints) if np.all(skeleton.axis_dof[j] >= 0) and frames_ok[j]]
    if ball and t > 1:
        slots = torch.as_tensor(skeleton.axis_dof[ball])  # (B, 3) dofs of the (z, y, x) slots
        ang = q[:, slots]  # (T, B, 3) as (z, y, x)
        rot = euler_zyx(ang)  # the joint's rotation in its own frame: Rz Ry Rx
        quat = rotation_matrix_to_quaternion(rot.reshape(-1, 3, 3)).reshape(t, len(ball), 4)
        q0 = Quaternion(quat[torch.as_tensor(i0)].reshape(-1, 4))
        q1 = Quaternion(quat[torch.as_tensor(i1)].reshape(-1, 4))
        wt = torch.as_tensor(w, dtype=torch.float64).repeat_interleave(len(ball))
        mid = quaternion_to_rotation_matrix(q0.slerp(q1, wt).data).reshape(len(times), len(ball), 3, 3)
        branches = _euler_branches(mid.numpy())[..., ::-1]  # (2, N, B, 3) as (z, y, x)
        lin = out[:, skeleton.axis_dof[ball]]  # (N, B, 3)
        branches = branches + 2 * math.pi * np.round((lin - branches) / (2 * math.pi))
        pick = np.abs(branches - lin).sum(-1).argmin(0)  # (N, B)
        best = np.take_along_axis(branches, pick[None, ..., None], 0)[0]
        out[:, skeleton.axis_dof[ball]] = best
    return out


def warp_times(key_frames: Sequence[int], key_times: np.ndarray, samples: int) -> np.ndarray:
    """Fractional frame of each of `samples` normalised times, piecewise linear through the key postures."""
    mu = np.linspace(0.0, 1.0, samples)
    return np.interp(mu, np.asarray(key_times, dtype=np.float64), np.asarray(key_frames, dtype=np.float64))


# ---------------------------------------------------------------- fitting


@dataclass(frozen=True)
class Clip:
    """One training clip: its skeleton, poses q (T, D) and frame rate."""

    name: str
    skeleton: Skeleton
    q: Tensor
    fps: float


def read_clips(paths: Sequence[str | Path]) -> list[Clip]:
    """Load AMC clips (each with the .asf beside it) through the acclaim loaders."""
    clips: list[Clip] = []
    skeletons: dict[Path, Skeleton] = {}
    for p in paths:
        p = Path(p)
        if not p.is_file():
            raise FileNotFoundError(f"training clip not found: {p}")
        asf = skeleton_beside(p)
        if asf is None:
            raise InputError(f"training clip {p}: no skeleton (.asf) beside it")
        sk = skeletons.get(asf) or skeletons.setdefault(asf, Skeleton.from_asf(asf))
        m = sk.load_amc(p)
        clips.append(Clip(p.name, sk, m.q, m.fps))
    return clips


def clip_paths(spec: Sequence[str]) -> list[Path]:
    """`motion.clips` -> AMC paths: the listed files, a single non-.amc entry being a clip-list file."""
    if len(spec) == 1 and not spec[0].lower().endswith(".amc"):
        if not Path(spec[0]).is_file():
            raise FileNotFoundError(f"config key 'motion.clips': clip list not found: {spec[0]}")
        return parse_clips(spec[0], what="config key 'motion.clips'")
    return [Path(s) for s in spec]


def fit_motion_model(clips: Sequence[Clip], cfg) -> MotionModel:
    """PCA motion model of training clips (see the module docstring). cfg: a `MotionConfig`.

    InputError: fewer than 2 clips, clips of different skeletons, key postures not found (naming the
    clip), more components than clips - 1.
    """
    _check_counts(len(clips), cfg.components)
    m = cfg.components
    sk0 = clips[0].skeleton
    for c in clips[1:]:
        if c.skeleton.dof_names != sk0.dof_names:
            raise InputError(f"training clip {c.name}: its skeleton's dofs differ from {clips[0].name}'s")
    idx = modelled_dofs(sk0, cfg.exclude)
    if not idx:
        raise InputError("config key 'motion.exclude' leaves no dof to model")
    key_frames = []
    for c in clips:
        with torch.no_grad():
            joints = c.skeleton.forward_kinematics(c.q)
        key_frames.append(detect_key_postures(joints, c.skeleton, c.fps, cfg, clip=c.name).numpy())
    kf = np.stack(key_frames).astype(np.float64)  # (M, P)
    key_times = ((kf - kf[:, :1]) / (kf[:, -1:] - kf[:, :1])).mean(0)
    motions = []
    for c, f in zip(clips, kf):
        x = np.unwrap(c.q.detach().cpu().double().numpy(), axis=0)  # AMC angles may wrap at +-180
        motions.append(resample(c.skeleton, torch.from_numpy(x), warp_times(f, key_times, cfg.samples))[:, idx])
    x = np.stack(motions)  # (M, N, D)
    x = x - 2 * math.pi * np.round((x.mean(1, keepdims=True) - x[:1].mean(1, keepdims=True)) / (2 * math.pi))
    mean = x.mean(0)
    centred = (x - mean).reshape(len(clips), -1)
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    comps = vt[:m]
    sign = np.sign(comps[np.arange(m), np.abs(comps).argmax(1)])  # largest entry positive: deterministic
    comps = comps * sign[:, None]
    var = s**2
    return MotionModel(
        dof_names=tuple(sk0.dof_names[i] for i in idx),
        skeleton_dof_names=tuple(sk0.dof_names),
        mean=torch.from_numpy(mean),
        components=torch.from_numpy(comps.reshape(m, *mean.shape).copy()),
        explained=torch.from_numpy(var[:m] / var.sum()),
        key_names=tuple(cfg.key_postures),
        key_times=torch.from_numpy(key_times),
        sigma=torch.from_numpy(s[:m] / math.sqrt(len(clips) - 1)),
        info={"skeleton": sk0.name, "clips": [c.name for c in clips], "key_frames": kf.astype(int).tolist()},
    )


def model_path(cfg) -> Path:
    """Where a config's motion model lives: `motion.model_file`, or ~/.cache/ptrack/motion/<name>.npz."""
    if cfg.motion.model_file:
        return Path(cfg.motion.model_file)
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    return cache / "ptrack" / "motion" / f"{cfg.name}.npz"


# ---------------------------------------------------------------- files


def save_motion_model(model: MotionModel, path: str | Path) -> Path:
    """Write the model (module docstring: format) atomically; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "dof_names": list(model.dof_names),
        "skeleton_dof_names": list(model.skeleton_dof_names),
        "key_names": list(model.key_names),
        **(model.info or {}),
    }
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as f:
        np.savez_compressed(
            f,
            mean=model.mean.double().numpy(),
            components=model.components.double().numpy(),
            explained=model.explained.double().numpy(),
            sigma=model.sigma.double().numpy(),
            key_times=model.key_times.double().numpy(),
            meta=np.array(json.dumps(meta)),
        )
    os.replace(tmp, path)
    return path


def load_motion_model(path: str | Path, skeleton: Skeleton | None = None) -> MotionModel:
    """Read a model file; InputError if it is corrupt or, given `skeleton`, the skeleton's dofs (its
    dof_names plus any removed by `freeze`) are not the model's training skeleton's."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"motion model file not found: {path}")
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in ("mean", "components", "explained", "sigma", "key_times", "meta")}
        meta = json.loads(str(arrays.pop("meta")))
        if meta.get("format") != FORMAT or meta.get("version") != VERSION:
            raise ValueError(f"not a {FORMAT} version {VERSION} file")
        dofs, sk_dofs, keys = (tuple(str(x) for x in meta[k]) for k in ("dof_names", "skeleton_dof_names", "key_names"))
        mean, comp = arrays["mean"], arrays["components"]
        n, d = mean.shape
        m = comp.shape[0]
        if comp.shape != (m, n, d) or d != len(dofs) or n < 2 or m < 1:
            raise ValueError(f"array shapes disagree (mean {mean.shape}, components {comp.shape}, {len(dofs)} dofs)")
        for k, want in (("explained", m), ("sigma", m), ("key_times", len(keys))):
            if arrays[k].shape != (want,):
                raise ValueError(f"{k} has shape {arrays[k].shape}, expected ({want},)")
        if not all(np.isfinite(a).all() for a in arrays.values()):
            raise ValueError("non-finite values")
    except (OSError, ValueError, KeyError, TypeError, EOFError, zipfile.BadZipFile, json.JSONDecodeError) as e:
        raise InputError(f"motion model file {path} is corrupt or not a motion model: {e}") from None
    model = MotionModel(
        dof_names=dofs,
        skeleton_dof_names=sk_dofs,
        **{k: torch.from_numpy(np.ascontiguousarray(v, dtype=np.float64)) for k, v in arrays.items()},
        key_names=keys,
        info={
            k: v
            for k, v in meta.items()
            if k not in ("format", "version", "dof_names", "skeleton_dof_names", "key_names")
        },
    )
    if skeleton is not None:
        have = set(skeleton.dof_names) | {name for name, _ in skeleton.frozen}
        if have != set(sk_dofs):
            diff = sorted(have ^ set(sk_dofs))
            raise InputError(
                f"motion model {path} was fitted on another skeleton: dofs differ from "
                f"{skeleton.name!r}'s ({len(diff)} differ, e.g. {diff[0]!r})"
            )
    return model


def fit_from_config(cfg) -> MotionModel:
    """Load `cfg.motion.clips` and fit their model (`ptrack fit-motion`). cfg: a `RunConfig`."""
    if not cfg.motion.clips:
        raise InputError("config key 'motion.clips' is required (AMC files or a clip-list file)")
    paths = clip_paths(cfg.motion.clips)
    _check_counts(len(paths), cfg.motion.components)  # before reading any clip
    return fit_motion_model(read_clips(paths), cfg.motion)


def _check_counts(clips: int, components: int) -> None:
    if clips < 2:
        raise InputError(f"a motion model needs at least 2 training clips, got {clips}")
    if components > clips - 1:
        raise InputError(
            f"config key 'motion.components' ({components}) must be at most the number of training "
            f"clips minus one ({clips - 1})"
        )


def check_writable(path: str | Path) -> Path:
    """InputError if a model could not be written at `path` (a folder, or under a file)."""
    path = Path(path)
    if path.is_dir():
        raise InputError(f"motion model output {path} is a folder; give a file name (e.g. {path / 'model.npz'})")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(f"motion model output {path}: {parent} is a file, not a folder")
            if not os.access(parent, os.W_OK):
                raise InputError(f"motion model output {path}: cannot write in {parent}")
            break
    return path
