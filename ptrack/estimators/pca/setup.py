"""What the golf tracker (`method: pca`) holds fixed over a sequence (`Setup`): the motion model (`motion_model_for`),
the index maps of its dofs and the root's, the tracked joints' observations, the foreground samples' rays, the
capsule model and the correspondences (`make_setup`). Shapes: T frames, K' tracked joints, S samples, P pairs."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
from torch import Tensor

from ptrack.body.keypoints import KeypointSet
from ptrack.body.skeleton import Skeleton
from ptrack.costs.ray_silhouette import mask_samples
from ptrack.errors import InputError
from ptrack.estimators.pca.config import PcaRunConfig
from ptrack.motion.motion_model import (
    MotionModel,
    clip_paths,
    dof_index,
    fit_motion_model,
    load_motion_model,
    model_path,
    read_clips,
    save_motion_model,
)
from ptrack.observe.silhouette import capsule_radii
from ptrack.problem import Problem

log = logging.getLogger(__name__)


def motion_model_for(cfg: PcaRunConfig, skeleton: Skeleton) -> MotionModel:
    """The run's motion model: `motion.model_file` (or the cache path) if it exists, else fitted from
    `motion.clips` and saved there. InputError for a corrupt file, one of another skeleton, or no file
    and no clips."""
    path = model_path(cfg)
    if path.is_file():
        log.info("pca: motion model %s", path)
        return load_motion_model(path, skeleton)
    if not cfg.motion.clips:
        raise InputError(
            f"no motion model at {path} (config key 'motion.model_file') and no training clips to fit "
            f"one (config key 'motion.clips'); run `ptrack fit-motion` or set motion.clips"
        )
    clips = read_clips(clip_paths(cfg.motion.clips))
    model = fit_motion_model(clips, cfg.motion)
    save_motion_model(model, path)
    log.info("pca: fitted a motion model on %d clips, saved to %s", len(clips), path)
    return load_motion_model(path, skeleton)


@dataclass(frozen=True, eq=False)
class Setup:
    """Everything fixed over the sequence: model, index maps, observations of the tracked joints, rays of the
    foreground samples."""

    problem: Problem
    cfg: PcaRunConfig  # the run's config (a `ptrack.pipeline.config.RunConfig`)
    model: MotionModel
    model_dofs: Tensor  # (Dm,) positions of the model's dofs in q
    root_dofs: Tensor  # (6,) positions of root tx, ty, tz and the root's three angles in q
    tracked: Tensor  # (K',) skeleton joints of the tracked keypoints
    observed: Tensor  # (T, K', 2) pixels
    confidence: Tensor  # (T, K') the detections' confidence (0: missing)
    rays: Tensor | None  # (T, S, 3) unit world rays of the foreground samples
    ray_valid: Tensor | None  # (T, S) bool
    bones: tuple[tuple[int, int], ...]
    radii: Tensor  # (B,) capsule radii, metres
    alpha_sigma: Tensor  # (m,) the training swings' spread of each PCA weight
    root_order: str  # the root's Euler order for `matrix_to_euler_np` ("XYZ": x applied first)
    root_xyz: tuple[int, ...]  # (3,) coordinate axis (0 x, 1 y, 2 z) of each of root_dofs[3:]
    root_rest: Tensor  # (3, 3) the root's world rotation at zero angles (the ASF root orientation)
    # correspondences by second frame t (None: none, or pca.correspondence_weight 0): p1 (T, P, 2) pixels in
    # frame t-1, p2 (T, P, 2) in frame t, weight (T, P) the pair's weight (0: padding)
    corr: tuple[Tensor, Tensor, Tensor] | None = None
    corr_rays: Tensor | None = None  # (T, P, 3) unit world rays of p1 (set with corr)

    @property
    def m(self) -> int:
        return self.model.num_components

    @property
    def silhouette_radii(self) -> Tensor:
        """(B,) the foreground term's capsule radii: the model's times pca.silhouette_radius_scale."""
        return self.radii * self.cfg.pca.silhouette_radius_scale


#: where a keypoint set has no point of that name, `pca.joints`' "head" (the simulated set's) is the first of these
#: landmarks the set has: the top of the head (OpenPose BODY_25B's HeadTop), else the nose (COCO-17, MediaPipe)
HEAD_LANDMARKS = ("head_top", "nose")


def tracked_keypoint(kps: KeypointSet, name: str) -> int | None:
    """The keypoint `pca.joints` names: by the set's own name ("LKnee" in BODY_25B), else by landmark ("l_knee" on
    any detector's set, `KeypointSet.find`); "head" also by `HEAD_LANDMARKS`. -> its index, or None."""
    if name in kps.names:
        return kps.names.index(name)
    for landmark in HEAD_LANDMARKS if name == "head" else (name,):
        k = kps.find(landmark)
        if k is not None:
            return k
    return None


def make_setup(problem: Problem, cfg: PcaRunConfig) -> Setup:
    sk, obs, kps = problem.skeleton, problem.observations, problem.keypoints
    p = cfg.pca
    dtype, device = obs.keypoints.dtype, obs.keypoints.device
    found = [tracked_keypoint(kps, j) for j in p.joints]
    kp = [k for k in found if k is not None]
    if len(kp) < len(found):
        missing = p.joints[found.index(None)]
        raise InputError(
            f"config key 'pca.joints': unknown keypoint {missing!r} (keypoints: {', '.join(kps.names)}; or a landmark "
            "such as l_knee)"
        )
    model = motion_model_for(cfg, sk)
    model_dofs = dof_index(model, sk).to(device)
    root = [int(d) for d in (*sk.translation_dof, *sorted(sk.axis_dof[0].tolist())) if d >= 0]
    if len(root) != 6:
        raise InputError(
            f"method pca needs a root with 3 translation and 3 rotation dofs; {sk.name!r} has "
            f"{len(root)} (check model.freeze)"
        )
    other = sorted(set(range(sk.num_dofs)) - set(root) - set(model_dofs.tolist()))
    if other:
        log.warning(
            "pca: %d dofs are not in the motion model and held at zero (e.g. %s)", len(other), sk.dof_names[other[0]]
        )
    tracked = torch.as_tensor([kps.joints[k] for k in kp], dtype=torch.long, device=device)
    observed = obs.keypoints[:, kp].to(dtype)
    conf = obs.confidence[:, kp].to(dtype)
    observed = torch.where(conf[..., None] > 0, observed, 0.0)
    bones = tuple((int(a), int(b)) for a, b in sk.bones())
    bone_t = torch.as_tensor(bones, dtype=torch.long)
    radii = capsule_radii(
        [sk.joint_names[b] for _, b in bones], torch.as_tensor(sk.lengths[bone_t[:, 1]], dtype=dtype)
    ).to(device)
    rays = valid = None
    if p.silhouette_weight > 0:
        if obs.masks is None:
            log.warning(
                "pca: pca.silhouette_weight is %g but the observations have no silhouettes "
                "(observations.silhouettes); tracking the joints only",
                p.silhouette_weight,
            )
        else:
            pixels, valid = mask_samples(obs.masks, p.silhouette_step_px, p.silhouette_samples)
            _, rays = obs.camera.rays(pixels.to(dtype))
    # the root turns by R(a1) R(a2) R(a3) (slot axes a1..a3, a3 applied first): its Euler order and axes
    axes = sk.axes[0]
    coord = [int(abs(a).argmax()) for a in axes]
    if any(not (abs(a[c] - 1.0) < 1e-9) for a, c in zip(axes, coord)):
        raise InputError(
            f"method pca needs a root turning about the coordinate axes; {sk.name!r}'s root axes are {axes.tolist()}"
        )
    order = "".join("XYZ"[c] for c in reversed(coord))
    slot_of = {int(d): k for k, d in enumerate(sk.axis_dof[0].tolist()) if d >= 0}
    root_xyz = tuple(coord[slot_of[d]] for d in root[3:])
    with torch.no_grad():
        _, rest = sk.forward_kinematics(torch.zeros(sk.num_dofs, dtype=dtype, device=device), rotations=True)
    corr = corr_rays = None
    if problem.correspondences is not None and p.correspondence_weight > 0:
        p1, p2, w = problem.correspondences.to(device=device, dtype=dtype).by_frame(obs.num_frames)
        corr = (p1, p2, w)
        _, corr_rays = obs.camera.rays(p1)  # backprojected once per window: made once here
    return Setup(
        problem,
        cfg,
        model,
        model_dofs,
        torch.as_tensor(root, device=device),
        tracked,
        observed,
        conf,
        rays,
        valid,
        bones,
        radii,
        model.sigma.to(dtype=dtype, device=device),
        order,
        root_xyz,
        rest[0],
        corr,
        corr_rays,
    )
