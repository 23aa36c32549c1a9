"""Floor contact: the lowest foot point of each pose rests on a known floor plane.

From one camera the depth of a standing person is set by the bone lengths alone, and a whole body tilted
towards or away from the camera projects almost the same. A calibration whose world has a known up axis and
its floor at a known height removes that freedom: at least one foot touches the floor in most frames of
people standing, walking or balancing. The term pulls the lowest of the foot points (heels, toes) to the floor
plus their clearance (how high those points sit when the foot stands flat), with a quadratic penalty below
the floor and a robust one above it, so that a foot in the air (a jump, a kick off the ground) costs little.

Heights are along the model frame's +Y (the estimators' world is Y up).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from ptrack.costs.base import PoseEval, PoseJacobian, check_positive, robust_loss, robust_loss_derivative, shape_of
from ptrack.errors import InputError


@dataclass(frozen=True, eq=False)
class FloorContact:
    """The lowest of the joints `joints` (F,) at `height_m` + `clearance_m` along +Y.

    residual r = (min_f joints[..., f, 1] - height_m - clearance_m) / sigma_m: (...,) -> (..., 1) for one frame,
    or with `time_axis` joints (..., T, J, 3) -> (..., T). energy 0.5 r^2 below the floor's contact height
    (r < 0), 0.5 rho(r^2, scale) above it (the robust `loss`, its scale in sigmas).
    """

    joints: tuple[int, ...]
    height_m: float = 0.0
    clearance_m: float = 0.0
    sigma_m: float = 0.03
    loss: str = "huber"
    scale: float = 1.0
    time_axis: bool = False
    _index: Tensor = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.joints:
            raise InputError("FloorContact needs at least one foot joint")
        check_positive("FloorContact.sigma_m", self.sigma_m)
        check_positive("FloorContact.scale", self.scale)
        robust_loss(self.loss)
        object.__setattr__(self, "_index", torch.as_tensor(self.joints, dtype=torch.long))

    def residual(self, ev: PoseEval) -> Tensor:
        """ev.joints (..., J, 3) -> (..., 1); with time_axis (..., T, J, 3) -> (..., T)."""
        x = ev.joints
        if x.ndim < (3 if self.time_axis else 2) or x.shape[-1] != 3 or int(self._index.max()) >= x.shape[-2]:
            raise InputError(f"FloorContact: ev.joints {shape_of(x)} must be (..., J, 3) with J > {max(self.joints)}")
        low = x.index_select(-2, self._index.to(x.device))[..., 1].amin(-1)
        r = (low - (self.height_m + self.clearance_m)) / self.sigma_m
        return r if self.time_axis else r.unsqueeze(-1)

    def jacobian(self, ev: PoseEval, jac: PoseJacobian) -> Tensor:
        """jac.joints (..., J, 3, D) -> (..., 1, D) (time_axis: (..., T, D)): the lowest foot point's height row
        over sigma_m (the minimum's derivative where it is unique)."""
        x = ev.joints
        idx = self._index.to(x.device)
        low = idx[x.index_select(-2, idx)[..., 1].argmin(-1)]  # (...,) the lowest foot joint
        rows = jac.joints[..., 1, :]  # (..., J, D) d height / d q
        j = rows.gather(-2, low[..., None, None].expand(*low.shape, 1, rows.shape[-1])) / self.sigma_m
        return j.squeeze(-2) if self.time_axis else j

    def energy(self, ev: PoseEval) -> Tensor:
        """ev -> (...,)."""
        r = self.residual(ev)
        s = r.square()
        return 0.5 * torch.where(r < 0, s, robust_loss(self.loss)(s, self.scale)).sum(-1)

    def robust_weights(self, ev: PoseEval) -> Tensor:
        """ev -> (..., M): 1 below the floor's contact height, rho'(r^2) above (IRLS weights)."""
        r = self.residual(ev)
        return torch.where(r < 0, torch.ones_like(r), robust_loss_derivative(self.loss)(r.square(), self.scale))
