"""The view a user opens (ptrack.io.viz's blueprint and scene) and scripts/screenshot.py.

The recording is read back with rerun.chunk.RrdReader: the data store, and the blueprint store that
`write_recording` puts in the same .rrd.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import subprocess
import sys
import uuid
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import rerun.chunk
import torch

from ptrack.errors import InputError
from ptrack.io.viz import IMAGE_PLANE_FRACTION, RunLog, _keypoint_bones, plot_groups, write_recording
from ptrack.observe.camera import Camera

ROOT = Path(__file__).resolve().parents[1]
T, J, N, W, H = 6, 5, 3, 80, 60

# which view classes draw an archetype (2D archetypes also show in a 3D view through a pinhole)
VIEW_CLASSES = {
    "Scalars": {"TimeSeries"},
    "Points3D": {"3D"},
    "LineStrips3D": {"3D"},
    "Arrows3D": {"3D"},
    "ViewCoordinates": {"3D"},
    "Transform3D": {"3D"},
    "Pinhole": {"3D", "2D"},
    "Points2D": {"2D", "3D"},
    "LineStrips2D": {"2D", "3D"},
    "SegmentationImage": {"2D", "3D"},
    "AnnotationContext": {"2D", "3D"},
    "AssetVideo": {"2D", "3D"},
    "VideoFrameReference": {"2D", "3D"},
}
CAM01 = ROOT / ".." / "shared" / "data" / "pose2sim" / "balancing" / "videos" / "cam01.mp4"


def _camera() -> Camera:
    """Looking at (0, 1, 0) from (3, 1.5, 3), world Y up."""
    center = np.array([3.0, 1.5, 3.0])
    forward = np.array([0.0, 1.0, 0.0]) - center
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    R = np.stack([right, np.cross(forward, right), forward])
    K = np.array([[70.0, 0.0, W / 2], [0.0, 70.0, H / 2], [0.0, 0.0, 1.0]])
    return Camera(K=K, R=R, t=-R @ center, width=W, height=H)


def _log(full: bool = True) -> RunLog:
    """A chain of J joints; keypoints on joints 0, 2, 4 (so keypoint bones skip joints 1 and 3)."""
    rng = np.random.default_rng(0)
    base = np.stack([np.zeros(J), np.linspace(0.2, 1.6, J), np.zeros(J)], axis=-1)
    estimate = base + 0.03 * rng.standard_normal((T, J, 3))
    camera = _camera()
    kp = [0, 2, 4]
    reprojected = camera.project(torch.as_tensor(estimate[:, kp])).pixels.numpy()
    confidence = np.ones((T, 3))
    confidence[2, 1] = 0.0  # frame 2: the middle keypoint is missing -> no observed bone that frame
    kw = {}
    if full:
        weights = np.tile([0.5, 0.3, 0.2], (T, 1))
        weights[:, 2] = np.nan  # h2 has no finite weight: not logged, not plotted
        kw = dict(
            hypotheses=estimate[:, None] + 0.05 * rng.standard_normal((T, N, J, 3)),
            hypothesis_weights=weights,
            hypothesis_costs=np.tile([1.0, 2.0, 3.0], (T, 1)),
            hypothesis_directions=0.01 * rng.standard_normal((T, N, J, 3)),
            jumps={"larm": np.arange(T), "rleg": np.ones(T)},
            masks=np.zeros((T, H, W), dtype=bool),
            ground_truth=base[None].repeat(T, 0),
        )
    return RunLog(
        joint_names=tuple(f"j{i}" for i in range(J)),
        parents=(-1,) + tuple(range(J - 1)),
        frames=np.arange(T) * 4 + 1,
        times=np.arange(T) * 4 / 120.0,
        estimate=estimate,
        ground_truth=kw.pop("ground_truth", None),
        camera=camera,
        observed=reprojected + rng.standard_normal(reprojected.shape),
        confidence=confidence,
        reprojected=reprojected,
        keypoint_names=("pelvis", "spine", "head"),
        keypoint_joints=kp,
        scalars={
            "mpjpe_mm": np.linspace(10, 20, T),
            "pa_mpjpe_mm": np.linspace(5, 9, T),
            "reprojection_error_px": np.ones(T),
            "flip_error_rate": np.zeros(T),
            "accel_error_mm_per_frame2": np.r_[np.nan, np.ones(T - 2), np.nan],
            "cost": np.ones(T),
            "cost_smooth": np.ones(T),
            "never": np.full(T, np.nan),
            "custom_score": np.arange(T, dtype=float),
            "jitter_mm_per_frame2": np.r_[np.nan, np.ones(T - 2), np.nan],  # real footage's checks
            "foot_skating_mm_per_frame": np.r_[np.nan, np.ones(T - 1)],
            "ambiguous_frame": np.ones(T),
            "person_missing": np.zeros(T),
            "left_right_exchanged": np.zeros(T),
        },
        **kw,
    )


class Recording:
    """An .rrd read back: per entity of the data store, its archetypes and its rows (static rows
    as one dict, temporal rows in order); the blueprint store's views and containers."""

    def __init__(self, path: Path):
        reader = rerun.chunk.RrdReader(path)
        self.archetypes: dict[str, set[str]] = defaultdict(set)
        self.static: dict[str, dict] = defaultdict(dict)
        self.rows: dict[str, list[dict]] = defaultdict(list)
        for chunk in reader.stream().to_chunks():
            entity = chunk.entity_path.lstrip("/")
            batch = chunk.to_record_batch()
            names = [n for n in batch.schema.names if ":" in n]
            self.archetypes[entity] |= {n.split(":")[0] for n in names}
            if chunk.is_static:
                self.static[entity].update({n: batch.column(n).to_pylist()[-1] for n in names})
            else:
                cols = {n: batch.column(n).to_pylist() for n in names + ["frame"] if n in batch.schema.names}
                self.rows[entity] += [{n: v[i] for n, v in cols.items()} for i in range(chunk.num_rows)]
        for rows in self.rows.values():
            rows.sort(key=lambda r: r.get("frame") or 0)
        self.blueprints = reader.blueprints()
        parts: dict[str, dict] = defaultdict(dict)
        for entry in self.blueprints:
            for chunk in reader.stream(store=entry).to_chunks():
                batch = chunk.to_record_batch()
                for n in batch.schema.names:
                    if ":" in n:
                        parts[chunk.entity_path.lstrip("/")][n.split(":", 1)[1]] = batch.column(n).to_pylist()[-1]
        self.parts = parts
        self.views = {
            path: dict(part, **parts.get(f"{path}/ViewContents", {}))
            for path, part in parts.items()
            if "class_identifier" in part
        }

    @property
    def root(self) -> str:
        """The viewport's root container, as a blueprint entity path."""
        return "container/" + str(uuid.UUID(bytes=bytes(self.parts["viewport"]["root_container"][0])))

    def component(self, entity: str, name: str) -> list:
        return [r[name] for r in self.rows[entity] if r.get(name) is not None]

    def reachable_views(self) -> list[dict]:
        """The views in the viewport's container tree, depth first."""
        out, stack = [], [self.root]
        while stack:
            node = stack.pop(0)
            if node.startswith("view/"):
                out.append(dict(self.views[node], id=node))
            else:
                stack[:0] = self.parts[node]["contents"]
        return out


def _matches(view: dict, entity: str) -> bool:
    """Rerun's query semantics: the most specific matching rule wins (exact > subtree, then longer),
    the last of equally specific ones; no match = excluded."""
    origin = view["space_origin"][0].strip("/")
    best = None
    for rule in view["query"]:
        rule = rule.strip()
        include = not rule.startswith("-")
        path = rule.lstrip("+-").strip().replace("$origin", "/" + origin).strip("/")
        subtree = path.endswith("/**") or path == "**"
        path = path.removesuffix("**").rstrip("/") if subtree else path
        hit = entity == path or (subtree and (path == "" or entity.startswith(path + "/")))
        if hit:
            rank = (path.count("/") + (path != ""), not subtree)
            if best is None or rank >= best[0]:
                best = (rank, include)
    return bool(best and best[1])


@pytest.fixture(scope="module")
def full(tmp_path_factory) -> tuple[RunLog, Recording]:
    log = _log(full=True)
    path = tmp_path_factory.mktemp("view") / "run.rrd"
    write_recording(path, log)
    return log, Recording(path)


def test_blueprint_is_stored_with_the_recording(full):
    _, rec = full
    assert [b.application_id for b in rec.blueprints] == ["ptrack"]
    assert rec.parts["time_panel"]["timeline"] == ["time"]  # plays at the real rate
    assert rec.parts["viewport"]["auto_views"] == [False]  # no extra views spawned beside ours
    views = rec.reachable_views()
    assert len(views) == len(rec.views)  # every view is placed in the layout
    # the 3D scene, a 3D close-up and the camera view side by side, the plots under them
    assert [(v["class_identifier"][0], v["space_origin"][0]) for v in views[:3]] == [
        ("3D", "/world"),
        ("3D", "/world"),
        ("2D", "/world/camera"),
    ]
    assert {v["class_identifier"][0] for v in views[3:]} == {"TimeSeries"}
    scene, closeup = views[0], views[1]
    assert _matches(scene, "world/camera") and not _matches(closeup, "world/camera/image/observed")
    assert _matches(closeup, "world/hypotheses/h1/bones") and not _matches(closeup, "world/legend")
    assert rec.parts[f"{closeup['id']}/EyeControls3D"]["tracking_entity"] == ["/world/estimate/joints"]
    root = rec.parts[rec.root]
    assert root["row_shares"][0] > root["row_shares"][1]  # the top row (3D + camera) is the larger


def test_scene_viewpoint_sees_the_person_and_the_camera(full):
    log, rec = full
    eye = rec.parts[f"{rec.reachable_views()[0]['id']}/EyeControls3D"]
    position, target = np.array(eye["position"][0]), np.array(eye["look_target"][0])
    camera = -log.camera.R.numpy().T @ log.camera.t.numpy()
    ahead = (target - position) / np.linalg.norm(target - position)
    for point in [camera, *log.estimate.reshape(-1, 3)]:  # the camera and every joint of every frame
        to = (point - position) / np.linalg.norm(point - position)
        assert np.degrees(np.arccos(np.clip(to @ ahead, -1, 1))) < 25  # inside the field of view
    assert np.linalg.norm(camera - position) > 1.0


@pytest.mark.parametrize("full_log", [True, False, "video"])
def test_every_logged_entity_is_in_a_view(tmp_path, full_log):
    log = _log(full=bool(full_log))
    if full_log == "video":
        if not CAM01.is_file():
            pytest.skip(f"Pose2Sim demo video not found at {CAM01.resolve()}")
        log = dataclasses.replace(log, video=str(CAM01), video_frames=np.arange(T))
    # a whole-sequence solver's uncertainty and cost per iteration (on its own timeline)
    log = dataclasses.replace(log, solver_cost=np.array([9.0, 5.0, 4.0]), joint_std=np.full((T, J), 0.02))
    write_recording(tmp_path / "run.rrd", log)
    rec = Recording(tmp_path / "run.rrd")
    views = rec.reachable_views()
    missing = []
    for entity, archetypes in rec.archetypes.items():
        archetypes = archetypes & set(VIEW_CLASSES)
        if not archetypes or entity == "world":
            continue  # nothing to draw (e.g. the recording's properties); `world`: view coordinates
        kinds = set.intersection(*(VIEW_CLASSES[a] for a in archetypes))
        if not any(v["class_identifier"][0] in kinds and _matches(v, entity) for v in views):
            missing.append(entity)
    assert not missing
    assert "metrics/never" not in rec.archetypes  # all NaN: neither logged nor plotted


def test_video_is_under_the_points_in_the_camera_view(tmp_path):
    """The camera's 2D view holds the video and draws it under every 2D point and line of the image."""
    if not CAM01.is_file():
        pytest.skip(f"Pose2Sim demo video not found at {CAM01.resolve()}")
    write_recording(tmp_path / "run.rrd", dataclasses.replace(_log(), video=str(CAM01), video_frames=np.arange(T)))
    rec = Recording(tmp_path / "run.rrd")
    camera_view = next(v for v in rec.reachable_views() if v["class_identifier"][0] == "2D")
    assert camera_view["display_name"] == ["camera: video, observed and reprojected keypoints"]
    video = "world/camera/image/video"
    assert _matches(camera_view, video) and {"AssetVideo", "VideoFrameReference"} <= rec.archetypes[video]
    under = rec.static[video]["VideoFrameReference:draw_order"][0]
    others = {
        e: s[k][0]
        for e, s in rec.static.items()
        for k in s
        if e.startswith("world/camera/image/") and e != video and k.endswith(":draw_order") and s[k]
    }
    assert len(others) >= 4 and all(under < order for order in others.values()), (under, others)


def test_plot_groups_cover_each_scalar_once(full):
    log, rec = full
    groups = dict(plot_groups(log))
    plotted = [e for entities in groups.values() for e in entities]
    scalars = {e for e, a in rec.archetypes.items() if "Scalars" in a}
    assert sorted(plotted) == sorted(scalars)  # each logged scalar in exactly one plot, none empty
    assert groups["joint position error (mm)"] == ["metrics/mpjpe_mm", "metrics/pa_mpjpe_mm"]
    assert groups["cost and its terms"] == ["metrics/cost", "metrics/cost_smooth"]
    assert groups["hypothesis weights"] == ["world/hypotheses/h0/weight", "world/hypotheses/h1/weight"]
    assert groups["kinematic jumps kept per chain"] == ["jumps/larm", "jumps/rleg"]
    assert groups["other metrics"] == ["metrics/custom_score"]
    assert groups["jitter (mm/frame²)"] == ["metrics/jitter_mm_per_frame2"]
    assert groups["foot skating (mm/frame)"] == ["metrics/foot_skating_mm_per_frame"]
    assert groups["ambiguous limbs, labels exchanged, person missing (0/1, share)"] == [
        "metrics/ambiguous_frame",
        "metrics/person_missing",
        "metrics/left_right_exchanged",
    ]
    titles = {v["display_name"][0]: v["query"] for v in rec.reachable_views()}
    assert titles["hypothesis costs"] == [f"+ /world/hypotheses/h{n}/cost" for n in range(N)]


def test_camera_image_plane_border_and_2d_bones(full):
    log, rec = full
    center = -log.camera.R.numpy().T @ log.camera.t.numpy()
    person = log.estimate.reshape(-1, 3).mean(axis=0)
    plane = rec.static["world/camera"]["Pinhole:image_plane_distance"][0]
    np.testing.assert_allclose(plane, IMAGE_PLANE_FRACTION * np.linalg.norm(person - center), rtol=1e-5)
    border = np.array(rec.static["world/camera/image/border"]["LineStrips2D:strips"][0])
    np.testing.assert_allclose(border, [[0, 0], [W, 0], [W, H], [0, H], [0, 0]])
    # keypoints on joints 0, 2, 4 of a chain: bones (0, 1) and (1, 2) in keypoint indices
    assert _keypoint_bones(log.parents, log.keypoint_joints).tolist() == [[0, 1], [1, 2]]
    observed = rec.component("world/camera/image/observed_bones", "LineStrips2D:strips")
    assert [len(s) for s in observed] == [2, 2, 0, 2, 2, 2]  # frame 2 misses the middle keypoint
    np.testing.assert_allclose(observed[0][1], log.observed[0, [1, 2]], atol=1e-4)
    reprojected = rec.component("world/camera/image/reprojected_bones", "LineStrips2D:strips")
    assert [len(s) for s in reprojected] == [2] * T
    np.testing.assert_allclose(reprojected[3][0], log.reprojected[3, [0, 1]], atol=1e-4)


def test_observed_and_reprojected_told_apart_labels_on_hover(full):
    _, rec = full
    obs, rep = rec.static["world/camera/image/observed"], rec.static["world/camera/image/reprojected"]
    assert obs["Points2D:radii"][0] > rep["Points2D:radii"][0]  # observed larger, under
    assert obs["Points2D:colors"] != rep["Points2D:colors"]
    assert obs["Points2D:draw_order"] < rep["Points2D:draw_order"]
    assert obs["Points2D:show_labels"] == rep["Points2D:show_labels"] == [False]
    assert rec.component("world/camera/image/observed", "Points2D:labels")[2] == ["pelvis", "head"]
    assert rec.static["world/hypotheses/h0/bones"]["LineStrips3D:show_labels"] == [False]


def test_legends_name_what_is_drawn(full, tmp_path):
    log, rec = full
    legend = rec.static["world/legend"]
    assert legend["Points3D:labels"] == ["estimate", "ground truth", "hypotheses"]
    assert legend["Points3D:show_labels"] == [True]
    top = log.estimate[..., 1].max()
    assert all(p[1] > top for p in legend["Points3D:positions"])  # above the person
    colors = {name: c for name, c in zip(legend["Points3D:labels"], legend["Points3D:colors"])}
    assert colors["estimate"] == rec.static["world/estimate/joints"]["Points3D:colors"][0]
    assert colors["ground truth"] == rec.static["world/ground_truth/joints"]["Points3D:colors"][0]
    image = rec.static["world/camera/image/legend"]
    assert image["Points2D:labels"] == ["observed", "reprojected estimate"]
    assert all(0 < x < W and 0 < y < H for x, y in image["Points2D:positions"])
    write_recording(tmp_path / "min.rrd", _log(full=False))
    assert Recording(tmp_path / "min.rrd").static["world/legend"]["Points3D:labels"] == ["estimate"]


@pytest.mark.parametrize("joints, needle", [((0, 2), "K=3"), ((0, 2, J), "outside")])
def test_bad_keypoint_joints(joints, needle):
    with pytest.raises(InputError, match=needle):
        dataclasses.replace(_log(full=False), keypoint_joints=joints)


def _vulkan_driver() -> bool:
    """Whether a Vulkan ICD (driver manifest) is installed where the loader looks for one."""
    if os.environ.get("VK_ICD_FILENAMES") or os.environ.get("VK_DRIVER_FILES"):
        return True
    dirs = ["/usr/share/vulkan/icd.d", "/etc/vulkan/icd.d", "/usr/local/share/vulkan/icd.d"]
    return any(Path(d).is_dir() and any(Path(d).glob("*.json")) for d in dirs)


@pytest.mark.skipif(shutil.which("rerun") is None, reason="no `rerun` executable on PATH")
@pytest.mark.skipif(not _vulkan_driver(), reason="no Vulkan driver (e.g. apt-get install mesa-vulkan-drivers)")
def test_screenshot_script_renders_the_view(tmp_path):
    write_recording(tmp_path / "run.rrd", _log(full=True))
    out = tmp_path / "shot.png"
    proc = subprocess.run(
        [
            sys.executable,
            str(ROOT / "scripts" / "screenshot.py"),
            str(tmp_path),
            str(out),
            "--time",
            "0.1",
            "--size",
            "962x601",
            "--timeout",
            "90",
        ],
        check=False,
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    from PIL import Image

    image = np.asarray(Image.open(out).convert("RGB")).astype(int)
    assert image.shape[:2] == (601, 962)
    # the viewer is gone with the script (`rerun` may be a launcher with the viewer as its child)
    ps = subprocess.run(["ps", "-eo", "args"], check=True, capture_output=True, text=True).stdout
    assert not [line for line in ps.splitlines() if "--headless" in line and "962x601" in line]

    def share(color, region):  # share of pixels within 40 of `color` in a region of the window
        return float((np.abs(region - np.asarray(color)).sum(-1) < 40).mean())

    top = image[: int(0.55 * 601)]
    # the estimate's orange and the observed keypoints' yellow are drawn in the top row's views
    assert share((255, 140, 30), top) > 1e-4
    assert share((255, 220, 0), top) > 1e-5
    # bad argument: no recording there
    bad = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "screenshot.py"), str(tmp_path / "none"), str(out)],
        check=False,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert bad.returncode == 2 and "no rerun recording" in bad.stderr
