"""Tests for the sampling trackers (`method: kjs`, `css`, `ss`) on seeded real CMU clips: the true pose
stays among the K modes, the outputs are well formed and reproducible, bad settings are refused."""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import json
import math
import os
from pathlib import Path

import pytest
import torch

from ptrack.cli import main
from ptrack.estimators import ESTIMATORS
from ptrack.estimators.kjs import KJS, track
from ptrack.estimators.kjs.lattice import Lattice, recombine, smooth_lattice
from ptrack.estimators.kjs.model import make_setup
from ptrack.estimators.kjs.step import _allocate, _chain_votes
from ptrack.pipeline import metrics as M
from ptrack.pipeline.config import load_config
from ptrack.pipeline.evaluate import asf_for
from ptrack.pipeline.run import compute_metrics, prepare, reprojected_keypoints
from ptrack.problem import Problem

REPO = Path(__file__).resolve().parents[1]
KJS_YAML = REPO / "configs" / "kjs.yaml"
# the accuracy setting: 1 px noise, nothing missing, frame 0 given in 3D; 1 s of the kick
EXACT = ["data.stop=120", "observations.noise_px=1", "observations.missing=0", "progress=false"]
K = 8


def _run(*extra: str, seed: int = 1):
    cfg = load_config(KJS_YAML, [*EXACT, *extra])
    prep = prepare(cfg)
    est = ESTIMATORS[cfg.method](prep.problem, cfg, torch.Generator().manual_seed(seed))
    return prep, est


def _metrics(prep, cfg, method: str = "kjs") -> dict:
    """`method` on `prep`'s problem, seeded as `ptrack run` seeds it -> its metrics.json values."""
    est = ESTIMATORS[method](prep.problem, cfg, torch.Generator().manual_seed(cfg.seed + 1))
    return compute_metrics(prep, est, reprojected_keypoints(prep, est))[0]


def _errors(prep, est) -> tuple[float, float]:
    """-> (best trajectory MPJPE, best-of-K MPJPE) over the 17 keypoints, mm."""
    idx = prep.problem.keypoints.index()
    gt = prep.gt_joints.to(est.joints).index_select(-2, idx)
    traj = M.mpjpe(est.joints.index_select(-2, idx), gt).mean()
    best = M.best_of_k_mpjpe(est.hypotheses.index_select(-2, idx), gt).mean()
    return float(traj), float(best)


@pytest.fixture(scope="module")
def kjs_run():
    return _run()


def test_outputs(kjs_run):
    prep, est = kjs_run
    T, D, J = 30, prep.problem.skeleton.num_dofs, prep.problem.skeleton.num_joints
    assert est.q.shape == (T, D) and est.joints.shape == (T, J, 3)
    assert est.hypotheses.shape == (T, K, J, 3)
    assert est.hypothesis_weights.shape == est.hypothesis_costs.shape == (T, K)
    torch.testing.assert_close(est.hypothesis_weights.sum(-1), torch.ones(T), atol=1e-5, rtol=0)
    assert (est.hypothesis_weights >= 0).all() and torch.isfinite(est.hypotheses).all()
    # q/joints is one hypothesis per frame (the Viterbi path)
    d = (est.hypotheses - est.joints[:, None]).norm(dim=-1).amax(-1).amin(-1)
    assert float(d.max()) < 1e-5


def test_keyframe_accuracy(kjs_run):
    """Issue target: best-of-K under 20 mm at 1 px, nothing missing, keyframe start (measured on frames
    0-116 of 10_02: best-of-K 7.0 mm, best trajectory 7.7 mm (7.4 with `kjs.weight_memory` 1); 6.6 and 7.3
    with `kjs.dynamics` null; with the smoother, the default since 2026-11-25: 6.6 and 6.7)."""
    traj, best = _errors(*kjs_run)
    assert best < 20.0, f"best-of-K {best:.1f} mm"
    assert traj < 25.0, f"best trajectory {traj:.1f} mm"


def test_deterministic_per_seed():
    _, est = _run("data.stop=24", seed=1)
    _, again = _run("data.stop=24", seed=1)
    assert torch.equal(again.hypotheses, est.hypotheses)
    _, other = _run("data.stop=24", seed=2)
    assert not torch.equal(other.hypotheses, est.hypotheses)


def test_inference_mode_changes_nothing(monkeypatch):
    """The tracker runs in torch.inference_mode (faster bookkeeping): the same result bit for bit as without
    it, handed back as ordinary tensors that callers may modify in place; the L-BFGS polisher, which needs
    autograd, runs outside it."""
    prep, est = _run("data.stop=24", "kjs.init=tree", seed=3)
    tensors = [v for v in est if isinstance(v, torch.Tensor)] + list(est.terms.values())
    assert tensors and not any(t.is_inference() for t in tensors)
    est.q.add_(0.0)  # an inference tensor would refuse this outside inference mode
    # the skeleton's cached FK plan was built during the run: autograd through it works afterwards
    q = est.q[:2].clone().requires_grad_(True)
    prep.problem.skeleton.forward_kinematics(q).square().sum().backward()
    assert q.grad is not None and torch.isfinite(q.grad).all()
    with monkeypatch.context() as m:
        m.setattr(torch, "inference_mode", lambda mode=True: contextlib.nullcontext())
        _, plain = _run("data.stop=24", "kjs.init=tree", seed=3)
    for a, b in zip(est, plain):
        if isinstance(a, torch.Tensor):
            assert torch.equal(a, b)
    prep, lb = _run("data.stop=12", "kjs.polisher=lbfgs", seed=3)
    assert torch.isfinite(lb.hypotheses).all() and _errors(prep, lb)[1] < 30.0


def test_tree_start_passes_in_two_processes_give_what_one_gives(monkeypatch):
    """After a tree start the two passes are independent (the backward one from the last frame's tree start, with
    its own generator): with a thread budget of 2 they run in two processes at once (`ptrack.threads`), with 1 one
    after the other, and the result is the same bit for bit. So do the halves of the stages' batched polishing
    (`polish_rows`: here the recombination's 240 grafts)."""
    kjs_track = importlib.import_module("ptrack.estimators.kjs.track")  # the package exports a function `track`
    kjs_model = importlib.import_module("ptrack.estimators.kjs.model")
    forks, splits = [], []
    real = kjs_track.in_two_processes
    monkeypatch.setattr(kjs_track, "in_two_processes", lambda a, b: forks.append(1) or real(a, b))
    monkeypatch.setattr(kjs_model, "in_two_processes", lambda a, b: splits.append(1) or real(a, b))
    before = torch.get_num_threads()
    runs = {}
    try:
        for budget in (1, 2):
            torch.set_num_threads(budget)
            runs[budget] = _run("data.stop=24", "kjs.init=tree", seed=3)[1]
    finally:
        torch.set_num_threads(before)
    assert len(forks) == (1 if hasattr(os, "fork") else 0)
    assert (len(splits) > 0) == hasattr(os, "fork")
    for a, b in zip(runs[1], runs[2]):
        if isinstance(a, torch.Tensor):
            assert torch.equal(a, b)


def test_tree_init_needs_no_3d():
    """init: tree fits the rest pose in view and enumerates every flip: no keyframe used. The issue's
    target, best-of-K under 30 mm (measured here, frames 0-76 of 10_02: best-of-K 15.6 mm, best trajectory
    24.2 mm; without the backward pass, `kjs.backward_pass` never, 20.4 and 24.2; at the defaults of
    2026-11-25, with the smoother, 16.7 and 23.8)."""
    cfg = load_config(KJS_YAML, [*EXACT, "kjs.init=tree", "data.stop=80"])
    prep = prepare(cfg)
    bare = Problem(prep.problem.skeleton, prep.problem.keypoints, prep.problem.observations)  # no keyframes
    est = track(bare, cfg, torch.Generator().manual_seed(1), KJS)
    _traj, best = _errors(prep, est)
    assert best < 30.0, f"best-of-K {best:.1f} mm"


@pytest.mark.parametrize("method", ["css", "ss"])
def test_sampling_baselines_run_at_the_same_budget(method):
    """css/ss: no jumps, same hypothesis budget (measured best-of-K on these 10 frames: 5.7 and 5.7 mm; 4.7
    and 5.3 with the smoother, 2026-11-25)."""
    prep, est = _run(f"method={method}", "data.stop=40")
    _, best = _errors(prep, est)
    assert est.hypotheses.shape[1] == K and best < 25.0


@pytest.mark.parametrize("backward", ["tree", "always"])  # after a keyframe start: forward pass only, both
def test_frames_without_keypoints_are_carried(backward):
    # forward pass only: also without the smoother, which would draw the blind frames towards their neighbours
    smooth = "kjs.stages=[recombine, decode]" if backward == "tree" else "kjs.stages=[smooth, recombine, decode]"
    cfg = load_config(KJS_YAML, [*EXACT, "data.stop=32", f"kjs.backward_pass={backward}", smooth])
    prep = prepare(cfg)
    obs = prep.problem.observations
    conf = obs.confidence.clone()
    conf[4:6] = 0.0
    blind = Problem(
        prep.problem.skeleton, prep.problem.keypoints, dataclasses.replace(obs, confidence=conf), prep.problem.keyframes
    )
    est = track(blind, cfg, torch.Generator().manual_seed(0), KJS)
    assert torch.isfinite(est.q).all() and torch.isfinite(est.hypotheses).all()
    assert torch.allclose(est.hypothesis_weights.sum(-1), torch.ones(obs.num_frames, dtype=est.q.dtype))
    if backward == "tree":  # one pass: the modes carried by the (constant-position) dynamics
        assert torch.equal(est.hypotheses[4], est.hypotheses[3])


def test_tree_start_with_a_blind_last_frame():
    """With nothing seen on the last frame the backward pass starts from the forward pass's last modes
    alone (no tree start there); blind frames in between are carried in both passes."""
    cfg = load_config(KJS_YAML, [*EXACT, "data.stop=32", "kjs.init=tree"])
    prep = prepare(cfg)
    obs = prep.problem.observations
    conf = obs.confidence.clone()
    conf[4:6] = 0.0
    conf[-1] = 0.0
    blind = Problem(prep.problem.skeleton, prep.problem.keypoints, dataclasses.replace(obs, confidence=conf))
    est = track(blind, cfg, torch.Generator().manual_seed(0), KJS)
    assert torch.isfinite(est.q).all() and torch.isfinite(est.hypotheses).all()
    assert torch.allclose(est.hypothesis_weights.sum(-1), torch.ones(obs.num_frames, dtype=est.q.dtype))


def test_chain_votes_follow_the_covariance(kjs_run):
    prep, _ = kjs_run
    cfg = load_config(KJS_YAML, EXACT)
    s = make_setup(prep.problem, cfg, KJS)
    D = prep.problem.skeleton.num_dofs
    chol = torch.eye(D).expand(2, D, D).clone() * 1e-3
    larm = s.chain_dofs[0]
    chol[1][larm] *= 100.0  # mode 1 is uncertain about the left arm
    votes = _chain_votes(s, chol)
    assert torch.allclose(votes.sum(-1), torch.ones(2))
    assert int(votes[1].argmax()) == 0 and float(votes[1, 0]) > 0.99


def test_merge_takes_the_two_passes_in_turn(kjs_run):
    """A frame's modes after the backward pass: the best trajectory's forward mode first, then the two
    passes' modes in turn, heaviest first; a mode within distinct_deg of one ranked before it is dropped;
    at most K; weights the mean of the two passes' weights, renormalised."""
    from ptrack.estimators.kjs.step import merge_mixtures
    from ptrack.hypotheses.mixture import Modes

    prep, _ = kjs_run
    cfg = load_config(KJS_YAML, [*EXACT, "kjs.modes=4"])
    s = make_setup(prep.problem, cfg, KJS)
    D = prep.problem.skeleton.num_dofs

    def modes(offsets_deg, weights):
        q = torch.zeros(len(offsets_deg), D)
        q[:, 5] = torch.deg2rad(torch.tensor(offsets_deg))
        w = torch.tensor(weights)
        return Modes(q, w, -torch.log(w), torch.eye(D).expand(len(w), D, D), torch.zeros_like(q))

    forward = modes([0.0, 10.0, 20.0], [0.6, 0.3, 0.1])
    backward = modes([30.0, 10.5, 40.0], [0.5, 0.4, 0.1])  # its second lies within 3 deg of the forward's
    got = merge_mixtures(s, forward, backward, lead=2)
    # in turn: f2 (the lead), b0, f0, b1, f1 (a repeat of b1: dropped), b2 -> the first four distinct
    torch.testing.assert_close(torch.rad2deg(got.q[:, 5]), torch.tensor([20.0, 30.0, 0.0, 10.5]))
    torch.testing.assert_close(got.weight, torch.tensor([0.05, 0.25, 0.3, 0.2]) / 0.8)
    torch.testing.assert_close(got.cost, -torch.log(torch.tensor([0.1, 0.5, 0.6, 0.4])))


def test_merge_serves_each_depth_order_first(kjs_run):
    """Both passes often hold one reading of the body many times over and the other reading of a limb only
    in a light mode: the first mode of each depth order of the limbs is taken before any repeat, so K
    slots keep the light one (02_01's left thigh after it crosses the image plane)."""
    from ptrack.estimators.kjs.step import _depth_orders, merge_mixtures
    from ptrack.hypotheses.mixture import Modes

    prep, _ = kjs_run
    cfg = load_config(KJS_YAML, [*EXACT, "kjs.modes=4"])
    s = make_setup(prep.problem, cfg, KJS)
    names = prep.problem.skeleton.dof_names
    neck, thigh = names.index("lowerneck.ry"), names.index("lfemur.rx")
    q0 = prep.gt_q[0].to(prep.problem.observations.keypoints.dtype)

    def modes(turns_deg, weights):
        q = q0.repeat(len(weights), 1)
        for i, (dof, deg) in enumerate(turns_deg):
            q[i, dof] += math.radians(deg)
        w = torch.tensor(weights)
        D = q.shape[1]
        return Modes(q, w, -torch.log(w), torch.eye(D).expand(len(w), D, D), torch.zeros_like(q))

    forward = modes([(neck, 0.0), (neck, 5.0), (neck, 10.0)], [0.5, 0.3, 0.2])
    backward = modes([(neck, 15.0), (neck, 20.0), (thigh, -40.0)], [0.6, 0.3, 0.1])  # the last: knee behind
    orders = _depth_orders(s, torch.cat([forward.q, backward.q]))
    assert (orders[:5] == orders[0]).all() and not (orders[5] == orders[0]).all()  # one order, then another
    got = merge_mixtures(s, forward, backward, lead=0)
    # in turn: f0, b0, f1, b1 would fill K = 4; b2 is the only mode of its order, so it comes second
    torch.testing.assert_close(got.q, torch.stack([forward.q[0], backward.q[2], backward.q[0], forward.q[1]]))


def test_allocation_follows_the_weights_with_one_sample_per_mode_at_least():
    weight = torch.tensor([0.97, 0.01, 0.01, 0.01])
    by_weight = _allocate(weight, 100)
    assert sum(by_weight) == 100 and min(by_weight[1:]) >= 1 and max(by_weight[1:]) <= 2
    assert _allocate(torch.tensor([0.5, 0.3, 0.2]), 10) == [5, 3, 2]
    assert _allocate(weight, 3) == [3, 0, 0, 0]  # fewer samples than modes: by weight alone


@pytest.mark.parametrize(
    "override, key",
    [
        ("kjs.chains=[larm,tail]", "kjs.chains"),
        ("kjs.modes=0", "kjs.modes"),
        ("kjs.samples=4", "kjs.samples"),
        ("kjs.scale=-1", "kjs.scale"),
        ("kjs.tail=uniform", "kjs.tail"),
        ("kjs.init=guess", "kjs.init"),
        ("kjs.even_share=0.5", "kjs.even_share"),
        ("kjs.weight_memory=-0.5", "kjs.weight_memory"),
        ("kjs.stages=[smooth, prior]", "kjs.stages"),
        ("kjs.stages=[decode, smooth]", "kjs.stages"),
        ("kjs.viterbi_sigma_m=0", "kjs.viterbi_sigma_m"),
        ("kjs.dynamics=walk", "kjs.dynamics"),
        ("kjs.dynamics_floor=-0.1", "kjs.dynamics_floor"),
        ("kjs.backward_pass=sideways", "kjs.backward_pass"),
        ("kjs.smooth_scale=0", "kjs.smooth_scale"),
        ("kjs.smooth_link_m=0.1", "kjs.smooth_link_m"),
        ("kjs.ceiling_deg=30", "kjs.ceiling_deg"),
        ("kjs.recombine_sigma_m=0", "kjs.recombine_sigma_m"),
        ("kjs.recombine=true", "kjs.recombine"),
        ("kjs.pose_mixture_weight=-1", "kjs.pose_mixture_weight"),
        ("kjs.pose_mixture_weight=.nan", "kjs.pose_mixture_weight"),
    ],
)
def test_bad_settings_are_one_line_errors(tmp_path, capsys, override, key):
    out = tmp_path / "run"
    rc = main(["run", str(KJS_YAML), "data.stop=12", override, f"out_dir={out}", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and err[0].startswith("ptrack: error:") and key in err[0], err
    assert not out.exists()


@pytest.mark.parametrize("table_name", ["cmu-train", "cmu"])
def test_per_dof_dynamics(table_name):
    """`kjs.dynamics`: each dof's velocity std per frame is its CMU RMS velocity times the frame interval
    (30 fps here) and `kjs.dynamics_scale`, at least the floor; the root's position keeps `kjs.prior_sigma`."""
    from ptrack.body.pose_prior import smoothing_prior

    table = smoothing_prior(table_name)["velocity"]
    for floor in (0.0, 0.02):
        cfg = load_config(KJS_YAML, ["data.stop=12", f"kjs.dynamics={table_name}", f"kjs.dynamics_floor={floor}"])
        setup = make_setup(prepare(cfg).problem, cfg, KJS)
        names = setup.problem.skeleton.dof_names
        sigma = dict(zip(names, setup.dynamics_sigma.tolist()))
        scale = cfg.kjs.dynamics_scale
        assert sigma["ltibia.rx"] == pytest.approx(max(table["ltibia.rx"] / 30 * scale, floor), rel=1e-6)  # a knee
        assert sigma["head.rx"] == pytest.approx(max(table["head.rx"] / 30 * scale, floor), rel=1e-6)  # the head
        assert sigma["root.tx"] == pytest.approx(cfg.kjs.prior_sigma, rel=1e-6)  # not in the table
        assert min(sigma.values()) >= floor * (1 - 1e-6)


def test_dynamics_default_and_null():
    """The default dynamics are the table fitted to the training clips; null: one std for every dof."""
    from ptrack.body.pose_prior import smoothing_prior

    cfg = load_config(KJS_YAML, ["data.stop=12"])
    assert cfg.kjs.dynamics == "cmu-train"
    problem = prepare(cfg).problem
    sigma = dict(zip(problem.skeleton.dof_names, make_setup(problem, cfg, KJS).dynamics_sigma.tolist()))
    table = smoothing_prior("cmu-train")["velocity"]
    assert cfg.kjs.dynamics_scale == 1.5
    expected = max(table["lfemur.rx"] / 30 * 1.5, cfg.kjs.dynamics_floor)
    assert sigma["lfemur.rx"] == pytest.approx(expected, rel=1e-6)
    flat_cfg = load_config(KJS_YAML, ["data.stop=12", "kjs.dynamics=null"])
    assert flat_cfg.kjs.dynamics is None
    flat = make_setup(prepare(flat_cfg).problem, flat_cfg, KJS).dynamics_sigma
    assert flat == flat_cfg.kjs.prior_sigma  # every dof: the float itself


def test_run_writes_hypotheses(tmp_path):
    out = tmp_path / "kjs"
    assert main(["run", str(KJS_YAML), "data.stop=16", f"out_dir={out}", "--quiet"]) == 0
    m = json.loads((out / "metrics.json").read_text())
    assert m["method"] == "kjs" and m["best_of_k_mpjpe_mm"] <= m["mpjpe_mm"] + 1e-6
    # the probabilities' metrics (issue 41): the heaviest mode is no better than the best of K, shares in [0, 1]
    assert m["heaviest_mpjpe_mm"] >= m["best_of_k_mpjpe_mm"] - 1e-6
    assert 0 <= m["heaviest_is_best_share"] <= 1 and 0 <= m["depth_order_brier"] <= 1
    assert 0 <= m["depth_order_in_modes"] <= 1


def test_tree_init_when_every_flip_is_pruned(cmu_file):
    """On the first frame of CMU 09_06 (a run) seen as configs/eval_kjs.yaml sees it, every flipped leaf
    broke the limits and the tracker crashed with no candidate left; the fitted pose itself always stays
    a candidate. (The camera frames the whole 3 s, so the problem is cut to 4 frames after `prepare`.)"""
    cfg = _clip(cmu_file, "09_06.amc", "kjs.init=tree")
    prep = prepare(cfg)
    obs = prep.problem.observations
    short = dataclasses.replace(obs, keypoints=obs.keypoints[:4], confidence=obs.confidence[:4], times=obs.times[:4])
    est = track(
        Problem(prep.problem.skeleton, prep.problem.keypoints, short), cfg, torch.Generator().manual_seed(0), KJS
    )
    assert torch.isfinite(est.hypotheses).all() and est.hypotheses.shape[:2] == (4, K)


def _clip(cmu_file, name: str, *extra: str):
    """`configs/eval_kjs.yaml` on the CMU clip `name` (e.g. "49_18.amc") and its skeleton, as `ptrack
    evaluate` runs it (2 px noise, 10% missing), with the overrides `extra`."""
    amc = cmu_file(name)
    overrides = [f"data.amc={amc}", f"data.asf={asf_for(amc)}", "progress=false", *extra]
    return load_config(REPO / "configs" / "eval_kjs.yaml", overrides)


def _clip_1px(cmu_file, name: str, *extra: str):
    """`_clip` at the issue's accuracy setting: 1 px noise (and sigma), nothing missing."""
    return _clip(cmu_file, name, "observations.noise_px=1", "observations.missing=0", "costs.sigma_px=1", *extra)


def _balance_1px(cmu_file, *extra: str):
    """`_clip_1px` on CMU 49_18 (one-leg balance)."""
    return _clip_1px(cmu_file, "49_18.amc", *extra)


def _left_knee_true_side(prep, hypotheses, frames: slice) -> int:
    """How many of `frames` have a hypothesis (T, K, J, 3) whose left knee is on the truth's side of the
    hip in depth; the truth must be well off the image plane there (5 cm), where the order is defined."""
    cam, names = prep.problem.observations.camera, prep.problem.skeleton.joint_names
    hip, knee = names.index("lhipjoint"), names.index("lfemur")

    def knee_behind(joints):  # (..., J, 3) -> (...) depth of the left knee behind the hip, metres
        depth = cam.world_to_camera(joints)[..., 2]
        return depth[..., knee] - depth[..., hip]

    truth = knee_behind(prep.gt_joints[frames])
    assert (truth > 0.05).all(), f"the truth's knee is near the image plane: {truth.tolist()}"
    return int((knee_behind(hypotheses[frames]) * truth[:, None].to(hypotheses) > 0).any(-1).sum())


def test_tree_start_keeps_raised_arms(cmu_file):
    """Frame 0 of CMU 49_18 (a one-leg balance, both arms raised sideways) at 1 px, nothing missing, from
    the tree start alone. Each flip combination reprojects alike; ranked with the start prior (per dof,
    around real people's mean pose: arms down) the raised arms were never among the 4K refined and the
    best of the K modes was 82 mm off. Ranked by the frame's own cost they are: 19 mm (measured)."""
    cfg = _balance_1px(cmu_file, "kjs.init=tree")
    prep = prepare(cfg)
    obs = prep.problem.observations
    first = dataclasses.replace(obs, keypoints=obs.keypoints[:1], confidence=obs.confidence[:1], times=obs.times[:1])
    est = track(
        Problem(prep.problem.skeleton, prep.problem.keypoints, first), cfg, torch.Generator().manual_seed(0), KJS
    )
    idx = prep.problem.keypoints.index()
    gt = prep.gt_joints[:1].to(est.joints).index_select(-2, idx)
    best = float(M.best_of_k_mpjpe(est.hypotheses.index_select(-2, idx), gt).mean())
    assert best < 30.0, f"best-of-K on frame 0: {best:.1f} mm"


def test_a_mode_that_lost_out_earlier_survives(cmu_file):
    """CMU 49_18 at 1 px, nothing missing, as `ptrack evaluate --seeds 3` runs it. With every past frame's
    evidence multiplied into the weights (`kjs.weight_memory` 1) the modes on the true branch of the right
    arm fell to weight ~0 while the two branches reprojected alike; at frame 61 they were pruned, though on
    frame 60 one of them was the cheapest mode, and the arm stayed flipped in depth for the rest of the
    clip: 0.32 of the frames (best trajectory 29.1 mm). With 0.5: no frame, 15.3 mm (14.0 with the smoother,
    2026-11-25): the forward pass's path (`kjs.stages` without `decode`) is asserted (14.2 mm). The MAP path of the
    final modes (`decode`, the default) takes the flipped arm on 0.5 of the frames here (38.8 mm: the lattice holds
    both readings from frame 1 to 47 and the sum of small differences of the frame costs chooses the wrong one).
    With the pose prior of before 2026-11-29 the paper's re-weighting (`kjs.reweight: mixture`) mended it (11.6 mm);
    with the prior fitted without the held-out clips it takes the flipped arm too (0.99 of the frames): one seed's
    choice between readings that reproject alike, not asserted."""
    for extra in ("kjs.stages=[smooth, recombine]",):
        cfg = _balance_1px(cmu_file, "seed=3", extra)
        prep = prepare(cfg)
        est = ESTIMATORS["kjs"](prep.problem, cfg, torch.Generator().manual_seed(cfg.seed + 1))  # as `ptrack run`
        rates = compute_metrics(prep, est, reprojected_keypoints(prep, est))[0]["flip_error_rate_per_limb"]
        arm = max(rates["r_shoulder-r_elbow"], rates["r_elbow-r_wrist"])
        assert arm < 0.1, f"{extra}: right arm flipped in {arm:.2f} of the frames"
        traj, _ = _errors(prep, est)
        assert traj < 22.0, f"{extra}: best trajectory {traj:.1f} mm"


def test_orders_first_ranks_each_depth_order_before_repeats(kjs_run):
    """`_orders_first` keeps the first pose of each depth order where it was and moves every repeat of an
    order behind all of them, in their old order: the ranking the backward pass keeps its K modes by."""
    from ptrack.estimators.kjs.step import _depth_orders, _orders_first

    prep, _ = kjs_run
    s = make_setup(prep.problem, load_config(KJS_YAML, EXACT), KJS)
    names = prep.problem.skeleton.dof_names
    neck, thigh = names.index("lowerneck.ry"), names.index("lfemur.rx")
    q = prep.gt_q[0].to(prep.problem.observations.keypoints.dtype).repeat(5, 1)
    q[1, neck] += math.radians(5.0)  # the same depth order as pose 0
    q[2, thigh] -= math.radians(40.0)  # the knee behind the hip: another order
    q[3, neck] += math.radians(10.0)  # pose 0's order again
    q[4, thigh] -= math.radians(40.0)
    q[4, neck] += math.radians(5.0)  # pose 2's order again
    orders = _depth_orders(s, q)
    assert (orders[[1, 3]] == orders[0]).all() and (orders[4] == orders[2]).all()
    assert not (orders[2] == orders[0]).all()
    rank = torch.tensor([0, 1, 2, 3, 4])
    assert torch.argsort(_orders_first(s, q, rank)).tolist() == [0, 2, 1, 3, 4]
    rank = torch.tensor([4, 3, 2, 1, 0])  # the other way round: pose 4 first, then 3
    assert torch.argsort(_orders_first(s, q, rank)).tolist() == [4, 3, 2, 1, 0]
    rank = torch.tensor([1, 4, 3, 0, 2])  # pose 3 leads pose 0's order, pose 4 leads the other
    assert torch.argsort(_orders_first(s, q, rank)).tolist() == [3, 4, 0, 2, 1]


def test_backward_pass_keeps_a_branch_the_forward_pass_lost(cmu_file):
    """CMU 49_18 at 1 px from the tree start (no 3D input), as `ptrack evaluate` runs seed 0. On frame 0
    the true branch of the right arm reprojects like the flipped one but costs more in the start prior:
    the forward pass weighted it 0.01 and lost it by frame 57; its modes are right again only from frame
    75. The backward pass from the last frame carries that reading back to frame 0 (measured best-of-K: 32.6 mm
    forward only, 19.2 mm with both passes started from the forward pass's last modes alone, 15.9 mm with the last
    frame's own tree start beside them; since 2026-11-30 the backward pass starts from that tree start alone, on its
    own generator: 15.4 mm, 22.0 forward only). The two passes' trajectories face
    the same way (within `HEADING_SPLIT_DEG`), so the forward pass's modes lead the merge (without `decode` in
    `kjs.stages` the run reports that path; compared without the smoother, which moves each pose towards its
    neighbours among either run's hypotheses)."""
    runs = {}
    for backward in ("tree", "never"):
        cfg = _balance_1px(
            cmu_file,
            "kjs.init=tree",
            "seed=0",
            f"kjs.backward_pass={backward}",
            "kjs.stages=[recombine]",
        )
        prep = prepare(cfg)
        runs[backward] = ESTIMATORS["kjs"](prep.problem, cfg, torch.Generator().manual_seed(1))  # as `ptrack run`
    est = runs["tree"]
    _, best = _errors(prep, est)
    assert best < 25.0, f"best-of-K {best:.1f} mm"
    assert torch.equal(est.joints, runs["never"].joints)  # the same best trajectory
    assert torch.equal(est.joints, est.hypotheses[:, 0])  # which is the first hypothesis of every frame


def test_backward_pass_carries_a_limb_across_the_image_plane(cmu_file):
    """CMU 02_01 (walk) at 1 px, nothing missing, after a keyframe start, its first 21 frames (`data.stop` 84), as
    `ptrack evaluate --seeds 0-4` runs them. The left knee passes from in front of the hip to behind it over frames
    7-8, and the forward pass, lagging behind, may hold only the mirrored side on frames 13-18 (the 2D cannot tell
    the two apart near the image plane). The backward pass, fed each frame by the forward
    pass's modes (`feed_backward`),
    carries the true side found later back. Which seed shows it is a matter of the last bits (seed 3 on the full 90
    frames: 0 of 6 frames forward only, 6 with both; seed 0 lost the true side in both passes after the polishing's
    summation order changed), so this judges five seeds together. Measured, frames 13-18 with the true side among
    the K modes, forward pass alone (`kjs.backward_pass` tree, which after a keyframe start means forward only) ->
    both passes, seeds 0-4 summed; mean best-of-K: this Xeon 27 -> 30 of 30, 22.5 -> 20.3 mm; under
    ATEN_CPU_CAPABILITY=default 27 -> 30, 23.3 -> 19.1 mm; on 30 frames (`data.stop` 120; the camera aims at the
    clip's bounding box, so another view) 25 -> 30, 21.8 -> 19.9 mm and 25 -> 30, 20.9 -> 18.1 mm. On 21 frames seed
    3 alone loses the true side forward (3 of 6 frames, natively and under default); one seed's best-of-K may get
    worse by a few tenths of a mm with both passes (seed 2: 26.8 -> 27.2 here, 27.0 -> 19.6 under default).
    With `kjs.reweight: mixture` (the paper's re-weighting, which keeps fewer light modes) 26 -> 27 of 30; the
    mechanism is asserted under `memory`, the default, as it was measured.
    Asserted: 28 of the 30 frames with both passes, more than forward only, mean best-of-K lower by 1 mm. Without
    the smoother, so that the best trajectories can be compared: the best trajectory is the forward pass's, bit for
    bit (both runs' forward passes are the same computation in one process; measured bit-equal for every seed
    natively and under default)."""
    found: dict[str, list[int]] = {"tree": [], "always": []}
    best: dict[str, list[float]] = {"tree": [], "always": []}
    for seed in range(5):
        runs = {}
        for backward in ("tree", "always"):  # after a keyframe start "tree" means the forward pass alone
            overrides = [f"kjs.backward_pass={backward}", f"seed={seed}", "data.stop=84"]
            overrides.append("kjs.stages=[recombine]")  # the forward pass's best trajectory, to compare bit for bit
            overrides.append("kjs.reweight=memory")  # as measured (the default); mixture in the docstring
            cfg = _clip_1px(cmu_file, "02_01.amc", *overrides)
            prep = prepare(cfg)
            est = ESTIMATORS["kjs"](prep.problem, cfg, torch.Generator().manual_seed(seed + 1))  # as `ptrack run`
            runs[backward] = est
            found[backward].append(_left_knee_true_side(prep, est.hypotheses, slice(13, 19)))
            best[backward].append(_errors(prep, est)[1])
        assert torch.equal(runs["always"].joints, runs["tree"].joints)  # the best trajectory is the forward pass's
    both, forward = sum(found["always"]), sum(found["tree"])
    assert both >= 28 and both > forward, f"true side on frames 13-18 (seeds 0-4): {found}"
    mean = {b: sum(v) / len(v) for b, v in best.items()}
    assert mean["always"] < mean["tree"] - 1.0, f"best-of-K {best} mm"


def test_backward_pass_keeps_a_light_depth_order(cmu_file):
    """CMU 07_05 (slow walk) at 1 px, nothing missing, after a keyframe start, as `ptrack evaluate --seeds
    0-2` runs it. The left knee passes behind the hip at frame 22 (frames 24-34: truth 8 to 23 cm behind)
    and the 2D cannot tell that from the mirrored reading; the forward pass may hold the mirrored one
    there, and the backward pass, keeping the heaviest mode of each depth order first (`_orders_first`,
    tested alone below), carries the true one back. Whether a given seed needs it is a matter of the last
    bits (seed 5: 11 of 11 frames on the author's machine, 2 of 11 on another Xeon), so this judges three
    seeds together. Measured (frames 24-34 with the true side among the K modes, seeds 0/1/2; best-of-K
    mm): this Xeon 11/11/11, 17.4/16.6/14.1; under ATEN_CPU_CAPABILITY=default 8/11/11, 18.5/16.2/14.3;
    without `_orders_first` 6/11/11, 18.7/17.2/13.5; the forward pass alone (`kjs.backward_pass` never)
    4/11/11, 21.3/18.0/14.6. Asserted: 27 of the 33 frames, mean best-of-K under 20 mm. Only seed 0 needs
    the backward pass here, so this fails on the forward pass alone but by one frame; that `_orders_first`
    keeps the light order is asserted exactly by the two tests of it below. Measured with `kjs.reweight: memory`
    (the default); with `mixture` (2026-11-29, this Xeon) 8/6/10 frames, 17.4/20.2/15.1 mm, against 7/6/8 and
    19.7/21.3/17.3 for the forward pass alone: the paper's re-weighting keeps fewer light modes here, and the
    held-out clips' truth-in-modes is the same under both (docs/results.md)."""
    found, best = [], []
    for seed in (0, 1, 2):
        cfg = _clip_1px(cmu_file, "07_05.amc", f"seed={seed}", "kjs.reweight=memory")
        prep = prepare(cfg)
        est = ESTIMATORS["kjs"](prep.problem, cfg, torch.Generator().manual_seed(seed + 1))  # as `ptrack run`
        found.append(_left_knee_true_side(prep, est.hypotheses, slice(24, 35)))
        best.append(_errors(prep, est)[1])
    assert sum(found) >= 27, f"true side on {found} of frames 24-34 (seeds 0-2)"
    assert sum(best) / 3 < 20.0, f"best-of-K {[round(b, 1) for b in best]} mm"


def test_backward_pass_restarts_on_the_last_frame(cmu_file):
    """CMU 49_18 from the tree start at the issue's evaluation setting (2 px, 10% missing), seeds 0-2 as
    `ptrack evaluate` runs them. Frame 0's tree start misses the body's reading (its best mode 69-196 mm
    off over seeds 0-4) and the forward pass never finds it (seed 0: best trajectory 243 mm, its body turned 52°
    from the truth's). The backward pass starts from the last frame's own tree start, which gets it
    right (seed 0 best-of-K 22.2 mm; 98.3 when the backward pass started from the forward pass's last
    modes alone). Measured with the pose prior fitted without the held-out clips (2026-11-29), the tree start beside
    the forward pass's last modes: best-of-K 20.4, 24.3, 26.0 mm, best trajectory 45.8, 47.4, 48.7 (24.8 on seed 0
    with the old prior); from the tree start alone (2026-11-30): 20.5, 24.1, 26.5 and 45.8, 25.7, 49.2. The modes hold
    the body's reading on every seed, and the best trajectory, one of them in every frame, is far from the forward
    pass's."""
    for seed in range(3):
        cfg = _clip(cmu_file, "49_18.amc", "kjs.init=tree", f"seed={seed}")
        prep = prepare(cfg)
        est = ESTIMATORS["kjs"](prep.problem, cfg, torch.Generator().manual_seed(seed + 1))  # as `ptrack run`
        traj, best = _errors(prep, est)
        assert best < 35.0, f"seed {seed}: best-of-K {best:.1f} mm"
        assert traj < 65.0, f"seed {seed}: best trajectory {traj:.1f} mm"
        d = (est.hypotheses - est.joints[:, None]).norm(dim=-1).amax(-1).amin(-1)
        assert float(d.max()) < 1e-5  # the best trajectory is one of the modes in every frame


def test_best_trajectory_beats_frame(cmu_file):
    """The issue's third accuracy target on a seeded dev clip, CMU 09_06 (a run), at the evaluation setting
    (2 px, 10% missing, seed 0 as `ptrack evaluate` runs it), both methods on the same observations.
    Measured: kjs (keyframe start) best trajectory 39.5 mm, flip rate 0.035 (37.2 mm, 0.029 with the
    smoother, 2026-11-25); `frame` 63.1 mm, 0.104. On
    49_18 (the one-leg balance) the two are level in flip rate, seed for seed (docs/results.md)."""
    cfg = _clip(cmu_file, "09_06.amc")
    prep = prepare(cfg)
    got = {}
    for method in ("kjs", "frame"):
        metrics = _metrics(prep, cfg, method)
        got[method] = (metrics["mpjpe_mm"], metrics["flip_error_rate"])
    assert got["kjs"][0] < got["frame"][0] and got["kjs"][1] < got["frame"][1], f"(MPJPE mm, flip rate): {got}"


def test_tree_start_headings(kjs_run):
    """The tree start turns the rest pose to 8 headings about the world's up axis (Y), each leaned
    forward and back: the hip line sweeps the circle, the spine stays vertical at lean 0."""
    from ptrack.problem import root_headings

    prep, _ = kjs_run
    sk = prep.problem.skeleton
    q0 = torch.zeros(sk.num_dofs)
    starts = root_headings(sk, q0, 8, (0.0, 0.5, -0.5))
    assert starts.shape == (24, sk.num_dofs)
    X = sk.forward_kinematics(starts)
    lhip, rhip, thorax = (sk.joint_index(n) for n in ("lhipjoint", "rhipjoint", "thorax"))
    hips = X[:, lhip] - X[:, rhip]
    heading = torch.atan2(hips[:, 0], hips[:, 2])
    turns = torch.remainder(heading[::3] - heading[0], 2 * torch.pi)
    torch.testing.assert_close(turns.sort().values, torch.arange(8) * torch.pi / 4, atol=1e-4, rtol=0)
    spine = X[::3, thorax] - X[::3, 0]  # a turn about Y keeps its height and its horizontal length
    torch.testing.assert_close(spine[:, 1], spine[:1, 1].expand(8), atol=1e-5, rtol=0)
    torch.testing.assert_close(
        spine[:, [0, 2]].norm(dim=-1), spine[:1, [0, 2]].norm(dim=-1).expand(8), atol=1e-5, rtol=0
    )
    leaned = X[1::3, thorax] - X[1::3, 0]
    assert float((leaned[:, [0, 2]].norm(dim=-1) - spine[:, [0, 2]].norm(dim=-1)).min()) > 0.1  # 0.5 rad of lean


def test_principal_directions_follow_the_largest_variance(kjs_run):
    from ptrack.estimators.kjs import principal_directions

    prep, _ = kjs_run
    sk = prep.problem.skeleton
    q = prep.gt_q[:2].to(torch.float64)
    D = sk.num_dofs
    d = sk.dof_names.index("lfemur.rx")
    chol = torch.eye(D, dtype=torch.float64).expand(2, D, D).clone() * 0.01
    chol[:, d, d] = 0.2 * 2.0  # std 0.2 rad after dividing out the scale 4
    got = principal_directions(sk, q, chol, 4.0)
    step = torch.zeros(D, dtype=torch.float64)
    step[d] = 0.2
    want = sk.forward_kinematics(q + step) - sk.forward_kinematics(q)
    torch.testing.assert_close(got, want, atol=1e-9, rtol=0)
    assert float(got[:, sk.joint_index("ltibia")].norm(dim=-1).min()) > 0.05  # the knee swings
    assert float(got[:, sk.joint_index("rtibia")].norm()) < 1e-9  # the other leg does not


def test_smoothing_moves_hypotheses_towards_their_nearest_neighbours(kjs_run):
    """`smooth_lattice` re-polishes a hypothesis towards its nearest neighbours in the frames before and after
    (padding is no neighbour); padding stays as it is."""
    prep, _ = kjs_run
    cfg = load_config(KJS_YAML, EXACT)
    s = make_setup(prep.problem, cfg, KJS)
    sk = prep.problem.skeleton
    q = prep.gt_q[10:13].to(torch.float32)
    turned = q.clone()
    turned[:, sk.dof_names.index("root.ry")] += math.pi / 2
    hq = torch.stack([q, turned], 1)  # (3, 2, D)
    hq[1, 0, sk.dof_names.index("lfemur.rx")] += 0.3  # a jittered thigh between its neighbours
    hw = torch.tensor([[1.0, 0.0], [0.5, 0.5], [1.0, 0.0]])  # the turned body is padding on frames 10 and 12
    hc = torch.zeros(3, 2)
    hl = torch.zeros(3, 2, sk.num_dofs, sk.num_dofs)
    sq, sw, sc, sl, sj = smooth_lattice(s, Lattice(hq, hw, hc, hl, sk.forward_kinematics(hq)))
    assert torch.equal(sw, hw)
    assert torch.equal(sq[[0, 2], 1], hq[[0, 2], 1]) and torch.equal(sc[[0, 2], 1], hc[[0, 2], 1])  # padding
    assert not torch.equal(sq[1, 1], hq[1, 1])  # the turned body is linked to its nearest neighbours too
    thigh = sk.dof_names.index("lfemur.rx")
    assert abs(float(sq[1, 0, thigh] - q[1, thigh])) < 0.5 * 0.3  # drawn back towards its neighbours
    assert bool(torch.isfinite(sc[:, 0]).all()) and float(sl[1, 0].abs().sum()) > 0
    torch.testing.assert_close(sj, sk.forward_kinematics(sq))  # the smoothed poses' joints


def test_recombination_joins_the_right_reading_of_each_chain(kjs_run):
    """`recombine`: the best trajectory's mode has the left arm wrong, another mode the right leg, a third
    both; no mode is right in both. The recombined pose takes each chain's reading on its own and is the
    truth; it fills the padding slot, and the best trajectory's mode is kept as it was."""
    prep, _ = kjs_run
    cfg = load_config(KJS_YAML, EXACT)
    s = make_setup(prep.problem, cfg, KJS)
    sk = prep.problem.skeleton
    q = prep.gt_q[:6].to(torch.float32)
    arm, leg = sk.dof_names.index("lhumerus.rx"), sk.dof_names.index("rfemur.rx")
    hq = q[:, None].repeat(1, 4, 1)  # (6, 4, D)
    hq[:, 0, arm] += 0.8
    hq[:, 1, leg] += 0.8
    hq[:, 2, arm] += 0.8
    hq[:, 2, leg] += 0.8
    hw = torch.tensor([0.5, 0.3, 0.2, 0.0]).repeat(6, 1)  # slot 3: padding
    hc = torch.zeros(6, 4)
    hl = torch.zeros(6, 4, sk.num_dofs, sk.num_dofs)
    path = torch.zeros(6, dtype=torch.long)
    rq, rw, rc, rl, rj = recombine(s, Lattice(hq, hw, hc, hl, sk.forward_kinematics(hq)), path)
    idx = prep.problem.keypoints.index()
    gt = prep.gt_joints[:6].to(rj).index_select(-2, idx)
    err = M.mpjpe(rj.index_select(-2, idx), gt[:, None].expand(-1, 4, -1, -1), root=0)  # (6, 4)
    assert float(err[:, 3].max()) < 10.0 and float(err[:, :3].min()) > 30.0, err  # 1 px noise: 3-7 mm
    assert torch.equal(rq[:, :3], hq[:, :3])  # the modes as they were, their weights in the same ratios
    torch.testing.assert_close(rw[:, :3] / rw[:, :1], hw[:, :3] / hw[:, :1])
    torch.testing.assert_close(rw.sum(1), torch.ones(6))
    assert float(rw[:, 3].min()) > 0 and bool(torch.isfinite(rc[:, 3]).all()) and float(rl[:, 3].abs().sum()) > 0
    torch.testing.assert_close(rj, sk.forward_kinematics(rq))


def test_recombination_after_a_tree_start(cmu_file):
    """CMU 09_06 (a run) from the tree start at the evaluation setting (2 px, 10% missing, seeds 0-2 as `ptrack
    evaluate` runs them), the stage `recombine` in `kjs.stages` or not, from the same passes: the best-of-K error
    falls on every seed, and without `decode` (the forward pass's path) the best trajectory is the same (the
    recombined pose replaces a light mode after the smoother). Measured with the pose prior fitted without the
    held-out clips (2026-11-29), `kjs.reweight: memory`: 39.6 -> 36.5, 33.8 -> 31.5, 41.8 -> 40.0 mm (seed 3: 49.9
    -> 47.9; with the old prior 49.1 -> 39.8)."""
    for seed in range(3):
        got = {}
        for on, stages in (("true", "[smooth, recombine]"), ("false", "[smooth]")):
            cfg = _clip(
                cmu_file,
                "09_06.amc",
                "kjs.init=tree",
                f"seed={seed}",
                f"kjs.stages={stages}",
                "kjs.reweight=memory",
            )
            metrics = _metrics(prepare(cfg), cfg)
            got[on] = (metrics["best_of_k_mpjpe_mm"], metrics["mpjpe_mm"])
        assert got["true"][0] < got["false"][0] - 1.0, f"seed {seed} (best-of-K mm, best trajectory mm): {got}"
        assert got["true"][1] == got["false"][1], got


def test_smoothing_steadies_the_trajectory(kjs_run):
    """One smoothing sweep (the default) against none, from the same passes (the smoother draws no random
    numbers): the best trajectory jitters less and is no less accurate; the hypotheses stay as close to the
    truth. Measured on this second of 10_02 at 1 px: acceleration error 9.6 -> 5.7 mm/frame², best
    trajectory 7.1 -> 6.7 mm, best-of-K 7.0 -> 6.6 mm."""
    prep, est = kjs_run
    _, raw = _run("kjs.stages=[recombine, decode]")
    idx = prep.problem.keypoints.index()
    gt = prep.gt_joints.to(est.joints).index_select(-2, idx)

    def accel(e):
        return float(M.accel_error(e.joints.index_select(-2, idx), gt, root=0).mean())

    (traj, best), (traj0, best0) = _errors(prep, est), _errors(prep, raw)
    assert accel(est) < 0.85 * accel(raw), (accel(est), accel(raw))
    assert traj < traj0 + 0.5 and best < best0 + 0.5, ((traj, best), (traj0, best0))


def test_keypoint_set_without_limbs_runs():
    """A keypoint set none of whose pairs is a flip-metric limb (names a detector might use) gives the
    depth-order ranking nothing to rank by: the passes merge as without it (this crashed in torch.unique)."""
    names = {"Hd": "head", "Pv": "root", "LK": "lfemur", "RK": "rfemur", "LA": "ltibia", "RA": "rtibia"}
    names |= {"LS": "lclavicle", "RS": "rclavicle", "LE": "lhumerus", "RE": "rhumerus"}
    mapping = "{" + ", ".join(f"{k}: {v}" for k, v in names.items()) + "}"
    prep, est = _run("data.stop=24", f"model.keypoints={mapping}", "kjs.samples=64", "kjs.modes=4")
    assert not prep.problem.keypoints.limbs
    assert est.hypotheses is not None and bool(torch.isfinite(est.joints).all())
    assert torch.allclose(est.hypothesis_weights.sum(-1), torch.ones(()).to(est.hypothesis_weights), atol=1e-6)


def test_mode_posterior_and_map_path():
    """The stage `decode` (posterior weights and the MAP path) comes after the tracking: the same hypotheses as
    without it (the filter's weights and the forward path), every frame's posterior weights sum to 1, and the MAP path
    takes one hypothesis per frame."""
    _, est = _run("data.stop=60", "kjs.stages=[smooth, recombine, decode]")
    _, fwd = _run("data.stop=60", "kjs.stages=[smooth, recombine]")
    assert torch.equal(fwd.hypotheses, est.hypotheses)
    w = est.hypothesis_weights
    torch.testing.assert_close(w.sum(-1), torch.ones(w.shape[0]), atol=1e-5, rtol=0)
    assert (w >= 0).all() and not torch.allclose(w, fwd.hypothesis_weights)
    d = (est.hypotheses - est.joints[:, None]).norm(dim=-1).amax(-1).amin(-1)
    assert float(d.max()) < 1e-5


def test_mixture_prior_weight_is_the_predicted_mixture():
    """kjs.reweight mixture: a new minimum's log prior, with its parent's dynamics term (already in its polishing
    cost) added back, is log sum_j w_j p_j(q), p_j the dynamics' density around mode j's prediction; so a minimum
    at the heavy mode's prediction gets the larger prior whichever mode it came from. memory: the parent's weight
    to the power kjs.weight_memory."""
    from ptrack.costs import HeavyTailedPrior, PoseEval
    from ptrack.estimators.kjs.step import prior_weights

    cfg = load_config(KJS_YAML, [*EXACT, "data.stop=12", "kjs.reweight=mixture"])
    problem = prepare(cfg).problem
    s = make_setup(problem, cfg, KJS)
    D = problem.skeleton.num_dofs
    gen = torch.Generator().manual_seed(0)
    predicted = torch.randn(2, D, generator=gen) * 0.3
    sigma = torch.full((2, D), 0.05)
    sigma[1] *= 2
    weight = torch.tensor([0.8, 0.2])
    q = torch.stack([predicted[0], predicted[0], predicted[1], predicted[1]]) + 0.01
    parent = torch.tensor([0, 1, 0, 1])
    got = prior_weights(s, q, parent, weight, predicted, sigma)
    ev = PoseEval(q, q.new_zeros(4, 0, 3), q.new_zeros(4, 0, 2), q.new_zeros(4, 0))
    k = cfg.kjs
    energy = torch.stack(
        [HeavyTailedPrior(predicted[j], sigma[j], k.prior_tail, k.prior_tail_scale).energy(ev) for j in (0, 1)], 1
    )
    want = torch.logsumexp(weight.log() - energy - sigma.log().sum(-1), 1)
    torch.testing.assert_close(got - energy[torch.arange(4), parent], want, rtol=1e-5, atol=1e-4)
    assert float(want[0]) > float(want[2])  # at the heavy mode's prediction (std 0.05) vs the light one's (0.1)
    memory = make_setup(problem, dataclasses.replace(cfg, kjs=dataclasses.replace(cfg.kjs, reweight="memory")), KJS)
    torch.testing.assert_close(
        prior_weights(memory, q, parent, weight, predicted, sigma), cfg.kjs.weight_memory * weight.log()[parent]
    )


def test_the_stage_names_are_the_stages():
    """`kjs.stages` is checked against config.STAGE_NAMES (the config does not import the lattice), the default in
    that order; lattice.STAGES runs them: the two name the same stages in the same order."""
    from ptrack.estimators.kjs.config import STAGE_NAMES
    from ptrack.estimators.kjs.lattice import STAGES

    assert tuple(STAGES) == STAGE_NAMES


def test_polish_chunks_depend_on_the_row_count_alone():
    """`polish_rows`' calls: every row once, in order, in chunks of sizes within one of each other; one call up to
    `SPLIT_ROWS` rows, else an even number of calls of at most `POLISH_CHUNK` rows (two processes take half each)."""
    from ptrack.estimators.kjs.model import POLISH_CHUNK, SPLIT_ROWS, polish_chunks

    for n in (1, SPLIT_ROWS, SPLIT_ROWS + 1, 400, 2 * POLISH_CHUNK, 2 * POLISH_CHUNK + 1, 4000):
        chunks = polish_chunks(n)
        assert torch.equal(torch.cat(chunks), torch.arange(n)), n
        sizes = [len(c) for c in chunks]
        assert max(sizes) - min(sizes) <= 1 and max(sizes) <= POLISH_CHUNK, (n, sizes)
        assert len(chunks) == 1 if n <= SPLIT_ROWS else len(chunks) % 2 == 0, (n, sizes)
