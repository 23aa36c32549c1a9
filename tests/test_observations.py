import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from ptrack.body.keypoints import make_keypoints
from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.errors import InputError
from ptrack.observe.camera import Camera, camera_for_motion, look_at
from ptrack.observe.observations import ChannelConfig, Observations, SimulationInfo, simulate_observations

DATA = Path(__file__).resolve().parents[1] / "ptrack" / "data"

NAMES = ("pelvis", "lknee", "rknee", "lwrist", "rwrist", "head")
PAIRS = ((1, 2), (3, 4))
FPS = 30.0


def _figure(T: int, dtype=torch.float32) -> torch.Tensor:
    """(T, 6, 3) a small stick figure swaying around (0, 1, 0), metres, Y up."""
    rest = torch.tensor(
        [[0.0, 1.0, 0.0], [0.15, 0.5, 0.0], [-0.15, 0.5, 0.0]] + [[0.4, 1.0, 0.1], [-0.4, 1.0, 0.1], [0.0, 1.7, 0.0]],
        dtype=dtype,
    )
    phase = torch.arange(T, dtype=dtype)[:, None, None] / FPS
    sway = torch.cat([0.1 * phase.sin(), 0.02 * (2 * phase).cos(), 0.1 * phase.sin()], dim=-1)
    return rest + sway


def _camera() -> Camera:
    return look_at((0.0, 1.0, 0.0), 4.0, 20.0, 5.0, 500.0, 320, 240)


def _simulate(T=60, channel=ChannelConfig(), seed=0, dtype=torch.float32, joints=None, pairs=PAIRS, **kw):
    joints = _figure(T, dtype) if joints is None else joints
    times = torch.arange(joints.shape[0], dtype=dtype) / FPS
    g = torch.Generator().manual_seed(seed)
    return simulate_observations(joints, torch.arange(6), _camera(), times, channel, g, NAMES, pairs, **kw)


def _runs(column: torch.Tensor) -> list[tuple[int, int]]:
    """(start, length) of each run of True in a 1-D bool tensor."""
    runs, start = [], None
    for i, x in enumerate(column.tolist() + [False]):
        if x and start is None:
            start = i
        elif not x and start is not None:
            runs.append((start, i - start))
            start = None
    return runs


def _same(a: torch.Tensor, b: torch.Tensor) -> bool:
    return bool(((a == b) | (a.isnan() & b.isnan())).all())


@pytest.fixture(scope="module")
def kick():
    """The bundled CMU clip 10_02 (590 frames at 120 fps): world joints in float64, keypoints, camera."""
    skeleton = Skeleton.from_asf(DATA / "10.asf")
    q = load_amc(DATA / "10_02.amc", skeleton).q.double()
    joints = skeleton.forward_kinematics(q)
    camera = camera_for_motion(joints, 6.0, 30.0, 10.0, 1000.0, 640, 480)
    return {"joints": joints, "kps": make_keypoints(skeleton), "camera": camera}


def _simulate_kick(kick, channel, dtype=torch.float64, seed=0):
    joints = kick["joints"].to(dtype)
    times = torch.arange(joints.shape[0], dtype=dtype) / 120.0
    kps = kick["kps"]
    g = torch.Generator().manual_seed(seed)
    return simulate_observations(joints, kps.index(), kick["camera"], times, channel, g, kps.names, kps.swap_pairs)


# -- simulate_observations ------------------------------------------------------------------------


def test_smoke_shapes_and_types():
    obs, info = _simulate(T=40, channel=ChannelConfig(missing=0.2, outliers=0.1))
    assert isinstance(obs, Observations) and isinstance(info, SimulationInfo)
    assert obs.keypoints.shape == (40, 6, 2) and obs.confidence.shape == (40, 6)
    assert obs.times.shape == (40,)
    assert obs.keypoint_names == NAMES and obs.num_frames == 40 and obs.num_keypoints == 6
    assert set(obs.confidence.unique().tolist()) <= {0.0, 1.0}
    assert info.projected.shape == (40, 6, 2) and info.dropped.shape == (40,)
    for m in (info.visible, info.deleted, info.occluded, info.outlier_mask, info.swapped):
        assert m.shape == (40, 6) and m.dtype == torch.bool
    # missing entries are NaN, kept ones finite
    assert bool(obs.keypoints[obs.confidence == 0].isnan().all())
    assert bool(obs.keypoints[obs.confidence == 1].isfinite().all())


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_noiseless_channel_gives_exact_projections(dtype):
    obs, info = _simulate(channel=ChannelConfig(noise_px=0.0), dtype=dtype)
    assert obs.keypoints.dtype == dtype and obs.confidence.dtype == dtype and obs.camera.dtype == dtype
    expected = _camera().to(dtype=dtype).project(_figure(60, dtype)).pixels
    assert bool((obs.confidence == 1).all())
    torch.testing.assert_close(obs.keypoints, expected, rtol=0, atol=1e-4)
    assert not info.outlier_mask.any() and not info.deleted.any() and not info.occluded.any()


def test_noise_has_requested_std():
    obs, info = _simulate(T=200, channel=ChannelConfig(noise_px=3.0))
    err = obs.keypoints - info.projected
    assert abs(err.std().item() - 3.0) < 0.15
    assert abs(err.mean().item()) < 0.15


def test_same_seed_same_observations_other_seed_differs():
    ch = ChannelConfig(noise_px=2.0, missing=0.2, occlusion_bursts=0.5, dropped_frames=0.1, outliers=0.1)
    a, ia = _simulate(channel=ch, seed=7)
    b, ib = _simulate(channel=ch, seed=7)
    c, _ = _simulate(channel=ch, seed=8)
    assert _same(a.keypoints, b.keypoints) and torch.equal(a.confidence, b.confidence)
    assert torch.equal(ia.outlier_mask, ib.outlier_mask) and torch.equal(ia.occluded, ib.occluded)
    assert not _same(a.keypoints, c.keypoints)
    assert not torch.equal(a.confidence, c.confidence)


def test_changing_one_rate_keeps_the_other_draws():
    a, _ = _simulate(channel=ChannelConfig(noise_px=2.0), seed=3)
    b, ib = _simulate(channel=ChannelConfig(noise_px=2.0, missing=0.3), seed=3)
    kept = b.confidence == 1
    assert bool(ib.deleted.any())
    torch.testing.assert_close(a.keypoints[kept], b.keypoints[kept], rtol=0, atol=0)


def test_missing_fraction_close_to_rate():
    obs, info = _simulate(T=600, channel=ChannelConfig(missing=0.3))
    # 3600 entries: binomial std ~0.008, allow 4 sigma
    assert abs(info.deleted.double().mean().item() - 0.3) < 0.035
    assert torch.equal(obs.confidence == 0, info.deleted)


def test_occlusion_bursts_are_contiguous_runs():
    lo, hi = 5, 12
    T = 900  # 30 s at 30 fps, 0.1 bursts/s -> 3 bursts per keypoint expected
    ch = ChannelConfig(noise_px=0.0, occlusion_bursts=0.1, burst_frames=(lo, hi))
    obs, info = _simulate(T=T, channel=ch)
    assert torch.equal(obs.confidence == 0, info.occluded)
    runs = [r for k in range(6) for r in _runs(info.occluded[:, k])]
    assert 8 <= len(runs) <= 32  # Poisson(18) total, minus rare overlaps
    for start, length in runs:
        if start + length < T:  # not clipped by the end of the clip
            assert length >= lo
        assert length <= 2 * hi or start + length == T  # overlaps of a few bursts at most
    assert sum(length <= hi for _, length in runs) >= 0.8 * len(runs)


def test_no_bursts_for_a_single_frame_or_zero_rate():
    _, info = _simulate(T=1, channel=ChannelConfig(occlusion_bursts=5.0))
    assert not info.occluded.any()
    _, info = _simulate(T=50, channel=ChannelConfig(occlusion_bursts=0.0))
    assert not info.occluded.any()


def test_dropped_frames_drop_whole_frames():
    obs, info = _simulate(T=400, channel=ChannelConfig(dropped_frames=0.25))
    assert bool(info.dropped.any()) and abs(info.dropped.double().mean().item() - 0.25) < 0.09
    assert bool((obs.confidence[info.dropped] == 0).all())
    assert bool((obs.confidence[~info.dropped] == 1).all())


def test_outlier_fraction_and_displacement_magnitude():
    ch = ChannelConfig(noise_px=0.0, outliers=0.3, outlier_px=40.0, swap_fraction=0.0)
    obs, info = _simulate(T=300, channel=ch)
    assert abs(info.outlier_mask.double().mean().item() - 0.3) < 0.04
    assert not info.swapped.any()
    assert bool((obs.confidence[info.outlier_mask] == 1).all())  # outliers look like detections
    dist = (obs.keypoints - info.projected).norm(dim=-1)
    d_out = dist[info.outlier_mask]
    assert bool((d_out >= 20.0 - 1e-3).all()) and bool((d_out <= 60.0 + 1e-3).all())
    assert bool((dist[~info.outlier_mask] < 1e-3).all())
    # uniform directions: mean unit displacement near zero
    unit = (obs.keypoints - info.projected)[info.outlier_mask] / d_out[:, None]
    assert unit.mean(0).norm().item() < 0.15


def test_swaps_exchange_left_right_partners():
    ch = ChannelConfig(noise_px=0.0, outliers=1.0, swap_fraction=1.0)
    obs, info = _simulate(T=20, channel=ch)
    assert bool(info.outlier_mask.all())
    assert bool(info.swapped[:, [1, 2, 3, 4]].all()) and not info.swapped[:, [0, 5]].any()
    for a, b in PAIRS:
        torch.testing.assert_close(obs.keypoints[:, a], info.projected[:, b])
        torch.testing.assert_close(obs.keypoints[:, b], info.projected[:, a])
    # unpaired keypoints fall back to random displacements
    dist = (obs.keypoints[:, [0, 5]] - info.projected[:, [0, 5]]).norm(dim=-1)
    assert bool((dist >= 24.9).all())


def test_swap_share_of_outliers():
    # swap_fraction is the share of *all* outliers that are swaps, though only 4 of 6 keypoints
    # have a partner; the outliers stay spread evenly over the keypoints (0.5 <= 4/6)
    ch = ChannelConfig(noise_px=0.0, outliers=0.5, swap_fraction=0.5)
    _, info = _simulate(T=400, channel=ch)  # 2400 entries, ~1200 outliers: share std ~0.015
    share = info.swapped.sum().item() / info.outlier_mask.sum().item()
    assert abs(share - 0.5) < 0.06
    assert not (info.swapped & ~info.outlier_mask).any()
    assert not info.swapped[:, [0, 5]].any()
    per_keypoint = info.outlier_mask.double().mean(0)
    assert bool(((per_keypoint - 0.5).abs() < 0.1).all()), per_keypoint


def test_all_outliers_are_swaps_when_partners_suffice():
    # swap_fraction 1 with 4 of 6 keypoints paired: the outliers are drawn on paired keypoints only
    ch = ChannelConfig(noise_px=0.0, outliers=0.5, swap_fraction=1.0)
    _, info = _simulate(T=400, channel=ch)
    assert torch.equal(info.swapped, info.outlier_mask)
    assert abs(info.outlier_mask.double().mean().item() - 0.5) < 0.05


def test_without_partners_outliers_keep_their_rate_as_displacements():
    ch = ChannelConfig(noise_px=0.0, outliers=0.3, swap_fraction=0.5)
    _, info = _simulate(T=400, channel=ch, pairs=())
    assert not info.swapped.any()
    assert abs(info.outlier_mask.double().mean().item() - 0.3) < 0.04


@pytest.mark.parametrize("outliers, swap_fraction", [(0.2, 0.0), (0.3, 0.2), (0.3, 0.5), (0.3, 1.0), (0.6, 0.8)])
def test_realised_swap_share_and_outlier_rate_on_real_clip(kick, outliers, swap_fraction):
    """The CMU kick, 17 keypoints (6 left/right pairs, 5 unpaired), 30% missing: 590 frames give
    ~7000 kept keypoints, so the share of swaps among outliers has std < 0.015."""
    ch = ChannelConfig(noise_px=2.0, missing=0.3, outliers=outliers, swap_fraction=swap_fraction)
    obs, info = _simulate_kick(kick, ch)
    kept = obs.confidence > 0
    n_out = info.outlier_mask.sum().item()
    assert abs(n_out / kept.sum().item() - outliers) < 0.025
    share = info.swapped.sum().item() / n_out
    assert abs(share - swap_fraction) < 0.04, f"swap share {share:.3f}, set {swap_fraction}"
    paired = torch.zeros(len(kick["kps"].names), dtype=torch.bool)
    paired[[i for pair in kick["kps"].swap_pairs for i in pair]] = True
    assert not info.swapped[:, ~paired].any()
    assert not (info.outlier_mask & ~kept).any()


@pytest.mark.parametrize("missing", [0.0, 0.5])
def test_outlier_rate_is_a_fraction_of_kept_keypoints(kick, missing):
    """`outliers` is the share of delivered detections (kept keypoints) that are wrong, whatever the
    deletion rate: 30% of the kept keypoints, not 30% of the visible ones."""
    ch = ChannelConfig(noise_px=2.0, missing=missing, dropped_frames=0.1, outliers=0.3, swap_fraction=0.5)
    obs, info = _simulate_kick(kick, ch)
    kept = obs.confidence > 0
    assert abs(info.outlier_mask.sum().item() / kept.sum().item() - 0.3) < 0.025
    assert bool(info.outlier_mask.any()) and not (info.outlier_mask & ~kept).any()


def test_float32_and_float64_give_the_same_observations(kick):
    ch = ChannelConfig(noise_px=2.0, missing=0.3, occlusion_bursts=0.5, dropped_frames=0.1, outliers=0.2)
    a, ia = _simulate_kick(kick, ch, dtype=torch.float32, seed=5)
    b, ib = _simulate_kick(kick, ch, dtype=torch.float64, seed=5)
    assert a.keypoints.dtype == torch.float32 and b.keypoints.dtype == torch.float64
    for name in ("visible", "deleted", "occluded", "dropped", "outlier_mask", "swapped"):
        assert torch.equal(getattr(ia, name), getattr(ib, name)), name
    assert torch.equal(a.confidence.double(), b.confidence)
    kept = b.confidence > 0
    assert (a.keypoints.double() - b.keypoints)[kept].abs().max().item() < 1e-3
    assert bool(a.keypoints[~kept].isnan().all()) and bool(b.keypoints[~kept].isnan().all())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_inputs_with_cpu_generator_match_cpu():
    ch = ChannelConfig(noise_px=2.0, missing=0.2, occlusion_bursts=0.5, outliers=0.2)
    a, ia = _simulate(channel=ch, seed=2)
    joints = _figure(60).cuda()
    g = torch.Generator().manual_seed(2)
    times = torch.arange(60.0).cuda() / FPS
    b, ib = simulate_observations(joints, torch.arange(6), _camera(), times, ch, g, NAMES, PAIRS)
    for x in (b.keypoints, b.confidence, b.times, *ib):
        assert x.device == joints.device
    assert torch.equal(ia.outlier_mask, ib.outlier_mask.cpu()) and torch.equal(a.confidence, b.confidence.cpu())
    assert (a.keypoints - b.keypoints.cpu())[a.confidence > 0].abs().max().item() < 1e-3


def test_points_behind_camera_or_outside_image_get_confidence_zero():
    joints = _figure(10)
    cam = _camera()
    behind = cam.center + 1.0 * (cam.center - torch.tensor([0.0, 1.0, 0.0]))  # 1 m behind the camera
    joints[:, 5] = behind
    joints[:5, 0] = torch.tensor([30.0, 1.0, 0.0])  # far to the side: outside the image
    obs, info = _simulate(joints=joints, channel=ChannelConfig(noise_px=0.0))
    assert bool((obs.confidence[:, 5] == 0).all()) and not info.visible[:, 5].any()
    assert bool((obs.confidence[:5, 0] == 0).all()) and bool((obs.confidence[5:, 0] == 1).all())
    assert bool(obs.keypoints[:, 5].isnan().all())


def test_camera_seeing_nothing_raises():
    cam = _camera()
    behind = cam.center + (cam.center - torch.tensor([0.0, 1.0, 0.0]))
    joints = behind + 0.1 * torch.randn(5, 6, 3, generator=torch.Generator().manual_seed(0))
    with pytest.raises(InputError, match="sees none"):
        _simulate(joints=joints)


def test_deleting_everything_raises():
    # the validator catches observations that end up empty after deletion
    with pytest.raises(InputError, match="sees none"):
        _simulate(T=3, channel=ChannelConfig(dropped_frames=0.999))


def test_masks_pass_through():
    masks = torch.zeros(10, 240, 320, dtype=torch.bool)
    masks[:, 100:140, 150:170] = True
    obs, _ = _simulate(T=10, masks=masks)
    assert torch.equal(obs.masks, masks)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"keypoint_index": [0, 1, 9, 3, 4, 5]}, "keypoint_index"),
        ({"keypoint_index": [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]}, "keypoint_index"),
        ({"times": torch.arange(5.0)}, "times"),
        ({"keypoint_names": ("a", "b")}, "keypoint_names"),
        ({"swap_pairs": ((1, 1),)}, "swap_pairs"),
        ({"swap_pairs": ((1, 2), (2, 3))}, "swap_pairs"),
        ({"swap_pairs": ((1, 7),)}, "swap_pairs"),
        ({"joints": torch.zeros(10, 6, 2)}, "joints"),
    ],
)
def test_simulate_rejects_bad_inputs(kwargs, match):
    args = {
        "joints": _figure(10),
        "keypoint_index": torch.arange(6),
        "camera": _camera(),
        "times": torch.arange(10.0) / FPS,
        "channel": ChannelConfig(),
        "generator": torch.Generator().manual_seed(0),
        "keypoint_names": NAMES,
        "swap_pairs": PAIRS,
    }
    args.update(kwargs)
    with pytest.raises(InputError, match=match):
        simulate_observations(**args)


def test_gradcheck_keypoints_wrt_joints():
    joints = _figure(3, torch.float64).requires_grad_(True)

    def f(j):
        obs, _ = simulate_observations(
            j,
            torch.arange(6),
            _camera(),
            torch.arange(3.0) / FPS,
            ChannelConfig(noise_px=1.0),
            torch.Generator().manual_seed(0),
            NAMES,
        )
        return obs.keypoints

    assert torch.autograd.gradcheck(f, (joints,))


# -- ChannelConfig --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "field, value",
    [
        ("noise_px", -1.0),
        ("noise_px", math.inf),
        ("missing", 1.0),
        ("missing", -0.1),
        ("occlusion_bursts", -1.0),
        ("burst_frames", (0, 5)),
        ("burst_frames", (6, 5)),
        ("burst_frames", (5,)),
        ("burst_frames", (5.0, 6.0)),
        ("dropped_frames", 1.0),
        ("outliers", 1.5),
        ("outlier_px", -2.0),
        ("swap_fraction", math.nan),
        ("swap_fraction", "half"),
    ],
)
def test_channel_config_rejects_bad_fields(field, value):
    with pytest.raises(InputError, match=f"ChannelConfig.{field}"):
        ChannelConfig(**{field: value})


def test_channel_config_accepts_burst_list():
    assert ChannelConfig(burst_frames=[3, 4]).burst_frames == (3, 4)


# -- Observations validation ----------------------------------------------------------------------


def _fields(T=4, K=3):
    return {
        "keypoints": torch.full((T, K, 2), 10.0),
        "confidence": torch.ones(T, K),
        "times": torch.arange(T, dtype=torch.float32) / FPS,
        "camera": _camera(),
        "keypoint_names": ("a", "b", "c")[:K],
    }


def test_frame_interval_is_the_median_step():
    f = _fields()
    f["times"] = torch.tensor([0.0, 0.1, 0.2, 0.5])  # one dropped-frame gap does not move the median
    assert Observations(**f).frame_interval == pytest.approx(0.1)
    one = {k: (v[:1] if isinstance(v, torch.Tensor) else v) for k, v in _fields().items()}
    assert Observations(**one).frame_interval == pytest.approx(1 / 30)


def test_observations_accepts_nan_where_missing_and_converts():
    f = _fields()
    f["keypoints"][1, 2] = math.nan
    f["confidence"][1, 2] = 0.0
    f["keypoint_names"] = ["a", "b", "c"]
    f["times"] = np.arange(4) / FPS
    obs = Observations(**f)
    assert obs.keypoint_names == ("a", "b", "c") and obs.times.dtype == torch.float32
    obs64 = obs.to(dtype=torch.float64)
    assert obs64.keypoints.dtype == torch.float64 and obs64.camera.dtype == torch.float64


@pytest.mark.parametrize(
    "change, match",
    [
        ({"keypoints": torch.zeros(4, 3, 3)}, r"keypoints.*\(T, K, 2\).*\(4, 3, 3\)"),
        ({"confidence": torch.ones(4, 2)}, r"confidence.*\(4, 3\).*\(4, 2\)"),
        ({"times": torch.arange(5.0)}, r"times.*\(4,\).*\(5,\)"),
        ({"keypoint_names": ("a", "b")}, "keypoint_names"),
        ({"keypoint_names": "abc"}, "keypoint_names"),
        ({"camera": {"K": 1}}, "camera"),
        ({"confidence": torch.full((4, 3), 1.5)}, r"confidence.*\[0, 1\]"),
        ({"confidence": torch.full((4, 3), -0.5)}, r"confidence.*\[0, 1\]"),
        ({"confidence": torch.zeros(4, 3)}, "sees none"),
        ({"times": torch.tensor([0.0, 0.1, 0.1, 0.2])}, "strictly increasing"),
        ({"times": torch.tensor([0.0, 0.2, 0.1, 0.3])}, "strictly increasing"),
        ({"masks": torch.zeros(4, 10, 10, dtype=torch.bool)}, r"masks.*\(4, 240, 320\)"),
        ({"masks": torch.zeros(4, 240, 320)}, "masks must be bool"),
    ],
)
def test_observations_validation(change, match):
    f = _fields()
    f.update(change)
    with pytest.raises(InputError, match=match):
        Observations(**f)


def test_observations_rejects_nan_where_visible():
    f = _fields()
    f["keypoints"][2, 1, 0] = math.inf
    with pytest.raises(InputError, match=r"NaN/inf.*frame 2, keypoint 1 \('b'\)"):
        Observations(**f)


# -- npz files ------------------------------------------------------------------------------------


def test_npz_round_trip(tmp_path):
    masks = torch.zeros(30, 240, 320, dtype=torch.bool)
    masks[:, 50:90, 100:120] = True
    obs, _ = _simulate(T=30, channel=ChannelConfig(missing=0.2), dtype=torch.float64, masks=masks)
    path = tmp_path / "detections.kp"  # no .npz suffix: written exactly here
    obs.save_npz(path)
    assert path.is_file()
    back = Observations.load_npz(path)
    assert back.keypoints.dtype == torch.float64
    assert _same(back.keypoints, obs.keypoints) and torch.equal(back.confidence, obs.confidence)
    assert torch.equal(back.times, obs.times) and torch.equal(back.masks, masks)
    assert back.keypoint_names == NAMES
    assert torch.equal(back.camera.K, obs.camera.K) and torch.equal(back.camera.R, obs.camera.R)
    assert (back.camera.width, back.camera.height) == (320, 240)


def _write(path, **arrays):
    with open(path, "wb") as f:
        np.savez(f, **arrays)
    return path


def _plain_arrays():
    cam = _camera()
    return {
        "keypoints": np.full((5, 3, 2), 7.0, dtype=np.float32),
        "confidence": np.ones((5, 3), dtype=np.float32),
        "times": np.arange(5) / FPS,
        "keypoint_names": np.array(["a", "b", "c"]),
        "camera": np.array(json.dumps(cam.to_dict())),
    }


def test_load_user_file_with_camera_arrays_and_uint8_masks(tmp_path):
    arrays = _plain_arrays()
    cam = arrays.pop("camera")
    d = json.loads(str(cam))
    arrays.update({key: np.array(d[key]) for key in ("K", "R", "t", "width", "height")})
    arrays["masks"] = np.zeros((5, 240, 320), dtype=np.uint8)
    arrays["masks"][:, 10:20, 10:20] = 255
    obs = Observations.load_npz(_write(tmp_path / "user.npz", **arrays))
    assert obs.keypoints.dtype == torch.float32 and obs.camera.dtype == torch.float32
    assert obs.masks.dtype == torch.bool and obs.masks.sum().item() == 5 * 100
    torch.testing.assert_close(obs.camera.K, _camera().K)


def test_load_with_camera_argument(tmp_path):
    arrays = _plain_arrays()
    del arrays["camera"]
    path = _write(tmp_path / "nocam.npz", **arrays)
    with pytest.raises(InputError, match=r"nocam.npz.*camera"):
        Observations.load_npz(path)
    cam = look_at((0.0, 0.0, 0.0), 3.0, 0.0, 0.0, 400.0, 320, 240)
    obs = Observations.load_npz(path, camera=cam)
    torch.testing.assert_close(obs.camera.t, cam.t)


@pytest.mark.parametrize(
    "change, match",
    [
        ({"keypoints": None}, "missing key 'keypoints'"),
        ({"confidence": None}, "missing key 'confidence'"),
        ({"times": None}, "missing key 'times'"),
        ({"keypoint_names": None}, "missing key 'keypoint_names'"),
        ({"keypoints": np.array(["x"] * 30).reshape(5, 3, 2)}, "'keypoints' must be a numeric"),
        ({"keypoint_names": np.arange(3)}, "'keypoint_names' must be a 1-D string"),
        ({"camera": np.array("{not json")}, "'camera' is not valid JSON"),
        ({"camera": np.array(json.dumps({"K": [1]}))}, "camera dict"),
        ({"camera": np.arange(3)}, "'camera' must be a JSON string"),
        ({"confidence": np.ones((5, 4))}, r"confidence.*\(5, 3\)"),
        ({"masks": np.zeros((5, 240, 320))}, "'masks' must be bool or integer"),
        ({"times": np.zeros(5)}, "strictly increasing"),
    ],
)
def test_load_rejects_malformed_files(tmp_path, change, match):
    arrays = _plain_arrays()
    for key, value in change.items():
        if value is None:
            del arrays[key]
        else:
            arrays[key] = value
    path = _write(tmp_path / "bad.npz", **arrays)
    with pytest.raises(InputError, match=r"bad\.npz") as exc:
        Observations.load_npz(path)
    assert exc.match(match)


def test_load_rejects_non_npz_files(tmp_path):
    with pytest.raises(InputError, match="not found"):
        Observations.load_npz(tmp_path / "missing.npz")
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"\x00\x01 not a zip archive at all")
    with pytest.raises(InputError, match=r"garbage\.npz"):
        Observations.load_npz(garbage)
    single = tmp_path / "single.npy"
    np.save(single, np.zeros(3))
    with pytest.raises(InputError, match=r"not an \.npz"):
        Observations.load_npz(single)
    pickled = tmp_path / "pickled.npz"
    _write(pickled, **{**_plain_arrays(), "keypoint_names": np.array([{"a": 1}] * 3, dtype=object)})
    with pytest.raises(InputError, match=r"pickled\.npz"):
        Observations.load_npz(pickled)
