"""`subject.static`: the subject's segment lengths from a static standing trial, before the main trial.

The static trial is a keypoint file (or folder) of the same person standing still, filmed by the same camera
(`camera.file` / `camera.name`) and read like `observations.file` (same format detection, same keypoint set).
It is prepared as a footage run of its own (`ptrack.pipeline.run.prepare_real`: the person, the lens
distortion, the template skeleton scaled to `subject.height_m`) and fitted frame by frame (`method: frame`
from the rest pose under several headings). The legs' and the trunk's lengths are then measured on the 2D
as segments in the upright plane that faces the camera (`ptrack.estimators.lengths.vertical_segment_lengths`:
the two ends on their camera rays, joined in that plane, at the fit's depth; a camera looking down on the
person does not shorten them), the median over the frames, left and right pooled. The up axis is the
calibration's (or, without extrinsics, the camera's image-up: the camera taken as level).

The height's template is the prior. One camera cannot tell a large person far away from a small one near:
the fit's depth, which sets the scale of every measured length, comes from a body of the template's size, and
the lengths measured at it are only as right as that depth (on the Pose2Sim static trial the fit stands the
person 1-5% too near). So the static trial gives the proportions and the height the size: the measured
lengths are scaled by one common factor that gives the skeleton the template's stature (`stature_scale`:
the standing height of the rest pose). Without it, legs measured shorter than the template's make a shorter
person, whom the main trial then places nearer the camera (on Pose2Sim: 6-9% too near). A measured length
outside `PRIOR_RANGE` times the template's is taken to be a detection fault and held at that bound (with a
warning). The main trial is then prepared with those lengths (`ptrack.body.subject.rescale_segments`); the
segments not measured keep their fractions of the height.
"""

from __future__ import annotations

import dataclasses
import logging
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from ptrack.errors import InputError

if TYPE_CHECKING:
    from ptrack.body.skeleton import Skeleton
    from ptrack.pipeline.config import RunConfig
    from ptrack.pipeline.run import Prepared

log = logging.getLogger(__name__)

#: the segments measured on a static standing trial (`ptrack.body.subject.SEGMENTS`): those that stand
#: upright whichever way the person faces. Not the arms, which hang forward or out by 20-40 degrees in a
#: relaxed stance, partly towards the camera (on the Pose2Sim static trial they measure 12-20% short), nor the
#: widths (hips, shoulders), which one camera sees at their length only when the person faces it (there the
#: person stands sideways to both cameras: 20-35% short)
STATIC_SEGMENTS = ("thigh", "shank", "trunk")
#: a measured length is held within these factors of the template's (the height's proportions)
PRIOR_RANGE = (0.75, 1.33)
#: headings of the rest pose tried on the static trial's first frame (`frame.init_yaws`)
STATIC_YAWS = 8


def static_segment_lengths(cfg: RunConfig, keypoint_set: str | None = None) -> dict[str, dict]:
    """The segment lengths of `cfg.subject.static` (see the module docstring) -> {segment: {length_m (the length
    used), measured_m (as measured), spread_m (half the interquartile range of the samples), samples (frames x
    sides), template_m (the height's), stature_scale (the common factor from measured to used)}}.

    InputError naming the static trial when it cannot be read, holds nobody, holds another keypoint set than
    `keypoint_set` (the main trial's; None: any) or too little to measure."""
    from ptrack.body.subject import SEGMENTS, segment_lengths
    from ptrack.estimators import ESTIMATORS
    from ptrack.estimators.lengths import vertical_segment_lengths
    from ptrack.pipeline.config import KeyframesConfig
    from ptrack.pipeline.run import prepare_real

    path = cfg.subject.static
    assert path is not None
    o = cfg.observations
    scfg = dataclasses.replace(
        cfg,
        method="frame",
        observations=dataclasses.replace(o, file=path, video=None, person=None),
        data=dataclasses.replace(cfg.data, start=0, stop=None),
        keyframes=KeyframesConfig(),
        subject=dataclasses.replace(cfg.subject, static=None, lengths="template"),
        frame=dataclasses.replace(cfg.frame, init="rest", init_yaws=max(cfg.frame.init_yaws, STATIC_YAWS)),
    )
    try:
        with tempfile.TemporaryDirectory(prefix="ptrack-static-") as tmp:
            prep = prepare_real(scfg, Path(tmp))
    except InputError as e:
        raise InputError(f"subject.static {path}: {e}") from None
    assert prep.footage is not None
    if keypoint_set is not None and prep.footage.keypoint_set != keypoint_set:
        raise InputError(
            f"subject.static {path} holds {prep.footage.keypoint_set} keypoints but the observations are "
            f"{keypoint_set}: the static trial must come from the same detector"
        )
    gen = torch.Generator(device="cpu").manual_seed(cfg.seed + 1)
    est = ESTIMATORS["frame"](prep.problem, scfg, gen)
    segments = {n: (a, b) for n, (a, b, _) in SEGMENTS.items() if n in STATIC_SEGMENTS}
    measured = vertical_segment_lengths(prep.problem, est, prep.footage.landmarks, segments)
    if not measured:
        raise InputError(f"subject.static {path}: no segment is seen in enough frames to measure")
    template = segment_lengths(prep.full)
    lo, hi = PRIOR_RANGE
    held = {}
    for name, (length, _, _) in measured.items():
        held[name] = min(max(length, lo * template[name]), hi * template[name])
        if held[name] != length:
            log.warning(
                "subject.static: the %s measures %.3f m, %.0f%% of the template's %.3f m; held at %.3f m",
                name,
                length,
                100 * length / template[name],
                template[name],
                held[name],
            )
    k = stature_scale(prep.problem.skeleton, prep.footage.height_m, held)
    out = {}
    for name, (length, spread, samples) in measured.items():
        out[name] = {
            "length_m": k * held[name],
            "measured_m": length,
            "spread_m": spread,
            "samples": samples,
            "template_m": template[name],
            "stature_scale": k,
        }
    return out


def stature(skeleton: Skeleton) -> float:
    """The rest pose's standing height: the highest joint above the lowest, metres."""
    y = skeleton.forward_kinematics(torch.zeros(skeleton.num_dofs, dtype=torch.float64))[:, 1]
    return float(y.max() - y.min())


def stature_scale(skeleton: Skeleton, height_m: float, lengths: dict[str, float], steps: int = 3) -> float:
    """The factor k that gives `skeleton` (the template scaled to `height_m`), with the segments of `lengths`
    at k times those lengths (`rescale_segments`), the template's stature: the proportions from the static
    trial, the size from the height. A few fixed-point steps (the measured segments stand nearly upright, so
    the stature changes by about their summed change)."""
    from ptrack.body.subject import rescale_segments

    want, total, k = stature(skeleton), sum(lengths.values()), 1.0
    for _ in range(steps):
        got = stature(rescale_segments(skeleton, height_m, {n: k * v for n, v in lengths.items()}))
        k *= 1.0 + (want - got) / (k * total)
    return k


def apply_static(prep: Prepared, cfg: RunConfig) -> Prepared:
    """`prep` (a footage run) with its model's segments at the lengths of the static trial `cfg.subject.static`,
    the footage record holding them (metrics.json `footage.segments_measured`)."""
    from ptrack.pipeline.run import with_segments

    assert prep.footage is not None
    lengths = static_segment_lengths(cfg, prep.footage.keypoint_set)
    log.info(
        "segment lengths from the static trial: %s", ", ".join(f"{n} {v['length_m']:.3f} m" for n, v in lengths.items())
    )
    return with_segments(prep, {n: {**v, "source": "static"} for n, v in lengths.items()})
