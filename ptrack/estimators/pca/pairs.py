"""The golf tracker's correspondences (`method: pca`, section 4.3): per window, each pair's p1 backprojected onto
the capsule model of the frame before its frame (`start_pairs`, `window_pairs`), as body-fixed points seen at p2
(`WindowPairs`), and the moved points of a whole trajectory (`correspondence_points`). Shapes: f frames of a
window, P pairs per frame, J joints."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ptrack.estimators.pca.poses import body_poses
from ptrack.estimators.pca.setup import Setup
from ptrack.observe.backprojection import Anchors, anchor_points, backproject_rays


@dataclass(frozen=True)
class WindowPairs:
    """The correspondences of a window of f frames, P per frame: body-fixed points (anchors (f, P)) to be
    seen at target (f, P, 2) pixels in their frame, with confidence (f, P) (the pair's weight, 0 for padding and
    pairs whose p1 missed the model): a `ptrack.costs.Reprojection` of the points."""

    anchors: Anchors
    target: Tensor
    confidence: Tensor


@dataclass(frozen=True)
class StartBody:
    """A window's body poses at its starting state, computed before its solve for the backprojection and kept
    for the solve's first linearisation (the LM starts there): key (1, m + f) the state's alpha and mu; q
    (1, f, D) and dq (1, f, D, m + f) of `body_poses`; joints (1, f, J, 3) and world rotations (1, f, J, 3, 3) of
    the skeleton's FK of q."""

    key: Tensor
    q: Tensor
    dq: Tensor
    joints: Tensor
    rotations: Tensor


def _world_frames(xb: Tensor, rb: Tensor, rot: Tensor, trans: Tensor) -> tuple[Tensor, Tensor]:
    """World joints (k, J, 3) and joint rotations (k, J, 3, 3) of k frames' body FK (joints xb (k, J, 3),
    rotations rb (k, J, 3, 3)) turned by root rotations rot (k, 3, 3) about the root and moved by trans (k, 3),
    as in `window_linearization`."""
    r0 = xb[:, :1]
    return trans[:, None] + r0 + (xb - r0) @ rot.mT, rot[:, None] @ rb


def start_pairs(
    s: Setup, frames: Tensor, a_start: Tensor, mu_start: Tensor, rot_start: Tensor, trans_start: Tensor, before
) -> tuple[WindowPairs | None, StartBody]:
    """The window's correspondences (`window_pairs`) backprojected on the frames before its frames: the final
    estimate of the frame before the window, then the window's frames but its last at the window's starting
    state (alpha a_start (m,), mu_start (f,), root rotations (f, 3, 3) and translations (f, 3)); and that
    state's body poses (`StartBody`), from one FK pass with the frame before. before: the estimate of the frame
    before the window (alpha (m,), mu (), rotation (3, 3), translation (3,)), None for a window at frame 0."""
    f = frames.shape[0]
    q, dq = body_poses(s, a_start[None], mu_start[None])  # (1, f, D), (1, f, D, m + f)
    body, rot, trans = q[0], rot_start, trans_start
    if before is not None:
        a_b, mu_b, rot_b, trans_b = before
        q_b, _ = body_poses(s, a_b[None], mu_b.reshape(1, 1))
        body, rot, trans = torch.cat([q_b[0], body]), torch.cat([rot_b[None], rot]), torch.cat([trans_b[None], trans])
    xb, rb = s.problem.skeleton.forward_kinematics(body, rotations=True)  # (f (+ 1), J, 3), (f (+ 1), J, 3, 3)
    start = StartBody(torch.cat([a_start, mu_start])[None], q, dq, xb[-f:][None], rb[-f:][None])
    # frame 0 has no pairs: any pose stands before it
    prev = (
        torch.arange(f, device=frames.device)
        if before is not None
        else (torch.arange(f, device=frames.device) - 1).clamp_min(0)
    )
    x_prev, r_prev = _world_frames(xb[prev], rb[prev], rot[prev], trans[prev])
    return window_pairs(s, frames, x_prev, r_prev), start


def _backproject(s: Setup, rays: Tensor, joints: Tensor, rotations: Tensor) -> Anchors:
    """Anchors (k, P) of the pixels p1 whose rays (k, P, 3) are given (`Setup.corr_rays`) on the capsule model of
    poses joints (k, J, 3), rotations (k, J, 3, 3)."""
    bones = torch.as_tensor(s.bones, dtype=torch.long, device=joints.device)
    cam = s.problem.observations.camera
    return backproject_rays(cam.center, rays, joints[:, None], rotations[:, None], bones, s.radii)


def window_pairs(s: Setup, frames: Tensor, joints_prev: Tensor, rotations_prev: Tensor) -> WindowPairs | None:
    """The correspondences whose second frame is in the window `frames` (f,), backprojected on the poses of the
    frames before them: joints_prev (f, J, 3), rotations_prev (f, J, 3, 3) (anything for frame 0, which has no
    pairs). None when the run has no correspondences."""
    if s.corr is None or s.corr_rays is None:
        return None
    _, p2, w = (x[frames] for x in s.corr)
    anchors = _backproject(s, s.corr_rays[frames], joints_prev, rotations_prev)
    keep = anchors.valid & (anchors.clearance >= s.cfg.pca.correspondence_margin_m)
    return WindowPairs(anchors, p2, torch.where(keep, w, torch.zeros_like(w)))


def correspondence_points(s: Setup, joints: Tensor, rotations: Tensor) -> tuple[Tensor, Tensor] | None:
    """Per frame t and pair, the body point of p1 (backprojected at frame t-1) moved with frame t, for a
    trajectory's world joints (T, J, 3) and rotations (T, J, 3, 3) -> points (T, P, 3) and their confidence
    (T, P) (the pair's weight; 0 at frame 0 and where p1 missed the model). None without correspondences."""
    if s.corr is None or s.corr_rays is None:
        return None
    _, _, w = s.corr
    prev = (torch.arange(joints.shape[0], device=joints.device) - 1).clamp_min(0)
    anchors = _backproject(s, s.corr_rays, joints[prev], rotations[prev])
    x = anchor_points(anchors, joints[:, None], rotations[:, None])
    return x, torch.where(anchors.valid, w, torch.zeros_like(w))
