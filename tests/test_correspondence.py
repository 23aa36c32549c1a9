"""Point correspondences (ptrack/observe/correspondences.py, ptrack/observe/backprojection.py,
ptrack/costs/correspondence.py): the ray-capsule hit against brute force, the front capsule hit, simulated pairs
that reproject exactly with the true poses,
the npz layout's round trip, and bad files and settings as one `ptrack: error:` line, exit 2."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from cli_errors import fail

from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.costs.correspondence import reprojection_rows
from ptrack.errors import InputError
from ptrack.observe.backprojection import anchor_points, backproject, backproject_rays, ray_capsule_hit
from ptrack.observe.camera import camera_for_motion
from ptrack.observe.correspondences import Correspondences, simulate_correspondences
from ptrack.observe.silhouette import capsule_radii

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "ptrack" / "data"
DEMO = REPO / "configs" / "demo.yaml"
FAST = ["data.stop=48", "data.stride=4", "frame.iterations=15", "frame.first_iterations=60", "progress=false"]
F64 = torch.float64


def _brute_depth(origin, d, a, b, r, far=10.0, n=200_001) -> float:
    """First s on a fine grid along the ray where the point is inside the capsule, refined by bisection."""
    s = torch.linspace(0, far, n, dtype=F64)
    x = origin + s[:, None] * d
    e = b - a
    ee = float(e @ e) or 1.0  # a ball: u = 0
    u = ((x - a) @ e / ee).clamp(0, 1)
    inside = ((x - a - u[:, None] * e).norm(dim=-1) <= r).nonzero()
    if inside.numel() == 0:
        return float("inf")
    hi = float(s[inside[0, 0]])
    lo = hi - far / (n - 1)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        p = origin + mid * d
        um = float(((p - a) @ e / ee).clamp(0, 1))
        lo, hi = (lo, mid) if float((p - a - um * e).norm()) <= r else (mid, hi)
    return hi


def test_ray_capsule_hit_matches_brute_force():
    g = torch.Generator().manual_seed(0)
    origin = torch.zeros(3, dtype=F64)
    a = torch.randn(5, 3, generator=g, dtype=F64) * 0.4 + torch.tensor([0, 0, 4.0], dtype=F64)
    b = a + torch.randn(5, 3, generator=g, dtype=F64) * 0.3
    b[2] = a[2]  # a ball (zero-length segment)
    radii = torch.rand(5, generator=g, dtype=F64) * 0.1 + 0.05
    d = torch.randn(40, 3, generator=g, dtype=F64) * 0.1 + torch.tensor([0, 0, 1.0], dtype=F64)
    d = d / d.norm(dim=-1, keepdim=True)
    d[0] = (a[1] - origin) / (a[1] - origin).norm()  # straight at a segment end
    d[1] = (b[0] - a[0]) / (b[0] - a[0]).norm()  # parallel to a segment
    hit = ray_capsule_hit(origin, d, a, b, radii)
    assert hit.hit[0]
    for i in range(d.shape[0]):
        per_bone = [_brute_depth(origin, d[i], a[k], b[k], float(radii[k])) for k in range(5)]
        best = min(per_bone)
        if best == float("inf"):
            assert not hit.hit[i]
            continue
        assert hit.hit[i] and abs(float(hit.depth[i]) - best) < 1e-6, (i, float(hit.depth[i]), best)
        assert int(hit.bone[i]) == int(np.argmin(per_bone))
        torch.testing.assert_close(hit.point[i], origin + best * d[i], rtol=0, atol=1e-6)
    # batched: leading dims of the rays broadcast against the capsules'
    both = ray_capsule_hit(origin, d.expand(2, -1, -1), a[None, None], b[None, None], radii)
    assert both.depth.shape == (2, 40) and torch.equal(both.bone[1], hit.bone)


def test_backprojection_hits_the_front_capsule():
    """Two capsules on the line of sight: the nearer one is hit, from either side; the anchor is fixed in the
    hit capsule's end joint's frame."""
    cam = camera_for_motion(torch.zeros(1, 2, 3, dtype=F64), 5.0, 0.0, 0.0, 500.0, 200, 200)
    joints = torch.tensor([[0.0, -0.3, 0.0], [0.0, 0.3, 0.0], [0.0, -0.3, -1.0], [0.0, 0.3, -1.0]], dtype=F64)
    bones = torch.tensor([[0, 1], [2, 3]])
    radii = torch.tensor([0.1, 0.2], dtype=F64)
    rot = torch.eye(3, dtype=F64).expand(4, 3, 3)
    centre = cam.project(torch.tensor([0.0, 0.0, -0.5], dtype=F64)).pixels
    near = 0 if float(cam.world_to_camera(joints[0])[2]) < float(cam.world_to_camera(joints[2])[2]) else 1
    anchors = backproject(cam, centre, joints, rot, bones, radii)
    assert bool(anchors.valid) and int(anchors.bone) == near and int(anchors.joint) == int(bones[near, 1])
    far = 1 - near
    swapped = backproject(cam, centre, joints, rot, bones.flip(0), radii.flip(0))
    assert int(swapped.bone) == 1 - near and int(swapped.joint) == int(bones[near, 1])
    # the hit is on the near capsule's surface, radius from its axis
    x = anchor_points(anchors, joints, rot)
    assert abs(float((x[[0, 2]] - joints[bones[near, 0], [0, 2]]).norm()) - float(radii[near])) < 1e-9
    assert float(anchors.clearance) >= 0.0
    # a pixel beside both capsules misses
    miss = backproject(cam, centre + torch.tensor([90.0, 0.0], dtype=F64), joints, rot, bones, radii)
    assert not bool(miss.valid) and float(radii[far]) > 0
    # the same from the pixels' rays, made beforehand
    pixels = torch.stack([centre, centre + torch.tensor([90.0, 0.0], dtype=F64)])
    _, rays = cam.rays(pixels)
    both = (joints.expand(2, 4, 3), rot.expand(2, 4, 3, 3), bones, radii)
    for got, want in zip(backproject_rays(cam.center, rays, *both), backproject(cam, pixels, *both)):
        torch.testing.assert_close(got, want, rtol=0, atol=0)


@pytest.fixture(scope="module")
def kick():
    """The bundled CMU kick (subject 10), 12 frames at 30 fps: full-skeleton joints and rotations, capsules,
    a camera, float64."""
    sk = Skeleton.from_asf(DATA / "10.asf")
    q = load_amc(DATA / "10_02.amc", sk).q[:48:4].to(F64)
    joints, rot = sk.forward_kinematics(q, rotations=True)
    bones = torch.as_tensor(sk.bones())
    radii = capsule_radii([sk.joint_names[b] for _, b in sk.bones()], torch.as_tensor(sk.lengths[bones[:, 1]]))
    cam = camera_for_motion(joints, 5.0, 30.0, 10.0, 1000.0, 640, 480)
    return joints, rot, bones, radii.to(F64), cam


def test_simulated_pairs_reproject_exactly_with_the_true_poses(kick):
    joints, rot, bones, radii, cam = kick
    corr, info = simulate_correspondences(joints, rot, bones, radii, cam, 30, torch.Generator().manual_seed(0), 0.0)
    t = joints.shape[0]
    assert corr.num_pairs == 30 * (t - 1) and torch.equal(
        torch.bincount(corr.frame, minlength=t)[1:], torch.full((t - 1,), 30)
    )
    assert bool(cam.in_image(corr.p1).all() & cam.in_image(corr.p2).all())
    prev, cur = corr.frame - 1, corr.frame
    anchors = backproject(cam, corr.p1, joints[prev], rot[prev], bones, radii)
    assert bool(anchors.valid.all()) and torch.equal(anchors.bone, info.bone)  # the capsule the pixel was drawn on
    x = anchor_points(anchors, joints[cur], rot[cur])
    r, jac = reprojection_rows(cam, x, torch.zeros(*x.shape, 1, dtype=F64), corr.p2, torch.ones_like(corr.weight))
    assert float(r.abs().max()) < 1e-6 and jac.shape == (corr.num_pairs, 2, 1)
    # many capsules are sampled, in proportion to their visible area (the torso more than a hand)
    assert len(set(info.bone.tolist())) > 10
    # noise on p2 only; outliers displaced far; same seed, same pairs
    noisy, ninfo = simulate_correspondences(
        joints, rot, bones, radii, cam, 30, torch.Generator().manual_seed(0), 1.5, outliers=0.2, outlier_px=40.0
    )
    torch.testing.assert_close(noisy.p1, corr.p1, rtol=0, atol=0)
    err = (noisy.p2 - ninfo.clean_p2).norm(dim=-1)
    assert 0.1 < float(ninfo.outlier.float().mean()) < 0.3 and float(err[ninfo.outlier].min()) >= 20.0 - 1e-9
    std = (noisy.p2 - ninfo.clean_p2)[~ninfo.outlier].std()
    assert 1.3 < float(std) < 1.7
    again, _ = simulate_correspondences(
        joints, rot, bones, radii, cam, 30, torch.Generator().manual_seed(0), 1.5, outliers=0.2, outlier_px=40.0
    )
    assert torch.equal(again.p2, noisy.p2) and torch.equal(again.frame, noisy.frame)


def test_by_frame_and_npz_round_trip(tmp_path):
    corr = Correspondences(
        frame=torch.tensor([2, 1, 2, 2]),
        p1=torch.arange(8.0).reshape(4, 2),
        p2=torch.arange(8.0).reshape(4, 2) + 1,
        weight=torch.tensor([1.0, 0.5, 2.0, 0.0]),
    )
    p1, p2, w = corr.by_frame(4)
    assert p1.shape == p2.shape == (4, 3, 2) and w.shape == (4, 3)
    torch.testing.assert_close(w, torch.tensor([[0, 0, 0], [0.5, 0, 0], [1, 2, 0], [0, 0, 0]]))
    torch.testing.assert_close(p1[2], torch.tensor([[0.0, 1], [4, 5], [6, 7]]))
    torch.testing.assert_close(p2[1], torch.tensor([[3.0, 4], [0, 0], [0, 0]]))
    corr.save_npz(tmp_path / "c.npz")
    back = Correspondences.load_npz(tmp_path / "c.npz", 4)
    assert torch.equal(back.frame, corr.frame) and torch.equal(back.p2.float(), corr.p2)
    with pytest.raises(InputError, match=r"c\.npz: correspondences: pair 0 has frame 2, outside 1\.\.1"):
        Correspondences.load_npz(tmp_path / "c.npz", 2)


def _write(path: Path, **arrays) -> Path:
    np.savez(path, **arrays)
    return path


def test_bad_correspondence_files_and_settings(tmp_path, capsys):
    """The demo clip at FAST's stride has 12 frames: pairs may name frames 1 .. 11."""
    out = tmp_path / "run"
    ok = {"frame": np.array([1, 5]), "p1": np.zeros((2, 2)), "p2": np.ones((2, 2))}

    def run(path: Path | str, *fragments: str, extra: tuple[str, ...] = ()) -> None:
        argv = ["run", str(DEMO), *FAST, f"observations.correspondence_file={path}", *extra, f"out_dir={out}"]
        fail(capsys, out, argv, *fragments)

    run(tmp_path / "none.npz", "correspondence file not found", "none.npz")
    (tmp_path / "text.npz").write_text("not an archive")
    run(tmp_path / "text.npz", "text.npz", "not an .npz archive")
    run(_write(tmp_path / "nokey.npz", frame=ok["frame"], p1=ok["p1"]), "nokey.npz", "missing key 'p2'")
    run(_write(tmp_path / "shape.npz", **{**ok, "p2": np.ones((2, 3))}), "shape.npz", "p2 must be (2, 2)")
    run(
        _write(tmp_path / "float.npz", **{**ok, "frame": np.array([1.0, 2.0])}), "float.npz", "'frame' must be integers"
    )
    nan = ok["p1"].copy()
    nan[1, 0] = np.nan
    run(_write(tmp_path / "nan.npz", **{**ok, "p1": nan}), "nan.npz", "p1 has NaN/inf", "pair 1")
    run(_write(tmp_path / "late.npz", **{**ok, "frame": np.array([1, 12])}), "late.npz", "frame 12", "outside 1..11")
    run(_write(tmp_path / "first.npz", **{**ok, "frame": np.array([0, 3])}), "first.npz", "frame 0", "outside 1..11")
    run(_write(tmp_path / "neg.npz", **ok, weight=np.array([1.0, -1.0])), "neg.npz", "weight must be >= 0")
    good = _write(tmp_path / "good.npz", **ok)
    run(good, "observations.correspondences", "not both", extra=("observations.correspondences=5",))
    for bad, key in (
        ("observations.correspondences=-1", "observations.correspondences"),
        ("observations.correspondence_noise_px=-1", "observations.correspondence_noise_px"),
        ("observations.correspondence_outliers=1.5", "observations.correspondence_outliers"),
        ("pca.correspondence_weight=-1", "pca.correspondence_weight"),
        ("pca.correspondence_margin_m=-0.1", "pca.correspondence_margin_m"),
    ):
        fail(capsys, out, ["run", str(DEMO), *FAST, bad, f"out_dir={out}"], key)


def test_simulated_correspondences_leave_the_keypoints_as_they_were():
    """Off by default; turned on, they are drawn after the keypoint channel, whose observations stay the same."""
    from ptrack.pipeline.config import load_config
    from ptrack.pipeline.run import prepare

    off = prepare(load_config(DEMO, FAST))
    corr = ["observations.correspondences=5", "observations.correspondence_outliers=0.2"]
    on = prepare(load_config(DEMO, [*FAST, *corr]))
    assert off.problem.correspondences is None and on.problem.correspondences is not None
    assert on.problem.correspondences.num_pairs > 0 and int(on.problem.correspondences.frame.min()) >= 1
    torch.testing.assert_close(on.problem.observations.keypoints, off.problem.observations.keypoints, equal_nan=True)
    torch.testing.assert_close(on.problem.observations.confidence, off.problem.observations.confidence)
