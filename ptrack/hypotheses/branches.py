"""The flip branches of a trajectory's posterior: which depth interpretation each limb takes per frame.

A monocular frame fixes each limb's image, not its depth: every link of a kinematic chain can take
either intersection of its camera ray with the sphere of its bone length (`ptrack.hypotheses.jumps`). A MAP
trajectory sits on one branch per chain and frame, and a Laplace approximation at it only sees the
curvature there, not the other branches' probability. This module puts them into the posterior:

1. `branch_poses`: at the trajectory q (B, T, D), each chain's interpretation tree through q's own
   projections (every leaf reprojects the chain's joints where q does) and closed-form IK
   (`ptrack.hypotheses.ik`, "project": angles clamped into the limits, the leaf then paying whatever image
   error that leaves) give L = 2^n poses per chain and frame, labelled by depth (leaf l: link k's
   end beyond its start along the camera ray iff bit k of l is set), so leaf l over time is one
   continuous branch; q is on one of them at each frame.
2. `relax_branches`: each leaf's whole trajectory, a rigid flip of q's, re-solved by the
   trajectory's own Levenberg-Marquardt in every dof: the nearest minimum of the objective to that
   branch. Where the flipped branch is not a minimum of its own it falls back onto q (or another
   leaf); where it is, it joins q smoothly at the keyframes and where the branches meet.
3. `branch_marginals`: "which leaf trajectory chain c follows at frame t" is a hidden state s_t
   with the energy (negative log posterior) the batch objective gives the stitched trajectory:

       E(s) = sum_t U_t(s_t) + sum_t V_t(s_t, s_{t+1}) + sum_t A_t(s_t, s_{t+1}, s_{t+2})

   U_t the frame's own terms (data, joint limits, keyframes: `frame_energy`) at leaf s_t's pose, V
   and A the first- and second-difference smoothing energies between consecutive frames' leaf
   poses: the objective's own smoothing terms (`ptrack.costs.Smoothness`) on each path of 2 and 3 frames
   (the prior is per dof, so a stitched path's smoothing energy is exactly these). The
   acceleration term is third-order; it is kept exactly by forward-backward on pair states
   (s_{t-1}, s_t), so the marginals p_t(s) are exact for this energy over these candidates. A leaf
   that repeats a lower one at a frame (`repeats`) is not a second state there.
4. `mixture_variance`: the joints' second moment about q under each chain's mixture,
   sum_c sum_s p_t(s) |X_j(q_t^{c,s}) - X_j(q_t)|^2, added by the caller to the Laplace variance
   (`ptrack.estimators.batch.joint_std`): the moment-matched spread about the estimate reported.

Approximations: each branch is weighed by its energy alone (its Laplace volume, the
log-determinant of its Hessian, taken equal to q's) and spread with q's covariance; the chains are
weighed separately and their second moments added (a re-solved leg may also move the pelvis,
which another chain's leaves move too); the candidates are the minima the rigid flips lead to, not
every minimum (a branch switch at a time no leaf trajectory switches at is not represented).

Shapes: `B` trajectories, `C` chains, `L` leaves (the largest 2^n; smaller chains padded with
invalid leaves), `T` frames, `D` dofs, `J` joints. Dtype and device follow q.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from ptrack.body.skeleton import Skeleton
from ptrack.costs import PoseEval, Smoothness
from ptrack.hypotheses.ik import ChainIK, chain_ik
from ptrack.hypotheses.jumps import Chain, interpretation_tree
from ptrack.observe.camera import Camera


class Branches(NamedTuple):
    """Branch poses of C chains at a trajectory.

    q: (B, C, L, T, D) each chain's leaf trajectories (depth-labelled, `branch_poses`; rigid leaves
        keep every dof off the chain at the trajectory's values, re-solved ones move any).
    valid: (B, C, L, T) bool, the leaf exists at that frame (IK reached a pose for its label; the
        chain has that many leaves; not a repeat of a lower leaf).
    dofs: (C, D) bool, the dofs each chain's leaves move (its IK's, and any a re-solve moved): the
        smoothing energies between leaves are summed over these.
    """

    chains: tuple[Chain, ...]
    q: Tensor
    valid: Tensor
    dofs: Tensor


class BranchPosterior(NamedTuple):
    """The branch marginals of C chains at a trajectory (`branch_posterior`).

    branches: the leaf poses (`Branches`).
    unary: (B, C, L, T) each leaf's frame energy above the trajectory's (inf where not valid).
    prob: (B, C, L, T) the marginal probability of each leaf per frame (sums to 1 over L).
    joints: (B, C, L, T, J, 3) metres, each leaf's joints.
    variance: (B, T, J) m^2, the mixture's second moment of each joint about the trajectory's.
    """

    branches: Branches
    unary: Tensor
    prob: Tensor
    joints: Tensor
    variance: Tensor


def branch_poses(
    sk: Skeleton, camera: Camera, q: Tensor, chains: Sequence[Chain], plans: Sequence[ChainIK]
) -> Branches:
    """Every leaf of every chain's interpretation tree at q (B, T, D) through q's own projections,
    turned into poses by closed-form IK (limits "project"), and labelled by depth: leaf l has link k's
    end beyond its start along the camera ray iff bit k of l is set. The tree's own labels (flip or
    keep relative to q) change meaning wherever q's limb turns through the plane facing the camera;
    depth labels do not, so leaf l over time is one continuous branch, and q lies on leaf l_t at
    each frame (l_t changing where branches meet). A label without a leaf of its own (a ray tangent
    to its sphere: both depths one point) takes the leaf with the fewest other labels.
    Angles of unlimited dofs are taken nearest to q's (the same rotation). -> `Branches`."""
    b_len, t_len, d = q.shape
    cam = camera.to(device=q.device, dtype=q.dtype)
    joints = sk.forward_kinematics(q)  # (B, T, J, 3)
    pixels = cam.project(joints).pixels
    conf = torch.ones(joints.shape[:-1], dtype=q.dtype, device=q.device)
    lower, upper = sk.limits(dtype=q.dtype, device=q.device)
    angular = torch.as_tensor(sk.angular_dofs(), device=q.device)
    unlimited = angular & ~(torch.isfinite(lower) & torch.isfinite(upper))
    leaves = max(c.num_leaves for c in chains)
    out = q[:, None, None].repeat(1, len(chains), leaves, 1, 1)  # (B, C, L, T, D)
    valid = torch.zeros(b_len, len(chains), leaves, t_len, dtype=torch.bool, device=q.device)
    dofs = torch.zeros(len(chains), d, dtype=torch.bool, device=q.device)
    for c, (chain, plan) in enumerate(zip(chains, plans)):
        n, n_leaves = chain.num_links, chain.num_leaves
        tree = interpretation_tree(chain, joints, cam, pixels, conf)  # positions (B, T, L_c, n+1, 3)
        ik = chain_ik(plan, q, tree.positions, mode="project")
        lq = ik.q  # (B, T, L_c, D)
        turn = torch.remainder(lq - q[:, :, None] + torch.pi, 2 * torch.pi) - torch.pi
        lq = torch.where(unlimited, q[:, :, None] + turn, lq)
        ok = ik.keep & torch.isfinite(lq).all(-1)  # (B, T, L_c)
        _, ray = cam.rays(pixels[:, :, list(chain.joints[1:])])  # (B, T, n, 3)
        pos = tree.positions
        deeper = ((pos[..., 1:, :] - pos[..., :-1, :]) * ray[:, :, None]).sum(-1) > 0  # (B, T, L_c, n)
        code = (deeper.long() << torch.arange(n, device=q.device)).sum(-1)  # (B, T, L_c)
        labels = torch.arange(n_leaves, device=q.device)
        differ = code[..., None, :] ^ labels[:, None]  # (B, T, L_c label, L_c leaf)
        hamming = sum(((differ >> k) & 1) for k in range(n))
        cost = torch.where(ok[..., None, :], hamming, n + 1)
        pick = cost.argmin(-1)  # (B, T, L_c): the leaf taken for each label
        has = cost.gather(-1, pick[..., None])[..., 0] <= n
        chosen = lq.gather(2, pick[..., None].expand(*pick.shape, d))  # (B, T, L_c, D)
        chosen = torch.where(has[..., None], chosen, q[:, :, None])
        out[:, c, :n_leaves] = chosen.movedim(2, 1)
        valid[:, c, :n_leaves] = has.movedim(2, 1)
        dofs[c, list(plan.dofs)] = True
    return Branches(tuple(chains), out, valid, dofs)


def relax_branches(starts: Tensor, solve: Callable[[Tensor], Tensor], q: Tensor | None = None) -> Tensor:
    """Start trajectories re-solved: the nearest minimum of the whole objective to each, by the
    trajectory solver `solve` (N, T, D) -> (N, T, D) (`method: batch`'s Levenberg-Marquardt in every
    dof, `ptrack.estimators.batch.solve_trajectory`). A rigid flip switches branch with a jump in the
    chain's angles and leaves the rest of the body where q had it; the re-solved trajectory leaves and
    rejoins q smoothly where the branches meet, and moves whatever else the other branch needs (a
    flipped leg tilts the pelvis), so the smoothing energy of a switch is what the objective says.

    starts (B, C, L, T, D) -> (B, C, L, T, D), one chain's leaves at a time (L times the solve's memory,
    not C L; all 20 leaves of a CMU skeleton in one batch were 4x slower per leaf on 148 frames). With
    the trajectory q (B, T, D), a start equal to q at every frame (q on that leaf throughout) is q's own
    minimum: returned as q, not re-solved."""
    t_len, d = starts.shape[-2:]
    out = starts.clone()
    for c in range(starts.shape[1]):
        flat = starts[:, c].reshape(-1, t_len, d)
        todo = torch.ones(flat.shape[0], dtype=torch.bool, device=starts.device)
        if q is not None:
            todo = ~(starts[:, c] == q[:, None]).all(-1).all(-1).reshape(-1)
        if bool(todo.any()):
            part = flat.clone()
            part[todo] = solve(flat[todo])
            out[:, c] = part.reshape(starts[:, c].shape)
    return out


#: leaves whose joints all lie within this of a lower leaf's at a frame are that leaf there (the same
#: minimum to the solver's precision, or both depths of a tangent ray), not a second state
SAME_M = 1e-3


def repeats(joints: Tensor, valid: Tensor) -> Tensor:
    """Leaves that repeat a valid lower leaf at a frame (every joint within `SAME_M`): joints
    (B, C, L, T, J, 3), valid (B, C, L, T) -> (B, C, L, T) bool (never leaf 0). Counting a minimum
    once per frame keeps the discrete states distinct trajectories."""
    out = torch.zeros_like(valid)
    for leaf in range(1, joints.shape[2]):
        gap = (joints[:, :, leaf : leaf + 1] - joints[:, :, :leaf]).norm(dim=-1).amax(-1)  # (B, C, leaf, T)
        out[:, :, leaf] = ((gap <= SAME_M) & valid[:, :, :leaf]).any(2)
    return out


def smoothing_factors(x: Tensor, smooth: Sequence[Smoothness]) -> tuple[Tensor | None, Tensor | None]:
    """The smoothing energy between consecutive frames' states, the shared terms' own: each order-n part of
    each term (`Smoothness.orders`, n = 1 or 2) priced on every path of n+1 frames through the states.

    x (..., S, T, m) each state's trajectory of m dofs; smooth: `Smoothness` terms on q over those m dofs
    (`Smoothness.select`). -> pair (..., T-1, S, S) [t, a, b] the first-difference energy from state a at t to b
    at t+1, triple (..., T-2, S, S, S) [t, a, b, c] the second difference's over t, t+1, t+2; None for an order
    the terms lack (or too few frames)."""
    t_len = x.shape[-2]
    x = x.transpose(-3, -2)  # (..., T, S, m)
    windows = {}  # n -> (..., T-n, S, .., S, n+1, m): every path of states over frames t .. t+n
    if t_len > 1:
        windows[1] = torch.stack(torch.broadcast_tensors(x[..., :-1, :, None, :], x[..., 1:, None, :, :]), -2)
    if t_len > 2:
        ends = (x[..., :-2, :, None, None, :], x[..., 1:-1, None, :, None, :], x[..., 2:, None, None, :, :])
        windows[2] = torch.stack(torch.broadcast_tensors(*ends), -2)
    energy: dict[int, Tensor] = {}
    for term in smooth:
        for n, part in term.orders():
            if n not in (1, 2):
                raise ValueError(f"smoothing_factors: difference order {n} is not 1 or 2")
            if n not in windows:
                continue
            q = windows[n]
            e = part.energy(PoseEval(q, q.new_zeros(0), q.new_zeros(0), q.new_zeros(0)))
            energy[n] = e if n not in energy else energy[n] + e
    return energy.get(1), energy.get(2)


def forward_backward(unary: Tensor, pair: Tensor | None = None, triple: Tensor | None = None) -> Tensor:
    """Exact marginals of p(s) ~ exp(-E(s)) over state paths s_0 .. s_{T-1} for a second-order chain:

        E(s) = sum_t unary[t, s_t] + sum_t pair[t, s_t, s_{t+1}] + sum_t triple[t, s_t, s_{t+1}, s_{t+2}]

    unary (..., T, L) (inf = impossible state), pair (..., T-1, L, L), triple (..., T-2, L, L, L),
    each optional factor None = absent. -> (..., T, L) probabilities. Forward-backward on pair states
    (s_{t-1}, s_t) in log space: O(T L^3)."""
    t_len, n = unary.shape[-2], unary.shape[-1]
    lu = -unary
    if t_len == 1:
        return torch.softmax(lu, -1)
    lead = unary.shape[:-2]
    zero2 = unary.new_zeros(*lead, n, n)
    zero3 = unary.new_zeros(*lead, n, n, n)
    lp = [zero2 if pair is None else -pair[..., t, :, :] for t in range(t_len - 1)]
    lt = [zero3 if triple is None else -triple[..., t, :, :, :] for t in range(t_len - 2)]
    # alpha[t] (..., L, L) over (s_{t-1}, s_t), t = 1 .. T-1: everything up to frame t
    alpha = [lu[..., 0, :, None] + lu[..., 1, None, :] + lp[0]]
    for t in range(1, t_len - 1):  # to (s_t, s_{t+1})
        step = alpha[-1][..., :, :, None] + lt[t - 1]  # (..., a, b, c)
        alpha.append(torch.logsumexp(step, -3) + lp[t] + lu[..., t + 1, None, :])
    beta = [torch.zeros_like(alpha[-1])]  # beta[t] over (s_{t-1}, s_t): everything after frame t
    for t in range(t_len - 2, 0, -1):  # beta over (s_{t-1}, s_t) from beta over (s_t, s_{t+1})
        step = lt[t - 1] + (lp[t] + lu[..., t + 1, None, :] + beta[-1])[..., None, :, :]
        beta.append(torch.logsumexp(step, -1))
    beta.reverse()
    out = []
    for t in range(1, t_len):
        joint = alpha[t - 1] + beta[t - 1]  # (..., L, L) over (s_{t-1}, s_t)
        joint = joint - torch.logsumexp(joint.flatten(-2), -1)[..., None, None]
        if t == 1:
            out.append(torch.logsumexp(joint, -1).exp())
        out.append(torch.logsumexp(joint, -2).exp())
    return torch.stack(out, -2)


def branch_marginals(branches: Branches, unary: Tensor, smooth: Sequence[Smoothness]) -> Tensor:
    """Each chain's leaf marginals per frame: unary (B, C, L, T) frame energies above the trajectory's
    (inf where not valid) and the smoothing prior's terms on q (D dofs) between the leaf poses, on the chain's
    dofs (`smoothing_factors`) -> (B, C, L, T) probabilities (module docstring, 3)."""
    out = []
    u = torch.where(branches.valid, unary, torch.full_like(unary, torch.inf)).transpose(-2, -1)  # (B, C, T, L)
    for c in range(branches.q.shape[1]):
        idx = branches.dofs[c].nonzero()[:, 0]
        pair, triple = smoothing_factors(branches.q[:, c].index_select(-1, idx), [t.select(idx) for t in smooth])
        out.append(forward_backward(u[:, c], pair, triple).transpose(-2, -1))
    return torch.stack(out, 1)


def mixture_variance(joints: Tensor, branch_joints: Tensor, prob: Tensor) -> Tensor:
    """The branches' second moment of each joint about the trajectory's: joints (B, T, J, 3), branch
    joints (B, C, L, T, J, 3), prob (B, C, L, T) -> (B, T, J) m^2 = sum_c sum_l p |X_l - X|^2."""
    d2 = (branch_joints - joints[:, None, None]).square().sum(-1)  # (B, C, L, T, J)
    return (prob[..., None] * d2).sum((1, 2))


def branch_posterior(
    sk: Skeleton,
    camera: Camera,
    q: Tensor,
    chains: Sequence[Chain],
    plans: Sequence[ChainIK],
    frame_energy: Callable[[Tensor], Tensor],
    smooth: Sequence[Smoothness],
    relax: Callable[[Tensor, Tensor], Tensor] | None = None,
) -> BranchPosterior:
    """The flip branches of trajectory q (B, T, D) in its posterior (module docstring).

    frame_energy: trajectories (N, T, D) -> (N, T) the objective's per-frame terms (everything but
    the smoothing prior); smooth: the prior, `Smoothness` terms on q (the objective's own, robust loss included);
    relax: (starts (B, C, L, T, D), q) -> the leaves re-solved (e.g. `relax_branches`), None = the
    rigid leaves."""
    br = branch_poses(sk, camera, q, chains, plans)
    if relax is not None:
        moved = relax(br.q, q)
        dofs = (moved != q[:, None, None]).any(-2).any(2).any(0)  # (C, D): the dofs the leaves move
        br = Branches(br.chains, moved, br.valid.any(-1, keepdim=True).expand_as(br.valid), dofs | br.dofs)
    branch_joints = sk.forward_kinematics(br.q)  # (B, C, L, T, J, 3)
    br = br._replace(valid=br.valid & ~repeats(branch_joints, br.valid))
    b_len, c_len, leaves_n, t_len, d = br.q.shape
    energy = frame_energy(br.q.reshape(-1, t_len, d)).reshape(b_len, c_len, leaves_n, t_len)
    unary = energy - frame_energy(q)[:, None, None]  # above q's (a constant per frame: cancels)
    unary = torch.where(br.valid, unary, torch.full_like(unary, torch.inf))
    prob = branch_marginals(br, unary, smooth)
    variance = mixture_variance(sk.forward_kinematics(q), branch_joints, prob)
    return BranchPosterior(br, unary, prob, branch_joints, variance)


__all__ = [
    "BranchPosterior",
    "Branches",
    "branch_marginals",
    "branch_poses",
    "branch_posterior",
    "forward_backward",
    "mixture_variance",
    "relax_branches",
    "repeats",
    "smoothing_factors",
]
