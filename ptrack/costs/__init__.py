"""Cost terms and the objective that sums them.

A cost term is three separate pieces (after theseus): a *residual* (a whitened vector per sample,
shape (..., M)), a *weight* (a float held by the `Objective`) and a *robust loss* rho applied to
squared residuals. A term's energy is 0.5 * sum rho(|r_g|^2) over its residual groups g (a group is
one residual entry, or both coordinates of one keypoint for `Reprojection`). Least-squares priors
use rho(s) = s. Gauss-Newton solvers read `Objective.residuals` plus the IRLS weights
`Objective.robust_weights`; particle trackers and L-BFGS read the energies.

Terms never run kinematics: they read a `PoseEval` made elsewhere (forward kinematics + camera).
For a trajectory the time axis is the last batch dim: q (..., T, D), joints (..., T, J, 3).
The batch shape of `energy` is the input's leading dims before the term's own event dims.
Pixel coordinates follow OpenCV: u = column, v = row; pixel (u, v) covers [u, u+1) x [v, v+1), its
centre at (u + 0.5, v + 0.5), as in `Camera` and `render_silhouettes`.
"""

from ptrack.costs.base import (
    CostTerm,
    PoseEval,
    Robust,
    cauchy,
    geman_mcclure,
    huber,
    l2,
    robust_loss,
    robust_loss_derivative,
)
from ptrack.costs.collision import SelfIntersection
from ptrack.costs.floor import FloorContact
from ptrack.costs.objective import Objective, ObjectiveValue
from ptrack.costs.silhouette import Silhouette, distance_transform
from ptrack.costs.smoothness import BandedGaussNewton, Smoothness
from ptrack.costs.terms import (
    HeavyTailedPrior,
    JointKeyframe,
    JointLimits,
    Keyframe,
    PosePrior,
    Reprojection,
    SwapReprojection,
)

__all__ = [
    "BandedGaussNewton",
    "CostTerm",
    "FloorContact",
    "HeavyTailedPrior",
    "JointKeyframe",
    "JointLimits",
    "Keyframe",
    "Objective",
    "ObjectiveValue",
    "PoseEval",
    "PosePrior",
    "Reprojection",
    "Robust",
    "SelfIntersection",
    "Silhouette",
    "Smoothness",
    "SwapReprojection",
    "cauchy",
    "distance_transform",
    "geman_mcclure",
    "huber",
    "l2",
    "robust_loss",
    "robust_loss_derivative",
]
