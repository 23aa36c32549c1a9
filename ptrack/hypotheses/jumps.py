"""Interpretation trees: the forwards/backwards flips of kinematic sub-chains that keep the image
projections of their joints (Sminchisescu & Triggs 2003, section 3, figs 1-3).

    chain = make_chain(sk, ("lclavicle", "lhumerus", "lradius"))        # or default_chains(sk)
    tree = interpretation_tree(chain, joints, camera, pixels, confidence)
    tree.positions                       # (N, L, n+1, 3): the chain's joints in each of L = 2^n leaves
    prod = product([tree_a, tree_b])     # product of independent trees: L = L_a * L_b leaves

A `Chain` is an ordered list of joints from its root outwards; each consecutive pair (p, c) is a
*link* (c a descendant of p, possibly several bones down). The tree is built from the root out:
for each link, the sphere centred on the (already chosen) parent position with radius |c - p|
(measured in the hypothesis) is pierced by the camera ray through c's observed pixel, giving

- two points: bit 0 of the link ("keep") takes the one nearer the hypothesis's own child (carried
  rigidly with the links above it), bit 1 ("flip") the other;
- one point (the ray is tangent to within `tangent_tol`): flagged `tangent`, and the flip branch
  counts as a repeat (`unique` False); the two intersections are still used as computed (they
  differ by under 2 sqrt(tangent_tol) L), or the sphere point nearest the ray when the ray passes
  just outside the sphere (within the tolerance: no penalty);
- none: both take the point of the sphere nearest the ray, flagged `infeasible`, and the gap
  (metres between ray and sphere) is added to the leaf's `penalty`;
- a missing observation (confidence <= 0 or a non-finite pixel): the link cannot flip; both
  branches keep the hypothesis's child carried rigidly with the links above (the rotation that
  took the links above to their new directions, composed from the root, is applied to it).

Leaf `l` has link k flipped iff bit k of `l` is set, so the leaf index *is* the flip bitmask; leaf 0
is the hypothesis itself when the observations are its own projections. Branches that coincide
(single-solution links) are kept, so every tree has exactly 2^n leaves (one batched shape), and
`unique` marks the leaves that do not repeat a leaf with fewer flips.

Only the chain's joints are placed. Joints past the chain's end (the hand beyond the wrist) and
unobserved joints inside a multi-bone link (the lower neck in thorax -> upper neck) are left to
inverse kinematics (`ptrack.hypotheses.ik`): its angles, through forward kinematics, carry them rigidly.

Chains whose moving parts are disjoint combine as a product of trees (paper, section 3): `product`
enumerates the combined leaves; chain c's links take bits [offset_c, offset_c + n_c) of the
combined bitmask, which again equals the combined leaf index.

Everything is batched over hypotheses x leaves in one pass (a Python loop over links only).
Shapes: `N` hypotheses (any leading batch dims), `J` joints, `n` links, `L` leaves.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise
from typing import Any, NamedTuple

import torch
from torch import Tensor

from ptrack.body.keypoints import KeypointSet
from ptrack.body.skeleton import Skeleton
from ptrack.errors import InputError
from ptrack.observe.camera import Camera

#: default chains of CMU ASF skeletons (joint = bone end): each arm from the shoulder, each leg
#: from the hip, the head from the thorax through the upper neck (all observed by the H36M-17 set)
CMU_CHAINS: dict[str, tuple[str, ...]] = {
    "larm": ("lclavicle", "lhumerus", "lradius"),  # shoulder -> elbow -> wrist
    "rarm": ("rclavicle", "rhumerus", "rradius"),
    "lleg": ("lhipjoint", "lfemur", "ltibia"),  # hip -> knee -> ankle
    "rleg": ("rhipjoint", "rfemur", "rtibia"),
    "head": ("thorax", "upperneck", "head"),  # thorax -> neck -> head top
}


@dataclass(frozen=True)
class Chain:
    """A kinematic sub-chain: joints (n+1,) skeleton indices from the root outwards, each a
    descendant of the one before; `links` are the n consecutive pairs."""

    name: str
    joints: tuple[int, ...]
    joint_names: tuple[str, ...]

    @property
    def num_links(self) -> int:
        return len(self.joints) - 1

    @property
    def num_leaves(self) -> int:
        return 1 << self.num_links

    @property
    def links(self) -> tuple[tuple[int, int], ...]:
        return tuple(zip(self.joints[:-1], self.joints[1:]))


def _is_descendant(sk: Skeleton, child: int, ancestor: int) -> bool:
    j = sk.parents[child]
    while j >= 0:
        if j == ancestor:
            return True
        j = sk.parents[j]
    return False


def path_below(sk: Skeleton, top: int, bottom: int) -> tuple[int, ...]:
    """Joints from just below `top` down to `bottom` (inclusive), `bottom` a descendant of `top`."""
    out = [bottom]
    while sk.parents[out[-1]] != top:
        out.append(sk.parents[out[-1]])
    return tuple(reversed(out))


def make_chain(sk: Skeleton, joint_names: Sequence[str], name: str | None = None) -> Chain:
    """A validated `Chain` of `sk` from joint names, root first (at least two joints; every joint a
    descendant of the previous one). Raises InputError naming the chain."""
    names = tuple(joint_names)
    label = name or "-".join(names)
    if len(names) < 2:
        raise InputError(f"chain {label!r} needs at least two joints (one link), got {list(names)}")
    if len(set(names)) != len(names):
        raise InputError(f"chain {label!r} repeats a joint: {list(names)}")
    missing = [n for n in names if n not in sk.joint_names]
    if missing:
        raise InputError(f"chain {label!r}: skeleton {sk.name!r} has no joint {missing[0]!r}")
    idx = tuple(sk.joint_names.index(n) for n in names)
    for (a, b), (na, nb) in zip(pairwise(idx), pairwise(names)):
        if not _is_descendant(sk, b, a):
            raise InputError(
                f"chain {label!r}: {nb!r} is not below {na!r} in skeleton {sk.name!r}; "
                "each joint must be a descendant of the previous one"
            )
    return Chain(name=label, joints=idx, joint_names=names)


def default_chains(sk: Skeleton, names: Sequence[str] | None = None) -> tuple[Chain, ...]:
    """The default chains of a CMU ASF skeleton (`CMU_CHAINS`: larm, rarm, lleg, rleg, head), or the
    named subset. Raises InputError if `sk` lacks a joint (other models must name their chains)."""
    keys = tuple(CMU_CHAINS) if names is None else tuple(names)
    unknown = [k for k in keys if k not in CMU_CHAINS]
    if unknown:
        raise InputError(f"unknown default chain {unknown[0]!r}; defaults: {', '.join(CMU_CHAINS)}")
    return tuple(make_chain(sk, CMU_CHAINS[k], name=k) for k in keys)


def moving_joints(sk: Skeleton, chain: Chain) -> frozenset[int]:
    """Joints a chain's flips can move: the subtree below the chain's root on the way to its first
    link's end."""
    top = path_below(sk, chain.joints[0], chain.joints[1])[0]
    return frozenset(j for j in range(sk.num_joints) if j == top or _is_descendant(sk, j, top))


def check_independent(sk: Skeleton, chains: Sequence[Chain]) -> None:
    """Raise InputError unless the chains can combine as a product: no chain moves another's root
    or any joint another moves."""
    moved = [moving_joints(sk, c) for c in chains]
    pairs = [(i, k) for i in range(len(chains)) for k in range(len(chains)) if i != k]
    for i, k in pairs:
        a, b = chains[i], chains[k]
        if b.joints[0] in moved[i]:
            raise InputError(
                f"chains {a.name!r} and {b.name!r} are not independent: {a.name!r} "
                f"moves {b.name!r}'s root {b.joint_names[0]!r}"
            )
    for i, k in pairs:
        shared = moved[i] & moved[k]
        if shared:
            raise InputError(
                f"chains {chains[i].name!r} and {chains[k].name!r} are not independent: "
                f"both move {sk.joint_names[min(shared)]!r}"
            )


# ---------------------------------------------------------------- observations


def joint_observations(
    keypoints: KeypointSet, pixels: Tensor, confidence: Tensor, num_joints: int
) -> tuple[Tensor, Tensor]:
    """Keypoint observations as per-joint arrays: pixels (..., K, 2), confidence (..., K) ->
    pixels (..., J, 2) (0 where no keypoint), confidence (..., J) (0 = missing)."""
    k = keypoints.num_keypoints
    if pixels.shape[-2:] != (k, 2) or confidence.shape[-1:] != (k,):
        raise InputError(
            f"joint_observations: pixels must be (..., {k}, 2) and confidence (..., {k}), "
            f"got {tuple(pixels.shape)} and {tuple(confidence.shape)}"
        )
    idx = keypoints.index(device=pixels.device)
    out_px = pixels.new_zeros(*pixels.shape[:-2], num_joints, 2).index_copy(-2, idx, pixels)
    conf = confidence.to(pixels)
    out_c = conf.new_zeros(*conf.shape[:-1], num_joints).index_copy(-1, idx, conf)
    return out_px, out_c


# ---------------------------------------------------------------- struct-of-arrays helpers
# The hot paths (trees here, `ptrack.hypotheses.ik`) hold vectors as (3, *M) and matrices as (3, 3, *M) (row,
# column), with hypotheses last: every elementwise op then runs over long contiguous rows. On CPU,
# torch ops broadcasting over tiny trailing dims ((..., 3) * (..., 1, 3)) are ~10x slower.


def sdot(a: Tensor, b: Tensor) -> Tensor:
    """(3, *M), (3, *M) -> (*M)."""
    return (a * b).sum(0)


def smv(r: Tensor, v: Tensor) -> Tensor:
    """(3, 3, *M) @ (3, *M) -> (3, *M)."""
    return (r * v[None]).sum(1)


def smm(a: Tensor, b: Tensor) -> Tensor:
    """(3, 3, *M) @ (3, 3, *M) -> (3, 3, *M)."""
    return a[:, 0, None] * b[0] + a[:, 1, None] * b[1] + a[:, 2, None] * b[2]


def stranspose(r: Tensor) -> Tensor:
    """Transpose: (3, 3, *M) -> (3, 3, *M)."""
    return r.transpose(0, 1)


def scross(a: Tensor, b: Tensor) -> Tensor:
    """(3, *M) x (3, *M) -> (3, *M)."""
    a0, a1, a2 = a
    b0, b1, b2 = b
    return torch.stack(torch.broadcast_tensors(a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0))


def snorm(a: Tensor) -> Tensor:
    return torch.sqrt(sdot(a, a))


def sunit(a: Tensor) -> Tensor:
    return a / snorm(a).clamp_min(torch.finfo(a.dtype).tiny)


def sconst(x: Tensor, ndim: int) -> Tensor:
    """A constant (3,) or (3, 3) shaped to broadcast against (3, *M) / (3, 3, *M) with len(M) = ndim."""
    return x.reshape(*x.shape, *([1] * ndim))


def seye(like: Tensor, ndim: int) -> Tensor:
    return sconst(torch.eye(3, dtype=like.dtype, device=like.device), ndim)


def smin_rotation(x: Tensor, y: Tensor) -> Tensor:
    """`min_rotation` on (3, *M) vectors -> (3, 3, *M)."""
    xu, yu = sunit(x), sunit(y)
    c = sdot(xu, yu)
    # within ~sqrt(eps) of opposite, the smallest rotation's axis is lost in rounding
    opposite = 1.0 + c < math.sqrt(torch.finfo(x.dtype).eps)
    x1 = torch.where(opposite, -xu, xu)
    k = scross(x1, yu)
    eye = seye(k, k.ndim - 1)
    zero = torch.zeros_like(k[0])
    kx = torch.stack([zero, -k[2], k[1], k[2], zero, -k[0], -k[1], k[0], zero]).unflatten(0, (3, 3))
    kk = k[:, None] * k[None] - sdot(k, k) * eye  # kx @ kx
    r = eye + kx + kk / (1.0 + torch.where(opposite, -c, c))  # x1 -> y
    if not bool(opposite.any()):  # one host sync; the rare case below costs as much as the rest
        return r
    # pi about u normal to x: 2 u u^T - I; u from the coordinate axis least aligned with x
    a0, a1, a2 = xu.abs()
    first = (a0 <= a1) & (a0 <= a2)
    second = ~first & (a1 <= a2)
    pick = torch.stack([first, second, ~first & ~second]).to(x)
    u = sunit(scross(xu, pick))
    half_turn = 2.0 * u[:, None] * u[None] - eye
    return torch.where(opposite, smm(r, half_turn), r)


def to_soa(x: Tensor, lead: int) -> Tensor:
    """(*M, *C) -> (*C, *M) contiguous, with len(C) = lead trailing component dims moved first."""
    return x.movedim(tuple(range(x.ndim - lead, x.ndim)), tuple(range(lead))).contiguous()


def to_aos(x: Tensor, lead: int) -> Tensor:
    """Inverse of `to_soa`: (*C, *M) -> (*M, *C) contiguous."""
    return x.movedim(tuple(range(lead)), tuple(range(x.ndim - lead, x.ndim))).contiguous()


def min_rotation(x: Tensor, y: Tensor) -> Tensor:
    """The smallest rotation taking direction x to direction y: (..., 3), (..., 3) -> (..., 3, 3).

    Exact for any pair: near-opposite directions (1 + cos < sqrt(eps), where the smallest rotation's
    axis is undefined) turn by pi about an axis normal to x, then by the small rotation from -x to y.
    """
    x, y = torch.broadcast_tensors(x, y)
    return to_aos(smin_rotation(to_soa(x, 1), to_soa(y, 1)), 2)


# ---------------------------------------------------------------- trees


class Tree(NamedTuple):
    """Interpretation tree of one chain for a batch of hypotheses (n links, L = 2^n leaves).

    positions: (N, L, n+1, 3) world positions of the chain's joints per leaf (root first, metres).
    flips: (L,) long bitmask of each leaf (bit k: link k took the other intersection) = arange(L).
    unique: (N, L) bool, False where the leaf repeats one with fewer flips (a flipped link had one
        solution: missing observation, tangent or infeasible).
    tangent: (N, L, n) bool, the link's ray touched its sphere (one solution).
    infeasible: (N, L, n) bool, the ray missed the sphere (the closest sphere point was used).
    penalty: (N, L) metres, sum over the leaf's links of the ray-to-sphere gap (0 if all feasible).
    observed: (N, n) bool, whether each link's end had an observation.
    """

    chain: Chain
    positions: Tensor
    flips: Tensor
    unique: Tensor
    tangent: Tensor
    infeasible: Tensor
    penalty: Tensor
    observed: Tensor


def _tile(x: Tensor, leaves: int) -> Tensor:
    """States indexed by the low bits of the leaf index -> all leaves: (3, S, B) -> (3, leaves, B)."""
    reps = leaves // x.shape[1]
    return x if reps == 1 else x.repeat(1, reps, 1)


def interpretation_tree(
    chain: Chain, joints: Tensor, camera: Camera, pixels: Tensor, confidence: Tensor, tangent_tol: float = 1e-6
) -> Tree:
    """All forwards/backwards flips of `chain` for each hypothesis (see the module docstring).

    Args:
        chain: the sub-chain.
        joints: (..., J, 3) hypothesised world joint positions, metres (e.g. forward kinematics).
        camera: the camera whose rays are intersected.
        pixels: (..., J, 2) observed pixel of each joint (only the chain's non-root joints are read),
            broadcastable against `joints`' batch dims (e.g. (J, 2) shared by all hypotheses);
            `joint_observations` makes it from keypoints.
        confidence: (..., J) observation confidence; <= 0 (or a non-finite pixel) = missing.
        tangent_tol: a link has one (tangent) solution when |L^2 - h^2| <= tangent_tol * L^2,
            h the ray's distance from the sphere centre (1e-6: half-chords under 0.1% of L).

    Returns:
        `Tree` with leading dims `...` in place of N. Dtype and device follow `joints`.
    """
    if not isinstance(joints, Tensor) or not joints.is_floating_point() or joints.ndim < 2 or joints.shape[-1] != 3:
        raise InputError(
            f"interpretation_tree: joints must be a floating tensor (..., J, 3), got "
            f"{tuple(getattr(joints, 'shape', ()))}"
        )
    j_count = joints.shape[-2]
    if max(chain.joints) >= j_count:
        raise InputError(f"chain {chain.name!r} uses joint {max(chain.joints)} but joints has {j_count}")
    if pixels.shape[-2:] != (j_count, 2) or confidence.shape[-1:] != (j_count,):
        raise InputError(
            f"interpretation_tree: pixels must be (..., {j_count}, 2) and confidence "
            f"(..., {j_count}), got {tuple(pixels.shape)} and {tuple(confidence.shape)}"
        )
    if not tangent_tol >= 0.0:
        raise InputError(f"tangent_tol must be >= 0, got {tangent_tol!r}")
    batch = joints.shape[:-2]
    n = chain.num_links
    leaves = chain.num_leaves
    dt, dev = joints.dtype, joints.device
    idx = torch.as_tensor(chain.joints, device=dev)
    x = joints.index_select(-2, idx).reshape(-1, n + 1, 3)
    b = x.shape[0]
    px = pixels.to(dtype=dt, device=dev).index_select(-2, idx[1:])
    conf = confidence.to(dtype=dt, device=dev).index_select(-1, idx[1:])
    px = px.expand(*batch, n, 2).reshape(b, n, 2)
    conf = conf.expand(*batch, n).reshape(b, n)
    observed = (conf > 0) & torch.isfinite(px).all(-1)  # (B, n)
    _, direction = camera.rays(torch.where(observed[..., None], px, torch.zeros_like(px)))
    origin = sconst(camera.center.to(dtype=dt, device=dev), 2)  # (3, 1, 1)
    xs = x.permute(1, 2, 0).contiguous()  # (n+1, 3, B)
    ds = direction.permute(1, 2, 0).contiguous()  # (n, 3, B)
    obs_s = observed.T.contiguous()  # (n, B)

    # states: the parent's position (3, S, B) in each of S = 2^k partial leaves (bits 0..k-1)
    parent = xs[0][:, None]
    carry: Tensor | None = None  # (3, 3, S, B) rotation of the links above, None = identity
    dup = torch.zeros(1, b, dtype=torch.bool, device=dev)
    pen = torch.zeros(1, b, dtype=dt, device=dev)
    levels = [parent]
    tangents: list[Tensor] = []
    misses: list[Tensor] = []
    for k in range(n):
        bone = (xs[k + 1] - xs[k])[:, None]  # (3, 1, B)
        length = snorm(bone)  # (1, B)
        moved = bone if carry is None else smv(carry, bone)
        ref = parent + moved  # the hypothesis's child carried with the links above
        d = ds[k][:, None]  # (3, 1, B)
        w = parent - origin
        e = w - sdot(w, d) * d  # from the ray's closest point to the centre
        h2 = sdot(e, e)
        disc = length * length - h2  # (S, B)
        tol = tangent_tol * length * length
        two = disc > tol
        s = torch.sqrt(disc.clamp_min(0.0))
        centre = parent - e
        # no intersection: the sphere point nearest the ray
        nearest = parent - length * sunit(e)
        hit = disc >= 0
        sol1 = torch.where(hit, centre + s * d, nearest)
        sol2 = torch.where(hit, centre - s * d, nearest)
        swap = sdot(sol2 - ref, sol2 - ref) < sdot(sol1 - ref, sol1 - ref)
        obs = obs_s[k]  # (B,)
        keep = torch.where(obs, torch.where(swap, sol2, sol1), ref)
        flip = torch.where(obs, torch.where(swap, sol1, sol2), ref)
        miss = obs & (disc < -tol)
        tangents.append(obs & ~two & ~miss)
        misses.append(miss)
        gap = torch.where(miss, torch.sqrt(h2) - length, torch.zeros_like(h2))
        single = ~obs | ~two
        child = torch.cat([keep, flip], dim=1)  # (3, 2S, B): the new bit k is the high bit
        if k + 1 < n:
            turn = smin_rotation(torch.cat([moved, moved], 1).expand_as(child), child - torch.cat([parent, parent], 1))
            carry = turn if carry is None else smm(turn, torch.cat([carry, carry], 2))
        dup = torch.cat([dup, dup | single], dim=0)
        pen = torch.cat([pen + gap, pen + gap], dim=0)
        parent = child
        levels.append(child)

    positions = torch.stack([_tile(p, leaves) for p in levels])  # (n+1, 3, L, B)
    tangent = torch.stack([_tile(t[None], leaves)[0] for t in tangents])  # (n, L, B)
    infeasible = torch.stack([_tile(m[None], leaves)[0] for m in misses])
    lead = (*batch, leaves)
    return Tree(
        chain=chain,
        positions=positions.permute(3, 2, 0, 1).contiguous().reshape(*lead, n + 1, 3),
        flips=torch.arange(leaves, device=dev),
        unique=(~dup).T.contiguous().reshape(lead),
        tangent=tangent.permute(2, 1, 0).contiguous().reshape(*lead, n),
        infeasible=infeasible.permute(2, 1, 0).contiguous().reshape(*lead, n),
        penalty=pen.T.contiguous().reshape(lead),
        observed=observed.reshape(*batch, n),
    )


def interpretation_trees(
    chains: Sequence[Chain],
    joints: Tensor,
    camera: Camera,
    pixels: Tensor,
    confidence: Tensor,
    tangent_tol: float = 1e-6,
) -> list[Tree]:
    """`interpretation_tree` for each chain (same arguments)."""
    return [interpretation_tree(c, joints, camera, pixels, confidence, tangent_tol) for c in chains]


# ---------------------------------------------------------------- product of trees


class Product(NamedTuple):
    """The product of independent trees (chains c = 0..C-1 with n_c links; L = prod 2^n_c leaves).

    leaf: (L, C) long, each chain's leaf index in each combined leaf.
    flips: (L,) long combined bitmask (chain c's link k is bit offset_c + k) = arange(L).
    offsets: (C,) bit offset of each chain.
    unique, penalty, infeasible: (N, L) as in `Tree` (unique and feasible only if every chain's
        leaf is; penalties add).
    """

    chains: tuple[Chain, ...]
    leaf: Tensor
    flips: Tensor
    offsets: tuple[int, ...]
    unique: Tensor
    infeasible: Tensor
    penalty: Tensor

    @property
    def num_bits(self) -> int:
        """T, the number of links of all chains: L = 2^T."""
        return sum(c.num_links for c in self.chains)

    def bits_view(self, c: int, x: Tensor, dim: int) -> Tensor:
        """Chain c's values per leaf as a view that broadcasts over the combined leaves: x with its
        L_c leaves at `dim` < 0 -> the leaf dim split into one size-2 dim per combined bit (highest
        bit first; size 1 for the other chains' bits). Broadcasting such views of several chains and
        flattening the T bit dims (expanded to 2) gives values per combined leaf without gathers."""
        d = x.ndim + dim
        n, off = self.chains[c].num_links, self.offsets[c]
        bits = [1] * (self.num_bits - off - n) + [2] * n + [1] * off
        return x.reshape(*x.shape[:d], *bits, *x.shape[d + 1 :])


def flatten_bits(x: Tensor, start: int, bits: int) -> Tensor:
    """Broadcast bit dims -> combined leaves: x (..., b_{T-1}, ..., b_0, ...) with each bit dim
    of size 1 or 2, starting at `start` -> (..., 2^T, ...)."""
    shape = list(x.shape)
    shape[start : start + bits] = [2] * bits
    return x.expand(shape).flatten(start, start + bits - 1)


def product(trees: Sequence[Tree]) -> Product:
    """Combine trees of independent chains (the caller checks independence with `check_independent`)
    over the same hypotheses into all combinations of their leaves."""
    if not trees:
        raise InputError("product needs at least one tree")
    batch = trees[0].unique.shape[:-1]
    for t in trees:
        if t.unique.shape[:-1] != batch:
            raise InputError(
                f"product: trees must share hypotheses, got batch {tuple(batch)} and "
                f"{tuple(t.unique.shape[:-1])} ({t.chain.name!r})"
            )
    bits = [t.chain.num_links for t in trees]
    offsets = tuple(int(sum(bits[:i])) for i in range(len(bits)))
    total = 1 << int(sum(bits))
    dev = trees[0].positions.device
    flips = torch.arange(total, device=dev)
    leaf = torch.stack([(flips >> o) & ((1 << nb) - 1) for o, nb in zip(offsets, bits)], dim=-1)
    # the layout only (bits_view reads chains and offsets): the last three fields are filled by _replace below
    unset: Any = None
    prod = Product(
        chains=tuple(t.chain for t in trees),
        leaf=leaf,
        flips=flips,
        offsets=offsets,
        unique=unset,
        infeasible=unset,
        penalty=unset,
    )
    unique = prod.bits_view(0, trees[0].unique, -1)
    infeasible = prod.bits_view(0, trees[0].infeasible.any(-1), -1)
    penalty = prod.bits_view(0, trees[0].penalty, -1)
    for c, t in enumerate(trees[1:], start=1):  # broadcasting over the bit dims: no gathers
        unique = unique & prod.bits_view(c, t.unique, -1)
        infeasible = infeasible | prod.bits_view(c, t.infeasible.any(-1), -1)
        penalty = penalty + prod.bits_view(c, t.penalty, -1)
    nb, start = prod.num_bits, len(batch)
    return prod._replace(
        unique=flatten_bits(unique, start, nb),
        infeasible=flatten_bits(infeasible, start, nb),
        penalty=flatten_bits(penalty, start, nb),
    )


def product_joints(joints: Tensor, trees: Sequence[Tree], prod: Product) -> Tensor:
    """Hypothesis joints with every chain's joints replaced by its leaf in each combined leaf:
    joints (..., J, 3) -> (..., L, J, 3). Other joints (hands past the wrists, ...) are unchanged;
    run IK and forward kinematics for a consistent skeleton."""
    total = prod.flips.shape[0]
    out = joints[..., None, :, :].expand(*joints.shape[:-2], total, *joints.shape[-2:]).clone()
    start = joints.ndim - 2
    for c, t in enumerate(trees):
        idx = torch.as_tensor(t.chain.joints, device=joints.device)
        out.index_copy_(-2, idx, flatten_bits(prod.bits_view(c, t.positions, -3), start, prod.num_bits))
    return out


def flip_names(prod: Product | Sequence[Chain], leaf: int) -> list[str]:
    """Human-readable flips of a (combined) leaf, e.g. ["larm:lhumerus", "head:head"]."""
    chains = prod.chains if isinstance(prod, Product) else tuple(prod)
    out, off = [], 0
    for c in chains:
        for k in range(c.num_links):
            if leaf >> (off + k) & 1:
                out.append(f"{c.name}:{c.joint_names[k + 1]}")
        off += c.num_links
    return out


__all__ = [
    "CMU_CHAINS",
    "Chain",
    "Product",
    "Tree",
    "check_independent",
    "default_chains",
    "flip_names",
    "interpretation_tree",
    "interpretation_trees",
    "joint_observations",
    "make_chain",
    "min_rotation",
    "moving_joints",
    "path_below",
    "product",
    "product_joints",
]
