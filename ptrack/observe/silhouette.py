"""Silhouettes of a capsule ("flesh") model of the skeleton, for foreground/background terms.

Each bone is a capsule: all points within ``radius`` of the 3D segment between its two joints. A
pixel is foreground when its camera ray (from the camera centre, forward only) passes within the
radius of some capsule's segment; the ray-segment distance is exact (a convex quadratic in the ray
and segment parameters, minimised over the interior and the four edges of its domain).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from ptrack.errors import InputError
from ptrack.observe.camera import Camera

#: default capsule radii (metres) per CMU bone name, without the l/r side prefix.
CMU_RADII_M = {
    "hipjoint": 0.08,
    "femur": 0.08,
    "tibia": 0.06,
    "foot": 0.045,
    "toes": 0.035,
    "lowerback": 0.14,
    "upperback": 0.14,
    "thorax": 0.13,
    "lowerneck": 0.06,
    "upperneck": 0.055,
    "head": 0.10,
    "clavicle": 0.06,
    "humerus": 0.05,
    "radius": 0.04,
    "wrist": 0.035,
    "hand": 0.03,
    "fingers": 0.03,
    "thumb": 0.03,
}
#: radius of a bone with an unknown name: this fraction of its length, clamped to the range below.
UNKNOWN_RADIUS_FRACTION = 0.25
UNKNOWN_RADIUS_RANGE_M = (0.02, 0.12)

#: (pixels x bones) pair evaluations per chunk: bounds memory to ~20 temporaries of this size.
_CHUNK_PAIRS = 1 << 20
#: tile side, in evaluated pixels, for culling bones by their projected bounding boxes.
_TILE = 16


def _radius_for(name: str) -> float | None:
    key = name.lower()
    if key in CMU_RADII_M:
        return CMU_RADII_M[key]
    if key[:1] in ("l", "r") and key[1:] in CMU_RADII_M:
        return CMU_RADII_M[key[1:]]
    return None


def capsule_radii(bone_names: Sequence[str], lengths: Tensor) -> Tensor:
    """Default capsule radius per bone: bone_names (B,), lengths (B,) metres -> radii (B,) metres.

    CMU names (``lfemur``, ``rtibia``, ``thorax``, ...; case-insensitive) get the values in
    `CMU_RADII_M`; other names get ``UNKNOWN_RADIUS_FRACTION * length`` clamped to
    `UNKNOWN_RADIUS_RANGE_M`. dtype/device follow ``lengths`` (integers become the default float).
    """
    lengths = torch.as_tensor(lengths)
    if not lengths.is_floating_point():
        lengths = lengths.to(torch.get_default_dtype())
    if isinstance(bone_names, str) or lengths.ndim != 1 or lengths.shape[0] != len(bone_names):
        raise InputError(
            f"capsule_radii: bone_names ({len(bone_names)} names) and lengths {tuple(lengths.shape)} "
            "must both have B entries"
        )
    lo, hi = UNKNOWN_RADIUS_RANGE_M
    fallback = (lengths * UNKNOWN_RADIUS_FRACTION).clamp(lo, hi)
    known = [_radius_for(n) for n in bone_names]
    is_known = torch.tensor([r is not None for r in known], device=lengths.device)
    values = torch.tensor([r or 0.0 for r in known], dtype=lengths.dtype, device=lengths.device)
    return torch.where(is_known, values, fallback)


def _min_sq_distance(d: Tensor, a: Tensor, e: Tensor) -> Tensor:
    """Squared distance between rays ``s d`` from the origin (s >= 0, |d| = 1) and segments
    ``a + u e`` (u in [0, 1]): d, a, e (..., 3) broadcastable -> (...)."""
    ee = (e * e).sum(-1)
    de = (d * e).sum(-1)
    wd = -(d * a).sum(-1)  # w = origin - a
    we = -(a * e).sum(-1)
    ww = (a * a).sum(-1)

    def ray_to_point(ww_: Tensor, wd_: Tensor) -> Tensor:  # min over s >= 0 of |w + s d|^2
        s = (-wd_).clamp_min(0)
        return ww_ + s * (s + 2 * wd_)

    at_a = ray_to_point(ww, wd)  # edge u = 0
    at_b = ray_to_point(ww - 2 * we + ee, wd - de)  # edge u = 1: w_b = w - e
    u0 = (we / ee.clamp_min(torch.finfo(ee.dtype).tiny)).clamp(0, 1)
    at_origin = ww + u0 * (u0 * ee - 2 * we)  # edge s = 0
    den = ee - de * de  # interior: solve the 2x2 normal equations
    ok = den > 1e-9 * ee
    u = (we - de * wd) / torch.where(ok, den, torch.ones_like(den))
    s = u * de - wd
    inside = ww + s * s + u * u * ee + 2 * s * wd - 2 * u * we - 2 * s * u * de
    ok = ok & (u >= 0) & (u <= 1) & (s >= 0)
    inside = torch.where(ok, inside, torch.full_like(inside, math.inf))
    return torch.minimum(torch.minimum(at_a, at_b), torch.minimum(at_origin, inside))


def _pixel_boxes(cam: Camera, a: Tensor, b: Tensor, radii: Tensor) -> Tensor:
    """Conservative pixel bounding boxes of capsules: a, b (B, 3) world, radii (B,) ->
    (B, 4) = (u_min, v_min, u_max, v_max); the whole image if the capsule reaches behind the
    near plane, an empty box if it lies entirely behind the camera."""
    pa, pb = cam.world_to_camera(a), cam.world_to_camera(b)
    lo = torch.minimum(pa, pb) - radii[:, None]
    hi = torch.maximum(pa, pb) + radii[:, None]
    corners = torch.stack(
        [torch.where(torch.tensor(bits, device=a.device), hi, lo) for bits in _CORNER_BITS], dim=1
    )  # (B, 8, 3): the camera-frame box around the capsule
    front = lo[:, 2] > _NEAR
    z = torch.where(front[:, None], corners[..., 2], torch.ones_like(corners[..., 2]))
    uv = (corners[..., :2] / z[..., None]) @ cam.K[:2, :2].T + cam.K[:2, 2]  # (B, 8, 2)
    box = torch.cat([uv.amin(dim=1), uv.amax(dim=1)], dim=-1)
    image = torch.tensor([0.0, 0.0, cam.width, cam.height], dtype=a.dtype, device=a.device)
    empty = torch.tensor([1.0, 1.0, -1.0, -1.0], dtype=a.dtype, device=a.device)
    box = torch.where(front[:, None], box, image)
    return torch.where((hi[:, 2] <= 0)[:, None], empty, box)


_CORNER_BITS = [(x, y, z) for x in (False, True) for y in (False, True) for z in (False, True)]
_NEAR = 1e-3  # metres: capsules closer than this to the camera plane are not culled


def render_silhouettes(joints: Tensor, bones: Tensor, radii: Tensor, camera: Camera, downsample: int = 1) -> Tensor:
    """Capsule-model silhouettes: joints (T, J, 3) world, bones (B, 2) long (start, end joint),
    radii (B,) metres -> masks (T, H, W) bool with H, W = camera.height, camera.width.

    A pixel is foreground if the ray through its centre passes within the radius of a bone's
    segment, in front of the camera. With ``downsample = k`` only the centre of every k x k block
    is evaluated and copied to the block (nearest upsampling). The image is cut into tiles and
    each bone is only tested against the tiles its projected bounding box touches, in chunks of
    about 2^20 pixel-bone pairs, so memory stays bounded at any image size.
    Not differentiable (boolean output); computed in joints' dtype on joints' device.
    """
    joints = torch.as_tensor(joints)
    if not joints.is_floating_point() or joints.ndim != 3 or joints.shape[-1] != 3:
        raise InputError(
            f"render_silhouettes: joints must be floating (T, J, 3), got {joints.dtype} {tuple(joints.shape)}"
        )
    T, J, _ = joints.shape
    bones = torch.as_tensor(bones, device=joints.device)
    if bones.ndim != 2 or bones.shape[-1] != 2 or bones.is_floating_point() or bones.dtype == torch.bool:
        raise InputError(f"render_silhouettes: bones must be (B, 2) integers, got {bones.dtype} {tuple(bones.shape)}")
    if bool(((bones < 0) | (bones >= J)).any()):
        raise InputError(f"render_silhouettes: bones has joint indices outside [0, {J})")
    B = bones.shape[0]
    radii = torch.as_tensor(radii).to(dtype=joints.dtype, device=joints.device)
    if tuple(radii.shape) != (B,) or not bool((radii > 0).all()):
        raise InputError(f"render_silhouettes: radii must be (B,) = ({B},) positive values, got {tuple(radii.shape)}")
    if isinstance(downsample, bool) or not isinstance(downsample, int) or downsample < 1:
        raise InputError(f"render_silhouettes: downsample must be an integer >= 1, got {downsample!r}")
    if not bool(torch.isfinite(joints).all()):
        raise InputError("render_silhouettes: joints has non-finite values")

    H, W, k, S = camera.height, camera.width, downsample, _TILE
    masks = torch.zeros(T, H, W, dtype=torch.bool, device=joints.device)
    if T == 0 or B == 0:
        return masks
    cam = camera.to(joints.device, joints.dtype)
    kw: dict[str, Any] = {"dtype": joints.dtype, "device": joints.device}
    h, w = -(-H // k), -(-W // k)  # evaluated grid
    ny, nx = -(-h // S), -(-w // S)  # tiles
    v = torch.arange(ny * S, **kw) * k + k / 2  # block centres; pixel (i, j) covers [i, i+1)
    u = torch.arange(nx * S, **kw) * k + k / 2
    pixels = torch.stack(torch.meshgrid(u, v, indexing="xy"), dim=-1)  # (ny*S, nx*S, 2)
    pixels = pixels.reshape(ny, S, nx, S, 2).transpose(1, 2).reshape(ny * nx, S * S, 2)
    _, dirs = cam.rays(pixels)  # (tiles, S*S, 3) unit, world frame, from the camera centre
    tile_v = v.reshape(ny, S)[:, [0, -1]]  # (ny, 2) first/last evaluated centre of each tile row
    tile_u = u.reshape(nx, S)[:, [0, -1]]
    chunk = max(1, _CHUNK_PAIRS // (S * S))
    centre = cam.center
    for t in range(T):
        a = joints[t, bones[:, 0]].detach()
        b = joints[t, bones[:, 1]].detach()
        box = _pixel_boxes(cam, a, b, radii)  # (B, 4)
        touch_v = (tile_v[:, None, 1] >= box[:, 1]) & (tile_v[:, None, 0] <= box[:, 3])  # (ny, B)
        touch_u = (tile_u[:, None, 1] >= box[:, 0]) & (tile_u[:, None, 0] <= box[:, 2])  # (nx, B)
        tile, bone = (touch_v[:, None] & touch_u[None]).reshape(ny * nx, B).nonzero(as_tuple=True)
        a, e = a - centre, b - a
        hits = torch.zeros(ny * nx, S * S, dtype=torch.int32, device=joints.device)
        for i in range(0, tile.shape[0], chunk):
            ti, bi = tile[i : i + chunk], bone[i : i + chunk]
            dist2 = _min_sq_distance(dirs[ti], a[bi, None], e[bi, None])  # (c, S*S)
            hits.index_add_(0, ti, (dist2 <= radii[bi, None] ** 2).to(torch.int32))
        grid = hits.reshape(ny, nx, S, S).transpose(1, 2).reshape(ny * S, nx * S)[:h, :w] > 0
        if k > 1:
            grid = grid.repeat_interleave(k, dim=0).repeat_interleave(k, dim=1)[:H, :W]
        masks[t] = grid
    return masks
