"""After the passes: every frame's modes as a (T, K) lattice, the best trajectory through it (Viterbi),
the choice between the two passes' trajectories after a tree start, the smoother over the hypotheses and
the recombination of each chain's reading.

Shapes: T frames, K modes (`kjs.modes`), D dofs, J joints, C chains."""

from __future__ import annotations

import math
from typing import NamedTuple, Protocol

import torch
from torch import Tensor

from ptrack.body.limits import wrapped_difference
from ptrack.estimators.kjs.model import (
    Setup,
    distinct_poses,
    frame_evidence,
    keyframe_cost,
    mode_cholesky,
    polish_rows,
)
from ptrack.hypotheses.mixture import Modes, forward_backward, viterbi_with_cost


def _pad(modes: Modes, k: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Modes (M) -> (K, D) q, (K,) weights, (K,) costs, (K, D, D) covariance factors, padding with copies
    of the best at weight 0."""
    m = modes.q.shape[0]
    if m >= k:
        return modes.q, modes.weight, modes.cost, modes.chol
    fill = k - m
    return (
        torch.cat([modes.q, modes.q[:1].expand(fill, -1)]),
        torch.cat([modes.weight, modes.weight.new_zeros(fill)]),
        torch.cat([modes.cost, modes.cost[:1].expand(fill)]),
        torch.cat([modes.chol, modes.chol[:1].expand(fill, -1, -1)]),
    )


def principal_directions(sk, q: Tensor, chol: Tensor, scale: float) -> Tensor:
    """Each mode's most uncertain direction, as 3D joint displacements: the top eigenvector of its
    covariance (chol chol^T / scale: the inverse Gauss-Newton Hessian, regularised, without the
    sampling scale), one standard deviation long, through forward kinematics. The sign is fixed so
    that the eigenvector's largest entry is positive. q (..., D), chol (..., D, D) -> (..., J, 3) metres."""
    cov = chol @ chol.transpose(-1, -2) / scale
    val, vec = torch.linalg.eigh(cov)
    v = vec[..., -1]  # (..., D)
    sign = torch.sign(v.gather(-1, v.abs().argmax(-1, keepdim=True)))
    dq = v * sign * val[..., -1:].clamp_min(0).sqrt()
    return sk.forward_kinematics(q + dq) - sk.forward_kinematics(q)


class Lattice(NamedTuple):
    """Every frame's K modes: q (T, K, D), weight (T, K) (each frame's summing to 1; 0: padding, a copy of the
    frame's first mode), cost (T, K) (the tracking cost), chol (T, K, D, D) (covariance factors) and joints
    (T, K, J, 3) (the forward kinematics of q)."""

    q: Tensor
    weight: Tensor
    cost: Tensor
    chol: Tensor
    joints: Tensor


def make_lattice(s: Setup, per_frame: list[Modes]) -> Lattice:
    """Each frame's modes (T of them) padded to K, with their joints."""
    padded = [_pad(m, s.cfg.kjs.modes) for m in per_frame]
    hq, hw, hc, hl = (torch.stack(x) for x in zip(*padded))
    with torch.no_grad():
        return Lattice(hq, hw, hc, hl, s.problem.skeleton.forward_kinematics(hq))


def chain_terms(s: Setup, lat: Lattice) -> tuple[Tensor, Tensor, float]:
    """The lattice's chain model, shared by the best trajectory (`best_path`) and the mode posterior
    (`decode`) -> unary (T, K), each mode's own frame cost (`frame_evidence`; padding inf; on frame 0 after
    a keyframe start also its distance from the keyframe, `keyframe_cost`, the start's own prior), the features
    (T, K, F) of the velocity prior between consecutive modes (every joint relative to the root: the body's motion
    in metres) and its std per frame (`kjs.viterbi_sigma_m`)."""
    k = s.cfg.kjs
    hq, hw, joints = lat.q, lat.weight, lat.joints
    T, K, D = hq.shape
    rows = torch.arange(T, device=hq.device).repeat_interleave(K)  # every mode with its own frame's 2D
    unary = frame_evidence(s, rows, hq.reshape(-1, D), joints.flatten(0, 1)).reshape(T, K)
    with torch.no_grad():
        unary = torch.cat([unary[:1] + keyframe_cost(s, hq[0]), unary[1:]])
        feats = (joints - joints[..., :1, :]).flatten(-2)
        return torch.where(hw > 0, unary, torch.full_like(unary, math.inf)), feats, k.viterbi_sigma_m


def best_path(s: Setup, lat: Lattice) -> tuple[Tensor, Tensor]:
    """Viterbi through the lattice: each mode's own frame cost (`frame_evidence`) plus a velocity prior between
    consecutive choices (`kjs.viterbi_sigma_m`); padding (weight 0) is never chosen. -> mode index per frame (T,),
    and the path's cost ()."""
    return viterbi_with_cost(*chain_terms(s, lat))


def decode(s: Setup, lat: Lattice) -> tuple[Tensor, Tensor]:
    """The chain model's answers on the lattice, its terms (`chain_terms`: every mode's frame cost) computed once:
    -> the MAP path (T,) (`best_path`'s) and every mode's posterior probability given the whole clip (T, K)
    (forward-backward, `ptrack.hypotheses.mixture.forward_backward`), each frame summing to 1, padding 0; a
    mode's probability never underflows to 0 (at least the dtype's smallest normal number), so that weight 0
    still means padding to the stages after."""
    terms = chain_terms(s, lat)
    with torch.no_grad():
        post = forward_backward(*terms)
        post = torch.where(lat.weight > 0, post.clamp_min(torch.finfo(post.dtype).tiny), torch.zeros_like(post))
    return viterbi_with_cost(*terms)[0], post


# ---------------------------------------------------------------- which pass leads after a tree start


#: after a tree start, the passes' best trajectories whose bodies face directions this far apart (mean over
#: the frames, degrees) hold two readings of the whole body, and the cheaper one is taken (`lead_pass`)
HEADING_SPLIT_DEG = 30.0


def _hips(s: Setup) -> tuple[int, int] | None:
    """The skeleton joints of the keypoints that mark the landmarks "l_hip" and "r_hip" (a detector's "LHip",
    "left_hip", ...), or None when the keypoint set lacks one."""
    kp = s.problem.keypoints
    left, right = kp.find("l_hip"), kp.find("r_hip")
    if left is None or right is None:
        return None
    return kp.joints[left], kp.joints[right]


def _heading(joints: Tensor, hips: tuple[int, int]) -> Tensor:
    """The direction of the hip line (left hip minus right hip, `_hips`) about the world's up axis (+Y):
    joints (T, J, 3) -> (T,) radians."""
    line = joints[:, hips[0]] - joints[:, hips[1]]
    return torch.atan2(line[:, 2], line[:, 0])


def lead_pass(s: Setup, path: Tensor, cost: Tensor, joints: Tensor, backward: list[Modes]) -> tuple[bool, Tensor]:
    """After a tree start: does the backward pass's best trajectory replace the forward pass's? path (T,),
    cost () and joints (T, K, J, 3): the forward pass's best trajectory, its cost and its lattice's joints.
    -> (backward leads, the leading path).

    Each pass starts from its own tree start (frame 0, the last frame), and either can hold a wrong reading
    of the whole body throughout (49_18 and 49_19 at 2 px: the forward pass's body turned 48-58° from the
    truth, 240-260 mm MPJPE; the backward pass's 2-4°). Where the two trajectories face apart by more than
    `HEADING_SPLIT_DEG` on average the cheaper (frame costs plus the velocity prior, what Viterbi
    minimises) is taken: it was the right one on every such run measured. Where they face alike and differ
    limb by limb the cost does not tell them apart (the backward one was the cheaper on most held-out runs
    and worse in MPJPE on most of those), so the forward pass's stays (docs/notes/kjs-history.md). Without hip
    keypoints the forward pass's stays."""
    hips = _hips(s)
    if hips is None:
        return False, path
    back = make_lattice(s, backward)
    back_path, back_cost = best_path(s, back)
    bj = back.joints
    frames = torch.arange(path.shape[0], device=path.device)
    apart = _heading(joints[frames, path], hips) - _heading(bj[frames, back_path], hips)
    apart = torch.remainder(apart + math.pi, 2 * math.pi) - math.pi
    if float(apart.abs().mean()) > math.radians(HEADING_SPLIT_DEG) and bool(back_cost < cost):
        return True, back_path
    return False, path


# ---------------------------------------------------------------- each chain's reading on its own


#: Levenberg-Marquardt iterations of each graft in `recombine` (a mode's chain on the best trajectory's pose)
#: and of the recombined pose: the chain moves little, the rest of the body settles around it
GRAFT_ITERATIONS, RECOMBINED_ITERATIONS = 3, 5


def recombine(s: Setup, lat: Lattice, path: Tensor) -> Lattice:
    """One more hypothesis per frame: the best trajectory's pose with each chain's reading chosen on its own.

    The modes hold the chains' readings (which way each limb points in depth) in combinations: one mode
    may have the left arm right and the right leg wrong, another the reverse, and no mode both (49_18 at
    2 px after a tree start: the best trajectory's mode 99 mm off, each of two others right in one limb).
    The 2D cannot tell the combinations apart, but each chain's own reading can be followed in time. It runs
    after the smoother (`smooth_lattice`), which then does not link the best trajectory's modes to it. For
    every frame t, chain c and mode m, the chain's dofs of mode m are grafted onto the best trajectory's
    pose and polished briefly around that graft; each chain then gets its own Viterbi pass over the modes:
    the graft's frame cost (`frame_evidence`) plus a velocity prior on the graft's joints relative to the root
    (std `kjs.recombine_sigma_m` per frame). The chosen readings of all chains on the best trajectory's pose,
    polished, replace frame t's padding or its lightest mode other than the best trajectory's, with that
    slot's weight (the lightest weight for padding), unless they are a mode already (`distinct_poses`). The
    best trajectory keeps its modes. Without chains (css and ss after a keyframe start) or with K = 1 nothing
    changes. path (T,): the best trajectory's mode per frame."""
    k = s.cfg.kjs
    hq, hw, hc, hl, joints = lat
    sk = s.problem.skeleton
    T, K, D = hq.shape
    C = len(s.chains)
    if C == 0 or K < 2:
        return lat
    frames = torch.arange(T, device=hq.device)
    lead = hq[frames, path]  # (T, D)
    graft = torch.where(s.chain_dofs[None, :, None], hq[:, None], lead[:, None, None]).reshape(-1, D)  # (T C K, D)
    rows = frames.repeat_interleave(C * K)  # each graft with its own frame's 2D
    graft, _, _ = polish_rows(s, rows, graft, graft, GRAFT_ITERATIONS, s.dynamics_sigma)
    with torch.no_grad():
        j = sk.forward_kinematics(graft)
    cost_tck = torch.where(hw[:, None] > 0, frame_evidence(s, rows, graft, j).reshape(T, C, K), math.inf)
    feats_tck = (j - j[:, :1]).reshape(T, C, K, -1)  # the grafts' joints relative to the root
    choice = torch.stack([viterbi_with_cost(cost_tck[:, c], feats_tck[:, c], k.recombine_sigma_m)[0] for c in range(C)])
    new = (choice != path[None]).any(0)  # (T,): some chain takes another mode's reading
    if not bool(new.any()):
        return lat
    picked = hq[frames[:, None], choice.T]  # (T, C, D)
    q = lead
    for c in range(C):
        q = torch.where(s.chain_dofs[c], picked[:, c], q)
    todo = frames[new]
    q, cost, hessian = polish_rows(s, todo, q[new], q[new], RECOMBINED_ITERATIONS, s.dynamics_sigma)
    chol = mode_cholesky(s, hessian)
    with torch.no_grad():
        q_joints = sk.forward_kinematics(q)
    hq, hw, hc, hl, joints = hq.clone(), hw.clone(), hc.clone(), hl.clone(), joints.clone()
    for i, t in enumerate(todo.tolist()):
        real = hw[t] > 0
        pool = torch.cat([hq[t][real], q[i : i + 1]])
        rank = torch.arange(pool.shape[0], dtype=hq.dtype, device=hq.device)
        if int(distinct_poses(s, pool, rank).max()) < pool.shape[0] - 1:
            continue  # the recombined pose is one of the modes
        order = torch.where(real, hw[t], torch.full_like(hw[t], -1.0))
        order[path[t]] = math.inf
        slot = int(order.argmin())
        hq[t, slot], hc[t, slot], hl[t, slot], joints[t, slot] = q[i], cost[i], chol[i], q_joints[i]
        if not bool(real[slot]):  # padding (weight 0) takes the lightest mode's weight
            hw[t, slot] = hw[t][real].min()
            hw[t] = hw[t] / hw[t].sum()
    return Lattice(hq, hw, hc, hl, joints)


# ---------------------------------------------------------------- the smoother


#: Levenberg-Marquardt iterations of each hypothesis in a smoothing sweep (`smooth_lattice`): it starts at a
#: minimum of its own frame's objective and moves only as far as its neighbours pull it
SMOOTH_ITERATIONS = 5


def smooth_lattice(s: Setup, lat: Lattice) -> Lattice:
    """One sweep of a smoother over the finished hypothesis lattice (the stage `smooth` of `kjs.stages`; named
    twice, two sweeps). Each tracked mode holds the evidence of its own frame and, through the dynamics, of the
    frames before (a filter): its depth jitters from frame to frame wherever the 2D leaves it loose. In a sweep
    each hypothesis of frame t is linked to the nearest hypothesis of frames t-1 and t+1 (by the mean distance of
    the joints relative to the root; none where the other frame holds only padding) and polished again on frame
    t's objective with the tracking prior around the mean of its linked neighbours, std `kjs.smooth_scale` times
    the dynamics' (times sqrt 2 with one neighbour). Padding keeps its pose. Every hypothesis moves from the poses
    of the lattice it was given (Jacobi). -> the lattice with the smoothed poses, their objective, covariance and
    joints (the weights as they were)."""
    k = s.cfg.kjs
    hq, hw, hc, hl, joints = lat
    sk = s.problem.skeleton
    T, K, D = hq.shape
    base = torch.as_tensor(s.dynamics_sigma, dtype=hq.dtype, device=hq.device).expand(D) * k.smooth_scale
    frames = torch.arange(T, device=hq.device)[:, None].expand(T, K)
    rel = joints - joints[..., :1, :]  # (T, K, J, 3)
    pull = torch.zeros_like(hq)  # (T, K, D): sum of the wrapped steps to the linked neighbours
    count = torch.zeros(T, K, 1, dtype=hq.dtype, device=hq.device)
    for here, there in ((slice(1, None), slice(None, -1)), (slice(None, -1), slice(1, None))):  # t-1, t+1
        gap = (rel[here][:, :, None] - rel[there][:, None]).norm(dim=-1).mean(-1)  # (T-1, K, K)
        gap = torch.where(hw[there][:, None] > 0, gap, math.inf)
        near, j = gap.min(-1)  # (T-1, K)
        linked = torch.isfinite(near).to(hq.dtype)[..., None]
        neighbour = torch.gather(hq[there], 1, j[..., None].expand(-1, -1, D))
        pull[here] += linked * wrapped_difference(neighbour - hq[here], s.angular)
        count[here] += linked
    move = (hw > 0) & (count[..., 0] > 0)  # (T, K)
    if not bool(move.any()):
        return lat
    n = count[move]  # (M, 1): 1 or 2 linked neighbours
    q, cost, hessian = polish_rows(
        s, frames[move], hq[move], hq[move] + pull[move] / n, SMOOTH_ITERATIONS, base * torch.sqrt(2 / n), True
    )
    hq, hc, hl = hq.clone(), hc.clone(), hl.clone()
    hq[move], hc[move], hl[move] = q, cost, mode_cholesky(s, hessian)
    with torch.no_grad():
        joints = sk.forward_kinematics(hq)
    return Lattice(hq, hw, hc, hl, joints)


# ---------------------------------------------------------------- the stages after the passes


class Stage(Protocol):
    """A stage of `kjs.stages`: (setup, lattice (T, K), the best trajectory's mode per frame (T,)) -> both, new."""

    def __call__(self, s: Setup, lat: Lattice, path: Tensor) -> tuple[Lattice, Tensor]: ...


def _smooth(s: Setup, lat: Lattice, path: Tensor) -> tuple[Lattice, Tensor]:
    return smooth_lattice(s, lat), path


def _recombine(s: Setup, lat: Lattice, path: Tensor) -> tuple[Lattice, Tensor]:
    return recombine(s, lat, path), path


def _decode(s: Setup, lat: Lattice, path: Tensor) -> tuple[Lattice, Tensor]:
    map_path, posterior = decode(s, lat)
    return lat._replace(weight=posterior), map_path


#: the stages that may follow the passes, by their name in `kjs.stages`, in the order a run names them:
#: `smooth` (one sweep of `smooth_lattice`), `recombine` (one more hypothesis per frame, `recombine`) and
#: `decode` (the chain model's posterior weights and MAP path, `decode`; last when named). Without `decode`
#: the weights are the passes' own and the best trajectory the forward pass's Viterbi path.
STAGES: dict[str, Stage] = {"smooth": _smooth, "recombine": _recombine, "decode": _decode}
