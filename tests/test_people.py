"""The person: tracks linked over frames (gaps, crossings, file track ids), the default choice, and
`person=` by track id or by a pixel; on the real Pose2Sim trials with a bystander and with two people."""

from __future__ import annotations

import numpy as np
import pytest
from keypoint_fixtures import SHIPPED_FRAMES, person, pose2sim

from ptrack.body.keypoint_sets import BODY_25B, COCO_17
from ptrack.errors import InputError
from ptrack.observe.keypoint_files import Detections, read_keypoints
from ptrack.observe.people import MAX_GAP, link_tracks, mirror_switches, select_person, track_summary

L_HIP, R_HIP = BODY_25B.index("LHip"), BODY_25B.index("RHip")


def _detections(frames: list[list[np.ndarray]], ids: list[list[int]] | None = None, kset=COCO_17) -> Detections:
    """Detections from per-frame lists of (K, 3) people (slots in the given order)."""
    T, P, K = len(frames), max(1, max(len(f) for f in frames)), kset.num_keypoints
    people = np.full((T, P, K, 3), np.nan)
    track_ids = np.full((T, P), -1)
    for t, f in enumerate(frames):
        for p, kp in enumerate(f):
            people[t, p] = kp
            if ids is not None:
                track_ids[t, p] = ids[t][p]
    return Detections(kset.name, np.arange(T), people, track_ids, 30.0, "test")


def _mid_hip(track) -> np.ndarray:
    return (track.points[:, L_HIP] + track.points[:, R_HIP]) / 2


# --- real footage -------------------------------------------------------------------------------------


def test_balancing_default_is_the_participant_in_every_frame():
    det = read_keypoints(pose2sim("balancing/pose/cam01_json"))
    assert det.people.shape[1] >= 2  # the bystander is detected too
    track = select_person(det)
    assert track.present.all() and track.n_tracks == 2  # the participant and the bystander
    # in frame 37 OpenPose split the participant into an upper and a lower body: one person again
    split = det.present[37] & (link_tracks(det)[37] == track.track_id)
    assert split.sum() == 2 and np.isfinite(track.points[37]).all()
    hips = np.isfinite(track.points[:, [L_HIP, R_HIP]]).all((1, 2))
    assert hips.sum() >= 95
    # the participant is the large person in the middle of the portrait frame (1088 wide), the bystander
    # stands at the left edge
    x = np.nanmedian(track.points[..., 0], axis=1)
    assert (x > 250).all()
    # consistent: the mid-hip moves a few pixels a frame (60 fps), never jumps to the other person
    step = np.linalg.norm(np.diff(_mid_hip(track), axis=0), axis=1)
    assert np.nanmax(step) < 40


def test_two_people_default_and_the_other():
    det = read_keypoints(pose2sim("two_people/pose/cam01_json"))
    default = select_person(det)
    infos = {i.track_id: i for i in track_summary(det, link_tracks(det))}
    # the other participant: the other track with hips in (nearly) every frame
    others = [
        tid
        for tid, i in infos.items()
        if tid != default.track_id and np.isfinite(_mid_hip(select_person(det, tid))).all(1).sum() >= 90
    ]
    assert len(others) == 1
    other = select_person(det, others[0])
    assert default.present.sum() >= 95 and other.present.sum() >= 95
    for track in (default, other):
        step = np.linalg.norm(np.diff(_mid_hip(track), axis=0), axis=1)
        assert np.nanmax(step) < 40  # no frame jumps between the two
    both = default.present & other.present
    gap = np.linalg.norm(_mid_hip(default)[both] - _mid_hip(other)[both], axis=1)
    assert gap.min() > 150
    # the default is the larger, more continuous one
    assert infos[default.track_id].size * default.present.sum() > infos[other.track_id].size * other.present.sum()
    # a pixel of the other person in the first frame picks it
    first = np.flatnonzero(other.present)[0]
    assert first == 0
    x, y = np.nanmedian(other.points[0], axis=0)
    assert select_person(det, (float(x), float(y))).track_id == other.track_id


def test_shipped_frames_pick_the_participant():
    det = read_keypoints(SHIPPED_FRAMES)
    track = select_person(det)
    assert track.present.all() and track.n_tracks == 3
    sizes = np.linalg.norm(np.nanmax(track.points, 1) - np.nanmin(track.points, 1), axis=1)
    assert (sizes > 700).all()  # the participant is about 900 px tall; the others about 500


# --- linking ------------------------------------------------------------------------------------------


def _walk(x0, vx, y, height, T):
    return [person(COCO_17, x0 + vx * t, y, height) for t in range(T)]


def test_crossing_people_keep_their_tracks():
    T = 40
    a = _walk(100, 20, 100, 400, T)  # walks right
    b = _walk(900, -20, 110, 380, T)  # walks left, crosses a near frame 20
    rng = np.random.default_rng(1)
    frames = []
    for t in range(T):
        f = [a[t] + [*rng.normal(0, 2, 2), 0], b[t] + [*rng.normal(0, 2, 2), 0]]
        if t % 3 == 0:
            f.reverse()  # the detector's order changes
        if 19 <= t <= 21:
            f = [a[t]]  # b hidden behind a while they cross
        frames.append(f)
    det = _detections(frames)
    ids = link_tracks(det)
    assert len(track_summary(det, ids)) == 2
    for tid in (0, 1):
        tr = select_person(det, tid)
        x = np.nanmean(tr.points[tr.present, :, 0], axis=1)
        dx = np.diff(x)
        assert (dx > 0).all() or (dx < 0).all()  # one direction: never switched to the other walker
    b_track = select_person(det, 1)
    assert b_track.present.sum() == T - 3 and not b_track.present[19:22].any()


def test_gap_of_a_few_frames_is_bridged_a_long_one_is_not():
    T = 60
    walk = _walk(100, 3, 50, 400, T)
    short = [[p] if not 10 <= t < 15 else [] for t, p in enumerate(walk)]
    det = _detections(short)
    assert len(track_summary(det, link_tracks(det))) == 1
    gone = MAX_GAP + 5
    long = [[p] if not 10 <= t < 10 + gone else [] for t, p in enumerate(walk)]
    det = _detections(long)
    assert [i.first for i in track_summary(det, link_tracks(det))] == [0, 10 + gone]


def test_a_person_split_in_two_detections_is_one():
    p = person(COCO_17, 200, 0, 500)
    upper, lower = p.copy(), p.copy()
    upper[11:] = (np.nan, np.nan, 0)
    lower[:11] = (np.nan, np.nan, 0)
    other = person(COCO_17, 700, 0, 480)
    frames = [[p, other]] * 3 + [[other, lower, upper]] + [[p, other]] * 3
    det = _detections(frames)
    ids = link_tracks(det)
    assert ids[3, 1] == ids[3, 2] == ids[0, 0] and ids[3, 0] == ids[0, 1]
    track = select_person(det)
    assert track.n_tracks == 2
    np.testing.assert_array_equal(track.points[3], p[:, :2])


def test_linker_numbers_tracks_by_first_appearance_then_size():
    small, big, late = person(COCO_17, 0, 0, 200), person(COCO_17, 500, 0, 600), person(COCO_17, 900, 0, 300)
    frames = [[small, big]] * 5 + [[small, big, late]] * 5
    det = _detections(frames)
    infos = track_summary(det, link_tracks(det))
    assert [(i.first, round(i.size / 100)) for i in infos] == [(0, 6), (0, 2), (5, 3)]


def test_file_track_ids_are_kept():
    a, b = person(COCO_17, 0, 0, 300), person(COCO_17, 600, 0, 300)
    frames = [[a, b]] * 4 + [[b, a]] * 4  # the file's own ids follow the people, not the slots
    det = _detections(frames, ids=[[7, 3]] * 4 + [[3, 7]] * 4)
    track = select_person(det, 7)
    np.testing.assert_array_equal(track.points, np.repeat(a[None, :, :2], 8, axis=0))
    assert track.track_id == 7 and track.n_tracks == 2
    with pytest.raises(InputError, match=r"no person with track id 0 \(tracks: 3 \(8 frames\), 7 \(8 frames\)\)"):
        select_person(det, 0)


# --- the choice ---------------------------------------------------------------------------------------


def test_default_maximises_size_times_coverage():
    T = 50
    big_brief = person(COCO_17, 600, 0, 800)  # 800 px, 10 frames
    steady = person(COCO_17, 0, 0, 300)  # 300 px, every frame
    frames = [[steady, big_brief] if t < 10 else [steady] for t in range(T)]
    det = _detections(frames)
    chosen = select_person(det)
    assert chosen.present.all()
    np.testing.assert_allclose(chosen.points[0], steady[:, :2])
    frames = [[steady, big_brief] if t < 30 else [steady] for t in range(T)]  # 800 x 30 > 300 x 50
    np.testing.assert_allclose(select_person(_detections(frames)).points[0], big_brief[:, :2])


def test_person_by_pixel_of_the_first_frame():
    a, b = person(COCO_17, 100, 100, 400), person(COCO_17, 700, 100, 400)
    det = _detections([[a, b]] * 3)
    assert select_person(det, (720, 300)).track_id == select_person(det, 1).track_id
    assert np.nanmean(select_person(det, [160, 250]).points[0, :, 0]) < 400  # inside a's box
    assert np.nanmean(select_person(det, (5000, 300)).points[0, :, 0]) > 600  # nearest: b


def test_frames_without_the_person_and_swaps_kept():
    p = person(COCO_17, 0, 0, 400)
    swapped = p[COCO_17.mirror_index()]  # the detector swapped left and right in frame 2
    frames = [[p], [], [swapped], [p]]
    track = select_person(_detections(frames))
    assert track.present.tolist() == [True, False, True, True]
    assert (track.scores[1] == 0).all() and np.isnan(track.points[1]).all()
    np.testing.assert_array_equal(track.points[2], swapped[:, :2])
    assert track.frames.tolist() == [0, 1, 2, 3] and track.keypoint_set == "COCO_17" and track.fps == 30.0


def test_a_mirrored_stretch_stays_the_same_person():
    """A detector that labels the whole body mirrored from some frame on (MediaPipe on the Pose2Sim trial's cam02)
    moves every paired keypoint by the body's width: the person stays one track, over every frame, with the
    detector's labels kept."""
    from ptrack.body.keypoint_sets import MEDIAPIPE_33

    walk = []
    for t in range(40):  # arms and legs spread (the standing person 4x as wide): exchanged, most keypoints move far
        p = person(MEDIAPIPE_33, 100 + 2 * t, 50, 500)
        p[:, 0] = 100 + 2 * t + 4 * (p[:, 0] - 100 - 2 * t)
        walk.append(p)
    frames = [[p[MEDIAPIPE_33.mirror_index()] if 15 <= t < 30 else p] for t, p in enumerate(walk)]
    det = _detections(frames, kset=MEDIAPIPE_33)
    assert len(track_summary(det, link_tracks(det))) == 1
    track = select_person(det)
    assert track.present.all()
    np.testing.assert_array_equal(track.points[20], frames[20][0][:, :2])  # kept as the detector labelled it
    # as given only (the linker before it read mirrored detections): the stretch was a track of its own
    assert _cost_as_labelled_splits(walk, frames)


def _cost_as_labelled_splits(walk, frames) -> bool:
    """Whether the mirrored frame 15 costs more than the link gate when read as labelled (the test's premise)."""
    from ptrack.observe.people import GATE, _cost_as_labelled, _Track

    track = _Track(0, walk[0][:, :2])
    for t in range(1, 15):
        track.update(t, walk[t][:, :2])
    return _cost_as_labelled(track, 15, frames[15][0][:, :2]) > GATE  # the labels as they are


def _walker(frames: int, width: float, seed: int = 0) -> np.ndarray:
    """(T, K, 2) a COCO-17 person drifting right 2 px a frame, its left/right spread `width` times a standing
    person's (small: seen from the side), 1.5 px of noise."""
    rng = np.random.default_rng(seed)
    out = []
    for t in range(frames):
        p = person(COCO_17, 100 + 2 * t, 50, 400)[:, :2]
        centre = p[:, 0].mean()
        p[:, 0] = centre + width * (p[:, 0] - centre)
        out.append(p + rng.normal(0, 1.5, p.shape))
    return np.asarray(out)


def test_mirror_switches_find_a_whole_body_exchange_only():
    """The frames where the detector exchanged every left/right label from the frame before, across a frame without
    the person; not a side view (both readings alike), not a few swapped keypoints, not noise."""
    mirror = COCO_17.mirror_index()
    front = _walker(30, 3.0)  # arms and legs spread: exchanged, every paired keypoint moves far
    seen = np.ones(front.shape[:2], dtype=bool)
    mirrored = front.copy()
    mirrored[10:20] = front[10:20][:, mirror]
    assert mirror_switches(front, seen, mirror).tolist() == []
    assert mirror_switches(mirrored, seen, mirror).tolist() == [10, 20]
    gap = seen.copy()
    gap[19:21] = False  # the person unseen when the labels turn back: frame 21 against frame 18
    assert mirror_switches(mirrored, gap, mirror).tolist() == [10, 21]
    side = _walker(30, 0.02)  # seen from the side: the two readings project within a few pixels
    side_mirrored = side.copy()
    side_mirrored[10:20] = side[10:20][:, mirror]
    assert mirror_switches(side_mirrored, seen, mirror).tolist() == []
    wrists = front.copy()  # only the wrists exchanged, as detectors often do: the median does not follow
    lw, rw = COCO_17.index("left_wrist"), COCO_17.index("right_wrist")
    wrists[10:20, [lw, rw]] = front[10:20][:, [rw, lw]]
    assert mirror_switches(wrists, seen, mirror).tolist() == []
    assert mirror_switches(mirrored[:1], seen[:1], mirror).tolist() == []  # one frame: nothing to compare


@pytest.mark.parametrize("bad", ["left", (1.0,), True, (np.nan, 3.0)])
def test_person_of_another_kind(bad):
    det = _detections([[person(COCO_17, 0, 0, 300)]])
    with pytest.raises(InputError, match="person must be a track id or a pixel"):
        select_person(det, bad)
