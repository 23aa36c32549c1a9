"""The config section of the golf tracker (`pca:`) and its checks. Composed into the run's config by
`ptrack.pipeline.config`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from ptrack.costs.base import ROBUST_LOSSES
from ptrack.costs.config import CostsConfig
from ptrack.errors import InputError
from ptrack.motion.config import MotionConfig
from ptrack.settings import setting

#: what tracks the frames after the swing (`pca.after_swing`)
AFTER_SWING = ("batch", "frame", "hold")


@dataclass(frozen=True)
class PcaMethodConfig:
    """`method: pca`, the golf-swing tracker over a PCA motion model (Urtasun, Fleet & Fua 2004): per sliding
    window, the PCA weights (shared), a normalised time per frame and the root pose per frame (eq. 5), fitted by
    Levenberg-Marquardt to the tracked joints and the silhouettes (eq. 7). The model is `motion.model_file`
    (fitted from `motion.clips` on first use and cached there)."""

    window: int = setting(3, "f: frames per window")
    step: int = setting(1, "frames the window slides by (at most the window; 1: every frame is fitted f times)")
    iterations: int = setting(2, "Levenberg-Marquardt iterations per window; 0 = the start alone (the mean motion)")
    joints: tuple[str, ...] = setting(
        ("l_knee", "r_knee", "l_ankle", "r_ankle", "l_wrist", "r_wrist", "head"),
        "tracked keypoints (the keypoint set's names; on a detector's file also landmarks, head: its top or the nose): "
        "the paper's knees, ankles, wrists, head",
    )
    joint_weight: float = setting(1.0, "w of the joint projections (pixels / costs.sigma_px, robust by costs.loss)")
    silhouette_weight: float = setting(1.0, "w of the foreground term (section 4.1); 0 = joints only")
    correspondence_weight: float = setting(0.3, "w of each point correspondence (section 4.3); 0 = unused")
    correspondence_margin_m: float = setting(
        0.03, "a pair counts only where p1's line of sight passes this far (m) from the model's outline"
    )
    silhouette_sigma_m: float = setting(0.02, "a ray this far (metres) from the model counts as one sigma")
    silhouette_loss: str = setting(
        "l2", "robust loss of each foreground sample's ray distance: l2, huber, cauchy, geman_mcclure"
    )
    silhouette_scale: float = setting(1.0, "scale of pca.silhouette_loss, in silhouette sigmas")
    silhouette_radius_scale: float = setting(
        1.0,
        "the foreground term's capsule radii times this: a ray through the wider capsules counts as explained (for "
        "silhouettes of a body other than the model's; docs/results.md)",
    )
    silhouette_samples: int = setting(96, "foreground samples per frame (a regular grid, evenly thinned)")
    silhouette_step_px: int = setting(4, "grid step of the samples, pixels")
    root_sigma_m: float = setting(0.02, "prediction std of the root position, metres per frame")
    root_sigma_deg: float = setting(3.0, "prediction std of the root orientation, degrees per frame")
    time_sigma: float = setting(0.01, "prediction std of the normalised time per frame")
    timing_sigma: float | None = setting(0.015, "std of a prior holding each frame's time near the start's; null: none")
    alpha_sigma: float = setting(0.1, "prediction std of the PCA weights, in the model's per-component std")
    alpha_prior_weight: float = setting(1.0, "weight of the prior alpha ~ N(0, sigma^2) of the training swings")
    alpha_bound: float = setting(3.0, "|alpha_i| at most this many training stds (a box in the solver)")
    init_yaws: int = setting(8, "headings of the first frame's root placement tried (section 5.1)")
    key_smooth_s: float = setting(0.05, "Gaussian smoothing (std, s) of the 2D wrist track before the key postures")
    after_swing: str = setting(
        "batch",
        "frames after the swing's end (its last key posture in the 2D), from the swing's last pose: batch = the MAP "
        "trajectory (batch: section) with that pose a keyframe; frame = per-frame fits (frame: section); hold = the "
        "model's last pose held, the root tracked",
    )


class PcaRunConfig(Protocol):
    """What the golf tracker reads of the run's config: `ptrack.pipeline.config.RunConfig` is one (estimators sit
    below the pipeline and do not import it; its module checks that it fits)."""

    @property
    def pca(self) -> PcaMethodConfig: ...

    @property
    def costs(self) -> CostsConfig: ...

    @property
    def motion(self) -> MotionConfig: ...

    @property
    def name(self) -> str: ...


def validate_pca(p: PcaMethodConfig, keypoints: dict[str, str] | None = None, names: bool = True) -> None:
    """Value checks of the `pca:` section; with `names` (method pca), the tracked joints must be names of the
    keypoint set `keypoints` (None: the default H36M-17 set)."""
    from ptrack.body.keypoints import H36M17

    if p.window < 1:
        raise InputError(f"config key 'pca.window' must be >= 1, got {p.window}")
    if p.iterations < 0:
        raise InputError(f"config key 'pca.iterations' must be >= 0, got {p.iterations}")
    for key in ("step", "silhouette_samples", "silhouette_step_px", "init_yaws"):
        if getattr(p, key) < 1:
            raise InputError(f"config key 'pca.{key}' must be >= 1, got {getattr(p, key)}")
    for key in (
        "joint_weight",
        "silhouette_weight",
        "correspondence_weight",
        "correspondence_margin_m",
        "alpha_prior_weight",
    ):
        if not getattr(p, key) >= 0:
            raise InputError(f"config key 'pca.{key}' must be >= 0, got {getattr(p, key)}")
    if p.timing_sigma is not None and not p.timing_sigma > 0:
        raise InputError(f"config key 'pca.timing_sigma' must be positive or null, got {p.timing_sigma}")
    if p.silhouette_loss not in ROBUST_LOSSES:
        raise InputError(
            f"config key 'pca.silhouette_loss' must be one of {', '.join(ROBUST_LOSSES)}, got {p.silhouette_loss!r}"
        )
    if p.after_swing not in AFTER_SWING:
        raise InputError(f"config key 'pca.after_swing' must be one of {', '.join(AFTER_SWING)}, got {p.after_swing!r}")
    if p.key_smooth_s < 0:
        raise InputError(f"config key 'pca.key_smooth_s' must be >= 0, got {p.key_smooth_s}")
    positive = (
        "silhouette_sigma_m",
        "silhouette_scale",
        "silhouette_radius_scale",
        "root_sigma_m",
        "root_sigma_deg",
        "time_sigma",
    )
    for key in (*positive, "alpha_sigma", "alpha_bound"):
        if not getattr(p, key) > 0:
            raise InputError(f"config key 'pca.{key}' must be positive, got {getattr(p, key)}")
    if not p.joints:
        raise InputError("config key 'pca.joints' must name at least one tracked keypoint")
    known = tuple(keypoints) if keypoints is not None else H36M17
    for j in p.joints if names else ():
        if j not in known:
            raise InputError(f"config key 'pca.joints': unknown keypoint {j!r} (keypoints: {', '.join(known)})")
