"""The person to reconstruct: detections linked over frames into tracks, and one track chosen.

`link_tracks(det)` gives every detected person a track id. When the file gives every person a track id
(OpenPose `person_id`, AlphaPose `idx`, MMPose `track_id`), those are kept. Otherwise people are linked
frame by frame: each live track predicts its keypoints in the new frame (its last keypoints moved by its
last per-frame translation, the median over keypoints, times the frames elapsed), the cost of giving it a
detection is the median distance between predicted and detected keypoints (over those both show; the
bounding-box centres when fewer than 3) divided by the track's size (median bounding-box diagonal of its
last detections), and the assignment of least total cost is taken (Hungarian). A pair costing more than
`GATE` (times 1 + (gap - 1) / 4 after a gap) is not linked; a track not seen for more than `MAX_GAP`
frames ends. A detection left over that fits a track linked in the same frame, and shares at most one
keypoint with the detection linked to it, is a part of that person the detector split off (OpenPose splits
the Pose2Sim participant into upper and lower body in some frames): it gets the same track id, and the
person's keypoints in that frame are taken from both parts. Any other detection left over starts a new
track. The median makes a link robust to a detector's
left/right swap of a few keypoints, the motion prediction keeps two people apart when they cross. A detection is
also compared with every left and right label exchanged, and the cheaper reading counts: a detector that takes
the person for one facing the other way labels the whole body mirrored (MediaPipe on the Pose2Sim trial's cam02,
from frame 41 to 73), every paired keypoint jumps by the body's width, and the person would otherwise start a
new track there (and the longer half be chosen). The detections themselves keep the detector's labels.
Linked tracks are numbered 0, 1, ... by first appearance, then by size (larger first).

`select_person(det, person)` chooses one track:

- `person=None` (default): the track maximising size x coverage, i.e. its median bounding-box diagonal
  (pixels) times the number of frames it is present in: the largest, most continuous person, so that a
  bystander who is smaller (further away) or passes through is not chosen.
- `person=int`: that track id (the file's own, or the linker's numbering when the file has none).
- `person=(x, y)`: a pixel of the first frame: the track whose bounding box there contains the pixel
  (the one whose box centre is nearest when several do), else the nearest box. Tracks absent from the
  first frame count, with their box in the first frame they appear, only when no track is in the first frame.

Left/right swaps of the detector are kept as they are (the estimators' robust terms handle them).
`mirror_switches(points, seen, mirror)` finds the frames where the detector exchanged every label of the person from
the frame before (the run then lets the kjs tracker read the labels exchanged too, `costs.swap_cost`).
"""

from __future__ import annotations

import itertools
import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy.optimize import linear_sum_assignment

from ptrack.body.keypoint_sets import get_keypoint_set
from ptrack.errors import InputError
from ptrack.observe.keypoint_files import Detections

log = logging.getLogger(__name__)

#: frames a track may go unseen and still be continued
MAX_GAP = 10
#: largest link cost (median keypoint distance / person size) between consecutive frames
GATE = 0.25
#: detections of a track whose sizes make its size (the median of the latest)
_SIZE_WINDOW = 15


@dataclass(frozen=True, eq=False)
class PersonTrack:
    """One person over every frame of the detections.

    frames: (T,) int input frame numbers (all of the file's frames).
    points: (T, K, 2) pixels, NaN where missing (the keypoint, or the person in that frame).
    scores: (T, K) observation weights, 0 where missing.
    present: (T,) bool, the person is detected in the frame.
    track_id: the chosen track's id; n_tracks: how many tracks the detections hold.
    keypoint_set: the keypoint set's registry name; fps: frames per second, None when unknown.
    """

    frames: np.ndarray
    points: np.ndarray
    scores: np.ndarray
    present: np.ndarray
    track_id: int
    n_tracks: int
    keypoint_set: str
    fps: float | None


class TrackInfo(NamedTuple):
    """One track: its id, the frame index (0..T-1) of its first detection, frames present, median
    bounding-box diagonal (pixels), and its bounding box (x0, y0, x1, y1) in its first frame."""

    track_id: int
    first: int
    frames_present: int
    size: float
    first_box: tuple[float, float, float, float]


def _box(xy: np.ndarray) -> np.ndarray:
    """(4,) [x0, y0, x1, y1] of the finite rows of xy (K, 2)."""
    ok = np.isfinite(xy).all(-1)
    p = xy[ok]
    return np.concatenate([p.min(0), p.max(0)])


def _size(xy: np.ndarray) -> float:
    b = _box(xy)
    return float(np.hypot(b[2] - b[0], b[3] - b[1]))


def _file_ids(det: Detections) -> bool:
    """Every detected person carries a track id from the file."""
    present = det.present
    return bool(present.any() and (det.track_ids[present] >= 0).all())


class _Track:
    """A live track of the linker: its latest keypoints and motion."""

    def __init__(self, t: int, xy: np.ndarray):
        self.first = t
        self.last_t = t
        self.last = xy
        self.velocity = np.zeros(2)
        self.sizes = [max(_size(xy), 1.0)]

    def predict(self, t: int) -> np.ndarray:
        return self.last + self.velocity * (t - self.last_t)

    @property
    def size(self) -> float:
        return float(np.median(self.sizes[-_SIZE_WINDOW:]))

    def update(self, t: int, xy: np.ndarray) -> None:
        step = (xy - self.last) / (t - self.last_t)
        ok = np.isfinite(step).all(-1)
        self.velocity = np.median(step[ok], axis=0) if ok.sum() >= 3 else np.zeros(2)
        # keep the latest position of keypoints missing now, so that they still count next frame
        self.last = np.where(np.isfinite(xy), xy, self.predict(t))
        self.last_t = t
        self.sizes.append(max(_size(xy), 1.0))


def _cost(track: _Track, t: int, xy: np.ndarray, mirror: np.ndarray) -> tuple[float, bool]:
    """The cost of giving detection xy (K, 2) to `track` on frame t, and whether it fits better with every left and
    right label exchanged (`mirror` (K,): the keypoint set's exchange)."""
    own = _cost_as_labelled(track, t, xy)
    other = _cost_as_labelled(track, t, xy[mirror])
    return (other, True) if other < own else (own, False)


def _cost_as_labelled(track: _Track, t: int, xy: np.ndarray) -> float:
    pred = track.predict(t)
    d = np.linalg.norm(pred - xy, axis=-1)
    d = d[np.isfinite(d)]
    if len(d) >= 3:
        dist = float(np.median(d))
    else:
        pb, xb = _box(pred), _box(xy)
        dist = float(np.linalg.norm((pb[:2] + pb[2:]) / 2 - (xb[:2] + xb[2:]) / 2))
    return dist / track.size


#: a whole-body exchange of the labels between two frames (`mirror_switches`): the left/right-paired keypoints' median
#: step, over the person's size, is at least `SWITCH_STEP` larger as labelled than with the labels exchanged, and
#: exchanged at most `SWITCH_RATIO` of it as labelled. Measured (2026-11-30) as labelled - exchanged: never above -0.04
#: on every clean input (Pose2Sim's OpenPose files of the three trials, MediaPipe's cam01, the synthetic COCO-17
#: clips); 0.13-0.31 where a body's labels were exchanged (MediaPipe's cam02, a stretch exchanged in those clips)
SWITCH_STEP, SWITCH_RATIO = 0.05, 0.5
#: paired keypoints seen in both frames that a switch needs
SWITCH_MIN_PAIRED = 4


def mirror_switches(points: np.ndarray, seen: np.ndarray, mirror: np.ndarray) -> np.ndarray:
    """The frames where the detector exchanged every left and right label of the person from the frame before it
    (the last one with the person seen, across frames without): it took the person for one facing the other way
    (or back), and each paired keypoint jumps to where its partner was. A side view, where both readings project
    alike, gives no switch; nor do a few keypoints swapped alone.

    points (T, K, 2) pixels (NaN where missing); seen (T, K) bool; mirror (K,) each keypoint's left/right partner
    (itself when unpaired) -> (S,) int, each a frame index t whose labels are exchanged from the previous seen
    frame's (`SWITCH_STEP`, `SWITCH_RATIO`, `SWITCH_MIN_PAIRED`; steps over the person's median bounding-box
    diagonal)."""
    points, seen, mirror = np.asarray(points, dtype=np.float64), np.asarray(seen, dtype=bool), np.asarray(mirror)
    paired = (mirror != np.arange(len(mirror))) & seen & seen[:, mirror] & np.isfinite(points).all(-1)
    frames = np.flatnonzero(paired.sum(-1) >= SWITCH_MIN_PAIRED)
    if len(frames) < 2:
        return np.zeros(0, dtype=np.int64)
    size = max(float(np.median([_size(points[t, paired[t]]) for t in frames])), 1.0)
    out = []
    for before, t in itertools.pairwise(frames):
        both = paired[t] & paired[before]
        if both.sum() < SWITCH_MIN_PAIRED:
            continue
        step = float(np.median(np.linalg.norm(points[t, both] - points[before, both], axis=-1))) / size
        exchanged = float(np.median(np.linalg.norm(points[t, mirror][both] - points[before, both], axis=-1))) / size
        if step - exchanged > SWITCH_STEP and exchanged < SWITCH_RATIO * step:
            out.append(t)
    return np.asarray(out, dtype=np.int64)


def link_tracks(det: Detections, max_gap: int = MAX_GAP, gate: float = GATE) -> np.ndarray:
    """(T, P) int track id of every detected person, -1 for empty slots (rules in the module docstring);
    two slots of a frame share an id when they are parts of one person.

    The file's track ids when it gives every person one, else the linker's, numbered by first appearance
    then size.
    """
    present = det.present
    if _file_ids(det):
        return np.where(present, det.track_ids, -1)
    T, P = present.shape
    xy = det.people[..., :2]
    mirror = get_keypoint_set(det.keypoint_set).mirror_index()
    raw = np.full((T, P), -1, dtype=np.int64)
    tracks: list[_Track] = []
    for t in range(T):
        slots = np.flatnonzero(present[t])
        live = [j for j, tr in enumerate(tracks) if t - tr.last_t <= max_gap + 1]
        taken: dict[int, int] = {}  # column (detection) -> row (live track) it continues
        if live and len(slots):
            costs = [[_cost(tracks[j], t, xy[t, p], mirror) for p in slots] for j in live]
            cost = np.array([[c for c, _ in row] for row in costs])
            mirrored = np.array([[m for _, m in row] for row in costs], dtype=bool)
            limit = np.array([gate * (1 + (t - tracks[j].last_t - 1) / 4) for j in live])[:, None]
            rows, cols = linear_sum_assignment(np.where(cost <= limit, cost, 1e6))
            taken = {c: r for r, c in zip(rows, cols, strict=True) if cost[r, c] <= limit[r, 0]}
            seen = np.isfinite(xy[t, slots]).all(-1)  # (D, K)
            for c in range(len(slots)):  # a part of a person the detector split off: joins that person
                if c in taken:
                    continue
                for c2, r in list(taken.items()):
                    if cost[r, c] <= limit[r, 0] and (seen[c] & seen[c2]).sum() <= 1:
                        taken[c] = r
                        break
            for r in set(taken.values()):
                parts = [c for c in taken if taken[c] == r]
                # the track keeps one labelling: a part read mirrored moves it in the track's own
                read = [xy[t, slots[c]][mirror] if mirrored[r, c] else xy[t, slots[c]] for c in parts]
                merged = read[0].copy()
                for part in read[1:]:
                    merged = np.where(np.isfinite(merged), merged, part)
                tracks[live[r]].update(t, merged)
                raw[t, slots[parts]] = live[r]
        for c, p in enumerate(slots):
            if c not in taken:
                raw[t, p] = len(tracks)
                tracks.append(_Track(t, xy[t, p]))
    # number by first appearance, then by size (larger first)
    order = sorted(range(len(tracks)), key=lambda j: (tracks[j].first, -tracks[j].size))
    renumber = np.full(len(tracks) + 1, -1, dtype=np.int64)
    renumber[np.array(order, dtype=np.int64)] = np.arange(len(tracks))
    return renumber[raw]


def track_summary(det: Detections, ids: np.ndarray) -> list[TrackInfo]:
    """Every track of `ids` (T, P) (from `link_tracks`), in id order."""
    present = det.present & (ids >= 0)
    out = []
    for tid in np.unique(ids[present]):
        ts, ps = np.nonzero(present & (ids == tid))
        sizes = [_size(det.people[t, p, :, :2]) for t, p in zip(ts, ps, strict=True)]
        box = _box(det.people[ts[0], ps[0], :, :2])
        out.append(
            TrackInfo(
                track_id=int(tid),
                first=int(ts[0]),
                frames_present=len(np.unique(ts)),
                size=float(np.median(sizes)),
                first_box=(float(box[0]), float(box[1]), float(box[2]), float(box[3])),
            )
        )
    return out


def _by_point(infos: list[TrackInfo], det: Detections, ids: np.ndarray, x: float, y: float) -> int:
    """The track id nearest the pixel (x, y) of the first frame (rule in the module docstring)."""
    boxes: list[tuple[int, np.ndarray]] = []
    for p in np.flatnonzero(det.present[0] & (ids[0] >= 0)):
        boxes.append((int(ids[0, p]), _box(det.people[0, p, :, :2])))
    if not boxes:
        boxes = [(i.track_id, np.array(i.first_box)) for i in infos]
    best, key = -1, (np.inf, np.inf)
    for tid, b in boxes:
        outside = np.hypot(max(b[0] - x, 0.0, x - b[2]), max(b[1] - y, 0.0, y - b[3]))
        centre = np.hypot((b[0] + b[2]) / 2 - x, (b[1] + b[3]) / 2 - y)
        if (outside, centre) < key:
            best, key = tid, (outside, centre)
    return best


def select_person(det: Detections, person: int | Sequence[float] | None = None) -> PersonTrack:
    """The track of one person (rules in the module docstring).

    person: None (the largest, most continuous track), a track id, or a pixel (x, y) of the first frame.
    An unknown track id, or a `person` of another kind, raises InputError.
    """
    ids = link_tracks(det)
    infos = track_summary(det, ids)
    if not infos:
        raise InputError(f"{det.source}: no person in any frame")
    known = ", ".join(f"{i.track_id} ({i.frames_present} frames)" for i in infos)
    if person is None:
        chosen = max(infos, key=lambda i: (i.size * i.frames_present, -i.track_id)).track_id
    elif isinstance(person, int | np.integer) and not isinstance(person, bool):
        chosen = int(person)
        if chosen not in {i.track_id for i in infos}:
            raise InputError(f"{det.source}: no person with track id {chosen} (tracks: {known})")
    elif (
        isinstance(person, Sequence)
        and not isinstance(person, str)
        and len(person) == 2
        and all(isinstance(v, int | float) and not isinstance(v, bool) and np.isfinite(v) for v in person)
    ):
        chosen = _by_point(infos, det, ids, float(person[0]), float(person[1]))
    else:
        raise InputError(f"person must be a track id or a pixel [x, y] of the first frame, got {person!r}")
    log.info("%s: %d tracks (id: frames present): %s; chose %d", det.source, len(infos), known, chosen)
    T, _, K, _ = det.people.shape
    points = np.full((T, K, 2), np.nan)
    scores = np.zeros((T, K))
    present = np.zeros(T, dtype=bool)
    for t, p in zip(*np.nonzero(det.present & (ids == chosen)), strict=True):
        better = det.people[t, p, :, 2] > scores[t]  # parts of one person: each keypoint from the surer one
        points[t, better] = det.people[t, p, better, :2]
        scores[t, better] = det.people[t, p, better, 2]
        present[t] = True
    return PersonTrack(
        frames=det.frames.copy(),
        points=points,
        scores=scores,
        present=present,
        track_id=chosen,
        n_tracks=len(infos),
        keypoint_set=det.keypoint_set,
        fps=det.fps,
    )
