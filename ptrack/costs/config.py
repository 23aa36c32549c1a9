"""The config section of the cost terms the estimators share (`costs:`): reprojection, joint limits, temporal
prior. Composed into the run's config by `ptrack.pipeline.config`."""

from __future__ import annotations

from dataclasses import dataclass

from ptrack.settings import setting

#: `costs.swap_cost: null` on real footage whose detector exchanged the person's labels between two frames: the
#: price at which the exchanged reading is then taken (energy units; on MediaPipe's Pose2Sim cam02 and the COCO-17
#: clips with a stretch exchanged, 1-3 measured alike and 2 taken, docs/results.md#real-footage)
AUTO_SWAP_COST = 2.0


@dataclass(frozen=True)
class CostsConfig:
    """Cost terms shared by the estimators: reprojection, joint limits, temporal prior."""

    sigma_px: float = setting(2.0, "reprojection noise scale, pixels")
    loss: str = setting("cauchy", "robust kernel of the reprojection: l2, huber, cauchy, geman_mcclure")
    robust_scale: float = setting(3.0, "the robust kernel's scale, in sigmas")
    limits_weight: float = setting(1.0, "weight of the joint-limit barrier")
    limits_sigma: float = setting(0.02, "scale of the joint-limit barrier, radians")
    smooth_weight: float = setting(1.0, "weight of the temporal prior")
    smooth_sigma: float = setting(0.15, "velocity scale of the temporal prior, radians (or metres) per frame")
    swap_cost: float | None = setting(
        None,
        "the price (energy units) at which the kjs tracker reads a frame's detections with every left and right label "
        "exchanged, a 2D detector's mirrored-body fault (ptrack.costs.terms.SwapReprojection); 0: off; null: "
        "AUTO_SWAP_COST on real footage whose detector exchanged every label of the person between two frames "
        "(footage.mirror_switch_frames in metrics.json), else off",
    )
    floor_weight: float = setting(1.0, "weight of the floor contact (real footage with a known floor; 0: off)")
    floor_sigma_m: float = setting(0.03, "scale of the floor contact: the lowest foot point's height, metres")
    accel_sigma: float | None = setting(
        None, "acceleration scale of the temporal prior, radians (or metres) per frame^2; null = velocity only"
    )
