"""Tests for ptrack.body.kinematics: batched forward kinematics of `Skeleton` models.

FK is checked three independent ways on real CMU data: against a plain numpy/scipy Acclaim
implementation written here from the ASF/AMC records, against pytorch-kinematics through the
model's URDF export, and by physical invariants (bone lengths, feet on the floor, head up).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from ptrack.body.acclaim import AsfFile, parse_amc, parse_asf
from ptrack.body.kinematics import forward_kinematics, local_rotations
from ptrack.body.skeleton import Skeleton
from ptrack.errors import InputError

# (skeleton, clip) pairs from different subjects and line-ending styles (05 and 131 are LF files)
SUBJECT_CLIPS = [("64", "64_01"), ("02", "02_01"), ("05", "05_02"), ("131", "131_03")]


@pytest.fixture(scope="module")
def sk(asf_64) -> Skeleton:
    return Skeleton.from_asf(asf_64)


@pytest.fixture(scope="module")
def q_clip(sk, amc_64_01) -> torch.Tensor:
    """The whole 64_01 swing, (448, 62) float64."""
    return sk.load_amc(amc_64_01).q


def _random_q(sk: Skeleton, shape, seed: int, dtype=torch.float64, scale: float = 0.5) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return scale * torch.randn(*shape, sk.num_dofs, generator=g, dtype=dtype)


# -- an independent Acclaim FK (numpy + scipy), straight from the parsed files ------------------


def _euler(order: str, angles_deg: np.ndarray) -> np.ndarray:
    """Rotations about fixed axes applied in `order`, first letter first (extrinsic): (..., 3, 3)."""
    return Rotation.from_euler(order.lower(), angles_deg, degrees=True).as_matrix()


def _reference_fk(asf: AsfFile, values: dict[str, np.ndarray]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Acclaim FK: bone end = parent end + G (length * direction), G = G_parent C M C^T with
    C from the bone's `axis` and M the AMC rotation (dof order). Returns name -> (p (T, 3), G (T, 3, 3))."""
    m = asf.metres_per_unit
    root = dict(zip(asf.root_order, values["root"].T))
    t = values["root"].shape[0]
    trans = np.stack([root.get(f"T{a}", np.zeros(t)) for a in "XYZ"], -1) * m
    rot_order = "".join(k[1] for k in asf.root_order if k[0] == "R")
    c = _euler(asf.root_axis, [asf.root_orientation["XYZ".index(a)] for a in asf.root_axis])
    mm = _euler(rot_order, np.stack([root[f"R{a}"] for a in rot_order], -1))
    out = {"root": (np.asarray(asf.root_position) * m + trans, c @ mm @ c.T)}
    bones = {b.name: b for b in asf.bones}
    pending = list(asf.hierarchy)
    while pending:
        parent, child = pending.pop(0)
        if parent not in out:
            pending.append((parent, child))
            continue
        b = bones[child]
        c = _euler(b.axis_order, [b.axis["XYZ".index(a)] for a in b.axis_order])
        if b.dof:
            mm = _euler("".join(d[1] for d in b.dof), values[child].reshape(t, len(b.dof)))
        else:
            mm = np.broadcast_to(np.eye(3), (t, 3, 3))
        p_par, g_par = out[parent]
        g = g_par @ (c @ mm @ c.T)
        out[child] = (p_par + g @ (np.asarray(b.direction) * b.length * m), g)
    return out


def _assert_matches_reference(sk: Skeleton, asf: AsfFile, amc_path, frames: slice, generic: bool) -> None:
    amc = parse_amc(amc_path, dict(sk.amc_layout.dof_counts))
    ref = _reference_fk(asf, {k: v[frames] for k, v in amc.values.items()})
    joints, rots = forward_kinematics(sk, sk.load_amc(amc_path).q[frames], rotations=True, generic=generic)
    for i, name in enumerate(sk.joint_names):
        np.testing.assert_allclose(joints[:, i].numpy(), ref[name][0], rtol=0, atol=1e-10, err_msg=name)
        np.testing.assert_allclose(rots[:, i].numpy(), ref[name][1], rtol=0, atol=1e-10, err_msg=name)


@pytest.mark.parametrize("generic", [False, True], ids=["closed_form", "generic"])
@pytest.mark.parametrize("subject,clip", SUBJECT_CLIPS)
def test_fk_matches_independent_acclaim_reference(cmu_file, subject, clip, generic):
    asf_path = cmu_file(f"{subject}.asf")
    _assert_matches_reference(
        Skeleton.from_asf(asf_path), parse_asf(asf_path), cmu_file(f"{clip}.amc"), slice(0, None, 60), generic
    )


@pytest.mark.parametrize("generic", [False, True], ids=["default", "generic"])
def test_fk_non_xyz_dof_order(tmp_path, asf_64, amc_64_01, generic):
    """A bone whose dofs are listed "rz ry rx" (applied z first) still matches the reference."""
    text = asf_64.read_bytes().decode()
    i = text.index("name lfemur")
    j = text.index("end", i)
    block = text[i:j].replace("dof rx ry rz", "dof rz ry rx")
    block = block.replace("(-160.0 20.0)", "@").replace("(-60.0 70.0)", "(-160.0 20.0)")  # swap rx, rz limits
    block = block.replace("@", "(-60.0 70.0)")
    assert "dof rz ry rx" in block and block.index("(-60.0 70.0)") < block.index("(-160.0 20.0)")
    p = tmp_path / "zyx.asf"
    p.write_bytes((text[:i] + block + text[j:]).encode())
    sk = Skeleton.from_asf(p)
    k = sk.dof_names.index("lfemur.rz")
    assert sk.dof_names[k : k + 3] == ("lfemur.rz", "lfemur.ry", "lfemur.rx")
    np.testing.assert_allclose(sk.lower[k : k + 3], np.radians([-60.0, -70.0, -160.0]))
    np.testing.assert_allclose(sk.upper[k : k + 3], np.radians([70.0, 70.0, 20.0]))
    _assert_matches_reference(sk, parse_asf(p), amc_64_01, slice(0, None, 90), generic)


def test_closed_form_and_generic_paths_agree(sk, q_clip):
    """The two FK implementations agree on real poses, a reduced model and random poses with gradients."""
    q = q_clip[::30]
    closed_form = forward_kinematics(sk, q, rotations=True)
    generic = forward_kinematics(sk, q, rotations=True, generic=True)
    for a, b in zip(closed_form, generic):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)
    r = sk.freeze(["*fingers", "*toes", "lfemur.ry"], value=0.4)
    qr = r.reduce(q, sk)
    torch.testing.assert_close(forward_kinematics(r, qr), forward_kinematics(r, qr, generic=True), rtol=0, atol=1e-12)
    q1 = _random_q(sk, (3,), seed=20).requires_grad_(True)
    q2 = q1.detach().clone().requires_grad_(True)
    forward_kinematics(sk, q1).square().sum().backward()
    forward_kinematics(sk, q2, generic=True).square().sum().backward()
    torch.testing.assert_close(q1.grad, q2.grad, rtol=0, atol=1e-10)


# -- shapes, dtypes, errors --------------------------------------------------------------------


@pytest.mark.parametrize("batch", [(), (1,), (5,), (2, 3), (2, 1, 4), (0,)])
def test_fk_shapes_any_leading_dims(sk, batch):
    q = _random_q(sk, batch, seed=1)
    joints = forward_kinematics(sk, q)
    assert joints.shape == (*batch, 31, 3)
    joints2, rots = forward_kinematics(sk, q, rotations=True)
    assert rots.shape == (*batch, 31, 3, 3)
    # the same FK by other paths: equal to rounding (a ~10-deep chain of rotations, a few ulps of metres
    # each), not bit for bit, which would hold for one CPU and torch build only
    torch.testing.assert_close(joints2, joints, rtol=0, atol=1e-13)
    assert local_rotations(sk, q).shape == (*batch, 31, 3, 3)
    torch.testing.assert_close(sk.forward_kinematics(q), joints, rtol=0, atol=1e-13)


def test_fk_batched_equals_one_by_one(sk):
    q = _random_q(sk, (2, 3), seed=2)
    joints, rots = forward_kinematics(sk, q, rotations=True)
    for a in range(2):
        for b in range(3):
            j1, r1 = forward_kinematics(sk, q[a, b], rotations=True)
            torch.testing.assert_close(joints[a, b], j1, rtol=0, atol=1e-14)
            torch.testing.assert_close(rots[a, b], r1, rtol=0, atol=1e-14)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_fk_output_dtype_follows_input(sk, dtype):
    q = _random_q(sk, (3,), seed=3, dtype=dtype)
    joints, rots = forward_kinematics(sk, q, rotations=True)
    assert joints.dtype == dtype and rots.dtype == dtype
    lengths = torch.as_tensor(sk.lengths, dtype=torch.float64 if dtype == torch.float32 else torch.float32)
    assert forward_kinematics(sk, q, lengths=lengths).dtype == dtype


def test_fk_float32_close_to_float64(sk, q_clip):
    j64 = forward_kinematics(sk, q_clip[::10])
    j32 = forward_kinematics(sk, q_clip[::10].float())
    assert (j32.double() - j64).abs().max() < 2e-6


@pytest.mark.parametrize("bad", [(61,), (4, 63), (4, 0)])
def test_fk_wrong_q_size(sk, bad):
    with pytest.raises(InputError) as exc:
        forward_kinematics(sk, torch.zeros(bad))
    msg = str(exc.value)
    assert str(bad[-1]) in msg and "62" in msg, msg


def test_fk_scalar_q_is_an_input_error(sk):
    with pytest.raises(InputError, match="62"):
        forward_kinematics(sk, torch.tensor(0.0))


def test_fk_wrong_lengths_size(sk):
    with pytest.raises(InputError, match="31"):
        forward_kinematics(sk, torch.zeros(62), lengths=torch.ones(30))


# -- rest pose and simple motions --------------------------------------------------------------


def test_rest_pose_is_cumulative_bone_vectors(sk, asf_64):
    """q = 0: every joint is the root position plus the sum of direction * length along its chain."""
    asf = parse_asf(asf_64)
    bones = {b.name: b for b in asf.bones}
    parent = {c: p for p, c in asf.hierarchy}
    m = asf.metres_per_unit
    joints, rots = forward_kinematics(sk, torch.zeros(62, dtype=torch.float64), rotations=True)
    for i, name in enumerate(sk.joint_names):
        expected = np.asarray(asf.root_position) * m
        n = name
        while n != "root":
            expected = expected + np.asarray(bones[n].direction) * bones[n].length * m
            n = parent[n]
        np.testing.assert_allclose(joints[i].numpy(), expected, rtol=0, atol=1e-12, err_msg=name)
    torch.testing.assert_close(rots, torch.eye(3, dtype=torch.float64).expand(31, 3, 3), rtol=0, atol=1e-15)
    # in the CMU rest pose the body is upright: head above the root, feet below it
    assert joints[sk.joint_index("head"), 1] > 0.4 and joints[sk.joint_index("lfoot"), 1] < -0.7


def test_root_translation_shifts_every_joint(sk):
    q = _random_q(sk, (4,), seed=4)
    shift = torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64)
    q2 = q.clone()
    q2[:, :3] += shift
    torch.testing.assert_close(forward_kinematics(sk, q2), forward_kinematics(sk, q) + shift, rtol=0, atol=1e-12)


def test_root_rotation_about_y_turns_the_body(sk):
    """root.ry = a (other root angles 0) turns the whole body by Ry(a) about the root."""
    q = _random_q(sk, (3,), seed=5)
    q[:, 3] = 0.0
    q[:, 5] = 0.0
    base = q.clone()
    base[:, 4] = 0.0
    a = q[:, 4]
    c, s = torch.cos(a), torch.sin(a)
    o, one = torch.zeros_like(a), torch.ones_like(a)
    ry = torch.stack([c, o, s, o, one, o, -s, o, c], -1).reshape(3, 3, 3)
    j0 = forward_kinematics(sk, base)
    j1 = forward_kinematics(sk, q)
    root = j0[:, :1]
    expected = root + torch.einsum("bij,bnj->bni", ry, j0 - root)
    torch.testing.assert_close(j1, expected, rtol=0, atol=1e-12)


def test_single_dof_moves_only_its_subtree(sk):
    """Turning the left tibia moves the tibia's end point (the ltibia joint) and everything below."""
    q = _random_q(sk, (), seed=6)
    q2 = q.clone()
    q2[sk.dof_names.index("ltibia.rx")] += 0.7
    moved = (forward_kinematics(sk, q2) - forward_kinematics(sk, q)).norm(dim=-1) > 1e-9
    below = {"ltibia", "lfoot", "ltoes"}
    assert {sk.joint_names[i] for i in torch.nonzero(moved).flatten().tolist()} == below


# -- lengths -----------------------------------------------------------------------------------


def test_scaled_lengths_scale_the_body(sk):
    q = _random_q(sk, (3,), seed=7)
    q[:, :3] = torch.tensor([0.2, 0.9, -0.4], dtype=torch.float64)
    j = forward_kinematics(sk, q)
    j2 = forward_kinematics(sk, q, lengths=1.5 * sk.length_tensor(torch.float64))
    torch.testing.assert_close(j2 - j2[:, :1], 1.5 * (j - j[:, :1]), rtol=0, atol=1e-12)
    torch.testing.assert_close(j2[:, 0], j[:, 0])


def test_batched_lengths(sk):
    q = _random_q(sk, (2,), seed=8)
    g = torch.Generator().manual_seed(9)
    lengths = sk.length_tensor(torch.float64) * (1 + 0.2 * torch.rand(2, 31, generator=g, dtype=torch.float64))
    j = forward_kinematics(sk, q, lengths=lengths)
    for b in range(2):
        torch.testing.assert_close(j[b], forward_kinematics(sk, q[b], lengths=lengths[b]), rtol=0, atol=1e-14)
    # each bone has the length it was given
    for p, c in sk.bones():
        torch.testing.assert_close((j[:, c] - j[:, p]).norm(dim=-1), lengths[:, c], rtol=0, atol=1e-12)


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-6), (torch.float32, 1e-5)])
def test_bone_lengths_preserved_on_real_clip(sk, q_clip, dtype, tol):
    joints = forward_kinematics(sk, q_clip.to(dtype))
    for p, c in sk.bones():
        err = ((joints[:, c] - joints[:, p]).norm(dim=-1).double() - float(sk.lengths[c])).abs().max()
        assert err < tol, (sk.joint_names[c], err)


# -- rotations ---------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype,tol", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_rotations_are_orthonormal(sk, q_clip, dtype, tol):
    _, rots = forward_kinematics(sk, q_clip[::8].to(dtype), rotations=True)
    eye = torch.eye(3, dtype=dtype)
    assert (rots @ rots.transpose(-1, -2) - eye).abs().max() < tol
    assert (torch.linalg.det(rots) - 1).abs().max() < tol
    local = local_rotations(sk, q_clip[::8].to(dtype))
    assert (local @ local.transpose(-1, -2) - eye).abs().max() < tol


def test_world_rotation_carries_bone_direction(sk, q_clip, asf_64):
    """An ASF bone's end point is its start plus G @ (length * rest direction)."""
    joints, rots = forward_kinematics(sk, q_clip[::50], rotations=True)
    bones = {b.name: b for b in parse_asf(asf_64).bones}
    for p, c in sk.bones():
        d = torch.as_tensor(bones[sk.joint_names[c]].direction, dtype=torch.float64)
        torch.testing.assert_close(joints[:, c] - joints[:, p], sk.lengths[c] * rots[:, c] @ d, rtol=0, atol=1e-12)


# -- agreement with pytorch-kinematics ---------------------------------------------------------


@pytest.mark.parametrize("subject,clip", SUBJECT_CLIPS)
def test_fk_matches_pytorch_kinematics(cmu_file, subject, clip):
    pk = pytest.importorskip("pytorch_kinematics")
    sk = Skeleton.from_asf(cmu_file(f"{subject}.asf"))
    q = sk.load_amc(cmu_file(f"{clip}.amc")).q[::40].float()
    chain = pk.build_chain_from_urdf(sk.to_urdf().encode())
    names = chain.get_joint_parameter_names()
    assert sorted(names) == sorted(sk.dof_names)
    tf = chain.forward_kinematics(q[:, [sk.dof_names.index(n) for n in names]])
    mats = torch.stack([tf[n].get_matrix() for n in sk.joint_names], dim=1)  # (T, J, 4, 4)
    joints, rots = forward_kinematics(sk, q, rotations=True)
    assert (mats[..., :3, 3] - joints).abs().max() < 1e-5
    assert (mats[..., :3, :3] - rots).abs().max() < 1e-5


# -- gradients ---------------------------------------------------------------------------------


@pytest.mark.parametrize("generic", [False, True], ids=["default", "generic"])
def test_gradcheck_wrt_q(sk, generic):
    q = _random_q(sk, (2,), seed=10).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: forward_kinematics(sk, x, rotations=True, generic=generic), (q,))


def test_gradcheck_wrt_lengths(sk):
    q = _random_q(sk, (2,), seed=11)
    lengths = sk.length_tensor(torch.float64).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda ln: forward_kinematics(sk, q, lengths=ln), (lengths,))
    lengths_b = lengths.detach().expand(2, 31).clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda ln: forward_kinematics(sk, q, lengths=ln), (lengths_b,))


def test_gradcheck_reduced_model(sk):
    r = sk.freeze(["*fingers", "*thumb", "*toes", "*clavicle"], value=0.2)
    q = _random_q(r, (1,), seed=12).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: forward_kinematics(r, x), (q,))


def test_gradient_at_zero_pose_is_finite(sk):
    q = torch.zeros(62, dtype=torch.float64, requires_grad=True)
    forward_kinematics(sk, q).square().sum().backward()
    assert torch.isfinite(q.grad).all() and q.grad[:3].abs().sum() > 0


# -- physical sanity on real data --------------------------------------------------------------


def test_golf_swing_is_physically_sane(sk, q_clip):
    joints = forward_kinematics(sk, q_clip)
    y = joints[..., 1]
    head, root = sk.joint_index("head"), 0
    assert torch.all(y[:, head] > y[:, root] + 0.3)  # Y up: the head is above the pelvis throughout
    feet = [sk.joint_index(n) for n in ("lfoot", "rfoot", "ltoes", "rtoes")]
    assert abs(y[:, feet].min().item()) < 0.15  # the feet touch the floor (y = 0)
    assert torch.all(y[:, feet].amin(dim=1) < 0.15)  # and some foot is on it in every frame
    assert 1.4 < y[0, head].item() < 1.9  # a standing adult at address
    assert y.max().item() < 2.6


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_fk_on_cuda_matches_cpu(sk, q_clip):
    q = q_clip[::20]
    j_cpu, r_cpu = forward_kinematics(sk, q, rotations=True)
    j_gpu, r_gpu = forward_kinematics(sk, q.float().cuda(), rotations=True)
    assert j_gpu.device.type == "cuda" and j_gpu.dtype == torch.float32
    assert (j_gpu.cpu().double() - j_cpu).abs().max() < 1e-5
    assert (r_gpu.cpu().double() - r_cpu).abs().max() < 1e-5
    lengths = sk.length_tensor(torch.float64, device="cuda").requires_grad_(True)
    forward_kinematics(sk, q.cuda(), lengths=lengths).sum().backward()
    assert lengths.grad.device.type == "cuda" and torch.isfinite(lengths.grad).all()


@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-10), (torch.float32, 2e-3)])
def test_analytical_backward_matches_autograd(sk, q_clip, dtype, tol):
    """The closed-form path's analytical gradient w.r.t. q equals autograd through the Rodrigues path
    on real poses, for a random upstream gradient and several leading dims; frozen dofs included."""
    reduced = sk.freeze(["*fingers", "*thumb", "*toes"], value=0.1)
    g = torch.Generator().manual_seed(3)
    for model in (sk, reduced):
        q = model.reduce(q_clip[::40], sk).to(dtype).reshape(2, -1, model.num_dofs)
        upstream = torch.randn(*q.shape[:-1], model.num_joints, 3, generator=g, dtype=dtype)
        grads = []
        for generic in (False, True):
            x = q.clone().requires_grad_(True)
            (forward_kinematics(model, x, generic=generic) * upstream).sum().backward()
            grads.append(x.grad)
        torch.testing.assert_close(grads[0], grads[1], rtol=tol, atol=tol)


def test_analytical_backward_used_only_for_positions(sk, q_clip):
    """Rotations and length gradients go through autograd (second derivatives stay available there)."""
    q = q_clip[:2].clone().requires_grad_(True)
    lengths = torch.as_tensor(sk.lengths).clone().requires_grad_(True)
    joints = forward_kinematics(sk, q, lengths=lengths)
    (gq, gl) = torch.autograd.grad(joints.sum(), (q, lengths), create_graph=True)
    assert gq.requires_grad and torch.isfinite(gl).all()
    _, rot = forward_kinematics(sk, q, rotations=True)
    (gr,) = torch.autograd.grad(rot.sum(), q)
    assert torch.isfinite(gr).all()


# -- second derivatives ------------------------------------------------------------------------


def test_hessian_through_fk_matches_autograd_path_and_finite_differences(sk):
    """Hessian of sum(FK(q)^2) w.r.t. q (float64): the default path (analytical first derivative)
    equals pure autograd through the Rodrigues path and central differences of the gradient."""
    q0 = _random_q(sk, (), seed=30)

    def energy(generic):
        return lambda x: forward_kinematics(sk, x, generic=generic).square().sum()

    hess = torch.autograd.functional.hessian(energy(False), q0)
    expected = torch.autograd.functional.hessian(energy(True), q0)
    assert expected.abs().max() > 1.0  # far from zero: a silently zero Hessian cannot pass
    torch.testing.assert_close(hess, expected, rtol=0, atol=1e-9)
    torch.testing.assert_close(hess, hess.T, rtol=0, atol=1e-9)

    def grad(x):
        x = x.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(energy(False)(x), x)
        return g

    eps = 1e-6
    steps = torch.eye(sk.num_dofs, dtype=torch.float64) * eps
    fd = torch.stack([(grad(q0 + s) - grad(q0 - s)) / (2 * eps) for s in steps])
    torch.testing.assert_close(hess, fd, rtol=0, atol=1e-6)


def test_hessian_vector_product_batched_with_create_graph(sk):
    """Double backward with a batch, an upstream weight and a reduced model (frozen dofs)."""
    model = sk.freeze(["*fingers", "*thumb", "*toes"], value=0.1)
    q = _random_q(model, (2, 3), seed=31)
    weights = torch.randn(2, 3, model.num_joints, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    v = torch.randn(q.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    hvps = []
    for generic in (False, True):
        x = q.clone().requires_grad_(True)
        (g,) = torch.autograd.grad(
            (forward_kinematics(model, x, generic=generic).square() * weights).sum(), x, create_graph=True
        )
        (hv,) = torch.autograd.grad((g * v).sum(), x)
        hvps.append(hv)
    assert hvps[1].abs().max() > 1e-3
    torch.testing.assert_close(hvps[0], hvps[1], rtol=0, atol=1e-10)


def test_gradgradcheck_reduced_model(sk):
    small = sk.freeze([n for n in sk.joint_names if n not in ("root", "lhipjoint", "lfemur", "ltibia")])
    q = _random_q(small, (1,), seed=32).requires_grad_(True)
    assert torch.autograd.gradgradcheck(lambda x: forward_kinematics(small, x), (q,))
