"""A subject's segment lengths from the sequence's 2D, given an estimate of the body's depth.

A segment of length L whose two end keypoints are seen d pixels apart at depth Z (the mean camera depth of
its two ends in the estimate) measures L * cos(a) = d * Z / f, where a is the segment's angle to the image
plane and f the focal length: d Z / f is at most L (up to the 2D noise) and reaches it in the frames where
the segment lies in the image plane. The estimate of L is a high quantile of d Z / f over the frames where
both ends are observed (left and right pooled for the paired segments): over a sequence in which each
segment passes near the image plane, it is near L; noise pushes it up, frames that never reach the plane
pull it down. Z comes from an estimate made with the template's lengths; a depth error of dZ changes L by
the factor dZ / Z (1-3% at 3-5 m).
"""

from __future__ import annotations

import numpy as np
import torch

from ptrack.problem import Estimate, Problem

#: the quantile of d Z / f taken as the segment's length
QUANTILE = 0.9
#: fewest frames with both ends observed for a segment to be measured (else it keeps its template length)
MIN_FRAMES = 10


def segment_lengths_from_2d(
    problem: Problem,
    est: Estimate,
    landmarks: tuple[str, ...],
    segments: dict[str, tuple[str, str]],
    quantile: float = QUANTILE,
    min_frames: int = MIN_FRAMES,
) -> dict[str, tuple[float, int]]:
    """Each segment's length measured in the 2D (see the module docstring) -> {segment: (metres, frames used)},
    for the segments with at least `min_frames` frames. landmarks: (K,) the landmark of each keypoint of
    `problem`; segments: {name: (landmark a, landmark b)} with left landmarks ("l_...") standing for both
    sides."""
    obs, kps = problem.observations, problem.keypoints
    cam = obs.camera
    with torch.no_grad():
        z = cam.world_to_camera(est.joints.detach().index_select(-2, kps.index(est.joints.device)))[..., 2]
    depth = z.double().cpu().numpy()  # (T, K)
    px = obs.keypoints.detach().double().cpu().numpy()
    seen = obs.confidence.detach().cpu().numpy() > 0
    focal = float(cam.K[0, 0] + cam.K[1, 1]) / 2
    pos = {m: k for k, m in enumerate(landmarks)}
    out: dict[str, tuple[float, int]] = {}
    for name, (a, b) in segments.items():
        pairs = [(a, b)]
        if (a.startswith("l_") or b.startswith("l_")) and not (a.startswith("r_") or b.startswith("r_")):
            pairs.append(tuple("r_" + m[2:] if m.startswith("l_") else m for m in (a, b)))  # type: ignore[arg-type]
        samples = []
        for pa, pb in pairs:
            if pa not in pos or pb not in pos:
                continue
            i, j = pos[pa], pos[pb]
            ok = seen[:, i] & seen[:, j] & (depth[:, i] > 0) & (depth[:, j] > 0)
            d = np.linalg.norm(px[ok, i] - px[ok, j], axis=-1)
            samples.append(d * (depth[ok, i] + depth[ok, j]) / (2 * focal))
        values = np.concatenate(samples) if samples else np.zeros(0)
        if len(values) >= min_frames:
            out[name] = (float(np.quantile(values, quantile)), len(values))
    return out
