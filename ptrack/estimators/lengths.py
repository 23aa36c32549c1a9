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

import dataclasses

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


#: `segment_length_spread`'s moving-block bootstrap: blocks of this many seconds (neighbouring frames measure nearly
#: the same, so resampling single frames would understate the spread), at least this many blocks in the clip (fewer
#: would draw the same frames in every resample), and this many resamples
BLOCK_S, MIN_BLOCKS, DRAWS = 0.5, 4, 200


def segment_length_spread(
    problem: Problem,
    est: Estimate,
    landmarks: tuple[str, ...],
    segments: dict[str, tuple[str, str]],
    quantile: float = QUANTILE,
    min_frames: int = MIN_FRAMES,
    block_s: float = BLOCK_S,
    draws: int = DRAWS,
    seed: int = 0,
) -> dict[str, float]:
    """The standard deviation (metres) of each segment's `segment_lengths_from_2d` over a circular moving-block
    bootstrap of the sequence's frames (blocks of `block_s` seconds, `draws` resamples, seeded): how much the length
    would change had other stretches of the same motion been filmed. It is the sampling spread only: a depth error
    of `est` (the factor dZ / Z of the module docstring) and the quantile's own bias are not in it; on a clip shorter
    than MIN_BLOCKS blocks the blocks are shorter, and the spread then understated.
    -> {segment: std}, for the segments measured in at least two resamples."""
    obs = problem.observations
    T = obs.keypoints.shape[0]
    dt = float(torch.diff(obs.times.double()).median()) if T > 1 else 1.0
    block = max(1, min(round(block_s / dt), T // MIN_BLOCKS))  # a clip too short for such blocks: shorter ones
    rng = np.random.default_rng(seed)
    found: dict[str, list[float]] = {}
    for _ in range(draws):
        starts = rng.integers(0, T, size=-(-T // block))
        idx = torch.as_tensor(((starts[:, None] + np.arange(block)) % T).reshape(-1)[:T], device=obs.keypoints.device)
        confidence = obs.confidence.index_select(0, idx)
        if not bool((confidence > 0).any()):
            continue  # only frames without the person drawn
        sample = dataclasses.replace(obs, keypoints=obs.keypoints.index_select(0, idx), confidence=confidence)
        measured = segment_lengths_from_2d(
            dataclasses.replace(problem, observations=sample),
            est._replace(joints=est.joints.detach().index_select(0, idx.to(est.joints.device))),
            landmarks,
            segments,
            quantile,
            min_frames,
        )
        for name, (length, _) in measured.items():
            found.setdefault(name, []).append(length)
    return {n: float(np.std(v, ddof=1)) for n, v in found.items() if len(v) > 1}
