"""The golf tracker's start (`method: pca`, section 5.1): every frame's normalised time from the key postures of
the 2D wrist track (`initial_timing`), and the root of the first frame placed under several headings
(`place_root`)."""

from __future__ import annotations

import dataclasses
import math

import torch
from torch import Tensor

from ptrack.errors import InputError
from ptrack.estimators.pca.poses import body_poses, rotation_exp
from ptrack.estimators.pca.setup import Setup
from ptrack.estimators.pca.window import (
    Prediction,
    state_vector,
    window_bounds,
    window_linearization,
    window_silhouette,
)
from ptrack.motion.key_postures import detect_key_postures_2d, initial_times
from ptrack.optim.solvers import levenberg_marquardt


def initial_timing(s: Setup) -> tuple[Tensor, Tensor]:
    """Key-posture frames (P,) from the 2D wrists and every frame's normalised time (T,)."""
    obs, kps = s.problem.observations, s.problem.keypoints
    wrists = [i for i in (kps.find("l_wrist"), kps.find("r_wrist")) if i is not None]
    if not wrists:
        raise InputError(
            "method pca finds the key postures from the 2D wrists: the keypoint set needs "
            "l_wrist or r_wrist (config key 'model.keypoints')"
        )
    fps = 1.0 / obs.frame_interval
    rules = dataclasses.replace(s.cfg.motion, smooth_s=s.cfg.pca.key_smooth_s)
    keys = detect_key_postures_2d(
        obs.keypoints[:, wrists].detach().cpu(), fps, rules, valid=(obs.confidence[:, wrists] > 0).cpu()
    )
    mu = initial_times(keys, s.model.key_times, obs.num_frames)
    return keys, mu.to(dtype=obs.keypoints.dtype, device=obs.keypoints.device)


def place_root(s: Setup, mu0: Tensor) -> tuple[Tensor, Tensor]:
    """Root rotation (3, 3) and translation (3,) of the mean motion at normalised time mu0 that best explain
    the first frame showing two tracked joints: `pca.init_yaws` headings about world Y, each at the depth
    its 2D size gives, fitted rigidly to the tracked joints and the silhouette; the lowest energy wins."""
    obs = s.problem.observations
    sk, cam = s.problem.skeleton, obs.camera
    dtype, device = obs.keypoints.dtype, obs.keypoints.device
    m, y = s.m, s.cfg.pca.init_yaws
    seen_frames = (s.confidence > 0).sum(-1) >= 2
    if not bool(seen_frames.any()):
        raise InputError("method pca: no frame shows two of the tracked joints (pca.joints)")
    frame = int(torch.nonzero(seen_frames)[0, 0])
    seen = s.confidence[frame] > 0
    alpha = torch.zeros(m, dtype=dtype, device=device)
    yaw = torch.arange(y, dtype=dtype, device=device) * (2 * math.pi / y)
    ref, _ = rotation_exp(torch.stack([torch.zeros_like(yaw), yaw, torch.zeros_like(yaw)], -1))  # (Y, 3, 3)
    with torch.no_grad():
        q, _ = body_poses(s, alpha[None], mu0.reshape(1, 1))
        xb = sk.forward_kinematics(q)[0, 0]  # (J, 3)
        r0 = xb[:1]
        joints = ((xb - r0) @ ref.mT + r0)[:, s.tracked][:, seen]  # (Y, k, 3), root translation 0
        pix = s.observed[frame][seen]
        size3 = (joints - joints.mean(1, keepdim=True)).norm(dim=-1).mean(-1)  # (Y,)
        size2 = (pix - pix.mean(0)).norm(dim=-1).mean().clamp(min=1.0)
        depth = cam.K[0, 0] * size3 / size2
        origin, direction = cam.rays(pix.mean(0))
        target = origin + direction * (depth / (direction @ cam.R[2]))[:, None]
        trans = target - joints.mean(1)  # (Y, 3)
    x0 = torch.cat([state_vector(alpha, mu0.reshape(1), t[None]) for t in trans])
    lo, hi = window_bounds(s, 1, x0, alpha=alpha, mu=mu0.reshape(1))
    frames = torch.tensor([frame], device=device)
    lin = window_linearization(
        s, frames, ref[:, None], Prediction(None, None, None, rotation=False), window_silhouette(s, frames)
    )
    x, info = levenberg_marquardt(lin, x0, lo, hi, max_iter=30, tol=1e-8)
    best = int(torch.argmin(torch.where(torch.isfinite(info.cost), info.cost, math.inf)))
    rot = rotation_exp(x[best, m + 4 : m + 7])[0] @ ref[best]
    return rot, x[best, m + 1 : m + 4]
