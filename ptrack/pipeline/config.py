"""Run configuration: frozen dataclasses hold every default; YAML files and `dotted.key=value`
overrides replace them. Unknown keys and wrong types are `InputError`s naming the dotted key.

Paths in a YAML file are relative to that file's folder; paths given as command-line overrides are
relative to the working directory. Both are stored resolved (absolute) in the run's config.yaml.

Every key carries one line of help (`setting`): `config_reference` lists them for `ptrack config --list` and
docs/config.md. Why a default is what it is: docs/notes/config-history.md.
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


_T = typing.TypeVar("_T")


def setting(default: _T, help: str) -> _T:
    """A config key's field: its default and one line of help, which `config_reference` (`ptrack config --list`,
    docs/config.md) reads from the field's metadata. The measurements behind the defaults are in
    docs/notes/config-history.md."""
    return field(default=default, metadata={"help": help})


@dataclass(frozen=True)
class DataConfig:
    """The motion capture clip: skeleton, motion and the frames used."""

    asf: str = setting("", "ASF skeleton file")
    amc: str = setting("", "AMC motion file (120 fps); an override of data.amc alone takes the skeleton beside it")
    start: int = setting(0, "first AMC frame index (0-based) to reconstruct")
    stop: int | None = setting(None, "one past the last frame index; null = to the end")
    stride: int = setting(4, "keep every stride-th frame (4: 120 -> 30 fps)")


@dataclass(frozen=True)
class CameraConfig:
    """The virtual camera, looking at the centre of the motion's bounding box."""

    distance_m: float = setting(5.0, "distance from the centre of the motion's bounding box, metres")
    azimuth_deg: float = setting(30.0, "about world up (+Y), from +Z towards +X, degrees")
    elevation_deg: float = setting(10.0, "above the horizontal, degrees; positive looks down")
    focal_px: float = setting(1000.0, "focal length, pixels")
    width: int | None = setting(
        None, "image width, pixels; null: 640 when simulating, else the camera file's or video's"
    )
    height: int | None = setting(
        None, "image height, pixels; null: 480 when simulating, else the camera file's or video's"
    )
    file: str | None = setting(
        None, "real footage: camera file (Pose2Sim TOML, OpenCV YAML/JSON, EasyMocap intri/extri)"
    )
    name: str | None = setting(None, "the camera of camera.file (cam01, cam_01 or 1); null: its only camera")
    up: str | None = setting(
        None, "the calibration world's up axis (x, y, z, -y, ...); null: +Z for Pose2Sim, else level camera"
    )
    fov_deg: float | None = setting(
        None, "no camera.file: diagonal field of view, degrees; null: focal = image diagonal"
    )


@dataclass(frozen=True)
class ObservationsConfig:
    """The 2D observations: a file, or the seeded lossy channel that simulates them (DiFranco et al. §2)."""

    file: str | None = setting(
        None, "real 2D keypoints: a detector's file or folder (OpenPose, COCO, MMPose, MediaPipe, npz); null = simulate"
    )
    video: str | None = setting(None, "a video to detect the keypoints in first (MediaPipe; the video extra)")
    format: str | None = setting(
        None, "observations.file's format: openpose, coco, mmpose, mediapipe, npz; null: inferred"
    )
    keypoint_set: str | None = setting(None, "the file's keypoint set (BODY_25B, COCO_17, ...); null: inferred")
    fps: float | None = setting(None, "frames per second of the keypoint file; null: the file's or the video's")
    person: int | tuple[float, ...] | None = setting(
        None, "the person to reconstruct: a track id, or [x, y] px in the first frame; null: largest, most present"
    )
    min_score: float = setting(0.3, "detector scores below this are missing keypoints (Pose2Sim's threshold)")
    noise_px: float = setting(2.0, "Gaussian pixel noise std")
    missing: float = setting(0.0, "fraction of keypoints deleted at random")
    outliers: float = setting(0.0, "fraction of kept keypoints (confidence 1) that are gross outliers")
    outlier_px: float = setting(50.0, "displacement of a gross outlier, pixels")
    swap_fraction: float = setting(0.5, "share of outliers that are left/right swaps")
    occlusion_bursts: float = setting(0.0, "expected occlusion bursts per keypoint per second")
    dropped_frames: float = setting(0.0, "fraction of whole frames dropped")
    silhouettes: bool = setting(False, "render capsule-model silhouettes")
    correspondence_file: str | None = setting(
        None,
        "npz of real point correspondences between consecutive frames (method pca; ptrack/observe/correspondences.py)",
    )
    correspondences: int = setting(0, "point correspondences simulated per frame on the capsule model (0: none)")
    correspondence_noise_px: float = setting(1.0, "Gaussian noise std of a simulated pair's second point, pixels")
    correspondence_outliers: float = setting(0.0, "share of wrong simulated pairs (displaced by outlier_px)")


@dataclass(frozen=True)
class ModelConfig:
    """The body model: which dofs are estimated, the keypoint set, the joint limits."""

    freeze: tuple[str, ...] = setting(
        ("*fingers", "*thumb", "*hand", "*toes"), "dofs held at zero (shell patterns on joint or dof names)"
    )
    keypoints: dict[str, str] | None = field(
        default=None, metadata={"help": "keypoint name -> skeleton joint; null = the H36M-17 set on CMU joints"}
    )
    limits: str = setting("data", "joint limits: data (measured on real CMU motion), asf (the file's own), none")


@dataclass(frozen=True)
class CostsConfig:
    """Cost terms shared by the estimators: reprojection, joint limits, temporal prior."""

    sigma_px: float = setting(2.0, "reprojection noise scale, pixels")
    loss: str = setting("cauchy", "robust kernel of the reprojection: l2, huber, cauchy, geman_mcclure")
    robust_scale: float = setting(3.0, "the robust kernel's scale, in sigmas")
    limits_weight: float = setting(1.0, "weight of the joint-limit barrier")
    limits_sigma: float = setting(0.02, "scale of the joint-limit barrier, radians")
    smooth_weight: float = setting(1.0, "weight of the temporal prior")
    smooth_sigma: float = setting(0.15, "velocity scale of the temporal prior, radians (or metres) per frame")
    accel_sigma: float | None = setting(
        None, "acceleration scale of the temporal prior, radians (or metres) per frame^2; null = velocity only"
    )


@dataclass(frozen=True)
class FrameMethodConfig:
    """`method: frame`, the per-frame baseline: L-BFGS on each frame from the previous one."""

    init: str = setting("keyframe", "keyframe: first frame's 3D pose given (as a user keyframe); rest: rest pose")
    iterations: int = setting(40, "L-BFGS iterations per frame")
    first_iterations: int = setting(200, "L-BFGS iterations on the first frame")
    init_yaws: int = setting(1, "init rest: headings of the rest pose fitted on the first frame (the cheapest kept)")


@dataclass(frozen=True)
class KjsMethodConfig:
    """Settings of the sampling trackers `kjs` (kinematic jumps + CSS diffusion), `css` and `ss`."""

    modes: int = setting(8, "K: mixture modes kept per frame")
    samples: int = setting(256, "hypotheses per frame: the K predicted modes, diffusion samples and (kjs) jump leaves")
    scale: float = setting(4.0, "covariance scale s of the diffusion (s times the inverse Gauss-Newton Hessian)")
    tail: str = setting("student", "diffusion tail: gaussian, student, cauchy")
    tail_dof: float = setting(3.0, "Student-t degrees of freedom (tail: student)")
    chains: tuple[str, ...] = setting(
        ("larm", "rarm", "lleg", "rleg", "head"), "kinematic sub-chains that may be flipped (ptrack.hypotheses.jumps)"
    )
    jumps_per_sample: int = setting(1, "chains flipped per diffusion sample, chosen by covariance voting")
    limits_mode: str = setting("prune", "jump leaves outside the joint limits: prune or project")
    polisher: str = setting("lm", "local optimiser of every hypothesis: lm (Levenberg-Marquardt) or lbfgs")
    polish_iterations: int = setting(4, "Levenberg-Marquardt iterations of every hypothesis")
    refine_iterations: int = setting(10, "further iterations of the 4K most promising distinct minima")
    momentum: float = setting(0.0, "share of a mode's last velocity in its prediction (0: constant position)")
    distinct_mm: float = setting(0.0, "minima whose joints are all closer (mm) are one; 0: compare dofs (distinct_deg)")
    distinct_deg: float = setting(3.0, "with distinct_mm 0: minima closer than this in every dof are one")
    even_share: float = setting(0.5, "share of the diffusion samples split equally over the modes (the rest by weight)")
    temperature: float = setting(1.0, "weights ∝ prior * exp(-cost / temperature)")
    weight_memory: float = setting(0.5, "a new mode's weight ∝ parent's weight ** weight_memory * exp(-cost / T)")
    prior_sigma: float = setting(0.05, "the dynamics' velocity std, radians (or metres) per frame, where no table")
    dynamics: str | None = setting(
        "cmu-train", "per-dof velocity std table: cmu-train, cmu (dev clips) or null (prior_sigma for all)"
    )
    dynamics_scale: float = setting(1.5, "the table's stds are multiplied by this")
    dynamics_floor: float = setting(0.02, "least velocity std per frame from the table")
    prior_tail: str = setting("cauchy", "tails of the dynamics prior: gaussian, or a robust loss (cauchy, ...)")
    prior_tail_scale: float = setting(3.0, "where the robust tail begins, in standard deviations")
    motion_scale: float = setting(1.0, "the prior's std widened by this times each mode's last displacement")
    pose_prior_weight: float = setting(
        0.1, "weight of the CMU pose prior (ptrack.body.pose_prior) in every tracking step"
    )
    collision_weight: float = setting(1.0, "weight of the body non-self-intersection term")
    floor_deg: float = setting(0.5, "smallest sampling std per dof (unobservable directions), degrees")
    ceiling_deg: float = setting(30.0, "largest sampling std per dof, degrees")
    viterbi_space: str = setting("joints", "best trajectory's velocity prior: on joints relative to the root, or dofs")
    viterbi_sigma_m: float = setting(0.05, "viterbi_space joints: velocity std, metres per frame and coordinate")
    viterbi_sigma: float = setting(0.05, "viterbi_space dofs: velocity std, radians per frame")
    init: str = setting("keyframe", "keyframe: frame 0's 3D pose given; tree: rest pose fitted in view + every flip")
    start_prior_scale: float = setting(1.5, "init tree: the CMU pose prior's spread is scaled by this")
    rest_sigma: float = setting(1.0, "init tree: std around 0 of the angles the pose prior does not name, radians")
    init_yaws: int = setting(8, "init tree: headings of the rest pose tried (each also leaned forward and back)")
    init_fits: int = setting(4, "init tree: distinct fitted poses whose chains are flipped (every combination)")
    backward_pass: str = setting("always", "a second pass backwards in time: always, tree (after a tree start), never")
    smooth_sweeps: int = setting(1, "sweeps of the smoother over every frame's hypotheses after the passes (0: none)")
    smooth_scale: float = setting(0.2, "the smoother's prior std, times the dynamics'")
    smooth_link_m: float = setting(0.1, "smoother: neighbours within this mean joint distance (metres) are linked")
    recombine: bool = setting(True, "one more hypothesis per frame: each chain's reading by its own Viterbi pass")
    recombine_sigma_m: float = setting(0.15, "recombine: velocity std on the chain's joints, metres per frame")


@dataclass(frozen=True)
class SubjectConfig:
    """The person of real footage: the template skeleton (data.asf) scaled to a height."""

    height_m: float | None = setting(None, "the person's height, metres; null: 1.70 m, with a warning")


@dataclass(frozen=True)
class KeyframesConfig:
    """3D keyframes: from a file (`ptrack/pipeline/keyframes.py` documents the YAML/JSON format) or, for
    synthetic evaluation, from the ground truth (frame 0 always; the methods other than batch read
    frame 0's only)."""

    file: str | None = setting(None, "YAML/JSON keyframe file; replaces the ground-truth keyframes")
    every_s: float | None = setting(None, "ground truth every this many seconds (null: frame 0 only)")
    last: bool = setting(False, "ground truth at the last frame too")
    noise_deg: float = setting(0.0, "Gaussian noise (std, degrees) added to the ground-truth keyframes' angles")
    sigma_deg: float = setting(2.0, "prior std of a ground-truth keyframe's angles (and a file's default), degrees")
    sigma_m: float = setting(0.02, "prior std of a ground-truth keyframe's root position (and a file's default), m")


@dataclass(frozen=True)
class PcaMethodConfig:
    """`method: pca`, the golf-swing tracker over a PCA motion model (Urtasun, Fleet & Fua 2004): per sliding
    window, the PCA weights (shared), a normalised time per frame and the root pose per frame (eq. 5), fitted by
    Levenberg-Marquardt to the tracked joints and the silhouettes (eq. 7). The model is `motion.model_file`
    (fitted from `motion.clips` on first use and cached there)."""

    window: int = setting(3, "f: frames per window")
    step: int = setting(1, "frames the window slides by (at most the window; 1: every frame is fitted f times)")
    iterations: int = setting(2, "Levenberg-Marquardt iterations per window; 0 = the start alone (the mean motion)")
    joints: tuple[str, ...] = setting(
        ("l_knee", "r_knee", "l_ankle", "r_ankle", "l_wrist", "r_wrist", "head"),
        "tracked keypoints (names of the keypoint set): the paper's knees, ankles, wrists, head",
    )
    joint_weight: float = setting(1.0, "w of the joint projections (pixels / costs.sigma_px, robust by costs.loss)")
    silhouette_weight: float = setting(1.0, "w of the foreground term (section 4.1); 0 = joints only")
    correspondence_weight: float = setting(0.3, "w of each point correspondence (section 4.3); 0 = unused")
    correspondence_margin_m: float = setting(
        0.03, "a pair counts only where p1's line of sight passes this far (m) from the model's outline"
    )
    silhouette_sigma_m: float = setting(0.02, "a ray this far (metres) from the model counts as one sigma")
    silhouette_samples: int = setting(96, "foreground samples per frame (a regular grid, evenly thinned)")
    silhouette_step_px: int = setting(4, "grid step of the samples, pixels")
    root_sigma_m: float = setting(0.02, "prediction std of the root position, metres per frame")
    root_sigma_deg: float = setting(3.0, "prediction std of the root orientation, degrees per frame")
    time_sigma: float = setting(0.01, "prediction std of the normalised time per frame")
    timing_sigma: float | None = setting(0.03, "std of a prior holding each frame's time near the start's; null: none")
    alpha_sigma: float = setting(0.1, "prediction std of the PCA weights, in the model's per-component std")
    alpha_prior_weight: float = setting(1.0, "weight of the prior alpha ~ N(0, sigma^2) of the training swings")
    alpha_bound: float = setting(3.0, "|alpha_i| at most this many training stds (a box in the solver)")
    init_yaws: int = setting(8, "headings of the first frame's root placement tried (section 5.1)")
    key_smooth_s: float = setting(0.05, "Gaussian smoothing (std, s) of the 2D wrist track before the key postures")


@dataclass(frozen=True)
class BatchMethodConfig:
    """`method: batch`, the MAP trajectory of the whole sequence (DiFranco, Cham & Rehg 2001)."""

    iterations: int = setting(30, "Levenberg-Marquardt iterations on the whole trajectory")
    tol: float = setting(1e-9, "relative energy decrease (or step) at which it stops")
    damping: float = setting(1e-8, "initial lambda, relative to the Hessian's largest diagonal entry")
    velocity_sigma: float | None = setting(3.0, "velocity smoothing std of the angles, rad/s; null drops the term")
    accel_sigma: float | None = setting(8.0, "acceleration smoothing std of the angles, rad/s^2; null drops the term")
    velocity_sigma_m: float | None = setting(1.0, "velocity smoothing std of the root position, m/s; null: none")
    accel_sigma_m: float | None = setting(2.0, "acceleration smoothing std of the root position, m/s^2; null: none")
    prior: str | None = setting("cmu", "per-dof smoothing scales replacing the sigmas: cmu (real motion) or null")
    smooth_loss: str = setting("cauchy", "the smoothing residuals' loss: l2, huber, cauchy, geman_mcclure")
    smooth_scale: float = setting(2.0, "the smoothing loss's scale, in prior standard deviations")
    upsample: int = setting(1, "reconstruct N frames per observed frame (data.stride must be divisible by N)")
    init: str = setting("frame", "start: frame (per-frame fits, frame.* settings) or keyframes (interpolated)")
    uncertainty: bool | str = setting(
        "branches", "joint_std in result.npz: branches (true), laplace (faster, overconfident), false = none"
    )
    flip_restarts: int = setting(3, "rounds of restarts from the limbs' depth-flip branches (0: none)")


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

    clips: tuple[str, ...] = setting((), "training clips: AMC files, or one text file listing them; .asf beside each")
    joints: tuple[str, ...] = setting(("lradius", "rradius"), "tracked point of the key postures: their mean (wrists)")
    exclude: tuple[str, ...] = setting(
        ("*fingers", "*thumb", "*hand", "*toes"), "dofs left out of the model besides the root's (as model.freeze)"
    )
    key_postures: dict[str, str] = field(
        default_factory=lambda: dict(GOLF_KEY_POSTURES),
        metadata={
            "help": "name -> rule, in temporal order (ptrack/motion/key_postures.py); an override replaces them all"
        },
    )
    smooth_s: float = setting(0.05, "Gaussian smoothing (std, seconds) of the tracked point before the rules")
    prominence: float = setting(0.02, "first/last extrema: least prominence, as a fraction of the signal's range")
    rest_fraction: float = setting(0.05, "rest: slower than this fraction of the clip's top speed")
    samples: int = setting(200, "N: normalised times per swing")
    components: int = setting(4, "m: eigen-motions kept (at most the number of clips - 1)")
    model_file: str | None = setting(
        None, "where fit-motion writes the model and pca reads it; null = ~/.cache/ptrack/motion/<name>.npz"
    )


@dataclass(frozen=True)
class RunConfig:
    """A run: the method, where it writes, and one section per part."""

    method: str = setting("frame", "estimator: frame, kjs, css, ss, batch, pca")
    seed: int = setting(0, "seeds the observation channel and any sampling")
    out_dir: str | None = setting(None, "run folder; null = logs/<config-name>-<time>/")
    device: str = setting("cpu", "where the estimators compute: cpu, cuda, cuda:N, mps")
    dtype: str = setting("float32", "precision of the estimators: float32 or float64")
    progress: bool = setting(True, "progress bar on a terminal, a progress line every 20 s elsewhere")
    data: DataConfig = field(default_factory=DataConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    observations: ObservationsConfig = field(default_factory=ObservationsConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    costs: CostsConfig = field(default_factory=CostsConfig)
    frame: FrameMethodConfig = field(default_factory=FrameMethodConfig)
    kjs: KjsMethodConfig = field(default_factory=KjsMethodConfig)
    subject: SubjectConfig = field(default_factory=SubjectConfig)
    keyframes: KeyframesConfig = field(default_factory=KeyframesConfig)
    batch: BatchMethodConfig = field(default_factory=BatchMethodConfig)
    pca: PcaMethodConfig = field(default_factory=PcaMethodConfig)
    motion: MotionConfig = field(default_factory=MotionConfig)
    init_from: str | None = setting(None, "batch: start from this earlier run folder's trajectory (same model, frames)")
    name: str = setting("run", "config name (default: the YAML file's), used in the default out_dir")


METHODS = ("frame", "kjs", "css", "ss", "batch", "pca")
_PATH_KEYS = {
    "data.asf",
    "data.amc",
    "observations.file",
    "observations.correspondence_file",
    "observations.video",
    "camera.file",
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
    if not cfg.data.amc and not cfg.observations.file and not cfg.observations.video:
        raise InputError(
            "config key 'data.amc' is required (path to the AMC file), or observations.file / observations.video"
        )
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
        if getattr(c, k) is not None and getattr(c, k) <= 0:
            raise InputError(f"config key 'camera.{k}' must be positive, got {getattr(c, k)}")
    from ptrack.observe.observations import CHANNEL_RANGES, channel_range_error

    for k in CHANNEL_RANGES:  # the channel's own intervals, named by the config key
        error = channel_range_error(k, getattr(cfg.observations, k))
        if error:
            raise InputError(f"config key 'observations.{k}' {error}")
    o = cfg.observations
    if o.file and o.video:
        raise InputError("config keys 'observations.file' and 'observations.video' are both set: give one")
    if o.fps is not None and not 0 < o.fps <= 10000:
        raise InputError(f"config key 'observations.fps' must be in (0, 10000], got {o.fps}")
    if not 0 <= o.min_score < 1:
        raise InputError(f"config key 'observations.min_score' must be in [0, 1), got {o.min_score}")
    if isinstance(o.person, tuple) and len(o.person) != 2:
        raise InputError(f"config key 'observations.person' must be a track id or [x, y], got {list(o.person)}")
    if c.fov_deg is not None and not 1 <= c.fov_deg <= 170:
        raise InputError(f"config key 'camera.fov_deg' must be in [1, 170] degrees, got {c.fov_deg}")
    if cfg.subject.height_m is not None:
        from ptrack.body.subject import check_height

        check_height(cfg.subject.height_m)
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
    if cfg.frame.init_yaws < 1:
        raise InputError(f"config key 'frame.init_yaws' must be >= 1, got {cfg.frame.init_yaws}")
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


class ConfigKey(typing.NamedTuple):
    """One config key of `config_reference`: its dotted name, type annotation, default (as YAML) and help."""

    key: str
    type: str
    default: str
    help: str


def sections() -> tuple[str, ...]:
    """The config's sections (`data`, `camera`, ...), in `RunConfig`'s order."""
    default = RunConfig()
    return tuple(f.name for f in dataclasses.fields(RunConfig) if dataclasses.is_dataclass(getattr(default, f.name)))


def _as_yaml(value: Any) -> str:
    """A default as one line of YAML that `load_yaml` reads back: `null`, `true`, `1e-09`, `[larm, rarm]`."""
    if isinstance(value, float):
        return repr(value)
    text = yaml.dump(to_dict(value), Dumper=YamlDumper, default_flow_style=True, width=10**9, sort_keys=False)
    return text.removesuffix("\n...\n").strip()


def config_reference(section: str | None = None) -> list[ConfigKey]:
    """Every config key (the top-level ones, then each section's), or one section's, with its type, default and
    one line of help (the fields' metadata, `setting`). An unknown section is an `InputError` listing them."""
    known = sections()
    if section is not None and section not in known:
        raise InputError(f"unknown config section {section!r} (sections: {', '.join(known)})")
    default = RunConfig()
    groups: list[tuple[str, Any, list[dataclasses.Field]]] = []
    if section is None:
        groups.append(("", default, [f for f in dataclasses.fields(RunConfig) if f.name not in known]))
    for name in known:
        if section in (None, name):
            groups.append((f"{name}.", getattr(default, name), list(dataclasses.fields(getattr(default, name)))))
    out = []
    for prefix, instance, fields in groups:
        for f in fields:
            value = getattr(instance, f.name)
            out.append(ConfigKey(prefix + f.name, str(f.type), _as_yaml(value), f.metadata.get("help", "")))
    return out


def dump_yaml(cfg: RunConfig) -> str:
    """The config as YAML that `load_config` reads back the same (`YamlDumper`)."""
    return yaml.dump(to_dict(cfg), Dumper=YamlDumper, sort_keys=False)
