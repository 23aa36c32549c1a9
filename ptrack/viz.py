"""Rerun recordings of a ptrack run: the only module that imports rerun.

`write_recording(path, log)` writes one `.rrd` file through a dedicated `rr.RecordingStream`
(application id "ptrack"), never the global recording, so a caller's own rerun recording is left
alone. `open_viewer(path)` opens a saved file in the rerun viewer.

World frame: metres, Y up (CMU). Camera axes: OpenCV (x right, y down, z forward), with
x_cam = R @ x_world + t.

Timelines: every per-frame entity is logged on both
- `frame`: sequence timeline of AMC frame numbers (`RunLog.frames`), and
- `time`: duration timeline in seconds (`RunLog.times`);
`solver/cost` alone is on `iteration` (solver iterations of a whole-sequence solve).

Entity layout (stable: tests and users rely on it):

    world                               ViewCoordinates RIGHT_HAND_Y_UP (static)
    world/ground_truth/joints           Points3D (J per frame), green          [if ground truth]
    world/ground_truth/bones            LineStrips3D, one 2-point strip per (parent, child) bone
    world/estimate/joints               Points3D, orange
    world/estimate/bones                LineStrips3D
    world/hypotheses/h{n}/bones         LineStrips3D per hypothesis n = 0..N-1, blue; label
                                        "h{n} w=... cost=..." per frame, radius and colour alpha
                                        scaled by the weight relative to the frame's best weight
    world/hypotheses/h{n}/direction     Arrows3D from each joint of hypothesis n: its principal
                                        covariance direction (1 std)      [if hypothesis_directions]
    world/hypotheses/h{n}/weight        Scalars (per frame)                    [if hypotheses]
    world/hypotheses/h{n}/cost          Scalars (per frame)                    [if costs given]
    world/camera                        Transform3D camera-to-world (translation = camera centre,
                                        mat3x3 = R^T) + Pinhole (image_from_camera = K,
                                        resolution = [W, H], camera_xyz = RDF), both static
    world/camera/image/observed         Points2D of confident keypoints (confidence > 0),
                                        labels = keypoint names, yellow
    world/camera/image/reprojected      Points2D of the estimate's projected keypoints, magenta
    world/camera/image/silhouette       SegmentationImage, class 1 = silhouette  [if masks]
    world/estimate/std                  Points3D at the estimate's joints, radius = that joint's 3D
                                        standard deviation (metres), translucent  [if joint_std]
    metrics/<name>                      Scalars, one per frame with a finite value
    jumps/<chain>                       Scalars: kinematic-jump leaves kept per frame for each chain
    solver/cost                         Scalars: the objective after each solver iteration, on its
                                        own sequence timeline `iteration` (0 = the start)
                                        [if solver_cost]

Bones entities are omitted for a skeleton without (parent, child) pairs (a single joint).
"""

from __future__ import annotations

import logging
import subprocess
import sys
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import rerun as rr

from ptrack.errors import InputError

if TYPE_CHECKING:
    from ptrack.camera import Camera

__all__ = ["RunLog", "write_recording", "open_viewer"]

logger = logging.getLogger(__name__)

GROUND_TRUTH_COLOR = (70, 200, 110)
ESTIMATE_COLOR = (255, 140, 30)
HYPOTHESIS_COLOR = (80, 140, 255)
OBSERVED_COLOR = (255, 220, 0)
REPROJECTED_COLOR = (230, 60, 200)
JOINT_RADIUS = 0.02  # metres
BONE_RADIUS = 0.01  # metres
HYPOTHESIS_RADIUS = 0.006  # metres, at the frame's best weight
DIRECTION_COLOR = (160, 90, 255)
DIRECTION_RADIUS = 0.004  # metres
STD_COLOR = (255, 140, 30, 70)  # the estimate's colour, translucent
KEYPOINT_RADIUS = 3.0  # pixels


@dataclass(frozen=True, eq=False)
class RunLog:
    """Everything logged for one run. Arrays are numpy (torch tensors are accepted and converted).

    joint_names: (J,); parents: (J,) parent index, -1 for the root; bones are (parent, child).
    frames: (T,) int AMC frame numbers; times: (T,) seconds.
    estimate: (T, J, 3) metres, world; ground_truth: (T, J, 3) or None.
    camera: a `ptrack.camera.Camera` (anything with K (3, 3), R (3, 3), t (3,), width, height).
    observed: (T, K, 2) pixels; confidence: (T, K), 0 = missing (not drawn);
    reprojected: (T, K, 2) pixels; keypoint_names: (K,).
    hypotheses: (T, N, J, 3) or None; hypothesis_weights, hypothesis_costs: (T, N) or None;
    hypothesis_directions: (T, N, J, 3) metres or None.
    jumps: chain name -> (T,) kinematic-jump leaves kept per frame.
    scalars: name -> (T,) per-frame values, NaN = no value that frame.
    masks: (T, H, W) bool silhouettes with H, W the camera's height, width, or None.
    joint_std: (T, J) metres, per-joint 3D standard deviation of the estimate, or None.
    solver_cost: (I+1,) objective after each iteration of a whole-sequence solver, or None.

    Shapes are checked on construction; a mismatch raises `InputError` naming the field.
    """

    joint_names: tuple[str, ...]
    parents: tuple[int, ...]
    frames: np.ndarray
    times: np.ndarray
    estimate: np.ndarray
    ground_truth: np.ndarray | None
    camera: Camera
    observed: np.ndarray
    confidence: np.ndarray
    reprojected: np.ndarray
    keypoint_names: tuple[str, ...]
    hypotheses: np.ndarray | None = None
    hypothesis_weights: np.ndarray | None = None
    hypothesis_costs: np.ndarray | None = None
    hypothesis_directions: np.ndarray | None = None
    jumps: Mapping[str, np.ndarray] = field(default_factory=dict)
    scalars: Mapping[str, np.ndarray] = field(default_factory=dict)
    masks: np.ndarray | None = None
    joint_std: np.ndarray | None = None
    solver_cost: np.ndarray | None = None

    def __post_init__(self) -> None:
        for name in ("frames", "times", "estimate", "ground_truth", "observed", "confidence",
                     "reprojected", "hypotheses", "hypothesis_weights", "hypothesis_costs",
                     "hypothesis_directions", "masks", "joint_std", "solver_cost"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, _as_numpy(value))
        object.__setattr__(self, "joint_names", tuple(self.joint_names))
        object.__setattr__(self, "parents", tuple(int(p) for p in self.parents))
        object.__setattr__(self, "keypoint_names", tuple(self.keypoint_names))
        object.__setattr__(self, "scalars", {str(k): _as_numpy(v) for k, v in self.scalars.items()})
        object.__setattr__(self, "jumps", {str(k): _as_numpy(v) for k, v in self.jumps.items()})
        self._validate()

    def _validate(self) -> None:
        J, K = len(self.joint_names), len(self.keypoint_names)
        T = _check_shape("frames", self.frames, (None,))[0]
        if T == 0:
            raise InputError("RunLog.frames is empty: nothing to log")
        _check_shape("times", self.times, (T,))
        _check_shape("estimate", self.estimate, (T, J, 3))
        if len(self.parents) != J:
            raise InputError(f"RunLog.parents has {len(self.parents)} entries, expected J={J}")
        for child, parent in enumerate(self.parents):
            if parent != -1 and not (0 <= parent < J and parent != child):
                raise InputError(
                    f"RunLog.parents[{child}] = {parent} is not -1 or another joint index"
                )
        if self.ground_truth is not None:
            _check_shape("ground_truth", self.ground_truth, (T, J, 3))
        _check_shape("observed", self.observed, (T, K, 2))
        _check_shape("confidence", self.confidence, (T, K))
        _check_shape("reprojected", self.reprojected, (T, K, 2))
        if self.hypotheses is not None:
            N = _check_shape("hypotheses", self.hypotheses, (T, None, J, 3))[1]
            for name in ("hypothesis_weights", "hypothesis_costs"):
                if getattr(self, name) is not None:
                    _check_shape(name, getattr(self, name), (T, N))
            if self.hypothesis_directions is not None:
                _check_shape("hypothesis_directions", self.hypothesis_directions, (T, N, J, 3))
        elif any(x is not None for x in (self.hypothesis_weights, self.hypothesis_costs, self.hypothesis_directions)):
            raise InputError("RunLog.hypothesis_weights/costs/directions given without RunLog.hypotheses")
        for name, values in self.jumps.items():
            _check_shape(f"jumps[{name!r}]", values, (T,))
        for name, values in self.scalars.items():
            if not name:
                raise InputError("RunLog.scalars has an empty metric name")
            _check_shape(f"scalars[{name!r}]", values, (T,))
        if self.masks is not None:
            H, W = int(self.camera.height), int(self.camera.width)
            _check_shape("masks", self.masks, (T, H, W))
        if self.joint_std is not None:
            _check_shape("joint_std", self.joint_std, (T, J))
        if self.solver_cost is not None and _check_shape("solver_cost", self.solver_cost, (None,))[0] == 0:
            raise InputError("RunLog.solver_cost is empty")

    @property
    def num_frames(self) -> int:
        """T, the number of logged frames."""
        return int(self.frames.shape[0])


def write_recording(path: str | Path, log: RunLog) -> None:
    """Write `log` to the rerun file `path` (.rrd), with the entity layout in the module docstring.

    Uses its own `rr.RecordingStream`; the global rerun recording is not touched.
    Raises FileNotFoundError if the parent folder of `path` does not exist.
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise FileNotFoundError(
            f"cannot write rerun recording {path}: folder {path.parent} does not exist"
        )
    rec = rr.RecordingStream(application_id="ptrack")
    rec.save(path)
    try:
        T = log.num_frames
        index = [
            rr.TimeColumn("frame", sequence=log.frames.astype(np.int64)),
            rr.TimeColumn("time", duration=log.times.astype(np.float64)),
        ]
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
        bones = _bones(log.parents)
        if log.ground_truth is not None:
            _log_skeleton(rec, "world/ground_truth", log.ground_truth, bones,
                          GROUND_TRUTH_COLOR, index)
        _log_skeleton(rec, "world/estimate", log.estimate, bones, ESTIMATE_COLOR, index)
        if log.joint_std is not None:
            radii = np.nan_to_num(log.joint_std.astype(np.float64), nan=0.0, posinf=0.0).reshape(-1)
            rec.log("world/estimate/std", rr.Points3D.from_fields(colors=[STD_COLOR]), static=True)
            rec.send_columns("world/estimate/std", indexes=index, columns=rr.Points3D.columns(
                positions=log.estimate.reshape(-1, 3), radii=radii).partition([log.estimate.shape[1]] * T))
        if log.hypotheses is not None:
            _log_hypotheses(rec, log, bones, index)
        _log_camera(rec, log.camera)
        _log_keypoints(rec, log, index)
        if log.masks is not None:
            _log_masks(rec, log.masks, index)
        for name, values in log.scalars.items():
            _log_scalar(rec, f"metrics/{name}", values, log)
        for name, values in log.jumps.items():
            _log_scalar(rec, f"jumps/{name}", values.astype(np.float64), log)
        if log.solver_cost is not None:
            cost = log.solver_cost.astype(np.float64)
            rec.send_columns("solver/cost", indexes=[rr.TimeColumn("iteration", sequence=np.arange(len(cost)))],
                             columns=rr.Scalars.columns(scalars=cost))
        rec.flush()
        logger.info("wrote rerun recording %s (%d frames)", path, T)
    finally:
        rec.disconnect()


def open_viewer(path: str | Path, wait: bool = True) -> int | None:
    """Launch the rerun viewer (`python -m rerun PATH`) on the saved recording `path`.

    wait: block until the viewer closes and return its exit status; False: return at once (None).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"rerun recording {path} does not exist")
    proc = subprocess.Popen([sys.executable, "-m", "rerun", str(path)])
    return proc.wait() if wait else None


def _as_numpy(x: Any) -> np.ndarray:
    """Tensor or array-like -> numpy array (detached, on the host)."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def _check_shape(name: str, x: np.ndarray, shape: tuple[int | None, ...]) -> tuple[int, ...]:
    """Raise InputError unless x.shape matches `shape` (None = any size); return x.shape."""
    ok = x.ndim == len(shape) and all(s is None or s == d for s, d in zip(shape, x.shape))
    if not ok:
        want = str(tuple("*" if s is None else s for s in shape)).replace("'", "")
        raise InputError(f"RunLog.{name} has shape {tuple(x.shape)}, expected {want}")
    return tuple(x.shape)


def _bones(parents: Sequence[int]) -> np.ndarray:
    """parents: (J,) -> (B, 2) int (parent, child) pairs."""
    pairs = [(p, c) for c, p in enumerate(parents) if p >= 0]
    return np.asarray(pairs, dtype=np.int64).reshape(-1, 2)


def _strips(X: np.ndarray, bones: np.ndarray) -> np.ndarray:
    """X: (T, J, 3), bones: (B, 2) -> (T * B, 2, 3) one 2-point strip per bone and frame."""
    return X[:, bones].reshape(-1, 2, 3)


def _log_skeleton(rec: rr.RecordingStream, root: str, X: np.ndarray, bones: np.ndarray,
                  color: tuple[int, int, int], index: list[rr.TimeColumn]) -> None:
    """X: (T, J, 3) -> `{root}/joints` Points3D and `{root}/bones` LineStrips3D on every frame."""
    T, J, _ = X.shape
    joints, bone_strips = f"{root}/joints", f"{root}/bones"
    rec.log(joints, rr.Points3D.from_fields(colors=[color], radii=JOINT_RADIUS), static=True)
    rec.send_columns(joints, indexes=index,
                     columns=rr.Points3D.columns(positions=X.reshape(-1, 3)).partition([J] * T))
    if len(bones):
        rec.log(bone_strips, rr.LineStrips3D.from_fields(colors=[color], radii=BONE_RADIUS),
                static=True)
        strips = rr.LineStrips3D.columns(strips=_strips(X, bones)).partition([len(bones)] * T)
        rec.send_columns(bone_strips, indexes=index, columns=strips)


def _log_hypotheses(rec: rr.RecordingStream, log: RunLog, bones: np.ndarray,
                    index: list[rr.TimeColumn]) -> None:
    """(T, N, J, 3) hypotheses -> `world/hypotheses/h{n}/...`; see the module docstring."""
    H = log.hypotheses
    T, N = H.shape[:2]
    weights = log.hypothesis_weights
    weights = np.full((T, N), 1.0 / N) if weights is None else weights.astype(np.float64)
    best = np.max(np.where(np.isfinite(weights), weights, -np.inf), axis=1, keepdims=True)
    relative = np.where(best > 0, weights / np.where(best > 0, best, 1.0), 1.0)
    relative = np.clip(np.nan_to_num(relative, nan=0.0), 0.0, 1.0)  # (T, N)
    radii = HYPOTHESIS_RADIUS * (0.25 + 0.75 * relative)
    alpha = np.round(40 + 215 * relative).astype(np.uint8)
    rgb = np.broadcast_to(np.asarray(HYPOTHESIS_COLOR, dtype=np.uint8), (T, N, 3))
    colors = np.concatenate([rgb, alpha[..., None]], axis=-1)  # (T, N, 4)
    costs = log.hypothesis_costs
    for n in range(N):
        labels = [f"h{n} w={w:.3g}" for w in weights[:, n]]
        if costs is not None:
            labels = [f"{label} cost={c:.4g}" for label, c in zip(labels, costs[:, n])]
        entity = f"world/hypotheses/h{n}"
        if len(bones):
            strips = rr.LineStrips3D.columns(strips=_strips(H[:, n], bones))
            rec.send_columns(f"{entity}/bones", indexes=index, columns=[
                *strips.partition([len(bones)] * T),
                *rr.LineStrips3D.columns(labels=labels, radii=radii[:, n], colors=colors[:, n]),
            ])
        if log.hypothesis_directions is not None:
            arrows = rr.Arrows3D.columns(origins=H[:, n].reshape(-1, 3),
                                         vectors=log.hypothesis_directions[:, n].reshape(-1, 3))
            rec.log(f"{entity}/direction", rr.Arrows3D.from_fields(colors=[DIRECTION_COLOR], radii=DIRECTION_RADIUS),
                    static=True)
            rec.send_columns(f"{entity}/direction", indexes=index, columns=arrows.partition([H.shape[2]] * T))
        _log_scalar(rec, f"{entity}/weight", weights[:, n], log)
        if costs is not None:
            _log_scalar(rec, f"{entity}/cost", costs[:, n], log)


def _log_camera(rec: rr.RecordingStream, camera: Camera) -> None:
    """Static camera pose (camera-to-world) and pinhole intrinsics at `world/camera`."""
    K = _as_numpy(camera.K).astype(np.float64)
    R = _as_numpy(camera.R).astype(np.float64)
    t = _as_numpy(camera.t).astype(np.float64)
    if K.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,):
        raise InputError(f"RunLog.camera has K {K.shape}, R {R.shape}, t {t.shape}; "
                         "expected (3, 3), (3, 3), (3,)")
    center = -R.T @ t
    rec.log("world/camera", rr.Transform3D(translation=center, mat3x3=R.T), static=True)
    rec.log("world/camera", rr.Pinhole(image_from_camera=K,
                                       resolution=[int(camera.width), int(camera.height)],
                                       camera_xyz=rr.ViewCoordinates.RDF), static=True)


def _log_keypoints(rec: rr.RecordingStream, log: RunLog, index: list[rr.TimeColumn]) -> None:
    """Observed (confident only, labelled) and reprojected keypoints under `world/camera/image`."""
    names = np.asarray(log.keypoint_names, dtype=object)
    seen = (log.confidence > 0) & np.isfinite(log.observed).all(axis=-1)  # (T, K)
    rec.log("world/camera/image/observed",
            rr.Points2D.from_fields(colors=[OBSERVED_COLOR], radii=KEYPOINT_RADIUS), static=True)
    rec.send_columns("world/camera/image/observed", indexes=index, columns=rr.Points2D.columns(
        positions=log.observed[seen].reshape(-1, 2),
        labels=names[np.nonzero(seen)[1]].tolist(),
    ).partition(seen.sum(axis=1)))
    finite = np.isfinite(log.reprojected).all(axis=-1)
    rec.log("world/camera/image/reprojected",
            rr.Points2D.from_fields(colors=[REPROJECTED_COLOR], radii=KEYPOINT_RADIUS), static=True)
    rec.send_columns("world/camera/image/reprojected", indexes=index, columns=rr.Points2D.columns(
        positions=log.reprojected[finite].reshape(-1, 2)).partition(finite.sum(axis=1)))


def _log_masks(rec: rr.RecordingStream, masks: np.ndarray, index: list[rr.TimeColumn]) -> None:
    """masks: (T, H, W) bool -> SegmentationImage (class 1 = silhouette) on every frame."""
    T, H, W = masks.shape
    entity = "world/camera/image/silhouette"
    rec.log(entity, rr.AnnotationContext([(1, "silhouette", (255, 255, 255))]), static=True)
    fmt = rr.components.ImageFormat(width=W, height=H, channel_datatype="U8")
    rec.log(entity, rr.SegmentationImage.from_fields(format=fmt, opacity=0.4), static=True)
    rec.send_columns(entity, indexes=index, columns=rr.SegmentationImage.columns(
        buffer=(masks != 0).astype(np.uint8).reshape(T, -1)))


def _log_scalar(rec: rr.RecordingStream, entity: str, values: np.ndarray, log: RunLog) -> None:
    """values: (T,) -> Scalars at `entity` on the frames where the value is finite."""
    values = values.astype(np.float64)
    keep = np.isfinite(values)
    if not keep.any():
        logger.debug("no finite values for %s: nothing logged", entity)
        return
    rec.send_columns(entity, indexes=[
        rr.TimeColumn("frame", sequence=log.frames[keep].astype(np.int64)),
        rr.TimeColumn("time", duration=log.times[keep].astype(np.float64)),
    ], columns=rr.Scalars.columns(scalars=values[keep]))
