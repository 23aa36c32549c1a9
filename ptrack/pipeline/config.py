"""Run configuration: frozen dataclasses hold every default; YAML files and `dotted.key=value`
overrides replace them. Unknown keys and wrong types are `InputError`s naming the dotted key.

Paths in a YAML file are relative to that file's folder; paths given as command-line overrides are
relative to the working directory. Both are stored resolved (absolute) in the run's config.yaml.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Union

import yaml

from ptrack.body.acclaim import skeleton_beside
from ptrack.body.pose_prior import check_smoothing_table
from ptrack.costs.base import ROBUST_LOSSES
from ptrack.errors import InputError

log = logging.getLogger(__name__)

_FLOAT_TAG = "tag:yaml.org,2002:float"
#: a float as people write it (YAML 1.2's core schema, which YAML 1.1 and so PyYAML's SafeLoader read as a string
#: when it has an exponent without a dot, `1e9`, or a signed exponent without a dot, `1E-6`), plus the words inf,
#: infinity and nan, with or without YAML's dot, in any case
_FLOAT = re.compile(
    r"""^(?:[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?
    |[-+]?\.?(?:inf|infinity)
    |\.?nan)$""",
    re.X | re.I,
)


class YamlLoader(yaml.SafeLoader):
    """PyYAML's SafeLoader with floats read as YAML 1.2 does (`_FLOAT`): `1e9`, `1E-6`, `.5`, `5.`, `+2.0`,
    `.inf`, `nan`. Integers stay integers (`+2` is 2). Every config file, override and keyframe file goes
    through it."""


class YamlDumper(yaml.SafeDumper):
    """PyYAML's SafeDumper that quotes every string `YamlLoader` would read as a float (`"1e9"`), so that a
    config.yaml it writes reads back the same."""


def _float_resolvers(cls) -> None:
    cls.yaml_implicit_resolvers = {
        first: [(tag, rx) for tag, rx in resolvers if tag != _FLOAT_TAG]
        for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
    }
    cls.add_implicit_resolver(_FLOAT_TAG, _FLOAT, list("-+0123456789.iInN"))


def _construct_float(loader: yaml.SafeLoader, node: yaml.ScalarNode) -> float:
    return float(re.sub(r"^([-+]?)\.(?=[a-zA-Z])", r"\1", str(loader.construct_scalar(node))))  # .inf -> inf


_float_resolvers(YamlLoader)
_float_resolvers(YamlDumper)
YamlLoader.add_constructor(_FLOAT_TAG, _construct_float)


def load_yaml(text: str) -> Any:
    """YAML text -> Python objects, floats as people write them (`YamlLoader`)."""
    return yaml.load(text, Loader=YamlLoader)  # a SafeLoader subclass


@dataclass(frozen=True)
class DataConfig:
    asf: str = ""  # ASF skeleton file
    amc: str = ""  # AMC motion file (120 fps)
    start: int = 0  # first AMC frame index (0-based) to reconstruct
    stop: int | None = None  # one past the last frame index; null = to the end
    stride: int = 4  # keep every stride-th frame (4: 120 -> 30 fps)


@dataclass(frozen=True)
class CameraConfig:
    distance_m: float = 5.0  # from the centre of the motion's bounding box
    azimuth_deg: float = 30.0  # about world up, from +Z towards +X
    elevation_deg: float = 10.0  # above the horizontal; positive looks down
    focal_px: float = 1000.0
    width: int = 640
    height: int = 480


@dataclass(frozen=True)
class ObservationsConfig:
    file: str | None = None  # npz of real 2D keypoints (Observations.save_npz layout); null = simulate
    noise_px: float = 2.0  # Gaussian pixel noise std
    missing: float = 0.0  # fraction of keypoints deleted at random
    outliers: float = 0.0  # fraction of kept keypoints (confidence 1) that are gross outliers
    outlier_px: float = 50.0
    swap_fraction: float = 0.5  # share of outliers that are left/right swaps
    occlusion_bursts: float = 0.0  # expected bursts per keypoint per second
    dropped_frames: float = 0.0  # fraction of whole frames dropped
    silhouettes: bool = False  # render capsule-model silhouettes
    # point correspondences between consecutive frames (ptrack/observe/correspondences.py), used by method pca:
    # an npz of real ones, or this many simulated per frame on the capsule model (0: none) with the noise std of their
    # second point and a share of wrong matches (displaced like keypoint outliers, by outlier_px)
    correspondence_file: str | None = None
    correspondences: int = 0
    correspondence_noise_px: float = 1.0
    correspondence_outliers: float = 0.0


@dataclass(frozen=True)
class ModelConfig:
    # dofs held at zero (shell patterns on joint or dof names); the rest are estimated
    freeze: tuple[str, ...] = ("*fingers", "*thumb", "*hand", "*toes")
    # keypoint name -> skeleton joint; null = the H36M-17 set on CMU joints
    keypoints: dict[str, str] | None = None
    # joint limits: "data" (measured on real CMU motion, ptrack/data/cmu_limits.json), "asf" (the
    # skeleton file's own), "none". The CMU ASF limits are broken by the ground truth itself.
    limits: str = "data"


@dataclass(frozen=True)
class CostsConfig:
    sigma_px: float = 2.0  # reprojection noise scale
    loss: str = "cauchy"  # robust kernel: l2, huber, cauchy, geman_mcclure
    robust_scale: float = 3.0  # kernel scale, in sigmas
    limits_weight: float = 1.0
    limits_sigma: float = 0.02  # radians
    smooth_weight: float = 1.0
    smooth_sigma: float = 0.15  # radians (or metres) per frame: velocity scale of the temporal prior
    # radians (or metres) per frame^2: acceleration scale of the temporal prior; null = velocity only.
    # On the dev clips 0.3 lowers acceleration error ~6% at equal MPJPE, 0.1 ~40% at +19% MPJPE.
    accel_sigma: float | None = None


@dataclass(frozen=True)
class FrameMethodConfig:
    init: str = "keyframe"  # "keyframe": first frame's 3D pose given (as a user keyframe); "rest": rest pose
    iterations: int = 40  # L-BFGS iterations per frame
    first_iterations: int = 200  # L-BFGS iterations on the first frame


@dataclass(frozen=True)
class KjsMethodConfig:
    """Settings of the sampling trackers `kjs` (kinematic jumps + CSS diffusion), `css` and `ss`."""

    modes: int = 8  # K: mixture modes kept per frame
    # hypothesis budget per frame, the same for all three methods: the K predicted modes, diffusion samples
    # and (kjs) their jump leaves. kjs's trees prune leaves (outside the limits, no sphere-ray intersection,
    # duplicates) without replacing them: on 10_02 (148 frames) it polishes 72-172 of 256 (mean 117). Filling the budget
    # with more samples measured worse on the dev clips (1 px: 25.3 / 21.4 mm against 23.7 / 20.1)
    samples: int = 256
    scale: float = 4.0  # covariance scale s of the diffusion (s times the inverse Gauss-Newton Hessian)
    tail: str = "student"  # diffusion tail: gaussian, student, cauchy
    tail_dof: float = 3.0  # Student-t degrees of freedom (tail: student)
    # kinematic sub-chains that may be flipped, by name (`ptrack.hypotheses.jumps.default_chains`: larm, rarm, lleg,
    # rleg, head); other chains through the Python API
    chains: tuple[str, ...] = ("larm", "rarm", "lleg", "rleg", "head")
    jumps_per_sample: int = 1  # chains flipped per diffusion sample, chosen by covariance voting
    limits_mode: str = "prune"  # jump leaves outside the joint limits: prune or project
    polisher: str = "lm"  # local optimiser of every hypothesis: lm (Levenberg-Marquardt) or lbfgs
    polish_iterations: int = 4  # Levenberg-Marquardt iterations of every hypothesis
    refine_iterations: int = 10  # further iterations of the 4K most promising distinct minima
    momentum: float = 0.0  # share of a mode's last velocity in its prediction (0: constant position)
    # minima whose joints are all closer than this (mm, per coordinate) are one; 0 (default): compare the
    # dofs instead (distinct_deg). Measured on the dev clips: 50 mm gave the tree start the same mean
    # best-of-K (44.1 against 44.6 mm), and after a keyframe start Viterbi picked flipped modes more often
    # (05_02: 28.4 against 20.7 mm best trajectory)
    distinct_mm: float = 0.0
    distinct_deg: float = 3.0  # with distinct_mm 0: minima closer than this in every dof are one
    # share of the diffusion samples split equally over the modes (the rest by weight), so that light modes,
    # which often hold a limb's other branch, keep exploring. 1 px dev clips, keyframe start, seeds 0-2 (best
    # trajectory / best-of-K mm / flip rate): 0 gave 26.8 / 20.7 / 0.069, 29.1 / 22.5 / 0.092, 26.8 / 19.5 /
    # 0.068; 0.5 gave 25.6 / 20.1 / 0.067, 28.4 / 20.3 / 0.081, 23.9 / 19.6 / 0.062 (1.0, seed 0: 27.3 / 20.6)
    even_share: float = 0.5
    temperature: float = 1.0  # weights ∝ prior * exp(-cost / temperature)
    # a new mode's weight ∝ (its parent mode's weight) ** weight_memory * exp(-cost / temperature). The paper
    # gives a new component the weight of its optimised likelihood (0) re-weighted by the closest prior mode
    # (1: every past frame's evidence multiplies in); with 1 a mode that lost out earlier stays near weight 0
    # and is pruned even when it is now the cheapest. Keyframe start, dev clips, five seeds (best trajectory /
    # best-of-K mm / flip rate), 1 -> 0.8 -> 0.5 -> 0.3: 1 px 21.6 / 17.5 / 0.052 -> 21.3 / 17.7 / 0.053 ->
    # 20.9 / 17.2 / 0.047 -> 21.6 / 18.4 / 0.051; 2 px, 1 -> 0.5: 28.2 / 24.7 / 0.053 -> 27.8 / 24.8 / 0.051;
    # held-out clips (never used to choose), seeds 0-2, 2 px 36.2 / 32.0 / 0.069 -> 34.7 / 31.7 / 0.058
    weight_memory: float = 0.5
    # radians (or metres) per frame: the dynamics' velocity prior. Each hypothesis is polished to
    # convergence, so this alone holds the weakly observed dofs: 0.05 measured better than 0.08 and 0.15
    # on 2 s of CMU 16_01 (42.4, 42.9, 63.6 mm)
    prior_sigma: float = 0.05
    # the dynamics' velocity std per dof instead of prior_sigma for all: a table of each CMU dof's RMS
    # velocity in real motion (`ptrack.body.pose_prior.SMOOTHING_TABLES`), times the frame interval and
    # dynamics_scale, at least dynamics_floor per frame; prior_sigma for the dofs it does not name (the root's
    # position). "cmu-train" (the default): fitted to configs/clips/train.txt, subjects with no dev clip;
    # "cmu": fitted to the dev clips themselves (batch.prior's table); null: prior_sigma for every dof.
    # Keyframe start, best trajectory / best-of-K mm / flip rate, null -> cmu-train at dynamics_scale 1 -> 1.5
    # -> 2: dev clips 1 px seed 0 23.7 / 20.1 / 0.066 -> 22.4 / 18.5 / 0.052 -> 19.5 / 17.2 / 0.035 -> 21.6 /
    # 17.8 / 0.047, seed 1 22.6 / 20.3 / 0.066 -> 21.7 / 18.2 / 0.060 -> 19.5 / 17.1 / 0.047; 2 px seed 0 32.7
    # / 29.6 / 0.057 -> 32.2 / 27.8 / 0.063 -> 27.5 / 25.0 / 0.050 -> 29.1 / 25.6 / 0.054, seed 1 35.3 / 31.5
    # / 0.072 -> 30.8 / 26.5 / 0.061 -> 28.9 / 24.5 / 0.056; held-out clips (configs/clips/heldout_batch.txt,
    # never used to choose) 2 px 42.8 / 39.6 / 0.090 -> 42.9 / 36.4 / 0.087 -> 37.0 / 32.9 / 0.073
    # (docs/notes/kjs-history.md). Fitted to the dev clips ("cmu", scale 1) it helped the dev clips but not the held-out
    # ones (2 px 45.5 / 38.3 / 0.098)
    dynamics: str | None = "cmu-train"
    dynamics_scale: float = 1.5
    dynamics_floor: float = 0.02
    # tails of that prior in tracking steps: gaussian, or a robust loss (cauchy, huber, geman_mcclure)
    # beyond prior_tail_scale standard deviations, so that a limb flipped far from the prediction
    # stays a competing mode (the paper's long-tailed mixture components). Dev clips, keyframe start
    # (best trajectory / best-of-K mm / flip rate): gaussian 35.2 / 33.4 / 0.064, cauchy at 3 sigma
    # 34.0 / 30.6 / 0.059, cauchy at 2 sigma 35.4 / 28.9 / 0.085 (more varied modes, worse choice)
    prior_tail: str = "cauchy"
    prior_tail_scale: float = 3.0
    # per mode and dof, the prior's std is sqrt(prior_sigma^2 + (motion_scale * last displacement)^2): a fast
    # limb may move as far again. Dev clips, keyframe start: 1.0 gave 36.5 mm mean best trajectory against
    # 41.2 at 0 (the run 09_06: 62 against 87 mm)
    motion_scale: float = 1.0
    # weight of the CMU pose prior (`ptrack.body.pose_prior`) in every tracking step; on the dev clips (keyframe
    # start) 0.1 measured 35.3 mm best trajectory against 36.5 at 0, and 0.3 lost the dance 05_02 (27.1 vs 20.8)
    pose_prior_weight: float = 0.1
    collision_weight: float = 1.0  # body non-self-intersection term
    floor_deg: float = 0.5  # smallest sampling std per dof (unobservable directions)
    ceiling_deg: float = 30.0  # largest sampling std per dof
    # the best trajectory through the modes (Viterbi): its velocity prior on the joints' positions relative
    # to the root (joints; std viterbi_sigma_m metres per frame and coordinate) or on the dofs (dofs; std
    # viterbi_sigma radians per frame). On the same recorded modes of the dev clips (best trajectory mm):
    # 1 px seed 0 dofs 25.6, joints 23.7; seed 1 28.4, 22.6; 2 px seed 0 34.1, 32.7 (joints 0.03 and 0.08 m
    # between). Euler-angle steps are not the body's motion: a root or shoulder angle near gimbal lock moves a lot
    viterbi_space: str = "joints"
    viterbi_sigma_m: float = 0.05
    viterbi_sigma: float = 0.05
    init: str = "keyframe"  # keyframe: frame 0's 3D pose given; tree: rest pose fitted in view + every flip
    # init tree: the CMU pose prior's spread is scaled by this (1.0-2.0 gave the same mean best-of-K on
    # frame 0 of the dev clips, 1.5 is between); angles it does not name: std rest_sigma around 0
    start_prior_scale: float = 1.5
    rest_sigma: float = 1.0
    init_yaws: int = 8  # init tree: headings of the rest pose tried (each also leaned forward and back)
    init_fits: int = 4  # init tree: distinct fitted poses whose chains are flipped (every combination)
    # after the forward pass, a second pass backwards in time from its last frame's modes (after a tree
    # start, with the last frame's own tree start beside them; after a keyframe start, fed each frame by
    # the forward pass's modes of the frame after); each frame's K hypotheses are then the forward
    # trajectory's mode and both passes' modes in turn, each depth order of the limbs before any repeat,
    # and the best trajectory stays the forward pass's (after a tree start the backward pass's when the two
    # trajectories face more than 30 degrees apart and it costs less): "always" (after either start), "tree" (after a
    # tree start only) or "never". It doubles the time. Dev clips, five seeds, best-of-K: keyframe start
    # 1 px 17.2 -> 15.3 mm (02_01 22.5 -> 18.8), 2 px 24.8 -> 22.6; tree start 1 px 25.2 -> 21.5
    # (02_01 28.4), 2 px 47.9 -> 32.2 (docs/notes/kjs-history.md)
    backward_pass: str = "always"
    # after the passes, sweeps of a smoother over every frame's hypotheses: each is polished again on its
    # frame with the tracking prior around the mean of its nearest neighbours in the frames before and after
    # (linked where their joints, relative to the root, are within smooth_link_m metres on average), std
    # smooth_scale times the dynamics'; 0 sweeps: the passes' modes as they are. Dev clips, five seeds, best
    # trajectory mm / best-of-K mm / flip rate / acceleration error mm per frame², 0 sweeps -> 1 sweep at
    # 0.2: keyframe start 2 px 27.7 / 22.7 / 0.0505 / 25.7 -> 25.8 / 21.4 / 0.0485 / 15.9, 1 px 21.0 / 15.8 /
    # 0.0477 / 19.0 -> 19.7 / 15.0 / 0.0473 / 12.6; tree start 2 px 44.9 / 31.9 / 0.141 / 25.5 -> 43.6 / 31.1
    # / 0.141 / 16.2. Scale 0.3 measured alike; more sweeps lost best-of-K (keyframe start 2 px, 2 sweeps at
    # 0.3: 25.5 / 21.7 / 0.0480 / 16.4; tree start 2 px, 3 sweeps: best-of-K 31.7)
    smooth_sweeps: int = 1
    smooth_scale: float = 0.2
    smooth_link_m: float = 0.1
    # after the passes, one more hypothesis per frame (in place of padding or the lightest mode other than the
    # best trajectory's): the best trajectory's pose with each chain's reading chosen by its own Viterbi pass
    # over the modes (velocity std recombine_sigma_m per frame on the chain's grafted joints). The modes hold
    # the limbs' readings in combinations, and often no mode holds the right reading of every limb at once.
    # css and ss have chains only after a tree start (`kjs.chains` serve the jumps and the trees), so only then.
    # Dev clips, five seeds, best-of-K mm: 2 px tree start 31.1 -> 30.0, keyframe start 21.4 -> 20.8; 1 px
    # keyframe start 15.0 -> 14.6; the best trajectory is the same. On saved lattices sigma 0.05 / 0.15 / 0.3 /
    # 1.0 gave 31.4 / 30.9 / 30.9 / 31.0 (tree start, 2 px, before the smoother)
    recombine: bool = True
    recombine_sigma_m: float = 0.15


@dataclass(frozen=True)
class KeyframesConfig:
    """3D keyframes: from a file (`ptrack/pipeline/keyframes.py` documents the YAML/JSON format) or, for
    synthetic evaluation, from the ground truth (frame 0 always; the methods other than batch read
    frame 0's only)."""

    file: str | None = None  # YAML/JSON keyframe file; replaces the ground-truth keyframes
    every_s: float | None = None  # ground truth every this many seconds (null: frame 0 only)
    last: bool = False  # ground truth at the last frame too
    noise_deg: float = 0.0  # Gaussian noise (std, degrees) added to the ground-truth keyframes' angles
    sigma_deg: float = 2.0  # prior std of a ground-truth keyframe's angles (and a file's default)
    sigma_m: float = 0.02  # prior std of a ground-truth keyframe's root position (and a file's default)


@dataclass(frozen=True)
class PcaMethodConfig:
    """`method: pca`, the golf-swing tracker over a PCA motion model (Urtasun, Fleet & Fua 2004): per sliding
    window, the PCA weights (shared), a normalised time per frame and the root pose per frame (eq. 5), fitted by
    Levenberg-Marquardt to the tracked joints and the silhouettes (eq. 7). The model is `motion.model_file`
    (fitted from `motion.clips` on first use and cached there)."""

    window: int = 3  # f: frames per window
    step: int = 1  # frames the window slides by (at most the window; 1: every frame is fitted f times)
    # Levenberg-Marquardt iterations per window; 0 = the initialisation alone (the mean motion). Leave-one-out over
    # the 7 golf swings: 2 gave the same mean MPJPE as 3 (27.4 mm over the swings), and 3 the same as 10 on 64_01
    iterations: int = 2
    # tracked keypoints (names of the keypoint set, `model.keypoints`): the paper's knees, ankles, wrists, head
    joints: tuple[str, ...] = ("l_knee", "r_knee", "l_ankle", "r_ankle", "l_wrist", "r_wrist", "head")
    joint_weight: float = 1.0  # w of the joint projections (pixels / costs.sigma_px, robust by costs.loss)
    silhouette_weight: float = 1.0  # w of the foreground term (section 4.1); 0 = joints only
    # w of each correspondence (section 4.3; pixels / costs.sigma_px, robust by costs.loss) where the observations
    # have them (observations.correspondences or .correspondence_file); 0 = unused. Leave-one-out over the 7 golf
    # swings, 40 pairs per frame: 1 let the tracker drift away on 64_05 (docs/results.md)
    correspondence_weight: float = 0.3
    # a pair counts only where p1's line of sight passes at least this far (metres) from every capsule's surface
    # in the estimate of frame t-1 (near an outline, an estimate a little off puts p1 on another part, whose
    # motion then misleads; 0 kept the most pairs but let 64_05 drift away at 2 px noise)
    correspondence_margin_m: float = 0.03
    silhouette_sigma_m: float = 0.02  # a ray this far (metres) from the model counts as one sigma
    silhouette_samples: int = 96  # foreground samples per frame (a regular grid, evenly thinned)
    silhouette_step_px: int = 4  # grid step of the samples, pixels
    # prediction terms (eq. 7, E_D): stds around the previous window's trajectory continued at its speed
    root_sigma_m: float = 0.02  # root position, metres per frame
    root_sigma_deg: float = 3.0  # root orientation, degrees per frame
    time_sigma: float = 0.01  # normalised time per frame
    # std of a prior holding each frame's normalised time near its start value (the key postures found in the
    # 2D wrist track, interpolated); null = none (the paper's eq. 7 has only the prediction)
    timing_sigma: float | None = 0.03
    alpha_sigma: float = 0.1  # PCA weights, in units of the model's per-component std (motion model sigma)
    alpha_prior_weight: float = 1.0  # weight of the prior alpha ~ N(0, sigma^2) of the training swings
    alpha_bound: float = 3.0  # |alpha_i| at most this many training stds (a box in the solver)
    init_yaws: int = 8  # headings of the first frame's root placement tried (section 5.1)
    # Gaussian smoothing (std, seconds) of the 2D wrist track before the key-posture rules (motion.key_postures):
    # 2D detections are noisier than motion capture (the golf swings at 2 px noise: 0.02 s misses the start,
    # 0.05 s finds the 3D ground truth's frames within one)
    key_smooth_s: float = 0.05


@dataclass(frozen=True)
class BatchMethodConfig:
    """`method: batch`, the MAP trajectory of the whole sequence (DiFranco, Cham & Rehg 2001)."""

    iterations: int = 30  # Levenberg-Marquardt iterations on the whole trajectory
    tol: float = 1e-9  # relative energy decrease (or step) at which it stops
    # initial lambda relative to the Hessian's largest diagonal entry, which is the smoothing prior's (linear
    # terms, no damping needed): 1e-8 converges in about half the iterations of 1e-4 to the same solutions
    # (dev and held-out clips, docs/notes/batch-history.md)
    damping: float = 1e-8
    # dynamic smoothing, per second (units: rad/s, rad/s^2 for angles; m/s, m/s^2 for the root
    # position); null drops the term
    # (chosen on the dev clips, docs/notes/batch-history.md: velocity 3 rad/s + acceleration 8 rad/s^2 gave a
    # mean MPJPE of 33.2 mm against 41.8 for acceleration 20 alone)
    velocity_sigma: float | None = 3.0
    accel_sigma: float | None = 8.0
    velocity_sigma_m: float | None = 1.0
    accel_sigma_m: float | None = 2.0
    # per-dof scales by dof name, replacing the sigmas above for the dofs it names: "cmu" (fitted to the
    # dev clips' motion, ptrack/data/cmu_smoothing.json, scripts/make_smoothing_prior.py), null = none
    prior: str | None = "cmu"
    # the smoothing residuals' loss (l2, huber, cauchy, geman_mcclure) and its scale in prior std units:
    # a heavier tail lets a motion faster than the prior's scale through (a run's legs). Dev clips,
    # keyframes every 1 s, MPJPE: l2 23.1 mm, huber 2 22.5, cauchy 3 21.6, 2 20.3, 1.5 19.8, 1 19.9 (one
    # walk 20 -> 32 mm: below 2 the loss is non-convex enough to stop in worse minima), docs/results.md
    smooth_loss: str = "cauchy"
    smooth_scale: float = 2.0
    upsample: int = 1  # reconstruct N frames per observed frame (data.stride must be divisible by N)
    init: str = "frame"  # start: "frame" (per-frame fits, `frame.*` settings) or "keyframes" (interpolated)
    # joint_std (T, J) in result.npz: "branches" (the Laplace covariance plus every limb's depth-flip
    # branches, ptrack/hypotheses/branches.py; true means this), "laplace" (the marginal covariances at the solution
    # alone: faster, overconfident between keyframes), false = none
    uncertainty: bool | str = "branches"
    # rounds of restarts from the limbs' depth-flip branches (ptrack/hypotheses/branches.py): after the solve, each
    # limb's flipped trajectory re-solved; the one of lowest whole energy, if lower than the solution's,
    # is solved again from and replaces it (0: none; a round that finds none ends them). Dev clips, keyframes
    # every 1 s, MPJPE / flip rate: 0 rounds 26.9 mm / 0.057, 1 round 25.1 / 0.045, 3 rounds 23.1 / 0.037
    flip_restarts: int = 3


#: the golf swing's key postures (Urtasun, Fleet & Fua 2004, fig. 2), rules of `ptrack.motion.key_postures`
GOLF_KEY_POSTURES = {
    "start": "rest before top",  # start of upswing: the hands still, before the upswing's fastest motion
    "top": "first max height",  # top of upswing: the hands' first high point
    "hit": "first min height after top",  # ball hit: the hands' low point of the downswing
    "end": "min speed after hit within 0.8 s",  # end of downswing: the hands' slowest, at the finish
}


@dataclass(frozen=True)
class MotionConfig:
    """`ptrack fit-motion`: a time-warped PCA motion model of one motion type (`ptrack.motion.motion_model`)."""

    # training clips: AMC files, or one text file listing them (one per line, relative to that file);
    # each clip's skeleton is the .asf beside it (<subject>.asf)
    clips: tuple[str, ...] = ()
    joints: tuple[str, ...] = ("lradius", "rradius")  # tracked point of the key postures: their mean (wrists)
    # dofs left out of the model besides the root's (shell patterns on joint or dof names, as model.freeze):
    # the CMU thumbs jump by whole turns and the tracker holds these at zero anyway
    exclude: tuple[str, ...] = ("*fingers", "*thumb", "*hand", "*toes")
    # name -> rule, in temporal order (grammar in ptrack/motion/key_postures.py); the default is the golf swing's.
    # An override of one posture (motion.key_postures.end=...) replaces the whole mapping: give them all
    key_postures: dict[str, str] = field(default_factory=lambda: dict(GOLF_KEY_POSTURES))
    smooth_s: float = 0.05  # Gaussian smoothing (std, seconds) of the tracked point before the rules
    prominence: float = 0.02  # first/last extrema: least prominence, as a fraction of the signal's range
    rest_fraction: float = 0.05  # rest: slower than this fraction of the clip's top speed
    samples: int = 200  # N: normalised times per swing
    components: int = 4  # m: eigen-motions kept (at most the number of clips - 1)
    # where fit-motion writes the model and the pca tracker reads it; null = ~/.cache/ptrack/motion/<name>.npz
    # ($XDG_CACHE_HOME/ptrack/... when set)
    model_file: str | None = None


@dataclass(frozen=True)
class RunConfig:
    method: str = "frame"
    seed: int = 0
    out_dir: str | None = None  # null = logs/<config-name>-<time>/
    device: str = "cpu"
    dtype: str = "float32"
    progress: bool = True
    data: DataConfig = field(default_factory=DataConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    observations: ObservationsConfig = field(default_factory=ObservationsConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    costs: CostsConfig = field(default_factory=CostsConfig)
    frame: FrameMethodConfig = field(default_factory=FrameMethodConfig)
    kjs: KjsMethodConfig = field(default_factory=KjsMethodConfig)
    keyframes: KeyframesConfig = field(default_factory=KeyframesConfig)
    batch: BatchMethodConfig = field(default_factory=BatchMethodConfig)
    pca: PcaMethodConfig = field(default_factory=PcaMethodConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    init_from: str | None = None  # batch: start from this earlier run folder's trajectory (same model, frames)
    name: str = "run"  # config name, used for the default out_dir


METHODS = ("frame", "kjs", "css", "ss", "batch", "pca")
_PATH_KEYS = {
    "data.asf",
    "data.amc",
    "observations.file",
    "observations.correspondence_file",
    "out_dir",
    "keyframes.file",
    "init_from",
    "motion.model_file",
}
_PATH_LIST_KEYS = {"motion.clips"}  # a path or a list of paths


#: scalar annotation -> (what the error says it must be, accepted Python types); bools are never numbers
_SCALARS = {
    bool: ("true or false", lambda v: isinstance(v, bool)),
    int: ("an integer", lambda v: isinstance(v, int)),
    float: ("a number", lambda v: isinstance(v, (int, float))),
    str: ("a string", lambda v: isinstance(v, str)),
}


def _check_type(key: str, value: Any, tp: Any) -> Any:
    """Check (and lightly coerce: int -> float, list -> tuple) `value` against annotation `tp`. A number must be
    finite."""
    origin = typing.get_origin(tp)
    if origin in (Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None:
            if type(None) in args:
                return None
            raise InputError(f"config key {key!r} must not be null")
        errors = []
        for a in args:
            if a is type(None):
                continue
            try:
                return _check_type(key, value, a)
            except InputError as e:
                errors.append(e)
        raise errors[0] if len(errors) == 1 else InputError(f"config key {key!r} has the wrong type: got {value!r}")
    if value is None:
        raise InputError(f"config key {key!r} must not be null")
    if tp in _SCALARS:
        what, accepts = _SCALARS[tp]
        if accepts(value) and not (isinstance(value, bool) and tp is not bool):
            if tp is float and not math.isfinite(value):  # no setting has a meaning for nan or inf
                raise InputError(f"config key {key!r} must be a finite number, got {value!r}")
            return tp(value)
        raise InputError(f"config key {key!r} must be {what}, got {value!r}")
    if origin is tuple:
        if isinstance(value, str):
            value = [value]
        if not isinstance(value, (list, tuple)):
            raise InputError(f"config key {key!r} must be a list, got {value!r}")
        (inner, _) = typing.get_args(tp)
        return tuple(_check_type(f"{key}[{i}]", v, inner) for i, v in enumerate(value))
    if origin is dict:
        if not isinstance(value, dict):
            raise InputError(f"config key {key!r} must be a mapping, got {value!r}")
        kt, vt = typing.get_args(tp)
        return {_check_type(f"{key} key", k, kt): _check_type(f"{key}.{k}", v, vt) for k, v in value.items()}
    raise TypeError(f"unsupported config annotation {tp!r} for {key}")


def _build(cls, raw: dict, prefix: str = ""):
    if not isinstance(raw, dict):
        raise InputError(f"config section {prefix.rstrip('.') or '(top level)'!r} must be a mapping, got {raw!r}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(raw) - names)
    if unknown:
        key = prefix + str(unknown[0])
        raise InputError(f"unknown config key {key!r} (known keys here: {', '.join(sorted(names))})")
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in raw:
            continue
        key = prefix + f.name
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            kwargs[f.name] = _build(tp, raw[f.name] if raw[f.name] is not None else {}, key + ".")
        else:
            kwargs[f.name] = _check_type(key, raw[f.name], tp)
    return cls(**kwargs)


def _set_dotted(raw: dict, key: str, value: Any) -> None:
    parts = key.split(".")
    node = raw
    for p in parts[:-1]:
        nxt = node.get(p)
        if nxt is None:
            nxt = node[p] = {}
        if not isinstance(nxt, dict):
            raise InputError(f"override {key!r}: {p!r} is not a section")
        node = nxt
    node[parts[-1]] = value


def _get_dotted(raw: dict, key: str) -> Any:
    node: Any = raw
    for p in key.split("."):
        if not isinstance(node, dict) or p not in node:
            return None
        node = node[p]
    return node


def parse_override(text: str) -> tuple[str, Any]:
    """`dotted.key=value` -> (key, YAML-parsed value)."""
    if "=" not in text:
        raise InputError(f"override {text!r} must look like dotted.key=value")
    key, _, value = text.partition("=")
    key = key.strip()
    if not key or any(not p for p in key.split(".")):
        raise InputError(f"override {text!r} has an empty key")
    if value.strip().startswith(("*", "&")):  # a shell pattern such as *toes, not a YAML alias
        return key, value.strip()
    try:
        return key, load_yaml(value) if value.strip() else None
    except yaml.YAMLError as e:
        raise InputError(f"override {text!r}: value is not valid YAML ({_one_line(e)})") from None


def _one_line(e: Exception) -> str:
    """A YAML/Unicode error as one line: its problem and where, without PyYAML's source excerpt."""
    problem = getattr(e, "problem", None)
    mark = getattr(e, "problem_mark", None)
    if problem and mark is not None:
        return f"{problem} at line {mark.line + 1}, column {mark.column + 1}"
    return " ".join(str(e).split())


def _resolve_paths(value: str | list, base: Path) -> str | list:
    """A path or a list of paths (non-strings left for the type check) resolved against `base`."""
    if isinstance(value, str):
        return str((base / value).resolve()) if value else value
    return [str((base / v).resolve()) if isinstance(v, str) and v else v for v in value]


def load_config(
    path: str | Path | None = None,
    overrides: list[str] | tuple[str, ...] = (),
    cwd: str | Path | None = None,
    run: bool = True,
) -> RunConfig:
    """Read a YAML run config (or only defaults when `path` is None) and apply overrides.

    run=False (`ptrack fit-motion`) does not require the data of a run (data.asf, data.amc)."""
    raw: dict = {}
    base = Path(cwd or Path.cwd())
    name = "run"
    if path is not None:
        p = Path(path)
        if not p.exists():
            raise FileNotFoundError(f"config file not found: {p}")
        if p.is_dir():
            found = sorted(p.glob("*.yaml"))
            raise InputError(f"config {p} is a folder; give a YAML file" + (f", e.g. {found[0]}" if found else ""))
        try:
            loaded = load_yaml(p.read_text(encoding="utf-8"))
        except (yaml.YAMLError, UnicodeDecodeError) as e:
            raise InputError(f"config file {p} is not valid YAML: {_one_line(e)}") from None
        if loaded is None:
            loaded = {}
        if not isinstance(loaded, dict):
            raise InputError(f"config file {p} must hold a mapping of keys, got {type(loaded).__name__}")
        raw = loaded
        name = p.stem
        for key in _PATH_KEYS:
            v = _get_dotted(raw, key)
            if isinstance(v, str) and v:
                _set_dotted(raw, key, str((p.resolve().parent / v).resolve()))
        for key in _PATH_LIST_KEYS:
            v = _get_dotted(raw, key)
            if isinstance(v, (str, list)):
                _set_dotted(raw, key, _resolve_paths(v, p.resolve().parent))
    raw.setdefault("name", name)
    over_keys = set()
    for text in overrides:
        key, value = parse_override(text)
        if key in _PATH_KEYS and isinstance(value, str) and value:
            value = str((base / value).resolve())
        if key in _PATH_LIST_KEYS and isinstance(value, (str, list)):
            value = _resolve_paths(value, base)
        _set_dotted(raw, key, value)
        over_keys.add(key)
    amc = _get_dotted(raw, "data.amc")
    if "data.amc" in over_keys and "data.asf" not in over_keys and isinstance(amc, str) and Path(amc).is_file():
        # another clip, maybe of another subject: its own skeleton, not the config's bone lengths
        asf, beside = _get_dotted(raw, "data.asf"), skeleton_beside(amc)
        if beside is None:
            log.warning(
                "data.amc is %s but no skeleton is beside it: keeping data.asf %s (set data.asf to choose)", amc, asf
            )
        elif not (isinstance(asf, str) and asf and Path(asf).resolve() == beside.resolve()):
            log.warning(
                "data.amc is %s: using the skeleton beside it, %s (set data.asf to choose another)", amc, beside
            )
            _set_dotted(raw, "data.asf", str(beside.resolve()))
    cfg = _build(RunConfig, raw)
    validate(cfg, run=run)
    return cfg


def validate(cfg: RunConfig, run: bool = True) -> None:
    """Value checks beyond types (InputError naming the key); run=False: no data.asf/amc needed."""
    if cfg.method not in METHODS:
        raise InputError(f"config key 'method' must be one of {', '.join(METHODS)}, got {cfg.method!r}")
    if not -(2**63) <= cfg.seed < 2**63:
        raise InputError(f"config key 'seed' must be between -2**63 and 2**63 - 1, got {cfg.seed}")
    validate_motion(cfg.motion)
    if not run:
        return
    if not cfg.data.asf:
        raise InputError("config key 'data.asf' is required (path to the ASF file)")
    if not cfg.data.amc and not cfg.observations.file:
        raise InputError("config key 'data.amc' is required (path to the AMC file)")
    d = cfg.data
    if d.start < 0:
        raise InputError(f"config key 'data.start' must be >= 0, got {d.start}")
    if d.stop is not None and d.stop <= d.start:
        raise InputError(f"config key 'data.stop' must be greater than data.start ({d.start}), got {d.stop}")
    if d.stride < 1:
        raise InputError(f"config key 'data.stride' must be >= 1, got {d.stride}")
    c = cfg.camera
    for k in ("distance_m", "focal_px"):
        if getattr(c, k) <= 0:
            raise InputError(f"config key 'camera.{k}' must be positive, got {getattr(c, k)}")
    for k in ("width", "height"):
        if getattr(c, k) <= 0:
            raise InputError(f"config key 'camera.{k}' must be positive, got {getattr(c, k)}")
    from ptrack.observe.observations import CHANNEL_RANGES, channel_range_error

    for k in CHANNEL_RANGES:  # the channel's own intervals, named by the config key
        error = channel_range_error(k, getattr(cfg.observations, k))
        if error:
            raise InputError(f"config key 'observations.{k}' {error}")
    o = cfg.observations
    if o.correspondences < 0:
        raise InputError(f"config key 'observations.correspondences' must be >= 0, got {o.correspondences}")
    if not 0 <= o.correspondence_noise_px < float("inf"):
        raise InputError(
            f"config key 'observations.correspondence_noise_px' must be >= 0, got {o.correspondence_noise_px}"
        )
    if not 0 <= o.correspondence_outliers <= 1:
        raise InputError(
            f"config key 'observations.correspondence_outliers' must be in [0, 1], got {o.correspondence_outliers}"
        )
    if o.correspondence_file and o.correspondences:
        raise InputError(
            "config keys 'observations.correspondence_file' and 'observations.correspondences' are both set: "
            "give a file of correspondences or simulate them, not both"
        )
    from ptrack.body.limits import SOURCES as LIMIT_SOURCES

    if cfg.model.limits not in LIMIT_SOURCES:
        raise InputError(
            f"config key 'model.limits' must be one of {', '.join(LIMIT_SOURCES)}, got {cfg.model.limits!r}"
        )
    if cfg.dtype not in ("float32", "float64"):
        raise InputError(f"config key 'dtype' must be float32 or float64, got {cfg.dtype!r}")
    check_device(cfg.device)
    if cfg.frame.init not in ("keyframe", "rest"):
        raise InputError(f"config key 'frame.init' must be 'keyframe' or 'rest', got {cfg.frame.init!r}")
    if cfg.frame.iterations < 1 or cfg.frame.first_iterations < 1:
        raise InputError("config keys 'frame.iterations' and 'frame.first_iterations' must be >= 1")
    kc = cfg.kjs
    if kc.modes < 1:
        raise InputError(f"config key 'kjs.modes' must be >= 1, got {kc.modes}")
    if kc.samples < kc.modes:
        raise InputError(f"config key 'kjs.samples' must be at least kjs.modes ({kc.modes}), got {kc.samples}")
    for key in (
        "scale",
        "tail_dof",
        "distinct_deg",
        "temperature",
        "prior_sigma",
        "floor_deg",
        "ceiling_deg",
        "viterbi_sigma",
        "viterbi_sigma_m",
        "rest_sigma",
        "start_prior_scale",
        "prior_tail_scale",
        "dynamics_scale",
        "smooth_scale",
        "smooth_link_m",
        "recombine_sigma_m",
    ):
        if not getattr(kc, key) > 0:
            raise InputError(f"config key 'kjs.{key}' must be positive, got {getattr(kc, key)}")
    if not kc.dynamics_floor >= 0:
        raise InputError(f"config key 'kjs.dynamics_floor' must be >= 0, got {kc.dynamics_floor}")
    check_smoothing_table(kc.dynamics, "kjs.dynamics")
    for key in ("init_yaws", "init_fits"):
        if getattr(kc, key) < 1:
            raise InputError(f"config key 'kjs.{key}' must be >= 1, got {getattr(kc, key)}")
    if kc.collision_weight < 0:
        raise InputError(f"config key 'kjs.collision_weight' must be >= 0, got {kc.collision_weight}")
    if kc.polish_iterations < 0 or kc.refine_iterations < 0 or kc.jumps_per_sample < 0:
        raise InputError(
            "config keys 'kjs.polish_iterations', 'kjs.refine_iterations' and 'kjs.jumps_per_sample' must be >= 0"
        )
    for key in ("motion_scale", "pose_prior_weight", "distinct_mm", "smooth_sweeps"):
        if getattr(kc, key) < 0:
            raise InputError(f"config key 'kjs.{key}' must be >= 0, got {getattr(kc, key)}")
    for key in ("momentum", "even_share", "weight_memory"):
        if not 0 <= getattr(kc, key) <= 1:
            raise InputError(f"config key 'kjs.{key}' must be in [0, 1], got {getattr(kc, key)}")
    for key, allowed in (
        ("tail", ("gaussian", "student", "cauchy")),
        ("limits_mode", ("prune", "project")),
        ("polisher", ("lm", "lbfgs")),
        ("init", ("keyframe", "tree")),
        ("backward_pass", ("tree", "always", "never")),
        ("viterbi_space", ("joints", "dofs")),
        ("prior_tail", ("gaussian", *(n for n in ROBUST_LOSSES if n != "l2"))),
    ):
        if getattr(kc, key) not in allowed:
            raise InputError(f"config key 'kjs.{key}' must be one of {', '.join(allowed)}, got {getattr(kc, key)!r}")
    kf = cfg.keyframes
    if kf.every_s is not None and not kf.every_s > 0:
        raise InputError(f"config key 'keyframes.every_s' must be positive or null, got {kf.every_s}")
    if kf.noise_deg < 0:
        raise InputError(f"config key 'keyframes.noise_deg' must be >= 0, got {kf.noise_deg}")
    for key in ("sigma_deg", "sigma_m"):
        if not getattr(kf, key) > 0:
            raise InputError(f"config key 'keyframes.{key}' must be positive, got {getattr(kf, key)}")
    b = cfg.batch
    if b.iterations < 1 or b.upsample < 1:
        raise InputError("config keys 'batch.iterations' and 'batch.upsample' must be >= 1")
    for key in ("tol", "damping"):
        if not getattr(b, key) > 0:
            raise InputError(f"config key 'batch.{key}' must be positive, got {getattr(b, key)}")
    for key in ("velocity_sigma", "accel_sigma", "velocity_sigma_m", "accel_sigma_m"):
        if getattr(b, key) is not None and not getattr(b, key) > 0:
            raise InputError(f"config key 'batch.{key}' must be positive or null, got {getattr(b, key)}")
    if b.smooth_loss not in ROBUST_LOSSES:
        raise InputError(
            f"config key 'batch.smooth_loss' must be one of {', '.join(ROBUST_LOSSES)}, got {b.smooth_loss!r}"
        )
    if not b.smooth_scale > 0:
        raise InputError(f"config key 'batch.smooth_scale' must be positive, got {b.smooth_scale}")
    if b.init not in ("frame", "keyframes"):
        raise InputError(f"config key 'batch.init' must be 'frame' or 'keyframes', got {b.init!r}")
    if isinstance(b.flip_restarts, bool) or not isinstance(b.flip_restarts, int) or b.flip_restarts < 0:
        raise InputError(f"config key 'batch.flip_restarts' must be an integer >= 0, got {b.flip_restarts!r}")
    if isinstance(b.uncertainty, str) and b.uncertainty not in ("laplace", "branches"):
        raise InputError(
            f"config key 'batch.uncertainty' must be 'branches', 'laplace', true (= branches) or false, "
            f"got {b.uncertainty!r}"
        )
    if b.upsample > 1 and cfg.data.stride % b.upsample:
        raise InputError(
            f"config key 'batch.upsample' ({b.upsample}) must divide data.stride ({cfg.data.stride}): "
            f"the reconstruction is read at stride {cfg.data.stride}/{b.upsample}"
        )
    if cfg.costs.sigma_px <= 0:
        raise InputError(f"config key 'costs.sigma_px' must be positive, got {cfg.costs.sigma_px}")
    if cfg.costs.loss not in ROBUST_LOSSES:
        raise InputError(f"config key 'costs.loss' must be one of {', '.join(ROBUST_LOSSES)}, got {cfg.costs.loss!r}")
    validate_pca(cfg.pca, cfg.model.keypoints, names=cfg.method == "pca")


def check_device(device: str) -> None:
    """InputError unless torch can run on `device` here: cpu; cuda, cuda:N where a CUDA GPU is; mps where
    Apple's GPU is. The error lists this machine's choices."""
    import torch

    cuda = torch.cuda.device_count() if torch.cuda.is_available() else 0
    mps = torch.backends.mps.is_available()
    here = ["cpu", *(["cuda", *(f"cuda:{i}" for i in range(cuda))] if cuda else []), *(["mps"] if mps else [])]
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        dev = None
    if dev is not None and (
        dev.type == "cpu"
        or (dev.type == "cuda" and cuda and (dev.index is None or dev.index < cuda))
        or (dev.type == "mps" and mps and not dev.index)
    ):
        return
    raise InputError(
        f"config key 'device' must be a device this machine has: {', '.join(here)} (cuda and cuda:N need a CUDA GPU, "
        f"mps an Apple GPU), got {device!r}"
    )


def validate_pca(p: PcaMethodConfig, keypoints: dict[str, str] | None = None, names: bool = True) -> None:
    """Value checks of the `pca:` section; with `names` (method pca), the tracked joints must be names of the
    keypoint set `keypoints` (None: the default H36M-17 set)."""
    from ptrack.body.keypoints import H36M17

    if p.window < 1:
        raise InputError(f"config key 'pca.window' must be >= 1, got {p.window}")
    if p.iterations < 0:
        raise InputError(f"config key 'pca.iterations' must be >= 0, got {p.iterations}")
    for key in ("step", "silhouette_samples", "silhouette_step_px", "init_yaws"):
        if getattr(p, key) < 1:
            raise InputError(f"config key 'pca.{key}' must be >= 1, got {getattr(p, key)}")
    for key in (
        "joint_weight",
        "silhouette_weight",
        "correspondence_weight",
        "correspondence_margin_m",
        "alpha_prior_weight",
    ):
        if not getattr(p, key) >= 0:
            raise InputError(f"config key 'pca.{key}' must be >= 0, got {getattr(p, key)}")
    if p.timing_sigma is not None and not p.timing_sigma > 0:
        raise InputError(f"config key 'pca.timing_sigma' must be positive or null, got {p.timing_sigma}")
    if p.key_smooth_s < 0:
        raise InputError(f"config key 'pca.key_smooth_s' must be >= 0, got {p.key_smooth_s}")
    for key in ("silhouette_sigma_m", "root_sigma_m", "root_sigma_deg", "time_sigma", "alpha_sigma", "alpha_bound"):
        if not getattr(p, key) > 0:
            raise InputError(f"config key 'pca.{key}' must be positive, got {getattr(p, key)}")
    if not p.joints:
        raise InputError("config key 'pca.joints' must name at least one tracked keypoint")
    known = tuple(keypoints) if keypoints is not None else H36M17
    for j in p.joints if names else ():
        if j not in known:
            raise InputError(f"config key 'pca.joints': unknown keypoint {j!r} (keypoints: {', '.join(known)})")


def validate_motion(m: MotionConfig) -> None:
    """Value checks of the `motion:` section (the clip count is checked when fitting)."""
    from ptrack.motion.key_postures import parse_rules

    if m.samples < 2:
        raise InputError(f"config key 'motion.samples' must be >= 2, got {m.samples}")
    if m.components < 1:
        raise InputError(f"config key 'motion.components' must be >= 1, got {m.components}")
    if not m.joints:
        raise InputError("config key 'motion.joints' must name at least one joint")
    if m.smooth_s < 0:
        raise InputError(f"config key 'motion.smooth_s' must be >= 0, got {m.smooth_s}")
    if not 0 <= m.prominence < 1:
        raise InputError(f"config key 'motion.prominence' must be in [0, 1), got {m.prominence}")
    if not 0 < m.rest_fraction < 1:
        raise InputError(f"config key 'motion.rest_fraction' must be in (0, 1), got {m.rest_fraction}")
    parse_rules(m.key_postures)


def to_dict(cfg) -> dict:
    """Plain nested dict (lists for tuples) of a config, for YAML/JSON output."""

    def conv(v):
        if dataclasses.is_dataclass(v):
            return {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, tuple):
            return [conv(x) for x in v]
        if isinstance(v, dict):
            return {k: conv(x) for k, x in v.items()}
        return v

    return conv(cfg)


def dump_yaml(cfg: RunConfig) -> str:
    """The config as YAML that `load_config` reads back the same (`YamlDumper`)."""
    return yaml.dump(to_dict(cfg), Dumper=YamlDumper, sort_keys=False)
