"""What an estimator is given and what it returns.

`Problem` bundles the model, the keypoint set, the observations and any user 3D keyframes;
`Estimate` is the result record every method returns. `evaluate_pose` runs forward kinematics and
projection once for a batch of poses, giving the `PoseEval` record that cost terms consume.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from ptrack.body.keypoints import KeypointSet
from ptrack.body.limits import outside_limits, wrap_to_limits
from ptrack.body.skeleton import Skeleton
from ptrack.costs import FloorContact, PoseEval
from ptrack.errors import InputError
from ptrack.observe.camera import Camera
from ptrack.observe.correspondences import Correspondences
from ptrack.observe.observations import Observations

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Keyframes:
    """User-given 3D poses. frames: (F,) indices into the reconstruction frames; q: (F, D);
    mask: (F, D) bool, True where a dof is given (partial keyframes), None = all given;
    sigma: (F, D) standard deviation of each given dof (radians / metres; DiFranco et al. eq. 4),
    None = the estimator's default; covariance: (F, D, D) the full covariance of each keyframe's given
    dofs (radians and metres; the entries of dofs not given are not read), replacing sigma, or None."""

    frames: Tensor
    q: Tensor
    mask: Tensor | None = None
    sigma: Tensor | None = None
    covariance: Tensor | None = None

    def __post_init__(self) -> None:
        if self.frames.ndim != 1 or self.q.ndim != 2 or self.q.shape[0] != self.frames.shape[0]:
            raise InputError(
                f"keyframes: frames (F,) and q (F, D) expected, got {tuple(self.frames.shape)} "
                f"and {tuple(self.q.shape)}"
            )
        if self.mask is not None and self.mask.shape != self.q.shape:
            raise InputError(f"keyframes: mask shape {tuple(self.mask.shape)} must equal q's {tuple(self.q.shape)}")
        if self.sigma is not None and self.sigma.shape != self.q.shape:
            raise InputError(f"keyframes: sigma shape {tuple(self.sigma.shape)} must equal q's {tuple(self.q.shape)}")
        f, d = self.q.shape
        if self.covariance is not None and self.covariance.shape != (f, d, d):
            raise InputError(f"keyframes: covariance shape {tuple(self.covariance.shape)} must be ({f}, {d}, {d})")


@dataclass(frozen=True)
class JointKeyframes:
    """User-given 3D joint positions. frames: (F,) indices into the reconstruction frames; joints:
    (F, J, 3) metres in the world frame; mask: (F, J) bool, True where a joint is given; sigma: (F, J)
    metres, the standard deviation of each coordinate of each given joint ((F,): one per keyframe);
    covariance: (F, 3J, 3J) the full covariance of each keyframe's joint coordinates (m^2; row 3j + c is
    joint j's coordinate c; only the given joints' block is read), replacing sigma, or None."""

    frames: Tensor
    joints: Tensor
    mask: Tensor
    sigma: Tensor
    covariance: Tensor | None = None

    def __post_init__(self) -> None:
        f = self.frames.shape[0]
        ok = self.frames.ndim == 1 and self.joints.ndim == 3 and self.joints.shape[0] == f and self.joints.shape[2] == 3
        j = self.joints.shape[1] if ok else 0
        if not ok or self.mask.shape != self.joints.shape[:2] or self.sigma.shape not in ((f,), (f, j)):
            raise InputError(
                f"joint keyframes: frames (F,), joints (F, J, 3), mask (F, J), sigma (F, J) expected, got "
                f"{tuple(self.frames.shape)}, {tuple(self.joints.shape)}, {tuple(self.mask.shape)}, "
                f"{tuple(self.sigma.shape)}"
            )
        if self.sigma.shape == (f,):
            object.__setattr__(self, "sigma", self.sigma[:, None].expand(f, j))
        if self.covariance is not None and self.covariance.shape != (f, 3 * j, 3 * j):
            raise InputError(
                f"joint keyframes: covariance shape {tuple(self.covariance.shape)} must be ({f}, {3 * j}, {3 * j})"
            )


@dataclass(frozen=True)
class Floor:
    """A known floor plane under the person: height_m along the model frame's +Y (metres), joints (F,) the
    skeleton's foot points that can touch it, clearance_m how high the lowest of them sits when a foot stands
    flat (metres)."""

    height_m: float
    joints: tuple[int, ...]
    clearance_m: float = 0.0

    def __post_init__(self) -> None:
        if not self.joints:
            raise InputError("floor: no foot joints to rest on it")

    def term(self, sigma_m: float) -> FloorContact:
        """The floor contact cost term on this floor, its scale `sigma_m` metres (`costs.floor_sigma_m`)."""
        return FloorContact(self.joints, self.height_m, self.clearance_m, sigma_m)


@dataclass(frozen=True)
class Problem:
    """skeleton: the model to estimate (possibly reduced); observations: T frames of K keypoints."""

    skeleton: Skeleton
    keypoints: KeypointSet
    observations: Observations
    keyframes: Keyframes | None = None
    joint_keyframes: JointKeyframes | None = None
    # point pairs between consecutive frames (section 4.3 of Urtasun et al.; read by method pca)
    correspondences: Correspondences | None = None
    # a known floor plane (real footage whose calibration gives the world's up axis; read by kjs and frame)
    floor: Floor | None = None

    def __post_init__(self) -> None:
        if self.observations.num_keypoints != self.keypoints.num_keypoints:
            raise InputError(
                f"observations have {self.observations.num_keypoints} keypoints, the keypoint set "
                f"has {self.keypoints.num_keypoints} ({', '.join(self.keypoints.names)})"
            )
        if self.keyframes is not None and self.keyframes.q.shape[-1] != self.skeleton.num_dofs:
            raise InputError(
                f"keyframes have {self.keyframes.q.shape[-1]} dofs, the model has {self.skeleton.num_dofs}"
            )
        if self.keyframes is not None:
            warn_keyframes_outside_limits(self.skeleton, self.keyframes)
        if self.correspondences is not None:
            self.correspondences.check_frames(self.observations.num_frames)


def later_frames(problem: Problem, start: int) -> Problem:
    """The same problem over its frames [start, T): observations (and silhouettes) from `start` on, keyframes and
    joint keyframes of those frames renumbered from 0; correspondences are left out (their pairs reach back to
    frame start - 1). For an estimator that hands the rest of a sequence to another (`method: pca` after the
    swing)."""
    if not 0 < start < problem.observations.num_frames:
        raise ValueError(f"later_frames: start {start} must be in (0, {problem.observations.num_frames})")
    return _frames(problem, start, 1)


def every_nth(problem: Problem, n: int) -> Problem:
    """The same problem over every n-th frame (0, n, 2n, ...): observations (times too, so the frame interval
    is n times longer) and silhouettes of those frames, keyframes and joint keyframes on them renumbered
    (t -> t / n), the others dropped; correspondences are left out (their pairs join neighbouring frames).
    n = 1: `problem` itself. For a first run that needs only a sample of the frames (real footage's
    measured lengths, `subject.measure_stride`)."""
    if n < 1:
        raise ValueError(f"every_nth: n {n} must be at least 1")
    return problem if n == 1 else _frames(problem, 0, n)


def _frames(problem: Problem, start: int, step: int) -> Problem:
    """The problem over its frames start, start + step, ...: observations and silhouettes of those frames,
    keyframes and joint keyframes on them renumbered ((t - start) / step), the others dropped; no
    correspondences (`later_frames`, `every_nth`)."""
    obs = problem.observations
    rows = slice(start, None, step)
    picked = Observations(
        obs.keypoints[rows],
        obs.confidence[rows],
        obs.times[rows],
        obs.camera,
        obs.keypoint_names,
        obs.masks[rows] if obs.masks is not None else None,
    )

    def on(frames: Tensor) -> Tensor:
        return (frames >= start) & ((frames - start) % step == 0)

    kf = problem.keyframes
    if kf is not None:
        keep = on(kf.frames)
        kf = (
            None
            if not bool(keep.any())
            else Keyframes(
                (kf.frames[keep] - start) // step,
                kf.q[keep],
                kf.mask[keep] if kf.mask is not None else None,
                kf.sigma[keep] if kf.sigma is not None else None,
                kf.covariance[keep] if kf.covariance is not None else None,
            )
        )
    jk = problem.joint_keyframes
    if jk is not None:
        keep = on(jk.frames)
        jk = (
            None
            if not bool(keep.any())
            else JointKeyframes(
                (jk.frames[keep] - start) // step,
                jk.joints[keep],
                jk.mask[keep],
                jk.sigma[keep],
                jk.covariance[keep] if jk.covariance is not None else None,
            )
        )
    return Problem(problem.skeleton, problem.keypoints, picked, kf, jk, None, problem.floor)


def first_keyframe(problem: Problem, key: str, lower: Tensor, upper: Tensor) -> Tensor:
    """The user's 3D pose of frame 0 as the start of a tracker whose config key `key` asked for it,
    its angles written in the limits' 2 pi window (the same pose; never clamped). -> (D,) in lower's
    dtype and device. Raises InputError when frame 0 has no keyframe."""
    kf = problem.keyframes
    if kf is None or not bool((kf.frames == 0).any()):
        raise InputError(f"{key} is 'keyframe' but no 3D keyframe is given for frame 0")
    q0 = kf.q[(kf.frames == 0).nonzero()[0, 0]].to(lower)
    angular = torch.as_tensor(problem.skeleton.angular_dofs(), device=lower.device)
    return wrap_to_limits(q0, lower, upper, angular)


def rest_pose_in_view(problem: Problem, dtype: torch.dtype, frame: int | None = None) -> Tensor:
    """A rest pose (all angles 0) whose root sits on the camera ray through the centre of the observed
    keypoints of `frame` (None, or a frame with none observed: the first frame with any), at the depth
    that makes the observed 2D body size match the model's. -> (D,)"""
    sk, obs, kps = problem.skeleton, problem.observations, problem.keypoints
    device = obs.keypoints.device
    q = torch.zeros(sk.num_dofs, dtype=dtype, device=device)
    conf = obs.confidence
    if frame is None or not bool((conf[frame] > 0).any()):
        frame = int(torch.nonzero(conf.sum(-1) > 0)[0, 0])
    valid = conf[frame] > 0
    pix = obs.keypoints[frame][valid].to(dtype)
    rest = sk.forward_kinematics(q)
    kp3 = rest.index_select(0, kps.index(device))[valid]
    size3 = (kp3 - kp3.mean(0)).norm(dim=-1).mean()
    size2 = (pix - pix.mean(0)).norm(dim=-1).mean().clamp(min=1.0)
    cam = obs.camera.to(device=device, dtype=dtype)
    depth = cam.K[0, 0] * size3 / size2
    origin, direction = cam.rays(pix.mean(0))
    target = origin + direction * (depth / (direction @ cam.R[2]))
    centre = kp3.mean(0)
    for k, d in enumerate(sk.translation_dof.tolist()):
        if d >= 0:
            q[d] = target[k] - centre[k]
    return q


def root_headings(skeleton: Skeleton, q: Tensor, yaws: int, tilts: tuple[float, ...] = (0.0,)) -> Tensor:
    """Start poses: q (D,) with its root turned to `yaws` headings about the world's up axis (+Y), each
    leaned by every one of `tilts` (radians) about the root's other horizontal axis. A pose fitted from one
    heading keeps that heading's depth order of the torso (which shoulder and hip is nearer the camera),
    so trackers without a 3D start try every heading. -> (yaws * len(tilts), D); q[None] when the root
    cannot rotate."""
    driven = [k for k in range(3) if skeleton.axis_dof[0, k] >= 0]
    if not driven:
        return q[None]
    world = skeleton.rest_rotation[0] @ skeleton.axes[0].T  # (3, 3): columns = the root's axes in the world
    up = max(driven, key=lambda k: abs(world[1, k]))
    side = [k for k in driven if k != up]
    starts = []
    for i in range(yaws):
        for tilt in tilts if side else (0.0,):
            x = q.clone()
            x[int(skeleton.axis_dof[0, up])] += 2 * math.pi * i / yaws * (1.0 if world[1, up] >= 0 else -1.0)
            if side:
                x[int(skeleton.axis_dof[0, side[-1]])] += tilt
            starts.append(x)
    return torch.stack(starts)


def warn_keyframes_outside_limits(skeleton: Skeleton, keyframes: Keyframes, tol: float = 1e-3) -> int:
    """Log a warning for each keyframe whose given dofs lie outside the model's joint limits.

    Keyframes are the user's word and are never moved into the limits; estimators keep them as given.
    Returns the number of keyframes that break the limits."""
    q = keyframes.q.detach()
    lower, upper = skeleton.limits(dtype=q.dtype, device=q.device)
    angular = torch.as_tensor(skeleton.angular_dofs(), device=q.device)
    out = outside_limits(q, lower, upper, angular)
    if keyframes.mask is not None:
        out = torch.where(keyframes.mask, out, torch.zeros_like(out))
    broken = 0
    for f, row in zip(keyframes.frames.tolist(), out):
        bad = torch.nonzero(row > tol)[:, 0].tolist()
        if not bad:
            continue
        broken += 1
        worst = sorted(bad, key=lambda d: -float(row[d]))[:3]
        names = ", ".join(
            f"{skeleton.dof_names[d]} by "
            + (f"{math.degrees(float(row[d])):.1f} deg" if angular[d] else f"{float(row[d]):.3f} m")
            for d in worst
        )
        more = f" and {len(bad) - len(worst)} more" if len(bad) > len(worst) else ""
        log.warning(
            "the 3D keyframe at frame %d lies outside the joint limits (%s%s); it is kept as given", f, names, more
        )
    return broken


class MotionFit(NamedTuple):
    """What a motion-model tracker (`method: pca`) found besides the poses, for T frames, m PCA weights, P key
    postures: weights (T, m) the PCA weights of each frame (of its last window); time (T,) each frame's
    normalised time in [0, 1]; key_frames (P,) int64 the key postures' frames found in the 2D; key_names (P,);
    modelled (T,) bool, True where the motion model gives the pose (the swing), False where the frames after the
    swing were handed to another estimator (their weights and time are the swing's last)."""

    weights: Tensor
    time: Tensor
    key_frames: Tensor
    key_names: tuple[str, ...]
    modelled: Tensor


class Estimate(NamedTuple):
    """An estimator's result for T frames (J joints, D dofs, N hypotheses).

    q: (T, D); joints: (T, J, 3) world metres; cost: (T,) final objective per frame; terms:
    per-term breakdown {name: (T,)}; hypotheses: (T, N, J, 3) or None, with weights (T, N) and
    costs (T, N); joint_std: (T, J) or None, sqrt of the trace of each joint's 3D position covariance.
    """

    q: Tensor
    joints: Tensor
    cost: Tensor
    terms: dict[str, Tensor]
    hypotheses: Tensor | None = None
    hypothesis_weights: Tensor | None = None
    hypothesis_costs: Tensor | None = None
    joint_std: Tensor | None = None  # (T, J) metres: per-joint 3D standard deviation, where a method has it
    solver_cost: Tensor | None = None  # (I+1,) objective after each solver iteration (start first), batch methods
    # (T, N, J, 3) metres: each hypothesis's principal covariance direction as joint displacements (trackers)
    hypothesis_directions: Tensor | None = None
    jumps: dict[str, Tensor] | None = None  # {chain: (T,) kinematic-jump leaves kept per frame} (kjs)
    motion: MotionFit | None = None  # a motion-model tracker's weights, timing and key postures (pca)


def evaluate_pose(
    skeleton: Skeleton, camera: Camera, keypoints: KeypointSet, q: Tensor, joint_pixels: bool = False
) -> PoseEval:
    """FK + projection. q: (..., D) -> PoseEval with joints (..., J, 3), pixels (..., K, 2)."""
    return pose_eval_from_joints(camera, keypoints, q, skeleton.forward_kinematics(q), joint_pixels)


def pose_eval_from_joints(
    camera: Camera, keypoints: KeypointSet, q: Tensor, joints: Tensor, joint_pixels: bool = False
) -> PoseEval:
    """`evaluate_pose` without the FK: joints (..., J, 3) given for the pose q (..., D)."""
    proj = camera.project(joints.index_select(-2, keypoints.index(q.device)))
    jp = camera.project(joints).pixels if joint_pixels else None
    return PoseEval(q=q, joints=joints, pixels=proj.pixels, depth=proj.depth, joint_pixels=jp)
