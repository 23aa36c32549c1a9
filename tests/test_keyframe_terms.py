"""Keyframes as the batch method uses them (issue 42 item 2): the shared `Keyframe` / `JointKeyframe` terms with a
full or diagonal covariance, their Gauss-Newton blocks in the banded trajectory assembler against autograd,
partial keyframes that pull only what they name, the ground-truth joint keyframes of `keyframes.joints`, and bad
keyframe files (one `ptrack: error:` line, exit 2)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest
import torch
from cli_errors import fail

from ptrack.costs import JointKeyframe, Keyframe, PoseEval
from ptrack.errors import InputError
from ptrack.estimators.batch import evaluate, total_energy, trajectory_objective
from ptrack.pipeline.config import load_config
from ptrack.pipeline.keyframes import read_keyframes
from ptrack.pipeline.run import prepare
from ptrack.problem import JointKeyframes, Keyframes

REPO = Path(__file__).resolve().parents[1]
BATCH = REPO / "configs" / "batch.yaml"
SHORT = ["data.stop=80", "progress=false", "batch.uncertainty=false", "batch.flip_restarts=0"]  # 20 frames
F64 = torch.float64


@pytest.fixture(scope="module")
def prep():
    return prepare(load_config(BATCH, [*SHORT, "keyframes.every_s=null"]))


def spd(n: int, seed: int) -> torch.Tensor:
    """A random symmetric positive definite (n, n) float64 matrix, well conditioned."""
    a = torch.randn(n, n, generator=torch.Generator().manual_seed(seed), dtype=F64)
    return a @ a.T / n + 0.5 * torch.eye(n, dtype=F64)


def with_keyframes(prep, keyframes=None, joint_keyframes=None):
    """The prepared problem with other keyframes, and its batch objective in float64."""
    cfg = load_config(BATCH, [*SHORT, "keyframes.every_s=null"])
    problem = dataclasses.replace(prep.problem, keyframes=keyframes, joint_keyframes=joint_keyframes)
    return trajectory_objective(problem, cfg, F64, torch.device("cpu"))


def near_truth(prep, seed=0, scale=0.05):
    q = prep.gt_q.double()
    return (q + scale * torch.randn(q.shape, generator=torch.Generator().manual_seed(seed), dtype=F64))[None]


def keyframe_blocks(obj, q):
    """The keyframe terms' share of evaluate's per-frame Hessian blocks and gradient: (T, D, D), (T, D)."""
    plain = dataclasses.replace(obj, keyframe=None, joint_keyframe=None, kf_frames=obj.kf_frames[:0])
    full, none = evaluate(obj, q), evaluate(plain, q)
    return full.h[0] - none.h[0], full.g[0] - none.g[0]


# -- the terms ------------------------------------------------------------------------------------------


def test_full_covariance_equals_diagonal_when_it_is_diagonal():
    target = torch.randn(3, 5, generator=torch.Generator().manual_seed(1), dtype=F64)
    var = torch.rand(3, 5, generator=torch.Generator().manual_seed(2), dtype=F64) + 0.1
    mask = torch.rand(3, 5, generator=torch.Generator().manual_seed(3)) > 0.3
    angular = torch.tensor([False, False, True, True, True])
    q = 4.0 * torch.randn(2, 8, 5, generator=torch.Generator().manual_seed(4), dtype=F64)
    ev = PoseEval(q, q.new_zeros(0), q.new_zeros(0), q.new_zeros(0))
    times = torch.tensor([0, 3, 7])
    diag = Keyframe(times, target, var, mask, diagonal=True, angular=angular)
    full = Keyframe(times, target, torch.diag_embed(var), mask, diagonal=False, angular=angular)
    torch.testing.assert_close(full.residual(ev), diag.residual(ev), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(full.whiten, diag.whiten, rtol=1e-12, atol=1e-12)
    # angles compared on the circle: a turn more is the same pose
    turned = q.clone()
    turned[..., 2:] += 2 * torch.pi
    torch.testing.assert_close(diag.energy(ev._replace(q=turned)), diag.energy(ev), rtol=1e-9, atol=1e-9)

    joints = torch.randn(2, 8, 4, 3, generator=torch.Generator().manual_seed(5), dtype=F64)
    jev = PoseEval(q, joints, q.new_zeros(0), q.new_zeros(0))
    jt = torch.randn(3, 4, 3, generator=torch.Generator().manual_seed(6), dtype=F64)
    jmask = torch.tensor([[True, False, True, False], [True, True, True, True], [False, False, False, True]])
    sigma = torch.rand(3, 4, generator=torch.Generator().manual_seed(7), dtype=F64) + 0.01
    per_joint = JointKeyframe(times, jt, jmask, sigma)
    cov = JointKeyframe(times, jt, jmask, 0.5, torch.diag_embed(sigma.square().repeat_interleave(3, -1)))
    torch.testing.assert_close(cov.residual(jev), per_joint.residual(jev), rtol=1e-12, atol=1e-12)
    e = (joints[:, times] - jt) / sigma[..., None]  # by hand
    torch.testing.assert_close(per_joint.energy(jev), 0.5 * (e.square().sum(-1) * jmask).sum((-1, -2)))


def test_full_covariance_is_the_mahalanobis_distance_of_the_given_entries():
    c = spd(6, 8)
    mask = torch.tensor([[True, True, False, True, False, True]])
    target = torch.zeros(1, 6, dtype=F64)
    q = torch.randn(1, 6, generator=torch.Generator().manual_seed(9), dtype=F64)
    term = Keyframe(torch.tensor([0]), target, c[None], mask, diagonal=False)
    s = mask[0]
    want = 0.5 * q[0, s] @ torch.linalg.solve(c[s][:, s], q[0, s])
    ev = PoseEval(q, q.new_zeros(0), q.new_zeros(0), q.new_zeros(0))
    torch.testing.assert_close(term.energy(ev), want)
    with pytest.raises(InputError, match="positive definite"):
        Keyframe(torch.tensor([0]), target, -c[None], mask, diagonal=False)


# -- the batch objective through the banded assembler -----------------------------------------------------


def test_batch_diagonal_sigma_and_diagonal_covariance_agree(prep):
    sk, gt = prep.problem.skeleton, prep.gt_q
    frames = torch.tensor([0, 9, 19])
    sigma = torch.rand(3, sk.num_dofs, generator=torch.Generator().manual_seed(3), dtype=F64) * 0.05 + 0.01
    mask = torch.rand(3, sk.num_dofs, generator=torch.Generator().manual_seed(4)) > 0.2
    by_sigma = with_keyframes(prep, Keyframes(frames, gt[frames], mask, sigma.to(gt)))
    by_cov = with_keyframes(prep, Keyframes(frames, gt[frames], mask, None, torch.diag_embed(sigma.square())))
    q = near_truth(prep)
    a, b = evaluate(by_sigma, q), evaluate(by_cov, q)
    for name in a.terms:
        torch.testing.assert_close(b.terms[name], a.terms[name], rtol=1e-6, atol=1e-9)  # sigma in float32
    torch.testing.assert_close(b.h, a.h, rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(b.g, a.g, rtol=1e-6, atol=1e-6)


def full_covariance_keyframes(prep):
    """Angle keyframes at 3 frames (one partial) and joint keyframes at 2 (some joints), all with full covariances."""
    sk, gt_q, gt_j = prep.problem.skeleton, prep.gt_q.double(), prep.gt_joints.double()
    d, j = sk.num_dofs, sk.num_joints
    frames = torch.tensor([0, 7, 15])
    mask = torch.ones(3, d, dtype=torch.bool)
    mask[1, : d // 2] = False
    cov = torch.stack([spd(d, s) * 1e-3 for s in (11, 12, 13)])
    kf = Keyframes(frames, gt_q[frames] + 0.05, mask, None, cov)
    jframes = torch.tensor([4, 12])
    jmask = torch.zeros(2, j, dtype=torch.bool)
    jmask[0, [0, 16, 20]] = True  # root, head, lwrist
    jmask[1, [27, 3]] = True  # rwrist, ltibia
    jcov = torch.stack([spd(3 * j, s) * 1e-3 for s in (14, 15)])
    jk = JointKeyframes(jframes, gt_j[jframes] + 0.03, jmask, torch.full((2, j), 0.02, dtype=F64), jcov)
    return kf, jk


def test_keyframe_jacobians_against_autograd(prep):
    """The keyframe terms' blocks in evaluate are J^T J and J^T r of their residuals, J by autograd through the
    forward kinematics; the whole gradient is autograd's gradient of the whole energy."""
    sk = prep.problem.skeleton
    kf, jk = full_covariance_keyframes(prep)
    obj = with_keyframes(prep, kf, jk)
    q = near_truth(prep, seed=2)
    t_len, d = q.shape[1:]

    def residual(x):
        x = x.reshape(1, t_len, d)
        ev = PoseEval(x, sk.forward_kinematics(x), x.new_zeros(0), x.new_zeros(0))
        assert obj.keyframe is not None and obj.joint_keyframe is not None
        return torch.cat([obj.keyframe.residual(ev), obj.joint_keyframe.residual(ev)], -1)[0]

    r = residual(q.flatten())
    jac = torch.autograd.functional.jacobian(residual, q.flatten()).reshape(-1, t_len, d)  # (M, T, D)
    h_kf, g_kf = keyframe_blocks(obj, q)
    for t in range(t_len):
        torch.testing.assert_close(h_kf[t], jac[:, t].T @ jac[:, t], rtol=1e-9, atol=1e-9)
        torch.testing.assert_close(g_kf[t], jac[:, t].T @ r, rtol=1e-9, atol=1e-9)
    x = q.clone().requires_grad_()
    (want,) = torch.autograd.grad(total_energy(obj, x).sum(), x)
    torch.testing.assert_close(evaluate(obj, q).g, want, rtol=1e-8, atol=1e-7)


def test_partial_keyframes_pull_only_what_they_name(prep):
    """A keyframe of a few dofs moves only those dofs' rows of the normal equations; one of a few joints' positions
    only the dofs that move those joints (the root and their chains), never the others (the left leg for a right
    wrist)."""
    sk, gt_q, gt_j = prep.problem.skeleton, prep.gt_q.double(), prep.gt_joints.double()
    d, j = sk.num_dofs, sk.num_joints
    named = [sk.dof_names.index(n) for n in ("lfemur.rx", "lfemur.rz", "rhumerus.ry")]
    mask = torch.zeros(1, d, dtype=torch.bool)
    mask[0, named] = True
    obj = with_keyframes(prep, Keyframes(torch.tensor([5]), gt_q[[5]] + 0.2, mask))
    h, g = keyframe_blocks(obj, near_truth(prep))
    rest = [i for i in range(d) if i not in named]
    assert float(g[5, named].abs().min()) > 0
    assert float(g[:, rest].abs().max()) == 0.0 and float(h[:, rest].abs().max()) == 0.0
    assert float(h[torch.arange(h.shape[0]) != 5].abs().max()) == 0.0

    rwrist = sk.joint_names.index("rwrist")
    jmask = torch.zeros(1, j, dtype=torch.bool)
    jmask[0, rwrist] = True
    target = gt_j[[8]] + torch.tensor([0.0, 0.0, 0.1], dtype=F64)
    obj = with_keyframes(prep, None, JointKeyframes(torch.tensor([8]), target, jmask, torch.tensor([0.02])))
    h, g = keyframe_blocks(obj, near_truth(prep))
    leg = [i for i, n in enumerate(sk.dof_names) if n.startswith(("lfemur", "ltibia", "lfoot", "rfemur", "rtibia"))]
    arm = [i for i, n in enumerate(sk.dof_names) if n.startswith(("rhumerus", "rradius"))]
    assert float(g[8, leg].abs().max()) == 0.0 and float(h[8][leg].abs().max()) == 0.0
    assert float(g[8, arm].abs().max()) > 0


def test_ground_truth_joint_keyframes_full_and_diagonal():
    over = [*SHORT, "keyframes.every_s=0.25", "keyframes.joints=[root,lwrist]", "keyframes.depth_noise_m=0.05"]
    full = prepare(load_config(BATCH, over)).problem
    diag = prepare(load_config(BATCH, [*over, "keyframes.joint_covariance=diagonal"])).problem
    assert full.keyframes is not None and full.keyframes.frames.tolist() == [0]  # frame 0: a full pose, the start
    jk, jd = full.joint_keyframes, diag.joint_keyframes
    assert jk is not None and jd is not None and jk.frames.tolist() == [8, 15] and jk.covariance is not None
    assert jk.mask.sum(-1).tolist() == [2, 2]
    torch.testing.assert_close(jk.joints, jd.joints)  # the same noise drawn
    block = jk.covariance[0, :3, :3]
    eigen = torch.linalg.eigvalsh(block)  # depth apart: sigma_m^2 twice, sigma_m^2 + depth^2 once
    torch.testing.assert_close(eigen, torch.tensor([0.02**2, 0.02**2, 0.02**2 + 0.05**2], dtype=F64))
    assert jd.covariance is not None
    torch.testing.assert_close(jd.covariance[0], torch.diag_embed(jk.covariance[0].diagonal()))


# -- keyframe files --------------------------------------------------------------------------------------


def test_file_covariance_and_per_joint_sigma(prep, tmp_path):
    sk = prep.problem.skeleton
    keys = {
        "keyframes": [
            {"frame": 2, "dofs": {"lfemur.rx": 10.0, "root.ty": 0.9}, "covariance": [[4.0, 0.01], [0.01, 0.0004]]},
            {"frame": 3, "dofs": {"rfemur.rx": 5.0}, "sigma_deg": 3.0},
            {
                "frame": 4,
                "joints": {"lwrist": [0.1, 1.2, 0.3], "head": {"position": [0.0, 1.7, 0.1], "sigma_m": 0.05}},
                "sigma_m": 0.01,
            },
        ]
    }
    path = tmp_path / "keys.json"
    path.write_text(json.dumps(keys))
    kf, jk = read_keyframes(path, sk, 20, 2.0, 0.02)
    assert kf is not None and jk is not None and kf.covariance is not None
    i, y = sk.dof_names.index("lfemur.rx"), sk.dof_names.index("root.ty")
    deg = torch.pi / 180
    torch.testing.assert_close(
        kf.covariance[0][[i, y]][:, [i, y]], torch.tensor([[4 * deg**2, 0.01 * deg], [0.01 * deg, 0.0004]], dtype=F64)
    )
    r = sk.dof_names.index("rfemur.rx")
    assert float(kf.covariance[1, r, r]) == pytest.approx((3 * deg) ** 2)  # no covariance given: its sigma
    lw, head = sk.joint_names.index("lwrist"), sk.joint_names.index("head")
    assert float(jk.sigma[0, lw]) == pytest.approx(0.01) and float(jk.sigma[0, head]) == pytest.approx(0.05)


CASES = [
    ("keyframes:\n  - frame: 3\n    dofs: {lfemur.rx: .nan}\n", ["lfemur.rx", "finite number"]),
    ("keyframes:\n  - frame: 3\n    joints: {lwrist: [0, .inf, 2]}\n", ["lwrist", "finite number"]),
    ("keyframes:\n  - frame: 3\n    joints: {lwrist: [0, 1]}\n", ["lwrist", "[x, y, z]"]),
    ("keyframes:\n  - frame: 3\n    joints: {lwrist: {pos: [0, 1, 2]}}\n", ["lwrist", "position"]),
    ("keyframes:\n  - frame: 3\n    joints: {lwrist: {position: [0, 1, 2], sigma_m: 0}}\n", ["sigma_m", "> 0"]),
    ("keyframes:\n  - frame: 3\n    dofs: {lfemur.rx: 1, lfemur.rz: 2}\n    covariance: [[1]]\n", ["2 x 2"]),
    (
        "keyframes:\n  - frame: 3\n    dofs: {lfemur.rx: 1, lfemur.rz: 2}\n    covariance: [[1, 2], [0, 1]]\n",
        ["symmetric"],
    ),
    (
        "keyframes:\n  - frame: 3\n    dofs: {lfemur.rx: 1, lfemur.rz: 2}\n    covariance: [[1, 2], [2, 1]]\n",
        ["positive"],
    ),
    ("keyframes:\n  - frame: 3\n    joints: {root: [0, 1, 2]}\n    joint_covariance: [[1, 0], [0, 1]]\n", ["3 x 3"]),
    ("keyframes:\n  - frame: 3\n    joints: {root: [0, 1, 2]}\n    covariance: [[1]]\n", ["'covariance'", "none"]),
    ("keyframes:\n  - frame: 3\n    q: [1, 2]\n", ["'q' must list all"]),
]


@pytest.mark.parametrize("text, fragments", CASES)
def test_bad_keyframe_files_exit_2_one_line(tmp_path, capsys, text, fragments):
    path = tmp_path / "keys.yaml"
    path.write_text(text)
    out = tmp_path / "out"
    fail(capsys, out, ["run", str(BATCH), *SHORT, f"keyframes.file={path}", f"out_dir={out}"], str(path), *fragments)


def test_bad_ground_truth_keyframe_settings(tmp_path, capsys):
    out = tmp_path / "out"
    fail(
        capsys,
        out,
        ["run", str(BATCH), *SHORT, "keyframes.joints=[nose]", f"out_dir={out}"],
        "keyframes.joints",
        "nose",
    )
    fail(capsys, out, ["run", str(BATCH), *SHORT, "keyframes.dofs=[zz*]", f"out_dir={out}"], "keyframes.dofs", "zz*")
    fail(
        capsys, out, ["run", str(BATCH), *SHORT, "keyframes.joint_covariance=no", f"out_dir={out}"], "joint_covariance"
    )


def test_ground_truth_partial_angle_keyframes():
    problem = prepare(load_config(BATCH, [*SHORT, "keyframes.every_s=0.25", "keyframes.dofs=[root.t*]"])).problem
    kf = problem.keyframes
    assert kf is not None and kf.mask is not None and kf.frames.tolist() == [0, 8, 15]
    names = problem.skeleton.dof_names
    assert bool(kf.mask[0].all())  # frame 0: the whole pose
    assert [names[i] for i in kf.mask[1].nonzero().flatten().tolist()] == ["root.tx", "root.ty", "root.tz"]
    assert problem.joint_keyframes is None
