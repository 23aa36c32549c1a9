"""Real footage in: a detector's keypoint file (or a video to detect), a camera, a person's height -> the
`Problem` an estimator solves, and the frames to report the result in.

The steps, each owned by its module: read the keypoint file (`observe.keypoint_files`), choose the person
(`observe.people`), read the camera (`observe.camera_files`; without one, intrinsics from the image size)
and remove its lens distortion from the keypoints, scale the template skeleton to the person's height (or keep
its bone lengths: `subject.lengths: asf`) and place the detector's landmarks on it (`body.subject`).

Frames of reference. ptrack's estimators work in a Y-up world (the CMU skeleton stands along +Y). The
model frame is the calibration's world rotated so that its up axis is +Y:

- a camera file with extrinsics and a known up axis (Pose2Sim: +Z; or `camera.up`): that axis; a
  coordinate axis is brought to +Y by a cyclic permutation of the axes (Z up: model (X, Y, Z) = world
  (Y, Z, X), as OpenSim's TRC files write the Pose2Sim lab), any other direction by the smallest rotation;
- extrinsics, up unknown: the camera's image-up direction (-y of the camera) as the world's up, i.e. the
  camera is taken to be level;
- no extrinsics: the camera frame turned Y-up: origin at the camera, X right, Y up, Z towards the viewer
  (the camera looks along -Z).

`FootageFrame.world_from_model` (3, 3) takes model coordinates back to the calibration's world;
`result.npz`'s `keypoints` are written in that world (without extrinsics: in the model frame, Y up).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path

import numpy as np
import torch

from ptrack.body.keypoint_sets import get_keypoint_set
from ptrack.body.keypoints import KeypointSet, landmark_keypoints
from ptrack.body.skeleton import Skeleton
from ptrack.body.subject import (
    add_landmark_joints,
    check_height,
    landmark_joints,
    scale_to_height,
    standing_height,
)
from ptrack.errors import InputError
from ptrack.observe.camera import Camera
from ptrack.observe.camera_files import (
    CameraFile,
    default_intrinsics,
    read_camera,
    read_cameras,
    undistort_points,
    world_up,
)
from ptrack.observe.keypoint_files import read_keypoints
from ptrack.observe.observations import Observations
from ptrack.observe.people import PersonTrack, mirror_switches, select_person

log = logging.getLogger(__name__)

#: the height assumed when subject.height_m is not given, metres (an adult's, both sexes pooled)
DEFAULT_HEIGHT_M = 1.70


@dataclasses.dataclass(frozen=True)
class FootageFrame:
    """What a real-footage run reports besides the estimate.

    frames: (T,) the input's frame numbers; keypoint_names: (K,) the input format's names of the keypoints
    the model places; world_from_model: (3, 3) rotation, model frame -> the calibration's world;
    camera: how the camera was obtained ("file NAME" or "focal from the image size ..."); height_m: the
    subject height used and whether it was given; person: the chosen track and how many there were;
    missing_frames: (M,) input frame numbers without the person; dropped: keypoints the model does not place.
    """

    frames: np.ndarray
    keypoint_names: tuple[str, ...]
    world_from_model: np.ndarray
    camera: str
    height_m: float
    height_given: bool
    track_id: int
    n_tracks: int
    missing_frames: np.ndarray
    dropped: tuple[str, ...]
    keypoint_set: str
    video: str | None = None
    landmarks: tuple[str, ...] = ()  # (K,) the landmark of each keypoint
    segments: dict | None = None  # {segment: {length_m, frames, std_m}} measured in the 2D (subject.lengths: observed)
    floor_m: float | None = None  # the floor's height along the model's +Y, when the calibration gives it
    lengths: str = "template"  # subject.lengths (asf: the skeleton file's bone lengths)
    fps: float = 30.0  # the input's frames per second (observations.fps, the keypoint file's or the video's)
    extrinsics: bool = False  # the camera file placed the camera in its world (else the world is the camera's frame)
    # where up came from: "calibration" (the camera file's world), "person" (the floor under the feet,
    # `ptrack.estimators.ground`), "image" (the camera's image-up, taken as level)
    up: str = "image"
    ground: dict | None = None  # up "person": the floor fit's tilt_deg, contacts, spread_m
    tracked_every: int = 1  # frames tracked: every n-th (`observations.track_fps`), the ones between filled
    # input frame numbers where the detector exchanged every left/right label from the frame before
    # (`ptrack.observe.people.mirror_switches`); with `costs.swap_cost: null` they turn the exchanged reading on
    mirror_switches: tuple[int, ...] = ()
    swap_cost: float | None = None  # the price of reading a frame's labels exchanged that the run used (0: off)
    filter_hz: float | None = None  # the reported trajectory low-passed at this frequency (`observations.filter_hz`)

    def summary(self) -> dict:
        """JSON-ready record for metrics.json."""
        return {
            "segments_measured": self.segments,
            "keypoint_set": self.keypoint_set,
            "camera": self.camera,
            "floor_m": self.floor_m,
            "fps": self.fps,
            "tracked_every": self.tracked_every,
            "mirror_switch_frames": list(self.mirror_switches),
            "swap_cost": self.swap_cost,
            "filter_hz": self.filter_hz,
            "up": self.up,
            "ground": self.ground,
            "height_m": self.height_m,
            "height_given": self.height_given,
            "person_track": self.track_id,
            "tracks": self.n_tracks,
            "frames_without_person": [int(f) for f in self.missing_frames],
            "keypoints_not_placed": list(self.dropped),
        }


def axis_to_y(up: np.ndarray) -> np.ndarray:
    """(3, 3) rotation A with A @ up = +Y: a cyclic permutation of the axes when `up` is +-X, +-Y or +-Z
    (a coordinate axis stays a coordinate axis), else the smallest rotation. up: (3,) unit vector."""
    up = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    k = int(np.argmax(np.abs(up)))
    if abs(abs(up[k]) - 1.0) < 1e-12:
        perm = {0: [[0, 0, 1], [1, 0, 0], [0, 1, 0]], 1: np.eye(3), 2: [[0, 1, 0], [0, 0, 1], [1, 0, 0]]}[k]
        A = np.asarray(perm, dtype=np.float64)
        return A if up[k] > 0 else np.diag([1.0, -1.0, -1.0]) @ A  # turned half about X: -axis -> +Y
    y = np.array([0.0, 1.0, 0.0])
    v, c = np.cross(up, y), float(up @ y)
    if np.linalg.norm(v) < 1e-12:  # up = -Y
        return np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


def _camera(cfg, track_image_size: tuple[int, int] | None, video_size: tuple[int, int] | None):
    """-> (CameraFile or None, K (3,3), R (3,3) world->camera, t (3,), width, height, description)."""
    c = cfg.camera
    if c.file:
        if c.name is None:  # the file's only camera, read once
            cameras = read_cameras(c.file)
            if len(cameras) > 1:
                raise InputError(
                    f"{c.file} holds {len(cameras)} cameras ({', '.join(cameras)}): set camera.name to one"
                )
            cam = next(iter(cameras.values()))
        else:
            cam = read_camera(c.file, c.name)
        width = cam.width or (video_size or track_image_size or (None, None))[0]
        height = cam.height or (video_size or track_image_size or (None, None))[1]
        if width is None or height is None:
            raise InputError(f"camera file {c.file} does not give the image size; set camera.width and camera.height")
        R = cam.R if cam.R is not None else np.eye(3)
        t = cam.t if cam.t is not None else np.zeros(3)
        return cam, cam.K, R, t, int(width), int(height), f"file {c.file} camera {cam.name}"
    size = video_size or track_image_size
    if size is None:
        if c.width is None or c.height is None:
            raise InputError(
                "no camera.file and the keypoint file does not give the image size: set camera.width and "
                "camera.height (the video's size in pixels) or camera.file"
            )
        size = (c.width, c.height)
    width, height = int(size[0]), int(size[1])
    K = default_intrinsics(width, height, c.fov_deg)
    fov = c.fov_deg if c.fov_deg is not None else math.degrees(2 * math.atan(0.5))
    what = f"no camera file: focal {K[0, 0]:.1f} px from the image size {width} x {height}"
    what += f" (diagonal field of view {fov:.1f} deg)"
    return None, K, np.eye(3), np.zeros(3), width, height, what


def model_frame(cam: CameraFile | None, R: np.ndarray, up_key: str | None) -> np.ndarray:
    """(3, 3) A: model coordinates = A @ world coordinates (see the module docstring)."""
    if cam is None or not cam.has_extrinsics:
        return np.diag([1.0, -1.0, -1.0])  # the world is the camera frame (R = I), turned Y-up
    up = world_up(cam, up_key)
    if up is None:
        up = R.T @ np.array([0.0, -1.0, 0.0])  # the camera's image-up, taken as level
        log.info("camera %s: the world's up axis is not known; the camera's image-up is taken as up", cam.name)
    return axis_to_y(up)


def person_observations(
    track: PersonTrack,
    placed: np.ndarray,
    names: tuple[str, ...],
    cam: CameraFile | None,
    camera: Camera,
    fps: float,
    min_score: float,
) -> Observations:
    """The chosen person's placed keypoints (K of them, `placed` (K,) indices into the file's, named `names`) as
    `Observations`: lens distortion removed, scores clipped to [0, 1], those under `min_score` missing."""
    xy = track.points[:, placed].astype(np.float64)
    conf = np.clip(np.nan_to_num(track.scores[:, placed], nan=0.0), 0.0, 1.0)
    conf[conf < min_score] = 0.0
    conf[~np.isfinite(xy).all(-1)] = 0.0
    if cam is not None and np.any(cam.dist != 0):
        seen = conf > 0
        xy[seen] = undistort_points(xy[seen], cam)
        conf[~np.isfinite(xy).all(-1)] = 0.0
    xy[conf == 0] = 0.0
    times = (track.frames - track.frames[0]) / fps
    return Observations(
        keypoints=torch.as_tensor(xy),
        confidence=torch.as_tensor(conf),
        times=torch.as_tensor(times, dtype=torch.float64),
        camera=camera,
        keypoint_names=names,
    )


def prepare_footage(
    cfg,
    template: Skeleton,
    keypoints_path: str | Path,
    video_size: tuple[int, int] | None = None,
    video_fps: float | None = None,
    video: str | None = None,
):
    """-> (skeleton scaled to the subject, KeypointSet, Observations (float64, CPU), FootageFrame).

    video_size (width, height) and video_fps: of the video the keypoints come from, when known."""
    o = cfg.observations
    det = read_keypoints(keypoints_path, o.format, o.keypoint_set, o.fps)
    fps = o.fps or det.fps or video_fps
    if fps is None:
        raise InputError(f"{keypoints_path} does not say its frame rate: set observations.fps")
    track = select_person(
        det, None if o.person is None else (o.person if isinstance(o.person, int) else tuple(o.person))
    )
    d = cfg.data
    if d.start >= len(track.frames):
        raise InputError(
            f"config key 'data.start' is {d.start} but {keypoints_path} has only {len(track.frames)} frames"
        )
    cut = slice(d.start, d.stop)  # data.start/stop index the input's frames (data.stride is for AMC clips)
    track = dataclasses.replace(
        track, frames=track.frames[cut], points=track.points[cut], scores=track.scores[cut], present=track.present[cut]
    )
    definition = get_keypoint_set(track.keypoint_set)
    switches = mirror_switches(track.points, track.scores >= o.min_score, definition.mirror_index())
    given, known = cfg.subject.height_m is not None, cfg.subject.lengths == "asf"  # asf: its bone lengths as they are
    height = check_height(cfg.subject.height_m) if given else standing_height(template) if known else DEFAULT_HEIGHT_M
    if not given and not known:
        log.warning("subject.height_m is not given: %.2f m is assumed (the result's scale follows it)", height)
    skeleton = add_landmark_joints(template if known else scale_to_height(template, height), height)
    joints = landmark_joints(skeleton, definition.landmarks)
    placed = np.array([k for k, j in enumerate(joints) if j is not None], dtype=np.int64)
    dropped = tuple(definition.names[k] for k, j in enumerate(joints) if j is None)
    if len(placed) < 6:
        raise InputError(
            f"keypoint set {definition.name} has {len(placed)} keypoints ptrack can place; at least 6 are needed"
        )
    if dropped:
        log.info("keypoints %s have no place on the skeleton and are not used", ", ".join(dropped))
    cam, K, R, t, width, height_px, what = _camera(cfg, det.image_size, video_size)
    A = model_frame(cam, R, cfg.camera.up)
    floor_known = cam is not None and cam.has_extrinsics and world_up(cam, cfg.camera.up) is not None
    floor = cfg.camera.floor_m if floor_known else None
    if floor is not None and not math.isfinite(floor):
        raise InputError(f"config key 'camera.floor_m' must be a finite number of metres, got {floor!r}")
    camera = Camera(K=torch.tensor(K), R=torch.tensor(R @ A.T), t=torch.tensor(t), width=width, height=height_px)
    names = tuple(definition.names[k] for k in placed)
    landmarks = tuple(definition.landmarks[k] for k in placed)
    obs = person_observations(track, placed, names, cam, camera, float(fps), o.min_score)
    kps = landmark_keypoints(skeleton, names, landmarks, [str(joints[k]) for k in placed])
    frame = FootageFrame(
        frames=track.frames,
        keypoint_names=names,
        landmarks=landmarks,
        world_from_model=A.T if cam is not None and cam.has_extrinsics else np.eye(3),
        camera=what,
        height_m=height,
        height_given=given,
        track_id=track.track_id,
        n_tracks=track.n_tracks,
        missing_frames=track.frames[~track.present],
        dropped=dropped,
        keypoint_set=definition.name,
        video=video or det.video,
        floor_m=floor,
        lengths=cfg.subject.lengths,
        fps=float(fps),
        extrinsics=cam is not None and cam.has_extrinsics,
        up="calibration" if floor_known else "image",
        mirror_switches=tuple(int(f) for f in track.frames[switches]),
    )
    return skeleton, kps, obs, frame


def keypoints_in_world(frame: FootageFrame, kps: KeypointSet, joints: torch.Tensor) -> np.ndarray:
    """joints (T, J, 3) model frame -> (T, K, 3) the placed keypoints in the calibration's world."""
    pts = joints.detach().cpu().double().index_select(-2, kps.index()).numpy()
    return pts @ frame.world_from_model.T
