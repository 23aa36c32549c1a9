"""Where the mixture trackers start: frame 0's 3D keyframe (`kjs.init: keyframe`), or, with no 3D input
(`kjs.init: tree`), the rest pose fitted to one frame's 2D under several headings and expanded by every
flip combination of the chains; and the backward pass's start and feed from the forward pass.

Shapes: N candidates, D dofs, K modes (`kjs.modes`)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ptrack.errors import EstimationError
from ptrack.estimators.kjs.model import (
    KEYFRAME_SIGMA,
    Setup,
    Strategy,
    frame_evidence,
    frame_objective,
    make_modes,
    polish,
    select_modes,
)
from ptrack.estimators.kjs.step import merge_mixtures
from ptrack.hypotheses.ik import chain_ik, product_ik
from ptrack.hypotheses.jumps import interpretation_trees, joint_observations, product
from ptrack.hypotheses.mixture import Modes, distinct_minima
from ptrack.hypotheses.samplers import project_to_limits
from ptrack.optim.jacobians import objective_linearization
from ptrack.optim.solvers import levenberg_marquardt
from ptrack.problem import first_keyframe, rest_pose_in_view, root_headings


def _init_keyframe(s: Setup) -> Tensor:
    return first_keyframe(s.problem, "kjs.init", s.lower, s.upper)[None]


def _start_prior(s: Setup, q: Tensor) -> tuple[Tensor, Tensor]:
    """The prior of a start without 3D input. Each angle the CMU pose prior names (`ptrack.body.pose_prior`)
    is held near real people's mean angle with `kjs.start_prior_scale` times their spread; any other
    angle near 0 with std `kjs.rest_sigma`; the root's position near where the rigid fit of the body put
    it (std 0.1 m: monocular depth is otherwise traded for limbs tilted in depth); its rotation free.
    q (N, D) -> mean (N, D), sigma (D,)."""
    sk, k = s.problem.skeleton, s.cfg.kjs
    root = s.root
    trans = torch.zeros_like(root)
    trans[[int(d) for d in sk.translation_dof if d >= 0]] = True
    mean, std, known = s.prior
    mean = torch.where(root, q, torch.where(known, mean, torch.zeros_like(mean)).expand_as(q))
    floor = math.radians(k.floor_deg)
    sigma = torch.where(known, k.start_prior_scale * std.clamp_min(floor), torch.full_like(std, k.rest_sigma))
    sigma = torch.where(root, torch.full_like(sigma, 1e3), sigma)
    sigma = torch.where(trans, torch.full_like(sigma, 0.1), sigma)
    return mean, sigma


def _init_tree(s: Setup, t: int = 0) -> Tensor:
    """No 3D input: the rest pose in view under every heading, each fitted rigidly to frame t's 2D
    (root dofs only), then in every dof with the rest prior; the distinct fits (by cost, at most
    `kjs.init_fits`) are expanded by every flip combination of the chains. -> candidates (N, D)."""
    prob = s.problem
    sk, obs = prob.skeleton, prob.observations
    k = s.cfg.kjs
    rest = torch.clamp(rest_pose_in_view(prob, s.lower.dtype, t), s.lower, s.upper)
    q = project_to_limits(
        root_headings(s.problem.skeleton, rest, k.init_yaws, (0.0, 0.5, -0.5)),
        s.lower,
        s.upper,
        s.angular,
        mode="reflect",
    )
    lo = torch.where(s.root, s.lower, q[0])
    hi = torch.where(s.root, s.upper, q[0])
    q, _ = levenberg_marquardt(
        objective_linearization(sk, frame_objective(s, t, None), obs.camera, prob.keypoints, True),
        q,
        lo,
        hi,
        max_iter=30,
    )
    mean, sigma = _start_prior(s, q)
    q, cost, _ = polish(s, t, q, mean, 30, sigma)
    # distinct in 3D (no joint 5 cm apart): headings 2 pi apart, or the two Euler triples of one
    # rotation, are one fit
    joints = sk.forward_kinematics(q)
    pick = distinct_minima(joints.flatten(-2), cost, 0.05, limit=k.init_fits)
    fits = q[pick]
    px, conf = joint_observations(prob.keypoints, obs.keypoints[t], obs.confidence[t], sk.num_joints)
    trees = interpretation_trees(s.chains, joints[pick], obs.camera, px, conf)
    prod = product(trees)
    results = [chain_ik(plan, fits, tree.positions, mode="project") for plan, tree in zip(s.plans, trees)]
    ik = product_ik(fits, results, prod)
    keep = ik.keep & prod.unique
    keep[:, 0] = False  # leaf 0 is the fit itself, kept below whatever its IK flags say
    return torch.cat([fits, ik.q[keep]])


def first_modes(s: Setup, strategy: Strategy, t: int = 0) -> Modes:
    """The modes of a start: frame 0's keyframe (`kjs.init: keyframe`), or a tree start on frame t."""
    k = s.cfg.kjs
    if k.init == "keyframe":  # the user's 3D pose, held by a tight prior (`KEYFRAME_SIGMA`): it is their word
        q = _init_keyframe(s)
        q, cost, hessian = polish(s, 0, q, q, 20, KEYFRAME_SIGMA)
    else:
        q = _init_tree(s, t)  # many candidates: polish all briefly, the 4K most promising to convergence
        mean, sigma = _start_prior(s, q)
        q, cost, _ = polish(s, t, q, mean, k.polish_iterations, sigma)
        # "most promising" by the frame's own cost (`frame_evidence`), not with the start prior: flip combinations
        # that reproject alike differ mostly in that prior, which is per dof around real people's mean pose
        # and so would drop a raised arm (49_18) before it is ever refined; the K kept below still weigh it
        best, _ = select_modes(s, q, frame_evidence(s, t, q), torch.zeros_like(cost), 4 * k.modes)
        q, cost, hessian = polish(s, t, q[best], mean[best], 20, sigma)
    keep, w = select_modes(s, q, cost, torch.zeros_like(cost), k.modes)
    if keep.numel() == 0:
        raise EstimationError(f"method {strategy.name!r}: no start pose with a finite cost on frame {t}")
    return make_modes(s, q[keep], cost[keep], hessian[keep], w, q[keep])


def backward_start(last: Modes) -> Modes:
    """The first modes of the backward pass after a keyframe start: the forward pass's last ones, moving the other
    way. (After a tree start the backward pass is a pass of its own: a tree start on the last frame, as the
    forward pass's on the first. The forward pass may have lost the true reading of the whole body from frame 0
    on (49_18 at 2 px); the last frame's own tree start gives the backward pass a second chance at it.)"""
    return last._replace(velocity=-last.velocity)


def feed_backward(s: Setup, backward: Modes, forward: Modes) -> Modes:
    """The backward pass's modes of frame t+1 joined by the forward pass's (`merge_mixtures`, its own heaviest
    first; the forward modes' velocity turned round), before the step to frame t. A limb crossing the
    image plane is read on the wrong side by both passes when each arrives from its own side of the
    crossing, lagging behind the motion (02_01, 1 px: the left thigh over frames 9-18). The forward pass finds
    the true side a few frames after the crossing, in a light mode, and carried backwards from there
    that reading stays on its side back to the crossing. Only after a keyframe start: after a tree start
    the forward pass may hold a wrong reading of the whole body, and fed to the backward pass it crowded
    out the last frame's own tree start (dev clips at 2 px, five seeds: best-of-K 32.2 -> 35.9 mm, 49_18
    38.0 -> 67.1)."""
    return merge_mixtures(s, backward, forward._replace(velocity=-forward.velocity), int(backward.weight.argmax()))
