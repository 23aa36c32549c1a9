"""Foreground/background term in 3D (Urtasun, Fleet & Fua 2004, section 4.1): samples of a foreground
mask whose lines of sight should meet the capsule ("flesh") model.

For each sampled foreground pixel, the residual is 0 when its ray (from the camera centre, forward
only) passes through some capsule, else the 3D distance from the model to the ray: the smallest
ray-segment distance over the bones minus that bone's radius. Minimised in the least-squares sense it
pulls the model under the mask; unlike `ptrack.costs.Silhouette` (bones pulled into the mask through
its 2D distance transform) it measures in metres, in 3D, and asks every part of the mask to be
explained by the model.

    mask_samples(masks (T, H, W), step, max_samples) -> pixels (T, S, 2), valid (T, S)
    ray_capsule_distance(origin (3,), directions (..., S, 3), a, b (..., B, 3), radii (B,))
        -> RayDistance(distance (..., S), bone (..., S), grad_a (..., S, 3), grad_b (..., S, 3))
    RaySilhouette(directions (*O, S, 3), valid (*O, S), origin, bones, radii, sigma_m)
        .residual(ev)            ev.joints (..., *O, J, 3) -> (..., |O|*S)
        .jacobian(ev, jac)       jac.joints (..., *O, J, 3, D) -> (..., |O|*S, D), closed form

The Jacobian is closed form by the envelope theorem: at the closest points ray(s*) and a + u* (b - a),
with n the unit vector from the segment's point to the ray's, d dist / d a = -(1 - u*) n and
d dist / d b = -u* n (the minimiser's own motion does not change the minimum to first order).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import torch
from torch import Tensor

from ptrack.costs.base import LeastSquaresMixin, PoseEval, PoseJacobian, check_positive, shape_of
from ptrack.errors import InputError


def mask_samples(masks: Tensor, step: int = 4, max_samples: int = 128) -> tuple[Tensor, Tensor]:
    """Foreground pixel centres on a regular grid, evenly thinned to at most `max_samples` per frame.

    masks (T, H, W) bool -> pixels (T, S, 2) (u, v at pixel centres, float32; padding at 0) and
    valid (T, S) bool, S = the largest per-frame count (<= max_samples). Deterministic: the grid
    holds the pixels whose row and column are multiples of `step`; a frame with more foreground grid
    pixels keeps `max_samples` of them at evenly spaced ranks of the raster order.
    """
    masks = torch.as_tensor(masks)
    if masks.dtype != torch.bool or masks.ndim != 3:
        raise InputError(f"mask_samples: masks must be bool (T, H, W), got {masks.dtype} {shape_of(masks)}")
    if step < 1 or max_samples < 1:
        raise InputError(f"mask_samples: step and max_samples must be >= 1, got {step}, {max_samples}")
    grid = masks[:, ::step, ::step]
    t_count = masks.shape[0]
    chosen: list[Tensor] = []
    for t in range(t_count):
        vu = grid[t].nonzero() * step  # (n, 2) row, column
        n = vu.shape[0]
        if n > max_samples:
            vu = vu[torch.linspace(0, n - 1, max_samples).round().long()]
        chosen.append(vu.flip(-1).float() + 0.5)
    s = max([c.shape[0] for c in chosen] + [1])
    pixels = torch.zeros(t_count, s, 2)
    valid = torch.zeros(t_count, s, dtype=torch.bool)
    for t, c in enumerate(chosen):
        pixels[t, : c.shape[0]] = c
        valid[t, : c.shape[0]] = True
    return pixels.to(masks.device), valid.to(masks.device)


class RayDistance(NamedTuple):
    """Distance from each ray to the capsule model and its derivatives (see `ray_capsule_distance`)."""

    distance: Tensor  # (..., S) metres, >= 0 (0: the ray meets a capsule)
    bone: Tensor  # (..., S) long, the nearest capsule
    grad_a: Tensor  # (..., S, 3) d distance / d (that bone's start joint)
    grad_b: Tensor  # (..., S, 3) d distance / d (that bone's end joint)


def ray_capsule_distance(origin: Tensor, directions: Tensor, a: Tensor, b: Tensor, radii: Tensor) -> RayDistance:
    """Distance from rays `origin + s d` (s >= 0) to the capsules of radius `radii` around segments a-b.

    origin (3,) world; directions (..., S, 3) unit; a, b (..., B, 3) segment ends; radii (B,) metres
    -> RayDistance: distance (..., S) = max(0, min_bone(|ray - segment| - radius)), the nearest bone,
    and the distance's gradient w.r.t. that bone's two ends (zero where the ray meets the model).
    Not differentiable through autograd by design: the gradients are returned in closed form.
    """
    a0 = a - origin  # (..., B, 3): the segment start seen from the camera centre
    e = b - a
    ee, ea, aa = (e * e).sum(-1)[..., None, :], (e * a0).sum(-1)[..., None, :], (a0 * a0).sum(-1)[..., None, :]
    de = directions @ e.mT  # (..., S, B)
    da = directions @ a0.mT
    tiny = torch.finfo(a.dtype).tiny
    # closest points by clamping (Ericson, Real-Time Collision Detection 5.1.9, a ray for the first segment):
    # u of the lines' closest points clamped into [0, 1], s the ray's best for that u; where s < 0, s = 0
    # and u the segment's point nearest the camera centre. Exact for this convex problem.
    den = ee - de * de
    par = den <= 1e-9 * ee  # parallel: any u gives the same distance to the line, take u = 0
    u = torch.where(par, 0.0, (de * da - ea) / torch.where(par, 1.0, den)).clamp(0, 1)
    s = da + u * de
    behind = s < 0
    u = torch.where(behind, (-ea / ee.clamp_min(tiny)).clamp(0, 1), u)
    s = s.clamp_min(0)
    # |s d - a0 - u e|^2 = s^2 + |a0|^2 + u^2 |e|^2 - 2 s d.a0 + 2 u e.a0 - 2 s u d.e
    sq = s * (s - 2 * da - 2 * u * de) + aa + u * (u * ee + 2 * ea)
    dist, bone = (sq.clamp_min(0).sqrt() - radii.to(a)).min(-1)  # (..., S)
    u = u.gather(-1, bone[..., None])[..., 0]
    s_ = s.gather(-1, bone[..., None])[..., 0]
    a_n = a0.gather(-2, bone[..., None].expand(*bone.shape, 3)) if a.ndim > 2 else a0[bone]
    e_n = e.gather(-2, bone[..., None].expand(*bone.shape, 3)) if a.ndim > 2 else e[bone]
    n = s_[..., None] * directions - a_n - u[..., None] * e_n  # (..., S, 3) from the segment to the ray
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(tiny)
    hit = dist <= 0
    n = torch.where(hit[..., None], torch.zeros_like(n), n)
    return RayDistance(distance=dist.clamp_min(0), bone=bone, grad_a=-(1 - u)[..., None] * n, grad_b=-u[..., None] * n)


@dataclass(frozen=True, eq=False)
class RaySilhouette(LeastSquaresMixin):
    """Foreground samples whose lines of sight should meet the capsule model (section 4.1).

    directions (*O, S, 3) unit world rays of the samples (`Camera.rays` of `mask_samples` pixels);
    valid (*O, S) bool (False: padding, zero residual); origin (3,) the camera centre; bones
    ((start, end), ...) skeleton joint indices with radii (B,) metres; sigma_m: a residual of 1 is
    this many metres. *O is () for one frame or (T,) for a trajectory. Reads ev.joints
    (..., *O, J, 3). residual (..., |O|*S): distance from ray to model / sigma_m.
    """

    directions: Tensor
    valid: Tensor
    origin: Tensor
    bones: tuple[tuple[int, int], ...]
    radii: Tensor
    sigma_m: float = 0.02
    _bones: Tensor = field(init=False, repr=False)

    def __post_init__(self) -> None:
        dirs, valid = torch.as_tensor(self.directions), torch.as_tensor(self.valid)
        if not dirs.is_floating_point() or dirs.ndim < 2 or dirs.shape[-1] != 3:
            raise InputError(f"RaySilhouette.directions must be floating (*O, S, 3), got {shape_of(dirs)}")
        if valid.dtype != torch.bool or valid.shape != dirs.shape[:-1]:
            raise InputError(
                f"RaySilhouette.valid must be bool {shape_of(dirs)[:-1]}, got {valid.dtype} {shape_of(valid)}"
            )
        bones = torch.as_tensor(self.bones)
        if (
            bones.ndim != 2
            or bones.shape[1] != 2
            or bones.shape[0] == 0
            or bones.is_floating_point()
            or bool((bones < 0).any())
        ):
            raise InputError(
                f"RaySilhouette.bones must be non-empty (start, end) joint index pairs, got {self.bones!r}"
            )
        radii = torch.as_tensor(self.radii, dtype=dirs.dtype)
        if radii.shape != (bones.shape[0],) or not bool((radii > 0).all()):
            raise InputError(f"RaySilhouette.radii must be ({bones.shape[0]},) positive, got {shape_of(radii)}")
        check_positive("RaySilhouette.sigma_m", self.sigma_m)
        object.__setattr__(self, "directions", dirs)
        object.__setattr__(self, "valid", valid)
        object.__setattr__(self, "origin", torch.as_tensor(self.origin, dtype=dirs.dtype))
        object.__setattr__(self, "radii", radii)
        object.__setattr__(self, "_bones", bones.long())

    def _distance(self, joints: Tensor) -> RayDistance:
        n_o = self.directions.ndim - 2
        if (
            joints.ndim < n_o + 2
            or joints.shape[joints.ndim - n_o - 2 : -2] != self.directions.shape[:-2]
            or joints.shape[-2] <= int(self._bones.max())
        ):
            raise InputError(
                f"RaySilhouette: ev.joints {shape_of(joints)} must be (..., "
                f"{''.join(f'{x}, ' for x in self.directions.shape[:-2])}J, 3) with J > "
                f"{int(self._bones.max())}"
            )
        bones = self._bones.to(joints.device)
        a, b = joints.index_select(-2, bones[:, 0]), joints.index_select(-2, bones[:, 1])
        return ray_capsule_distance(self.origin.to(joints), self.directions.to(joints), a, b, self.radii.to(joints))

    def residual(self, ev: PoseEval) -> Tensor:
        """ev.joints (..., *O, J, 3) -> (..., |O|*S): ray-to-model distance / sigma_m, 0 on padding."""
        r = self.residual_per_frame(ev.joints)
        return r.flatten(r.ndim - self.valid.ndim)

    def residual_per_frame(self, joints: Tensor) -> Tensor:
        """joints (..., *O, J, 3) -> (..., *O, S): the residuals with the sample axis kept apart."""
        return self._distance(joints).distance * (self.valid.to(joints) / self.sigma_m)

    def jacobian(self, ev: PoseEval, jac: PoseJacobian) -> Tensor:
        """jac.joints (..., *O, J, 3, D) -> (..., |O|*S, D), rows as in `residual`."""
        return self.linearize_joints(ev.joints, jac.joints)[1]

    def residual_jacobian(self, ev: PoseEval, jac: PoseJacobian) -> tuple[Tensor, Tensor]:
        """`residual` and `jacobian` from one ray-to-model distance (what `Objective.linearize` asks first)."""
        return self.linearize_joints(ev.joints, jac.joints)

    def linearize_joints(self, joints: Tensor, d_joints: Tensor) -> tuple[Tensor, Tensor]:
        """Residual and Jacobian w.r.t. any parameters P, given joints (..., *O, J, 3) and their
        derivative d_joints (..., *O, J, 3, P) -> (..., |O|*S), (..., |O|*S, P)."""
        rd = self._distance(joints)
        w = self.valid.to(joints) / self.sigma_m
        bones = self._bones.to(joints.device)
        ja, jb = bones[:, 0][rd.bone], bones[:, 1][rd.bone]  # (..., *O, S) joint indices
        p = d_joints.shape[-1]
        da = d_joints.gather(-3, ja[..., None, None].expand(*ja.shape, 3, p))  # (..., *O, S, 3, P)
        db = d_joints.gather(-3, jb[..., None, None].expand(*jb.shape, 3, p))
        jrow = ((rd.grad_a[..., None] * da).sum(-2) + (rd.grad_b[..., None] * db).sum(-2)) * w[..., None]
        n = self.valid.ndim
        return (rd.distance * w).flatten(-n), jrow.flatten(-n - 1, -2)
