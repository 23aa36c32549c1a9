"""Point correspondences between consecutive images (Urtasun, Fleet & Fua 2004, section 4.3).

A pair (p1 in image t-1, p2 in image t) says: the body point seen at p1 in image t-1 is seen at p2 in
image t. Its residual backprojects p1 onto the capsule ("flesh") model at frame t-1 (the nearest
intersection of p1's line of sight with the capsules of `ptrack.observe.silhouette`), attaches the hit to the
hit capsule's segment, moves it with the pose of frame t and reprojects it: residual = reprojection -
p2, pixels. The point is attached to the frame of the capsule's end joint y (a bone's segment, from
its parent joint to y, is rigid in y's frame: origin p_y, axes y's world rotation G_y), as
body-fixed coordinates `local = G_y^T (x - p_y)`; its position at any pose is `p_y + G_y local`, with
the geometric Jacobian of `ptrack.optim.jacobians.point_jacobian`. The backprojection (ray_capsule_hit,
backproject, backproject_rays, anchor_points) lives in `ptrack.observe.backprojection`, below the costs: the
simulated correspondences use it too.

    reprojection_rows(camera, points (..., 3), d_points (..., 3, Q), target (..., 2), weight (...))
        -> residuals (..., 2), jacobian (..., 2, Q)

The backprojection is not differentiated: a tracker backprojects once with its current estimate of
frame t-1 and then fits frame t's pose to the pairs (as ICP fixes its matches per step).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ptrack.observe.camera import Camera


def reprojection_rows(
    camera: Camera, points: Tensor, d_points: Tensor, target: Tensor, weight: Tensor
) -> tuple[Tensor, Tensor]:
    """Whitened residuals and Jacobian of points reprojected against their second image points.

    points (..., 3) world and their derivative d_points (..., 3, Q) w.r.t. any Q parameters; target (..., 2)
    pixels (p2); weight (...) (sqrt of the pair's weight / sigma_px; 0 drops a pair) -> residuals
    (proj - target) * weight (..., 2), jacobian (..., 2, Q).
    """
    proj, dpix = camera.project_jacobian(points)
    w = weight[..., None]
    r = (proj.pixels - target) * w
    r = torch.where(w > 0, r, torch.zeros_like(r))  # a dropped pair's target may hold anything
    return r, (dpix @ d_points) * w[..., None]
