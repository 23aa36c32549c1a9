"""Tests for `method: batch` (ptrack.estimators.batch, ptrack.pipeline.keyframes): recovery of a noise-free clip
from keyframes, missing data and dropped frames, partial angle and joint-position keyframes, joint
limits at the solution, the calibration of joint_std, warm starts, upsampling, accuracy on a CMU clip
the method was not tuned on, and bad keyframe files / init_from folders through the CLI."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from cli_errors import fail

from ptrack.cli import main
from ptrack.costs import robust_loss_derivative
from ptrack.errors import InputError
from ptrack.estimators import batch, estimate_batch
from ptrack.estimators.batch import lower_branch, total_energy, trajectory_objective, warp_to_keyframes
from ptrack.pipeline import metrics as M
from ptrack.pipeline.config import load_config
from ptrack.pipeline.keyframes import read_keyframes
from ptrack.pipeline.run import prepare

REPO = Path(__file__).resolve().parents[1]
BATCH = REPO / "configs" / "batch.yaml"
SHORT = ["data.stop=160", "progress=false", "batch.uncertainty=false", "batch.flip_restarts=0"]  # 1.3 s, 40 frames


@pytest.fixture(autouse=True)
def _one_thread():
    """The runs around the solver (per-frame starts, metrics, recordings) on one thread too: on the
    shared 2-core machine multithreaded small ops made this file 3x slower."""
    from ptrack.threads import one_thread

    with one_thread():
        yield


def solve(*overrides: str):
    cfg = load_config(BATCH, [*SHORT, *overrides])
    prep = prepare(cfg)
    est = estimate_batch(prep.problem, cfg, torch.Generator().manual_seed(0))
    return cfg, prep, est


def mpjpe_mm(prep, est) -> float:
    idx = prep.problem.keypoints.index()
    return float(
        M.mpjpe(est.joints.index_select(-2, idx), prep.gt_joints.to(est.joints).index_select(-2, idx), root=0).mean()
    )


def test_noise_free_clip_is_recovered_from_keyframes():
    over = ("observations.noise_px=0", "observations.missing=0", "keyframes.every_s=0.5", "dtype=float64")
    _, prep, est = solve(*over, "batch.pose_prior_weight=0")
    assert mpjpe_mm(prep, est) < 12.0
    # what is left is the smoothing prior's energy of the clip's own motion: ~18% of the start's with the
    # per-dof scales of real motion (batch.prior: cmu), ~5% with one scale for all dofs (the pose prior, off
    # here, would add its energy at the clip's own poses)
    assert float(est.solver_cost[-1]) < 0.25 * float(est.solver_cost[0])


def test_missing_keypoints_and_dropped_frames():
    _, prep, est = solve("observations.missing=0.3", "observations.dropped_frames=0.15")
    conf = prep.problem.observations.confidence
    empty = (conf.sum(-1) == 0).nonzero().flatten()
    assert empty.numel() > 0  # some frames have no 2D at all: the dynamics fill them
    assert torch.isfinite(est.q).all()
    idx = prep.problem.keypoints.index()
    err = M.mpjpe(est.joints.index_select(-2, idx), prep.gt_joints.to(est.joints).index_select(-2, idx), root=0)
    assert float(err.mean()) < 45.0 and float(err[empty].mean()) < 60.0


def test_joint_limits_hold_at_the_solution():
    _, prep, est = solve("observations.noise_px=4", "batch.hard_limits=true")
    lower, upper = prep.problem.skeleton.limits(dtype=est.q.dtype)
    assert bool(((est.q >= lower - 1e-6) & (est.q <= upper + 1e-6)).all())


def test_soft_limits_act_and_hard_limits_hold():
    """The joint-limit barrier (DiFranco et al. eq. 2) acts without the box (`batch.hard_limits: false`):
    on limits narrowed so that the data pull a knee past them, the solution leaves the box by less than
    it does with no limits, and the barrier's energy is positive; with the box every iterate stays inside
    and the barrier is 0 (the term the issue found dead)."""
    import dataclasses

    from ptrack.estimators.batch import solve_trajectory

    over = ["observations.noise_px=0", "observations.missing=0", "batch.iterations=8", "batch.hard_limits=false"]
    cfg = load_config(BATCH, [*SHORT, *over])
    prep = prepare(cfg)
    obj = trajectory_objective(prep.problem, cfg, torch.float64, torch.device("cpu"))
    assert not obj.hard_limits
    assert all(bool(torch.isinf(b).all()) for b in obj.box())
    i = prep.problem.skeleton.dof_names.index("rtibia.rx")
    gt = prep.gt_q.double()
    lower, upper = obj.lower.clone(), obj.upper.clone()
    upper[i] = float(gt[:, i].min()) - 0.2  # the truth bends the knee 0.2 rad past it on every frame
    start = torch.minimum(torch.maximum(gt, lower), upper)[None]

    def violation(o):
        q, _ = solve_trajectory(o, start, cfg.batch)
        over = float((q[0, :, i] - upper[i]).clamp(min=0).max())
        return over, float(batch.evaluate(o, q, with_jacobian=False).terms["limits"].sum()), q

    soft = dataclasses.replace(obj, lower=lower, upper=upper, hard_limits=False)
    none = dataclasses.replace(soft, lower=torch.full_like(lower, -math.inf), upper=torch.full_like(upper, math.inf))
    hard = dataclasses.replace(soft, hard_limits=True)
    over_soft, energy_soft, _ = violation(soft)
    over_none, _, _ = violation(none)
    over_hard, energy_hard, q_hard = violation(hard)
    assert over_none > 0.15  # unconstrained, the knee follows the data and the keyframes (measured 0.244 rad)
    assert 0 < over_soft < 0.5 * over_none and energy_soft > 0  # the barrier pulls it back (0.054 rad)
    assert over_hard == 0.0 and energy_hard == 0.0
    assert bool(((q_hard >= lower - 1e-12) & (q_hard <= upper + 1e-12)).all())
    g = batch.evaluate(soft, start + 0.3).g  # past the bound the barrier's gradient is there and is autograd's
    x = (start + 0.3).requires_grad_()
    (want,) = torch.autograd.grad(sum(v.sum() for v in batch.evaluate(soft, x, with_jacobian=False).terms.values()), x)
    torch.testing.assert_close(g, want, rtol=1e-9, atol=1e-7)


@pytest.mark.parametrize("setting, held", [("all", "xyz"), ("vertical", "y"), ("none", "")])
def test_root_velocity_prior_lets_a_constant_velocity_root_pass(setting, held):
    """`batch.root_velocity`: the velocity prior holds only the root translations it names (y up), so a
    root walking at a constant 1.4 m/s along the ground costs no more smoothing energy than a root at
    rest under `vertical` and `none`, and more under `all`; the acceleration prior is the same in all."""
    cfg = load_config(BATCH, [*SHORT, f"batch.root_velocity={setting}"])
    prep = prepare(cfg)
    sk = prep.problem.skeleton
    obj = trajectory_objective(prep.problem, cfg, torch.float64, torch.device("cpu"))
    (n1, a1), (n2, a2) = obj.smooth
    assert (n1, n2) == (1, 2)
    tx, ty, tz = sk.translation_dof.tolist()
    assert [bool(a1[d] > 0) for d in (tx, ty, tz)] == [c in held for c in "xyz"]
    assert bool((a2[[tx, ty, tz]] > 0).all())
    rest = prep.gt_q.double().clone()
    rest[:, [tx, ty, tz]] = rest[0, [tx, ty, tz]]
    walk = rest.clone()
    t = prep.problem.observations.times.double() - float(prep.problem.observations.times[0])
    walk[:, tx] += 1.0 * t
    walk[:, tz] += 1.0 * t
    e_rest, e_walk = (float(batch.robust_smoothing(obj, x[None], derivatives=False)[0].sum()) for x in (rest, walk))
    if setting == "all":
        assert e_walk > e_rest + 1.0
    else:
        assert e_walk == pytest.approx(e_rest, rel=1e-9, abs=1e-9)
    if setting == "vertical":
        climb = rest.clone()
        climb[:, ty] += 1.0 * t
        assert float(batch.robust_smoothing(obj, climb[None], derivatives=False)[0].sum()) > e_rest + 1.0


def test_bad_root_velocity_setting():
    with pytest.raises(InputError, match=r"batch\.root_velocity"):
        load_config(BATCH, [*SHORT, "batch.root_velocity=sideways"])


def test_reprojection_blocks_are_the_gauss_newton_of_the_residual():
    """`evaluate`'s per-frame blocks J_t^T W J_t of the reprojection (assembled from `Reprojection.jacobian`
    on d pixels / d X and the joint Jacobians) equal those from the autograd Jacobian of the whitened
    residual with the IRLS weights rho'(s) of each keypoint (no limits, no pose prior; frames without keyframes)."""
    from ptrack.problem import evaluate_pose

    # 6 frames, a keyframe at frame 0 only
    cfg = load_config(BATCH, [*SHORT, "data.stop=24", "batch.pose_prior_weight=0"])
    prep = prepare(cfg)
    obj = trajectory_objective(prep.problem, cfg, torch.float64, torch.device("cpu"), limits=False)
    p = prep.problem
    cam = p.observations.camera.to(dtype=torch.float64)
    noise = torch.randn(prep.gt_q.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    q = prep.gt_q.double() + 0.05 * noise
    t_len, d = q.shape
    rp = obj.reprojection

    def residual(x):
        return rp.residual(evaluate_pose(p.skeleton, cam, p.keypoints, x.reshape(t_len, d)))

    r = residual(q.flatten())
    jac = torch.autograd.functional.jacobian(residual, q.flatten())  # (T K 2, T D)
    k = r.numel() // (2 * t_len)
    w = robust_loss_derivative(rp.loss)(r.reshape(t_len, k, 2).square().sum(-1), rp.scale)  # (T, K)
    h = batch.evaluate(obj, q[None]).h[0]
    assert obj.kf_frames.tolist() == [0]
    for t in range(1, t_len):
        jt = jac[t * 2 * k : (t + 1) * 2 * k, t * d : (t + 1) * d]  # (2K, D)
        want = jt.T @ (w[t].repeat_interleave(2)[:, None] * jt)
        torch.testing.assert_close(h[t], want, rtol=1e-9, atol=1e-9)


def test_partial_angle_and_joint_keyframes(tmp_path):
    cfg = load_config(BATCH, [*SHORT, "keyframes.every_s=null"])
    prep = prepare(cfg)
    sk, gt_q, gt_j = prep.problem.skeleton, prep.gt_q, prep.gt_joints
    lf = [i for i, n in enumerate(sk.dof_names) if n.startswith(("lfemur", "ltibia"))]
    rhand = sk.joint_names.index("rwrist")
    kf = {
        "units": "radians",
        "keyframes": [
            {"frame": 0, "q": [float(v) for v in gt_q[0]]},
            {"frame": 30, "dofs": {sk.dof_names[i]: float(gt_q[30, i]) for i in lf}, "sigma_deg": 0.5},
            {"frame": 25, "joints": {"rwrist": [float(v) for v in gt_j[25, rhand]]}, "sigma_m": 0.005},
        ],
    }
    path = tmp_path / "keys.json"
    path.write_text(json.dumps(kf))
    angles, joints = read_keyframes(path, sk, prep.problem.observations.num_frames, 2.0, 0.02)
    assert angles.mask[1].sum() == len(lf) and not angles.mask[1, 0]  # a partial keyframe: no root prior
    assert joints.mask[0].sum() == 1
    cfg = load_config(BATCH, [*SHORT, f"keyframes.file={path}", "batch.init=keyframes"])
    prep = prepare(cfg)
    est = estimate_batch(prep.problem, cfg, torch.Generator())
    assert float((est.q[30, lf] - gt_q[30, lf].to(est.q)).abs().max()) < np.radians(3.0)
    assert float((est.joints[25, rhand] - gt_j[25, rhand].to(est.q)).norm()) < 0.02


def test_linearisation_on_two_threads_equals_one(tmp_path, monkeypatch):
    """From 64 frames on, with a thread budget of 2, the per-frame part of the linearisation runs on the
    two halves of the sequence on two threads: the same energies, Hessian blocks and gradient (a joint
    keyframe included) as one thread, up to float64 rounding.

    Not bit for bit: the halves' FK, projections and batched J^T J run on other shapes, and BLAS/SIMD
    kernels (which depend on the CPU and the torch build) may sum in another order there. The bounds are
    the rounding of those sums. Every Hessian block H_t (D, D) is a Gram matrix, J^T J over 2K = 34
    residual rows plus non-negative diagonal terms, so |H_t,ij| <= sqrt(H_t,ii H_t,jj), and a sum of n
    products in another order moves by at most ~n u of that (u = 1.1e-16; the rows themselves come out of
    FK chains ~10 rotations deep, a few u each): a few 1e-14. Likewise the gradient's per-frame part
    J^T r is bounded by sqrt(H_t,ii) |r_t| <= sqrt(H_t,ii * 2 E_t) (E_t the frame's energy, IRLS weights
    <= 1), and the energies are sums of non-negative terms (relative error ~n u). The test allows 1e-11
    of those scales, ~1,000 times the rounding. Measured (Xeon; also under ATEN_CPU_CAPABILITY=default
    and avx2): 1.4e-14 on H, 2.2e-14 on g, 3,810 of 200,000 entries of H not bit-equal, energies
    bit-equal. A half on the wrong frames, or a term left out of one, moves them by O(1) of these scales."""
    import ptrack.estimators.batch as batch
    import ptrack.estimators.batch.objective as objective

    cfg = load_config(BATCH, ["data.stop=320", "progress=false"])  # 80 frames
    prep = prepare(cfg)
    sk, gt_q, gt_j = prep.problem.skeleton, prep.gt_q, prep.gt_joints
    rhand = sk.joint_names.index("rwrist")
    keys = [
        {"frame": 0, "q": [float(v) for v in gt_q[0]]},
        {"frame": 79, "q": [float(v) for v in gt_q[79]]},
        {"frame": 50, "joints": {"rwrist": [float(v) for v in gt_j[50, rhand]]}},
    ]
    path = tmp_path / "keys.json"
    path.write_text(json.dumps({"units": "radians", "keyframes": keys}))
    cfg = load_config(BATCH, ["data.stop=320", "progress=false", f"keyframes.file={path}", "batch.init=keyframes"])
    prep = prepare(cfg)
    obj = trajectory_objective(prep.problem, cfg, torch.float64, torch.device("cpu"))
    assert obj.jk_frames.tolist() == [50] and obj.problem.observations.num_frames == 80
    q = batch.interpolate_keyframes(prep.problem, obj.lower, obj.upper)[None]
    q = q + 0.01 * torch.randn(q.shape, generator=torch.Generator().manual_seed(0), dtype=q.dtype)
    out = {}
    for two in (False, True):
        monkeypatch.setattr(objective, "parallel_halves", lambda device, two=two: two)
        out[two] = batch.evaluate(obj, q)
    (terms1, h1, g1, _), (terms2, h2, g2, _) = out[False], out[True]
    tol = 1e-11
    for name in terms1:  # (B, T) sums of non-negative terms
        torch.testing.assert_close(terms2[name], terms1[name], rtol=tol, atol=0)
    diag = h1.diagonal(dim1=-2, dim2=-1)  # (B, T, D), >= 0
    h_scale = (diag[..., :, None] * diag[..., None, :]).sqrt()  # (B, T, D, D) Cauchy-Schwarz bound of |H_ij|
    energy = torch.stack(list(terms1.values())).sum(0)  # (B, T)
    g_scale = (2 * diag * energy[..., None]).sqrt()  # (B, T, D)
    assert float(h_scale.amax()) > 1.0 and float(g_scale.amax()) > 1.0  # scales of real size, not ~0
    worst_h = float(((h2 - h1).abs() - tol * h_scale).amax())
    worst_g = float(((g2 - g1).abs() - tol * g_scale).amax())
    assert worst_h <= 0.0, f"a Hessian entry differs by {worst_h:.3g} more than {tol:g} sqrt(H_ii H_jj)"
    assert worst_g <= 0.0, f"a gradient entry differs by {worst_g:.3g} more than {tol:g} sqrt(2 H_ii E_t)"


@pytest.mark.parametrize("loss", ["l2", "huber", "cauchy"])
def test_robust_smoothing_gradient_and_band(loss):
    """With a robust loss on the smoothing residuals, `evaluate`'s gradient is the energy's (autograd) and
    the linearisation's band is the Gauss-Newton Hessian of the smoothing, D^T diag(w a^2) D, dense."""
    cfg = load_config(BATCH, [*SHORT, "data.stop=60", f"batch.smooth_loss={loss}", "batch.smooth_scale=1.5"])
    prep = prepare(cfg)
    obj = trajectory_objective(prep.problem, cfg, torch.float64, torch.device("cpu"))
    noise = torch.randn((2, *prep.gt_q.shape), generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    q = (prep.gt_q.double() + 0.05 * noise).requires_grad_()
    energy = sum(v.sum() for v in batch.evaluate(obj, q, with_jacobian=False).terms.values())
    (grad,) = torch.autograd.grad(energy, q)
    g = batch.evaluate(obj, q.detach()).g
    torch.testing.assert_close(g, grad, rtol=1e-9, atol=1e-7)
    if loss == "cauchy":  # bad values: one error line naming the key
        for bad in ("batch.smooth_loss=tukey", "batch.smooth_scale=0"):
            with pytest.raises(InputError, match=bad.split("=")[0].replace(".", r"\.")):
                load_config(BATCH, [*SHORT, bad])
    t_len, d = q.shape[1:]
    if loss == "l2":
        band = obj.band[None]
    else:
        band = batch.weighted_band(t_len, batch.robust_smoothing(obj, q.detach())[2], q)
        assert band.shape[0] == 2 and not torch.equal(band[0], obj.band)  # the weights moved it
    dense = torch.zeros(2, t_len * d, t_len * d, dtype=torch.float64)
    x = q.detach()
    for n, a in obj.smooth:  # D_n^T diag(w a^2) D_n from the residuals' own derivative, one dof at a time
        rows = t_len - n
        dn = torch.zeros(rows, t_len, dtype=torch.float64)
        for j in range(n + 1):
            dn[torch.arange(rows), torch.arange(rows) + j] = (-1.0) ** (n - j) * math.comb(n, j)
        r2 = (a * torch.diff(x, n=n, dim=-2)).square()  # (2, rows, D)
        w = torch.ones_like(r2) if loss == "l2" else robust_loss_derivative(loss)(r2, 1.5)
        for k in range(d):
            blk = torch.einsum("it,bi,iu->btu", dn, w[..., k] * a[k] ** 2, dn)
            dense[:, k::d, k::d] += blk
    for t in range(t_len):
        for k in range(band.shape[2]):
            if t - k >= 0:
                blk = dense[:, t * d : (t + 1) * d, (t - k) * d : (t - k + 1) * d]
                want = band[:, t, k].expand(2, d)
                torch.testing.assert_close(torch.diagonal(blk, dim1=-2, dim2=-1), want, rtol=1e-12, atol=1e-9)
                assert float((blk - torch.diag_embed(torch.diagonal(blk, dim1=-2, dim2=-1))).abs().max()) == 0.0


def test_robust_smoothing_without_smoothing_terms():
    """The ablation without smoothing (every sigma null) runs with the default robust loss too."""
    nulls = [f"batch.{k}=null" for k in ("velocity_sigma", "accel_sigma", "velocity_sigma_m", "accel_sigma_m")]
    _, _, est = solve("data.stop=60", *nulls)
    assert torch.isfinite(est.q).all() and float(est.terms["smooth"].abs().sum()) == 0.0


def test_joint_std_and_its_coverage_are_written(tmp_path):
    """joint_std in result.npz (finite, positive, per joint-frame), the calibration applied to it
    (`batch.std_calibration`, the raw std otherwise), and its coverage of the truth in metrics.json."""
    out = tmp_path / "run"
    assert main(["run", str(BATCH), *SHORT[:2], "batch.uncertainty=laplace", f"out_dir={out}"]) == 0
    with np.load(out / "result.npz") as z:
        std, joints, gt = z["joint_std"], z["joints"], z["gt_joints"]
        assert std.shape == joints.shape[:2] and np.isfinite(std).all() and (std > 0).all()
        assert z["solver_cost"][-1] < z["solver_cost"][0]
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["joint_std_mean_m"] > 0 and metrics["solver_iterations"] >= 1
    err = np.linalg.norm(joints - gt, axis=-1)
    for k in (1, 2, 3):  # every joint, the share of joint-frames within k std
        assert metrics[f"joint_within_{k}std"] == pytest.approx(float((err <= k * std).mean()), abs=1e-6)
    _, prep, cal = solve("batch.uncertainty=laplace")
    _, _, raw = solve("batch.uncertainty=laplace", "batch.std_calibration=false")
    travel = batch.keyframe_travel(raw.joints, keyframe_frames_of(prep.problem))
    expected = batch.calibrate_std(raw.joint_std, batch.std_calibration("laplace"), travel)
    torch.testing.assert_close(cal.joint_std, expected)


def keyframe_frames_of(problem) -> torch.Tensor:
    """(F,) the frames of the problem's keyframes and joint keyframes."""
    frames = [k.frames for k in (problem.keyframes, problem.joint_keyframes) if k is not None]
    return torch.cat(frames) if frames else torch.zeros(0, dtype=torch.long)


def test_keyframe_travel_and_the_calibration_formula():
    """keyframe_travel: each joint's distance from its position at the nearest keyframe before or after (the
    smaller), 0 at a keyframe, one-sided past the last one, from frame 0 without keyframes; calibrate_std:
    sqrt((scale std)^2 + floor^2 + (travel m)^2)."""
    t = torch.arange(7, dtype=torch.float64)
    joints = torch.zeros(7, 2, 3, dtype=torch.float64)
    joints[:, 0, 0] = t  # joint 0 walks 1 m a frame along x, joint 1 stands
    travel = batch.keyframe_travel(joints, torch.tensor([4, 0, 4]))  # unsorted, repeated
    torch.testing.assert_close(travel[:, 0], torch.tensor([0.0, 1, 2, 1, 0, 1, 2], dtype=torch.float64))
    assert float(travel[:, 1].abs().max()) == 0.0
    torch.testing.assert_close(batch.keyframe_travel(joints, torch.zeros(0, dtype=torch.long))[:, 0], t)
    std = torch.full((7, 2), 0.015, dtype=torch.float64)
    cal = batch.calibrate_std(std, batch.StdCalibration(2.0, 0.04, 0.05), travel)
    torch.testing.assert_close(cal, ((2 * std) ** 2 + 0.04**2 + (0.05 * travel) ** 2).sqrt())
    flat = batch.calibrate_std(std, batch.StdCalibration(2.0, 0.04, 0.0), travel)
    torch.testing.assert_close(flat, torch.full_like(std, 0.05))  # no travel share: a scale and a floor (3-4-5)


def test_shipped_calibration_was_fitted_on_no_held_out_clip():
    """Both modes' calibrations list their runs (folder/clip/seed): none is a clip of the held-out list the
    coverage is judged on, and both keyframe settings are among them."""
    from ptrack.clips import parse_clips
    from ptrack.package_data import data_file

    doc = json.loads(data_file(batch.uncertainty.CALIBRATION_FILE).read_text())
    held = {p.stem for p in parse_clips(str(REPO / "configs" / "clips" / "heldout_batch.txt"))}
    for mode in ("branches", "laplace"):
        runs = doc[mode]["runs"]
        clips = {r.split("/")[1] for r in runs}
        assert clips and not clips & held, mode
        assert any("firstlast" in r.split("/")[0] for r in runs) and any("every1" in r.split("/")[0] for r in runs)
        assert batch.std_calibration(mode).scale == doc[mode]["scale"]


def test_calibrated_joint_std_covers_the_truth():
    """The shipped calibration (fitted on the dev and train clips) on a clip it was not fitted on: the bundled
    kick's first 80 frames from its first and last frame only (`uncertainty: branches`, the defaults). Measured
    2026-11-29 (scale 1.22, no floor, travel share 0.25; the pose prior at 0.03): within 2 std 0.89 raw, 0.998
    calibrated, 0.94 without the travel term; within 1 std 0.64 raw, 0.87 calibrated. The calibrated std must
    cover the truth as a calibrated one does (0.9 or more within 2 std), stay an uncertainty, not a blanket
    (under 0.95 within 1 std; a Gaussian puts 0.68 there, and this easy clip is covered more than the held-out
    clips the calibration is judged on), and be wider where a joint has travelled far from the keyframes: the
    travel term covers more than the same scale and floor without it, and widens the far quarter of the
    joint-frames against the rest more than the raw std does."""
    _, prep, est = solve(
        "data.stop=320", "keyframes.every_s=null", "keyframes.last=true", "batch.uncertainty=branches",
        "batch.flip_restarts=3", "batch.std_calibration=false",
    )  # fmt: skip
    gt = prep.gt_joints.to(est.joints)
    err = (est.joints - gt).norm(dim=-1)
    raw = est.joint_std
    shipped = batch.std_calibration("branches")
    assert shipped.travel > 0
    travel = batch.keyframe_travel(est.joints, keyframe_frames_of(prep.problem))
    cal = batch.calibrate_std(raw, shipped, travel)
    within = {k: float(M.std_coverage(est.joints, gt, cal, k)) for k in (1, 2)}
    assert within[2] >= 0.9, within
    assert within[1] <= 0.95, within
    assert float((err <= 2 * raw).double().mean()) < within[2]  # the calibration widens the raw std
    flat = batch.calibrate_std(raw, shipped._replace(travel=0.0), travel)
    assert float(M.std_coverage(est.joints, gt, flat, 2)) < within[2]
    far = travel > travel.quantile(0.75)  # the calibrated std grows with the travel more than the raw one
    assert float(cal[far].mean() / cal[~far].mean()) > float(raw[far].mean() / raw[~far].mean())


def test_warm_start_from_a_run_folder_and_upsampling(tmp_path):
    out, few = tmp_path / "cold", ["data.stop=100", *SHORT[1:]]
    assert main(["run", str(BATCH), *few, f"out_dir={out}"]) == 0
    cold = json.loads((out / "metrics.json").read_text())
    warm_dir = tmp_path / "warm"
    assert main(["run", str(BATCH), *few, f"init_from={out}", f"out_dir={warm_dir}"]) == 0
    warm = json.loads((warm_dir / "metrics.json").read_text())
    # the warm start begins where the cold solve ended (not at the per-frame/keyframe start) and only improves
    assert warm["solver_cost_start"] == pytest.approx(cold["solver_cost_final"], rel=1e-4)
    assert warm["solver_cost_start"] < 0.9 * cold["solver_cost_start"]
    assert warm["solver_cost_final"] <= warm["solver_cost_start"]
    _, prep, est = solve("batch.upsample=2", "data.stop=80")
    conf = prep.problem.observations.confidence
    assert est.q.shape[0] == conf.shape[0] == 40 and bool((conf[1::2] == 0).all())
    assert mpjpe_mm(prep, est) < 60.0  # measured 53.5 mm over all 40 frames (20 of them without 2D)


def test_warp_to_keyframes_meets_a_new_keyframe_and_keeps_the_met_ones():
    """The init_from start: a keyframe the start misses is met, the change fades linearly to the
    keyframes it already meets (anchors); a start meeting every keyframe is left as it is."""
    cfg = load_config(BATCH, SHORT)  # keyframes at frames 0 and 30
    prep = prepare(cfg)
    obj = trajectory_objective(prep.problem, cfg, torch.float64, torch.device("cpu"))
    assert obj.kf_frames.tolist() == [0, 30]
    q = obj.kf_target[0].expand(40, -1).clone()
    q[30] = obj.kf_target[1]
    q[1:30] = obj.kf_target[0] + (obj.kf_target[1] - obj.kf_target[0]) * torch.arange(1, 30)[:, None] / 30
    assert torch.equal(warp_to_keyframes(q, obj), q)  # meets both: unchanged
    i = prep.problem.skeleton.dof_names.index("lfemur.rx")
    moved = q.clone()
    moved[20:, i] += 0.3  # misses the keyframe at 30 by 0.3 rad (~9 sigma), meets frame 0
    warped = warp_to_keyframes(moved, obj)
    assert float((warped[30] - obj.kf_target[1]).abs().max()) < 1e-9
    assert float(warped[15, i] - moved[15, i]) == pytest.approx(-0.15)  # halfway down the ramp
    assert float((warped[0] - moved[0]).abs().max()) == 0.0
    assert float(warped[39, i] - moved[39, i]) == pytest.approx(-0.3)


def test_accuracy_on_a_clip_not_tuned_on(cmu_file):
    """CMU 35_01 (walk; not a dev clip), 3 s at 30 fps, 2 px noise, 10% missing, keyframes every second.
    Measured 2026-11-23 with the per-dof smoothing scales fitted to the dev clips (batch.prior: cmu):
    27.5 mm MPJPE from the interpolated keyframes and from the per-frame fits (one scale for all dofs:
    40.6 / 36.4 mm); 26.6 mm from either with the Cauchy smoothing loss (batch.smooth_loss),
    acceleration error 4.8 mm/f^2 against 46.2 for `method: frame` on the same observations; the other
    held-out clips are in docs/results.md."""
    amc, asf = cmu_file("35_01.amc"), cmu_file("35.asf")
    cfg = load_config(
        BATCH,
        [
            f"data.amc={amc}",
            f"data.asf={asf}",
            "data.stop=360",
            "progress=false",
            "batch.uncertainty=false",
            "keyframes.every_s=1",
        ],
    )
    prep = prepare(cfg)
    est = estimate_batch(prep.problem, cfg, torch.Generator())
    idx = prep.problem.keypoints.index()
    gt = prep.gt_joints.index_select(-2, idx).to(est.joints)
    assert mpjpe_mm(prep, est) < 30.0  # the target
    assert float(M.accel_error(est.joints.index_select(-2, idx), gt, root=0).mean()) < 10.0  # frame: 46


# -- bad input: one error line naming the file and the problem, exit 2, nothing written ---------------


@pytest.mark.parametrize(
    "text, suffix, fragments",
    [
        ("keyframes:\n  - frame: 999\n    dofs: {lfemur.rx: 10}\n", ".yaml", ["frame 999", "outside the sequence"]),
        ("keyframes:\n  - frame: 3\n    dofs: {lfemur.qq: 10}\n", ".yaml", ["unknown dof", "lfemur.qq"]),
        ("keyframes:\n  - frame: 3\n    joints: {nose: [0, 1, 2]}\n", ".yaml", ["unknown joint", "nose"]),
        ("keyframes:\n  - frame: 3\n    dofs: {lfemur.rx: 10}\n    sigma_deg: 0\n", ".yaml", ["sigma_deg", "> 0"]),
        ("keyframes:\n  - frame: 3\n    joints: {lwrist: [0, 1, 2]}\n    sigma_m: -1\n", ".yaml", ["sigma_m"]),
        ("keyframes: [ {frame: 3, dofs: {lfemur.rx: 1}\n", ".yaml", ["not valid YAML"]),
        ('{"keyframes": [{"frame": 3,}]}', ".json", ["not valid JSON"]),
    ],
)
def test_bad_keyframe_files(tmp_path, capsys, text, suffix, fragments):
    path = tmp_path / f"keys{suffix}"
    path.write_text(text)
    out = tmp_path / "out"
    fail(capsys, out, ["run", str(BATCH), *SHORT, f"keyframes.file={path}", f"out_dir={out}"], str(path), *fragments)


def test_lower_branch_replaces_the_solution_only_when_the_objective_prefers_it():
    """A flip branch replaces the solution when its whole energy is lower (the solve stopped in a local
    minimum), never when it is higher. The candidates here: the converged solution and its start."""
    cfg, prep, est = solve()
    obj = trajectory_objective(prep.problem, cfg, torch.float64, torch.device("cpu"))
    solution = est.q.to(torch.float64)[None]
    start = solution.clone()
    start[..., 6:] += 0.2  # every angle off: a trajectory the objective likes less
    assert float(total_energy(obj, start)[0]) > float(total_energy(obj, solution)[0])

    class Leaves:  # the fields of a BranchPosterior that lower_branch reads: (B, C, L, T, D) trajectories
        def __init__(self, q):
            self.branches = type("Branches", (), {"q": q[:, None, None]})()

    torch.testing.assert_close(lower_branch(obj, start, Leaves(solution)), solution)  # type: ignore[arg-type]
    assert lower_branch(obj, solution, Leaves(start)) is None  # type: ignore[arg-type]


def test_flip_restarts_never_raise_the_cost(tmp_path, capsys):
    runs = {}
    for rounds in (0, 1):
        out = tmp_path / f"r{rounds}"
        assert main(["run", str(BATCH), *SHORT[:3], f"batch.flip_restarts={rounds}", f"out_dir={out}"]) == 0
        runs[rounds] = json.loads((out / "metrics.json").read_text())
    assert runs[1]["solver_cost_final"] <= runs[0]["solver_cost_final"] * (1 + 1e-6)
    out = tmp_path / "bad"
    fail(
        capsys, out, ["run", str(BATCH), *SHORT[:3], "batch.flip_restarts=-1", f"out_dir={out}"], "batch.flip_restarts"
    )


def test_bad_init_from(tmp_path, capsys):
    out = tmp_path / "out"
    fail(
        capsys,
        out,
        ["run", str(BATCH), *SHORT, f"init_from={tmp_path}", f"out_dir={out}"],
        str(tmp_path),
        "not a run folder",
    )
    short = tmp_path / "short"
    assert main(["run", str(BATCH), "data.stop=120", *SHORT[1:], f"out_dir={short}"]) == 0
    fail(capsys, out, ["run", str(BATCH), *SHORT, f"init_from={short}", f"out_dir={out}"], str(short), "frames")
    fail(
        capsys,
        out,
        ["run", str(BATCH), *SHORT, f"init_from={short}", "model.freeze=[]", f"out_dir={out}", "data.stop=120"],
        str(short),
        "dofs",
    )


def test_no_keyframe_at_all_and_the_kjs_start(tmp_path, capsys):
    """`keyframes.first: false` with no other keyframe leaves the problem without any 3D keyframe; `batch.init: kjs`
    then starts from the kjs tracker's tree start (it needs no keyframe) and solves; a tracker told to start from
    frame 0's keyframe says there is none, in one line."""
    none = ["keyframes.every_s=null", "keyframes.first=false", "keyframes.last=false"]
    assert prepare(load_config(BATCH, [*SHORT, *none])).problem.keyframes is None
    out = tmp_path / "run"
    small = ["kjs.samples=32", "kjs.modes=4", "kjs.backward_pass=never", "batch.iterations=3"]
    assert main(["run", str(BATCH), *SHORT, *none, "batch.init=kjs", *small, f"out_dir={out}", "--quiet"]) == 0
    with np.load(out / "result.npz") as z:
        assert np.isfinite(z["q"]).all() and z["solver_cost"][-1] <= z["solver_cost"][0]
    k = tmp_path / "k"
    fail(capsys, k, ["run", str(BATCH), *SHORT, *none, "method=kjs", "kjs.init=keyframe", f"out_dir={k}"], "kjs.init")


def test_pose_prior_term_gradient_and_weight():
    """`batch.pose_prior_weight`: the CMU pose prior is a term of the batch energy (0 without it), and evaluate's
    gradient with it is autograd's gradient of the whole energy."""
    over = [*SHORT, "data.stop=40"]
    prep = prepare(load_config(BATCH, over))
    q = (
        prep.gt_q.double()[None]
        + 0.05 * torch.randn(prep.gt_q.shape, generator=torch.Generator().manual_seed(0)).double()
    )
    for weight in (0.0, 0.1):
        cfg = load_config(BATCH, [*over, f"batch.pose_prior_weight={weight}"])
        obj = trajectory_objective(prep.problem, cfg, torch.float64, torch.device("cpu"))
        energy = batch.evaluate(obj, q, with_jacobian=False).terms["pose_prior"]
        assert (float(energy.sum()) > 0) == (weight > 0)
        x = q.clone().requires_grad_()
        (want,) = torch.autograd.grad(total_energy(obj, x).sum(), x)
        torch.testing.assert_close(batch.evaluate(obj, q).g, want, rtol=1e-8, atol=1e-7)
