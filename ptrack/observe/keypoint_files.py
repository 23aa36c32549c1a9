"""2D detector keypoint files: OpenPose JSON folders, COCO-style results, MMPose predictions, MediaPipe
landmarks and plain npz arrays, read into one `Detections` record (every person of every frame).

`read_keypoints(path, format=None, keypoint_set=None, fps=None)` reads any of these containers:

- ``openpose``: a folder of per-frame JSON files as OpenPose's ``--write_json`` writes them
  (``name_000000000012_keypoints.json``, or Pose2Sim's ``cam01.0012.json``; any ``*.json``), each
  ``{"people": [{"person_id": -1 | [-1], "pose_keypoints_2d": [x0, y0, c0, x1, y1, c1, ...]}, ...]}``
  (OpenPose doc/02_output.md, "JSON Output Format"; the key ``pose_keypoints`` of OpenPose 1.0 is read
  too). The frame number is the last run of digits in the file name; a ``person_id`` other than -1 is a
  track id. One such JSON file (not a folder) is read as a single frame.
- ``coco``: a COCO keypoint results file (cocodataset.org/#format-results), as written by AlphaPose
  (docs/output.md), Detectron and MMPose's COCO evaluation: a JSON list of
  ``{"image_id": 12 | "frame_000012.jpg", "category_id": 1, "keypoints": [x, y, s] * K, "score": s,
  "idx": track}``: one entry per person; entries of one image are one frame; the frame number is the
  ``image_id`` (or the last run of digits of its file name); AlphaPose's ``idx`` (or ``track_id``), when an
  integer, is a track id; entries whose ``category_id`` is not 1 (person) are skipped.
- ``mmpose``: MMPose's predictions (``demo/topdown_demo_with_mmdet.py --save-predictions``, the
  inferencer's ``pred_out_dir``): ``{"meta_info": {...}, "instance_info": [{"frame_id": n,
  "instances": [{"keypoints": [[x, y], ...], "keypoint_scores": [s, ...], "track_id": t?}, ...]}, ...]}``,
  the bare list of such frames, or one image's list of instances (frame 0). ``meta_info.dataset_name``
  ("coco", "coco_wholebody", "halpe26", "h36m") names the keypoint set when it is not given. On images,
  ``MMPoseInferencer(..., pred_out_dir=DIR)`` writes one ``<image name>.json`` per image, each that image's
  list of instances (``[]`` when nobody is found; mmpose/apis/inferencers/base_mmpose_inferencer.py,
  ``postprocess``; the instances as mmpose/structures/utils.py ``split_instances`` makes them, ``bbox`` as
  ``[[x1, y1, x2, y2]]``): such a folder is read with the frame number from each file name, as OpenPose's.
- ``mediapipe``: the landmarks ``ptrack detect`` writes (`write_mediapipe_landmarks`, layout below).
- ``npz``: arrays as lifting research code keeps them: ``keypoints`` (T, K, 2 | 3) or (T, P, K, 2 | 3)
  (or the archive's only array), with the score as the last channel or in ``scores`` / ``confidence``
  (T, K) | (T, P, K) (default 1 where the point is finite), optional ``frames`` (T,) int, ``fps`` (),
  ``keypoint_names`` (K,) str (which name the set when they match one). A ptrack observation npz is read
  this way too.

The format is inferred from the content when not given: a folder -> openpose when its files are objects,
mmpose when they are lists (MMPose's per-image predictions); an npz with
``world_landmarks`` -> mediapipe, another npz -> npz; a JSON list of entries with ``image_id`` -> coco;
``instance_info`` or frames with ``frame_id`` / ``instances`` -> mmpose; an object with ``people`` ->
openpose. The keypoint set is inferred from the count a person (`ptrack.body.keypoint_sets`, which tells
the 17- and 25-point sets apart by content or asks for ``keypoint_set=``).

Scores are kept as the file gives them (the observation weight; AlphaPose's can exceed 1). A keypoint is
missing when its score is 0, negative or not finite, or its triplet is 0, 0, 0: it is stored as
[NaN, NaN, 0]. A finite score > 0 with a non-finite x or y is an error. People whose keypoints are all
missing are dropped.

MediaPipe landmarks file (`MEDIAPIPE_KEYS`), a plain npz (no pickles):

    frames           int   (T,)        input video frame numbers (0-based)
    landmarks        float (T, 33, 3)  x px, y px (MediaPipe's normalised image coordinates times the
                                       width and height), visibility in [0, 1]; NaN, NaN, 0 where no person
    world_landmarks  float (T, 33, 3)  MediaPipe's pose_world_landmarks unchanged: metres, origin midway
                                       between the hips; NaN where no person
    fps              float ()          the video's frame rate (NaN if the container gives none)
    width, height    int   ()          image size, pixels
    video            str   ()          the video file the landmarks come from ("" if unknown)
    keypoint_set     str   ()          "MEDIAPIPE_33" (optional when read)

The landmarks are stored as float32 (a thousandth of a pixel at 4K; MediaPipe's own are float32).

Every problem is an `InputError` of one line naming the file and the first bad frame.
"""

from __future__ import annotations

import json
import logging
import os
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ptrack.body.keypoint_sets import (
    KEYPOINT_SETS,
    MEDIAPIPE_33,
    KeypointDefinition,
    get_keypoint_set,
    infer_keypoint_set,
)
from ptrack.errors import InputError
from ptrack.observe.observations import read_npz

log = logging.getLogger(__name__)

#: the container names `read_keypoints` accepts for `format`
FORMATS: tuple[str, ...] = ("openpose", "coco", "mmpose", "mediapipe", "npz")
_FORMAT_ALIASES = {"alphapose": "coco", "blazepose": "mediapipe"}

#: the keys of a MediaPipe landmarks file (layout in the module docstring)
MEDIAPIPE_KEYS = ("frames", "landmarks", "world_landmarks", "fps", "width", "height", "video", "keypoint_set")

#: MMPose `meta_info.dataset_name` -> keypoint set
_MMPOSE_DATASETS = {
    "coco": "COCO_17",
    "coco_wholebody": "COCO_WHOLEBODY",
    "halpe26": "HALPE_26",
    "halpe": "HALPE_26",
    "h36m": "H36M_17",
}


@dataclass(frozen=True, eq=False)
class Detections:
    """Every detected person of every frame of a keypoint file.

    keypoint_set: registry name of the keypoint set (`ptrack.body.keypoint_sets.get_keypoint_set`).
    frames: (T,) int input frame numbers, strictly increasing (not necessarily contiguous: a COCO results
        file lists only images with a detection).
    people: (T, P, K, 3) float [x px, y px, score]; a missing keypoint is [NaN, NaN, 0]; slots beyond a
        frame's people are all NaN (P is the most people in a frame).
    track_ids: (T, P) int, the file's track id of each person, -1 where unknown or no person.
    fps: frames per second (given, or from the file), None when unknown.
    source: the file or folder read.
    image_size: (width, height) pixels when the file says, else None.
    video: the video the detections come from when the file says, else None.
    """

    keypoint_set: str
    frames: np.ndarray
    people: np.ndarray
    track_ids: np.ndarray
    fps: float | None
    source: str
    image_size: tuple[int, int] | None = None
    video: str | None = None

    @property
    def present(self) -> np.ndarray:
        """(T, P) bool: the slot holds a person."""
        return np.isfinite(self.people[..., 2]).any(-1)

    @property
    def definition(self) -> KeypointDefinition:
        return get_keypoint_set(self.keypoint_set)


@dataclass(frozen=True, eq=False)
class MediaPipeLandmarks:
    """MediaPipe Pose's landmarks for a run of video frames (`ptrack.observe.detector.detect`'s result, the
    content of a MediaPipe landmarks file; meaning and units in the module docstring).

    frames: (T,) int64; landmarks: (T, 33, 3) x px, y px, visibility; world_landmarks: (T, 33, 3) metres;
    fps: frames per second (NaN when unknown); width, height: pixels (0 when unknown); video: the video's
    path as given ("" when unknown). The keypoints are `ptrack.body.keypoint_sets.MEDIAPIPE_33`'s."""

    frames: np.ndarray
    landmarks: np.ndarray
    world_landmarks: np.ndarray
    fps: float
    width: int
    height: int
    video: str

    @property
    def found(self) -> np.ndarray:
        """(T,) bool: frames where MediaPipe found a person."""
        return np.isfinite(self.landmarks[..., :2]).all((-1, -2))


# --- one frame's people as the containers give them --------------------------------------------------


@dataclass
class _Frame:
    number: int
    where: str  # for messages: "FILE" or "FILE: frame N"
    people: list[np.ndarray]  # each (M, 3)
    tracks: list[int]


def _frame_number(name: str, where: str) -> int:
    """The last run of digits in a file name's stem (`cam01.0012` -> 12, `x_000000000012_keypoints` -> 12)."""
    stem = Path(name).name
    for suffix in (".json", ".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp"):
        if stem.lower().endswith(suffix):
            stem = stem[: -len(suffix)]
    found = re.findall(r"\d+", stem)
    if not found:
        raise InputError(f"{where}: no frame number in the name {name!r}")
    return int(found[-1])


def _triplets(values: Any, where: str, key: str) -> np.ndarray:
    """(M, 3) float array of a flat [x, y, c, ...] list."""
    if not isinstance(values, list):
        raise InputError(f"{where}: {key} must be a list of numbers, got {type(values).__name__}")
    try:
        a = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{where}: {key} holds something that is not a number") from None
    if a.ndim != 1 or a.size % 3:
        raise InputError(f"{where}: {key} has {a.size} values, not a whole number of (x, y, score) triplets")
    return a.reshape(-1, 3)


def _track(value: Any) -> int:
    """A track id from a JSON value (int, or a one-element list as OpenPose writes it), -1 if none."""
    if isinstance(value, list) and len(value) == 1:
        value = value[0]
    if isinstance(value, bool) or not isinstance(value, int | float) or value != int(value) or value < 0:
        return -1
    return int(value)


def _load_json(path: Path) -> Any:
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except json.JSONDecodeError as e:
        raise InputError(f"{path}: malformed JSON (line {e.lineno}, column {e.colno}: {e.msg})") from None
    except UnicodeDecodeError:
        raise InputError(f"{path}: not a text JSON file") from None
    except OSError as e:
        raise InputError(f"{path}: cannot read ({e.strerror})") from None


def _openpose_frame(data: Any, number: int, where: str) -> _Frame:
    if not isinstance(data, dict) or not isinstance(data.get("people"), list):
        raise InputError(f"{where}: not an OpenPose keypoint file (no 'people' list)")
    people, tracks = [], []
    for i, person in enumerate(data["people"]):
        if not isinstance(person, dict):
            raise InputError(f"{where}: person {i} is not an object")
        key = "pose_keypoints_2d" if "pose_keypoints_2d" in person else "pose_keypoints"
        if key not in person:
            raise InputError(f"{where}: person {i} has no pose_keypoints_2d")
        people.append(_triplets(person[key], f"{where}: person {i}", key))
        tracks.append(_track(person.get("person_id", -1)))
    return _Frame(number, where, people, tracks)


def _read_openpose(path: Path) -> list[_Frame]:
    """One OpenPose JSON file: one frame, its number from the name (0 when the name has none)."""
    n = int(re.findall(r"\d+", path.stem)[-1]) if re.search(r"\d", path.stem) else 0
    return [_openpose_frame(_load_json(path), n, str(path))]


def _read_folder(path: Path, format: str | None) -> list[_Frame]:
    """A folder of per-frame JSON files: OpenPose's (an object with ``people``) or MMPose's per-image
    predictions (a list of instances, ``[]`` for an image without anyone) -> frames. The frame number is
    the last run of digits in each file name; every file must be of the one format (`format`, or the first
    file's)."""
    files = sorted(p for p in path.iterdir() if p.suffix.lower() == ".json" and p.is_file())
    if not files:
        raise InputError(f"{path}: no keypoint files (*.json) in the folder")
    frames = []
    for f in files:
        n = _frame_number(f.name, str(f))
        data, where = _load_json(f), f"{f} (frame {n})"
        kind = "mmpose" if isinstance(data, list) else "openpose"  # not an object: OpenPose's error
        if format is None:
            format = kind
        if kind == "mmpose" and format == "openpose":
            raise InputError(f"{where}: not an OpenPose keypoint file (a list, as MMPose writes, not an object)")
        if kind == "openpose" and format == "mmpose":
            raise InputError(f"{where}: not MMPose's predictions of one image (a list of instances)")
        if format == "openpose":
            frames.append(_openpose_frame(data, n, where))
        elif data and not all(isinstance(d, dict) and "keypoints" in d for d in data):
            raise InputError(
                f"{where}: not one image's MMPose instances (a list of objects with keypoints); a video's "
                f"predictions file is read on its own, not in a folder"
            )
        else:
            frames.append(_mmpose_instances(data, n, where))
    return frames


def _read_coco(data: Any, path: Path) -> list[_Frame]:
    if not isinstance(data, list):
        raise InputError(f"{path}: a COCO results file is a JSON list of detections")
    by_frame: dict[int, _Frame] = {}
    for i, entry in enumerate(data):
        where = f"{path}: entry {i}"
        if not isinstance(entry, dict) or "image_id" not in entry or "keypoints" not in entry:
            raise InputError(f"{where}: not a COCO keypoint result (needs image_id and keypoints)")
        if entry.get("category_id", 1) != 1:
            continue
        image = entry["image_id"]
        if isinstance(image, bool) or not isinstance(image, int | str):
            raise InputError(f"{where}: image_id must be an integer or a file name, got {image!r}")
        n = image if isinstance(image, int) else _frame_number(image, where)
        where = f"{path}: frame {n} (entry {i})"
        kp = _triplets(entry["keypoints"], where, "keypoints")
        frame = by_frame.setdefault(n, _Frame(n, f"{path}: frame {n}", [], []))
        frame.people.append(kp)
        frame.tracks.append(_track(entry.get("idx", entry.get("track_id", -1))))
    return list(by_frame.values())


def _mmpose_instances(items: Any, number: int, where: str) -> _Frame:
    if not isinstance(items, list):
        raise InputError(f"{where}: instances must be a list")
    people, tracks = [], []
    for i, inst in enumerate(items):
        w = f"{where}: instance {i}"
        if not isinstance(inst, dict) or "keypoints" not in inst:
            raise InputError(f"{w}: no keypoints")
        try:
            xy = np.asarray(inst["keypoints"], dtype=float)
            score = np.asarray(inst.get("keypoint_scores", np.ones(len(xy))), dtype=float)
        except (TypeError, ValueError):
            raise InputError(f"{w}: keypoints or keypoint_scores hold something that is not a number") from None
        if xy.ndim == 3 and xy.shape[0] == 1:  # some writers keep the instance axis
            xy = xy[0]
        if score.ndim == 2 and score.shape[0] == 1:
            score = score[0]
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise InputError(f"{w}: keypoints must be a list of [x, y] pairs, got shape {xy.shape}")
        if score.shape != (len(xy),):
            raise InputError(f"{w}: {len(xy)} keypoints but keypoint_scores has shape {score.shape}")
        people.append(np.concatenate([xy, score[:, None]], axis=1))
        tracks.append(_track(inst.get("track_id", -1)))
    return _Frame(number, where, people, tracks)


def _read_mmpose(data: Any, path: Path) -> tuple[list[_Frame], str | None]:
    """Frames and the keypoint set the meta_info names (None if it names none ptrack knows)."""
    hint = None
    if isinstance(data, dict):
        if "instance_info" not in data:
            raise InputError(f"{path}: not an MMPose prediction file (no instance_info)")
        meta = data.get("meta_info")
        if isinstance(meta, dict):
            hint = _MMPOSE_DATASETS.get(str(meta.get("dataset_name", "")).lower())
        data = data["instance_info"]
    if not isinstance(data, list):
        raise InputError(f"{path}: MMPose instance_info must be a list")
    if data and all(isinstance(d, dict) and "keypoints" in d for d in data):  # one image's instances
        return [_mmpose_instances(data, 0, f"{path}: frame 0")], hint
    frames = []
    for i, entry in enumerate(data):
        if not isinstance(entry, dict) or "instances" not in entry:
            raise InputError(f"{path}: entry {i}: an MMPose frame needs frame_id and instances")
        n = entry.get("frame_id", i)
        if isinstance(n, bool) or not isinstance(n, int):
            raise InputError(f"{path}: entry {i}: frame_id must be an integer, got {n!r}")
        frames.append(_mmpose_instances(entry["instances"], n, f"{path}: frame {n}"))
    return frames, hint


# --- arrays: the checks every container shares --------------------------------------------------------


def _numeric(arrays: dict[str, np.ndarray], key: str, path: Path) -> np.ndarray:
    a = arrays[key]
    if a.dtype.kind not in "fiub":
        raise InputError(f"{path}: key {key!r} must be numeric, got dtype {a.dtype}")
    return a.astype(float)


def _scalar(arrays: dict[str, np.ndarray], key: str, path: Path) -> float | None:
    if key not in arrays:
        return None
    a = _numeric(arrays, key, path)
    if a.size != 1:
        raise InputError(f"{path}: key {key!r} must be one number, got shape {a.shape}")
    return float(a.reshape(()))


def _frames_array(arrays: dict[str, np.ndarray], T: int, path: Path) -> np.ndarray:
    if "frames" not in arrays:
        return np.arange(T)
    f = _numeric(arrays, "frames", path)
    if f.shape != (T,) or not np.isfinite(f).all() or (f != np.round(f)).any():
        raise InputError(f"{path}: key 'frames' must be ({T},) integers, got shape {f.shape}")
    return f.astype(np.int64)


def _check_fps(fps: float | None, what: str) -> float | None:
    if fps is None:
        return None
    fps = float(fps)
    if not np.isfinite(fps) or fps <= 0:
        raise InputError(f"{what}: fps must be a positive number, got {fps}")
    return fps


def _resolve_set(
    count: int, given: KeypointDefinition | None, hint: str | None, points: np.ndarray, path: Path
) -> KeypointDefinition:
    """The keypoint set of a file with `count` keypoints a person (the given one, or the file's hint, or
    inferred), checking that the count fits it."""
    if (
        given is None
        and hint is not None
        and count in (KEYPOINT_SETS[hint].num_keypoints, KEYPOINT_SETS[hint].file_count)
    ):
        given = KEYPOINT_SETS[hint]
    if given is not None:
        if count not in (given.num_keypoints, given.file_count):
            raise InputError(f"{path}: {count} keypoints a person, but {given.name} has {given.num_keypoints}")
        return given
    return infer_keypoint_set(count, points, str(path))


def _finish(
    people: np.ndarray,
    frames: np.ndarray,
    tracks: np.ndarray,
    wheres: Sequence[str],
    kset: KeypointDefinition,
    fps: float | None,
    path: Path,
    image_size: tuple[int, int] | None = None,
    video: str | None = None,
) -> Detections:
    """Check and clean (T, P, M, 3) people (all-NaN slots: nobody), keep the set's K keypoints, sort frames."""
    sort = np.argsort(frames, kind="stable")  # frame order first, so that an error names the first bad frame
    frames = np.asarray(frames, dtype=np.int64)[sort]
    wheres = [wheres[i] for i in sort]
    dup = np.flatnonzero(np.diff(frames) == 0)
    if len(dup):
        raise InputError(f"{wheres[dup[0] + 1]}: frame {frames[dup[0]]} appears twice")
    people = np.array(people[sort][:, :, : kset.num_keypoints], dtype=float)
    tracks = np.asarray(tracks)[sort]
    slot = ~np.isnan(people).all((-1, -2))  # (T, P): a person's row (padding is all NaN)
    score = people[..., 2]
    positive = np.nan_to_num(score, nan=0.0, neginf=0.0, posinf=1.0) > 0
    bad = slot[..., None] & ((positive & ~np.isfinite(people[..., :2]).all(-1)) | np.isposinf(score))
    if bad.any():
        t, p, k = np.argwhere(bad)[0]
        x, y, c = people[t, p, k]
        raise InputError(
            f"{wheres[t]}: person {p}, keypoint {k} ({kset.names[k]}): x, y, score = {x}, {y}, {c}: not finite"
        )
    missing = ~(np.isfinite(score) & (score > 0))  # 0, 0, 0 triplets included
    people[missing & slot[..., None]] = (np.nan, np.nan, 0.0)
    empty = slot & missing.all(-1)  # a person without any keypoint: dropped
    people[empty] = np.nan
    present = slot & ~empty
    tracks = np.where(present, tracks, -1)
    if not present.any():
        raise InputError(f"{path}: no person in any frame")
    for t in range(len(frames)):  # a file track id names one person a frame; ids that do not are dropped
        ids = tracks[t][tracks[t] >= 0]
        if len(np.unique(ids)) < len(ids):
            log.warning("%s: two people have the same track id; the file's track ids are ignored", wheres[t])
            tracks[:] = -1
            break
    # put each frame's people first, then drop slots nobody uses
    order = np.argsort(~present, axis=1, kind="stable")
    people = np.take_along_axis(people, order[:, :, None, None], axis=1)
    tracks = np.take_along_axis(tracks, order, axis=1)
    P = int(present.sum(1).max())
    people, tracks = people[:, :P], tracks[:, :P]
    return Detections(
        keypoint_set=kset.name,
        frames=frames,
        people=people,
        track_ids=tracks.astype(np.int64),
        fps=fps,
        source=str(path),
        image_size=image_size,
        video=video,
    )


def _from_frames(
    frames: list[_Frame], path: Path, given: KeypointDefinition | None, hint: str | None, fps: float | None
) -> Detections:
    if not frames:  # e.g. MMPose's empty instance_info, COCO results without a person entry
        raise InputError(f"{path}: no person in any frame")
    for f in frames:  # an empty keypoint list (OpenPose writes some) is nobody
        keep = [i for i, p in enumerate(f.people) if len(p)]
        f.people, f.tracks = [f.people[i] for i in keep], [f.tracks[i] for i in keep]
    counts = [(f, i, len(p)) for f in frames for i, p in enumerate(f.people)]
    if not counts:
        raise InputError(f"{path}: no person in any frame")
    if given is not None:
        allowed = {given.num_keypoints, given.file_count}
        for f, i, m in counts:
            if m not in allowed:
                raise InputError(
                    f"{f.where}: person {i} has {m} keypoints ({3 * m} values), "
                    f"but {given.name} has {given.num_keypoints} ({3 * given.num_keypoints} values)"
                )
    else:
        first = counts[0][2]
        for f, i, m in counts:
            if m != first:
                raise InputError(f"{f.where}: person {i} has {m} keypoints, earlier people have {first}")
    M = counts[0][2]
    T, P = len(frames), max(len(f.people) for f in frames)
    people = np.full((T, P, M, 3), np.nan)
    tracks = np.full((T, P), -1, dtype=np.int64)
    for t, f in enumerate(frames):
        for i, (p, tr) in enumerate(zip(f.people, f.tracks, strict=True)):
            people[t, i] = p
            tracks[t, i] = tr
    flat = people.reshape(-1, M, 3)
    kset = _resolve_set(M, given, hint, flat[~np.isnan(flat).all((-1, -2))], path)
    numbers = np.array([f.number for f in frames], dtype=np.int64)
    return _finish(people, numbers, tracks, [f.where for f in frames], kset, fps, path)


def _read_array_npz(
    arrays: dict[str, np.ndarray], path: Path, given: KeypointDefinition | None, fps: float | None
) -> Detections:
    if "keypoints" in arrays:
        key = "keypoints"
    elif len(arrays) == 1:
        key = next(iter(arrays))
    else:
        raise InputError(f"{path}: no key 'keypoints' and more than one array (has {sorted(arrays)})")
    kp = _numeric(arrays, key, path)
    if kp.ndim == 3:
        kp = kp[:, None]
    if kp.ndim != 4 or kp.shape[-1] not in (2, 3) or 0 in kp.shape:
        raise InputError(f"{path}: key {key!r} must have shape (T, K, 2|3) or (T, P, K, 2|3), got {kp.shape}")
    T, P, M, _ = kp.shape
    score_key = "scores" if "scores" in arrays else "confidence" if "confidence" in arrays else None
    if score_key is not None:
        s = _numeric(arrays, score_key, path)
        if s.shape == (T, M) and P == 1:
            s = s[:, None]
        if s.shape != (T, P, M):
            raise InputError(
                f"{path}: key {score_key!r} must have shape {(T, M) if P == 1 else (T, P, M)}, got {s.shape}"
            )
        if kp.shape[-1] == 3:
            raise InputError(f"{path}: scores given twice (key {key!r} has 3 channels and {score_key!r} exists)")
    else:
        s = np.isfinite(kp[..., :2]).all(-1).astype(float) if kp.shape[-1] == 2 else kp[..., 2]
    people = np.concatenate([kp[..., :2], s[..., None]], axis=-1)
    frames = _frames_array(arrays, T, path)
    if given is None and "keypoint_names" in arrays and arrays["keypoint_names"].dtype.kind in "US":
        names = tuple(str(n) for n in arrays["keypoint_names"].tolist())
        for d in KEYPOINT_SETS.values():
            if names in (d.names, d.other_names):
                given = d
    valid = people.reshape(-1, M, 3)
    kset = _resolve_set(M, given, None, valid[~np.isnan(valid).all((-1, -2))], path)
    fps = fps if fps is not None else _check_fps(_scalar(arrays, "fps", path), str(path))
    wheres = [f"{path}: frame {n}" for n in frames]
    tracks = np.full((T, P), -1, dtype=np.int64)
    return _finish(people, frames, tracks, wheres, kset, fps, path)


def read_mediapipe_landmarks(path: str | Path) -> MediaPipeLandmarks:
    """Read a MediaPipe landmarks file (layout in the module docstring)."""
    path = Path(path)
    arrays = read_npz(path, "MediaPipe landmarks file")
    missing = [k for k in ("landmarks", "world_landmarks") if k not in arrays]
    if missing:
        raise InputError(f"{path}: missing keys {missing} of a MediaPipe landmarks file (has {sorted(arrays)})")
    kset = arrays.get("keypoint_set")
    if kset is not None and (kset.dtype.kind not in "US" or str(kset.reshape(()).item()) != MEDIAPIPE_33.name):
        raise InputError(f"{path}: key 'keypoint_set' must be {MEDIAPIPE_33.name!r}, got {kset!r}")
    lm = _numeric(arrays, "landmarks", path)
    world = _numeric(arrays, "world_landmarks", path)
    if lm.ndim != 3 or lm.shape[1:] != (33, 3) or lm.shape[0] == 0:
        raise InputError(f"{path}: key 'landmarks' must have shape (T, 33, 3), got {lm.shape}")
    if world.shape != lm.shape:
        raise InputError(f"{path}: key 'world_landmarks' must have shape {lm.shape}, got {world.shape}")
    fps = _scalar(arrays, "fps", path)
    fps = _check_fps(None if fps is None or np.isnan(fps) else fps, str(path))  # NaN: the video gave none
    size = [_scalar(arrays, k, path) for k in ("width", "height")]
    video = arrays.get("video")
    return MediaPipeLandmarks(
        frames=_frames_array(arrays, len(lm), path),
        landmarks=lm,
        world_landmarks=world,
        fps=float("nan") if fps is None else fps,
        width=0 if size[0] is None else int(size[0]),
        height=0 if size[1] is None else int(size[1]),
        video="" if video is None or video.dtype.kind not in "US" else str(video.reshape(()).item()),
    )


def write_mediapipe_landmarks(path: str | Path, landmarks: MediaPipeLandmarks) -> Path:
    """Write `landmarks` to the npz at `path` in the layout of the module docstring (the file `ptrack detect`
    writes; its folder is made when missing). The file appears complete or not at all: written to a hidden
    file beside it and renamed, the hidden file removed on any error or interruption. -> path.

    InputError: no frames, frames not strictly increasing integers (T,), landmarks or world_landmarks not
    (T, 33, 3), fps neither positive nor NaN, width or height not positive."""
    path = Path(path)
    frames = np.asarray(landmarks.frames)
    lm = np.asarray(landmarks.landmarks, dtype=np.float32)
    world = np.asarray(landmarks.world_landmarks, dtype=np.float32)
    T = len(frames)
    if T == 0:
        raise InputError("MediaPipe landmarks: no frames to write")
    if frames.shape != (T,) or frames.dtype.kind not in "iu" or (np.diff(frames) <= 0).any():
        raise InputError(f"MediaPipe landmarks: frames must be strictly increasing integers (T,), got {frames.shape}")
    if lm.shape != (T, 33, 3) or world.shape != (T, 33, 3):
        raise InputError(
            f"MediaPipe landmarks: landmarks and world_landmarks must have shape {(T, 33, 3)}, "
            f"got {lm.shape} and {world.shape}"
        )
    fps = float(landmarks.fps)
    if not np.isnan(fps):
        _check_fps(fps, "MediaPipe landmarks")
    width, height = int(landmarks.width), int(landmarks.height)
    if width <= 0 or height <= 0:
        raise InputError(f"MediaPipe landmarks: width and height must be positive, got {width} x {height}")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")  # a file mode as the umask says, unlike mkstemp's
    try:
        with open(tmp, "wb") as f:
            np.savez(
                f,
                frames=frames.astype(np.int64),
                landmarks=lm,
                world_landmarks=world,
                fps=np.float64(fps),
                width=np.int64(width),
                height=np.int64(height),
                video=np.str_(str(landmarks.video)),
                keypoint_set=np.str_(MEDIAPIPE_33.name),
            )
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def _read_mediapipe(path: Path, fps: float | None) -> Detections:
    m = read_mediapipe_landmarks(path)
    people = m.landmarks[:, None].copy()
    nobody = np.isnan(m.landmarks[..., :2]).all((-1, -2))
    people[nobody] = np.nan
    tracks = np.full((len(m.frames), 1), -1, dtype=np.int64)
    wheres = [f"{path}: frame {n}" for n in m.frames]
    size = (m.width, m.height) if m.width > 0 and m.height > 0 else None
    fps = fps if fps is not None else (None if np.isnan(m.fps) else m.fps)
    return _finish(people, m.frames, tracks, wheres, MEDIAPIPE_33, fps, path, size, m.video or None)


def _json_format(data: Any) -> str | None:
    """The container of parsed JSON content, None when it is none of them."""
    if isinstance(data, dict):
        if "people" in data:
            return "openpose"
        if "instance_info" in data:
            return "mmpose"
        return None
    if isinstance(data, list) and data and isinstance(data[0], dict):
        if "image_id" in data[0]:
            return "coco"
        if "instances" in data[0] or "frame_id" in data[0] or "keypoint_scores" in data[0]:
            return "mmpose"
    return None


def read_keypoints(
    path: str | Path,
    format: str | None = None,
    keypoint_set: str | None = None,
    fps: float | None = None,
) -> Detections:
    """Read a keypoint file or folder (containers and rules in the module docstring).

    format: one of `FORMATS` ("alphapose" means coco), inferred from the content when None.
    keypoint_set: a name `get_keypoint_set` knows, inferred from the keypoint count when None.
    fps: frames per second; overrides the file's.
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"keypoint file not found: {path}")
    kset = None if keypoint_set is None else get_keypoint_set(keypoint_set)
    fps = _check_fps(fps, str(path))
    if format is not None:
        name = _FORMAT_ALIASES.get(str(format).lower(), str(format).lower())
        if name not in FORMATS:
            raise InputError(f"unknown keypoint file format {format!r} (known: {', '.join(FORMATS)})")
        format = name
    if path.is_dir():
        if format not in (None, "openpose", "mmpose"):
            raise InputError(
                f"{path}: a folder is read as OpenPose JSON or MMPose per-image predictions (one file a frame), "
                f"not {format}"
            )
        return _from_frames(_read_folder(path, format), path, kset, None, fps)
    if path.suffix.lower() == ".npz" or format in ("npz", "mediapipe"):
        if format is None:
            format = "mediapipe" if "world_landmarks" in read_npz(path, "keypoint file") else "npz"
        if format == "mediapipe":
            if kset is not None and kset.name != "MEDIAPIPE_33":
                raise InputError(f"{path}: MediaPipe landmarks are MEDIAPIPE_33, not {kset.name}")
            return _read_mediapipe(path, fps)
        if format == "npz":
            return _read_array_npz(read_npz(path, "keypoint file"), path, kset, fps)
        raise InputError(f"{path}: an .npz file is read as npz or mediapipe, not {format}")
    data = _load_json(path)
    found = _json_format(data)
    if format is None:
        if found is None:
            if isinstance(data, list) and not data:
                raise InputError(f"{path}: no person in any frame (an empty list)")
            raise InputError(
                f"{path}: cannot tell the keypoint file format (give observations.format: {', '.join(FORMATS)})"
            )
        format = found
    if format == "openpose":
        return _from_frames(_read_openpose(path), path, kset, None, fps)
    if format == "coco":
        if isinstance(data, list) and not data:
            raise InputError(f"{path}: no person in any frame (an empty list)")
        return _from_frames(_read_coco(data, path), path, kset, None, fps)
    if format == "mmpose":
        frames, hint = _read_mmpose(data, path)
        return _from_frames(frames, path, kset, hint, fps)
    raise InputError(f"{path}: a JSON file is read as openpose, coco or mmpose, not {format}")
