"""The config section of the batch estimator (`batch:`) and its checks. Composed into the run's config by
`ptrack.pipeline.config`."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ptrack.costs.base import ROBUST_LOSSES
from ptrack.errors import InputError
from ptrack.settings import setting

#: `batch.root_velocity`: the root translations (x, y, z; y up) the velocity prior holds, by setting
ROOT_VELOCITY: dict[str, tuple[bool, bool, bool]] = {
    "all": (True, True, True),
    "vertical": (False, True, False),
    "none": (False, False, False),
}


@dataclass(frozen=True)
class BatchMethodConfig:
    """`method: batch`, the MAP trajectory of the whole sequence (DiFranco, Cham & Rehg 2001)."""

    iterations: int = setting(30, "Levenberg-Marquardt iterations on the whole trajectory")
    tol: float = setting(1e-9, "relative energy decrease (or step) at which it stops")
    damping: float = setting(1e-8, "initial lambda, relative to the Hessian's largest diagonal entry")
    velocity_sigma: float | None = setting(3.0, "velocity smoothing std of the angles, rad/s; null drops the term")
    accel_sigma: float | None = setting(8.0, "acceleration smoothing std of the angles, rad/s^2; null drops the term")
    velocity_sigma_m: float | None = setting(1.0, "velocity smoothing std of the root position, m/s; null: none")
    accel_sigma_m: float | None = setting(2.0, "acceleration smoothing std of the root position, m/s^2; null: none")
    root_velocity: str = setting(
        "all",
        "root translations the velocity prior pulls to rest: all (x, y, z), vertical (y: a walker's constant "
        "ground-plane velocity costs nothing, the acceleration prior still acts) or none",
    )
    prior: str | None = setting("cmu", "per-dof smoothing scales replacing the sigmas: cmu (real motion) or null")
    smooth_loss: str = setting("cauchy", "the smoothing residuals' loss: l2, huber, cauchy, geman_mcclure")
    smooth_scale: float = setting(2.0, "the smoothing loss's scale, in prior standard deviations")
    upsample: int = setting(1, "reconstruct N frames per observed frame (data.stride must be divisible by N)")
    init: str = setting(
        "frame",
        "start: frame (per-frame fits, frame.* settings), keyframes (interpolated) or kjs (the kjs tracker's best "
        "trajectory, kjs.* settings; its tree start where frame 0 has no full keyframe)",
    )
    uncertainty: bool | str = setting(
        "branches",
        "joint_std in result.npz: branches (true: Laplace + the limbs' flip branches), laplace (the Laplace "
        "approximation alone: worse calibrated where a limb's depth is ambiguous), false = none",
    )
    std_calibration: bool = setting(
        True,
        "widen joint_std by the calibration of its batch.uncertainty mode fitted on the dev and train clips (a "
        "scale and a share of each joint's travel from its nearest keyframe: ptrack/data/batch_std_calibration.json); "
        "false: the raw std (overconfident: ~0.8 within 2 std)",
    )
    flip_restarts: int = setting(3, "rounds of restarts from the limbs' depth-flip branches (0: none)")
    branch_iterations: int = setting(
        10,
        "Levenberg-Marquardt iterations of each flip branch's re-solve (restarts, branches; the branch a "
        "restart takes is then solved with batch.iterations); 0: the rigid flips",
    )
    pose_prior_weight: float = setting(
        0.03,
        "weight of the CMU per-dof pose prior (ptrack.body.pose_prior) on every frame, as kjs holds it at 0.1 "
        "(0.03: chosen on the dev clips; steadies limbs far from any keyframe); 0: none",
    )
    hard_limits: bool = setting(
        False,
        "also keep every iterate inside the joint-limit box (false: the soft barrier costs.limits_* alone, "
        "the paper's eq. 2)",
    )


def validate_batch(b: BatchMethodConfig) -> None:
    """Value checks of the `batch:` section (InputError naming the key); `batch.upsample` against `data.stride`
    is checked with the whole config (`ptrack.pipeline.config.validate`)."""
    if b.iterations < 1 or b.upsample < 1:
        raise InputError("config keys 'batch.iterations' and 'batch.upsample' must be >= 1")
    for key in ("tol", "damping"):
        if not getattr(b, key) > 0:
            raise InputError(f"config key 'batch.{key}' must be positive, got {getattr(b, key)}")
    for key in ("velocity_sigma", "accel_sigma", "velocity_sigma_m", "accel_sigma_m"):
        if getattr(b, key) is not None and not getattr(b, key) > 0:
            raise InputError(f"config key 'batch.{key}' must be positive or null, got {getattr(b, key)}")
    if b.smooth_loss not in ROBUST_LOSSES:
        raise InputError(
            f"config key 'batch.smooth_loss' must be one of {', '.join(ROBUST_LOSSES)}, got {b.smooth_loss!r}"
        )
    if not b.smooth_scale > 0:
        raise InputError(f"config key 'batch.smooth_scale' must be positive, got {b.smooth_scale}")
    if b.root_velocity not in ROOT_VELOCITY:
        raise InputError(
            f"config key 'batch.root_velocity' must be one of {', '.join(ROOT_VELOCITY)}, got {b.root_velocity!r}"
        )
    if b.init not in ("frame", "keyframes", "kjs"):
        raise InputError(f"config key 'batch.init' must be 'frame', 'keyframes' or 'kjs', got {b.init!r}")
    if isinstance(b.branch_iterations, bool) or not isinstance(b.branch_iterations, int) or b.branch_iterations < 0:
        raise InputError(f"config key 'batch.branch_iterations' must be an integer >= 0, got {b.branch_iterations!r}")
    if not b.pose_prior_weight >= 0 or not math.isfinite(b.pose_prior_weight):
        raise InputError(f"config key 'batch.pose_prior_weight' must be >= 0, got {b.pose_prior_weight}")
    if isinstance(b.flip_restarts, bool) or not isinstance(b.flip_restarts, int) or b.flip_restarts < 0:
        raise InputError(f"config key 'batch.flip_restarts' must be an integer >= 0, got {b.flip_restarts!r}")
    if isinstance(b.uncertainty, str) and b.uncertainty not in ("laplace", "branches"):
        raise InputError(
            f"config key 'batch.uncertainty' must be 'branches', 'laplace', true (= branches) or false, "
            f"got {b.uncertainty!r}"
        )
