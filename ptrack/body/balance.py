"""Static balance: the body's centre of mass above the foot it stands on.

One camera leaves some readings of a pose open that no 2D term can choose between: the trunk leaning along the
camera's ray, a thigh raised in front of the hip or behind it. The readings reproject alike and the pose priors
do not always prefer the right one (docs/notes/footage-history.md). Gravity does: a person standing, balancing
or walking keeps the whole body's centre of mass near the foot that carries it. In the CMU clips the priors are
fitted on (`scripts/balance_stats.py`, 5693 frames) it lies +0.016 ± 0.085 m forward and +0.001 ± 0.053 m to the
side of the support defined below, 0.057 m away at the median and 0.16 m at the 90th percentile; leaning the trunk
30 degrees forward at the lower back from the bundled kick's standing first frame takes it from 0.06 to 0.13 m.

`Balance` scores that distance on poses whose up axis is known (the model frame's +Y, as the floor contact has
it: a calibration's world, or the floor fitted under the person's feet). Like the pose mixture it ranks the kjs
tracker's modes (`kjs.balance_weight`, in `ptrack.estimators.kjs.model.frame_evidence`); it does not move them.

- The centre of mass: the segments' centres of mass weighted by their share of the body's mass, from
  D. A. Winter, *Biomechanics and Motor Control of Human Movement*, 4th ed. (2009), table 4.1 (mass fraction and
  the centre's place from the proximal end): thigh 0.100 at 0.433, leg (shank) 0.0465 at 0.433, foot 0.0145 at
  0.5, upper arm 0.028 at 0.436, forearm 0.016 at 0.430, hand 0.006 at 0.506, trunk 0.497 midway between the
  hips' and the shoulders' midpoints, head and neck 0.081 midway between the neck's base and the head's end.
- The support: each foot's point (the mean of its points: ankle, toe, heel, little toe as the skeleton has
  them), weighted by how low the foot is, exp(-(h - h_lowest) / `SUPPORT_SOFTNESS_M`): the lower foot carries
  the body; two feet at one height share it.
- The cost: log(1 + (d / sigma)^2) of the horizontal distance d between the two, a Cauchy-like term that grows
  slowly once far off (running, a kick, a jump leave the centre of mass over no foot for a while);
  `kjs.balance_sigma_m` (0.1 m) lies between the CMU clips' median distance and their 90th percentile.

Shapes: J joints, F foot points per foot."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ptrack.body.skeleton import Skeleton
from ptrack.errors import InputError

#: (proximal joint, distal joint, centre of mass from the proximal end / length, mass / body mass) per segment
#: of each side, on a CMU ASF skeleton's joints (a joint is the end of its bone); "*" is "l" or "r". Winter (2009)
#: table 4.1
LIMB_SEGMENTS: tuple[tuple[str, str, float, float], ...] = (
    ("*hipjoint", "*femur", 0.433, 0.100),
    ("*femur", "*tibia", 0.433, 0.0465),
    ("*tibia", "*toes", 0.5, 0.0145),
    ("*clavicle", "*humerus", 0.436, 0.028),
    ("*humerus", "*radius", 0.430, 0.016),
    ("*radius", "*hand", 0.506, 0.006),
)
TRUNK_MASS = 0.497  # midway between the hips' midpoint and the shoulders'
HEAD_MASS = 0.081  # head and neck: midway between the neck's base (lowerneck's end) and the head's end

#: each foot's points: CMU's ankle (the tibia's end) and toe end, and the heel and little-toe landmark joints
#: (`ptrack.body.subject.add_landmark_joints`) where the skeleton has them
FOOT_POINTS: tuple[str, ...] = ("*tibia", "*toes", "lm_*_heel", "lm_*_small_toe")

#: how much lower (metres) one foot must be to carry the body alone: the support's weights fall by e per this much
SUPPORT_SOFTNESS_M = 0.03


@dataclass(frozen=True, eq=False)
class Balance:
    """The horizontal distance of the centre of mass from the support, as a cost; `for_skeleton` builds it.

    segments (S, 2) proximal and distal joint, fraction (S,) and mass (S,) of the limb segments; hips, shoulders
    (2,) the left and right joints whose midpoints bound the trunk; neck, head: the head segment's ends; feet
    (2, F) each foot's points; sigma_m the distance at which the cost is log 2."""

    segments: Tensor
    fraction: Tensor
    mass: Tensor
    hips: Tensor
    shoulders: Tensor
    neck: int
    head: int
    feet: Tensor
    sigma_m: float
    free_m: float = 0.0

    @classmethod
    def for_skeleton(cls, skeleton: Skeleton, sigma_m: float, free_m: float = 0.0) -> Balance:
        """The term on a CMU ASF skeleton (InputError when it lacks the joints above)."""
        names = skeleton.joint_names

        def index(name: str) -> int:
            if name not in names:
                raise InputError(f"balance: skeleton {skeleton.name!r} has no joint {name!r} (a CMU ASF skeleton has)")
            return names.index(name)

        rows = [(index(a.replace("*", s)), index(b.replace("*", s)), f, m) for s in "lr" for a, b, f, m in LIMB_SEGMENTS]
        feet = []
        for s in "lr":
            pts = [names.index(p.replace("*", s)) for p in FOOT_POINTS if p.replace("*", s) in names]
            if len(pts) < 2:
                raise InputError(f"balance: skeleton {skeleton.name!r} has too few foot points on the {s} side")
            feet.append(pts)
        if len(feet[0]) != len(feet[1]):
            raise InputError(f"balance: skeleton {skeleton.name!r} has other foot points on the left than on the right")
        if not sigma_m > 0:
            raise InputError(f"balance: sigma_m must be > 0, got {sigma_m}")
        if not free_m >= 0:
            raise InputError(f"balance: free_m must be >= 0, got {free_m}")
        return cls(
            segments=torch.as_tensor([r[:2] for r in rows], dtype=torch.long),
            fraction=torch.as_tensor([r[2] for r in rows], dtype=torch.float64),
            mass=torch.as_tensor([r[3] for r in rows], dtype=torch.float64),
            hips=torch.as_tensor([index("lhipjoint"), index("rhipjoint")]),
            shoulders=torch.as_tensor([index("lclavicle"), index("rclavicle")]),
            neck=index("lowerneck"),
            head=index("head"),
            feet=torch.as_tensor(feet, dtype=torch.long),
            sigma_m=float(sigma_m),
            free_m=float(free_m),
        )

    def centre_of_mass(self, joints: Tensor) -> Tensor:
        """joints (..., J, 3) -> (..., 3) the whole body's centre of mass."""
        dev = joints.device
        frac = self.fraction.to(joints)
        prox = joints.index_select(-2, self.segments[:, 0].to(dev))
        dist = joints.index_select(-2, self.segments[:, 1].to(dev))
        limbs = ((prox + frac[:, None] * (dist - prox)) * self.mass.to(joints)[:, None]).sum(-2)
        hips = joints.index_select(-2, self.hips.to(dev)).mean(-2)
        shoulders = joints.index_select(-2, self.shoulders.to(dev)).mean(-2)
        trunk = 0.5 * (hips + shoulders)
        head = 0.5 * (joints[..., self.neck, :] + joints[..., self.head, :])
        total = float(self.mass.sum()) + TRUNK_MASS + HEAD_MASS
        return (limbs + TRUNK_MASS * trunk + HEAD_MASS * head) / total

    def support(self, joints: Tensor) -> Tensor:
        """joints (..., J, 3) -> (..., 3) the point the body stands on: the feet's points, the lower foot first."""
        pts = joints.index_select(-2, self.feet.flatten().to(joints.device)).unflatten(-2, tuple(self.feet.shape))
        low = pts[..., 1].amin(-1)  # (..., 2) each foot's lowest point along +Y
        w = torch.softmax(-(low - low.amin(-1, keepdim=True)) / SUPPORT_SOFTNESS_M, dim=-1)
        return (w[..., None] * pts.mean(-2)).sum(-2)

    def distance(self, joints: Tensor) -> Tensor:
        """joints (..., J, 3) -> (...,) metres: the centre of mass's horizontal (X, Z) distance from the support."""
        gap = self.centre_of_mass(joints) - self.support(joints)
        return torch.hypot(gap[..., 0], gap[..., 2])

    def energy(self, joints: Tensor) -> Tensor:
        """joints (..., J, 3) -> (...,) log(1 + (max(distance - free_m, 0) / sigma_m)^2)."""
        return torch.log1p(((self.distance(joints) - self.free_m).clamp_min(0.0) / self.sigma_m).square())


__all__ = ["Balance", "FOOT_POINTS", "LIMB_SEGMENTS", "SUPPORT_SOFTNESS_M"]
