"""Lines of sight onto the capsule ("flesh") model: which body point a pixel sees.

A pixel's line of sight meets the capsules of `ptrack.observe.silhouette` (the nearest intersection);
the hit is attached to the hit capsule's segment as body-fixed coordinates in the frame of the
capsule's end joint y (a bone's segment, from its parent joint to y, is rigid in y's frame: origin p_y,
axes y's world rotation G_y): `local = G_y^T (x - p_y)`; its position at any pose is `p_y + G_y local`.
Used by the point correspondences (`ptrack.observe.correspondences`: simulation) and the correspondence
term (`ptrack.costs.correspondence`, the pca tracker).

    ray_capsule_hit(origin (3,), directions (..., 3), a, b (..., B, 3), radii (B,))
        -> CapsuleHit(point (..., 3), depth (...), bone (...), hit (...))
    backproject(camera, pixels (..., 2), joints (..., J, 3), rotations (..., J, 3, 3), bones (B, 2), radii (B,))
        -> Anchors(joint (...), local (..., 3), bone (...), valid (...))
    backproject_rays(origin (3,), directions (..., 3), joints, rotations, bones, radii) -> the same, given rays
    anchor_points(anchors, joints (..., J, 3), rotations (..., J, 3, 3)) -> (..., 3)

The backprojection is not differentiated: a tracker backprojects once with its current estimate of
frame t-1 and then fits frame t's pose to the pairs (as ICP fixes its matches per step).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from ptrack.observe.camera import Camera


class CapsuleHit(NamedTuple):
    """The nearest intersection of each ray with the capsule model (see `ray_capsule_hit`)."""

    point: Tensor  # (..., 3) world; the ray's origin where there is no hit
    depth: Tensor  # (...) distance from the origin along the unit ray; inf where there is no hit
    bone: Tensor  # (...) long, the capsule hit (0 where there is no hit)
    hit: Tensor  # (...) bool
    clearance: Tensor  # (...) metres: the smallest |line-of-sight-to-axis distance - radius| over the capsules


def ray_capsule_hit(origin: Tensor, directions: Tensor, a: Tensor, b: Tensor, radii: Tensor) -> CapsuleHit:
    """Nearest intersection of rays `origin + s d` (s > 0) with capsules of radius `radii` around segments a-b.

    origin (3,) world; directions (..., 3) unit; a, b (..., B, 3) segment ends (leading dims broadcast with
    the directions'); radii (B,) metres -> CapsuleHit (...). A capsule is the union of its two end balls and
    the cylinder between them, so the ray enters it at the nearest of its entries into the balls and into
    the cylinder's side within the segment (the cylinder's flat ends lie inside the balls). The nearest over
    all capsules is the visible surface point (front-facing, not hidden by another capsule). Origins inside
    a capsule are not handled (a camera is outside the body). Not differentiable by design.
    """
    d = directions[..., None, :]  # (..., 1, 3)
    r2 = radii.to(a).square()
    oa = origin - a
    ba = b - a
    baba, bard, baoa = (ba * ba).sum(-1), (ba * d).sum(-1), (ba * oa).sum(-1)
    rdoa, oaoa = (d * oa).sum(-1), (oa * oa).sum(-1)
    inf = torch.full_like(baba, torch.inf)
    # the cylinder's side: |(o + s d - a) x ba|^2 = r^2 |ba|^2, a quadratic A s^2 + 2 B s + C = 0 (times |ba|^2)
    qa = baba - bard * bard
    qb = baba * rdoa - baoa * bard
    qc = baba * oaoa - baoa * baoa - r2 * baba
    h = qb * qb - qa * qc
    side = (qa > 1e-12 * baba) & (h >= 0)  # a ray along the axis meets the balls first
    s_side = (-qb - h.clamp_min(0).sqrt()) / torch.where(side, qa, torch.ones_like(qa))
    y = baoa + s_side * bard  # |ba| times the hit's position along the segment
    s_side = torch.where(side & (y >= 0) & (y <= baba) & (s_side > 0), s_side, inf)
    best = s_side
    for centre in (a, b):
        oc = origin - centre
        bs = (d * oc).sum(-1)
        hs = bs * bs - ((oc * oc).sum(-1) - r2)
        s_ball = -bs - hs.clamp_min(0).sqrt()
        best = torch.minimum(best, torch.where((hs >= 0) & (s_ball > 0), s_ball, inf))
    depth, bone = best.min(-1)
    hit = torch.isfinite(depth)
    point = origin + torch.where(hit, depth, torch.zeros_like(depth))[..., None] * directions
    # distance from the line of sight to each segment: min over u in [0, 1] of |w + u ba|^2 - ((w + u ba).d)^2,
    # w = a - o, a quadratic in u
    u = ((baoa - rdoa * bard) / torch.where(qa > 0, qa, torch.ones_like(qa))).clamp(0, 1)
    line2 = oaoa - rdoa * rdoa + u * (2 * (rdoa * bard - baoa) + u * qa)
    clearance = (line2.clamp_min(0).sqrt() - radii.to(a)).abs().amin(-1)
    bone = torch.where(hit, bone, torch.zeros_like(bone))
    return CapsuleHit(point=point, depth=depth, bone=bone, hit=hit, clearance=clearance)


class Anchors(NamedTuple):
    """Body-fixed points: each in the frame of a skeleton joint (see the module docstring)."""

    joint: Tensor  # (...) long: the joint whose frame carries the point (the hit capsule's end joint)
    local: Tensor  # (..., 3) metres, in that joint's frame (origin p_y, axes G_y); 0 where not valid
    bone: Tensor  # (...) long: the capsule hit
    valid: Tensor  # (...) bool: the line of sight met the model
    clearance: Tensor  # (...) metres: how far the line of sight passes from every capsule's surface (CapsuleHit)


def _gather_joint(x: Tensor, joint: Tensor) -> Tensor:
    """x (..., J, *E) and joint (...) long (leading dims broadcast) -> x[..., joint, *E] (..., *E) per leading
    index."""
    extra = x.shape[joint.ndim + 1 :]
    x = x.expand(*torch.broadcast_shapes(x.shape[: joint.ndim], joint.shape), *x.shape[joint.ndim :])
    joint = joint.expand(x.shape[: joint.ndim])
    idx = joint.reshape(*joint.shape, 1, *([1] * len(extra))).expand(*joint.shape, 1, *extra)
    return x.gather(joint.ndim, idx).squeeze(joint.ndim)


def backproject(
    camera: Camera, pixels: Tensor, joints: Tensor, rotations: Tensor, bones: Tensor, radii: Tensor
) -> Anchors:
    """The body points seen at `pixels`: pixels (..., 2); joints (..., J, 3) and world rotations
    (..., J, 3, 3) of the pose they are seen in; bones (B, 2) long (parent, child) joint indices; radii (B,)
    metres -> Anchors (...). A pixel whose line of sight misses the model gives valid False."""
    _, directions = camera.rays(pixels.to(joints))
    return backproject_rays(camera.center, directions, joints, rotations, bones, radii)


def backproject_rays(
    origin: Tensor, directions: Tensor, joints: Tensor, rotations: Tensor, bones: Tensor, radii: Tensor
) -> Anchors:
    """`backproject` of lines of sight given as rays (the pixels' rays from `Camera.rays`, e.g. made once for
    pixels backprojected on many poses): origin (3,) the camera centre, directions (..., 3) unit; the rest
    as in `backproject` -> Anchors (...)."""
    bones = bones.to(joints.device)
    hit = ray_capsule_hit(
        origin.to(joints),
        directions.to(joints),
        joints.index_select(-2, bones[:, 0]),
        joints.index_select(-2, bones[:, 1]),
        radii.to(joints),
    )
    joint = bones[:, 1][hit.bone]
    p_y, g_y = _gather_joint(joints, joint), _gather_joint(rotations, joint)
    local = ((hit.point - p_y)[..., None, :] @ g_y)[..., 0, :]  # G_y^T (x - p_y)
    local = torch.where(hit.hit[..., None], local, torch.zeros_like(local))
    return Anchors(joint=joint, local=local, bone=hit.bone, valid=hit.hit, clearance=hit.clearance)


def anchor_points(anchors: Anchors, joints: Tensor, rotations: Tensor) -> Tensor:
    """World positions p_y + G_y local (..., 3) of anchors (...) at a pose: joints (..., J, 3), rotations
    (..., J, 3, 3)."""
    p_y, g_y = _gather_joint(joints, anchors.joint), _gather_joint(rotations, anchors.joint)
    return p_y + (g_y @ anchors.local[..., None])[..., 0]
