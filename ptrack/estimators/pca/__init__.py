"""`method: pca` — the golf-swing tracker of Urtasun, Fleet & Fua (2004), over a PCA motion model.

The motion model (`ptrack.motion.motion_model`) gives every joint angle but the root's as a function of the
PCA weights alpha (m,) and a normalised time mu in [0, 1] (eq. 2). The tracker fits it over sliding
windows of f frames (`pca.window`, slid by `pca.step`, default one frame); the state of a window is (eq. 5)

    S = [alpha_1 .. alpha_m, mu_1 .. mu_f, G_1 .. G_f]     (m + 7 f parameters)

with alpha shared by the window and, per frame, a normalised time and the root pose G_t (translation,
and a rotation vector w_t turning the frame's predicted root rotation: R_t = exp(w_t) R^_t; the root,
which the model leaves out, is not parametrised by the skeleton's Euler angles because CMU subject 64
stands near their singularity). Its energy (eq. 7) is

    w_joint  sum rho(|proj(joint) - observed|^2 / sigma_px^2)   tracked joints (knees, ankles, wrists, head)
    + w_fg   sum (ray-to-model distance / sigma_m)^2             foreground samples (section 4.1,
                                                                 `ptrack.costs.ray_silhouette`; the model's
                                                                 radii times pca.silhouette_radius_scale)
    + w_corr sum rho(|proj(x_i) - p2_i|^2 / sigma_px^2)         point correspondences (section 4.3,
                                                                 `ptrack.costs.correspondence`)
    + |(G - G^) / sigma_G|^2 + |(mu - mu^) / sigma_mu|^2 + |(alpha - alpha^) / (s sigma_alpha)|^2
    + w_prior |alpha / sigma_alpha|^2 + |(mu - mu_0) / sigma_timing|^2

where the predictions ^ are the previous window's trajectory continued at its last speed (the frames
the window shares with the previous one keep their previous values as prediction), alpha^ the previous
window's weights, sigma_alpha the spread of the training swings' weights (the model's `sigma`), and
mu_0 the start's timing (below; `pca.timing_sigma`, null drops it). Beyond the paper's eq. 7, which has
none of them, time never runs backwards (each window's times are bounded below by the time of the frame
that last left a window), the weights are boxed in `pca.alpha_bound` training stds, and the timing prior
is there: without it the tracker read a held-out downswing as the backswing reversed (docs/notes/golf-history.md).
The energy is an `ptrack.costs.Objective` of the shared terms (`window.window_objective`): `Reprojection` for the
tracked joints and for the correspondences' points, `RaySilhouette` for the foreground samples, and `PosePrior` on
parts of the state for every prediction and prior; the terms read a `PoseEval` whose q is the window's state.
Each window is one Levenberg-Marquardt solve of `ptrack.optim.solvers` with a closed-form Jacobian: the
decoder is linear in alpha and piecewise linear in mu, the joints' Jacobian is the geometric one
(`ptrack.optim.jacobians.joint_jacobian`), the projections' is the camera's, and the silhouette term's comes
from the envelope theorem. A frame's result is its value in the last window that holds it.

Correspondences (p1 in frame t-1, p2 in frame t; `Problem.correspondences`), where given: before each
window's solve, every pair whose frame t is in the window has p1 backprojected onto the capsule model of
the current estimate of frame t-1 (the window's starting state, or the final estimate for the frame
before the window; a line of sight that misses the model, or passes within `pca.correspondence_margin_m` of
any capsule's surface, drops the pair for this window) and attached to
the hit capsule's frame; x_i is that body-fixed point moved with frame t's pose in the window, whose
Jacobian is the geometric one of a point on the segment (`ptrack.optim.jacobians.point_jacobian`). The pair's
weight (1 for simulated ones) scales its squared residual. Cost: p1's rays are made once; per window one FK
pass of the frame before it and the window's starting state serves the backprojection and the solve's first
linearisation (`StartBody`); each linearisation has one FK pass for joints and points
(`ptrack.optim.jacobians.joint_and_point_jacobian`) and projects them together.

Start (section 5.1), with no 3D input: the four key postures are found in the 2D wrist track
(`ptrack.motion.key_postures.detect_key_postures_2d`, rules `motion.key_postures`), every frame's normalised
time is interpolated through them (`initial_times`), the PCA weights are zero, and the root is placed
from the first frame: the mean motion's pose at that time under `pca.init_yaws` headings, at the depth
its 2D size gives, each fitted rigidly (root only) to the first frame's tracked joints and silhouette;
the best fit is kept. `pca.iterations: 0` returns that start itself: the mean motion with the initial
timing, the root held where the first frame put it (the paper's fig. 8).

After the swing: the windows track the frames up to the swing's end, its last key posture found in the 2D (the
end of the follow-through, where the model's time reaches 1); a clip that goes on shows motion no training swing
has, and its frames are handed on from the swing's last pose to the estimator `pca.after_swing` names (`batch`:
the MAP trajectory with that pose as a keyframe; `frame`: per-frame fits; `ptrack.estimators` passes them in as
`after`), or with `hold` the model's last pose is held and the root tracked. The estimate carries the weights,
the time of every frame and the key postures (`ptrack.problem.MotionFit`).

The model is read from `motion.model_file` (default ~/.cache/ptrack/motion/<config name>.npz); when no
file is there it is fitted from `motion.clips` (`ptrack fit-motion` does the same) and saved there.

Modules: `setup` (what is fixed over the sequence, the motion model), `poses` (the state's poses and their
derivatives), `window` (one window's terms and the kinematics of its linearisation), `pairs` (the
correspondences), `start` (the initial timing and root) and `track` (`estimate_pca`).
"""

from __future__ import annotations

from ptrack.estimators.pca.config import PcaMethodConfig
from ptrack.estimators.pca.pairs import StartBody, WindowPairs, correspondence_points
from ptrack.estimators.pca.poses import poses_of, root_angles
from ptrack.estimators.pca.setup import Setup, motion_model_for
from ptrack.estimators.pca.start import initial_timing, place_root
from ptrack.estimators.pca.track import estimate_pca
from ptrack.estimators.pca.window import Prediction

__all__ = [
    "PcaMethodConfig",
    "Prediction",
    "Setup",
    "StartBody",
    "WindowPairs",
    "correspondence_points",
    "estimate_pca",
    "initial_timing",
    "motion_model_for",
    "place_root",
    "poses_of",
    "root_angles",
]
