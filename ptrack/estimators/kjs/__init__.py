"""`method: kjs` (kinematic jumps + covariance scaled diffusion), `css` and `ss`: mixture density
propagation trackers (Sminchisescu & Triggs 2003, figs. 4-5).

The posterior of each frame is a mixture of K modes (`ptrack.hypotheses.mixture.Modes`). One step of the tracker,
from frame t-1's modes to frame t's:

1. predict: each mode's centre is carried to frame t (constant position; its prior below is the
   dynamics' velocity noise, per dof from real motion, `kjs.dynamics`);
2. diffusion: samples around the modes, mode m getting a share of the budget by its weight, drawn
   from its covariance scaled by `kjs.scale` (CSS), or isotropically with the same volume (SS), with
   Gaussian, Student-t or Cauchy tails, then projected onto the joint limits;
3. jumps (kjs only): each sample picks a chain by the covariance vote of its mode (the chain holding
   most of the mode's uncertainty is flipped most often), the chain's interpretation tree is grown
   through the observed 2D joints of frame t (`ptrack.hypotheses.jumps`), and every leaf is turned back into
   angles by closed-form IK (`ptrack.hypotheses.ik`); leaves outside the limits are pruned or projected;
4. polishing: every hypothesis (the predicted modes, the samples, the leaves: `kjs.samples` in all,
   the same budget for kjs, css and ss) runs a batched Levenberg-Marquardt or L-BFGS
   (`ptrack.optim.solvers`) on robust reprojection + joint limits + body non-self-intersection + the
   prior around its mode's prediction;
5. distinct minima (two hypotheses are one when no joint coordinate differs by more than
   `kjs.distinct_mm`; with distinct_mm 0, when no dof differs by more than `kjs.distinct_deg`),
   weights ∝ prior * exp(-cost / temperature) (the prior: `kjs.reweight`, below), the K
   heaviest kept, each with the covariance scale * (Gauss-Newton Hessian)^-1 for the next frame's diffusion.

The polishing objective holds robust reprojection, joint limits, body non-self-intersection, the
dynamics (a prior around each mode's prediction, std per dof `kjs.dynamics` (or `kjs.prior_sigma`), widened by
`kjs.motion_scale` times the mode's last motion, Gaussian within `kjs.prior_tail_scale` std and
heavy-tailed beyond (`kjs.prior_tail`, cauchy: the paper's long-tailed components), so a limb
flipped far from the prediction remains a minimum of comparable cost) and a weak CMU pose prior
(`kjs.pose_prior_weight`, `ptrack.body.pose_prior`). Limits, priors and collision are folded into the
normal equations rather than stacked as residual rows (`ptrack.costs.Objective.linearize`).

Frame 0 starts from a 3D keyframe (`kjs.init: keyframe`), or, with no 3D input (`init: tree`), from
the rest pose placed in view under `kjs.init_yaws` headings (each also leaned forward and back),
fitted to frame 0's 2D rigidly and then in every dof under the pose prior; the `kjs.init_fits` best
fits that differ in 3D are expanded by every flip combination of the chains (the product of their
trees), the 4K of lowest frame-0 cost without the start prior refined, and the K best distinct minima
kept. A frame with no observed keypoint is carried by the dynamics.

The output's `hypotheses` are the K modes of each frame after the stages below. Their weights and the best
trajectory come from one model of the whole lattice (`lattice.chain_terms`): a chain whose states are each
frame's modes, with each mode's own frame cost as its emission (data, limits, collision, pose prior;
`frame_evidence`, a negative log-likelihood) and a Gaussian velocity prior between consecutive modes' joints
relative to the root (std `kjs.viterbi_sigma_m` per frame) as its transition. `hypothesis_weights` are each
mode's posterior probability given the whole clip under that chain (forward-backward, the stage `decode`), and
`q`/`joints` its MAP path (Viterbi, `best_path`); after a keyframe start frame 0's emission also holds the keyframe's
prior (`keyframe_cost`). On the held-out clips this took the best trajectory from 33.5 to 29.3 mm and the share of
frames whose heaviest mode is within 10 mm of the best one from 0.70 to 0.86 (docs/results.md). Without `decode` in
`kjs.stages` a run reports the passes' own
weights and the Viterbi path of the forward pass's modes, as before.

Inside the passes a new minimum's weight is its prior times exp(-cost / `kjs.temperature`). With
`kjs.reweight: memory` the prior is its parent mode's weight to the power `kjs.weight_memory`; with `mixture`
it is the predicted mixture at the minimum, the sum over the previous modes of weight times the dynamics'
density around that mode's prediction (the paper's, `step.prior_weights`).

A second pass runs backwards in time (`kjs.backward_pass: always`; `tree`: after a tree start only). After a tree
start it is a pass of its own, from a tree start on the last frame, with its own generator (`run_pass`): without 3D
input the forward pass can hold a limb's wrong branch, or the whole body's, from frame 0 on, and the backward pass
brings the later reading back. The two passes then run at once in two processes when torch may use two threads
(`ptrack.threads.in_two_processes`), with the same result as one after the other. After a keyframe start it
starts from the forward pass's last modes (`backward_start`), and each backward step also from the forward pass's
modes of the frame after (`feed_backward`): where a limb crosses
the image plane both passes lag on the side they came from, and the forward pass's true reading, found a
few frames after the crossing in a light mode, is carried back to the crossing; the backward pass keeps
the heaviest mode of each depth order of the limbs before any order's second (`_orders_first`), so that
such a light mode is not crowded out by many heavier copies of the other reading. Each frame's K
hypotheses are taken from both passes in turn (`merge_mixtures`): the forward trajectory's mode first, then each
pass's heaviest, each depth order of the limbs before any order twice. After a tree start the backward pass's
own modes lead the merge when the two passes' trajectories face directions more than `HEADING_SPLIT_DEG` apart
(two readings of the whole body) and it costs less (`lead_pass`).

What follows the passes is a list of named stages, `kjs.stages` (`lattice.STAGES`; default `[smooth, recombine,
decode]`), each taking the lattice and the best trajectory's mode per frame and returning both.

`smooth`: one sweep of a smoother (`smooth_lattice`; named twice, two sweeps) re-polishes every frame's
hypotheses with the prior around the mean of their nearest neighbours in the frames before and after. The passes are
filters: each mode holds its own frame's evidence and the past's (or the future's), so its depth jitters from frame to
frame where the 2D leaves it loose; the smoother brings in both sides.

`recombine` (`recombine`): each frame gets one more hypothesis: the forward pass's best trajectory's
pose with each chain's reading (which way each limb points in depth) chosen on its own, by a Viterbi pass per
chain over the modes' readings of it. The modes hold the readings in combinations, and often none holds the
right reading of every limb at once. It replaces a light mode.

`decode` (last when named): the chain model above gives the final modes their posterior weights and the MAP
path.

The package: `model` (the fixed setup, each frame's objective and polishing), `step` (one tracking step),
`start` (the starts of both passes), `lattice` (the lattice record, its chain model with the posterior and the
MAP path, the smoother, the recombination, the named stages) and `track`
(the loop and the estimators).
"""

from ptrack.estimators.kjs.config import KjsMethodConfig
from ptrack.estimators.kjs.lattice import principal_directions
from ptrack.estimators.kjs.model import CSS, KJS, SS, Setup, Strategy
from ptrack.estimators.kjs.track import estimate_css, estimate_kjs, estimate_ss, track

__all__ = [
    "CSS",
    "KJS",
    "SS",
    "KjsMethodConfig",
    "Setup",
    "Strategy",
    "estimate_css",
    "estimate_kjs",
    "estimate_ss",
    "principal_directions",
    "track",
]
