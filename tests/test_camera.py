import json
import math

import pytest
import torch
from kornia.geometry.camera.perspective import project_points

from ptrack.errors import InputError
from ptrack.observe.camera import Camera, Projection, camera_for_motion, look_at


def _f64(x) -> torch.Tensor:
    return torch.tensor(x, dtype=torch.float64)


def _rot_y(angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float64)


def _camera(dtype=torch.float64) -> Camera:
    K = torch.tensor([[500.0, 0.0, 320.0], [0.0, 400.0, 240.0], [0.0, 0.0, 1.0]])
    return Camera(K=K, R=_rot_y(0.3), t=torch.tensor([0.1, -0.2, 4.0]), width=640, height=480).to(dtype=dtype)


def _random_points(gen: torch.Generator, shape, cam: Camera, dtype=torch.float64) -> torch.Tensor:
    """World points in front of `cam`: camera-frame xy in [-1, 1], z in [2, 6]."""
    x_cam = torch.empty(*shape, 3, dtype=dtype)
    x_cam[..., :2] = torch.rand(*shape, 2, generator=gen, dtype=dtype) * 2 - 1
    x_cam[..., 2] = torch.rand(*shape, generator=gen, dtype=dtype) * 4 + 2
    R, t = cam.R.to(dtype), cam.t.to(dtype)
    return (x_cam - t) @ R  # R^T (x_cam - t)


# -- construction and validation ----------------------------------------------------------------


def test_smoke_identity_camera_known_values():
    K = torch.tensor([[100.0, 0.0, 50.0], [0.0, 200.0, 40.0], [0.0, 0.0, 1.0]])
    cam = Camera(K=K, R=torch.eye(3), t=torch.zeros(3), width=100, height=80)
    X = torch.tensor([[0.0, 0.0, 2.0], [1.0, 0.5, 2.0], [-0.2, 0.1, 0.5]])
    proj = cam.project(X)
    assert isinstance(proj, Projection)
    # u = fx x / z + cx, v = fy y / z + cy
    expected = torch.tensor([[50.0, 40.0], [100.0, 90.0], [10.0, 80.0]])
    torch.testing.assert_close(proj.pixels, expected)
    torch.testing.assert_close(proj.depth, torch.tensor([2.0, 2.0, 0.5]))
    assert proj.in_front.all()
    assert cam.in_image(proj.pixels).tolist() == [True, False, False]  # u=100 / v=80 are outside


def test_known_values_with_rotation_translation_and_skew():
    K = torch.tensor([[100.0, 5.0, 50.0], [0.0, 120.0, 40.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    R = _rot_y(math.pi / 2)  # world +Z -> camera +X, world +X -> camera -Z
    t = torch.tensor([0.0, 0.0, 3.0], dtype=torch.float64)
    cam = Camera(K=K, R=R, t=t, width=100, height=80)
    X = torch.tensor([-1.0, 0.5, 0.4], dtype=torch.float64)  # camera frame: (0.4, 0.5, 4.0)
    torch.testing.assert_close(cam.world_to_camera(X), _f64([0.4, 0.5, 4.0]))
    proj = cam.project(X)
    u = 100 * 0.1 + 5 * 0.125 + 50
    v = 120 * 0.125 + 40
    torch.testing.assert_close(proj.pixels, torch.tensor([u, v], dtype=torch.float64))
    assert proj.depth.shape == () and proj.in_front.item()
    torch.testing.assert_close(cam.center, torch.tensor([3.0, 0.0, 0.0], dtype=torch.float64))


def test_agrees_with_kornia_in_front():
    gen = torch.Generator().manual_seed(0)
    cam = _camera()
    X = _random_points(gen, (50,), cam)
    ours = cam.project(X).pixels
    theirs = project_points(cam.world_to_camera(X), cam.K)
    torch.testing.assert_close(ours, theirs)


def test_array_likes_are_converted_and_dtypes_promoted():
    cam = Camera(
        K=[[10, 0, 5], [0, 10, 5], [0, 0, 1]],
        R=torch.eye(3, dtype=torch.float64),
        t=[0, 0, 1],
        width=10,
        height=10,
    )
    assert cam.K.dtype == cam.R.dtype == cam.t.dtype == torch.float64
    assert cam.device == torch.device("cpu")


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"K": torch.eye(4)}, "K"),
        ({"K": torch.eye(3)[:2]}, "K"),
        ({"K": torch.tensor([[1.0, 0, 0], [0, 1, 0], [0, 0, 2]])}, "K"),
        ({"K": torch.tensor([[-1.0, 0, 0], [0, 1, 0], [0, 0, 1]])}, "K"),
        ({"K": torch.tensor([[1.0, 0, 0], [0, float("nan"), 0], [0, 0, 1]])}, "K"),
        ({"R": torch.eye(3) * 1.1}, "R"),
        ({"R": torch.diag(torch.tensor([1.0, 1.0, -1.0]))}, "R"),  # reflection, det -1
        ({"R": torch.ones(3)}, "R"),
        ({"t": torch.zeros(3, 1)}, "t"),
        ({"t": torch.tensor([0.0, float("inf"), 0.0])}, "t"),
        ({"width": 0}, "width"),
        ({"height": -5}, "height"),
        ({"width": 64.0}, "width"),
        ({"height": True}, "height"),
    ],
)
def test_bad_inputs_raise_input_error(kwargs, field):
    base = {"K": torch.eye(3), "R": torch.eye(3), "t": torch.zeros(3), "width": 64, "height": 48}
    base.update(kwargs)
    with pytest.raises(InputError, match=f"Camera.{field}"):
        Camera(**base)


def test_bad_shape_message_names_shape():
    with pytest.raises(InputError, match=r"\(4, 4\)"):
        Camera(K=torch.eye(4), R=torch.eye(3), t=torch.zeros(3), width=64, height=48)


def test_camera_is_frozen():
    cam = _camera()
    with pytest.raises(AttributeError):
        cam.width = 3  # type: ignore[misc]


def test_bad_points_raise_input_error():
    cam = _camera()
    with pytest.raises(InputError, match="X"):
        cam.project(torch.zeros(4, 2, dtype=torch.float64))
    with pytest.raises(InputError, match="X"):
        cam.project(torch.zeros(4, 3, dtype=torch.int64))
    with pytest.raises(InputError, match="pixels"):
        cam.rays(torch.zeros(4, 3))
    with pytest.raises(InputError, match="min_depth"):
        cam.project(torch.zeros(3, dtype=torch.float64), min_depth=0.0)


# -- dtype, device, batching --------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_outputs_follow_points_dtype(dtype):
    cam = _camera(torch.float32)
    X = torch.tensor([[0.1, 0.2, 0.3]], dtype=dtype)
    proj = cam.project(X)
    assert proj.pixels.dtype == proj.depth.dtype == dtype
    assert proj.in_front.dtype == torch.bool
    origins, dirs = cam.rays(proj.pixels)
    assert origins.dtype == dirs.dtype == dtype


def test_to_changes_dtype_and_keeps_values():
    cam = _camera(torch.float64)
    cam32 = cam.to(dtype=torch.float32)
    assert cam32.K.dtype == cam32.R.dtype == cam32.t.dtype == torch.float32
    torch.testing.assert_close(cam32.R.double(), cam.R, atol=1e-7, rtol=0)
    assert cam.to().K.dtype == torch.float64
    with pytest.raises(InputError, match="dtype"):
        cam.to(dtype=torch.int32)


def test_batched_shapes_several_leading_dims():
    gen = torch.Generator().manual_seed(1)
    cam = _camera()
    X = _random_points(gen, (2, 3, 4), cam)
    proj = cam.project(X)
    assert proj.pixels.shape == (2, 3, 4, 2)
    assert proj.depth.shape == proj.in_front.shape == (2, 3, 4)
    assert cam.world_to_camera(X).shape == (2, 3, 4, 3)
    assert cam.in_image(proj.pixels).shape == (2, 3, 4)
    origins, dirs = cam.rays(proj.pixels)
    assert origins.shape == dirs.shape == (2, 3, 4, 3)
    # batched result equals the per-point result
    single = cam.project(X[1, 2, 3]).pixels
    torch.testing.assert_close(proj.pixels[1, 2, 3], single)


# -- behind the camera --------------------------------------------------------------------------


def test_behind_camera_flagged_and_not_mirrored():
    K = torch.tensor([[100.0, 0.0, 50.0], [0.0, 100.0, 40.0], [0.0, 0.0, 1.0]])
    cam = Camera(K=K, R=torch.eye(3), t=torch.zeros(3), width=100, height=80)
    X = torch.tensor([[0.2, -0.1, -2.0], [0.2, -0.1, 2.0], [0.0, 0.0, 0.0], [0.1, 0.1, 1e-4]])
    proj = cam.project(X, min_depth=1e-3)
    assert proj.in_front.tolist() == [False, True, False, False]
    mirrored = torch.tensor([50.0 - 100 * 0.1, 40.0 + 100 * 0.05])  # pinhole with z = -2
    assert not torch.allclose(proj.pixels[0], mirrored)
    # same side of the principal point as the camera-frame x/y, and far outside the image
    assert proj.pixels[0, 0] > 50.0 and proj.pixels[0, 1] < 40.0
    assert not cam.in_image(proj.pixels[0]).item()
    clamped = torch.tensor([50.0 + 100 * 0.2 / 1e-3, 40.0 - 100 * 0.1 / 1e-3])
    torch.testing.assert_close(proj.pixels[0], clamped)
    assert torch.isfinite(proj.pixels).all()


def test_gradients_finite_at_zero_depth():
    cam = _camera()
    X_cam = torch.tensor([[0.3, -0.2, 0.0], [0.0, 0.0, 0.0], [0.1, 0.1, -1.0]], dtype=torch.float64)
    X = ((X_cam - cam.t) @ cam.R).requires_grad_(True)
    proj = cam.project(X)
    proj.pixels.sum().backward()
    assert torch.isfinite(proj.pixels).all()
    assert torch.isfinite(X.grad).all()


# -- rays ---------------------------------------------------------------------------------------


def test_rays_round_trip():
    gen = torch.Generator().manual_seed(2)
    cam = _camera()
    X = _random_points(gen, (5, 7), cam)
    pixels = cam.project(X).pixels
    origins, dirs = cam.rays(pixels)
    torch.testing.assert_close(dirs.norm(dim=-1), torch.ones(5, 7, dtype=torch.float64))
    torch.testing.assert_close(origins, cam.center.expand(5, 7, 3))
    v = X - origins
    s = (v * dirs).sum(-1)
    assert (s > 0).all()  # directions point forward
    torch.testing.assert_close(origins + s.unsqueeze(-1) * dirs, X)


def test_rays_with_skew_round_trip():
    K = _f64([[300.0, 7.0, 100.0], [0.0, 280.0, 90.0], [0.0, 0.0, 1.0]])
    cam = Camera(K=K, R=_rot_y(-0.7), t=_f64([0.3, 0.1, 2.0]), width=200, height=180)
    gen = torch.Generator().manual_seed(3)
    X = _random_points(gen, (20,), cam)
    origins, dirs = cam.rays(cam.project(X).pixels)
    along = ((X - origins) * dirs).sum(-1, keepdim=True) * dirs
    torch.testing.assert_close(origins + along, X)


def test_principal_point_ray_is_optical_axis():
    cam = _camera()
    _, dirs = cam.rays(cam.K[:2, 2])
    torch.testing.assert_close(dirs, cam.R[2])  # camera +z in world frame


# -- gradcheck ----------------------------------------------------------------------------------


def test_gradcheck_project_wrt_points():
    gen = torch.Generator().manual_seed(4)
    cam = _camera()
    X = _random_points(gen, (2, 3), cam).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: cam.project(x).pixels, (X,))


def test_gradcheck_rays_wrt_pixels():
    gen = torch.Generator().manual_seed(5)
    cam = _camera()
    pixels = (torch.rand(2, 3, 2, generator=gen, dtype=torch.float64) * 600).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: cam.rays(p)[1], (pixels,))


def test_gradcheck_world_to_camera():
    gen = torch.Generator().manual_seed(6)
    cam = _camera()
    X = torch.randn(4, 3, generator=gen, dtype=torch.float64).requires_grad_(True)
    assert torch.autograd.gradcheck(cam.world_to_camera, (X,))


# -- serialisation ------------------------------------------------------------------------------


def test_dict_round_trip_through_json():
    cam = _camera(torch.float64)
    d = json.loads(json.dumps(cam.to_dict()))
    back = Camera.from_dict(d, dtype=torch.float64)
    for name in ("K", "R", "t"):
        assert torch.equal(getattr(back, name), getattr(cam, name))
    assert (back.width, back.height) == (cam.width, cam.height)
    assert Camera.from_dict(d).K.dtype == torch.get_default_dtype()


@pytest.mark.parametrize(
    "change, key",
    [
        ({"K": None}, "K"),
        ({"R": "eye"}, "R"),
        ({"t": [0.0, "x", 1.0]}, "t"),
        ({"t": [0.0, 1.0]}, "t"),
        ({"width": "640"}, "width"),
        ({"fov": 1.0}, "fov"),
    ],
)
def test_from_dict_bad_dict_raises(change, key):
    d = _camera().to_dict()
    d.update(change)
    with pytest.raises(InputError, match=key):
        Camera.from_dict(d)


def test_from_dict_missing_key_and_not_mapping():
    d = _camera().to_dict()
    del d["R"]
    with pytest.raises(InputError, match="'R'"):
        Camera.from_dict(d)
    with pytest.raises(InputError, match="mapping"):
        Camera.from_dict([1, 2, 3])  # type: ignore[arg-type]


# -- look_at and camera_for_motion --------------------------------------------------------------


@pytest.mark.parametrize("az, el", [(0.0, 0.0), (37.0, 15.0), (-120.0, -30.0), (200.0, 60.0)])
def test_look_at_target_at_principal_point_and_distance(az, el):
    target = torch.tensor([0.5, 1.2, -0.3], dtype=torch.float64)
    cam = look_at(target, 4.0, az, el, focal_px=800.0, width=640, height=480)
    proj = cam.project(target)
    torch.testing.assert_close(proj.pixels, torch.tensor([320.0, 240.0], dtype=torch.float64))
    torch.testing.assert_close(proj.depth, torch.tensor(4.0, dtype=torch.float64))
    torch.testing.assert_close((cam.center - target).norm(), torch.tensor(4.0, dtype=torch.float64))
    assert cam.dtype == torch.float64
    torch.testing.assert_close(cam.K[0, 0], torch.tensor(800.0, dtype=torch.float64))


def test_look_at_azimuth_and_elevation_geometry():
    target = torch.zeros(3, dtype=torch.float64)
    d = 5.0
    expected = {
        (0.0, 0.0): [0.0, 0.0, d],
        (90.0, 0.0): [d, 0.0, 0.0],
        (180.0, 0.0): [0.0, 0.0, -d],
        (-90.0, 0.0): [-d, 0.0, 0.0],
        (0.0, 30.0): [0.0, d * 0.5, d * math.sqrt(3) / 2],
        (90.0, -45.0): [d / math.sqrt(2), -d / math.sqrt(2), 0.0],
    }
    for (az, el), c in expected.items():
        cam = look_at(target, d, az, el, 500.0, 64, 48)
        torch.testing.assert_close(cam.center, _f64(c), atol=1e-12, rtol=0)
    # positive elevation looks down: optical axis (third row of R) has a negative world-Y component
    assert look_at(target, d, 30.0, 20.0, 500.0, 64, 48).R[2, 1] < 0
    # azimuth 0, elevation 0: image x is world +X
    torch.testing.assert_close(look_at(target, d, 0.0, 0.0, 500.0, 64, 48).R[0], _f64([1.0, 0.0, 0.0]))


@pytest.mark.parametrize("az", [0.0, 90.0, 225.0])
@pytest.mark.parametrize("el", [0.0, 40.0, -20.0])
def test_upright_person_projects_upright(az, el):
    feet = torch.tensor([0.0, 0.0, 0.0])
    head = torch.tensor([0.0, 1.8, 0.0])
    cam = look_at(torch.tensor([0.0, 0.9, 0.0]), 6.0, az, el, 1000.0, 640, 480)
    px = cam.project(torch.stack([head, feet])).pixels
    assert px[0, 1] < px[1, 1]  # head has smaller v than feet
    assert torch.allclose(px[0, 0], px[1, 0], atol=1e-3)  # stays vertical on the centre line


@pytest.mark.parametrize("el", [90.0, -90.0])
def test_look_at_vertical_is_finite_and_valid(el):
    target = torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64)
    cam = look_at(target, 3.0, 30.0, el, 500.0, 64, 48)
    for x in (cam.K, cam.R, cam.t):
        assert torch.isfinite(x).all()
    torch.testing.assert_close(cam.project(target).pixels, _f64([32.0, 24.0]))
    sign = 1.0 if el > 0 else -1.0
    torch.testing.assert_close(cam.center, target + _f64([0.0, sign * 3.0, 0.0]))


def test_look_at_custom_up_axis_matches_rotated_scene():
    # With up = +Z, a person standing along +Z projects upright.
    cam = look_at([0.0, 0.0, 0.9], 5.0, 0.0, 10.0, 800.0, 640, 480, up=(0.0, 0.0, 1.0))
    px = cam.project(torch.tensor([[0.0, 0.0, 1.8], [0.0, 0.0, 0.0]])).pixels
    assert px[0, 1] < px[1, 1]
    assert cam.center[2] > 0.9  # positive elevation is above along `up`


def test_look_at_bad_inputs():
    with pytest.raises(InputError, match="distance_m"):
        look_at([0.0, 0.0, 0.0], 0.0, 0.0, 0.0, 500.0, 64, 48)
    with pytest.raises(InputError, match="focal_px"):
        look_at([0.0, 0.0, 0.0], 1.0, 0.0, 0.0, -1.0, 64, 48)
    with pytest.raises(InputError, match="target"):
        look_at([0.0, 0.0], 1.0, 0.0, 0.0, 500.0, 64, 48)
    with pytest.raises(InputError, match="up"):
        look_at([0.0, 0.0, 0.0], 1.0, 0.0, 0.0, 500.0, 64, 48, up=(0.0, 0.0, 0.0))
    with pytest.raises(InputError, match="width"):
        look_at([0.0, 0.0, 0.0], 1.0, 0.0, 0.0, 500.0, 0, 48)


def test_camera_for_motion_targets_bounding_box_centre():
    joints = torch.zeros(3, 4, 3)
    joints[0, 0] = torch.tensor([-1.0, 0.0, 2.0])
    joints[2, 3] = torch.tensor([3.0, 1.8, -2.0])
    joints[1, 2] = torch.tensor([0.0, 0.5, 0.0])
    cam = camera_for_motion(joints, 6.0, 45.0, 10.0, 900.0, 640, 480)
    centre = torch.tensor([1.0, 0.9, 0.0])
    pixels = cam.project(centre).pixels
    torch.testing.assert_close(pixels, torch.tensor([320.0, 240.0]), atol=1e-3, rtol=0)
    torch.testing.assert_close((cam.center - centre).norm(), torch.tensor(6.0), atol=1e-5, rtol=0)
    assert cam.dtype == torch.float32


def test_camera_for_motion_bad_joints():
    with pytest.raises(InputError, match=r"\(T, J, 3\)"):
        camera_for_motion(torch.zeros(4, 3), 6.0, 0.0, 0.0, 900.0, 640, 480)
    with pytest.raises(InputError, match="empty"):
        camera_for_motion(torch.zeros(0, 4, 3), 6.0, 0.0, 0.0, 900.0, 640, 480)
    with pytest.raises(InputError, match="non-finite"):
        camera_for_motion(torch.full((2, 4, 3), float("nan")), 6.0, 0.0, 0.0, 900.0, 640, 480)
