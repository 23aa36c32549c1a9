"""Run configuration: frozen dataclasses hold every default; YAML files and `dotted.key=value`
overrides replace them. Unknown keys and wrong types are `InputError`s naming the dotted key.

Paths in a YAML file are relative to that file's folder; paths given as command-line overrides are
relative to the working directory. Both are stored resolved (absolute) in the run's config.yaml.

Every key carries one line of help (`ptrack.settings.setting`): `config_reference` lists them for `ptrack config
--list` and docs/config.md. Why a default is what it is: docs/notes/config-history.md.

`RunConfig` composes the sections. A method's section and its value checks live beside the method
(`ptrack/estimators/frame.py`, `estimators/kjs/config.py`, `estimators/batch/config.py`, `estimators/pca/config.py`),
the motion model's in `ptrack/motion/config.py`, the shared cost terms' in `ptrack/costs/config.py`; the sections
of the run itself (data, camera, observations, model, keyframes), loading, overrides and the checks that span
sections are here.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path, PurePath
from typing import Any, Union

import yaml

from ptrack.body.acclaim import skeleton_beside
from ptrack.costs.base import ROBUST_LOSSES
from ptrack.costs.config import CostsConfig
from ptrack.errors import InputError
from ptrack.estimators.batch.config import BatchMethodConfig, validate_batch
from ptrack.estimators.frame import FrameMethodConfig, validate_frame
from ptrack.estimators.kjs.config import KjsMethodConfig, validate_kjs
from ptrack.estimators.pca.config import PcaMethodConfig, validate_pca
from ptrack.motion.config import MotionConfig, validate_motion
from ptrack.settings import setting

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
    floor_m: float | None = setting(
        0.0,
        "the floor's height along the calibration world's up axis, metres (used when camera.file has extrinsics "
        "and the up axis is known); null: no floor",
    )
    floor_from_person: bool = setting(
        True,
        "when the camera does not say where up is: the floor (its tilt where the feet span it, and its height) "
        "fitted to a first pass's feet, and the run made again on it (results then Y up along the floor's normal)",
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
    track_fps: float | None = setting(
        None,
        "real footage above this rate is tracked every n-th frame (n = round(fps / track_fps)), the frames between "
        "filled from their neighbours (docs/outputs.md); null: every frame",
    )
    filter_hz: float | None = setting(
        None,
        "real footage: the reported trajectory's poses low-passed at this frequency (Hz; zero-phase Butterworth, "
        "between jumps; ptrack.pipeline.run.lowpass_trajectory); null: as tracked",
    )
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
    body_height_m: float | None = setting(
        None,
        "simulated: the person seen is data.asf scaled to this height with Winter's proportions (as real footage's "
        "subject; ptrack/observe/person.py), a body other than the tracker's: its joints make the 2D, the "
        "silhouettes and the ground truth; null: data.asf itself",
    )
    silhouette_height_m: float | None = setting(
        None,
        "simulated: the silhouettes (and simulated correspondences) alone from the capsules of data.asf scaled to "
        "this height with Winter's proportions, the 2D and the ground truth from the seen person; null: theirs",
    )
    silhouette_radius_scale: float = setting(1.0, "simulated: the seen body's capsule radii times this")
    silhouette_radius_jitter: float = setting(
        0.0, "simulated: each capsule radius times a factor drawn in [1 - this, 1 + this] (left and right alike)"
    )
    keypoint_offset_m: float = setting(
        0.0,
        "simulated detector bias: each 2D keypoint marks a point this far (m) from its joint centre, in a direction "
        "fixed to its bone, drawn per seed",
    )
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
class SubjectConfig:
    """The person of real footage: the template skeleton (data.asf) scaled to a height, or as it is (lengths: asf)."""

    height_m: float | None = setting(
        None, "the person's height, metres; null: 1.70 m, with a warning (lengths asf: the skeleton's standing height)"
    )
    lengths: str = setting(
        "template",
        "template: the height's proportions; observed: measured in the 2D, then the method run again; asf: the bone "
        "lengths of data.asf as they are (a known skeleton; height_m null: the skeleton's standing height)",
    )
    static: str | None = setting(
        None,
        "keypoint file/folder of a static standing trial, same camera and format: the segment lengths measured "
        "on it replace the template's (ptrack/pipeline/static.py); subject.lengths observed is then not measured",
    )
    measure_stride: int = setting(
        1,
        "the first run of real footage (lengths observed, the floor from the person) tracks every n-th frame only; "
        "the second run tracks every frame",
    )
    measure_backward_pass: str | None = setting(
        None, "method kjs: kjs.backward_pass of that first run (always, tree, never); null: kjs.backward_pass"
    )
    depth_from_floor: bool = setting(
        False,
        "lengths observed with a calibrated floor: the first run's depths are scaled so that its standing feet touch "
        "the floor before the segments are measured (ptrack.estimators.lengths.floor_depth_factor)",
    )


@dataclass(frozen=True)
class KeyframesConfig:
    """3D keyframes: from a file (`ptrack/pipeline/keyframes.py` documents the YAML/JSON format) or, for
    synthetic evaluation, from the ground truth (frame 0 always; the methods other than batch read
    frame 0's only)."""

    file: str | None = setting(None, "YAML/JSON keyframe file; replaces the ground-truth keyframes")
    every_s: float | None = setting(None, "ground truth every this many seconds (null: frame 0 only)")
    last: bool = setting(False, "ground truth at the last frame too")
    first: bool = setting(
        True, "ground truth at frame 0 (false, with every_s null and last false: no 3D keyframe; for batch)"
    )
    noise_deg: float = setting(0.0, "Gaussian noise (std, degrees) added to the ground-truth keyframes' angles")
    sigma_deg: float = setting(2.0, "prior std of a ground-truth keyframe's angles (and a file's default), degrees")
    sigma_m: float = setting(
        0.02, "prior std of a ground-truth keyframe's root position and joints (and a file's default), m"
    )
    joints: tuple[str, ...] = setting(
        (),
        "ground truth after frame 0 gives only these joints' 3D positions (skeleton joint names, e.g. root, "
        "lwrist), not the pose; frame 0 stays a full pose (the start); empty: the whole pose",
    )
    dofs: tuple[str, ...] = setting(
        (),
        "ground truth after frame 0 gives only these dofs (names or shell patterns, e.g. 'root.*'), with "
        "keyframes.joints too if given; empty: every dof unless keyframes.joints is given",
    )
    noise_m: float = setting(
        0.0, "Gaussian noise (std, m) added to the ground-truth joint keyframes across the camera's view"
    )
    depth_noise_m: float = setting(
        0.0, "Gaussian noise (std, m) added to the ground-truth joint keyframes along the camera's optical axis"
    )
    joint_covariance: str = setting(
        "full",
        "prior of the ground-truth joint keyframes: full (the covariance of their noise plus sigma_m^2, "
        "depth apart from the image plane) or diagonal (its world-axis variances only)",
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
    plots: bool = setting(True, "write plots/ (PNG pictures of the run) in the run folder, results.png in evaluate's")
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


if typing.TYPE_CHECKING:
    from ptrack.estimators.frame import FrameRunConfig
    from ptrack.estimators.kjs.config import KjsRunConfig
    from ptrack.estimators.pca.config import PcaRunConfig

    # mypy: RunConfig is what each estimator reads of it (the protocols typing their `cfg`)
    _READ_BY_ESTIMATORS: tuple[FrameRunConfig, KjsRunConfig, PcaRunConfig] = (RunConfig(), RunConfig(), RunConfig())


METHODS = ("frame", "kjs", "css", "ss", "batch", "pca")
_PATH_KEYS = {
    "data.asf",
    "data.amc",
    "observations.file",
    "observations.correspondence_file",
    "observations.video",
    "camera.file",
    "subject.static",
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


#: keys that older configs may still hold -> what took their place (the error names it)
RETIRED_KEYS: dict[str, str] = {
    "kjs.smooth_sweeps": "kjs.stages (name smooth once per sweep, e.g. [smooth, recombine, decode])",
    "kjs.recombine": "kjs.stages (name recombine in it, e.g. [smooth, recombine, decode])",
    "kjs.weights": "kjs.stages (decode last: posterior weights; without it the passes' weights)",
    "kjs.path": "kjs.stages (decode last: the MAP path; without it the forward pass's Viterbi path)",
    "kjs.momentum": "nothing: it was removed on 2026-11-29 (measured worse)",
    "kjs.viterbi_space": "kjs.viterbi_sigma_m (the chain model's velocity prior is on the joints)",
    "kjs.viterbi_sigma": "kjs.viterbi_sigma_m (the chain model's velocity prior is on the joints)",
    "kjs.even_share": "nothing: it was removed on 2026-11-29 (0 measured the same within the seed spread; the "
    "diffusion samples follow the modes' weights, every mode at least one)",
    "kjs.smooth_link_m": "nothing: it was removed on 2026-11-29 (1000 measured the same on held-out, dev and "
    "tree-start runs; the smoother links each hypothesis to its nearest neighbours)",
    "kjs.ceiling_deg": "nothing: it was removed on 2026-11-29 (180 measured the same as 30 within the seed "
    "spread on the held-out and the dev clips; no sampling std is capped below half a turn)",
}


def _build(cls, raw: dict, prefix: str = ""):
    if not isinstance(raw, dict):
        raise InputError(f"config section {prefix.rstrip('.') or '(top level)'!r} must be a mapping, got {raw!r}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(raw) - names)
    if unknown:
        key = prefix + str(unknown[0])
        if key in RETIRED_KEYS:
            raise InputError(f"config key {key!r} is retired; use {RETIRED_KEYS[key]}")
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
    overrides: list[str] | tuple[str, ...] | Mapping[str, Any] = (),
    cwd: str | Path | None = None,
    run: bool = True,
) -> RunConfig:
    """Read a YAML run config (or only defaults when `path` is None) and apply overrides: `dotted.key=value`
    strings as the command line gives them (the value read as YAML), or from Python a mapping {dotted.key: value}
    of values as they are (a path may be a `Path`; relative paths are read from `cwd` either way).

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
    pairs = overrides.items() if isinstance(overrides, Mapping) else map(parse_override, overrides)
    for key, value in pairs:
        if isinstance(value, PurePath):
            value = str(value)
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
    if o.filter_hz is not None and not (math.isfinite(o.filter_hz) and o.filter_hz > 0):
        raise InputError(f"config key 'observations.filter_hz' must be a positive number or null, got {o.filter_hz}")
    if o.track_fps is not None and not 0 < o.track_fps <= 10000:
        raise InputError(f"config key 'observations.track_fps' must be in (0, 10000] or null, got {o.track_fps}")
    if not 0 <= o.min_score < 1:
        raise InputError(f"config key 'observations.min_score' must be in [0, 1), got {o.min_score}")
    if isinstance(o.person, tuple) and len(o.person) != 2:
        raise InputError(f"config key 'observations.person' must be a track id or [x, y], got {list(o.person)}")
    if c.fov_deg is not None and not 1 <= c.fov_deg <= 170:
        raise InputError(f"config key 'camera.fov_deg' must be in [1, 170] degrees, got {c.fov_deg}")
    if cfg.subject.lengths not in ("observed", "template", "asf"):
        raise InputError(f"config key 'subject.lengths' must be observed, template or asf, got {cfg.subject.lengths!r}")
    if cfg.subject.static and cfg.subject.lengths == "asf":
        raise InputError(
            "config keys 'subject.static' and 'subject.lengths: asf' both set the segment lengths: give one"
        )
    if cfg.subject.measure_stride < 1:
        raise InputError(f"config key 'subject.measure_stride' must be at least 1, got {cfg.subject.measure_stride}")
    if cfg.subject.measure_backward_pass not in (None, "always", "tree", "never"):
        raise InputError(
            "config key 'subject.measure_backward_pass' must be always, tree, never or null, got "
            f"{cfg.subject.measure_backward_pass!r}"
        )
    if cfg.subject.height_m is not None:
        from ptrack.body.subject import check_height

        check_height(cfg.subject.height_m)
    for key in ("body_height_m", "silhouette_height_m"):
        if getattr(o, key) is not None:
            from ptrack.body.subject import check_height

            check_height(getattr(o, key), f"observations.{key}")
    if not 0 < o.silhouette_radius_scale < float("inf"):
        raise InputError(
            f"config key 'observations.silhouette_radius_scale' must be positive, got {o.silhouette_radius_scale}"
        )
    if not 0 <= o.silhouette_radius_jitter < 1:
        raise InputError(
            f"config key 'observations.silhouette_radius_jitter' must be in [0, 1), got {o.silhouette_radius_jitter}"
        )
    if not 0 <= o.keypoint_offset_m < float("inf"):
        raise InputError(f"config key 'observations.keypoint_offset_m' must be >= 0, got {o.keypoint_offset_m}")
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
    validate_frame(cfg.frame)
    validate_kjs(cfg.kjs)
    kf = cfg.keyframes
    if kf.every_s is not None and not kf.every_s > 0:
        raise InputError(f"config key 'keyframes.every_s' must be positive or null, got {kf.every_s}")
    if kf.noise_deg < 0:
        raise InputError(f"config key 'keyframes.noise_deg' must be >= 0, got {kf.noise_deg}")
    for key in ("sigma_deg", "sigma_m"):
        if not getattr(kf, key) > 0:
            raise InputError(f"config key 'keyframes.{key}' must be positive, got {getattr(kf, key)}")
    for key in ("noise_m", "depth_noise_m"):
        if not getattr(kf, key) >= 0:
            raise InputError(f"config key 'keyframes.{key}' must be >= 0, got {getattr(kf, key)}")
    if kf.joint_covariance not in ("full", "diagonal"):
        raise InputError(
            f"config key 'keyframes.joint_covariance' must be 'full' or 'diagonal', got {kf.joint_covariance!r}"
        )
    b = cfg.batch
    validate_batch(b)
    if b.upsample > 1 and cfg.data.stride % b.upsample:
        raise InputError(
            f"config key 'batch.upsample' ({b.upsample}) must divide data.stride ({cfg.data.stride}): "
            f"the reconstruction is read at stride {cfg.data.stride}/{b.upsample}"
        )
    if cfg.costs.sigma_px <= 0:
        raise InputError(f"config key 'costs.sigma_px' must be positive, got {cfg.costs.sigma_px}")
    if cfg.costs.swap_cost is not None and not (math.isfinite(cfg.costs.swap_cost) and cfg.costs.swap_cost >= 0):
        raise InputError(
            f"config key 'costs.swap_cost' must be a finite number >= 0 or null, got {cfg.costs.swap_cost}"
        )
    if cfg.costs.loss not in ROBUST_LOSSES:
        raise InputError(f"config key 'costs.loss' must be one of {', '.join(ROBUST_LOSSES)}, got {cfg.costs.loss!r}")
    # the tracked keypoints are checked against the simulated set here; observations read from a file (a detector's,
    # or saved ones) are checked once the file's set is known (`ptrack.estimators.pca.setup.tracked_keypoint`: its own
    # names or landmarks)
    footage = cfg.observations.file is not None or cfg.observations.video is not None
    validate_pca(cfg.pca, cfg.model.keypoints, names=cfg.method == "pca" and not footage)


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
