"""Closed-form IK of a chain's angles (Sminchisescu & Triggs 2003, section 3.1), chosen by
`plan.ik_plan` from the skeleton:

- "limb": root -> ball -> hinge, e.g. CMU shoulder (`lclavicle`) -> elbow (`lhumerus`, a 3-dof
  ball: the humerus's rx ry rz in its ASF `axis` frame) -> wrist (`lradius`, a 1-dof hinge: the
  radius's rx); likewise hip -> knee -> ankle. The hinge angle comes from the angle between the
  two links (two candidates, t and its mirror); the ball's rotation Z is the one taking the
  upper bone and the lower bone (for that hinge angle) onto the target directions, so the
  upper bone's twist is recovered from the next joint. When the limb is straight (the targets
  collinear to `collinear_tol`) the twist is undetermined and the current one is kept: Z is the
  smallest rotation from the current upper bone direction to the target, applied to the current Z.
- "swing": every link's first joint is a 3-dof ball (e.g. thorax -> upper neck -> head: the lower
  neck turns the neck link, the head joint the head link). A single point per link fixes only
  the swing, so each ball turns by the smallest rotation taking its link onto the target and
  keeps its current twist; joints inside a link keep their angles.

Each ball's rotation has two Euler solutions (y and pi - y) and a limb's hinge two candidates, all
reproducing the same positions; the one inside the joint limits is chosen (least violation, ties going
to the nearest to the current angles: `angles.pick_candidate`). Targets x (n+1, 3, L, B), current
angles from qs (D', B); angles out (M, L, B).
"""

from __future__ import annotations

import torch
from torch import Tensor

from ptrack.hypotheses.ik.angles import pick_candidate, seuler_solutions
from ptrack.hypotheses.ik.kinematics import fk_step, seuler, slot_angles
from ptrack.hypotheses.ik.plan import ChainIK
from ptrack.hypotheses.jumps import sconst, scross, sdot, smin_rotation, smm, smv, snorm, stranspose, sunit


def _lower_bone(lc: dict, t: Tensor) -> Tensor:
    """The limb's lower bone v(t) = D Rot(n, t) c in the ball's axis frame: t (*M) -> (3, *M)."""
    nd = t.ndim
    ct, st = torch.cos(t), torch.sin(t)
    rot_c = sconst(lc["c"], nd) * ct + sconst(lc["ncross"], nd) * st + sconst(lc["n"] * lc["nc"], nd) * (1 - ct)
    return smv(sconst(lc["d"], nd), rot_c)


def limb_fk(tc: dict, a_frame: Tensor, p_r: Tensor, theta: Tensor) -> Tensor:
    """Forward kinematics of a limb: positions (3, 3, L, B) of root, ball and hinge joints from the
    ball's parent axis frame a_frame = G_r C (3, 3, 1, B), root position p_r (3, 1, B) and angles
    theta (4, L, B). The ball joint's frame is G_r C Z C^T E (`ptrack.body.skeleton`), so its bone is
    G_r C Z a and the next one G_r C Z v(t)."""
    lc = tc["limb"]
    az = smm(a_frame, seuler(theta[:3]))
    p_m = p_r + lc["length_m"] * smv(az, sconst(lc["a"], 2))
    p_e = p_m + lc["length_e"] * smv(az, _lower_bone(lc, theta[3]))
    return torch.stack(torch.broadcast_tensors(p_r, p_m, p_e))


def limb_angles(plan: ChainIK, tc: dict, a_frame: Tensor, qs: Tensor, x: Tensor, ctol: float) -> Tensor:
    """Limb angles (4, L, B) = ball (z, y, x), hinge, for targets x (3, 3, L, B) (joint, xyz, ...)."""
    lc = tc["limb"]
    cur_ball = slot_angles(tc["per"][plan.balls[0]], qs)  # (3, B)
    cur = torch.cat([cur_ball, qs[tc["hinge_row"]][None]])  # (4, B)
    at = stranspose(a_frame)
    b1 = sunit(smv(at, x[1] - x[0]))  # (3, L, B) bone directions in the ball's parent axis frame
    b2 = sunit(smv(at, x[2] - x[1]))
    cos_k = sdot(b1, b2)
    # a . v(t) = rho cos(t - phi) + gamma must equal |a||c| cos_k. Not with acos (which loses half
    # the digits at a straight limb): with h-, h+ = |b1 -+ b2|^2 / 2 (exact near 0 and pi) and
    # delta = rho - (|a||c| - gamma) <= 0, rho cos(t - phi) = rho - delta - |a||c| h-, and
    # rho^2 sin^2(t - phi) = (delta + |a||c| h-) (delta - 2 gamma + |a||c| h+).
    dm, dp = b1 - b2, b1 + b2
    hm, hp = 0.5 * sdot(dm, dm), 0.5 * sdot(dp, dp)
    ac, delta, gamma = lc["ac"], lc["delta"], lc["gamma"]
    sin_part = torch.sqrt(((delta + ac * hm) * (delta - 2.0 * gamma + ac * hp)).clamp_min(0.0))
    half = torch.atan2(sin_part, lc["rho"] - delta - ac * hm)
    t = lc["phi"] + torch.stack([half, -half])  # (2, L, B) hinge candidates
    v = _lower_bone(lc, t)  # (3, 2, L, B)
    # Z takes the frame (a, v(t)) onto the frame (b1, b2): Z = sum_i g_i f_i^T
    f1 = sconst(lc["a_unit"], 3)
    f2 = sunit(v - sdot(v, f1) * f1)
    f3 = scross(f1, f2)
    g2 = sunit(b2 - cos_k * b1)
    g3 = scross(b1, g2)
    z = b1[:, None, None] * f1[None] + g2[:, None, None] * f2[None] + g3[:, None, None] * f3[None]
    # straight limb: keep the current twist (smallest turn of the current upper bone onto b1)
    straight = snorm(scross(b1, b2)) < ctol  # (L, B)
    if bool(straight.any()):  # one host sync; skips ~60 ops when no leaf is straight
        z_cur = seuler(cur_ball)[:, :, None]  # (3, 3, 1, B)
        z_swing = smm(smin_rotation(smv(z_cur, sconst(lc["a"], 2)).expand_as(b1), b1), z_cur)
        z = torch.where(straight, z_swing[:, :, None], z)  # (3, 3, 2, L, B)
    eul = seuler_solutions(z, cur_ball[2])  # (3, 2 Euler, 2 hinge, L, B)
    cands = torch.cat([eul, t[None, None].expand(1, *eul.shape[1:])]).flatten(1, 2)  # (4, 4, L, B)
    return pick_candidate(cands, cur[:, None], tc)


def swing_angles(plan: ChainIK, tc: dict, g_r: Tensor, p_r: Tensor, qs: Tensor, x: Tensor) -> Tensor:
    """Swing angles (3 n, L, B) (each ball's z, y, x) for targets x (n+1, 3, L, B)."""
    per = tc["per"]
    frames = {plan.chain.joints[0]: (g_r, p_r)}
    g, p = g_r, p_r
    for j in plan.path:  # current frames and positions along the path (per hypothesis)
        g, p = fk_step(per[j], g, p, slot_angles(per[j], qs))
        frames[j] = (g, p)
    turn: Tensor | None = None
    out = []
    for k, ((pa, ch), ball) in enumerate(zip(plan.chain.links, plan.balls)):
        g_p = frames[pa][0][:, :, None]  # (3, 3, 1, B)
        link = (frames[ch][1] - frames[pa][1])[:, None]  # (3, 1, B)
        if turn is not None:
            g_p, link = smm(turn, g_p), smv(turn, link)
        target = x[k + 1] - x[k]
        delta = smin_rotation(link.expand_as(target), target)
        turn = delta if turn is None else smm(delta, turn)
        local = smm(stranspose(g_p), smm(turn, frames[ball][0][:, :, None]))
        if per[ball]["rest"] is not None:
            local = smm(local, sconst(per[ball]["rest"].T, 2))
        cb = sconst(per[ball]["c"], 2)
        zmat = smm(smm(stranspose(cb), local), cb)
        cur = slot_angles(per[ball], qs)[:, None]  # (3, 1, B)
        sl = slice(3 * k, 3 * k + 3)
        out.append(pick_candidate(seuler_solutions(zmat, cur[2]), cur, tc, sl))
    return torch.cat(out)


def swing_slots(plan: ChainIK, tc: dict, theta: Tensor) -> dict[int, Tensor]:
    """Solved angles (M, L, B) -> slot angles {joint: (3, L, B)} for `path_fk` (swing chains)."""
    return {b: theta[3 * i : 3 * i + 3] for i, b in enumerate(plan.balls)}
