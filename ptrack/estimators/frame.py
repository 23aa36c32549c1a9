"""`method: frame` — independent per-frame fits, each started from the previous frame's solution.

Per frame t, L-BFGS minimises a robust reprojection term on the observed keypoints, the joint-limit
barrier, and a temporal prior: a velocity term on (q_{t-1}, q_t), plus, with `costs.accel_sigma` set,
an acceleration term on (q_{t-2}, q_{t-1}, q_t) that favours constant velocity (the fit then starts
from the constant-velocity prediction instead of q_{t-1}). It is the
simplest estimator that exercises the whole pipeline; the trackers and the batch solver of later
issues replace it. The first frame starts from a user 3D keyframe (config `frame.init: keyframe`)
or from the rest pose placed in front of the camera (`rest`). With a known floor (`Problem.floor`) the floor
contact term (`ptrack.costs.floor`) joins the sum.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Protocol, cast

import torch
from torch import Tensor

from ptrack.costs import JointLimits, PoseEval, Reprojection, Smoothness
from ptrack.costs.config import CostsConfig
from ptrack.errors import InputError
from ptrack.problem import Estimate, Problem, evaluate_pose, first_keyframe, rest_pose_in_view, root_headings
from ptrack.settings import setting
from ptrack.threads import one_thread


@dataclass(frozen=True)
class FrameMethodConfig:
    """`method: frame`, the per-frame baseline: L-BFGS on each frame from the previous one."""

    init: str = setting("keyframe", "keyframe: first frame's 3D pose given (as a user keyframe); rest: rest pose")
    iterations: int = setting(40, "L-BFGS iterations per frame")
    first_iterations: int = setting(200, "L-BFGS iterations on the first frame")
    init_yaws: int = setting(1, "init rest: headings of the rest pose fitted on the first frame (the cheapest kept)")


class FrameRunConfig(Protocol):
    """What the per-frame fits read of the run's config: `ptrack.pipeline.config.RunConfig` is one (estimators sit
    below the pipeline and do not import it; its module checks that it fits)."""

    @property
    def frame(self) -> FrameMethodConfig: ...

    @property
    def costs(self) -> CostsConfig: ...


def validate_frame(f: FrameMethodConfig) -> None:
    """Value checks of the `frame:` section (InputError naming the key)."""
    if f.init not in ("keyframe", "rest"):
        raise InputError(f"config key 'frame.init' must be 'keyframe' or 'rest', got {f.init!r}")
    if f.init_yaws < 1:
        raise InputError(f"config key 'frame.init_yaws' must be >= 1, got {f.init_yaws}")
    if f.iterations < 1 or f.first_iterations < 1:
        raise InputError("config keys 'frame.iterations' and 'frame.first_iterations' must be >= 1")


def _total(e: dict[str, Tensor]) -> Tensor:
    """The sum of the energy terms (never empty, so a tensor)."""
    return cast(Tensor, sum(e.values()))


def estimate_frames(
    problem: Problem,
    cfg: FrameRunConfig,
    generator: torch.Generator,
    progress: Callable[[Iterable], Iterable] = lambda x: x,
) -> Estimate:
    """Per-frame L-BFGS fits (see module docstring). Deterministic: uses no randomness. Runs on one intra-op
    thread (`ptrack.threads.one_thread`), as every method does: each frame's L-BFGS is a loop of small ops (one
    pose). `scripts/bench_pca.py --threads` measured no gain here on a loaded 2-core machine (30 frames: 3.35 s
    on one thread, 3.05 s on torch's default 2, runs overlapping), where `method: pca` gained 8-11x."""
    with one_thread():
        return _fit_frames(problem, cfg, progress)


def frames_after(
    problem: Problem,
    cfg: FrameRunConfig,
    q_before: Tensor,
    progress: Callable[[Iterable], Iterable] = lambda x: x,
) -> Estimate:
    """Per-frame fits of every frame of `problem` continuing a pose q_before (D,) of the frame before its first:
    the first frame is fitted from q_before with the velocity prior on (q_before, q), as a 3D keyframe is with
    `frame.init: keyframe`, whatever `frame.init` says. Another estimator hands the rest of a sequence on with it
    (`method: pca` after the swing; composed in `ptrack.estimators`). Deterministic; one intra-op thread."""
    with one_thread():
        return _fit_frames(problem, cfg, progress, q_before)


def _fit_frames(
    problem: Problem,
    cfg: FrameRunConfig,
    progress: Callable[[Iterable], Iterable],
    q_before: Tensor | None = None,
) -> Estimate:
    fc, cc = cfg.frame, cfg.costs
    obs = problem.observations
    sk = problem.skeleton
    dtype, device = obs.keypoints.dtype, obs.keypoints.device
    camera = obs.camera
    lower, upper = sk.limits(dtype=dtype, device=device)
    limits = JointLimits(lower, upper, sigma=cc.limits_sigma)
    smooth_pair = Smoothness(dt=1.0, sigma_velocity=cc.smooth_sigma)
    smooth = (
        smooth_pair
        if cc.accel_sigma is None
        else Smoothness(dt=1.0, sigma_velocity=cc.smooth_sigma, sigma_acceleration=cc.accel_sigma)
    )

    floor = problem.floor.term(cc.floor_sigma_m) if problem.floor is not None and cc.floor_weight > 0 else None

    from_pose = q_before is not None or fc.init == "keyframe"  # frame 0 continues a given pose
    if q_before is not None:
        q0 = q_before.detach().to(dtype=dtype, device=device)
        starts = q0[None]
    elif fc.init == "keyframe":
        q0 = first_keyframe(problem, "frame.init", lower, upper)  # kept as given (Problem warns off limits)
        starts = q0[None]
    else:
        q0 = torch.clamp(rest_pose_in_view(problem, dtype), lower, upper)
        starts = torch.clamp(root_headings(sk, q0, fc.init_yaws), lower, upper)  # frame 0: every heading tried
    q_prev = q0
    history: list[Tensor] = []  # previous solutions, which the temporal prior sees

    qs, costs = [], []
    terms: dict[str, list[Tensor]] = {"reprojection": [], "limits": [], "smooth": []}
    if floor is not None:
        terms["floor"] = []
    for t in progress(range(obs.num_frames)):
        reproj = Reprojection(
            obs.keypoints[t], obs.confidence[t], sigma_px=cc.sigma_px, loss=cc.loss, scale=cc.robust_scale
        )
        # frame 0 with a keyframe: the velocity term on (keyframe, q) acts as the keyframe prior
        past = history[-2:] if t > 0 or not from_pose else [q_prev]
        if cc.accel_sigma is None:
            past = past[-1:]
        anchor = q_prev.detach()
        # start from a constant-velocity prediction (kept inside the limits) when two past frames are known
        start = torch.clamp(2 * past[1] - past[0], lower, upper) if len(past) == 2 else anchor
        prior = smooth if len(past) == 2 else smooth_pair

        def energies(q: Tensor) -> dict[str, Tensor]:
            ev = evaluate_pose(sk, camera, problem.keypoints, q)
            e = {"reprojection": reproj.energy(ev), "limits": cc.limits_weight * limits.energy(ev)}
            if floor is not None:
                e["floor"] = cc.floor_weight * floor.energy(ev)
            if past:
                traj = PoseEval(q=torch.stack([*past, q]), joints=ev.joints, pixels=ev.pixels, depth=ev.depth)
                e["smooth"] = cc.smooth_weight * prior.energy(traj)
            else:
                e["smooth"] = torch.zeros((), dtype=dtype, device=device)
            return e

        def fit(start: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
            q = start.clone().requires_grad_(True)
            opt = torch.optim.LBFGS(
                [q],
                lr=1.0,
                max_iter=fc.first_iterations if t == 0 else fc.iterations,
                line_search_fn="strong_wolfe",
                tolerance_grad=1e-9,
                tolerance_change=1e-12,
                history_size=20,
            )

            def closure() -> Tensor:
                opt.zero_grad()
                total = _total(energies(q))
                total.backward()
                return total

            opt.step(closure)
            with torch.no_grad():
                if not bool(torch.isfinite(q).all()):
                    q.copy_(anchor)
                return q, energies(q)

        # frame 0 without a keyframe: every heading's fit, the cheapest kept (the first on a tie)
        fits = [fit(x) for x in starts] if t == 0 else [fit(start)]
        q, e = min(fits, key=lambda f: float(_total(f[1])))
        q_prev = q.detach()
        history.append(q_prev)
        qs.append(q_prev)
        costs.append(_total(e).detach())
        for k, v in e.items():
            terms[k].append(v.detach())
    q_all = torch.stack(qs)
    with torch.no_grad():
        joints = sk.forward_kinematics(q_all)
    return Estimate(
        q=q_all, joints=joints, cost=torch.stack(costs), terms={k: torch.stack(v) for k, v in terms.items()}
    )
