"""Body non-self-intersection (Sminchisescu & Triggs 2003: poses are optimised "subject to joint and
body non-self-intersection constraints"): a penetration cost between non-adjacent body capsules.

Each bone is a capsule: all points within a radius of the segment from its parent joint to its own
joint (the `ptrack.observe.silhouette` "flesh" model, shrunk: see below). Capsules a, b interpenetrate by
radius_a + radius_b - d_ab, d_ab the exact closest distance between their segments. The cost prunes
kinematic flips that pass an arm or a leg through the body.

Defaults of `SelfIntersection.for_skeleton`, and why. The flesh radii are rough and isotropic (the
torso is a 0.13-0.14 m capsule round the spine, though it is much shallower front to back), so real
motion "penetrates" them: on the ground truth of the CMU clips 10_02, 02_01, 05_02, 64_01, 10_01,
16_01, 49_18 and 124_01 (5,372 frames), with the flesh radii and pairs within 2 hops excluded,
every frame penetrates somewhere, up to 8.3 cm: upper arms and forearms in the torso capsules
(kicks, golf, pitch), thigh in thigh (standing), hand and thumb in hand (golf grip). So:

- pairs within `min_hops` = 2 in the bone graph are not checked (bones sharing a joint are 1 hop
  apart; 2 hops covers the shoulder girdle and pelvis: clavicle vs thorax, hip bone vs lower back,
  neck vs upper back, thigh vs the other hip bone, and the spine's own links);
- the extremities (`DEFAULT_SKIP`: hand, fingers, thumb, wrist, toes) are not checked: hands grip
  each other and rest on the body, and a flipped forearm is still caught by its `radius` capsule;
- collision radii are `radius_scale` = 0.5 times the flesh radii (a core inside the flesh: torso
  0.065-0.07 m, thigh 0.04 m, forearm 0.02 m), margin 0.

With these defaults no frame of the eight clips penetrates (energy exactly 0; the closest approach
leaves 7 mm on 124_01 and 12-74 mm on the others). Without the skip 24% of the golf frames do (hands,
2 cm); with min_hops = 1 every frame does (spine, up to 2.7 cm). An arm swung through the torso
penetrates by ~7 cm (energy ~40 at the default sigma = 1 cm). On 28 further CMU clips (24,349
frames, held out: not used to choose) 6 have penetrating frames, 0.8% of the frames in all, all
real self-contact that the cores still overlap: a shin hooked round the other leg (dance 05_04,
10% of its frames, 2.9 cm), thighs (131_07, 5%, 2.0 cm), forearms on a sword grip (02_07, 1%,
1.5 cm), a forearm on the thigh (135_07, 1.4 cm); 131_03 and 16_05 under 4 mm.

Time: the energy of 4096 hypotheses of the CMU skeleton (20 capsules, 141 pairs, float32, CPU) takes
~45 ms, ~90 ms with its gradient (single-thread CPU time; forward kinematics of the same batch:
~30 ms).
"""

from __future__ import annotations

import fnmatch
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from ptrack.checks import as_float_tensor
from ptrack.costs.base import LeastSquaresMixin, PoseEval, PoseJacobian, check_positive, shape_of
from ptrack.errors import InputError
from ptrack.observe.silhouette import capsule_radii

if TYPE_CHECKING:
    from ptrack.body.skeleton import Skeleton

#: bones left out by `SelfIntersection.for_skeleton` (fnmatch patterns, case-insensitive)
DEFAULT_SKIP = ("*hand", "*fingers", "*thumb", "*wrist", "*toes")


def segment_distance(p0: Tensor, p1: Tensor, q0: Tensor, q1: Tensor, eps: float = 1e-6) -> Tensor:
    """Closest distance between segments [p0, p1] and [q0, q1]: each (..., 3), broadcastable -> (...).

    Exact (Ericson, Real-Time Collision Detection, 5.1.9: the line-line solution clamped to the
    segments, then the other parameter re-solved and clamped), including parallel and degenerate
    (point) segments. Returns sqrt(|c_p - c_q|^2 + eps^2) for the closest points c_p, c_q (eps in
    the inputs' units: eps at contact, within eps^2 / 2d of d elsewhere), so the gradient is defined
    everywhere (zero at contact, not NaN).

    The closest-point parameters are found without autograd: d is stationary in them (or they sit
    on a bound), so the gradient is exact wherever d is differentiable (Danskin's theorem), and
    cheap; second derivatives hold the closest points' parameters fixed (the Gauss-Newton part).
    """
    p0, p1, q0, q1 = (x.movedim(-1, 0) for x in torch.broadcast_tensors(p0, p1, q0, q1))
    return _distance(p1 - p0, q1 - q0, p0 - q0, eps)


def _distance(u: Tensor, v: Tensor, w: Tensor, eps: float) -> Tensor:
    """`segment_distance` from u = p1 - p0, v = q1 - q0, w = p0 - q0, coordinates first:
    (3, ...) each -> (...). (Coordinates first: the dot products add three contiguous slabs.)"""
    with torch.no_grad():
        s, t = _closest_parameters(u, v, w)
    gap = w + s * u - t * v
    return torch.sqrt((gap * gap).sum(0) + eps * eps)


def _closest_parameters(u: Tensor, v: Tensor, w: Tensor) -> tuple[Tensor, Tensor]:
    """Parameters s, t in [0, 1] of the closest points p0 + s u, q0 + t v of two segments, with
    u = p1 - p0, v = q1 - q0, w = p0 - q0: (3, ...) each -> (s (...), t (...))."""
    a, e, b = (u * u).sum(0), (v * v).sum(0), (u * v).sum(0)
    c, f = (u * w).sum(0), (v * w).sum(0)
    zero, one = torch.zeros_like(a), torch.ones_like(a)
    a_ok = a > 1e-12 * (a + e)  # p is a proper segment, not a point
    e_ok = e > 1e-12 * (a + e)
    a_safe, e_safe = torch.where(a_ok, a, one), torch.where(e_ok, e, one)
    den = a * e - b * b  # a e sin^2(angle) >= 0: 0 for parallel segments
    den_ok = den > 16 * torch.finfo(a.dtype).eps * a * e
    # Both proper: s from the line-line solution (any s for parallel lines: 0), clamped; t for that
    # s; if t leaves [0, 1], clamp it and re-solve s for the clamped end.
    s = torch.where(den_ok, (b * f - c * e) / torch.where(den_ok, den, one), zero).clamp(0.0, 1.0)
    t_raw = (b * s + f) / e_safe
    s = torch.where(t_raw < 0.0, -c / a_safe, torch.where(t_raw > 1.0, (b - c) / a_safe, s))
    s, t = s.clamp(0.0, 1.0), t_raw.clamp(0.0, 1.0)
    # One or both segments are points.
    s = torch.where(a_ok, torch.where(e_ok, s, (-c / a_safe).clamp(0.0, 1.0)), zero)
    t = torch.where(e_ok, torch.where(a_ok, t, (f / e_safe).clamp(0.0, 1.0)), zero)
    return s, t


def _joint_classes(bones: Sequence[tuple[int, int]], zero_length: Sequence[bool], n_joints: int) -> list[int]:
    """Joint -> representative joint (J,): the two ends of every zero-length bone are one joint."""
    rep = list(range(n_joints))

    def find(j: int) -> int:
        while rep[j] != j:
            j = rep[j]
        return j

    for (p, c), zero in zip(bones, zero_length):
        if zero:
            rep[find(c)] = find(p)
    return [find(j) for j in range(n_joints)]


def _hop_distances(bones: Sequence[tuple[int, int]], n_joints: int) -> list[list[int]]:
    """Shortest path lengths in the bone graph, bones adjacent when they share a joint:
    bones (B,) (start, end) joint pairs -> (B, B) nested lists; B + 1 between unconnected bones."""
    touching: list[list[int]] = [[] for _ in range(n_joints)]
    for i, bone in enumerate(bones):
        for j in set(bone):
            touching[j].append(i)
    n = len(bones)
    hops = [[n + 1] * n for _ in range(n)]
    for src in range(n):
        hops[src][src] = 0
        frontier = [src]
        while frontier:
            nxt = []
            for i in frontier:
                for j in bones[i]:
                    for k in touching[j]:
                        if hops[src][k] > n:
                            hops[src][k] = hops[src][i] + 1
                            nxt.append(k)
            frontier = nxt
    return hops


def _index_tensor(name: str, value, cols: int) -> Tensor:
    t = torch.as_tensor(value)
    if t.ndim != 2 or t.shape[1] != cols or t.is_floating_point() or t.is_complex() or t.dtype == torch.bool:
        raise InputError(f"SelfIntersection.{name} must be an integer tensor (n, {cols}), got {t.dtype} {shape_of(t)}")
    if (t < 0).any():
        raise InputError(f"SelfIntersection.{name} must be >= 0")
    return t.long()


@dataclass(frozen=True, eq=False)
class SelfIntersection(LeastSquaresMixin):
    """Penetration between non-adjacent body capsules, on ev.joints.

    segments (C, 2) int: (start, end) joint indices of each capsule; radii (C,) metres; pairs
    (P, 2) int: the capsule index pairs checked; names (C,) optional capsule names.
    Reads ev.joints (..., J, 3). residual (..., P) = max(0, radius_a + radius_b - d_ab - margin) /
    sigma, d_ab the exact closest distance between the two segments (`segment_distance`, eps its
    smoothing in metres); energy (...,) = 0.5 |r|^2. `for_skeleton` builds it for a `Skeleton`.
    """

    segments: Tensor
    radii: Tensor
    pairs: Tensor
    sigma: float = 0.01
    margin: float = 0.0
    eps: float = 1e-6
    names: tuple[str, ...] = ()
    _ends: Tensor = field(init=False, repr=False)  # (4P,): starts, ends of capsules a, then of b
    _reach: Tensor = field(init=False, repr=False)  # (P,) radius_a + radius_b
    _joints_needed: int = field(init=False, repr=False)  # 1 + the largest joint index used

    def __post_init__(self) -> None:
        seg, pairs = _index_tensor("segments", self.segments, 2), _index_tensor("pairs", self.pairs, 2)
        radii = as_float_tensor(self.radii, "radii")
        if radii.shape != seg.shape[:1] or not (torch.isfinite(radii).all() and (radii >= 0).all()):
            raise InputError(
                f"SelfIntersection.radii must be finite, >= 0 and of shape "
                f"({seg.shape[0]},) like segments, got {shape_of(radii)}"
            )
        if (pairs >= seg.shape[0]).any():
            raise InputError(f"SelfIntersection.pairs must index the {seg.shape[0]} segments, got {int(pairs.max())}")
        if self.names and len(self.names) != seg.shape[0]:
            raise InputError(f"SelfIntersection.names has {len(self.names)} entries for {seg.shape[0]} segments")
        check_positive("SelfIntersection.sigma", self.sigma)
        check_positive("SelfIntersection.eps", self.eps)
        try:
            margin = float(self.margin)
        except (TypeError, ValueError):
            margin = math.nan
        if not math.isfinite(margin):
            raise InputError(f"SelfIntersection.margin must be a finite number, got {self.margin!r}")
        object.__setattr__(self, "segments", seg)
        object.__setattr__(self, "radii", radii)
        object.__setattr__(self, "pairs", pairs)
        object.__setattr__(self, "margin", margin)
        object.__setattr__(self, "names", tuple(self.names))
        object.__setattr__(self, "_joints_needed", int(seg.max()) + 1 if seg.numel() else 0)
        object.__setattr__(self, "_ends", seg[pairs].permute(1, 2, 0).reshape(-1))
        object.__setattr__(self, "_reach", radii[pairs].sum(-1))

    @property
    def pair_names(self) -> list[tuple[str, str]]:
        """(P,) capsule names of each checked pair ("" without names)."""
        names = self.names or ("",) * self.segments.shape[0]
        return [(names[a], names[b]) for a, b in self.pairs.tolist()]

    def _segment_ends(self, joints: Tensor) -> Tensor:
        """joints (..., J, 3) -> (4, 3, ..., P): capsule a's start, end, capsule b's start, end of every
        checked pair, coordinates second (the layout `_distance` reads); shape errors raised here."""
        if joints.ndim < 2 or joints.shape[-1] != 3:
            raise InputError(f"SelfIntersection: joints must be (..., J, 3), got {shape_of(joints)}")
        if joints.shape[-2] < self._joints_needed:
            raise InputError(
                f"SelfIntersection: segments use joint {self._joints_needed - 1} but "
                f"joints {shape_of(joints)} has J={joints.shape[-2]}"
            )
        ends = joints.index_select(-2, self._ends.to(joints.device)).unflatten(-2, (4, -1))
        return ends.movedim((-3, -1), (0, 1))

    def penetration(self, joints: Tensor) -> Tensor:
        """joints (..., J, 3) -> (..., P) metres: radius_a + radius_b - d_ab per checked pair
        (negative when apart; the margin is not subtracted)."""
        p0, p1, q0, q1 = self._segment_ends(joints).contiguous()  # (3, ..., P) each
        return self._reach.to(joints) - _distance(p1 - p0, q1 - q0, p0 - q0, self.eps)

    def residual(self, ev: PoseEval) -> Tensor:
        """ev.joints (..., J, 3) -> (..., P): penetration beyond the margin / sigma, >= 0."""
        return (self.penetration(ev.joints) - self.margin).clamp(min=0.0) / self.sigma

    def jacobian(self, ev: PoseEval, jac: PoseJacobian) -> Tensor:
        """jac.joints (..., J, 3, D) -> (..., P, D) in closed form: with the closest points held
        (Danskin), d d_ab / d end = +-(1 - s or s) n along the unit gap n, zero for pairs apart."""
        joints = ev.joints
        p0, p1, q0, q1 = self._segment_ends(joints)  # (3, ..., P) each
        u, v, w = p1 - p0, q1 - q0, p0 - q0
        with torch.no_grad():
            s, t = _closest_parameters(u, v, w)
        gap = w + s * u - t * v
        d = torch.sqrt((gap * gap).sum(0) + self.eps * self.eps)
        active = (self._reach.to(joints) - d - self.margin) > 0
        out = joints.new_zeros(*active.shape, jac.joints.shape[-1])  # (..., P, D)
        hit = active.flatten(0, -2).any(0).nonzero()[:, 0] if active.ndim > 1 else active.nonzero()[:, 0]
        if hit.numel() == 0:  # nothing penetrates anywhere in the batch (the usual case)
            return out
        n = (gap / d).movedim(0, -1) * (-active.to(joints) / self.sigma)[..., None]  # (..., P, 3)
        coef = torch.stack([1 - s, s, t - 1, -t], dim=-2)  # (..., 4, P)
        ends = self._ends.to(joints.device).view(4, -1)[:, hit].reshape(-1)
        dx = jac.joints.index_select(-3, ends).unflatten(-3, (4, -1))  # (..., 4, H, 3, D), H pairs hit
        rows = torch.einsum("...ep,...pc,...epcd->...pd", coef.index_select(-1, hit), n.index_select(-2, hit), dx)
        return out.index_copy(-2, hit, rows)

    def _maybe(self, joints: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """joints (B, J, 3) -> the (pose b, pair k) entries that may penetrate, b (A,) and k (A,), and the capsules'
        ends (2, B, C, 3) (starts, then ends). Two segments are at least as far apart as their midpoints less both
        half-lengths, so every other entry surely does not penetrate (residual exactly 0); the bound is made per
        capsule first (C capsules, fewer than the P pairs)."""
        seg = self.segments.to(joints.device)
        caps = joints.index_select(-2, seg.T.reshape(-1)).unflatten(-2, (2, -1)).movedim(-3, 0)  # (2, B, C, 3)
        mid, half = 0.5 * (caps[0] + caps[1]), 0.5 * (caps[1] - caps[0]).square().sum(-1).sqrt()  # (B, C, 3), (B, C)
        a, b = self.pairs.to(joints.device).T
        apart = (mid.index_select(-2, a) - mid.index_select(-2, b)).square().sum(-1).sqrt()
        bound = apart - half.index_select(-1, a) - half.index_select(-1, b)  # (B, P) <= d_ab
        # a hair of slack (1e-6 of the reach, and a nanometre) for the bound's own rounding
        reach = self._reach.to(bound) - self.margin
        pose, pair = (bound < reach + 1e-6 * reach.abs() + 1e-9).nonzero(as_tuple=True)
        return pose, pair, caps

    def gauss_newton(self, ev: PoseEval, jac: PoseJacobian) -> tuple[Tensor, Tensor, Tensor]:
        """This term's share of the Gauss-Newton normal equations, from the (pose, pair) entries that can
        penetrate only (`_maybe`; the rows of the others are zero): jac.joints (..., J, 3, D) -> energy (...,),
        J^T J (..., D, D), J^T r (..., D). The same values as stacking `residual` and `jacobian`."""
        joints = ev.joints
        d = jac.joints.shape[-1]
        batch = joints.shape[:-2]
        flat = joints.reshape(-1, *joints.shape[-2:])  # (B, J, 3)
        energy = flat.new_zeros(flat.shape[0])
        h = flat.new_zeros(flat.shape[0], d, d)
        g = flat.new_zeros(flat.shape[0], d)
        b, k, caps = self._maybe(flat)
        if b.numel():
            pairs = self.pairs.to(joints.device)
            ca, cb = pairs[k, 0], pairs[k, 1]
            p0, p1, q0, q1 = (caps[e][b, c].T for e, c in ((0, ca), (1, ca), (0, cb), (1, cb)))  # (3, A) each
            u, v, w = p1 - p0, q1 - q0, p0 - q0
            with torch.no_grad():
                s, t = _closest_parameters(u, v, w)
            gap = w + s * u - t * v
            dist = torch.sqrt((gap * gap).sum(0) + self.eps * self.eps)
            r = (self._reach.to(joints)[k] - dist - self.margin).clamp(min=0.0) / self.sigma  # (A,)
            hit = (r > 0).nonzero()[:, 0]  # the penetrating entries
            if hit.numel():
                b, k, r, s, t = b[hit], k[hit], r[hit], s[hit], t[hit]
                n = (gap[:, hit] / dist[hit]).T * (-1.0 / self.sigma)  # (A', 3) d r / d gap
                coef = torch.stack([1 - s, s, t - 1, -t], dim=-1)  # (A', 4)
                idx = self._ends.to(joints.device).view(4, -1)[:, k].T  # (A', 4) joints of the ends
                dx = jac.joints.reshape(-1, *jac.joints.shape[-3:])[b[:, None], idx]  # (A', 4, 3, D)
                rows = ((coef[..., None] * n[:, None, :])[..., None] * dx).sum((1, 2))  # (A', D)
                energy.index_add_(0, b, 0.5 * r.square())
                h.index_add_(0, b, rows[:, :, None] * rows[:, None, :])
                g.index_add_(0, b, rows * r[:, None])
        return energy.reshape(batch), h.reshape(*batch, d, d), g.reshape(*batch, d)

    @staticmethod
    def for_skeleton(
        sk: Skeleton,
        radii: Tensor | Mapping[str, float] | None = None,
        min_hops: int = 2,
        sigma: float = 0.01,
        margin: float = 0.0,
        radius_scale: float = 0.5,
        skip: Sequence[str] = DEFAULT_SKIP,
        exclude: Sequence[tuple[str, str]] = (),
    ) -> SelfIntersection:
        """The term for a skeleton (defaults measured on CMU motion: see the module docstring).

        One capsule per bone of non-zero length, named by its child joint, from `sk.bones()`.
        radii: None = `ptrack.observe.silhouette.capsule_radii`; a (B,) tensor in `sk.bones()` order; or a
        {bone name: radius} mapping overriding some of those. Each is multiplied by radius_scale.
        Pairs checked: every two capsules more than `min_hops` apart in the bone graph (bones
        sharing a joint are 1 hop apart; a zero-length bone's two joints count as one), except the
        bones matching a `skip` pattern (fnmatch, case-insensitive) and the `exclude` name pairs.
        """
        if isinstance(min_hops, bool) or int(min_hops) != min_hops or min_hops < 1:
            raise InputError(f"SelfIntersection.for_skeleton: min_hops must be an integer >= 1, got {min_hops!r}")
        check_positive("SelfIntersection.radius_scale", radius_scale)
        if isinstance(skip, str):
            raise InputError(
                f"SelfIntersection.for_skeleton: skip must be a sequence of patterns, got the string {skip!r}"
            )
        bones = sk.bones()
        names = [sk.joint_names[c] for _, c in bones]
        lengths = torch.as_tensor(sk.lengths, dtype=torch.float64)[[c for _, c in bones]]
        base = capsule_radii(names, lengths)
        if isinstance(radii, Mapping):
            unknown = sorted(set(radii) - set(names))
            if unknown:
                raise InputError(f"SelfIntersection.for_skeleton: radii name unknown bones {unknown}")
            base = torch.tensor([float(radii.get(n, r)) for n, r in zip(names, base.tolist())], dtype=torch.float64)
        elif radii is not None:
            base = as_float_tensor(radii, "radii").to(torch.float64)
            if base.shape != (len(bones),):
                raise InputError(
                    f"SelfIntersection.for_skeleton: radii must have shape "
                    f"({len(bones)},), one per bone of sk.bones(), got {shape_of(base)}"
                )
        excluded = set()
        for pair in exclude:
            if isinstance(pair, str) or len(pair) != 2 or any(n not in names for n in pair):
                raise InputError(
                    f"SelfIntersection.for_skeleton: exclude entry {pair!r} must be two bone names of the skeleton"
                )
            excluded.add(frozenset(pair))
        zero = (lengths <= 0).tolist()
        rep = _joint_classes(bones, zero, sk.num_joints)
        hops = _hop_distances([(rep[p], rep[c]) for p, c in bones], sk.num_joints)
        keep = [
            i
            for i, n in enumerate(names)
            if not zero[i] and not any(fnmatch.fnmatch(n.lower(), pat.lower()) for pat in skip)
        ]
        pairs = [
            (a, b)
            for a in range(len(keep))
            for b in range(a + 1, len(keep))
            if hops[keep[a]][keep[b]] > min_hops and frozenset((names[keep[a]], names[keep[b]])) not in excluded
        ]
        return SelfIntersection(
            segments=torch.tensor([bones[i] for i in keep], dtype=torch.long).reshape(-1, 2),
            radii=(base[keep] * radius_scale).to(torch.get_default_dtype()),
            pairs=torch.tensor(pairs, dtype=torch.long).reshape(-1, 2),
            sigma=sigma,
            margin=margin,
            names=tuple(names[i] for i in keep),
        )
