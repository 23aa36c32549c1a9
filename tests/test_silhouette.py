import pytest
import torch

import ptrack.observe.silhouette as silhouette
from ptrack.costs import PoseEval, Silhouette
from ptrack.errors import InputError
from ptrack.observe.camera import camera_for_motion, look_at
from ptrack.observe.silhouette import capsule_radii, render_silhouettes

METRES_PER_UNIT = 0.0254 / 0.45


@pytest.fixture(scope="module")
def rest_pose(cmu_file):
    """Rest pose of a real CMU skeleton (subject 02) read from its ASF file: joints (J, 3) metres
    (root first, then each bone's end), bones (B, 2), bone names (B,), lengths (B,) metres, float64.
    Root at the origin."""
    dtype = torch.float64
    lines = cmu_file("02.asf").read_text().splitlines()
    bones, block = {}, {}
    for line in lines[lines.index(":bonedata") + 1 : lines.index(":hierarchy")]:
        tok = line.split()
        if tok and tok[0] in ("name", "direction", "length"):
            block[tok[0]] = tok[1:]
        elif tok and tok[0] == "end":
            bones[block["name"][0]] = ([float(x) for x in block["direction"]], float(block["length"][0]))
            block = {}
    pos, names, edges = {"root": torch.zeros(3, dtype=dtype)}, [], []
    for line in lines[lines.index(":hierarchy") + 2 :]:
        parent, *children = line.split() or ["end"]
        if parent == "end":
            break
        for child in children:
            direction, length = bones[child]
            pos[child] = pos[parent] + torch.tensor(direction, dtype=dtype) * length * METRES_PER_UNIT
            edges.append((list(pos).index(parent), list(pos).index(child)))
            names.append(child)
    lengths = torch.tensor([bones[n][1] * METRES_PER_UNIT for n in names], dtype=dtype)
    return torch.stack(list(pos.values())), torch.tensor(edges), names, lengths


def _frontal_camera(dtype=torch.float64):
    return look_at(torch.tensor([0.0, 1.0, 0.0], dtype=dtype), 4.0, 0.0, 0.0, 500.0, 320, 240)


# -- capsule_radii --------------------------------------------------------------------------------


def test_capsule_radii_cmu_names_and_fallback():
    names = ["lfemur", "RTIBIA", "lowerback", "head", "lhand", "rthumb", "ltoes", "tail", "antenna"]
    lengths = torch.tensor([0.4, 0.4, 0.1, 0.1, 0.1, 0.1, 0.05, 0.2, 2.0], dtype=torch.float64)
    r = capsule_radii(names, lengths)
    assert r.dtype == torch.float64 and r.shape == (9,)
    expected = [0.08, 0.06, 0.14, 0.10, 0.03, 0.03, 0.035, 0.05, 0.12]
    torch.testing.assert_close(r, torch.tensor(expected, dtype=torch.float64))


def test_capsule_radii_real_skeleton_is_sensible(rest_pose):
    _, _, names, lengths = rest_pose
    r = capsule_radii(names, lengths)
    assert r.shape == (30,) and bool((r >= 0.02).all()) and bool((r <= 0.15).all())
    assert r[names.index("lfemur")] > r[names.index("ltibia")] > r[names.index("lfoot")]


def test_capsule_radii_rejects_mismatched_lengths():
    with pytest.raises(InputError, match="bone_names"):
        capsule_radii(["lfemur", "ltibia"], torch.ones(3))


def test_capsule_radii_gradcheck():
    lengths = torch.tensor([0.2, 0.3, 0.15], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: capsule_radii(["a", "lfemur", "b"], x), (lengths,))


# -- render_silhouettes ---------------------------------------------------------------------------


def _row_widths(mask):
    return mask.sum(dim=-1)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_vertical_capsule_frontal_is_rounded_rectangle(dtype):
    joints = torch.tensor([[[0.0, 0.6, 0.0], [0.0, 1.4, 0.0]]], dtype=dtype)
    r, f, depth = 0.1, 500.0, 4.0
    radii = torch.tensor([r], dtype=dtype)
    mask = render_silhouettes(joints, torch.tensor([[0, 1]]), radii, _frontal_camera())[0]
    assert mask.shape == (240, 320) and mask.dtype == torch.bool
    width_px, half_len_px = f * 2 * r / depth, f * 0.4 / depth  # 25 px wide, segment 100 px tall
    widths = _row_widths(mask)
    straight = widths[120 - 45 : 120 + 45]  # rows along the segment, away from the caps
    assert bool(((straight - width_px).abs() <= 1.5).all())
    assert int(straight.max() - straight.min()) <= 1  # a rectangle
    cols = mask.any(dim=0).nonzero().flatten()
    assert abs((cols[0] + cols[-1] + 1).item() / 2 - 160) <= 0.5  # centred on the image
    rows = mask.any(dim=1).nonzero().flatten()
    assert abs(len(rows) - (2 * half_len_px + width_px)) <= 2  # segment plus two half-disc caps
    # rounded ends: 10 px into a cap of radius 12.5 px the width is 2 sqrt(12.5^2 - 10^2) = 15 px
    cap_row = 120 - int(half_len_px) - 10
    assert abs(widths[cap_row].item() - 15) <= 2
    assert bool((widths[rows[0] : rows[0] + 3] < widths[120]).all())


def test_silhouette_cost_is_zero_on_rendered_pixels():
    # renderer, camera and silhouette cost share one pixel convention: the camera projection of a
    # point on the ray through a foreground pixel's centre reads distance 0, background >= 1
    cam = _frontal_camera()
    joints = torch.tensor([[[0.0, 0.6, 0.0], [0.3, 1.4, 0.1]]], dtype=torch.float64)
    mask = render_silhouettes(joints, torch.tensor([[0, 1]]), torch.tensor([0.02]), cam)[0]
    v, u = torch.meshgrid(torch.arange(240.0), torch.arange(320.0), indexing="ij")
    origins, dirs = cam.rays(torch.stack([u, v], dim=-1).double() + 0.5)
    pixels = cam.project(origins + 4.0 * dirs).pixels.reshape(-1, 1, 2).expand(-1, 2, 2)
    z = torch.zeros(1, dtype=torch.float64)
    ev = PoseEval(q=z, joints=z, pixels=z, depth=z, joint_pixels=pixels)
    d = Silhouette(mask, bones=((0, 1),), samples_per_bone=2).residual(ev)[:, 0].reshape(240, 320)
    assert mask.sum() > 100 and d[mask].abs().max() < 1e-6 and d[~mask].min() > 1 - 1e-6


def test_cmu_rest_pose_joints_fall_inside_mask(rest_pose):
    joints, bones, names, lengths = rest_pose
    frames = torch.stack([joints, joints + torch.tensor([0.2, 0.0, 0.1], dtype=torch.float64)])
    cam = camera_for_motion(frames, 5.0, 30.0, 10.0, 400.0, 320, 240).to(dtype=torch.float64)
    masks = render_silhouettes(frames, bones, capsule_radii(names, lengths), cam)
    proj = cam.project(frames)
    assert bool(cam.in_image(proj.pixels).all())
    px = proj.pixels.floor().long()
    for t in range(2):
        assert bool(masks[t, px[t, :, 1], px[t, :, 0]].all())
    coverage = masks.double().mean(dim=(1, 2))
    assert bool((coverage > 0.02).all()) and bool((coverage < 0.4).all())
    assert not masks[:, :5, :5].any()  # the corner is background
    assert not torch.equal(masks[0], masks[1])  # the figure moved


def test_downsample_approximates_full_resolution(rest_pose):
    joints, bones, names, lengths = rest_pose
    cam = camera_for_motion(joints[None], 5.0, 0.0, 0.0, 400.0, 320, 240).to(dtype=torch.float64)
    radii = capsule_radii(names, lengths)
    full = render_silhouettes(joints[None], bones, radii, cam)
    for k in (2, 3, 7):  # 7 does not divide the image: the last block is cropped
        coarse = render_silhouettes(joints[None], bones, radii, cam, downsample=k)
        assert coarse.shape == full.shape
        assert (coarse != full).double().mean().item() < 0.01 * k
        # nearest upsampling: constant on k x k blocks
        blocks = coarse[0, ::k, ::k].repeat_interleave(k, 0).repeat_interleave(k, 1)
        assert torch.equal(blocks[:240, :320], coarse[0])


def _reference_masks(joints, bones, radii, cam):
    """Brute force: every pixel against every bone, segment sampled densely (no culling)."""
    v, u = torch.meshgrid(torch.arange(cam.height) + 0.5, torch.arange(cam.width) + 0.5, indexing="ij")
    _, d = cam.rays(torch.stack([u, v], dim=-1).to(joints.dtype))  # (H, W, 3)
    s = torch.linspace(0, 1, 801, dtype=joints.dtype)
    out = []
    for frame in joints:
        best = torch.full(d.shape[:2], float("inf"), dtype=joints.dtype)
        margin = torch.full(d.shape[:2], float("inf"), dtype=joints.dtype)
        for (i, j), r in zip(bones.tolist(), radii):
            pts = frame[i] + s[:, None] * (frame[j] - frame[i]) - cam.center  # (S, 3)
            proj = pts @ d.reshape(-1, 3).T  # (S, P) position along each ray
            along = proj.clamp_min(0)
            dist = pts.square().sum(-1, keepdim=True) - 2 * along * proj + along**2
            dist = dist.clamp_min(0).sqrt().amin(0).reshape(d.shape[:2])
            best = torch.minimum(best, dist - r)
            margin = torch.minimum(margin, (dist - r).abs())
        out.append((best <= 0, margin))
    return out


def test_matches_brute_force_including_bones_behind_camera():
    g = torch.Generator().manual_seed(0)
    cam = look_at(torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), 2.0, 20.0, 10.0, 150.0, 64, 48)
    spread = torch.tensor([0.5, 0.5, 2.0], dtype=torch.float64)
    joints = torch.randn(2, 12, 3, generator=g, dtype=torch.float64) * spread
    joints = joints + torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    bones = torch.stack([torch.arange(11), torch.arange(1, 12)], dim=1)
    radii = torch.rand(11, generator=g, dtype=torch.float64) * 0.08 + 0.02
    depth = cam.world_to_camera(joints)[..., 2]
    assert bool((depth < 0).any()) and bool((depth > 0).any())  # some joints behind the camera
    masks = render_silhouettes(joints, bones, radii, cam)
    for t, (ref, margin) in enumerate(_reference_masks(joints, bones, radii, cam)):
        decided = margin > 2e-3  # the sampled reference is only exact up to its sampling step
        assert torch.equal(masks[t][decided], ref[decided])
        assert ref.any() and (~ref).any()


def test_capsule_behind_camera_is_invisible():
    cam = _frontal_camera()
    behind = cam.center + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)  # camera looks towards -Z
    joints = torch.stack([behind, behind + torch.tensor([0.0, 0.5, 0.0], dtype=torch.float64)])[None]
    masks = render_silhouettes(joints, torch.tensor([[0, 1]]), torch.tensor([0.3]), cam)
    assert not masks.any()
    # a bone reaching from behind the camera to in front of it is still rendered (no culling)
    joints[0, 1] = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    masks = render_silhouettes(joints, torch.tensor([[0, 1]]), torch.tensor([0.05]), cam)
    assert masks.any()


def test_chunking_and_larger_images(monkeypatch, rest_pose):
    joints, bones, names, lengths = rest_pose
    joints, lengths = joints.float(), lengths.float()  # float32 path
    shift = torch.tensor([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [-0.3, 0.1, 0.2]])
    frames = joints[None] + shift[:, None]  # T = 3, 30 bones, 320 x 240
    cam = camera_for_motion(frames, 4.0, 0.0, 0.0, 300.0, 320, 240)
    radii = capsule_radii(names, lengths)
    masks = render_silhouettes(frames, bones, radii, cam)
    assert masks.shape == (3, 240, 320)
    monkeypatch.setattr(silhouette, "_CHUNK_PAIRS", 1000)  # ~4 tiles per chunk
    assert torch.equal(render_silhouettes(frames, bones, radii, cam), masks)
    monkeypatch.setattr(silhouette, "_TILE", 5)  # tiles that do not divide the image
    assert torch.equal(render_silhouettes(frames, bones, radii, cam), masks)


def test_empty_inputs():
    cam = _frontal_camera()
    none = render_silhouettes(torch.zeros(0, 3, 3), torch.tensor([[0, 1]]), torch.tensor([0.1]), cam)
    assert none.shape == (0, 240, 320)
    no_bones = torch.zeros(0, 2, dtype=torch.long)
    empty = render_silhouettes(torch.zeros(2, 3, 3), no_bones, torch.zeros(0), cam)
    assert empty.shape == (2, 240, 320) and not empty.any()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"joints": torch.zeros(2, 3, 2)}, "joints"),
        ({"joints": torch.zeros(2, 3, 3, dtype=torch.long)}, "joints"),
        ({"joints": torch.full((2, 3, 3), float("nan"))}, "non-finite"),
        ({"bones": torch.tensor([[0, 3]])}, "bones"),
        ({"bones": torch.tensor([0, 1])}, "bones"),
        ({"radii": torch.tensor([-0.1])}, "radii"),
        ({"radii": torch.tensor([0.1, 0.1])}, "radii"),
        ({"downsample": 0}, "downsample"),
        ({"downsample": 1.5}, "downsample"),
    ],
)
def test_rejects_bad_inputs(kwargs, match):
    args = {
        "joints": torch.rand(2, 3, 3),
        "bones": torch.tensor([[0, 1]]),
        "radii": torch.tensor([0.1]),
        "camera": _frontal_camera(),
    }
    args.update(kwargs)
    with pytest.raises(InputError, match=match):
        render_silhouettes(**args)
