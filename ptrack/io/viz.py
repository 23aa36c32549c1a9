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
                                        "h{n} w=... cost=..." per frame (shown on hover), radius and
                                        colour alpha scaled by the weight relative to the frame's
                                        best weight
    world/hypotheses/h{n}/direction     Arrows3D from each joint of hypothesis n: its principal
                                        covariance direction (1 std)      [if hypothesis_directions]
    world/hypotheses/h{n}/weight        Scalars (per frame)                    [if hypotheses]
    world/hypotheses/h{n}/cost          Scalars (per frame)                    [if costs given]
    world/camera                        Transform3D camera-to-world (translation = camera centre,
                                        mat3x3 = R^T) + Pinhole (image_from_camera = K,
                                        resolution = [W, H], camera_xyz = RDF,
                                        image_plane_distance = IMAGE_PLANE_FRACTION x the distance
                                        from the camera to the mean estimated joint), both static
    world/legend                        Points3D above the motion, one per skeleton kind drawn, in
                                        its colour, labelled "estimate", "ground truth",
                                        "hypotheses" (static)
    world/camera/image/border           LineStrips2D: the image rectangle [0, W] x [0, H] (static)
    world/camera/image/observed         Points2D of confident keypoints (confidence > 0), large,
                                        yellow; labels = keypoint names (shown on hover)
    world/camera/image/observed_bones   LineStrips2D between observed keypoints whose keypoint
                                        parent is observed too          [if keypoint_joints]
    world/camera/image/reprojected      Points2D of the estimate's projected keypoints, small,
                                        in the estimate's colour, drawn above the observed ones
    world/camera/image/reprojected_bones  LineStrips2D between reprojected keypoints  [if keypoint_joints]
    world/camera/image/legend           Points2D along the image's top edge labelled "observed" and
                                        "reprojected estimate" (static)
    world/camera/image/silhouette       SegmentationImage, class 1 = silhouette, class 0
                                        transparent  [if masks]
    world/camera/image/video            AssetVideo (the input video's file, static) + VideoFrameReference
                                        per frame (`RunLog.video_frames`), drawn under everything else
                                        in the image, on the same `frame`/`time` rows as the 3D
                                        [if video; `log_video`]
    world/estimate/std                  Points3D at the estimate's joints, radius = that joint's 3D
                                        standard deviation (metres), translucent  [if joint_std]
    metrics/<name>                      Scalars, one per frame with a finite value; real footage adds
                                        the checks without ground truth: jitter_mm_per_frame2,
                                        foot_skating_mm_per_frame (the mean horizontal step of the
                                        foot points on the floor), ambiguous_frame (0/1) and
                                        ambiguous_limb_share (with hypotheses), left_right_exchanged
                                        (0/1: the result reads the detector's labels the other way
                                        round), person_missing (0/1)
    jumps/<chain>                       Scalars: kinematic-jump leaves kept per frame for each chain
    pca/time                            Scalars: the motion model's normalised time per frame  [if motion_time]
    pca/weights/alpha<i>                Scalars: the i-th PCA weight per frame  [if motion_weights]
    pca/key_postures                    TextLog at each key posture's frame: its name (`start`, `top`,
                                        ...)  [if key_postures]
    solver/cost                         Scalars: the objective after each solver iteration, on its
                                        own sequence timeline `iteration` (0 = the start)
                                        [if solver_cost]

Bones entities are omitted for a skeleton without (parent, child) pairs (a single joint). A
keypoint's parent is the nearest skeleton ancestor of its joint that is a keypoint too.

Blueprint (the layout the viewer opens with): `blueprint(log)` is sent with every recording as its
active and default blueprint (stored in the same .rrd as a blueprint store). On top, side by side:
the 3D scene (`world`, seen from beside the line from the person to the camera, so that both are in
view), a 3D close-up of the person that follows the estimate (the camera and legend left out), and
the camera's 2D view; under them a grid of time-series plots, `plot_groups(log)`, in which every
scalar entity is in exactly one plot.
The time panel starts on `time`, so playback runs at the clip's real rate; `frame` (AMC frame
numbers, 120 per second) stays available in the timeline menu.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import quote

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from ptrack.errors import InputError

if TYPE_CHECKING:
    from ptrack.observe.camera import Camera

__all__ = ["RunLog", "blueprint", "log_video", "open_viewer", "plot_groups", "write_recording"]

logger = logging.getLogger(__name__)

GROUND_TRUTH_COLOR = (70, 200, 110)
ESTIMATE_COLOR = (255, 140, 30)
HYPOTHESIS_COLOR = (80, 140, 255)
OBSERVED_COLOR = (255, 220, 0)
REPROJECTED_COLOR = ESTIMATE_COLOR  # the estimate, seen through the camera
BORDER_COLOR = (150, 150, 150)
JOINT_RADIUS = 0.02  # metres
BONE_RADIUS = 0.01  # metres
HYPOTHESIS_RADIUS = 0.008  # metres, at the frame's best weight
DIRECTION_COLOR = (160, 90, 255)
DIRECTION_RADIUS = 0.004  # metres
STD_COLOR = (255, 140, 30, 70)  # the estimate's colour, translucent
KEYPOINT_RADIUS = 3.0  # pixels, reprojected keypoints
OBSERVED_RADIUS = 6.0  # pixels: observed keypoints are drawn larger, under the reprojected ones
KEYPOINT_BONE_RADIUS = 1.0  # pixels
LEGEND_RADIUS = 0.05  # metres
LEGEND_SPACING = 0.4  # metres between the 3D legend's entries
IMAGE_PLANE_FRACTION = 0.3  # the camera's image plane in 3D, as a share of its distance to the person
VIDEO_ENTITY = "world/camera/image/video"
VIDEO_DRAW_ORDER = -20.0  # under the border (5), the bones (10, 30) and the keypoints (20, 40)
EYE_AZIMUTH_DEG = 75.0  # 3D scene viewpoint: from the person-to-camera direction turned about +Y by this,
EYE_ELEVATION_DEG = 20.0  # ... and raised by this, far enough that a cone of half-angle
EYE_HALF_FOV_DEG = 24.0  # ... this holds the sphere around the camera and the whole motion
CLOSEUP_AZIMUTH_DEG = -60.0  # close-up viewpoint: the person-to-camera direction turned about +Y by this,
CLOSEUP_DISTANCE_M = 2.8  # ... this far from the person,
CLOSEUP_HEIGHT_M = 0.6  # ... and this much higher


@dataclass(frozen=True, eq=False)
class RunLog:
    """Everything logged for one run. Arrays are numpy (torch tensors are accepted and converted).

    joint_names: (J,); parents: (J,) parent index, -1 for the root; bones are (parent, child).
    frames: (T,) int AMC frame numbers; times: (T,) seconds.
    estimate: (T, J, 3) metres, world; ground_truth: (T, J, 3) or None.
    camera: a `ptrack.observe.camera.Camera` (anything with K (3, 3), R (3, 3), t (3,), width, height).
    observed: (T, K, 2) pixels; confidence: (T, K), 0 = missing (not drawn);
    reprojected: (T, K, 2) pixels; keypoint_names: (K,).
    keypoint_joints: (K,) skeleton joint index of each keypoint, or None (then no 2D bones).
    hypotheses: (T, N, J, 3) or None; hypothesis_weights, hypothesis_costs: (T, N) or None;
    hypothesis_directions: (T, N, J, 3) metres or None.
    jumps: chain name -> (T,) kinematic-jump leaves kept per frame.
    motion_weights: (T, m) a motion model's PCA weights per frame, or None; motion_time: (T,) its normalised time;
    key_postures: key posture name -> index (0..T-1) of its frame (method pca).
    scalars: name -> (T,) per-frame values, NaN = no value that frame.
    masks: (T, H, W) bool silhouettes with H, W the camera's height, width, or None.
    joint_std: (T, J) metres, per-joint 3D standard deviation of the estimate, or None.
    solver_cost: (I+1,) objective after each iteration of a whole-sequence solver, or None.
    video: the input video's file (MP4), shown under the camera view's keypoints, or None; its frames are the
        camera's image (the same W x H pixels).
    video_frames: (T,) int, the video's frame number (from 0) of each logged frame; given with `video`.

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
    keypoint_joints: tuple[int, ...] | None = None
    hypotheses: np.ndarray | None = None
    hypothesis_weights: np.ndarray | None = None
    hypothesis_costs: np.ndarray | None = None
    hypothesis_directions: np.ndarray | None = None
    jumps: Mapping[str, np.ndarray] = field(default_factory=dict)
    motion_weights: np.ndarray | None = None
    motion_time: np.ndarray | None = None
    key_postures: Mapping[str, int] = field(default_factory=dict)
    scalars: Mapping[str, np.ndarray] = field(default_factory=dict)
    masks: np.ndarray | None = None
    joint_std: np.ndarray | None = None
    solver_cost: np.ndarray | None = None
    video: str | None = None
    video_frames: np.ndarray | None = None

    def __post_init__(self) -> None:
        for name in (
            "frames",
            "times",
            "estimate",
            "ground_truth",
            "observed",
            "confidence",
            "reprojected",
            "hypotheses",
            "hypothesis_weights",
            "hypothesis_costs",
            "hypothesis_directions",
            "masks",
            "joint_std",
            "solver_cost",
            "video_frames",
            "motion_weights",
            "motion_time",
        ):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, _as_numpy(value))
        object.__setattr__(self, "joint_names", tuple(self.joint_names))
        object.__setattr__(self, "parents", tuple(int(p) for p in self.parents))
        object.__setattr__(self, "keypoint_names", tuple(self.keypoint_names))
        if self.keypoint_joints is not None:
            object.__setattr__(self, "keypoint_joints", tuple(int(j) for j in self.keypoint_joints))
        object.__setattr__(self, "scalars", {str(k): _as_numpy(v) for k, v in self.scalars.items()})
        object.__setattr__(self, "jumps", {str(k): _as_numpy(v) for k, v in self.jumps.items()})
        object.__setattr__(self, "key_postures", {str(k): int(v) for k, v in self.key_postures.items()})
        if self.video is not None:
            object.__setattr__(self, "video", str(self.video))
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
                raise InputError(f"RunLog.parents[{child}] = {parent} is not -1 or another joint index")
        if self.ground_truth is not None:
            _check_shape("ground_truth", self.ground_truth, (T, J, 3))
        _check_shape("observed", self.observed, (T, K, 2))
        _check_shape("confidence", self.confidence, (T, K))
        _check_shape("reprojected", self.reprojected, (T, K, 2))
        if self.keypoint_joints is not None:
            if len(self.keypoint_joints) != K:
                raise InputError(f"RunLog.keypoint_joints has {len(self.keypoint_joints)} entries, expected K={K}")
            if any(not 0 <= j < J for j in self.keypoint_joints):
                raise InputError(f"RunLog.keypoint_joints {self.keypoint_joints} has an index outside 0..{J - 1}")
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
        if self.motion_weights is not None:
            _check_shape("motion_weights", self.motion_weights, (T, None))
        if self.motion_time is not None:
            _check_shape("motion_time", self.motion_time, (T,))
        for name, index in self.key_postures.items():
            if not 0 <= index < T:
                raise InputError(f"RunLog.key_postures[{name!r}] = {index} is not a frame index in 0..{T - 1}")
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
        if (self.video is None) != (self.video_frames is None):
            raise InputError("RunLog.video and RunLog.video_frames go together: give both or neither")
        if self.video_frames is not None:
            _check_shape("video_frames", self.video_frames, (T,))
            if not np.issubdtype(self.video_frames.dtype, np.integer) or (self.video_frames < 0).any():
                raise InputError(f"RunLog.video_frames must be frame numbers >= 0, got {self.video_frames.dtype}")

    @property
    def num_frames(self) -> int:
        """T, the number of logged frames."""
        return int(self.frames.shape[0])


def write_recording(path: str | Path, log: RunLog) -> None:
    """Write `log` to the rerun file `path` (.rrd), with the entity layout in the module docstring.

    Uses its own `rr.RecordingStream`; the global rerun recording is not touched.
    Raises FileNotFoundError if the parent folder of `path` does not exist; `log_video`'s InputError for
    `log.video` (before anything is written).
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"cannot write rerun recording {path}: folder {path.parent} does not exist")
    video = None if log.video is None else _video_asset(log.video, log.video_frames)
    rec = rr.RecordingStream(application_id="ptrack")
    rec.save(path)
    try:
        rec.send_blueprint(blueprint(log), make_active=True, make_default=True)
        T = log.num_frames
        index = [
            rr.TimeColumn("frame", sequence=log.frames.astype(np.int64)),
            rr.TimeColumn("time", duration=log.times.astype(np.float64)),
        ]
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
        bones = _bones(log.parents)
        if log.ground_truth is not None:
            _log_skeleton(rec, "world/ground_truth", log.ground_truth, bones, GROUND_TRUTH_COLOR, index)
        _log_skeleton(rec, "world/estimate", log.estimate, bones, ESTIMATE_COLOR, index)
        if log.joint_std is not None:
            radii = np.nan_to_num(log.joint_std.astype(np.float64), nan=0.0, posinf=0.0).reshape(-1)
            rec.log("world/estimate/std", rr.Points3D.from_fields(colors=[STD_COLOR]), static=True)
            rec.send_columns(
                "world/estimate/std",
                indexes=index,
                columns=rr.Points3D.columns(positions=log.estimate.reshape(-1, 3), radii=radii).partition(
                    [log.estimate.shape[1]] * T
                ),
            )
        if log.hypotheses is not None:
            _log_hypotheses(rec, log, bones, index)
        _log_camera(rec, log.camera, _center(log))
        _log_legend(rec, log)
        _log_keypoints(rec, log, index)
        if video is not None:
            _log_video_asset(rec, video[0], video[1], index, VIDEO_ENTITY)
        if log.masks is not None:
            _log_masks(rec, log.masks, index)
        for name, values in log.scalars.items():
            _log_scalar(rec, f"metrics/{name}", values, log)
        for name, values in log.jumps.items():
            _log_scalar(rec, f"jumps/{name}", values.astype(np.float64), log)
        _log_motion(rec, log)
        if log.solver_cost is not None:
            cost = log.solver_cost.astype(np.float64)
            rec.send_columns(
                "solver/cost",
                indexes=[rr.TimeColumn("iteration", sequence=np.arange(len(cost)))],
                columns=rr.Scalars.columns(scalars=cost),
            )
        rec.flush()
        logger.info("wrote rerun recording %s (%d frames)", path, T)
    finally:
        rec.disconnect()


def log_video(
    rec: rr.RecordingStream,
    video: str | Path,
    video_frames: np.ndarray,
    index: Sequence[rr.TimeColumn],
    entity: str = VIDEO_ENTITY,
) -> int:
    """Show the frames of the file `video` in the camera's image, on the run's timelines: the file itself as a
    static `rr.AssetVideo` at `entity` (its bytes go into the recording; the viewer decodes it), and for each of
    the T rows of `index` a `VideoFrameReference` to the video's frame `video_frames[t]` (counted from 0 in
    presentation order, as `ptrack.observe.video` numbers them).

    video_frames: (T,) int; index: the run's time columns (`frame`, `time`), T rows each. Only MP4 files can be
    shown (rerun's limit; its native viewer decodes AV1, and H.264 through an `ffmpeg` on the PATH).
    -> the number of frames in the video. InputError: no such file, a file rerun cannot read, a frame number
    outside the video, `video_frames` not (T,) integers.
    """
    asset, stamps, count = _video_asset(video, video_frames)
    _log_video_asset(rec, asset, stamps, index, entity)
    return count


def _video_asset(video: str | Path, video_frames: np.ndarray | None) -> tuple[rr.AssetVideo, np.ndarray, int]:
    """`log_video`'s checks: the asset of `video`, the (T,) int64 presentation time stamps (nanoseconds) of the
    frames `video_frames`, and the number of frames in the video (`log_video`: errors)."""
    path = Path(video)
    if not path.is_file():
        raise InputError(f"video not found: {path}")
    frames = np.asarray(video_frames)
    if frames.ndim != 1 or not np.issubdtype(frames.dtype, np.integer):
        raise InputError(f"video frame numbers must be (T,) integers, got {frames.dtype} {frames.shape}")
    asset = rr.AssetVideo(path=path)
    try:
        stamps = np.sort(np.asarray(asset.read_frame_timestamps_nanos(), dtype=np.int64))
    except Exception as e:  # rerun raises RuntimeError (or a PanicException) for what it cannot demux
        raise InputError(f"cannot show video {path} in the recording (rerun reads MP4 files only): {e}") from None
    if len(frames) and (frames.min() < 0 or frames.max() >= len(stamps)):
        raise InputError(
            f"video {path} has {len(stamps)} frames; frame numbers {int(frames.min())}..{int(frames.max())} asked"
        )
    return asset, stamps[frames], len(stamps)


def _log_video_asset(
    rec: rr.RecordingStream, asset: rr.AssetVideo, stamps: np.ndarray, index: Sequence[rr.TimeColumn], entity: str
) -> None:
    rec.log(entity, asset, static=True)
    rec.log(entity, rr.VideoFrameReference.from_fields(draw_order=VIDEO_DRAW_ORDER), static=True)
    rec.send_columns(entity, indexes=list(index), columns=rr.VideoFrameReference.columns_nanos(stamps))


def has_display() -> bool:
    """Whether a native window can open here: on Linux and other X11/Wayland systems, DISPLAY or
    WAYLAND_DISPLAY is set; macOS and Windows always have one."""
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def open_viewer(path: str | Path, wait: bool = True) -> int | None:
    """Launch the rerun viewer (`python -m rerun PATH`) on the saved recording `path`; its listener binds to
    127.0.0.1. Without a display (a server, a container) raise InputError saying how to view the run instead.

    wait: block until the viewer closes and return its exit status (`run_child`: a Ctrl-C or SIGTERM meanwhile
    closes it too); False: return at once (None).
    """
    path = check_recording(path)
    if not has_display():
        raise InputError(
            f"no display here (DISPLAY and WAYLAND_DISPLAY are unset) to open {path} in: serve it with "
            f"`ptrack replay {path} --web` (rerun's web viewer on 127.0.0.1), or copy it to a machine "
            f"with a display and run `rerun {path.name}` there"
        )
    argv = [sys.executable, "-m", "rerun", str(path), "--bind", "127.0.0.1", "--port", "auto"]
    if wait:
        return run_child(argv)
    subprocess.Popen(argv)
    return None


#: the first bytes of a rerun recording (.rrd): b"RRF" and the format's digit (b"RRF2" since rerun 0.23)
RRD_MAGIC = b"RRF"


def check_recording(path: str | Path) -> Path:
    """`path` if it is a rerun recording (a file starting with rerun's header `RRD_MAGIC`), else
    FileNotFoundError (no such file) or InputError (another kind of file), before any viewer starts."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"rerun recording {path} does not exist")
    with path.open("rb") as f:
        head = f.read(4)
    if head[:3] != RRD_MAGIC or not head[3:].isdigit():
        raise InputError(f"{path} is not a rerun recording (.rrd): give a run folder (it holds run.rrd) or its run.rrd")
    return path


def run_child(argv: Sequence[str], env: Mapping[str, str] | None = None, grace_s: float = 5.0) -> int:
    """Run `argv` (the rerun viewer or its web server) and return its exit status. It runs in its own process
    group (`python -m rerun` starts rerun's binary as a child of its own), so that when this process is
    interrupted or terminated while waiting (Ctrl-C, or SIGTERM turned into an exception by the command
    line), the whole group is sent SIGTERM, then SIGKILL after `grace_s`, before the exception goes on: no
    server is left holding its ports."""
    posix = os.name == "posix"
    proc = subprocess.Popen(list(argv), env=None if env is None else dict(env), start_new_session=posix)
    try:
        return proc.wait()
    except BaseException:
        end_group(proc, grace_s)
        raise


def end_group(proc: subprocess.Popen, grace_s: float) -> None:
    """Stop `proc` and, on POSIX, every process of its group (it leads one): SIGTERM, SIGKILL after grace_s."""
    if os.name != "posix":
        proc.kill()
        proc.wait()
        return
    try:
        os.killpg(proc.pid, signal.SIGTERM)
    except ProcessLookupError:
        return
    with contextlib.suppress(subprocess.TimeoutExpired):
        proc.wait(timeout=grace_s)
    for _ in range(int(grace_s / 0.05)):  # what the leader started (rerun's binary) ends after it
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.05)
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()


def _free_port(host: str) -> int:
    with socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET) as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def web_viewer_command(path: str | Path, bind: str = "127.0.0.1") -> tuple[list[str], str]:
    """The command serving recording `path` to rerun's web viewer, bound to `bind`, and the address to open:
    (argv, url). Both servers (the viewer's HTTP and rerun's gRPC) take free ports."""
    path = check_recording(path)
    web, grpc = _free_port(bind), _free_port(bind)
    host = f"[{bind}]" if ":" in bind else bind
    shown = "127.0.0.1" if bind in ("0.0.0.0", "::") else host
    url = f"http://{shown}:{web}?url=" + quote(f"rerun+http://{shown}:{grpc}/proxy", safe="")
    argv = [
        sys.executable,
        "-m",
        "rerun",
        str(path),
        "--serve-web",
        "--bind",
        bind,
        "--web-viewer-port",
        str(web),
        "--port",
        str(grpc),
    ]
    return argv, url


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


def _log_skeleton(
    rec: rr.RecordingStream,
    root: str,
    X: np.ndarray,
    bones: np.ndarray,
    color: tuple[int, int, int],
    index: list[rr.TimeColumn],
) -> None:
    """X: (T, J, 3) -> `{root}/joints` Points3D and `{root}/bones` LineStrips3D on every frame."""
    T, J, _ = X.shape
    joints, bone_strips = f"{root}/joints", f"{root}/bones"
    rec.log(joints, rr.Points3D.from_fields(colors=[color], radii=JOINT_RADIUS), static=True)
    rec.send_columns(joints, indexes=index, columns=rr.Points3D.columns(positions=X.reshape(-1, 3)).partition([J] * T))
    if len(bones):
        rec.log(bone_strips, rr.LineStrips3D.from_fields(colors=[color], radii=BONE_RADIUS), static=True)
        strips = rr.LineStrips3D.columns(strips=_strips(X, bones)).partition([len(bones)] * T)
        rec.send_columns(bone_strips, indexes=index, columns=strips)


def _log_hypotheses(rec: rr.RecordingStream, log: RunLog, bones: np.ndarray, index: list[rr.TimeColumn]) -> None:
    """(T, N, J, 3) hypotheses -> `world/hypotheses/h{n}/...`; see the module docstring."""
    H = log.hypotheses
    assert H is not None  # called only for logs that have hypotheses
    T, N = H.shape[:2]
    weights = log.hypothesis_weights
    weights = np.full((T, N), 1.0 / N) if weights is None else weights.astype(np.float64)
    best = np.max(np.where(np.isfinite(weights), weights, -np.inf), axis=1, keepdims=True)
    relative = np.where(best > 0, weights / np.where(best > 0, best, 1.0), 1.0)
    relative = np.clip(np.nan_to_num(relative, nan=0.0), 0.0, 1.0)  # (T, N)
    radii = HYPOTHESIS_RADIUS * (0.4 + 0.6 * relative)
    alpha = np.round(90 + 165 * relative).astype(np.uint8)  # the least likely still visible
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
            rec.log(f"{entity}/bones", rr.LineStrips3D.from_fields(show_labels=False), static=True)
            rec.send_columns(
                f"{entity}/bones",
                indexes=index,
                columns=[
                    *strips.partition([len(bones)] * T),
                    *rr.LineStrips3D.columns(labels=labels, radii=radii[:, n], colors=colors[:, n]),
                ],
            )
        if log.hypothesis_directions is not None:
            arrows = rr.Arrows3D.columns(
                origins=H[:, n].reshape(-1, 3), vectors=log.hypothesis_directions[:, n].reshape(-1, 3)
            )
            rec.log(
                f"{entity}/direction",
                rr.Arrows3D.from_fields(colors=[DIRECTION_COLOR], radii=DIRECTION_RADIUS),
                static=True,
            )
            rec.send_columns(f"{entity}/direction", indexes=index, columns=arrows.partition([H.shape[2]] * T))
        _log_scalar(rec, f"{entity}/weight", weights[:, n], log)
        if costs is not None:
            _log_scalar(rec, f"{entity}/cost", costs[:, n], log)


def _log_camera(rec: rr.RecordingStream, camera: Camera, target: np.ndarray) -> None:
    """Static camera pose (camera-to-world) and pinhole intrinsics at `world/camera`; the image
    plane is drawn at IMAGE_PLANE_FRACTION of the distance to `target` (3,), the person."""
    K = _as_numpy(camera.K).astype(np.float64)
    R = _as_numpy(camera.R).astype(np.float64)
    t = _as_numpy(camera.t).astype(np.float64)
    if K.shape != (3, 3) or R.shape != (3, 3) or t.shape != (3,):
        raise InputError(f"RunLog.camera has K {K.shape}, R {R.shape}, t {t.shape}; expected (3, 3), (3, 3), (3,)")
    center = _camera_center(camera)
    W, H = int(camera.width), int(camera.height)
    plane = IMAGE_PLANE_FRACTION * float(np.linalg.norm(target - center))
    rec.log("world/camera", rr.Transform3D(translation=center, mat3x3=R.T), static=True)
    rec.log(
        "world/camera",
        rr.Pinhole(
            image_from_camera=K,
            resolution=[W, H],
            camera_xyz=rr.ViewCoordinates.RDF,
            image_plane_distance=plane if plane > 0 else None,
        ),
        static=True,
    )
    rec.log(
        "world/camera/image/border",
        rr.LineStrips2D(
            [[(0, 0), (W, 0), (W, H), (0, H), (0, 0)]], colors=[BORDER_COLOR], radii=KEYPOINT_BONE_RADIUS, draw_order=5
        ),
        static=True,
    )


def _log_keypoints(rec: rr.RecordingStream, log: RunLog, index: list[rr.TimeColumn]) -> None:
    """Observed (confident only, labelled) and reprojected keypoints under `world/camera/image`,
    with 2D bones between keypoints and their keypoint parents where `log.keypoint_joints` is given."""
    names = np.asarray(log.keypoint_names, dtype=object)
    seen = (log.confidence > 0) & np.isfinite(log.observed).all(axis=-1)  # (T, K)
    finite = np.isfinite(log.reprojected).all(axis=-1)  # (T, K)
    image = "world/camera/image"
    for name, points, keep, color, radius, order in (
        ("observed", log.observed, seen, OBSERVED_COLOR, OBSERVED_RADIUS, 20),
        ("reprojected", log.reprojected, finite, REPROJECTED_COLOR, KEYPOINT_RADIUS, 40),
    ):
        rec.log(
            f"{image}/{name}",
            rr.Points2D.from_fields(colors=[color], radii=radius, show_labels=False, draw_order=order),
            static=True,
        )
        rec.send_columns(
            f"{image}/{name}",
            indexes=index,
            columns=rr.Points2D.columns(
                positions=points[keep].reshape(-1, 2),
                labels=names[np.nonzero(keep)[1]].tolist(),
            ).partition(keep.sum(axis=1)),
        )
    if log.keypoint_joints is None:
        return
    pairs = _keypoint_bones(log.parents, log.keypoint_joints)  # (B, 2)
    if not len(pairs):
        return
    for name, xy, ok, color, order in (
        ("observed_bones", log.observed, seen, OBSERVED_COLOR, 10),
        ("reprojected_bones", log.reprojected, finite, REPROJECTED_COLOR, 30),
    ):
        both = ok[:, pairs].all(axis=-1)  # (T, B)
        rec.log(
            f"{image}/{name}",
            rr.LineStrips2D.from_fields(colors=[color], radii=KEYPOINT_BONE_RADIUS, draw_order=order),
            static=True,
        )
        rec.send_columns(
            f"{image}/{name}",
            indexes=index,
            columns=rr.LineStrips2D.columns(strips=xy[:, pairs][both]).partition(both.sum(axis=1)),
        )


def _log_masks(rec: rr.RecordingStream, masks: np.ndarray, index: list[rr.TimeColumn]) -> None:
    """masks: (T, H, W) bool -> SegmentationImage (class 1 = silhouette) on every frame."""
    T, H, W = masks.shape
    entity = "world/camera/image/silhouette"
    rec.log(
        entity, rr.AnnotationContext([(0, "background", (0, 0, 0, 0)), (1, "silhouette", (255, 255, 255))]), static=True
    )
    fmt = rr.components.ImageFormat(width=W, height=H, channel_datatype="U8")
    rec.log(entity, rr.SegmentationImage.from_fields(format=fmt, opacity=0.4), static=True)
    rec.send_columns(
        entity, indexes=index, columns=rr.SegmentationImage.columns(buffer=(masks != 0).astype(np.uint8).reshape(T, -1))
    )


def _keypoint_bones(parents: Sequence[int], keypoint_joints: Sequence[int]) -> np.ndarray:
    """(B, 2) (parent, child) keypoint index pairs: each keypoint joined to the nearest skeleton
    ancestor of its joint that is a keypoint too."""
    keypoint_of = {j: k for k, j in enumerate(keypoint_joints)}
    pairs = []
    for k, j in enumerate(keypoint_joints):
        p = parents[j]
        for _ in range(len(parents)):  # bounded: `parents` is not checked for cycles
            if p < 0 or p in keypoint_of:
                break
            p = parents[p]
        if p >= 0 and p in keypoint_of and keypoint_of[p] != k:
            pairs.append((keypoint_of[p], k))
    return np.asarray(pairs, dtype=np.int64).reshape(-1, 2)


def _finite_joints(log: RunLog) -> np.ndarray:
    """(M, 3) every finite estimated joint position of every frame, metres."""
    X = log.estimate.reshape(-1, 3).astype(np.float64)
    return X[np.isfinite(X).all(axis=-1)]


def _center(log: RunLog) -> np.ndarray:
    """(3,) the mean finite estimated joint, metres (the origin if there is none)."""
    X = _finite_joints(log)
    return X.mean(axis=0) if len(X) else np.zeros(3)


def _turn_y(degrees: float) -> np.ndarray:
    """(3, 3) rotation about the world's +Y (up) axis."""
    c, s = np.cos(np.deg2rad(degrees)), np.sin(np.deg2rad(degrees))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _camera_center(camera: Camera) -> np.ndarray:
    """(3,) the camera centre in the world, metres."""
    R = _as_numpy(camera.R).astype(np.float64)
    return -R.T @ _as_numpy(camera.t).astype(np.float64)


def _toward_camera(log: RunLog) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The person's centre (3,), the camera centre (3,), and the horizontal unit vector (3,) from the
    person towards the camera, metres."""
    person, camera = _center(log), _camera_center(log.camera)
    v = camera - person
    v[1] = 0.0
    return person, camera, v / max(float(np.linalg.norm(v)), 1e-9)


def _log_legend(rec: rr.RecordingStream, log: RunLog) -> None:
    """Static `world/legend` (3D, above the motion) and `world/camera/image/legend` (2D, top edge)."""
    kinds = [("estimate", ESTIMATE_COLOR)]
    if log.ground_truth is not None:
        kinds.append(("ground truth", GROUND_TRUTH_COLOR))
    if log.hypotheses is not None:
        kinds.append(("hypotheses", HYPOTHESIS_COLOR))
    X = _finite_joints(log)
    top = X[:, 1].max() if len(X) else 0.0
    base = _center(log) * np.array([1.0, 0.0, 1.0])  # a column above the motion, read from any side
    heights = top + LEGEND_SPACING * (1.5 + np.arange(len(kinds))[::-1])
    rec.log(
        "world/legend",
        rr.Points3D(
            base + heights[:, None] * np.array([0.0, 1.0, 0.0]),
            colors=[c for _, c in kinds],
            radii=LEGEND_RADIUS,
            labels=[name for name, _ in kinds],
            show_labels=True,
        ),
        static=True,
    )
    W, H = float(log.camera.width), float(log.camera.height)
    y = max(H / 16, 4 * OBSERVED_RADIUS)  # labels are drawn centred under their points
    rec.log(
        "world/camera/image/legend",
        rr.Points2D(
            [(0.15 * W, y), (0.45 * W, y)],
            colors=[OBSERVED_COLOR, REPROJECTED_COLOR],
            radii=[OBSERVED_RADIUS, KEYPOINT_RADIUS],
            labels=["observed", "reprojected estimate"],
            show_labels=True,
            draw_order=50,
        ),
        static=True,
    )


def _has_values(values: np.ndarray) -> bool:
    """Whether `_log_scalar` logs anything for `values` (any finite value)."""
    return bool(np.isfinite(values.astype(np.float64)).any())


def _metric_plot(name: str) -> str:
    """The plot title a per-frame metric `name` is drawn in (grouped by unit)."""
    if name.startswith("accel"):
        return "accel. error (mm/frame²)"
    if name.startswith("jitter"):
        return "jitter (mm/frame²)"
    if name.startswith("foot_skating"):
        return "foot skating (mm/frame)"
    if name.startswith("ambiguous") or name in ("person_missing", "left_right_exchanged"):
        return "ambiguous limbs, labels exchanged, person missing (0/1, share)"
    if name.endswith("_mm"):
        return "joint position error (mm)"
    if name.endswith("_px"):
        return "reprojection error (px)"
    if name.startswith("flip"):
        return "flip error rate"
    if name == "cost" or name.startswith("cost_"):
        return "cost and its terms"
    if name.endswith("_m"):
        return "uncertainty (m)"
    return "other metrics"


def plot_groups(log: RunLog) -> list[tuple[str, list[str]]]:
    """The time-series plots of `blueprint(log)`: (title, scalar entity paths), every scalar entity
    `write_recording` logs in exactly one, none empty."""
    groups: dict[str, list[str]] = {}
    for name, values in log.scalars.items():
        if _has_values(values):
            groups.setdefault(_metric_plot(name), []).append(f"metrics/{name}")
    if log.hypotheses is not None:
        N = log.hypotheses.shape[1]
        weights = log.hypothesis_weights
        if weights is None or any(_has_values(weights[:, n]) for n in range(N)):
            groups["hypothesis weights"] = [
                f"world/hypotheses/h{n}/weight" for n in range(N) if weights is None or _has_values(weights[:, n])
            ]
        costs = log.hypothesis_costs
        if costs is not None and any(_has_values(costs[:, n]) for n in range(N)):
            groups["hypothesis costs"] = [f"world/hypotheses/h{n}/cost" for n in range(N) if _has_values(costs[:, n])]
    if log.jumps:
        groups["kinematic jumps kept per chain"] = [f"jumps/{name}" for name in log.jumps]
    if log.motion_time is not None and _has_values(log.motion_time):
        groups["motion model: normalised time"] = ["pca/time"]
    if log.motion_weights is not None:
        alphas = [
            f"pca/weights/alpha{i}" for i in range(log.motion_weights.shape[1]) if _has_values(log.motion_weights[:, i])
        ]
        if alphas:
            groups["motion model: PCA weights"] = alphas
    if log.solver_cost is not None:
        groups["solver cost (timeline: iteration)"] = ["solver/cost"]
    return list(groups.items())


def _eye(log: RunLog) -> rrb.EyeControls3D:
    """A 3D viewpoint beside and above the line from the person to the camera, looking at the centre
    of the sphere that holds the camera and the motion's bounding box over the whole clip, from far
    enough that the sphere fits in a cone of half-angle EYE_HALF_FOV_DEG: the camera's frustum and
    the person are in view at every frame."""
    person, camera, v = _toward_camera(log)
    X = _finite_joints(log)
    lo, hi = (X.min(axis=0), X.max(axis=0)) if len(X) else (person, person)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    points = np.vstack([corners, camera])
    target = (points.min(axis=0) + points.max(axis=0)) / 2
    radius = max(float(np.linalg.norm(points - target, axis=1).max()), 1.0)
    up = np.deg2rad(EYE_ELEVATION_DEG)
    direction = np.cos(up) * (_turn_y(EYE_AZIMUTH_DEG) @ v) + np.sin(up) * np.array([0.0, 1.0, 0.0])
    position = target + radius / np.sin(np.deg2rad(EYE_HALF_FOV_DEG)) * direction
    return rrb.EyeControls3D(position=position, look_target=target, eye_up=[0.0, 1.0, 0.0])


def _closeup_eye(log: RunLog) -> rrb.EyeControls3D:
    """A 3D viewpoint near the person (the camera's side turned by CLOSEUP_AZIMUTH_DEG), following
    the estimate's joints as they move."""
    person, _, v = _toward_camera(log)
    position = person + CLOSEUP_DISTANCE_M * (_turn_y(CLOSEUP_AZIMUTH_DEG) @ v) + np.array([0.0, CLOSEUP_HEIGHT_M, 0.0])
    return rrb.EyeControls3D(
        position=position, look_target=person, eye_up=[0.0, 1.0, 0.0], tracking_entity="/world/estimate/joints"
    )


def blueprint(log: RunLog) -> rrb.Blueprint:
    """The viewer layout for `log`'s recording: the 3D scene, a 3D close-up and the camera view side
    by side, a grid of time-series plots (`plot_groups`) under them, the time panel on `time`."""
    W, H = float(log.camera.width), float(log.camera.height)
    margin = 0.03 * max(W, H)
    scene = rrb.Spatial3DView(
        name="3D: scene and camera", origin="/world", contents="$origin/**", eye_controls=_eye(log)
    )
    closeup = rrb.Spatial3DView(
        name="3D: close-up (follows the estimate)",
        origin="/world",
        contents=["+ $origin/**", "- /world/camera/**", "- /world/legend"],
        eye_controls=_closeup_eye(log),
    )
    image = rrb.Spatial2DView(
        name="camera: video, observed and reprojected keypoints"
        if log.video is not None
        else "camera: observed and reprojected keypoints",
        origin="/world/camera",
        contents="$origin/**",
        visual_bounds=rrb.VisualBounds2D(x_range=[-margin, W + margin], y_range=[-margin, H + margin]),
    )
    plots = [
        rrb.TimeSeriesView(name=title, origin="/", contents=[f"+ /{e}" for e in entities])
        for title, entities in plot_groups(log)
    ]
    top = rrb.Horizontal(scene, closeup, image, column_shares=[4, 3, 3])
    layout: rrb.Container
    if plots:
        columns = len(plots) if len(plots) <= 5 else -(-len(plots) // 2)
        layout = rrb.Vertical(top, rrb.Grid(*plots, grid_columns=columns), row_shares=[3, 2])
    else:
        layout = top
    return rrb.Blueprint(
        layout,
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(timeline="time", state="collapsed"),
        auto_views=False,
    )


def _log_motion(rec: rr.RecordingStream, log: RunLog) -> None:
    """A motion model's normalised time, PCA weights and key postures (`pca/...`), where the log has them."""
    if log.motion_time is not None:
        _log_scalar(rec, "pca/time", log.motion_time, log)
    if log.motion_weights is not None:
        for i in range(log.motion_weights.shape[1]):
            _log_scalar(rec, f"pca/weights/alpha{i}", log.motion_weights[:, i], log)
    for name, index in log.key_postures.items():
        rec.set_time("frame", sequence=int(log.frames[index]))
        rec.set_time("time", duration=float(log.times[index]))
        rec.log("pca/key_postures", rr.TextLog(f"key posture {name}"))
    if log.key_postures:
        rec.reset_time()


def _log_scalar(rec: rr.RecordingStream, entity: str, values: np.ndarray, log: RunLog) -> None:
    """values: (T,) -> Scalars at `entity` on the frames where the value is finite."""
    values = values.astype(np.float64)
    keep = np.isfinite(values)
    if not keep.any():
        logger.debug("no finite values for %s: nothing logged", entity)
        return
    rec.send_columns(
        entity,
        indexes=[
            rr.TimeColumn("frame", sequence=log.frames[keep].astype(np.int64)),
            rr.TimeColumn("time", duration=log.times[keep].astype(np.float64)),
        ],
        columns=rr.Scalars.columns(scalars=values[keep]),
    )
