"""Starts of the batch solve besides the per-frame fits: an earlier run's trajectory (`load_init`, warped onto
the keyframes by `warp_to_keyframes`), or the full angle keyframes interpolated (`interpolate_keyframes`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from ptrack.body.limits import wrap_to_limits, wrapped_difference
from ptrack.errors import InputError
from ptrack.estimators.batch.objective import Trajectory
from ptrack.problem import Problem


def load_init(run_dir: str | Path, problem: Problem, dtype: torch.dtype, device: torch.device) -> Tensor:
    """The trajectory q (T, D) of an earlier run folder, checked to be the same model and frames."""
    path = Path(run_dir) / "result.npz"
    if not path.is_file():
        raise InputError(f"init_from {run_dir}: not a run folder (no result.npz)")
    try:
        with np.load(path) as z:
            q, names, times = z["q"], [str(n) for n in z["dof_names"]], z["times"]
    except (OSError, ValueError, KeyError) as e:
        raise InputError(f"init_from {path}: unreadable run result ({' '.join(str(e).split())})") from None
    sk, obs = problem.skeleton, problem.observations
    if names != list(sk.dof_names):
        raise InputError(
            f"init_from {run_dir}: its dofs ({len(names)}) are not this model's ({sk.num_dofs}); "
            f"the run must use the same skeleton and model.freeze"
        )
    own = obs.times.detach().double().cpu().numpy()
    if q.shape != (obs.num_frames, sk.num_dofs) or times.shape != own.shape or not np.allclose(times, own, atol=1e-6):
        raise InputError(
            f"init_from {run_dir}: its {q.shape[0]} frames are not this run's {obs.num_frames} frames "
            f"(data.start/stop/stride and batch.upsample must match)"
        )
    if not np.isfinite(q).all():
        raise InputError(f"init_from {run_dir}: its trajectory has non-finite values")
    return torch.as_tensor(q, dtype=dtype, device=device)


def has_full_keyframe(problem: Problem) -> bool:
    """Whether some keyframe gives every dof (an angle keyframe with no dof left out)."""
    kf = problem.keyframes
    return kf is not None and kf.frames.numel() > 0 and (kf.mask is None or bool(kf.mask.all(-1).any()))


def has_full_first_keyframe(problem: Problem) -> bool:
    """Whether frame 0 has a keyframe that gives every dof (a start the per-frame fits and kjs can take)."""
    kf = problem.keyframes
    return kf is not None and any(
        bool(kf.mask is None or kf.mask[i].all()) for i in torch.nonzero(kf.frames == 0).flatten().tolist()
    )


def interpolate_keyframes(problem: Problem, lower: Tensor, upper: Tensor) -> Tensor:
    """A start from the full angle keyframes: linear between them, constant beyond. -> (T, D)."""
    kf = problem.keyframes
    t_len = problem.observations.num_frames
    full = (
        None
        if kf is None
        else (torch.ones(kf.frames.shape, dtype=torch.bool) if kf.mask is None else kf.mask.all(-1).cpu())
    )
    if kf is None or full is None or not bool(full.any()):
        raise InputError(
            "batch.init is 'keyframes' but no keyframe gives every dof: start from the per-frame fits "
            "(batch.init=frame) or add a full keyframe"
        )
    frames = kf.frames.cpu()[full]
    order = torch.argsort(frames)
    frames, q = frames[order], kf.q.to(lower)[full.to(lower.device)][order.to(lower.device)]
    angular = torch.as_tensor(problem.skeleton.angular_dofs(), device=lower.device)
    q = wrap_to_limits(q, lower, upper, angular)
    t = torch.arange(t_len, dtype=lower.dtype, device=lower.device)
    f = frames.to(lower)
    idx = torch.searchsorted(f, t, right=True).clamp(1, max(len(f) - 1, 1)) - 1
    nxt = (idx + 1).clamp(max=len(f) - 1)
    span = (f[nxt] - f[idx]).clamp(min=1)
    u = ((t - f[idx]) / span).clamp(0, 1)[:, None]
    out = q[idx] + u * (q[nxt] - q[idx])
    return torch.minimum(torch.maximum(out, lower), upper)


def warp_to_keyframes(q: Tensor, obj: Trajectory) -> Tensor:
    """Motion warping of a start (Witkin & Popovic 1995): per dof, the offsets that bring q (T, D) onto
    each angle keyframe giving that dof, linearly interpolated in time between those keyframes (held
    beyond the first and last), added to q; keyframe dofs already met within 3 of their std count as
    offset 0 (anchors: a solution misses some keyframe dofs by 1-2 std where the data pulls against
    them, and re-meeting those exactly would only move the start off its minimum). -> (T, D). A start
    from an earlier solution (`init_from`) already meets the keyframes it was solved with (offsets ~0
    there), so a keyframe added since is met at once and its change fades out towards its neighbours:
    the solver refines that stretch instead of first dragging it there."""
    if obj.kf_frames.numel() == 0:
        return q
    diff = wrapped_difference(obj.kf_target - q[obj.kf_frames], obj.angular)  # (F, D)
    given = (obj.kf_weight > 0).cpu().numpy()
    frames = obj.kf_frames.cpu().numpy()
    # a dof the start already meets within 3 of its keyframe's std is an anchor: offset 0 there
    delta = torch.where(diff.abs() * obj.kf_weight > 3, diff, 0.0).detach().cpu().double().numpy()
    order = np.argsort(frames, kind="stable")
    frames, delta, given = frames[order], delta[order], given[order]
    t = np.arange(q.shape[0], dtype=np.float64)
    offset = np.zeros(tuple(q.shape))
    for d in range(q.shape[1]):
        sel = given[:, d]
        if sel.any():
            offset[:, d] = np.interp(t, frames[sel].astype(np.float64), delta[sel, d])
    return q + torch.as_tensor(offset, dtype=q.dtype, device=q.device)
