"""Tests for ptrack.io.viz: write a synthetic run to .rrd, read it back with rerun.chunk.RrdReader."""

from __future__ import annotations

import dataclasses
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import rerun as rr
import rerun.chunk
import torch

from ptrack.errors import InputError
from ptrack.io.viz import RunLog, log_video, open_viewer, plot_groups, write_recording
from ptrack.observe.camera import Camera

T, J, N = 5, 4, 3
W, H = 64, 48


CENTER = np.array([3.0, 1.5, 3.0])


def _camera() -> Camera:
    """A look-at camera built by hand: at CENTER, looking at (0, 1, 0), world Y up."""
    forward = np.array([0.0, 1.0, 0.0]) - CENTER
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(forward, right), forward])  # rows: x right, y down, z forward
    K = np.array([[60.0, 0.0, W / 2], [0.0, 62.0, H / 2 + 1], [0.0, 0.0, 1.0]])
    return Camera(K=K, R=R, t=-R @ CENTER, width=W, height=H)


def _run_log(full: bool = True, frames: int = T, joints: int = J) -> RunLog:
    rng = np.random.default_rng(0)
    T_, J_ = frames, joints
    # a vertical chain of joints
    base = np.stack([np.zeros(J_), np.linspace(0.2, 1.6, J_), np.zeros(J_)], axis=-1)
    estimate = base + 0.05 * rng.standard_normal((T_, J_, 3))
    camera = _camera()
    reprojected = camera.project(torch.as_tensor(estimate)).pixels.numpy()
    observed = reprojected + rng.standard_normal(reprojected.shape)
    confidence = rng.uniform(0.2, 1.0, (T_, J_))
    if T_ >= 4 and J_ >= 4:
        confidence[1, 2] = 0.0
        confidence[3, [0, 3]] = 0.0
    kw = {}
    if full:
        hyp = estimate[:, None] + 0.1 * rng.standard_normal((T_, N, J_, 3))
        masks = np.zeros((T_, H, W), dtype=bool)
        masks[:, 10:40, 20:30] = True
        masks[2] = False
        kw = dict(
            hypotheses=hyp,
            hypothesis_weights=np.tile([0.6, 0.3, 0.1], (T_, 1)),
            hypothesis_costs=np.tile([1.0, 2.0, 3.5], (T_, 1)),
            hypothesis_directions=0.02 * rng.standard_normal((T_, N, J_, 3)),
            jumps={"larm": np.arange(T_), "rleg": np.zeros(T_, dtype=int)},
            masks=masks,
        )
    return RunLog(
        joint_names=tuple(f"j{i}" for i in range(J_)),
        parents=(-1,) + tuple(range(J_ - 1)),
        frames=np.arange(T_) * 4 + 10,
        times=np.arange(T_) * 4 / 120.0,
        estimate=estimate,
        ground_truth=base[None].repeat(T_, 0) if full else None,
        camera=camera,
        observed=observed,
        confidence=confidence,
        reprojected=reprojected,
        keypoint_names=tuple(f"k{i}" for i in range(J_)),
        scalars={
            "mpjpe": np.where(np.arange(T_) == 1, np.nan, 0.1 * np.arange(1, T_ + 1)),
            "cost": np.arange(T_, dtype=float),
        },
        **kw,
    )


class Rec:
    """Read-back of an .rrd: temporal rows sorted by frame, and static values, per entity."""

    def __init__(self, path: Path):
        self.temporal: dict[str, list[dict]] = defaultdict(list)
        self.static: dict[str, dict] = defaultdict(dict)
        for chunk in rerun.chunk.RrdReader(path).stream().to_chunks():
            entity = chunk.entity_path.lstrip("/")
            batch = chunk.to_record_batch()
            names = [n for n in batch.schema.names if n != "rerun.controls.RowId"]
            cols = {n: batch.column(n) for n in names}
            if chunk.is_static:
                for n in names:
                    self.static[entity][n] = cols[n].to_pylist()[-1]
                continue
            for i in range(chunk.num_rows):
                row = {n: (c[i].value if n == "time" else c[i].as_py()) for n, c in cols.items()}
                self.temporal[entity].append(row)
        for rows in self.temporal.values():
            rows.sort(key=lambda r: r["frame"] if "frame" in r else r["iteration"])

    @property
    def entities(self) -> set[str]:
        return set(self.temporal) | set(self.static)

    def column(self, entity: str, component: str) -> list:
        """Per-frame values of one component, rows without it skipped."""
        return [r[component] for r in self.temporal[entity] if r.get(component) is not None]


@pytest.fixture(scope="module")
def full(tmp_path_factory) -> tuple[RunLog, Rec]:
    log = _run_log(full=True)
    path = tmp_path_factory.mktemp("viz") / "run.rrd"
    write_recording(path, log)
    return log, Rec(path)


def test_entity_layout(full):
    _, rec = full
    expected = (
        {
            "world",
            "world/camera",
            "world/ground_truth/joints",
            "world/ground_truth/bones",
            "world/estimate/joints",
            "world/estimate/bones",
            "world/camera/image/observed",
            "world/camera/image/reprojected",
            "world/camera/image/silhouette",
            "metrics/mpjpe",
            "metrics/cost",
        }
        | {f"world/hypotheses/h{n}/{c}" for n in range(N) for c in ("bones", "weight", "cost", "direction")}
        | {"jumps/larm", "jumps/rleg"}
    )
    assert expected <= rec.entities
    assert not any(e.startswith("world/hypotheses/h3") for e in rec.entities)
    assert rec.static["world"]["ViewCoordinates:xyz"] == [
        [d.value for d in rr.ViewCoordinates.RIGHT_HAND_Y_UP.coordinates]
    ]


def test_frame_and_time_timelines(full):
    log, rec = full
    rows = rec.temporal["world/estimate/joints"]
    assert len(rows) == T
    assert [r["frame"] for r in rows] == log.frames.tolist()
    np.testing.assert_allclose([r["time"] for r in rows], log.times * 1e9, atol=1.0)  # ns
    for entity in (
        "world/estimate/bones",
        "world/ground_truth/joints",
        "world/camera/image/observed",
        "world/camera/image/reprojected",
        "world/hypotheses/h1/bones",
    ):
        assert [r["frame"] for r in rec.temporal[entity]] == log.frames.tolist(), entity


def test_estimate_and_ground_truth_positions_roundtrip(full):
    log, rec = full
    est = np.array(rec.column("world/estimate/joints", "Points3D:positions"))
    np.testing.assert_allclose(est, log.estimate, atol=1e-6)  # stored as float32
    gt = np.array(rec.column("world/ground_truth/joints", "Points3D:positions"))
    np.testing.assert_allclose(gt, log.ground_truth, atol=1e-6)
    bones = np.array(rec.column("world/estimate/bones", "LineStrips3D:strips"))  # (T, B, 2, 3)
    assert bones.shape == (T, J - 1, 2, 3)
    np.testing.assert_allclose(bones[:, :, 0], log.estimate[:, :-1], atol=1e-6)  # parent end
    np.testing.assert_allclose(bones[:, :, 1], log.estimate[:, 1:], atol=1e-6)  # child end
    assert (
        rec.static["world/estimate/joints"]["Points3D:colors"]
        != rec.static["world/ground_truth/joints"]["Points3D:colors"]
    )


def test_camera_pose_and_pinhole(full):
    log, rec = full
    cam = rec.static["world/camera"]
    assert cam["Pinhole:resolution"] == [[W, H]]
    K = np.array(cam["Pinhole:image_from_camera"][0]).reshape(3, 3).T  # arrow stores column-major
    np.testing.assert_allclose(K, log.camera.K.numpy())
    assert cam["Pinhole:camera_xyz"] == [[d.value for d in rr.ViewCoordinates.RDF.coordinates]]
    # Transform3D maps camera coordinates to world: the camera origin lands on the camera centre,
    # and world points taken back into the camera through it project like Camera.project does.
    world_from_cam = np.array(cam["Transform3D:mat3x3"][0]).reshape(3, 3).T
    translation = np.array(cam["Transform3D:translation"][0])
    np.testing.assert_allclose(translation, CENTER, atol=1e-6)
    X = log.estimate[0]  # (J, 3)
    x_cam = (X - translation) @ world_from_cam  # inverse of x_world = M @ x_cam + translation
    pixels = x_cam @ K.T
    pixels = pixels[:, :2] / pixels[:, 2:]
    np.testing.assert_allclose(pixels, log.reprojected[0], atol=1e-3)


def test_missing_keypoints_not_drawn(full):
    log, rec = full
    positions = rec.column("world/camera/image/observed", "Points2D:positions")
    labels = rec.column("world/camera/image/observed", "Points2D:labels")
    for t in range(T):
        seen = np.nonzero(log.confidence[t] > 0)[0]
        assert labels[t] == [log.keypoint_names[k] for k in seen]
        np.testing.assert_allclose(positions[t], log.observed[t, seen], atol=1e-4)
    assert len(positions[1]) == J - 1 and "k2" not in labels[1]
    assert labels[3] == ["k1", "k2"]
    reproj = rec.column("world/camera/image/reprojected", "Points2D:positions")
    assert [len(p) for p in reproj] == [J] * T  # the estimate's projection is always drawn
    np.testing.assert_allclose(np.array(reproj), log.reprojected, atol=1e-4)


def test_metric_scalars(full):
    _log, rec = full
    rows = rec.temporal["metrics/mpjpe"]
    assert [r["frame"] for r in rows] == [10, 18, 22, 26]  # the NaN frame (14) is skipped
    np.testing.assert_allclose([r["Scalars:scalars"][0] for r in rows], [0.1, 0.3, 0.4, 0.5])
    cost = [r["Scalars:scalars"][0] for r in rec.temporal["metrics/cost"]]
    np.testing.assert_allclose(cost, np.arange(T))


def test_hypotheses(full):
    log, rec = full
    for n in range(N):
        bones = np.array(rec.column(f"world/hypotheses/h{n}/bones", "LineStrips3D:strips"))
        np.testing.assert_allclose(bones[:, :, 1], log.hypotheses[:, n, 1:], atol=1e-6)
        labels = rec.column(f"world/hypotheses/h{n}/bones", "LineStrips3D:labels")
        assert len(labels) == T and labels[0][0].startswith(f"h{n} ")
        assert f"cost={log.hypothesis_costs[0, n]:.4g}" in labels[0][0]
        weights = [r["Scalars:scalars"][0] for r in rec.temporal[f"world/hypotheses/h{n}/weight"]]
        np.testing.assert_allclose(weights, log.hypothesis_weights[:, n])
        costs = [r["Scalars:scalars"][0] for r in rec.temporal[f"world/hypotheses/h{n}/cost"]]
        np.testing.assert_allclose(costs, log.hypothesis_costs[:, n])
    first = [rec.temporal[f"world/hypotheses/h{n}/bones"][0] for n in range(N)]
    radii = [row["LineStrips3D:radii"][0] for row in first]
    alphas = [row["LineStrips3D:colors"][0] & 0xFF for row in first]  # packed RGBA
    assert radii[0] > radii[1] > radii[2] > 0  # weights 0.6 > 0.3 > 0.1
    assert alphas[0] == 255 and alphas[0] > alphas[1] > alphas[2]


def test_covariance_directions_and_jumps(full):
    log, rec = full
    for n in range(N):
        entity = f"world/hypotheses/h{n}/direction"
        origins = np.array(rec.column(entity, "Arrows3D:origins"))
        vectors = np.array(rec.column(entity, "Arrows3D:vectors"))
        np.testing.assert_allclose(origins, log.hypotheses[:, n], atol=1e-6)
        np.testing.assert_allclose(vectors, log.hypothesis_directions[:, n], atol=1e-6)
    larm = [r["Scalars:scalars"][0] for r in rec.temporal["jumps/larm"]]
    np.testing.assert_allclose(larm, np.arange(T))


def test_silhouette(full):
    log, rec = full
    buffers = rec.column("world/camera/image/silhouette", "SegmentationImage:buffer")
    assert len(buffers) == T
    got = np.array(buffers, dtype=np.uint8).reshape(T, H, W)
    np.testing.assert_array_equal(got, log.masks.astype(np.uint8))
    fmt = rec.static["world/camera/image/silhouette"]["SegmentationImage:format"][0]
    assert (fmt["width"], fmt["height"]) == (W, H)


def test_optional_parts_absent(tmp_path):
    log = _run_log(full=False)
    assert log.hypotheses is None and log.masks is None and log.ground_truth is None
    path = tmp_path / "minimal.rrd"
    write_recording(path, log)
    rec = Rec(path)
    assert {
        "world",
        "world/camera",
        "world/estimate/joints",
        "world/estimate/bones",
        "world/camera/image/observed",
        "metrics/mpjpe",
    } <= rec.entities
    assert not any(e.startswith(("world/ground_truth", "world/hypotheses")) for e in rec.entities)
    assert "world/camera/image/silhouette" not in rec.entities
    assert "world/camera/image/video" not in rec.entities  # no video given: none logged
    assert len(rec.temporal["world/estimate/joints"]) == T


def test_joint_std_and_solver_cost(tmp_path):
    """A batch solve's uncertainty (per-joint std as point radii at the estimate) and its cost per
    iteration on the `iteration` timeline."""
    std = np.linspace(0.01, 0.05, T * J).reshape(T, J)
    std[2, 1] = np.nan  # not finite: drawn with radius 0
    cost = np.array([50.0, 20.0, 9.0, 8.5])
    log = dataclasses.replace(_run_log(full=False), joint_std=std, solver_cost=cost)
    path = tmp_path / "batch.rrd"
    write_recording(path, log)
    rec = Rec(path)
    positions = np.array(rec.column("world/estimate/std", "Points3D:positions"))
    radii = np.array(rec.column("world/estimate/std", "Points3D:radii"))
    np.testing.assert_allclose(positions, log.estimate, atol=1e-6)
    np.testing.assert_allclose(radii, np.nan_to_num(std), atol=1e-7)
    rows = rec.temporal["solver/cost"]
    assert [r["iteration"] for r in rows] == [0, 1, 2, 3] and all("frame" not in r for r in rows)
    np.testing.assert_allclose([r["Scalars:scalars"][0] for r in rows], cost)
    with pytest.raises(InputError, match="joint_std"):
        dataclasses.replace(log, joint_std=np.ones((T, J + 1)))
    with pytest.raises(InputError, match="solver_cost"):
        dataclasses.replace(log, solver_cost=np.ones((2, 2)))


def test_single_joint_and_uniform_weights_and_torch_inputs(tmp_path):
    base = _run_log(full=True, joints=1)
    log = dataclasses.replace(
        base,
        parents=(-1,),
        hypothesis_weights=None,
        hypothesis_costs=None,
        estimate=torch.as_tensor(base.estimate, dtype=torch.float32),
        scalars={},
    )
    assert isinstance(log.estimate, np.ndarray) and log.estimate.dtype == np.float32
    path = tmp_path / "one.rrd"
    write_recording(path, log)
    rec = Rec(path)
    assert "world/estimate/bones" not in rec.entities  # no (parent, child) pairs
    assert "world/hypotheses/h0/cost" not in rec.entities
    weights = [r["Scalars:scalars"][0] for r in rec.temporal["world/hypotheses/h2/weight"]]
    np.testing.assert_allclose(weights, [1 / N] * T)
    np.testing.assert_allclose(
        np.array(rec.column("world/estimate/joints", "Points3D:positions")), base.estimate, atol=1e-6
    )


def test_global_recording_untouched(tmp_path):
    before = rr.get_global_data_recording()
    write_recording(tmp_path / "g.rrd", _run_log(full=False))
    assert rr.get_global_data_recording() is before


def test_motion_model_time_weights_and_key_postures(tmp_path):
    """The golf tracker's own output (method pca): normalised time and PCA weights as scalars in their own plots,
    the key postures as text at their frames."""
    weights = np.linspace(-1.0, 1.0, T * 2).reshape(T, 2)
    time = np.linspace(0.0, 1.0, T)
    log = dataclasses.replace(
        _run_log(full=False), motion_weights=weights, motion_time=time, key_postures={"top": 1, "end": T - 1}
    )
    path = tmp_path / "pca.rrd"
    write_recording(path, log)
    rec = Rec(path)
    np.testing.assert_allclose([r["Scalars:scalars"][0] for r in rec.temporal["pca/time"]], time)
    for i in range(2):
        got = [r["Scalars:scalars"][0] for r in rec.temporal[f"pca/weights/alpha{i}"]]
        np.testing.assert_allclose(got, weights[:, i])
    rows = rec.temporal["pca/key_postures"]
    assert [(r["frame"], r["TextLog:text"][0]) for r in rows] == [
        (int(log.frames[1]), "key posture top"),
        (int(log.frames[T - 1]), "key posture end"),
    ]
    groups = dict(plot_groups(log))
    assert groups["motion model: normalised time"] == ["pca/time"]
    assert groups["motion model: PCA weights"] == ["pca/weights/alpha0", "pca/weights/alpha1"]
    with pytest.raises(InputError, match="motion_weights"):
        dataclasses.replace(log, motion_weights=np.ones((T + 1, 2)))
    with pytest.raises(InputError, match="key_postures"):
        dataclasses.replace(log, key_postures={"top": T})


@pytest.mark.parametrize(
    "change, needle",
    [
        (dict(estimate=np.zeros((T, J + 1, 3))), "estimate"),
        (dict(times=np.zeros(T + 1)), "times"),
        (dict(confidence=np.zeros((T, J + 2))), "confidence"),
        (dict(parents=(-1, 0, 5, 2)), "parents[2]"),
        (dict(parents=(-1, 0)), "parents"),
        (dict(masks=np.zeros((T, H + 1, W), dtype=bool)), "masks"),
        (dict(hypothesis_weights=np.ones((T, N + 1))), "hypothesis_weights"),
        (dict(hypothesis_directions=np.ones((T, N, J, 2))), "hypothesis_directions"),
        (dict(jumps={"larm": np.ones(T + 1)}), "larm"),
        (dict(scalars={"mpjpe": np.zeros(T - 1)}), "mpjpe"),
        (dict(frames=np.zeros(0, dtype=int)), "frames"),
    ],
)
def test_bad_input_names_the_field(change, needle):
    with pytest.raises(InputError, match=needle.replace("[", r"\[").replace("]", r"\]")):
        dataclasses.replace(_run_log(full=True), **change)


def test_missing_paths(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"nope\.rrd"):
        open_viewer(tmp_path / "nope.rrd")
    with pytest.raises(FileNotFoundError, match="no_such_dir"):
        write_recording(tmp_path / "no_such_dir" / "x.rrd", _run_log(full=False))


def test_long_run_is_written(tmp_path):
    """600 frames x 31 joints with 8 hypotheses, logged column-wise (no timing here: timed assertions
    belong in benchmarks, not tests)."""
    base = _run_log(full=False, frames=600, joints=31)
    rng = np.random.default_rng(1)
    log = dataclasses.replace(
        base,
        hypotheses=base.estimate[:, None] + 0.01 * rng.standard_normal((600, 8, 31, 3)),
        hypothesis_weights=rng.uniform(size=(600, 8)),
        hypothesis_costs=rng.uniform(size=(600, 8)),
        scalars={"m": rng.uniform(size=600)},
    )
    write_recording(tmp_path / "long.rrd", log)
    assert (tmp_path / "long.rrd").stat().st_size > 600 * 31 * 3 * 4


CAM01 = (
    Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "pose2sim" / "balancing" / "videos" / "cam01.mp4"
)


def test_video_under_the_camera_view(tmp_path):
    """The Pose2Sim clip (60 fps) as a video asset, frames 10..19 shown on the run's `frame` and `time` rows."""
    if not CAM01.is_file():
        pytest.skip(f"Pose2Sim demo video not found at {CAM01.resolve()}")
    frames = np.arange(10, 20)
    path = tmp_path / "video.rrd"
    rec = rr.RecordingStream(application_id="ptrack")
    rec.save(path)
    index = [rr.TimeColumn("frame", sequence=frames + 100), rr.TimeColumn("time", duration=frames / 60.0)]
    assert log_video(rec, CAM01, frames, index) == 100
    rec.flush()
    rec.disconnect()
    got = Rec(path)
    static = got.static["world/camera/image/video"]
    assert bytes(static["AssetVideo:blob"][0]) == CAM01.read_bytes()
    assert static["AssetVideo:media_type"] == ["video/mp4"]
    assert static["VideoFrameReference:draw_order"] == [-20.0]  # under the keypoints and bones
    rows = got.temporal["world/camera/image/video"]
    assert [r["frame"] for r in rows] == list(range(110, 120))
    stamps = [r["VideoFrameReference:timestamp"] for r in rows]
    np.testing.assert_allclose(np.ravel(stamps), frames * 1e9 / 60, atol=1)  # the video's own 60 fps stamps, ns


def test_video_errors(tmp_path):
    rec = rr.RecordingStream(application_id="ptrack")
    index = [rr.TimeColumn("frame", sequence=[0, 1])]
    with pytest.raises(InputError, match=r"video not found: .*gone\.mp4"):
        log_video(rec, tmp_path / "gone.mp4", np.arange(2), index)
    text = tmp_path / "notes.mp4"
    text.write_text("not a video\n")
    with pytest.raises(InputError, match=r"cannot show video .*notes\.mp4"):
        log_video(rec, text, np.arange(2), index)
    with pytest.raises(InputError, match="integers"):
        log_video(rec, text, np.array([0.0, 1.0]), index)
    if CAM01.is_file():
        with pytest.raises(InputError, match=r"has 100 frames; frame numbers 99..100"):
            log_video(rec, CAM01, np.array([99, 100]), index)


def test_run_log_with_video(tmp_path):
    """RunLog.video: the file as an AssetVideo under the camera image, one VideoFrameReference per logged frame
    on the same `frame` and `time` rows as the 3D, pointing at RunLog.video_frames."""
    if not CAM01.is_file():
        pytest.skip(f"Pose2Sim demo video not found at {CAM01.resolve()}")
    video_frames = np.arange(T) * 2 + 3
    log = dataclasses.replace(_run_log(full=False), video=CAM01, video_frames=video_frames)
    assert log.video == str(CAM01)
    path = tmp_path / "video.rrd"
    write_recording(path, log)
    rec = Rec(path)
    static = rec.static["world/camera/image/video"]
    assert bytes(static["AssetVideo:blob"][0]) == CAM01.read_bytes()
    assert static["VideoFrameReference:draw_order"] == [-20.0]
    rows = rec.temporal["world/camera/image/video"]
    joints = rec.temporal["world/estimate/joints"]
    assert [r["frame"] for r in rows] == [r["frame"] for r in joints] == log.frames.tolist()
    assert [r["time"] for r in rows] == [r["time"] for r in joints]
    stamps = np.ravel([r["VideoFrameReference:timestamp"] for r in rows])
    np.testing.assert_allclose(stamps, video_frames * 1e9 / 60, atol=1)  # cam01 runs at 60 fps


def test_run_log_video_errors(tmp_path):
    log = _run_log(full=False)
    with pytest.raises(InputError, match="go together"):
        dataclasses.replace(log, video=str(CAM01))
    with pytest.raises(InputError, match="video_frames"):
        dataclasses.replace(log, video=str(CAM01), video_frames=np.arange(T + 1))
    with pytest.raises(InputError, match="video_frames must be frame numbers"):
        dataclasses.replace(log, video=str(CAM01), video_frames=np.arange(T) - 1)
    text = tmp_path / "notes.mp4"
    text.write_text("not a video\n")
    with pytest.raises(InputError, match=r"cannot show video .*notes\.mp4"):
        write_recording(tmp_path / "run.rrd", dataclasses.replace(log, video=str(text), video_frames=np.arange(T)))
    assert not (tmp_path / "run.rrd").exists()  # checked before the recording is started
