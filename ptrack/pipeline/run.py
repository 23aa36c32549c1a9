"""One config-driven run: data -> observations -> estimator -> metrics -> outputs.

`prepare(cfg)` loads the skeleton, the clip and the camera and makes (or reads) the observations;
`estimate(cfg)` runs the configured estimator on them and returns both, writing nothing (the Python API);
`execute(cfg)` does that, computes metrics and writes the run folder:

    config.yaml   resolved config
    metrics.json  every applicable metric, plus seconds and frames
    result.npz    frames, q, joints, joint_names, ... (see `result_arrays`)
    result.bvh    the estimated motion for animation tools (ptrack.io.export)
    run.rrd       rerun recording (ptrack.io.viz)
    plots/        PNG pictures of the run (ptrack.io.plots; config key `plots`)

The folder is assembled in a hidden sibling `.NAME.partial` and renamed into place at the end, so a
failed run leaves nothing half-written at `out_dir`. That sibling is also the run's claim on `out_dir`,
taken before any work: a second run into the same `out_dir` refuses at once. The run holds a lock on it
(flock) while it lives, so what a killed run left (SIGKILL, a power cut) is told from a live run's and
removed by the next run into the same parent folder (`remove_partial`).
"""

from __future__ import annotations

import dataclasses
import errno
import itertools
import json
import logging
import math
import os
import shutil
import stat
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Sized
from contextlib import suppress
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from ptrack.body.keypoints import make_keypoints
from ptrack.body.limits import wrapped_difference
from ptrack.body.skeleton import Motion, Skeleton, load_amc
from ptrack.body.subject import floor_points, segment_lengths
from ptrack.errors import EstimationError, InputError
from ptrack.estimators import ESTIMATORS
from ptrack.io.export import write_bvh
from ptrack.motion import lowpass
from ptrack.observe.camera import camera_for_motion
from ptrack.observe.correspondences import Correspondences, simulate_correspondences
from ptrack.observe.observations import ChannelConfig, Observations, simulate_observations
from ptrack.observe.person import keypoint_offsets, offset_keypoints, seen_radii, seen_skeleton
from ptrack.observe.silhouette import capsule_radii, render_silhouettes
from ptrack.pipeline import metrics as M
from ptrack.pipeline.config import RunConfig, check_device, dump_yaml
from ptrack.pipeline.footage import FootageFrame, keypoints_in_world, prepare_footage
from ptrack.pipeline.keyframes import ground_truth_joint_keyframes, ground_truth_keyframes, read_keyframes
from ptrack.pipeline.memory import check_memory
from ptrack.problem import Estimate, Floor, Problem, every_nth

if TYPE_CHECKING:
    from ptrack.io.viz import RunLog  # imports rerun: on first use only

try:
    import fcntl
except ImportError:  # Windows: no flock; runs' claims still exclude each other, but none is ever judged stale
    fcntl = None  # type: ignore[assignment]

log = logging.getLogger(__name__)

DTYPES = {"float32": torch.float32, "float64": torch.float64}
PARTIAL = ".partial"  # the suffix of the hidden sibling a run folder is assembled in (`claim_out_dir`)
CLAIMING = ".claim"  # the suffix of the folder a claim is prepared in before it is renamed to `.NAME.partial`
PROBE = ".probe"  # the suffix of the empty folder `check_out_dir` makes and removes to see that it can write


@dataclass(frozen=True)
class Prepared:
    """Everything a run needs before estimation. T frames; `full` is the ASF model, `problem.skeleton`
    the (possibly reduced) model being estimated."""

    full: Skeleton
    motion: Motion | None  # the clip slice (None when observations come from a file without AMC)
    gt_q: torch.Tensor | None  # (T, D) reduced-model ground truth
    gt_joints: torch.Tensor | None  # (T, J, 3) ground truth from the full model
    problem: Problem
    frames: np.ndarray  # (T,) AMC frame numbers (or observation indices)
    # (T, K) keypoints the camera sees (simulated: in front and in the image; a file: confidence > 0)
    visible: torch.Tensor | None = None
    footage: FootageFrame | None = None  # real footage: input frame numbers, frames of reference, the person


def _device(cfg: RunConfig) -> torch.device:
    """cfg.device as a torch device, checked as `load_config` checks it (a RunConfig made in code is not)."""
    check_device(cfg.device)
    return torch.device(cfg.device)


def is_observations_npz(path: str | Path) -> bool:
    """Whether `path` is for `Observations.load_npz`, ptrack's own observations layout, rather than a detector's
    keypoint file: an .npz holding its arrays (keypoints, confidence, times), or one numpy cannot read (whose
    error `load_npz` reports)."""
    p = Path(path)
    if p.suffix != ".npz" or not p.is_file():
        return False
    try:
        with np.load(p, allow_pickle=False) as z:
            return {"keypoints", "confidence", "times"} <= set(z.files)
    except (OSError, ValueError):
        return True


def prepare(cfg: RunConfig, work_dir: Path | None = None) -> Prepared:
    """Load data and make the observations for `cfg` (see module docstring). work_dir: where a run keeps
    what it derives from its inputs (observations.video's detections); None: a temporary folder."""
    if cfg.observations.video or (cfg.observations.file and not is_observations_npz(cfg.observations.file)):
        if work_dir is None:
            with tempfile.TemporaryDirectory(prefix="ptrack-") as tmp:
                return prepare_real(cfg, Path(tmp))
        return prepare_real(cfg, work_dir)
    dtype, device = DTYPES[cfg.dtype], _device(cfg)
    full = Skeleton.from_asf(cfg.data.asf).with_limits(cfg.model.limits)
    model = full.freeze(list(cfg.model.freeze)) if cfg.model.freeze else full
    if model.num_dofs == 0:
        raise InputError(
            f"config key 'model.freeze' {list(cfg.model.freeze)} freezes every dof of {cfg.data.asf}; "
            f"nothing is left to estimate"
        )
    kps = make_keypoints(model, cfg.model.keypoints)
    gen = torch.Generator(device="cpu").manual_seed(cfg.seed)

    motion = gt_q = gt_joints = None
    correspondences: Correspondences | None = None
    upsample = cfg.batch.upsample if cfg.method == "batch" else 1  # batch: frames between the observed ones
    if upsample > 1 and cfg.observations.file:
        raise InputError("batch.upsample > 1 needs simulated observations (data.amc), not observations.file")
    if cfg.data.amc:
        motion = load_amc(cfg.data.amc, full)
        n = motion.q.shape[0]
        if cfg.data.start >= n:
            raise InputError(f"config key 'data.start' is {cfg.data.start} but {cfg.data.amc} has only {n} frames")
        stop = None if cfg.data.stop is None else min(cfg.data.stop, n)
        motion = motion.slice(cfg.data.start, stop, cfg.data.stride // upsample)
        if motion.q.shape[0] < 3:
            raise InputError(
                f"the selected frames of {cfg.data.amc} (start {cfg.data.start}, stop {cfg.data.stop}, "
                f"stride {cfg.data.stride}) give {motion.q.shape[0]} frames; at least 3 are needed"
            )
        q_full = motion.q.to(dtype)
        seen = seen_skeleton(full, cfg.observations.body_height_m)  # the person the camera sees
        gt_joints = seen.forward_kinematics(q_full)
        gt_q = model.reduce(q_full, full)

    if cfg.observations.file:
        obs = Observations.load_npz(cfg.observations.file)
        if motion is not None and obs.num_frames != motion.q.shape[0]:
            raise InputError(
                f"{cfg.observations.file} has {obs.num_frames} frames but the selected AMC frames are "
                f"{motion.q.shape[0]} (check data.start/stop/stride)"
            )
        frames = motion.frames if motion is not None else np.arange(obs.num_frames)
        visible = obs.confidence > 0
    else:
        assert motion is not None and gt_joints is not None  # the config check: data.amc without observations.file
        c = cfg.camera
        camera = camera_for_motion(
            gt_joints, c.distance_m, c.azimuth_deg, c.elevation_deg, c.focal_px, c.width or 640, c.height or 480
        )
        o = cfg.observations
        channel = ChannelConfig(
            noise_px=o.noise_px,
            missing=o.missing,
            occlusion_bursts=o.occlusion_bursts,
            dropped_frames=o.dropped_frames,
            outliers=o.outliers,
            outlier_px=o.outlier_px,
            swap_fraction=o.swap_fraction,
        )
        masks = None
        # the capsule model of silhouettes and correspondences ("flesh"): the seen person's, or another body's
        # (observations.silhouette_height_m), its radii turned by observations.silhouette_radius_* (a generator
        # of their own: the channel's draws stay as they were)
        flesh = seen_skeleton(seen, o.silhouette_height_m)
        bones = torch.as_tensor(flesh.bones(), dtype=torch.long)
        names = [flesh.joint_names[b] for _, b in flesh.bones()]
        radii = capsule_radii(names, torch.as_tensor(flesh.lengths[bones[:, 1]], dtype=dtype))
        person_gen = torch.Generator(device="cpu").manual_seed(cfg.seed + 3)
        radii = seen_radii(names, radii, o.silhouette_radius_scale, o.silhouette_radius_jitter, person_gen)
        offsets = keypoint_offsets(len(kps.names), o.keypoint_offset_m, person_gen)
        _, rotations = seen.forward_kinematics(q_full, rotations=True)
        points = offset_keypoints(gt_joints, rotations, torch.as_tensor(kps.index()), offsets)  # what a detector marks
        flesh_joints, flesh_rotations = gt_joints, rotations
        if flesh is not seen:
            flesh_joints, flesh_rotations = flesh.forward_kinematics(q_full, rotations=True)
        if o.silhouettes:
            masks = render_silhouettes(flesh_joints, bones, radii, camera)
        times = torch.as_tensor(motion.times, dtype=dtype)
        obs, info = simulate_observations(
            points, range(len(kps.names)), camera, times, channel, gen, kps.names, kps.swap_pairs, masks
        )
        visible = info.visible
        frames = motion.frames
        if o.correspondences:  # drawn after the keypoints' channel: turning them on leaves its draws as they were
            correspondences, _ = simulate_correspondences(
                flesh_joints,
                flesh_rotations,
                bones,
                radii,
                camera,
                o.correspondences,
                gen,
                noise_px=o.correspondence_noise_px,
                outliers=o.correspondence_outliers,
                outlier_px=o.outlier_px,
            )
        if upsample > 1:  # 2D on every upsample-th reconstructed frame only
            observed = (torch.arange(obs.num_frames) % upsample == 0).to(obs.confidence)
            obs = dataclasses.replace(obs, confidence=obs.confidence * observed[:, None])
    if tuple(obs.keypoint_names) != kps.names:
        raise InputError(
            f"observation keypoints {list(obs.keypoint_names)} differ from the model's keypoint set "
            f"{list(kps.names)} (config model.keypoints)"
        )
    if cfg.observations.file:  # the file is usable: say which settings it makes moot
        ignored = [
            f"observations.{f.name}"
            for f in dataclasses.fields(cfg.observations)
            if f.name not in ("file", "correspondence_file") and getattr(cfg.observations, f.name) != f.default
        ]
        if ignored:
            log.warning(
                "observations.file is given, so %s (for simulated observations) %s ignored",
                ", ".join(ignored),
                "is" if len(ignored) == 1 else "are",
            )
    if cfg.observations.correspondence_file:
        correspondences = Correspondences.load_npz(cfg.observations.correspondence_file, obs.num_frames)
    if correspondences is not None:
        correspondences = correspondences.to(device=device, dtype=dtype)
        if cfg.method != "pca":
            log.warning("method %s does not use the point correspondences (only method pca does)", cfg.method)
    check_visibility(visible)
    check_observed(obs.confidence[::upsample] > 0, visible[::upsample])  # the frames meant to be observed
    obs = obs.to(device=device, dtype=dtype)
    keyframes = joint_keyframes = None
    kc = cfg.keyframes
    if kc.file:
        keyframes, joint_keyframes = read_keyframes(kc.file, model, obs.num_frames, kc.sigma_deg, kc.sigma_m, dtype)
    elif gt_q is not None:  # the clip's own poses play the user's 3D keyframes (frame 0 unless keyframes.* ask more)
        partial = bool(kc.dofs or kc.joints)
        kf_gen = torch.Generator(device="cpu").manual_seed(cfg.seed + 2)
        keyframes = ground_truth_keyframes(
            gt_q,
            obs.times,
            model,
            kc.every_s,
            kc.last,
            kc.noise_deg,
            kc.sigma_deg,
            kc.sigma_m,
            kf_gen,
            tuple(kc.dofs) if partial else None,
            kc.first,
        )
        if kc.joints:
            assert gt_joints is not None  # with gt_q
            joint_keyframes = ground_truth_joint_keyframes(
                gt_joints,
                obs.times,
                model,
                tuple(kc.joints),
                kc.every_s,
                kc.last,
                kc.sigma_m,
                kc.noise_m,
                kc.depth_noise_m,
                obs.camera.R,
                kc.joint_covariance == "full",
                kf_gen,
            )
    problem = Problem(
        skeleton=model,
        keypoints=kps,
        observations=obs,
        keyframes=keyframes,
        joint_keyframes=joint_keyframes,
        correspondences=correspondences,
    )
    return Prepared(
        full=full,
        motion=motion,
        gt_q=gt_q,
        gt_joints=gt_joints,
        problem=problem,
        frames=np.asarray(frames),
        visible=visible.cpu(),
    )


def prepare_real(cfg: RunConfig, work_dir: Path) -> Prepared:
    """`prepare` for real footage: a detector's keypoint file (or a video detected first, its detections
    written to `work_dir`), a camera file (or none), the subject's height (`ptrack.pipeline.footage`)."""
    dtype, device = DTYPES[cfg.dtype], _device(cfg)
    if cfg.data.amc:
        log.warning("data.amc is ignored: observations come from real footage (%s)", cfg.observations.file)
    if cfg.keyframes.every_s is not None or cfg.keyframes.last:
        log.warning("keyframes.every_s/last take ground truth, which real footage has not; they are ignored")
    template = Skeleton.from_asf(cfg.data.asf).with_limits(cfg.model.limits)
    video = cfg.observations.video
    keypoints_file: str | Path
    size: tuple[int, int] | None = None
    fps: float | None = None
    if video:
        from ptrack.observe.video import video_info
        from ptrack.pipeline.detections import detections_for_video

        info = video_info(video)
        keypoints_file = detections_for_video(video, work_dir, progress=progress_display(cfg.progress, "detect"))
        size, fps = (info.width, info.height), info.fps
    else:
        assert cfg.observations.file is not None  # prepare's choice
        keypoints_file = cfg.observations.file
    full, kps, obs, footage = prepare_footage(cfg, template, keypoints_file, size, fps, video)
    model = full.freeze(list(cfg.model.freeze)) if cfg.model.freeze else full
    visible = obs.confidence > 0  # what a real camera sees is what the detector found
    check_visibility(visible)
    obs = obs.to(device=device, dtype=dtype)
    keyframes = joint_keyframes = None
    kc = cfg.keyframes
    if kc.file:
        keyframes, joint_keyframes = read_keyframes(kc.file, model, obs.num_frames, kc.sigma_deg, kc.sigma_m, dtype)
    floor = None
    if footage.floor_m is not None:
        joints, clearance = floor_points(model, footage.height_m)
        floor = Floor(footage.floor_m, joints, clearance)
    problem = Problem(
        skeleton=model,
        keypoints=kps,
        observations=obs,
        keyframes=keyframes,
        joint_keyframes=joint_keyframes,
        floor=floor,
    )
    return Prepared(
        full=full,
        motion=None,
        gt_q=None,
        gt_joints=None,
        problem=problem,
        frames=np.asarray(footage.frames),
        visible=visible.cpu(),
        footage=footage,
    )


#: a frame counts as seen when at least this share of its keypoints is visible; a run needs MIN_SEEN_FRAMES
SEEN_FRAME_SHARE, MIN_SEEN_FRAMES = 1 / 3, 3


def check_visibility(visible: torch.Tensor) -> None:
    """Refuse (InputError) observations where fewer than MIN_SEEN_FRAMES frames have at least a third of their
    keypoints visible; warn when under half of all keypoints are. visible: (T, K) bool."""
    per_frame = visible.float().mean(-1)
    seen, fraction = int((per_frame >= SEEN_FRAME_SHARE).sum()), float(per_frame.mean())
    if seen < MIN_SEEN_FRAMES:
        raise InputError(
            f"the camera sees too little: {seen} of {visible.shape[0]} frames have at least a third of "
            f"the keypoints visible ({MIN_SEEN_FRAMES} are needed; visible_fraction {fraction:.3f}); "
            f"check camera.* or the observations"
        )
    if fraction < 0.5:
        log.warning(
            "the camera sees only %.0f%% of the keypoints (visible_fraction %.3f): the estimate rests on "
            "few observations",
            100 * fraction,
            fraction,
        )


#: under this share of observed keypoints (confidence > 0) a run warns, as it does under this share of visible ones
OBSERVED_WARN = 0.5


def check_observed(observed: torch.Tensor, visible: torch.Tensor) -> None:
    """Warn when under OBSERVED_WARN of the keypoints are observed though the camera sees more (where it sees
    little, `check_visibility` has said so). observed, visible: (T, K) bool."""
    fraction, seen = float(observed.float().mean()), float(visible.float().mean())
    if fraction < OBSERVED_WARN <= seen:
        log.warning(
            "only %.0f%% of the keypoints are observed (observed_fraction %.3f; the camera sees %.0f%%): the "
            "estimate rests on few observations (observations.missing, occlusion_bursts, dropped_frames)",
            100 * fraction,
            fraction,
            100 * seen,
        )


#: the estimate explains the observations poorly when the median distance of its keypoints to the observed ones is
#: over both REPROJECTION_SIGMAS times costs.sigma_px and REPROJECTION_DIAGONAL of the image's diagonal
REPROJECTION_SIGMAS, REPROJECTION_DIAGONAL = 10.0, 0.05


def check_reprojection(prep: Prepared, reproj: torch.Tensor, sigma_px: float) -> float:
    """Warn when no pose explains the observations (see REPROJECTION_SIGMAS); -> the median distance, pixels
    (NaN when nothing is observed). reproj: (T, K, 2) from `reprojected_keypoints`."""
    obs = prep.problem.observations
    seen = obs.confidence > 0
    err = (reproj.to(obs.keypoints) - obs.keypoints).norm(dim=-1)[seen]
    if err.numel() == 0:
        return math.nan
    median = float(err.double().median())
    diagonal = math.hypot(obs.camera.width, obs.camera.height)
    limit = max(REPROJECTION_SIGMAS * sigma_px, REPROJECTION_DIAGONAL * diagonal)
    if not median <= limit:
        log.warning(
            "the estimate's keypoints lie a median %.3g px from the observed ones, over %.3g px (%g times "
            "costs.sigma_px %g and %.0f%% of the image's diagonal): no pose explains these observations; "
            "check the observations (observations.*), the camera (camera.*) and costs.sigma_px",
            median,
            limit,
            REPROJECTION_SIGMAS,
            sigma_px,
            100 * REPROJECTION_DIAGONAL,
        )
    return median


def reprojected_keypoints(prep: Prepared, est: Estimate) -> torch.Tensor:
    """The estimate's keypoints in the image: (T, K, 2) pixels."""
    prob = prep.problem
    kp = est.joints.detach().index_select(-2, prob.keypoints.index(est.joints.device))
    return prob.observations.camera.project(kp).pixels


#: the multiples of `joint_std` whose coverage of the truth metrics.json reports (`joint_within_<k>std`)
STD_COVERAGE = (1, 2, 3)


def compute_metrics(prep: Prepared, est: Estimate, reproj: torch.Tensor) -> tuple[dict, dict[str, np.ndarray]]:
    """Summary metrics (JSON-able) and per-frame series {name: (T,)} for logging.
    reproj: (T, K, 2) from `reprojected_keypoints`."""
    prob = prep.problem
    obs, kps, sk = prob.observations, prob.keypoints, prob.skeleton
    cam = obs.camera
    idx = kps.index(est.joints.device)
    est_kp = est.joints.detach().index_select(-2, idx)
    series: dict[str, np.ndarray] = {}
    summary: dict = {}

    def put(name: str, per_frame: torch.Tensor) -> None:
        v = per_frame.detach().double().cpu().numpy()
        series[name] = v
        summary[name] = float(np.nanmean(v)) if np.isfinite(v).any() else None

    exchanged = exchanged_frames(prep, reproj)
    observed, confidence = detections_as_read(prep, exchanged)
    put("reprojection_error_px", M.reprojection_error_px(reproj, observed, confidence))
    if prep.visible is not None:  # a small reprojection error means little when the camera sees little
        summary["visible_fraction"] = float(prep.visible.float().mean())
    summary["observed_fraction"] = float((obs.confidence > 0).float().mean())  # what the estimator was given
    lower, upper = sk.limits(dtype=est.q.dtype, device=est.q.device)
    angular = torch.as_tensor(sk.angular_dofs(), device=est.q.device)
    report = M.joint_limit_violations(est.q.detach(), lower, upper, angular=angular)
    summary["joint_limit_violation_fraction"] = float(report.fraction)
    summary["joint_limit_max_violation_deg"] = float(report.max_deg)
    if prep.gt_q is not None:  # how far the truth itself lies outside the limits in use
        gt_report = M.joint_limit_violations(prep.gt_q.to(est.q), lower, upper, angular=angular)
        summary["gt_joint_limit_violation_fraction"] = float(gt_report.fraction)
        summary["gt_joint_limit_max_violation_deg"] = float(gt_report.max_deg)
    if prep.gt_joints is not None:
        gt = prep.gt_joints.to(est.joints)
        gt_kp = gt.index_select(-2, idx)
        root = kps.joints.index(0) if 0 in kps.joints else 0
        put("mpjpe_mm", M.mpjpe(est_kp, gt_kp, root=root))
        put("pa_mpjpe_mm", M.pa_mpjpe(est_kp, gt_kp))
        put("mpjpe_abs_mm", M.mpjpe_absolute(est_kp, gt_kp, cam.R.to(gt), cam.t.to(gt)))
        summary["mpjpe_all_joints_mm"] = float(M.mpjpe(est.joints.detach(), gt).mean())
        for name, acc_root in (("accel_error_mm_per_frame2", root), ("accel_error_abs_mm_per_frame2", None)):
            acc = M.accel_error(est_kp, gt_kp, root=acc_root)
            summary[name] = float(acc.mean())
            series[name] = np.concatenate([[np.nan], acc.double().cpu().numpy(), [np.nan]])
        if kps.limbs:
            flips = M.limb_flip_errors(est_kp, gt_kp, kps.limbs, cam.R.to(gt), cam.t.to(gt))
            per_limb = M.flip_error_rate(flips)
            summary["flip_error_rate"] = float(flips.nanmean())  # NaN -> null in metrics.json
            summary["flip_error_rate_per_limb"] = {
                f"{kps.names[a]}-{kps.names[b]}": float(r) for (a, b), r in zip(kps.limbs, per_limb)
            }
            series["flip_error_rate"] = flips.nanmean(-1).double().cpu().numpy()
        if est.hypotheses is not None:
            hyp_kp = est.hypotheses.detach().index_select(-2, idx)
            put("best_of_k_mpjpe_mm", M.best_of_k_mpjpe(hyp_kp, gt_kp, root=root))
            if est.hypothesis_weights is not None:
                checks, series["heaviest_mpjpe_mm"] = mixture_checks(
                    hyp_kp, est.hypothesis_weights.detach(), gt_kp, root, kps.limbs, cam
                )
                summary.update(checks)
    if est.hypotheses is not None and est.hypothesis_weights is not None:  # how many readings the modes hold
        distinct = M.distinct_modes(est.hypotheses.detach().cpu(), est.hypothesis_weights.detach().cpu())
        summary["distinct_modes_5cm"] = float(distinct.double().mean())
    if prep.footage is not None:
        checks, per_frame = footage_checks(prep, est, est_kp, reproj, (observed, confidence), exchanged)
        summary.update(checks)
        series.update(per_frame)
    if est.joint_std is not None:
        put("joint_std_mean_m", est.joint_std.mean(-1))
        series["joint_std_max_m"] = est.joint_std.amax(-1).detach().double().cpu().numpy()
        if prep.gt_joints is not None:  # how often the truth lies within 1, 2, 3 std (every joint)
            std, gt_all = est.joint_std.detach(), prep.gt_joints.to(est.joints)
            for mult in STD_COVERAGE:
                summary[f"joint_within_{mult}std"] = float(M.std_coverage(est.joints.detach(), gt_all, std, mult))
    if est.solver_cost is not None:
        summary["solver_iterations"] = int(est.solver_cost.shape[0] - 1)
        summary["solver_cost_start"], summary["solver_cost_final"] = (
            float(est.solver_cost[0]),
            float(est.solver_cost[-1]),
        )
    series["cost"] = est.cost.detach().double().cpu().numpy()
    for k, v in est.terms.items():
        series[f"cost_{k}"] = v.detach().double().cpu().numpy()
    return summary, series


def exchanged_frames(prep: Prepared, reproj: torch.Tensor) -> torch.Tensor | None:
    """Real footage: the frames (T,) bool whose detections the result fits better with every left and right label
    exchanged (`metrics.exchanged_label_frames`); None off real footage or for a keypoint set without pairs.
    reproj: (T, K, 2) the result reprojected."""
    if prep.footage is None:
        return None
    obs, kps = prep.problem.observations, prep.problem.keypoints
    return M.exchanged_label_frames(reproj.cpu(), obs.keypoints.cpu(), obs.confidence.cpu(), kps.mirror_index())


def detections_as_read(prep: Prepared, exchanged: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
    """The observed keypoints (T, K, 2) and confidences (T, K) as the run read them: on real footage whose run read
    each frame's labels both ways (`FootageFrame.swap_cost` > 0), the `exchanged` frames (`exchanged_frames`) with
    every left and right label exchanged, so that their reprojection error is the one of the labels the run used;
    else as detected."""
    obs, kps = prep.problem.observations, prep.problem.keypoints
    if prep.footage is None or not prep.footage.swap_cost or exchanged is None:
        return obs.keypoints, obs.confidence
    mirror = kps.mirror_index(obs.keypoints.device)
    at = exchanged.to(obs.keypoints.device)
    observed = torch.where(at[:, None, None], obs.keypoints.index_select(1, mirror), obs.keypoints)
    return observed, torch.where(at[:, None], obs.confidence.index_select(1, mirror), obs.confidence)


#: the heaviest mode counts as the best one in a frame when its MPJPE is within this of the best mode's (mm)
HEAVIEST_BEST_MM = 10.0


def mixture_checks(
    hyp_kp: torch.Tensor, weights: torch.Tensor, gt_kp: torch.Tensor, root: int, limbs, cam
) -> tuple[dict, np.ndarray]:
    """How much the trackers' weights say (issue 41): the heaviest mode's MPJPE (`heaviest_mpjpe_mm`), the share of
    frames where it is within `HEAVIEST_BEST_MM` of the best mode (`heaviest_is_best_share`), and over the limb-frames
    whose true depth difference exceeds 2 cm the Brier score of each limb's depth-order probability
    (`depth_order_brier`: the summed weight of the modes that put the limb's end nearer the camera, against the
    truth) and the share where some mode holds the true order (`depth_order_in_modes`). hyp_kp (T, N, K, 3),
    weights (T, N), gt_kp (T, K, 3); limbs keypoint index pairs. -> (summary, the heaviest mode's MPJPE per frame
    (T,))."""
    heavy = M.mpjpe(M.heaviest_mode(hyp_kp, weights), gt_kp, root=root)
    each = M.mpjpe(hyp_kp, gt_kp[:, None].expand_as(hyp_kp), root=root)  # (T, N)
    best = torch.where(weights > 0, each, torch.full_like(each, math.inf)).amin(-1)
    out: dict = {
        "heaviest_mpjpe_mm": float(heavy.mean()),
        "heaviest_is_best_share": float((heavy <= best + HEAVIEST_BEST_MM).to(heavy.dtype).mean()),
    }
    if limbs:
        scores = M.depth_order_scores(hyp_kp, weights, gt_kp, limbs, cam.R.to(gt_kp), cam.t.to(gt_kp))
        brier, found = scores.brier.nanmean(), scores.in_modes.nanmean()
        out["depth_order_brier"] = float(brier) if torch.isfinite(brier) else None
        out["depth_order_in_modes"] = float(found) if torch.isfinite(found) else None
    return out, heavy.double().cpu().numpy()


#: foot landmarks whose skating `footage_checks` measures
FOOT_LANDMARKS = ("l_ankle", "r_ankle", "l_heel", "r_heel", "l_big_toe", "r_big_toe")


def footage_checks(
    prep: Prepared,
    est: Estimate,
    est_kp: torch.Tensor,
    reproj: torch.Tensor,
    read: tuple[torch.Tensor, torch.Tensor],
    exchanged: torch.Tensor | None,
) -> tuple[dict, dict[str, np.ndarray]]:
    """What a person checks without ground truth (real footage): the median reprojection error of each
    keypoint (px), each keypoint's jitter (mean second difference, mm/frame^2) and their means, the skating
    of the feet (horizontal mm/frame while within 5 cm of their floor height, `M.foot_skating_mm`; the model frame is
    Y up), and
    with hypotheses the share of frames where the modes disagree about some limb's depth order (summed weight
    between 0.1 and 0.9), and the input frames whose detections the result fits better with every left and right
    label exchanged (a detector's mirrored body; `costs.swap_cost`). est_kp: (T, K, 3) the estimate's keypoints;
    read: the detections as the run read them (`detections_as_read`); exchanged: `exchanged_frames`.
    -> (summary, per-frame series (T,) for the rerun log's plots: the jitter (NaN at the two ends), the feet's
    mean sliding step (NaN at frame 0 and where no foot is on the floor), whether some limb is ambiguous (0/1) and
    the share of the limbs that are, whether the result reads the labels exchanged (0/1) and whether the person is
    missing (0/1))."""
    assert prep.footage is not None
    prob = prep.problem
    obs, kps = prob.observations, prob.keypoints
    names = kps.names
    kp = est_kp.detach().double().cpu()
    per_kp = M.reprojection_error_per_keypoint(reproj.cpu(), read[0].cpu(), read[1].cpu())
    shake = M.second_differences_mm(kp)  # (T-2, K)
    jitter = shake.mean(0) if len(shake) else shake.new_full((len(names),), float("nan"))
    out: dict = {
        "reprojection_error_px_per_keypoint": {n: float(v) for n, v in zip(names, per_kp)},
        "jitter_mm_per_frame2": float(jitter.nanmean()),
        "jitter_mm_per_frame2_per_keypoint": {n: float(v) for n, v in zip(names, jitter)},
    }
    series = {"jitter_mm_per_frame2": np.concatenate([[np.nan], shake.mean(-1).numpy(), [np.nan]])[: len(kp)]}
    feet = [k for k, m in enumerate(prep.footage.landmarks) if m in FOOT_LANDMARKS]
    if feet:
        steps = M.foot_sliding_steps_mm(kp[:, feet], torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
        out["foot_skating_mm_per_frame"] = {names[k]: float(v) for k, v in zip(feet, steps.nanmean(0))}
        series["foot_skating_mm_per_frame"] = np.concatenate([[np.nan], steps.nanmean(-1).numpy()])  # feet on the floor
    if est.hypotheses is not None and est.hypothesis_weights is not None and kps.limbs:
        hyp = est.hypotheses.detach().index_select(-2, kps.index(est.hypotheses.device)).double().cpu()
        cam = obs.camera.to(device="cpu", dtype=torch.float64)
        ambiguous = M.ambiguous_limb_frames(hyp, est.hypothesis_weights.detach().cpu(), kps.limbs, cam.R, cam.t)
        out["ambiguous_frame_share"] = float(ambiguous.any(-1).double().mean())
        series["ambiguous_frame"] = ambiguous.any(-1).double().numpy()  # 0/1: some limb's depth order in doubt
        series["ambiguous_limb_share"] = ambiguous.double().mean(-1).numpy()
        out["ambiguous_frame_share_per_limb"] = {
            f"{names[a]}-{names[b]}": float(v) for (a, b), v in zip(kps.limbs, ambiguous.double().mean(0))
        }
    if exchanged is not None:  # where the result reads the detector's left and right the other way round
        out["left_right_exchanged_frames"] = [int(f) for f in np.asarray(prep.footage.frames)[exchanged.numpy()]]
        series["left_right_exchanged"] = exchanged.double().numpy()  # 0/1
    series["person_missing"] = np.isin(prep.footage.frames, prep.footage.missing_frames).astype(np.float64)  # 0/1
    given = prep.footage.lengths == "asf"
    out["bone_lengths"] = M.bone_lengths_report(segment_lengths(prob.skeleton), prep.footage.segments, given)
    return out, series


def json_safe(obj):
    """`obj` with every non-finite float replaced by None (JSON null; JSON has no NaN)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    return obj


def check_finite(est: Estimate, method: str) -> None:
    """Raise EstimationError when any frame of the estimate (q or joints) is not finite.

    Such frames are not scored as missing: a mean over the remaining frames would rank an estimate
    that lost half its frames beside a complete one."""
    bad = ~(torch.isfinite(est.q).all(-1) & torch.isfinite(est.joints).flatten(-2).all(-1))
    n = int(bad.sum())
    if n:
        first = torch.nonzero(bad)[:5, 0].tolist()
        raise EstimationError(
            f"method {method!r} returned non-finite poses in {n} of {bad.shape[0]} frames "
            f"(nonfinite_frames={n}; first at frame indices {first}); no results were written"
        )


def default_out_dir(cfg: RunConfig, root: str | Path = "logs") -> Path:
    return Path(root) / f"{cfg.name}-{datetime.now().strftime('%Y%m%d-%H%M%S-%f')}"


def check_out_dir(out: Path) -> None:
    """Raise InputError unless `out` is a new or empty folder that can be made and written, before any work:
    creates and removes a hidden folder where the run's folder will be assembled."""
    if out.exists() and not out.is_dir():
        raise InputError(f"out_dir {out} is an existing file, not a folder; choose another out_dir")
    if out.is_dir() and any(out.iterdir()):
        raise InputError(f"out_dir {out} already exists and is not empty; choose another out_dir")
    parent = out.absolute().parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise InputError(f"out_dir {out} cannot be made: {parent} is a file, not a folder")
    try:
        probe = tempfile.mkdtemp(prefix=f".{out.name}.", suffix=PROBE, dir=parent)
    except OSError as e:
        raise InputError(f"out_dir {out} cannot be made: cannot write in {parent} ({e.strerror})") from None
    with suppress(FileNotFoundError):  # another run's `remove_partial` may have taken it first
        os.rmdir(probe)
    if out.is_dir() and hasattr(os, "geteuid"):  # an empty folder: the finished run replaces it
        there, folder = parent.stat(), out.stat()
        if there.st_mode & stat.S_ISVTX and os.geteuid() not in (0, there.st_uid, folder.st_uid):
            raise InputError(
                f"out_dir {out} belongs to another user in the sticky folder {parent}, so the run could not "
                f"put its folder there; choose another out_dir"
            )


@dataclass
class Claim:
    """A run's hold on its `out_dir`: the hidden sibling `.NAME.partial` (holding the file `pid`) that the run
    folder is assembled in, locked through `fd` for as long as the run lives. `made`: the parent folders the
    claim created (removed again when the run fails, if still empty)."""

    path: Path
    fd: int
    made: list[Path]

    def finish(self, out: Path) -> None:
        """Put the assembled folder at `out` (absent or empty) in one rename; InputError when that fails."""
        (self.path / "pid").unlink()
        try:
            if os.name == "nt" and out.exists():
                out.rmdir()  # empty (checked before the run); POSIX renames over it in one step
            os.replace(self.path, out)
        except OSError as e:
            self.release()
            raise InputError(
                f"cannot put the finished run at out_dir {out} ({e.strerror}); nothing was written there"
            ) from None
        self._unlock()

    def release(self) -> None:
        """Remove the claim and what it holds, and the parent folders it made that are still empty."""
        shutil.rmtree(self.path, ignore_errors=True)
        self._unlock()
        _remove_empty(self.made)

    def _unlock(self) -> None:
        _close(self.fd)
        self.fd = -1  # closed once: a later release does not close a descriptor opened since


def claim_out_dir(out: Path) -> Claim:
    """Take `out` for this run before any work: make its parent folders, remove the partial siblings that
    killed runs left there (`remove_partial`), and create the locked `.NAME.partial` sibling in one rename.
    InputError when another live run holds it ("being written by another run (pid N)")."""
    parent = out.absolute().parent
    made = []
    for folder in reversed([parent, *parent.parents]):
        if not folder.exists():
            try:
                folder.mkdir()
            except FileExistsError:  # made at the same moment by another run
                continue
            made.append(folder)
    remove_partial(parent, recursive=False)
    target = parent / f".{out.name}{PARTIAL}"
    umask = os.umask(0)
    os.umask(umask)
    for _ in range(5):  # a claim that vanished or went stale between two looks: look again
        try:
            tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=CLAIMING, dir=parent))
        except FileNotFoundError:  # the parent, empty, was removed by a run that failed at that moment
            parent.mkdir(parents=True, exist_ok=True)
            continue
        fd = -1
        try:
            if fcntl is not None:
                fd = os.open(tmp, os.O_RDONLY)
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # a new folder: never held
            tmp.chmod(0o777 & ~umask)  # mkdtemp makes 0700; the run folder gets a new folder's usual mode
            (tmp / "pid").write_text(f"{os.getpid()}\n", encoding="utf-8")
            os.rename(tmp, target)  # fails while another claim (never empty: it holds `pid`) stands there
            return Claim(target, fd, made)
        except OSError as e:
            _close(fd)
            shutil.rmtree(tmp, ignore_errors=True)
            if e.errno not in (errno.EEXIST, errno.ENOTEMPTY, errno.ENOENT, errno.EAGAIN, errno.EWOULDBLOCK):
                raise
        except BaseException:
            _close(fd)
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        if not _remove_if_stale(target):
            try:
                owner = f" (pid {int((target / 'pid').read_text(encoding='utf-8'))})"
            except (OSError, ValueError):
                owner = ""
            _remove_empty(made)
            raise InputError(f"out_dir {out} is being written by another run{owner}; choose another out_dir")
    raise InputError(f"out_dir {out} cannot be claimed: {target} keeps reappearing; remove it and run again")


def _remove_empty(made: list[Path]) -> None:
    """Remove the folders `made` (outermost first) from the innermost up, while they are empty."""
    for folder in reversed(made):
        try:
            folder.rmdir()
        except OSError:
            break


def _close(fd: int) -> None:
    if fd >= 0:
        os.close(fd)


def _remove_if_stale(path: Path) -> bool:
    """Remove `path`, a run's claim, when no live process holds its lock (its run was killed); False when one
    does (or, without flock, always: no claim is judged stale)."""
    if fcntl is None:
        return not path.exists()
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return True
    except OSError:
        return False
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False
        try:
            if os.path.samestat(os.fstat(fd), os.stat(path)):  # still the folder locked, not a new claim
                log.info("removing %s, left by a run that was killed", path)
                shutil.rmtree(path, ignore_errors=True)
        except FileNotFoundError:
            pass
        return True
    finally:
        os.close(fd)


def estimate(cfg: RunConfig, progress: bool = False, work_dir: Path | None = None) -> tuple[Prepared, Estimate]:
    """The data and observations of `cfg` (`prepare`) and the configured method's estimate of them, as
    `execute` computes them (same seed, same result), without writing anything. progress: a progress
    bar on stderr (on a terminal only)."""
    prep, est = _estimate(cfg, progress, work_dir)
    if prep.footage is not None:  # one set of root angles along the path, then `with_filter`'s low-pass
        est = est._replace(q=continuous_root(prep.problem.skeleton, est.q))
        if prep.footage.filter_hz is not None:
            est = lowpass_trajectory(prep.problem.skeleton, est, prep.footage.fps, prep.footage.filter_hz)
    return prep, est


def _estimate(cfg: RunConfig, progress: bool, work_dir: Path | None) -> tuple[Prepared, Estimate]:
    """`estimate` before `observations.filter_hz`."""
    prep = prepare(cfg, work_dir)
    cfg, prep = with_swap_cost(cfg, prep)
    prep = with_filter(cfg, prep)
    if cfg.subject.static:  # the segment lengths of a static trial (ptrack.pipeline.static)
        from ptrack.pipeline.static import apply_static

        if prep.footage is None:
            raise InputError("config key 'subject.static' needs real footage (observations.file or .video)")
        prep = apply_static(prep, cfg)
    check_memory(cfg, prep.problem)  # refuse settings that would not fit before the estimator allocates

    def run(problem: Problem, run_cfg: RunConfig = cfg) -> Estimate:
        gen = torch.Generator(device="cpu").manual_seed(
            cfg.seed + 1
        )  # the samplers' draws (cfg.seed: the observations')
        return ESTIMATORS[cfg.method](problem, run_cfg, gen, progress_display(progress, cfg.method))

    # real footage above `observations.track_fps`: every `every`-th frame tracked, the others filled
    every = tracked_every(cfg, prep)
    if every > 1:
        assert prep.footage is not None  # tracked_every: real footage only
        prep = dataclasses.replace(prep, footage=dataclasses.replace(prep.footage, tracked_every=every))

    def track(problem: Problem) -> Estimate:
        if every == 1:
            return run(problem)
        return fill_frames(problem.skeleton, run(every_nth(problem, every)), every, problem.observations.num_frames)

    # real footage measured on a first run (lengths, floor), then run again: the first run may be cheaper
    # (every n-th frame, kjs without its backward pass), as it only gives the depths the 2D is measured at.
    # A static trial's lengths are the better measurement; rescaling the model leaves the floor as it is.
    measure_lengths = cfg.subject.lengths == "observed" and not cfg.subject.static
    measure_floor = prep.problem.floor is None and cfg.camera.floor_m is not None and cfg.camera.floor_from_person
    if prep.footage is None or not (measure_lengths or measure_floor):
        return prep, track(prep.problem)
    n, first_cfg = cfg.subject.measure_stride * every, measure_config(cfg)
    first = est = run(every_nth(prep.problem, n), first_cfg)
    if n > 1:  # every frame's joints (linear between the tracked ones): the lengths are measured on all the 2D
        est = est._replace(joints=between_frames(est.joints, n, prep.problem.observations.num_frames))
    again = False
    if measure_lengths:
        prep, again = rescale_subject(prep, est, cfg.subject.depth_from_floor), True
    if measure_floor:
        leveled = level_to_person(prep, est)  # the floor under the first pass's feet, then run again on it
        prep, again = leveled or prep, again or leveled is not None
    if again or n > every or first_cfg is not cfg:  # the first run was not the configured one
        return prep, track(prep.problem)
    return prep, fill_frames(prep.problem.skeleton, first, every, prep.problem.observations.num_frames)


#: `lowpass_trajectory`: a frame whose joints move more than this many times the clip's median step from the frame
#: before starts a new stretch (a change of reading, which a filter would smear over its neighbours)
JUMP_FACTOR = 5.0


def with_filter(cfg: RunConfig, prep: Prepared) -> Prepared:
    """`observations.filter_hz` decided before anything is tracked: on real footage, under half its frame rate, it
    goes into the footage record (`FootageFrame.filter_hz`), which `estimate` filters the result at; else a warning
    that it will not be used (without real footage, or at or above half the frame rate: a trajectory sampled at that
    rate holds nothing faster) and `prep` as it was."""
    hz = cfg.observations.filter_hz
    if hz is None:
        return prep
    if prep.footage is None:
        log.warning("observations.filter_hz is for real footage; it is not used on simulated observations")
        return prep
    if hz >= prep.footage.fps / 2:
        log.warning(
            "observations.filter_hz (%g Hz) is not under half the frame rate (%g fps): the trajectory is not filtered",
            hz,
            prep.footage.fps,
        )
        return prep
    return dataclasses.replace(prep, footage=dataclasses.replace(prep.footage, filter_hz=hz))


def continuous_root(sk: Skeleton, q: torch.Tensor) -> torch.Tensor:
    """A trajectory q (T, D) -> the same poses with each frame's root angles in whichever of their two sets
    (`Skeleton.root_twin`) lies nearer the frame before's (summed wrapped differences), from frame 0 on: the same
    joints, root angles that change only as the body turns. A path that goes from one mode to another can change
    sets between two frames where the body hardly moves (modes of two tree starts), and a low-pass or an
    interpolation of the angles across that change would turn the body over (the trial's cam02, seed 1: ankles 1.5 m
    up, 345 mm world MPJPE against 195 unfiltered). q itself where the root has no twin."""
    dofs = sk.root_twin_dofs()
    if dofs is None or q.shape[0] < 2:
        return q
    twin = sk.root_twin(q)
    both = torch.stack([q, twin], 1)[:, :, list(dofs)].detach().double().cpu()  # (T, 2, 3): each frame's two sets
    angular = torch.ones(3, dtype=torch.bool)
    use_twin = torch.zeros(q.shape[0], dtype=torch.bool)
    prev = both[0, 0]
    for t in range(1, q.shape[0]):
        near, far = wrapped_difference(both[t] - prev, angular).abs().sum(-1)
        use_twin[t] = far < near
        prev = both[t, int(use_twin[t])]
    if not use_twin.any():
        return q
    return torch.where(use_twin.to(q.device)[:, None], twin, q)


def lowpass_trajectory(sk: Skeleton, est: Estimate, fps: float, cutoff_hz: float) -> Estimate:
    """The reported trajectory low-passed in time: each dof of q (T, D) (angles unwrapped) through a zero-phase
    second-order Butterworth filter (`ptrack.motion.lowpass`: forwards and backwards) at `cutoff_hz`, in stretches
    between jumps (a frame whose joints move more than `JUMP_FACTOR` times the clip's median step from the frame
    before); stretches too short for the filter stay as they are. The poses are kept within the joint limits and the
    joints are their forward kinematics; the hypotheses, costs and weights stay as tracked (they are each frame's
    own)."""
    q = est.q.detach().double().cpu().numpy()
    frames = q.shape[0]
    joints = est.joints.detach().double().cpu().numpy()
    step = np.linalg.norm(joints[1:] - joints[:-1], axis=-1).mean(-1)  # (T-1,)
    jumps = np.flatnonzero(step > JUMP_FACTOR * max(float(np.median(step)) if len(step) else 0.0, 1e-9)) + 1
    bounds = [0, *jumps.tolist(), frames]
    angular = np.asarray(sk.angular_dofs(), dtype=bool)
    unwrapped = q.copy()
    unwrapped[:, angular] = np.unwrap(q[:, angular], axis=0)
    b, a = lowpass.butterworth2(cutoff_hz, fps)
    smooth = unwrapped.copy()
    for start, end in itertools.pairwise(bounds):
        if end - start > lowpass.PAD:  # the filter's end padding needs more frames than this
            smooth[start:end] = lowpass.filtfilt(b, a, unwrapped[start:end])
    lower, upper = (x.double().cpu().numpy() for x in sk.limits(dtype=torch.float64))
    out = torch.as_tensor(np.clip(q + (smooth - unwrapped), lower, upper), dtype=est.q.dtype, device=est.q.device)
    return est._replace(q=out, joints=sk.forward_kinematics(out))


def with_swap_cost(cfg: RunConfig, prep: Prepared) -> tuple[RunConfig, Prepared]:
    """`costs.swap_cost: null` resolved: `AUTO_SWAP_COST` on real footage whose detector exchanged every left/right
    label of the person between two frames (`FootageFrame.mirror_switches`), else 0 (off); a number is kept. ->
    the config with the price the run uses, and `prep` whose footage record holds it (metrics.json)."""
    from ptrack.costs.config import AUTO_SWAP_COST

    price = cfg.costs.swap_cost
    if price is None:
        price = AUTO_SWAP_COST if prep.footage is not None and prep.footage.mirror_switches else 0.0
        if price:
            assert prep.footage is not None
            log.warning(
                "the detector turns every left/right label of the person over at frame(s) %s (it takes them for "
                "someone facing the other way): each frame is read both ways, at costs.swap_cost %g",
                ", ".join(str(f) for f in prep.footage.mirror_switches),
                price,
            )
        cfg = dataclasses.replace(cfg, costs=dataclasses.replace(cfg.costs, swap_cost=price))
    if prep.footage is not None:
        prep = dataclasses.replace(prep, footage=dataclasses.replace(prep.footage, swap_cost=float(price)))
    return cfg, prep


def tracked_every(cfg: RunConfig, prep: Prepared) -> int:
    """How many input frames one tracked frame stands for: real footage faster than `observations.track_fps` is
    tracked every n-th frame, n = round(fps / track_fps) (60 fps at 30: every 2nd); else 1."""
    track_fps = cfg.observations.track_fps
    if prep.footage is None or track_fps is None or prep.footage.fps <= track_fps:
        return 1
    return max(round(prep.footage.fps / track_fps), 1)


def fill_frames(sk: Skeleton, est: Estimate, n: int, frames: int) -> Estimate:
    """An estimate of every n-th frame (S of them: frames 0, n, ..., (S-1) n) -> one of every frame (`frames`).

    The pose q between two tracked frames is interpolated (angles along their shorter way round, the root's in one
    set of angles along the path: `continuous_root`), the last one
    held after it, and its joints are its forward kinematics. A filled frame's cost, terms, hypothesis weights and
    costs, joint std and hypothesis directions are those of the tracked frame before it; its hypotheses are that
    frame's moved with the reported body (each by the filled frame's joints minus the tracked frame's); no kinematic
    jumps are counted on it. n = 1: `est` itself."""
    if n == 1:
        return est
    est = est._replace(q=continuous_root(sk, est.q))  # interpolated within one set of root angles
    lo, hi, w = _neighbours(n, frames, est.q.shape[0])
    tracked = torch.arange(frames) == lo * n  # the others filled (and any held after the last tracked frame)
    step = est.q[hi] - est.q[lo]
    angular = torch.as_tensor(sk.angular_dofs(), device=est.q.device)
    step = wrapped_difference(step, angular)
    q = est.q[lo] + w.to(est.q.dtype)[:, None] * step
    with torch.no_grad():
        joints = sk.forward_kinematics(q).to(est.joints.dtype)

    def held(x: torch.Tensor | None) -> torch.Tensor | None:
        return None if x is None else x[lo.to(x.device)]

    hypotheses = None
    if est.hypotheses is not None:
        moved = (joints - est.joints[lo.to(joints.device)])[:, None]
        hypotheses = est.hypotheses[lo.to(est.hypotheses.device)] + moved.to(est.hypotheses)
    jumps = None
    if est.jumps is not None:
        jumps = {c: torch.where(tracked.to(x.device), x[lo.to(x.device)], 0) for c, x in est.jumps.items()}
    return est._replace(
        q=q,
        joints=joints,
        cost=est.cost[lo.to(est.cost.device)],
        terms={k: v[lo.to(v.device)] for k, v in est.terms.items()},
        hypotheses=hypotheses,
        hypothesis_weights=held(est.hypothesis_weights),
        hypothesis_costs=held(est.hypothesis_costs),
        joint_std=held(est.joint_std),
        hypothesis_directions=held(est.hypothesis_directions),
        jumps=jumps,
    )


def measure_config(cfg: RunConfig) -> RunConfig:
    """The config of real footage's first (measuring) run: `cfg` with kjs.backward_pass set to
    `subject.measure_backward_pass` (when given and the method is kjs); else `cfg` itself."""
    bp = cfg.subject.measure_backward_pass
    if cfg.method != "kjs" or bp is None or bp == cfg.kjs.backward_pass:
        return cfg
    return dataclasses.replace(cfg, kjs=dataclasses.replace(cfg.kjs, backward_pass=bp))


def between_frames(x: torch.Tensor, n: int, frames: int) -> torch.Tensor:
    """Values of every n-th frame (S, ...) (frames 0, n, ..., (S-1) n) -> every frame (frames, ...): linear
    between the given ones, the last one held after it."""
    lo, hi, w = _neighbours(n, frames, x.shape[0])
    w = w.to(x.dtype).reshape(-1, *([1] * (x.ndim - 1)))
    return x[lo] * (1 - w) + x[hi] * w


def _neighbours(n: int, frames: int, count: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each of `frames` frames between the `count` tracked ones (frames 0, n, ..., (count-1) n) -> the tracked
    frame before it and after it (frames,) long, indices into the tracked ones, and its weight on the one after
    (frames,) float64 in [0, 1): 0 on a tracked frame and after the last one (held)."""
    t = torch.arange(frames, dtype=torch.float64) / n
    lo = t.floor().long().clamp(max=count - 1)
    hi = (lo + 1).clamp(max=count - 1)
    w = torch.where(lo == hi, torch.zeros_like(t), (t - lo).clamp(max=1.0))
    return lo, hi, w


def level_to_person(prep: Prepared, est: Estimate) -> Prepared | None:
    """Real footage whose camera does not give the up axis: `prep` turned so that +Y is the normal of the floor
    fitted to the feet of `est` (`ptrack.estimators.ground`), with that floor (`Problem.floor`), or None when the
    feet do not show it. The model frame turns by G (the smallest rotation taking the normal to +Y): the camera's
    R becomes R G^T; a calibration world keeps its own frame (world_from_model W G^T), a camera without
    extrinsics reports the turned frame itself (world_from_model = I)."""
    from ptrack.body.subject import floor_points
    from ptrack.estimators.ground import floor_from_feet
    from ptrack.pipeline.footage import axis_to_y

    f = prep.footage
    assert f is not None
    prob = prep.problem
    joints, clearance = floor_points(prob.skeleton, f.height_m)
    feet = est.joints.detach().double().cpu().numpy()[:, list(joints)]
    seen = prep.visible.numpy().any(-1) if prep.visible is not None else np.ones(len(feet), dtype=bool)
    fit = floor_from_feet(feet[seen], np.array([0.0, 1.0, 0.0]), clearance)
    if fit is None:
        log.info("the floor could not be fitted to the feet: the camera's image-up stays up, no floor")
        return None
    G = axis_to_y(fit.normal)
    log.info(
        "floor from the person: tilted %.1f degrees from the camera's image-up, %.2f m along it (%d frames on it, "
        "spread %.2f x %.2f m)",
        fit.tilt_deg,
        fit.height_m,
        fit.contacts,
        *fit.spread_m,
    )
    cam = prob.observations.camera
    Gt = torch.as_tensor(G.T, dtype=cam.R.dtype, device=cam.R.device)
    camera = dataclasses.replace(cam, R=cam.R @ Gt)
    ground = {"tilt_deg": fit.tilt_deg, "contacts": fit.contacts, "spread_m": [float(v) for v in fit.spread_m]}
    footage = dataclasses.replace(
        f,
        floor_m=fit.height_m,
        world_from_model=f.world_from_model @ G.T if f.extrinsics else f.world_from_model,
        up="person",
        ground=ground,
    )
    problem = dataclasses.replace(
        prob,
        observations=dataclasses.replace(prob.observations, camera=camera),
        floor=Floor(fit.height_m, joints, clearance),
    )
    return dataclasses.replace(prep, problem=problem, footage=footage)


#: the segments `subject.lengths: observed` measures in the 2D
MEASURED_SEGMENTS = ("thigh", "shank", "upper_arm", "forearm", "trunk")


def rescale_subject(prep: Prepared, est: Estimate, depth_from_floor: bool = False) -> Prepared:
    """Real footage, `subject.lengths: observed`: `prep` with its model rescaled to the segments' lengths measured
    in the 2D at the depths of `est` (`ptrack.estimators.lengths`; with `depth_from_floor` and a floor, those depths
    scaled so that the standing feet touch it), the footage record holding them."""
    from ptrack.body.subject import SEGMENTS
    from ptrack.estimators.lengths import floor_depth_factor, segment_length_spread, segment_lengths_from_2d

    assert prep.footage is not None
    f = prep.footage
    # the limbs and the trunk: the widths (hips, shoulders) reach the image plane only when the person faces the
    # camera, the head and foot segments rarely
    segments = {n: (a, b) for n, (a, b, _) in SEGMENTS.items() if n in MEASURED_SEGMENTS}
    scale = floor_depth_factor(prep.problem, est) if depth_from_floor else None
    if scale is not None:
        log.info("the first run's standing feet touch the floor %.3f times as far from the camera", scale)
    measured = segment_lengths_from_2d(prep.problem, est, f.landmarks, segments, scale=scale)
    spread = segment_length_spread(prep.problem, est, f.landmarks, segments, scale=scale)  # other frames' spread
    record = {n: {"length_m": v, "frames": k, "std_m": spread.get(n)} for n, (v, k) in measured.items()}
    log.info("segment lengths from the 2D: %s", ", ".join(f"{n} {v:.3f} m" for n, (v, _) in measured.items()))
    return with_segments(prep, record)


def with_segments(prep: Prepared, record: dict[str, dict]) -> Prepared:
    """Real footage: `prep` with its model's segments at the lengths `record` gives ({segment: {"length_m", ...}},
    the others at their fractions of the height: `ptrack.body.subject.rescale_segments`), the footage record
    holding `record` (metrics.json `footage.segments_measured`)."""
    from ptrack.body.subject import rescale_segments

    assert prep.footage is not None
    lengths = {n: v["length_m"] for n, v in record.items()}
    sk = rescale_segments(prep.problem.skeleton, prep.footage.height_m, lengths)
    return dataclasses.replace(
        prep,
        problem=dataclasses.replace(prep.problem, skeleton=sk),
        full=dataclasses.replace(prep.full, lengths=sk.lengths),
        footage=dataclasses.replace(prep.footage, segments=record),
    )


def execute(cfg: RunConfig, progress: bool | None = None) -> Path:
    """Run `cfg` end to end and write its folder; returns the folder's path."""
    out = Path(cfg.out_dir) if cfg.out_dir else default_out_dir(cfg)
    check_out_dir(out)
    claim = claim_out_dir(out)  # a second run into `out` refuses from here on
    try:
        cfg = dataclasses.replace(cfg, out_dir=str(out.resolve()))  # config.yaml records the folder used
        t0 = time.perf_counter()
        prep, est = estimate(cfg, cfg.progress if progress is None else progress, work_dir=claim.path)
        seconds = time.perf_counter() - t0
        check_finite(est, cfg.method)
        reproj = reprojected_keypoints(prep, est)
        summary, series = compute_metrics(prep, est, reproj)
        check_reprojection(prep, reproj, cfg.costs.sigma_px)
        summary = {
            "method": cfg.method,
            "frames": int(est.q.shape[0]),
            "seconds": seconds,
            "fps": float(est.q.shape[0] / seconds),
            **summary,
        }
        if prep.footage is not None:
            summary["footage"] = prep.footage.summary()
        _write_outputs(claim.path, cfg, prep, est, result_arrays(prep, est, reproj), summary, series)
        claim.finish(out)
    except BaseException:
        claim.release()
        raise
    return out


def remove_partial(folder: Path, recursive: bool = True) -> None:
    """Remove what runs that were killed while writing left in `folder` (recursive: and below it): the hidden
    siblings their folders were being assembled in and the empty folders `check_out_dir` probes with (a run
    stopped any other way removes its own). A live run's claim, locked by its process, stays."""
    found = folder.rglob if recursive else folder.glob
    for tmp in sorted([*found(f".*{PARTIAL}"), *found(f".*{CLAIMING}")]):
        if tmp.is_dir():
            _remove_if_stale(tmp)
    for probe in found(f".*{PROBE}"):  # empty folders, never locked: a run killed between making and removing
        with suppress(OSError):
            probe.rmdir()


#: off a terminal, progress is a log line (logger `ptrack.pipeline.run.progress`, INFO) at most every
#: PROGRESS_SECONDS, the first after PROGRESS_FIRST_SECONDS (a short run says nothing); the environment variable
#: PTRACK_PROGRESS_SECONDS replaces both (read at each run)
PROGRESS_SECONDS, PROGRESS_FIRST_SECONDS = 20.0, 10.0
progress_log = logging.getLogger(f"{__name__}.progress")


def progress_display(show: bool, desc: str) -> Callable[[Iterable], Iterable]:
    """A progress bar on stderr on a terminal; elsewhere (a file, a CI log: each update of a bar would be a line)
    a log line now and then (`progress_lines`)."""
    if not show:
        return lambda it: it
    if not sys.stderr.isatty():
        env = os.environ.get("PTRACK_PROGRESS_SECONDS", "").strip()
        every, first = PROGRESS_SECONDS, PROGRESS_FIRST_SECONDS
        if env:
            try:
                every = first = float(env)
            except ValueError:
                raise InputError(f"environment variable PTRACK_PROGRESS_SECONDS must be seconds, got {env!r}") from None
        return lambda it: progress_lines(it, desc, every=every, first=first)
    from tqdm.auto import tqdm

    return lambda it: tqdm(it, desc=desc, unit="frame", leave=False)


def progress_lines(
    items: Iterable, desc: str, every: float, first: float, clock: Callable[[], float] = time.monotonic
) -> Iterable:
    """`items` one by one, logging (`progress_log`, INFO) how far the loop is, its rate and the time left, when an
    item is taken `first` seconds or more after the start and then at most every `every` seconds:
    "kjs: frame 400/2751 (14%), 12.3 frames/s, about 3 min left" (without a total, the count and rate)."""
    total = len(items) if isinstance(items, Sized) else None
    start = clock()
    due = start + first
    for i, item in enumerate(items):
        now = clock()
        if i and now >= due:
            rate = i / max(now - start, 1e-9)
            if total:
                progress_log.info(
                    "%s: frame %d/%d (%.0f%%), %.3g frames/s, about %s left",
                    desc,
                    i,
                    total,
                    100 * i / total,
                    rate,
                    _duration((total - i) / rate),
                )
            else:
                progress_log.info("%s: frame %d, %.3g frames/s", desc, i, rate)
            due = now + every
        yield item


def _duration(seconds: float) -> str:
    """A rough duration: "40 s", "3 min", "1.5 h"."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def result_arrays(prep: Prepared, est: Estimate, reproj: torch.Tensor | None = None) -> dict[str, np.ndarray]:
    """The arrays of result.npz: frames (T,) AMC frame numbers; times (T,) s; fps () the exact frame rate
    (`frame_rate`); q (T, D); dof_names (D,); joints (T, J, 3)
    metres in the mocap world frame (Y up); joint_names (J,) (ASF bone names, "root" first); parents (J,);
    gt_joints (T, J, 3) when there is ground truth; keypoints_observed (T, K, 2), confidence (T, K),
    keypoint_names (K,), keypoints_reprojected (T, K, 2); camera_K/R/t, image_size; cost (T,);
    hypotheses (T, N, J, 3), hypothesis_weights (T, N), hypothesis_costs (T, N) where the method has them;
    hypothesis_directions (T, N, J, 3) (each hypothesis's principal covariance direction as joint displacements),
    jump_chains (C,) and jump_counts (T, C) (kinematic-jump leaves kept per chain and frame) from the trackers;
    pca_weights (T, m), pca_time (T,), pca_modelled (T,) bool, key_posture_frames (P,) (indices into the run's
    frames) and key_posture_names (P,) from `method: pca`;
    joint_std (T, J) metres and solver_cost (I+1,) (objective per solver iteration) from `method: batch`.
    reproj: `reprojected_keypoints(prep, est)` when already computed."""
    if reproj is None:
        reproj = reprojected_keypoints(prep, est)
    prob = prep.problem
    obs, sk = prob.observations, prob.skeleton
    cam = obs.camera
    joints = est.joints.detach()
    arrays = {
        "frames": prep.frames.astype(np.int64),
        "times": obs.times.detach().cpu().numpy(),
        "fps": np.float64(frame_rate(prep)),
        "q": est.q.detach().cpu().numpy(),
        "dof_names": np.asarray(sk.dof_names),
        "joints": joints.cpu().numpy(),
        "joint_names": np.asarray(sk.joint_names),
        "parents": np.asarray(sk.parents, dtype=np.int64),
        "keypoints_observed": obs.keypoints.detach().cpu().numpy(),
        "confidence": obs.confidence.detach().cpu().numpy(),
        "keypoint_names": np.asarray(prob.keypoints.names),
        "keypoints_reprojected": reproj.cpu().numpy(),
        "camera_K": cam.K.detach().cpu().numpy(),
        "camera_R": cam.R.detach().cpu().numpy(),
        "camera_t": cam.t.detach().cpu().numpy(),
        "image_size": np.asarray([cam.width, cam.height], dtype=np.int64),
        "cost": est.cost.detach().cpu().numpy(),
    }
    if prep.gt_joints is not None:
        arrays["gt_joints"] = prep.gt_joints.detach().cpu().numpy()
    if prep.footage is not None:  # the keypoints under the input format's names, in the calibration's world
        arrays["keypoints"] = keypoints_in_world(prep.footage, prob.keypoints, joints)
        arrays["world_from_model"] = prep.footage.world_from_model
    for name in (
        "hypotheses",
        "hypothesis_weights",
        "hypothesis_costs",
        "joint_std",
        "solver_cost",
        "hypothesis_directions",
    ):
        v = getattr(est, name)
        if v is not None:
            arrays[name] = v.detach().cpu().numpy()
    if est.jumps:
        arrays["jump_chains"] = np.asarray(list(est.jumps))
        arrays["jump_counts"] = torch.stack(list(est.jumps.values()), dim=-1).cpu().numpy()
    if est.motion is not None:
        arrays["pca_weights"] = est.motion.weights.detach().cpu().numpy()
        arrays["pca_time"] = est.motion.time.detach().cpu().numpy()
        arrays["pca_modelled"] = est.motion.modelled.detach().cpu().numpy().astype(bool)
        arrays["key_posture_frames"] = est.motion.key_frames.detach().cpu().numpy().astype(np.int64)
        arrays["key_posture_names"] = np.asarray(est.motion.key_names)
    return arrays


def frame_rate(prep: Prepared) -> float:
    """The run's frames per second, exactly: the clip's (120 / data.stride for CMU), the footage's (observations.fps,
    the keypoint file's or the video's), else from the observations' times (their median step; 30 for one frame)."""
    if prep.footage is not None:
        return prep.footage.fps
    if prep.motion is not None:
        return float(prep.motion.fps)
    times = prep.problem.observations.times.detach().cpu().double().numpy()
    return float(1.0 / np.median(np.diff(times))) if len(times) > 1 else 30.0


def _write_outputs(
    tmp: Path,
    cfg: RunConfig,
    prep: Prepared,
    est: Estimate,
    res: dict[str, np.ndarray],
    summary: dict,
    series: dict[str, np.ndarray],
) -> None:
    """Write the run's files into `tmp` (the run's claim, `claim_out_dir`)."""
    from ptrack.io.viz import write_recording

    (tmp / "config.yaml").write_text(dump_yaml(cfg), encoding="utf-8")
    (tmp / "metrics.json").write_text(
        json.dumps(json_safe(summary), indent=2, allow_nan=False) + "\n", encoding="utf-8"
    )
    np.savez_compressed(tmp / "result.npz", **res)  # type: ignore[arg-type]  # numpy's stub: a key could be allow_pickle
    (tmp / "skeleton.urdf").write_text(prep.problem.skeleton.to_urdf(), encoding="utf-8")  # `ptrack export` reads it
    floor = prep.footage.floor_m if prep.footage is not None else None  # the BVH's floor at Y = 0 when known
    write_bvh(tmp / "result.bvh", prep.problem.skeleton, est.q, float(res["fps"]), floor_m=floor)
    write_recording(tmp / "run.rrd", _run_log(prep, res, series))
    if cfg.plots:
        write_run_plots(tmp / "plots", res, series)


def write_run_plots(folder: Path, res: dict[str, np.ndarray], series: dict[str, np.ndarray]) -> None:
    """The run's pictures (`ptrack.io.plots`) in `folder`; a failure is a warning, never the run's."""
    try:
        from ptrack.io.plots import write_plots

        write_plots(folder, res, series)
    except Exception as e:
        log.warning("plots not written: %s: %s", type(e).__name__, e)


def recording(prep: Prepared, est: Estimate) -> RunLog:
    """The rerun log of `est` (`estimate`'s), as a run's run.rrd holds it: `ptrack.io.viz.write_recording(path,
    recording(prep, est))` writes it, `rerun path` shows it."""
    reproj = reprojected_keypoints(prep, est)
    _, series = compute_metrics(prep, est, reproj)
    return _run_log(prep, result_arrays(prep, est, reproj), series)


def _run_log(prep: Prepared, res: dict[str, np.ndarray], series: dict[str, np.ndarray]) -> RunLog:
    """The rerun log of a run from its result arrays (`result_arrays`) and per-frame metrics (`compute_metrics`)."""
    from ptrack.io.viz import RunLog

    prob = prep.problem
    obs = prob.observations
    return RunLog(
        joint_names=prob.skeleton.joint_names,
        parents=prob.skeleton.parents,
        frames=prep.frames,
        times=res["times"],
        estimate=res["joints"],
        ground_truth=res.get("gt_joints"),
        camera=obs.camera.to(device="cpu"),
        observed=res["keypoints_observed"],
        confidence=res["confidence"],
        reprojected=res["keypoints_reprojected"],
        keypoint_names=prob.keypoints.names,
        keypoint_joints=prob.keypoints.joints,
        hypotheses=res.get("hypotheses"),
        hypothesis_weights=res.get("hypothesis_weights"),
        hypothesis_costs=res.get("hypothesis_costs"),
        hypothesis_directions=res.get("hypothesis_directions"),
        jumps=dict(zip(res["jump_chains"].tolist(), res["jump_counts"].T)) if "jump_chains" in res else {},
        motion_weights=res.get("pca_weights"),
        motion_time=res.get("pca_time"),
        key_postures=dict(zip(res["key_posture_names"].tolist(), res["key_posture_frames"].tolist()))
        if "key_posture_names" in res
        else {},
        scalars=series,
        masks=obs.masks.cpu().numpy() if obs.masks is not None else None,
        joint_std=res.get("joint_std"),
        solver_cost=res.get("solver_cost"),
        **_video(prep),
    )


def _video(prep: Prepared) -> dict:
    """RunLog's video arguments: the run's MP4 video and the video frame of each run frame, where there is one."""
    video = prep.footage.video if prep.footage is not None else None
    if video is None or Path(video).suffix.lower() != ".mp4" or not Path(video).is_file():
        return {}
    return {"video": str(video), "video_frames": np.asarray(prep.frames, dtype=np.int64)}
