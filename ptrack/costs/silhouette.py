"""Silhouette term: projected bones pulled inside a foreground mask through its distance transform."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from ptrack.costs.base import PoseEval, RobustMixin, check_positive, log, robust_loss, shape_of
from ptrack.errors import InputError


def distance_transform(mask: Tensor) -> Tensor:
    """Exact Euclidean distance in pixels from each pixel to the nearest True pixel.

    mask: (..., H, W) bool -> (..., H, W) float64 on mask's device; 0 on the mask. An image with
    no True pixel reads hypot(H, W) everywhere: finite (no NaN gradients downstream) and larger
    than any distance inside an H x W image. Linear time per image: scipy's exact transform
    (`scipy.ndimage.distance_transform_edt`), run on the CPU one image at a time.
    Construction-time helper, not differentiable.
    """
    from scipy.ndimage import distance_transform_edt  # lazy: importing scipy costs ~0.6 s

    mask = torch.as_tensor(mask, dtype=torch.bool)
    if mask.ndim < 2:
        raise InputError(f"distance_transform: mask must be (..., H, W), got {shape_of(mask)}")
    h, w = mask.shape[-2:]
    images = mask.cpu().reshape(math.prod(mask.shape[:-2]), h, w).numpy()
    out = np.empty(images.shape, dtype=np.float64)
    for image, dist, has_pixel in zip(images, out, np.asarray(images.any(axis=(-2, -1)))):
        if has_pixel:
            distance_transform_edt(~image, distances=dist)
        else:
            dist.fill(math.hypot(h, w))
    return torch.from_numpy(out).reshape(mask.shape).to(mask.device)


@dataclass(frozen=True, eq=False)
class Silhouette(RobustMixin):
    """Keeps projected bones inside a foreground mask, on ev.joint_pixels (..., *O, J, 2).

    masks (*O, H, W) bool, *O = () or (T,); bones ((parent, child), ...) skeleton joint indices.
    Each bone is sampled at samples_per_bone points from parent to child (ends included); a
    sample's residual is DT(point) / sigma_px with DT the distance (pixels) to the nearest mask
    pixel, read by bilinear `grid_sample`. Pixels follow `Camera` and `render_silhouettes`: pixel
    (u, v) covers [u, u+1) x [v, v+1) and DT holds its value at the centre (u + 0.5, v + 0.5).
    Points outside the hull of the centres, [0.5, W - 0.5] x [0.5, H - 0.5] (outside the image,
    or within half a pixel of its edge), read DT at the nearest hull point plus their distance
    to it. Frames with an empty mask count as missing (zero residual).
    residual (..., |O|*B*S), rho per sample.
    """

    masks: Tensor
    bones: tuple[tuple[int, int], ...]
    sigma_px: float = 1.0
    samples_per_bone: int = 8
    loss: str = "l2"
    scale: float = 1.0
    _group: ClassVar[int] = 1
    _dt: Tensor = field(init=False, repr=False)
    _present: Tensor = field(init=False, repr=False)
    _bones: Tensor = field(init=False, repr=False)

    def __post_init__(self) -> None:
        masks = torch.as_tensor(self.masks)
        if masks.dtype != torch.bool or masks.ndim < 2 or min(masks.shape[-2:]) < 2:
            raise InputError(
                f"Silhouette.masks must be a bool tensor (*O, H, W) with H, W >= 2, got {masks.dtype} {shape_of(masks)}"
            )
        bones = torch.as_tensor(self.bones)
        if (
            bones.ndim != 2
            or bones.shape[1] != 2
            or bones.shape[0] == 0
            or bones.is_floating_point()
            or (bones < 0).any()
        ):
            raise InputError(
                f"Silhouette.bones must be non-empty (parent, child) pairs of joint indices >= 0, got {self.bones!r}"
            )
        if int(self.samples_per_bone) != self.samples_per_bone or self.samples_per_bone < 2:
            raise InputError(f"Silhouette.samples_per_bone must be an integer >= 2, got {self.samples_per_bone!r}")
        check_positive("Silhouette.sigma_px", self.sigma_px)
        check_positive("Silhouette.scale", self.scale)
        robust_loss(self.loss)
        dt = distance_transform(masks)
        present = masks.flatten(-2).any(-1)
        if not present.all():
            log.warning(
                "Silhouette: %d of %d masks are empty and count as missing", int((~present).sum()), present.numel()
            )
        object.__setattr__(self, "masks", masks)
        object.__setattr__(self, "_dt", torch.where(present[..., None, None], dt, 0.0))
        object.__setattr__(self, "_present", present)
        object.__setattr__(self, "_bones", bones.long())

    def residual(self, ev: PoseEval) -> Tensor:
        """ev.joint_pixels (..., *O, J, 2) -> (..., |O|*B*S): distance outside mask / sigma_px."""
        jp = ev.joint_pixels
        if jp is None:
            raise InputError(
                "Silhouette needs PoseEval.joint_pixels (..., J, 2), the projected "
                "pixels of all skeleton joints, but it is None"
            )
        frames, (h, w) = self.masks.shape[:-2], self.masks.shape[-2:]
        n_o = len(frames)
        if (
            jp.ndim < n_o + 2
            or jp.shape[-1] != 2
            or jp.shape[jp.ndim - n_o - 2 : -2] != frames
            or jp.shape[-2] <= int(self._bones.max())
        ):
            raise InputError(
                f"Silhouette: ev.joint_pixels {shape_of(jp)} must be (..., "
                f"{', '.join(map(str, frames)) + ', ' if n_o else ''}J, 2) with J > "
                f"{int(self._bones.max())}"
            )
        bones = self._bones.to(jp.device)
        parent, child = jp.index_select(-2, bones[:, 0]), jp.index_select(-2, bones[:, 1])
        t = torch.linspace(0.0, 1.0, self.samples_per_bone, dtype=jp.dtype, device=jp.device)
        pts = parent[..., None, :] + t[:, None] * (child - parent)[..., None, :]
        batch, n_frames = jp.shape[: jp.ndim - n_o - 2], math.prod(frames)
        pts = pts.reshape(-1, n_frames, pts.shape[-3] * pts.shape[-2], 2).transpose(0, 1)
        u, v = pts.unbind(-1)
        uc, vc = u.clamp(0.5, w - 0.5), v.clamp(0.5, h - 0.5)  # the hull of pixel centres
        off2 = (u - uc).square() + (v - vc).square()
        outside = torch.where(off2 > 0, torch.where(off2 > 0, off2, 1.0).sqrt(), 0.0)
        # align_corners=False: -1 and 1 are the image edges 0 and W (H), centres at i + 0.5
        grid = torch.stack([2.0 * uc / w - 1.0, 2.0 * vc / h - 1.0], dim=-1)
        dt = self._dt.to(jp).reshape(n_frames, 1, h, w)
        d = F.grid_sample(dt, grid, mode="bilinear", padding_mode="border", align_corners=False)
        d = (d[:, 0] + outside) * self._present.to(jp).reshape(n_frames, 1, 1)
        return d.transpose(0, 1).reshape(*batch, -1) / self.sigma_px
