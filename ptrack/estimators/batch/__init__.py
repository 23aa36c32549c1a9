"""`method: batch` — the maximum a posteriori trajectory of the whole sequence (DiFranco, Cham &
Rehg 2001, eq. 5), by Levenberg-Marquardt on its block-banded normal equations.

For the trajectory Q = (q_0 .. q_{T-1}), q_t (D,), the energy is

    L(Q) = sum_t [ robust reprojection_t(q_t) + joint limits_t(q_t) ]        per frame (eqs. 1, 2)
         + 1/2 sum_n sum_t,d rho(|a_n * diff_n(Q)_t,d|^2)                   smoothing (eq. 3), n = 1, 2
         + 1/2 sum_f |L_f^{-1} (q_{t_f} - f_f)_S|^2 over the given dofs S     angle keyframes (eq. 4)
         + 1/2 sum_g |M_g^{-1} (X(q_{t_g}) - x_g)_G|^2 over the given joints G joint-position keyframes

with L_f L_f^T the covariance R_f of keyframe f's given dofs (its sigmas squared on the diagonal unless the
keyframe gives a full covariance; angle differences on the circle) and M_g M_g^T that of keyframe g's given
joint coordinates: the shared terms `ptrack.costs.Keyframe` and `JointKeyframe`. Every term is a shared cost
term (`Reprojection`, `JointLimits`, `Smoothness`, `Keyframe`, `JointKeyframe`), their normal equations summed
by the banded trajectory assembler `ptrack.optim.trajectory`. And a_1 = 1 / (dt sigma_velocity), a_2 = 1 /
(dt^2 sigma_acceleration) per dof: by default (`batch.prior: cmu`) each CMU dof's own scale, the RMS velocity
and acceleration of real motion (`ptrack/data/cmu_smoothing.json`, fitted to the dev clips by
`scripts/make_smoothing_prior.py`: a knee accelerates at ~27 rad/s^2, the head at ~7), else
`batch.velocity_sigma` / `accel_sigma` for angles and `*_sigma_m` for the root position; the root
translations' velocity term holds only those `batch.root_velocity` names (`all`; `vertical`: a constant
walking velocity on the ground costs nothing, only its changes do). rho is `batch.smooth_loss` at
`batch.smooth_scale` prior std (default Cauchy at 2: quadratic for the motion the prior expects, logarithmic
for faster motion, so a run's legs are not pulled flat; l2 is the paper's Gaussian). Missing keypoints
(confidence 0) and frames without any 2D add nothing: the dynamics fill them, which is how
`batch.upsample` reconstructs frames between the observed ones. The per-frame terms give the
diagonal blocks J_t^T W J_t of the Gauss-Newton Hessian (J_t from the geometric joint Jacobian, one
FK pass batched over all frames); the smoothing prior is linear in Q and couples each dof only with
itself, so it adds a band of diagonal couplings (block-pentadiagonal with an acceleration term;
constant for l2, else D_n^T diag(w a_n^2) D_n with the IRLS weights w = rho' of the residuals at the
current Q). `ptrack.optim.solvers.banded_levenberg_marquardt` solves it with `ptrack.optim.banded` (never a
dense (T*D)^2 matrix). The joint limits are the paper's barrier, 1/2 |(violation) / costs.limits_sigma|^2
times costs.limits_weight, on each limited angle's nearest turn (the default); with `batch.hard_limits` the solver
also keeps every iterate inside the limit box, and the barrier is then 0 throughout.

Uncertainty: the diagonal blocks of the inverse Gauss-Newton Hessian at the solution (the banded
recursion of `ptrack.optim.banded.marginal_blocks`) are the per-frame marginal covariances of the pose;
through the joint Jacobian G_t (J, 3, D) each joint's position covariance is G Sigma_t G^T, and
`joint_std` (T, J) is the square root of its trace (metres: the RMS 3D error it predicts). That
Laplace approximation only sees the curvature of the branch the solution took; with
`batch.uncertainty: branches` (the default) each limb's depth flips are added as a mixture
(`flip_posterior`, `ptrack.hypotheses.branches`): their second moment about the solution joins the trace.
Each branch is re-solved for `batch.branch_iterations` (10) iterations; after a restart the next round's
branches start warm, from the earlier ones moved by the restart's change. The same re-solved branches
restart the solve (`batch.flip_restarts` rounds, `lower_branch`): one whose whole energy is lower than
the solution's, and which is another trajectory (some joint more than 1 mm away), shows the solve stopped
in a local minimum on the other branch, and the solve continues from it. The std is that of the
objective's own model (its 2D noise, smoothing scales and branches) and misses what the model leaves out
(depth drift between keyframes, motion faster than the prior's): by default (`batch.std_calibration`) it is
calibrated, std' = sqrt((scale std)^2 + floor^2 + (travel m)^2), m the joint's distance from where it was at
the nearest keyframe (`keyframe_travel`), scale, floor and travel fitted on the dev and train clips
(`calibrate_std`, `ptrack/data/batch_std_calibration.json`, `scripts/make_std_calibration.py`); metrics.json
reports the share of joint-frames within 1, 2 and 3 std (`joint_within_2std` held out: 0.970 with keyframes
every 1 s, 0.955 every 2 s, 0.904 from the first and last frame only, against the target 0.9-0.98).

The start is the per-frame fit (`method: frame`), or an earlier run's trajectory (`init_from`, warped
onto the keyframes: `warp_to_keyframes`), or the keyframes interpolated (`batch.init: keyframes`;
the per-frame fit where no keyframe gives every dof, e.g. a user's file of partial or joint keyframes).

Modules: `objective` (the energy: `Trajectory`, `trajectory_objective`, `evaluate`), `smoothing` (the smoothing
prior as one shared `Smoothness` term per order, which gives its energy, gradient and robust weights; its band),
`solve` (the banded linearisation and Levenberg-Marquardt), `uncertainty` (`joint_std`, the flip branches and the
restarts from them), `start` (`init_from`, interpolated keyframes) and `estimate` (`estimate_batch`).
"""

from __future__ import annotations

from ptrack.estimators.batch.config import BatchMethodConfig
from ptrack.estimators.batch.estimate import PerFrame, estimate_batch
from ptrack.estimators.batch.objective import Evaluation, Trajectory, evaluate, total_energy, trajectory_objective
from ptrack.estimators.batch.smoothing import robust_smoothing, smoothing_band
from ptrack.estimators.batch.solve import linearization, solve_trajectory
from ptrack.estimators.batch.start import has_full_keyframe, interpolate_keyframes, load_init, warp_to_keyframes
from ptrack.estimators.batch.uncertainty import (
    StdCalibration,
    calibrate_std,
    flip_posterior,
    joint_std,
    keyframe_travel,
    lower_branch,
    std_calibration,
)
from ptrack.optim.trajectory import weighted_band

__all__ = [
    "BatchMethodConfig",
    "Evaluation",
    "PerFrame",
    "StdCalibration",
    "Trajectory",
    "calibrate_std",
    "estimate_batch",
    "evaluate",
    "flip_posterior",
    "has_full_keyframe",
    "interpolate_keyframes",
    "joint_std",
    "keyframe_travel",
    "linearization",
    "load_init",
    "lower_branch",
    "robust_smoothing",
    "smoothing_band",
    "solve_trajectory",
    "std_calibration",
    "total_energy",
    "trajectory_objective",
    "warp_to_keyframes",
    "weighted_band",
]
