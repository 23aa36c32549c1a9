"""Keypoint file readers: fixtures written from each format's published layout, the real Pose2Sim OpenPose
folders, and one-line errors for each kind of bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
from keypoint_fixtures import SHIPPED_FRAMES, person, pose2sim

from ptrack.body.keypoint_sets import BODY_25, BODY_25B, COCO_17, H36M_17, HALPE_26, KEYPOINT_SETS
from ptrack.errors import InputError
from ptrack.observe.keypoint_files import (
    MediaPipeLandmarks,
    read_keypoints,
    read_mediapipe_landmarks,
    write_mediapipe_landmarks,
)

WHOLEBODY = KEYPOINT_SETS["COCO_WHOLEBODY"]
MEDIAPIPE = KEYPOINT_SETS["MEDIAPIPE_33"]


def _write(path, obj):
    path.write_text(json.dumps(obj))
    return path


def _openpose_file(folder, name, people, ids=None):
    """One frame as OpenPose --write_json writes it (doc/02_output.md), people: list of (K, 3)."""
    entries = []
    for i, p in enumerate(people):
        pid = -1 if ids is None else ids[i]
        entries.append(
            {
                "person_id": [pid],
                "pose_keypoints_2d": [round(float(v), 3) for v in np.asarray(p).ravel()],
                "face_keypoints_2d": [],
                "hand_left_keypoints_2d": [],
                "hand_right_keypoints_2d": [],
                "pose_keypoints_3d": [],
            }
        )
    return _write(folder / name, {"version": 1.3, "people": entries})


def _one_line_error(match, *args, **kwargs):
    with pytest.raises(InputError, match=match) as e:
        read_keypoints(*args, **kwargs)
    assert "\n" not in str(e.value)
    return str(e.value)


# --- OpenPose -----------------------------------------------------------------------------------------


def test_openpose_folder(tmp_path):
    a, b = person(BODY_25, 300, 50, 600), person(BODY_25, 900, 200, 300)
    a[19] = 0  # LBigToe not detected: OpenPose writes 0, 0, 0
    for n in (7, 8, 9):
        people = [a + [n, 0, 0], b] if n != 8 else []  # frame 8: nobody
        _openpose_file(tmp_path, f"clip_{n:012d}_keypoints.json", people)
    (tmp_path / "notes.txt").write_text("not a keypoint file")
    det = read_keypoints(tmp_path)
    assert det.keypoint_set == "BODY_25"  # inferred: MidHip lies between the hips
    assert det.frames.tolist() == [7, 8, 9]
    assert det.people.shape == (3, 2, 25, 3)
    assert det.present.tolist() == [[True, True], [False, False], [True, True]]
    np.testing.assert_allclose(det.people[0, 0, 8], a[8] + [7, 0, 0], atol=1e-3)
    np.testing.assert_allclose(det.people[2, 1, :, :2], b[:, :2], atol=1e-3)
    assert np.isnan(det.people[0, 0, 19, :2]).all() and det.people[0, 0, 19, 2] == 0
    assert np.isnan(det.people[1]).all()  # padding: nobody
    assert (det.track_ids == -1).all() and det.fps is None and det.source == str(tmp_path)


def test_openpose_person_ids_and_fps(tmp_path):
    for n in range(3):
        _openpose_file(tmp_path, f"cam.{n:04d}.json", [person(BODY_25B, 100, 10, 400)], ids=[4])
    det = read_keypoints(tmp_path, fps=60)
    assert det.keypoint_set == "BODY_25B" and det.fps == 60.0
    assert det.track_ids[:, 0].tolist() == [4, 4, 4]


def test_openpose_single_file(tmp_path):
    f = _openpose_file(tmp_path, "frame_000012_keypoints.json", [person(BODY_25B, 0, 0, 500)])
    det = read_keypoints(f)
    assert det.frames.tolist() == [12] and det.people.shape == (1, 1, 25, 3)


def test_shipped_real_frames():
    det = read_keypoints(SHIPPED_FRAMES)
    assert det.keypoint_set == "BODY_25B"
    assert det.frames.tolist() == [2, 3, 4, 5]
    assert det.people.shape == (4, 3, 25, 3)
    # the people of frame 2 as the file has them, missing keypoints (0, 0, 0) as NaN, NaN, 0
    people = json.loads((SHIPPED_FRAMES / "cam01.0002.json").read_text())["people"]
    for i, p in enumerate(people):
        expected = np.array(p["pose_keypoints_2d"]).reshape(25, 3)
        expected[expected[:, 2] == 0] = (np.nan, np.nan, 0)
        np.testing.assert_array_equal(det.people[0, i], expected)


@pytest.mark.parametrize("trial, people", [("balancing", 3), ("two_people", 4)])
def test_pose2sim_folders(trial, people):
    det = read_keypoints(pose2sim(f"{trial}/pose/cam01_json"))
    assert det.keypoint_set == "BODY_25B"
    assert det.frames.tolist() == list(range(100))
    assert det.people.shape == (100, people, 25, 3)
    assert det.present.sum(1).min() >= 1


# --- COCO-style results (AlphaPose, Detectron) --------------------------------------------------------


def _coco_entry(image_id, kp, idx=None, category=1):
    e = {"image_id": image_id, "category_id": category, "keypoints": np.asarray(kp).ravel().tolist(), "score": 2.5}
    if idx is not None:
        e["idx"] = idx
    return e


def test_coco_results_with_track_idx(tmp_path):
    a, b = person(COCO_17, 100, 20, 500), person(COCO_17, 600, 200, 250)
    a[3:5] = 0  # ears not seen: score 0
    entries = [_coco_entry(0, a, idx=5), _coco_entry(0, b, idx=2), _coco_entry(1, a, idx=5)]
    entries.append(_coco_entry(1, b * 0 + 1, category=2))  # not a person: skipped
    entries.append(_coco_entry(3, b, idx=2))  # image 2 had nobody: the file has no entry
    det = read_keypoints(_write(tmp_path / "alphapose-results.json", entries))
    assert det.keypoint_set == "COCO_17" and det.frames.tolist() == [0, 1, 3]
    assert det.track_ids.tolist() == [[5, 2], [5, -1], [2, -1]]
    assert det.people[0, 0, 3, 2] == 0 and np.isnan(det.people[0, 0, 3, 0])
    np.testing.assert_allclose(det.people[2, 0], b)


def test_coco_results_image_names_halpe_and_wholebody(tmp_path):
    h = [_coco_entry(f"frames/img_{n:05d}.jpg", person(HALPE_26, 10, 10, 300)) for n in (10, 11)]
    det = read_keypoints(_write(tmp_path / "halpe.json", h), format="alphapose")
    assert det.keypoint_set == "HALPE_26" and det.frames.tolist() == [10, 11]
    full = np.concatenate([person(WHOLEBODY, 10, 10, 300), np.full((110, 3), 7.0)])  # face and hands after
    det = read_keypoints(_write(tmp_path / "wholebody.json", [_coco_entry(0, full)]))
    assert det.keypoint_set == "COCO_WHOLEBODY" and det.people.shape == (1, 1, 23, 3)
    np.testing.assert_allclose(det.people[0, 0], full[:23])


# --- MMPose -------------------------------------------------------------------------------------------


def _mmpose_instance(kp, track=None):
    inst = {"keypoints": kp[:, :2].tolist(), "keypoint_scores": kp[:, 2].tolist(), "bbox": [[0, 0, 1, 1]]}
    if track is not None:
        inst["track_id"] = track
    return inst


def test_mmpose_predictions_with_meta_info(tmp_path):
    full = np.concatenate([person(WHOLEBODY, 50, 50, 400), np.ones((110, 3))])
    frames = [{"frame_id": n, "instances": [_mmpose_instance(full + [n, 0, 0])]} for n in (1, 2, 3)]
    frames[1]["instances"] = []
    data = {"meta_info": {"dataset_name": "coco_wholebody", "num_keypoints": 133}, "instance_info": frames}
    det = read_keypoints(_write(tmp_path / "results_video.json", data))
    assert det.keypoint_set == "COCO_WHOLEBODY"
    assert det.frames.tolist() == [1, 2, 3] and det.present[:, 0].tolist() == [True, False, True]
    np.testing.assert_allclose(det.people[2, 0, :, 0], full[:23, 0] + 3)


def test_mmpose_plain_list_and_single_image(tmp_path):
    h = person(H36M_17, 0, 0, 700)
    frames = [{"frame_id": n, "instances": [_mmpose_instance(h, track=1)]} for n in range(4)]
    det = read_keypoints(_write(tmp_path / "frames.json", frames))
    assert det.keypoint_set == "H36M_17" and det.track_ids[:, 0].tolist() == [1, 1, 1, 1]
    det = read_keypoints(_write(tmp_path / "image.json", [_mmpose_instance(person(COCO_17, 0, 0, 300))]))
    assert det.keypoint_set == "COCO_17" and det.frames.tolist() == [0]


def _mmpose_image_file(folder, image, instances):
    """One image's predictions as MMPoseInferencer(pred_out_dir=...) writes them for image input
    (base_mmpose_inferencer.py postprocess: `<image stem>.json` holding split_instances' list, `bbox` as
    [[x1, y1, x2, y2]] and a `bbox_score`; `[]` for an image without anyone)."""
    items = []
    for kp in instances:
        x, y = kp[:, 0], kp[:, 1]
        items.append(
            {
                "keypoints": kp[:, :2].tolist(),
                "keypoint_scores": kp[:, 2].tolist(),
                "bbox": [[float(x.min()), float(y.min()), float(x.max()), float(y.max())]],
                "bbox_score": 0.98,
            }
        )
    (folder / f"{image}.json").write_text(json.dumps(items, indent=2))


def test_mmpose_per_image_folder(tmp_path):
    folder = tmp_path / "predictions"
    folder.mkdir()
    for n in (3, 4, 5, 7):  # frame 6 not written, frame 5 without anyone; a bystander in frame 4
        people = [] if n == 5 else [person(COCO_17, 10 * n, 0, 300)]
        if n == 4:
            people.append(person(COCO_17, 600, 0, 150, score=0.5))
        _mmpose_image_file(folder, f"frame_{n:06d}", people)
    (folder / "notes.txt").write_text("not a prediction")
    det = read_keypoints(folder)
    assert det.keypoint_set == "COCO_17" and det.frames.tolist() == [3, 4, 5, 7]
    assert det.present.sum(-1).tolist() == [1, 2, 0, 1]
    np.testing.assert_allclose(det.people[3, 0], person(COCO_17, 70, 0, 300))
    assert read_keypoints(folder, format="mmpose").frames.tolist() == [3, 4, 5, 7]
    with pytest.raises(InputError, match=r"frame_000003.json \(frame 3\): not an OpenPose keypoint file \(a list"):
        read_keypoints(folder, format="openpose")
    _openpose_file(folder, "frame_000008.json", [person(COCO_17, 0, 0, 300)])  # one file of another detector
    with pytest.raises(InputError, match=r"frame_000008\.json \(frame 8\): not MMPose's predictions of one image"):
        read_keypoints(folder)
    (folder / "frame_000008.json").unlink()
    video = [{"frame_id": 0, "instances": []}]  # a video's predictions file does not belong in the folder
    (folder / "frame_000009.json").write_text(json.dumps(video))
    with pytest.raises(InputError, match=r"frame_000009\.json \(frame 9\): not one image's MMPose instances"):
        read_keypoints(folder)


# --- MediaPipe, npz -----------------------------------------------------------------------------------


def test_mediapipe_landmarks_round_trip(tmp_path):
    T = 5
    lm = np.stack([person(MEDIAPIPE, 100 + t, 40, 800, score=0.8) for t in range(T)])
    lm[2] = np.nan  # no person detected in frame 2
    world = np.random.default_rng(0).normal(0, 0.3, (T, 33, 3))
    world[2] = np.nan
    m = MediaPipeLandmarks(np.arange(10, 10 + T), lm, world, fps=30, width=1920, height=1080, video="a.mp4")
    path = write_mediapipe_landmarks(tmp_path / "clip.mediapipe.npz", m)
    assert [p.name for p in tmp_path.iterdir()] == ["clip.mediapipe.npz"]  # nothing left beside it
    m = read_mediapipe_landmarks(path)
    np.testing.assert_allclose(m.world_landmarks, world, atol=1e-6)
    assert (m.width, m.height, m.fps, m.video) == (1920, 1080, 30.0, "a.mp4")
    det = read_keypoints(path)  # inferred from world_landmarks
    assert det.keypoint_set == "MEDIAPIPE_33" and det.frames.tolist() == [10, 11, 12, 13, 14]
    assert det.present[:, 0].tolist() == [True, True, False, True, True]
    assert det.image_size == (1920, 1080) and det.video == "a.mp4" and det.fps == 30.0
    np.testing.assert_allclose(det.people[3, 0], lm[3], atol=1e-3)


def test_write_mediapipe_rejects_bad_shapes(tmp_path):
    with pytest.raises(InputError, match="shape"):
        bad = MediaPipeLandmarks(np.arange(3), np.zeros((3, 17, 3)), np.zeros((3, 17, 3)), 30, 10, 10, "")
        write_mediapipe_landmarks(tmp_path / "x.npz", bad)
    assert not list(tmp_path.iterdir())


def test_npz_arrays(tmp_path):
    T = 6
    kp = np.stack([person(H36M_17, t, 0, 600)[:, :2] for t in range(T)])
    kp[1, 3] = np.nan  # a missing point
    scores = np.full((T, 17), 0.7)
    scores[1, 3] = 0
    np.savez(tmp_path / "a.npz", keypoints=kp, scores=scores, frames=np.arange(100, 100 + T), fps=np.float64(50))
    det = read_keypoints(tmp_path / "a.npz")
    assert det.keypoint_set == "H36M_17" and det.fps == 50.0 and det.frames[0] == 100
    assert det.people.shape == (T, 1, 17, 3) and det.people[1, 0, 3, 2] == 0.0 and det.people[0, 0, 3, 2] == 0.7
    # the only array, (T, K, 3), given fps wins over the file's
    np.savez(tmp_path / "b.npz", poses=np.stack([person(COCO_17, 0, 0, 300)] * T))
    det = read_keypoints(tmp_path / "b.npz", fps=25)
    assert det.keypoint_set == "COCO_17" and det.fps == 25.0 and det.frames.tolist() == list(range(T))
    # ptrack's own observation npz names its keypoints (ptrack.body.keypoints.H36M17)
    np.savez(tmp_path / "c.npz", keypoints=kp, confidence=scores, keypoint_names=np.array(H36M_17.other_names))
    assert read_keypoints(tmp_path / "c.npz", format="npz").keypoint_set == "H36M_17"
    # (T, K, 2) without scores: a finite point has weight 1, a NaN one is missing
    np.savez(tmp_path / "d.npz", keypoints=kp)
    det = read_keypoints(tmp_path / "d.npz")
    assert det.people[1, 0, 3, 2] == 0 and (np.delete(det.people[..., 2].ravel(), 1 * 17 + 3) == 1).all()


# --- bad input: one line naming the file and the first bad frame ---------------------------------------


def test_error_missing_path(tmp_path):
    _one_line_error("keypoint file not found: .*nope", tmp_path / "nope")


def test_error_folder_without_keypoint_files(tmp_path):
    (tmp_path / "readme.txt").write_text("x")
    _one_line_error(r"no keypoint files \(\*\.json\) in the folder", tmp_path)


def test_error_malformed_json_names_the_file(tmp_path):
    _openpose_file(tmp_path, "c.0000.json", [person(BODY_25B, 0, 0, 300)])
    (tmp_path / "c.0001.json").write_text('{"people": [{"pose_keypoints_2d": [1, 2, ')
    _one_line_error(r"c\.0001\.json: malformed JSON \(line 1", tmp_path)
    (tmp_path / "results.json").write_text('[{"image_id": 0, "keypoints": [1, 2, 0.5,]}]')
    _one_line_error(r"results\.json: malformed JSON", tmp_path / "results.json")


def test_error_keypoint_list_not_triplets(tmp_path):
    p = person(BODY_25B, 0, 0, 300).ravel().tolist()
    _openpose_file(tmp_path, "c.0000.json", [np.array(p)])
    _write(tmp_path / "c.0001.json", {"people": [{"person_id": [-1], "pose_keypoints_2d": p[:-1]}]})
    msg = _one_line_error("74 values, not a whole number of", tmp_path)
    assert "c.0001.json (frame 1): person 0" in msg


def test_error_count_differs_between_people(tmp_path):
    _coco_entry_list = [_coco_entry(0, person(COCO_17, 0, 0, 300)), _coco_entry(4, person(BODY_25B, 0, 0, 300))]
    msg = _one_line_error(
        "frame 4: person 0 has 25 keypoints, earlier people have 17", _write(tmp_path / "r.json", _coco_entry_list)
    )
    assert "r.json" in msg


def test_error_count_does_not_match_the_given_set(tmp_path):
    _openpose_file(tmp_path, "c.0003.json", [person(BODY_25B, 0, 0, 300)])
    _one_line_error(
        r"c\.0003\.json \(frame 3\): person 0 has 25 keypoints .* COCO_17 has 17", tmp_path, keypoint_set="COCO_17"
    )
    np.savez(tmp_path / "k.npz", keypoints=np.zeros((4, 17, 2)) + 5)
    _one_line_error("k.npz: 17 keypoints a person, but BODY_25 has 25", tmp_path / "k.npz", keypoint_set="BODY_25")


def test_error_non_finite_with_positive_score(tmp_path):
    frames = [{"frame_id": n, "instances": [_mmpose_instance(person(COCO_17, 0, 0, 300))]} for n in range(3)]
    frames[2]["instances"][0]["keypoints"][5] = [float("nan"), 3.0]
    path = tmp_path / "mm.json"
    path.write_text(json.dumps(frames))  # json writes NaN as the bare literal NaN, which it reads back
    _one_line_error(
        r"mm\.json: frame 2: person 0, keypoint 5 \(left_shoulder\).*x, y, score = nan, 3\.0, 0\.9: not finite", path
    )


def test_error_no_person_in_any_frame(tmp_path):
    for n in range(3):
        _openpose_file(tmp_path, f"c.{n:04d}.json", [])
    _one_line_error("no person in any frame", tmp_path)
    _one_line_error("no person in any frame", _write(tmp_path / "empty.json", []))
    _one_line_error("no person in any frame", _write(tmp_path / "mm.json", {"meta_info": {}, "instance_info": []}))
    cars = [_coco_entry(0, person(COCO_17, 0, 0, 300), category=3)]
    _one_line_error("no person in any frame", _write(tmp_path / "cars.json", cars))
    zeros = np.zeros((25, 3))
    _one_line_error(
        "no person in any frame", _write(tmp_path / "z.json", [_coco_entry(0, zeros)]), keypoint_set="BODY_25"
    )


def test_error_unknown_format_and_set(tmp_path):
    f = _write(tmp_path / "r.json", [_coco_entry(0, person(COCO_17, 0, 0, 300))])
    _one_line_error(
        r"unknown keypoint file format 'openpifpaf' \(known: openpose, coco, mmpose, mediapipe, npz\)",
        f,
        format="openpifpaf",
    )
    _one_line_error("unknown keypoint set 'coco_18'", f, keypoint_set="coco_18")
    _one_line_error("cannot tell the keypoint file format", _write(tmp_path / "o.json", {"foo": 1}))


def test_error_ambiguous_count_asks_for_the_set(tmp_path):
    p = person(BODY_25B, 0, 0, 300)
    p[[0, 1, 2, 8, 9], 2] = 0
    _openpose_file(tmp_path, "c.0000.json", [p])
    _one_line_error("could be BODY_25B or BODY_25 .*give the keypoint set", tmp_path)
    assert read_keypoints(tmp_path, keypoint_set="BODY_25B").keypoint_set == "BODY_25B"


def test_error_frame_number_twice(tmp_path):
    _openpose_file(tmp_path, "a_0001.json", [person(BODY_25B, 0, 0, 300)])
    _openpose_file(tmp_path, "b_1.json", [person(BODY_25B, 0, 0, 300)])
    _one_line_error(r"b_1\.json \(frame 1\): frame 1 appears twice", tmp_path)


def test_error_names_the_first_bad_frame_in_frame_order(tmp_path):
    bad = person(COCO_17, 0, 0, 300)
    bad[2, 0] = np.inf
    entries = [_coco_entry(9, bad), _coco_entry(3, bad), _coco_entry(1, person(COCO_17, 0, 0, 300))]
    _one_line_error(r"r\.json: frame 3: person 0, keypoint 2 \(right_eye\)", _write(tmp_path / "r.json", entries))


def test_track_ids_that_are_not_ids_are_dropped(tmp_path, caplog):
    a, b = person(COCO_17, 0, 0, 300), person(COCO_17, 600, 0, 300)
    entries = [_coco_entry(0, a, idx=0), _coco_entry(0, b, idx=0), _coco_entry(1, a, idx=0)]
    det = read_keypoints(_write(tmp_path / "r.json", entries))
    assert (det.track_ids == -1).all()
    assert "two people have the same track id" in caplog.text
