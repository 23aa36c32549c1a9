"""ptrack.costs.ray_silhouette: ray-capsule distances against brute force, closed-form Jacobians
against finite differences, mask sampling, and the term on a rendered silhouette."""

import pytest
import torch

from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.costs import PoseEval
from ptrack.costs.base import PoseJacobian
from ptrack.costs.ray_silhouette import RaySilhouette, mask_samples, ray_capsule_distance
from ptrack.errors import InputError
from ptrack.observe.camera import camera_for_motion
from ptrack.observe.silhouette import capsule_radii, render_silhouettes
from ptrack.optim.jacobians import joint_jacobian

F64 = torch.float64


def _random_scene(seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    origin = torch.randn(3, generator=g, dtype=F64)
    ahead = torch.tensor([0.0, 0.0, 3.0], dtype=F64)  # segments in front, crossing near the rays
    dirs = torch.nn.functional.normalize(0.2 * torch.randn(4, 5, 3, generator=g, dtype=F64) + ahead, dim=-1)
    a = origin + ahead + 0.5 * torch.randn(4, 6, 3, generator=g, dtype=F64)
    b = origin + ahead + 0.5 * torch.randn(4, 6, 3, generator=g, dtype=F64)
    return origin, dirs, a, b, torch.full((6,), 0.05, dtype=F64)


def test_distance_matches_brute_force():
    origin, dirs, a, b, radii = _random_scene()
    rd = ray_capsule_distance(origin, dirs, a, b, radii)
    # brute force over the segment (a fine grid of u), exact over the ray (the clamped projection)
    u = torch.linspace(0, 1, 20001, dtype=F64)
    seg = a[..., None, :] + u[:, None] * (b - a)[..., None, :]  # (4, 6, Nu, 3)
    rel = seg[:, None] - origin  # (4, 1, 6, Nu, 3)
    d = dirs[:, :, None, None, :]  # (4, 5, 1, 1, 3)
    s = (rel * d).sum(-1, keepdim=True).clamp_min(0)
    brute = (s * d - rel).norm(dim=-1).amin(-1) - radii  # (4, 5, 6)
    assert rd.distance.shape == (4, 5) and rd.bone.shape == (4, 5)
    best = brute.amin(-1).clamp_min(0)
    assert bool((rd.distance <= best + 1e-9).all())  # exact minimum, at most the grid's
    assert torch.allclose(rd.distance, best, atol=1e-6)
    assert bool((rd.distance == 0).any() and (rd.distance > 0).any())
    miss = rd.distance > 0
    assert torch.equal(rd.bone[miss], brute.argmin(-1)[miss])


def test_hit_is_zero_with_zero_gradient():
    origin = torch.zeros(3, dtype=F64)
    dirs = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64)
    a, b = torch.tensor([[-1.0, 0.01, 5.0]], dtype=F64), torch.tensor([[1.0, 0.01, 5.0]], dtype=F64)
    rd = ray_capsule_distance(origin, dirs, a, b, torch.tensor([0.05], dtype=F64))
    assert rd.distance.item() == 0 and rd.grad_a.abs().sum() == 0 and rd.grad_b.abs().sum() == 0


def test_gradients_match_finite_differences():
    origin, dirs, a, b, radii = _random_scene(1)
    rd = ray_capsule_distance(origin, dirs, a, b, radii)
    eps = 1e-6
    for end, grad in ((a, rd.grad_a), (b, rd.grad_b)):
        for k in range(3):
            moved = end.clone()
            idx = torch.arange(4)[:, None], rd.bone
            moved[idx[0], idx[1], k] += eps  # moves each ray's nearest bone
            other = ray_capsule_distance(origin, dirs, moved if end is a else a, moved if end is b else b, radii)
            fd = (other.distance - rd.distance) / eps
            near = rd.distance > 0
            assert torch.allclose(fd[near], grad[..., k][near], atol=1e-4)


def _cmu_scene(dtype=F64):
    sk = Skeleton.from_asf("ptrack/data/10.asf")
    q = load_amc("ptrack/data/10_02.amc", sk).q[:8:4].to(dtype)
    joints = sk.forward_kinematics(q)
    cam = camera_for_motion(joints, 5.0, 30.0, 10.0, 800.0, 320, 240)
    bones = torch.as_tensor(sk.bones())
    radii = capsule_radii(
        [sk.joint_names[j] for _, j in sk.bones()], torch.as_tensor(sk.lengths[bones[:, 1]], dtype=dtype)
    )
    return sk, q, joints, cam, bones, radii


def test_term_zero_on_own_silhouette_and_jacobian():
    sk, q, joints, cam, bones, radii = _cmu_scene()
    masks = render_silhouettes(joints, bones, radii, cam)
    pixels, valid = mask_samples(masks, step=3, max_samples=64)
    assert pixels.shape[0] == 2 and bool(valid.any(-1).all())
    _, dirs = cam.to(dtype=F64).rays(pixels.to(F64))
    term = RaySilhouette(dirs, valid, cam.to(dtype=F64).center, tuple(map(tuple, bones.tolist())), radii, sigma_m=0.02)
    ev = PoseEval(q=q, joints=joints, pixels=joints[..., :1, :2], depth=joints[..., :1, 2])
    assert term.residual(ev).abs().max() < 1e-9  # every sample's ray meets the model that drew it
    # move the pose: residuals appear, and the closed-form Jacobian matches finite differences
    q2 = q.clone()
    q2[:, 0] += 0.15
    q2[:, 4] += 0.3
    x, dx = joint_jacobian(sk, q2)
    r, jac = term.linearize_joints(x, dx)
    assert r.shape == (2 * pixels.shape[1],) and jac.shape == (2 * pixels.shape[1], sk.num_dofs)
    assert r.abs().max() > 0.5
    ev2 = PoseEval(q=q2, joints=x, pixels=x[..., :1, :2], depth=x[..., :1, 2])
    assert torch.allclose(term.jacobian(ev2, PoseJacobian(joints=dx, pixels=dx, depth=dx)), jac)
    # residual_jacobian: both from one distance, as Objective.linearize asks; the residual is `residual`'s
    r2, jac2 = term.residual_jacobian(ev2, PoseJacobian(joints=dx, pixels=dx, depth=dx))
    assert torch.equal(r2, term.residual(ev2)) and torch.equal(jac2, jac)
    eps = 1e-7
    for dof in (0, 4, 10):
        q3 = q2.clone()
        q3[:, dof] += eps
        fd = (
            term.residual(PoseEval(q=q3, joints=sk.forward_kinematics(q3), pixels=x[..., :1, :2], depth=x[..., :1, 2]))
            - r
        ) / eps
        assert torch.allclose(fd, jac[:, dof], atol=1e-3), dof


def test_mask_samples_grid_and_thinning():
    m = torch.zeros(2, 20, 30, dtype=torch.bool)
    m[0, 5:15, 10:20] = True
    pixels, valid = mask_samples(m, step=2, max_samples=10)
    assert pixels.shape == (2, 10, 2) and valid.sum(1).tolist() == [10, 0]
    inside = m[0, pixels[0, :, 1].long(), pixels[0, :, 0].long()]
    assert bool(inside.all())
    with pytest.raises(InputError):
        mask_samples(m.float())
    with pytest.raises(InputError):
        RaySilhouette(
            torch.zeros(4, 3), torch.ones(4, dtype=torch.bool), torch.zeros(3), ((0, 1),), torch.tensor([-1.0])
        )
