"""A subject's segment lengths from the sequence's 2D, given an estimate of the body's depth.

A segment of length L whose two end keypoints are seen d pixels apart at depth Z (the mean camera depth of
its two ends in the estimate) measures L * cos(a) = d * Z / f, where a is the segment's angle to the image
plane and f the focal length: d Z / f is at most L (up to the 2D noise) and reaches it in the frames where
the segment lies in the image plane. The estimate of L is a high quantile of d Z / f over the frames where
both ends are observed (left and right pooled for the paired segments): over a sequence in which each
segment passes near the image plane, it is near L; noise pushes it up, frames that never reach the plane
pull it down. Z comes from an estimate made with the template's lengths; a depth error of dZ changes L by
the factor dZ / Z.

That depth error is not small. The 2D fixes a body's size only over its depth: a template shorter in the limbs
than the person stands nearer the camera, and every length measured at its depth comes out short by the same
factor (5-10% on CMU clips; docs/notes/footage-history.md). A calibrated floor says where the depth is: a foot that
stands on it is where its camera ray meets the floor. `floor_depth_factor` measures how far along their rays the
estimate's standing feet must move to touch the floor, and the measurements take the depths times that factor.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ptrack.problem import Estimate, Problem

#: the quantile of d Z / f taken as the segment's length
QUANTILE = 0.9
#: fewest frames with both ends observed for a segment to be measured (else it keeps its template length)
MIN_FRAMES = 10

#: `floor_depth_factor`: frames whose lowest foot point is a standing foot, within this of the lowest over the clip
#: (metres, along up) ...
STANDING_BAND_M = 0.1
#: ... and whose camera ray to it descends at least this steeply to the floor (degrees): a ray nearly parallel to
#: the floor meets it anywhere
MIN_RAY_SLOPE_DEG = 3.0
#: the factor is kept within these bounds (a calibration far off would ask for more)
FACTOR_RANGE = (0.5, 2.0)


def floor_depth_factor(problem: Problem, est: Estimate, min_frames: int = MIN_FRAMES) -> float | None:
    """How much farther from the camera the estimate should stand for its feet to touch the problem's floor:
    for each frame whose lowest foot point (the floor's joints) lies within `STANDING_BAND_M` of the clip's lowest,
    the point's camera ray is followed to the floor's contact height (`Floor.height_m` + `clearance_m`, along +Y)
    and the ratio of the two distances from the camera taken; -> the median ratio (within `FACTOR_RANGE`), or None
    without a floor or with fewer than `min_frames` such frames."""
    floor = problem.floor
    if floor is None:
        return None
    cam = problem.observations.camera
    with torch.no_grad():
        index = torch.as_tensor(floor.joints, device=est.joints.device)
        feet = est.joints.detach().index_select(-2, index).double().cpu().numpy()  # (T, F, 3) model frame, +Y up
        centre = cam.center.detach().double().cpu().numpy()
    low = feet[np.arange(len(feet)), feet[..., 1].argmin(-1)]  # (T, 3) each frame's lowest foot point
    ray = low - centre
    contact = floor.height_m + floor.clearance_m
    down = -ray[:, 1] / np.linalg.norm(ray, axis=-1)
    ok = (low[:, 1] < low[:, 1].min() + STANDING_BAND_M) & (down > math.sin(math.radians(MIN_RAY_SLOPE_DEG)))
    ok &= np.isfinite(low).all(-1)
    if int(ok.sum()) < min_frames:
        return None
    # centre + s ray meets the contact height at s = (contact - centre_y) / ray_y; the estimate's point is s = 1
    factor = float(np.median((contact - centre[1]) / ray[ok, 1]))
    return float(np.clip(factor, *FACTOR_RANGE))


def _observed_at_depth(
    problem: Problem, est: Estimate, scale: float | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """-> depth (T, K) of each keypoint of `problem` in the camera frame at the poses of `est` (times `scale` when
    given: `floor_depth_factor`), the observed pixels (T, K, 2) and whether each is seen (T, K) bool (a positive
    depth included)."""
    obs, kps = problem.observations, problem.keypoints
    with torch.no_grad():
        z = obs.camera.world_to_camera(est.joints.detach().index_select(-2, kps.index(est.joints.device)))[..., 2]
    depth = z.double().cpu().numpy() * (1.0 if scale is None else scale)
    seen = (obs.confidence.detach().cpu().numpy() > 0) & (depth > 0)
    return depth, obs.keypoints.detach().double().cpu().numpy(), seen


def _sides(a: str, b: str, pos: dict[str, int]) -> list[tuple[int, int]]:
    """The keypoint index pairs of the segment (a, b): its own and, when "l_..." landmarks stand for both sides,
    the right side's; only the pairs whose two landmarks are among `pos` {landmark: keypoint index}."""
    pairs = [(a, b)]
    if (a.startswith("l_") or b.startswith("l_")) and not (a.startswith("r_") or b.startswith("r_")):
        pairs.append(("r_" + a[2:] if a.startswith("l_") else a, "r_" + b[2:] if b.startswith("l_") else b))
    return [(pos[pa], pos[pb]) for pa, pb in pairs if pa in pos and pb in pos]


def segment_lengths_from_2d(
    problem: Problem,
    est: Estimate,
    landmarks: tuple[str, ...],
    segments: dict[str, tuple[str, str]],
    quantile: float = QUANTILE,
    min_frames: int = MIN_FRAMES,
    scale: float | None = None,
) -> dict[str, tuple[float, int]]:
    """Each segment's length measured in the 2D (see the module docstring) -> {segment: (metres, frames used)},
    for the segments with at least `min_frames` frames. landmarks: (K,) the landmark of each keypoint of
    `problem`; segments: {name: (landmark a, landmark b)} with left landmarks ("l_...") standing for both
    sides; scale: the estimate's depths are taken times it (`floor_depth_factor`)."""
    depth, px, seen = _observed_at_depth(problem, est, scale)
    return _lengths(depth, px, seen, _focal(problem), landmarks, segments, quantile, min_frames)


def _focal(problem: Problem) -> float:
    """The camera's focal length, pixels (the mean of fx and fy)."""
    K = problem.observations.camera.K
    return float(K[0, 0] + K[1, 1]) / 2


def _lengths(
    depth: np.ndarray,
    px: np.ndarray,
    seen: np.ndarray,
    focal: float,
    landmarks: tuple[str, ...],
    segments: dict[str, tuple[str, str]],
    quantile: float,
    min_frames: int,
) -> dict[str, tuple[float, int]]:
    """`segment_lengths_from_2d` of `_observed_at_depth`'s arrays: depth (T, K), px (T, K, 2), seen (T, K)."""
    pos = {m: k for k, m in enumerate(landmarks)}
    out: dict[str, tuple[float, int]] = {}
    for name, (a, b) in segments.items():
        samples = []
        for i, j in _sides(a, b, pos):
            ok = seen[:, i] & seen[:, j]
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
    scale: float | None = None,
) -> dict[str, float]:
    """The standard deviation (metres) of each segment's `segment_lengths_from_2d` over a circular moving-block
    bootstrap of the sequence's frames (blocks of `block_s` seconds, `draws` resamples, seeded): how much the length
    would change had other stretches of the same motion been filmed. It is the sampling spread only: a depth error
    of `est` (the factor dZ / Z of the module docstring) and the quantile's own bias are not in it; on a clip shorter
    than MIN_BLOCKS blocks the blocks are shorter, and the spread then understated. scale: as in
    `segment_lengths_from_2d`. -> {segment: std}, for the segments measured in at least two resamples."""
    obs = problem.observations
    T = obs.keypoints.shape[0]
    dt = float(torch.diff(obs.times.double()).median()) if T > 1 else 1.0
    block = max(1, min(round(block_s / dt), T // MIN_BLOCKS))  # a clip too short for such blocks: shorter ones
    rng = np.random.default_rng(seed)
    depth, px, seen = _observed_at_depth(problem, est, scale)  # once: a resample only picks frames of them
    focal, present = _focal(problem), obs.confidence.detach().cpu().numpy() > 0
    found: dict[str, list[float]] = {}
    for _ in range(draws):
        starts = rng.integers(0, T, size=-(-T // block))
        idx = ((starts[:, None] + np.arange(block)) % T).reshape(-1)[:T]
        if not bool(present[idx].any()):
            continue  # only frames without the person drawn
        measured = _lengths(depth[idx], px[idx], seen[idx], focal, landmarks, segments, quantile, min_frames)
        for name, (length, _) in measured.items():
            found.setdefault(name, []).append(length)
    return {n: float(np.std(v, ddof=1)) for n, v in found.items() if len(v) > 1}


#: fewest samples (frames x sides) for a segment of a static trial to be measured
STATIC_MIN_SAMPLES = 3


def vertical_segment_lengths(
    problem: Problem,
    est: Estimate,
    landmarks: tuple[str, ...],
    segments: dict[str, tuple[str, str]],
    min_samples: int = STATIC_MIN_SAMPLES,
) -> dict[str, tuple[float, float, int]]:
    """The lengths of segments in the upright plane that faces the camera: a person standing still, legs and
    trunk upright (+Y of the model frame), a camera that may look down on them and roll.

    The plane is spanned by the up axis u and the horizontal direction h across the image (the camera's x axis
    made orthogonal to u). Per frame, the segment's two end keypoints are taken on their camera rays,
    x_a = alpha r_a and x_b = beta r_b (r = K^-1 (u, v, 1), depth 1), with x_b - x_a = s u + w h: the ray geometry
    fixes alpha, beta, s and w up to one scale (the null vector of [r_a, u, h, -r_b]), which the mean depth of
    the two ends in `est` sets, and the length is |(s, w)|. Unlike the 2D length times depth / f, a segment seen
    shortened by the camera's tilt is measured at its length; what is not seen (a lean towards the camera) is
    not. The scale, the depth, is the only thing taken from `est`. The median over the frames is the estimate,
    left and right pooled for the paired segments (as in `segment_lengths_from_2d`).

    -> {segment: (metres, spread metres, samples)} for the segments with at least `min_samples` samples;
    spread: half the interquartile range of the samples. landmarks: (K,) the landmark of each keypoint of
    `problem`; segments: {name: (landmark a, landmark b)}, "l_..." landmarks standing for both sides."""
    cam = problem.observations.camera
    depth, px, seen = _observed_at_depth(problem, est)
    k_inv = np.linalg.inv(cam.K.detach().double().cpu().numpy())
    rays = np.concatenate([px, np.ones_like(px[..., :1])], axis=-1) @ k_inv.T  # (T, K, 3), depth 1
    up = cam.R.detach().double().cpu().numpy()[:, 1]  # the model's +Y in the camera frame
    across = np.array([1.0, 0.0, 0.0]) - up[0] * up
    across /= np.linalg.norm(across)  # a camera looking straight down has no such direction: taken as its x
    pos = {m: k for k, m in enumerate(landmarks)}
    out: dict[str, tuple[float, float, int]] = {}
    for name, (a, b) in segments.items():
        values = []
        for i, j in _sides(a, b, pos):
            for t in np.flatnonzero(seen[:, i] & seen[:, j]):
                m = np.stack([rays[t, i], up, across, -rays[t, j]], axis=1)  # (3, 4): alpha r_a + s u + w h = beta r_b
                alpha, s, w, beta = np.linalg.svd(m)[2][-1]
                if alpha < 0:
                    alpha, s, w, beta = -alpha, -s, -w, -beta
                if alpha <= 0 or beta <= 0:  # no such pair of points in front of the camera
                    continue
                scale = (depth[t, i] + depth[t, j]) / (alpha + beta)  # rays have depth 1
                values.append(math.hypot(s, w) * scale)
        if len(values) >= min_samples:
            q1, med, q3 = np.quantile(values, [0.25, 0.5, 0.75])
            out[name] = (float(med), float(q3 - q1) / 2, len(values))
    return out
