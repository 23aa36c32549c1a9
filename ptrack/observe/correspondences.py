"""2D point correspondences between consecutive observation frames (Urtasun, Fleet & Fua 2004, section 4.3),
read from a file or simulated from the ground truth.

A pair is (p1 in image t-1, p2 in image t): the same body point seen in two consecutive frames, as an
optical-flow or correlation matcher finds it. Users bring their own as a plain ``.npz`` archive (numpy
arrays, no pickles; config key `observations.correspondence_file`):

    frame    integer (M,)    t, the second frame of each pair, an observation frame index in 1 .. T-1
    p1       float (M, 2)    pixels (u right, v down) in frame t-1
    p2       float (M, 2)    pixels in frame t
    weight   float (M,)      optional, >= 0 (default 1): scales the pair's squared residual

`simulate_correspondences` makes them from a motion-capture pose sequence and the capsule model
(`observations.correspondences` pairs per frame): it samples pixels on the model's projection in
image t-1, backprojects them to the visible surface, carries each body-fixed point to frame t with
the true motion, keeps the points still visible there and adds noise and outliers to p2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ptrack.errors import InputError
from ptrack.observe.backprojection import anchor_points, backproject, ray_capsule_hit
from ptrack.observe.camera import Camera
from ptrack.observe.observations import read_npz

#: a simulated point counts as visible in frame t when the model's first surface along its line of sight is
#: this close to it (metres)
VISIBLE_TOL_M = 1e-4


@dataclass(frozen=True, eq=False)
class Correspondences:
    """M point pairs between consecutive frames: frame (M,) long, the second frame t of each pair; p1 (M, 2)
    pixels in frame t-1; p2 (M, 2) pixels in frame t; weight (M,) >= 0. Array-likes become tensors (p1's
    float dtype, or float32). Bad shapes, non-finite values and negative weights raise `InputError`;
    frames are checked against a clip by `check_frames`."""

    frame: Tensor
    p1: Tensor
    p2: Tensor
    weight: Tensor

    def __post_init__(self) -> None:
        frame = torch.as_tensor(self.frame)
        if frame.ndim != 1 or frame.is_floating_point() or frame.dtype == torch.bool:
            raise InputError(f"correspondences: frame must be (M,) integers, got {frame.dtype} {tuple(frame.shape)}")
        m = frame.shape[0]
        p1 = torch.as_tensor(self.p1)
        dtype = p1.dtype if p1.is_floating_point() else torch.float32
        arrays = {"p1": p1, "p2": torch.as_tensor(self.p2), "weight": torch.as_tensor(self.weight)}
        for name, x in arrays.items():
            shape = (m,) if name == "weight" else (m, 2)
            if tuple(x.shape) != shape or x.dtype == torch.bool or x.is_complex():
                raise InputError(
                    f"correspondences: {name} must be {shape} numbers (M = {m} pairs in frame), "
                    f"got {x.dtype} {tuple(x.shape)}"
                )
            x = x.to(device=frame.device, dtype=dtype)
            bad = ~torch.isfinite(x) if x.ndim == 1 else ~torch.isfinite(x).all(-1)
            if bool(bad.any()):
                raise InputError(f"correspondences: {name} has NaN/inf, first at pair {int(bad.nonzero()[0])}")
            arrays[name] = x
        if bool((arrays["weight"] < 0).any()):
            i = int((arrays["weight"] < 0).nonzero()[0])
            raise InputError(f"correspondences: weight must be >= 0, got {float(arrays['weight'][i])} at pair {i}")
        object.__setattr__(self, "frame", frame.long())
        for name, x in arrays.items():
            object.__setattr__(self, name, x)

    @property
    def num_pairs(self) -> int:
        return self.frame.shape[0]

    def check_frames(self, num_frames: int, source: str = "correspondences") -> None:
        """InputError unless every pair's second frame t is in 1 .. num_frames - 1 (its first, t-1, in the clip)."""
        bad = (self.frame < 1) | (self.frame >= num_frames)
        if bool(bad.any()):
            i = int(bad.nonzero()[0])
            raise InputError(
                f"{source}: pair {i} has frame {int(self.frame[i])}, outside 1..{num_frames - 1} (frame is the "
                f"second frame t of the pair (t-1, t) and the clip has {num_frames} observation frames)"
            )

    def to(self, device: torch.device | str | None = None, dtype: torch.dtype | None = None) -> Correspondences:
        """A copy on `device` with p1, p2 and weight cast to `dtype`."""
        return Correspondences(
            frame=self.frame.to(device),
            p1=self.p1.to(device=device, dtype=dtype),
            p2=self.p2.to(device=device, dtype=dtype),
            weight=self.weight.to(device=device, dtype=dtype),
        )

    def by_frame(self, num_frames: int) -> tuple[Tensor, Tensor, Tensor]:
        """The pairs per second frame, padded: p1 (T, P, 2), p2 (T, P, 2), weight (T, P) (0 on padding), with
        P the most pairs any frame has (at least 1)."""
        order = torch.argsort(self.frame, stable=True)
        frame = self.frame[order]
        counts = torch.bincount(frame, minlength=num_frames)
        first = torch.cumsum(counts, 0) - counts
        rank = torch.arange(frame.shape[0], device=frame.device) - first[frame]
        p = max(int(counts.max()) if counts.numel() else 0, 1)
        p1 = self.p1.new_zeros(num_frames, p, 2)
        p2 = self.p2.new_zeros(num_frames, p, 2)
        weight = self.weight.new_zeros(num_frames, p)
        p1[frame, rank] = self.p1[order]
        p2[frame, rank] = self.p2[order]
        weight[frame, rank] = self.weight[order]
        return p1, p2, weight

    def save_npz(self, path: str | Path) -> None:
        """Write the layout of the module docstring (compressed, exactly at `path`)."""
        arrays = {k: getattr(self, k).detach().cpu().numpy() for k in ("frame", "p1", "p2", "weight")}
        with open(path, "wb") as f:
            np.savez_compressed(f, **arrays)

    @classmethod
    def load_npz(cls, path: str | Path, num_frames: int | None = None) -> Correspondences:
        """Read the layout of the module docstring; with `num_frames`, also `check_frames`. A missing file, a
        missing key, a wrong dtype or shape, NaN, a negative weight or a frame outside the clip raise
        `InputError` naming the file."""
        path = Path(path)
        arrays = read_npz(path, "correspondence file")
        for key in ("frame", "p1", "p2"):
            if key not in arrays:
                raise InputError(f"{path}: missing key {key!r} (has {sorted(arrays)}; needs frame, p1, p2)")
        if arrays["frame"].dtype.kind not in "iu":
            raise InputError(f"{path}: key 'frame' must be integers, got dtype {arrays['frame'].dtype}")
        for key in ("p1", "p2", "weight"):
            if key in arrays and arrays[key].dtype.kind not in "fiu":
                raise InputError(f"{path}: key {key!r} must be numeric, got dtype {arrays[key].dtype}")
        m = arrays["frame"].shape[0] if arrays["frame"].ndim == 1 else -1
        weight = arrays.get("weight", np.ones(max(m, 0)))
        try:
            corr = cls(
                frame=torch.from_numpy(arrays["frame"].astype(np.int64)),
                p1=torch.from_numpy(arrays["p1"].astype(np.float64)),
                p2=torch.from_numpy(arrays["p2"].astype(np.float64)),
                weight=torch.from_numpy(np.asarray(weight).astype(np.float64)),
            )
            if num_frames is not None:
                corr.check_frames(num_frames)
        except InputError as e:
            raise InputError(f"{path}: {e}") from None
        return corr


class SimulatedInfo(NamedTuple):
    """What `simulate_correspondences` drew, per pair (M,), for tests: the capsule hit in frame t-1, whether
    p2 is an outlier, and the exact p2 (M, 2) before noise and outliers."""

    bone: Tensor
    outlier: Tensor
    clean_p2: Tensor


def _boxes(camera: Camera, joints: Tensor, margin_m: float) -> tuple[Tensor, Tensor]:
    """Per frame, the pixel box (lo, hi) (T, 2) of the joints' projections widened by `margin_m` at the nearest
    joint's depth, clipped to the image."""
    proj = camera.project(joints)
    pad = camera.K[0, 0].to(joints) * margin_m / proj.depth.clamp_min(0.1).amin(-1)  # (T,)
    size = torch.tensor([camera.width, camera.height], dtype=joints.dtype, device=joints.device)
    lo = (proj.pixels.amin(-2) - pad[:, None]).clamp(min=torch.zeros_like(size), max=size)
    hi = (proj.pixels.amax(-2) + pad[:, None]).clamp(min=torch.zeros_like(size), max=size)
    return lo, hi


def simulate_correspondences(
    joints: Tensor,
    rotations: Tensor,
    bones: Tensor,
    radii: Tensor,
    camera: Camera,
    per_frame: int,
    generator: torch.Generator,
    noise_px: float = 1.0,
    outliers: float = 0.0,
    outlier_px: float = 50.0,
    candidates: int = 8,
) -> tuple[Correspondences, SimulatedInfo]:
    """Correspondences between consecutive frames of a true motion, seen through the capsule model.

    joints (T, J, 3) and world rotations (T, J, 3, 3) of the true poses; bones (B, 2) long (parent, child);
    radii (B,) metres; per_frame: pairs wanted per frame pair (t-1, t). For each t, `candidates * per_frame`
    pixels are drawn uniformly in the box of the model's projection in image t-1 and backprojected to the
    visible capsule surface (`ptrack.observe.backprojection.backproject`: the nearest hit, so front-facing and
    not hidden by another capsule); each hit, fixed in its capsule's frame, is carried to frame t by the true
    motion and kept when it is still visible there (the first surface along its line of sight, within
    VISIBLE_TOL_M) and inside the image; the first `per_frame` kept, in draw order, are the pairs (fewer
    when fewer are found). p1 is the drawn pixel; p2 the carried point's projection plus Gaussian noise of
    std `noise_px`, and for a share `outliers` of the pairs displaced by U(0.5, 1.5) * outlier_px in a
    uniform direction instead (a wrong match). Weights are 1.

    Every draw comes from `generator`, in float64 and a fixed order whatever is found (so the same seed
    gives the same pairs in float32 and float64); the geometry is computed in float64. Returns
    (Correspondences in joints' dtype on its device, SimulatedInfo).
    """
    if per_frame < 1 or candidates < 1:
        raise InputError(
            f"simulate_correspondences: per_frame and candidates must be >= 1, got {per_frame}, {candidates}"
        )
    t_count = joints.shape[0]
    f64 = torch.float64
    x, rot = joints.to(f64), rotations.to(f64)
    cam = camera.to(dtype=f64)
    radii = radii.to(x)
    bones = torch.as_tensor(bones, dtype=torch.long, device=x.device)
    n = candidates * per_frame
    gdev = generator.device

    def draw(*shape: int, normal: bool = False) -> Tensor:
        fn = torch.randn if normal else torch.rand
        return fn(shape, generator=generator, device=gdev, dtype=f64).to(x.device)

    u = draw(t_count - 1, n, 2)
    noise = draw(t_count - 1, n, 2, normal=True) * noise_px
    u_out = draw(t_count - 1, n)
    angle = draw(t_count - 1, n) * (2 * math.pi)
    magnitude = (0.5 + draw(t_count - 1, n)) * outlier_px
    lo, hi = _boxes(cam, x[:-1], float(radii.max()))
    p1 = lo[:, None] + u * (hi - lo)[:, None]  # (T-1, n, 2)
    anchors = backproject(cam, p1, x[:-1, None], rot[:-1, None], bones, radii)
    carried = anchor_points(anchors, x[1:, None], rot[1:, None])  # (T-1, n, 3)
    proj = cam.project(carried)
    _, dirs = cam.rays(proj.pixels)
    again = ray_capsule_hit(cam.center, dirs, x[1:, None, bones[:, 0]], x[1:, None, bones[:, 1]], radii)
    seen = again.hit & ((again.depth - (carried - cam.center).norm(dim=-1)).abs() <= VISIBLE_TOL_M)
    keep = anchors.valid & seen & proj.in_front & cam.in_image(proj.pixels)
    keep = keep & (torch.cumsum(keep.long(), -1) <= per_frame)
    outlier = keep & (u_out < outliers)
    offset = magnitude[..., None] * torch.stack([angle.cos(), angle.sin()], -1)
    p2 = proj.pixels + torch.where(outlier[..., None], offset, noise)
    frame = torch.arange(1, t_count, device=x.device)[:, None].expand_as(keep)
    dtype = joints.dtype
    corr = Correspondences(
        frame=frame[keep],
        p1=p1[keep].to(dtype),
        p2=p2[keep].to(dtype),
        weight=torch.ones(int(keep.sum()), dtype=dtype, device=x.device),
    )
    return corr, SimulatedInfo(bone=anchors.bone[keep], outlier=outlier[keep], clean_p2=proj.pixels[keep].to(dtype))
