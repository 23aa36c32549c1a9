"""Benchmark of the batch MAP solver (`method: batch`): speed against scipy, and peak memory.

    python scripts/bench_batch.py              # 300 frames, full CMU skeleton (62 dofs), 30 iterations, + scipy
    python scripts/bench_batch.py --memory     # peak memory of 3 iterations + joint_std at 1,000 and 10,000 frames

Problem: the bundled CMU soccer kick (subject 10) at 120 fps, frames 0-299, default virtual camera,
2 px noise, 10% missing, full skeleton (`model.freeze=[]`: 62 dofs), ground-truth keyframes every
second, the batch objective with least-squares reprojection (`costs.loss=l2`, so that it is the plain
0.5 |r|^2 scipy minimises), joint limits as bounds and barrier, acceleration smoothing. Both solvers
start from the keyframes interpolated. Ours: `banded_levenberg_marquardt`, 30 iterations (no early
stop). scipy: `least_squares(method='trf', jac_sparsity=...)` (finite differences grouped by the
sparsity, lsmr on the sparse Jacobian), run until its cost is within 1% of ours or `--scipy-nfev`
evaluations; the script prints both times, both costs and the ratio. One torch thread (the machine's
2 cores are shared; multithreaded small products were slower here).
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from ptrack.config import load_config  # noqa: E402
from ptrack.estimators.batch import evaluate, interpolate_keyframes, linearization, trajectory_objective  # noqa: E402
from ptrack.problem import evaluate_pose  # noqa: E402
from ptrack.run import prepare  # noqa: E402
from ptrack.solvers import banded_levenberg_marquardt  # noqa: E402

CONFIG = REPO / "configs" / "batch.yaml"


def problem(frames: int):
    cfg = load_config(CONFIG, ["data.stride=1", f"data.stop={frames}", "model.freeze=[]", "costs.loss=l2",
                               "keyframes.every_s=1", "progress=false"])
    prep = prepare(cfg)
    obj = trajectory_objective(prep.problem, cfg, torch.float64, torch.device("cpu"))
    q0 = interpolate_keyframes(prep.problem, obj.lower, obj.upper)
    return cfg, prep, obj, q0


def residuals(obj, q: torch.Tensor) -> torch.Tensor:
    """The stacked residual vector whose 0.5 |r|^2 is the batch energy (l2 loss). q (T, D) -> (M,)."""
    p = obj.problem
    ev = evaluate_pose(p.skeleton, p.observations.camera.to(dtype=q.dtype), p.keypoints, q)
    parts = [obj.reprojection.residual(ev),
             ((torch.clamp(q - obj.lower, max=0.0) + torch.clamp(q - obj.upper, min=0.0)) * obj.limits_scale).flatten()]
    for n, a in obj.smooth:
        parts.append((a * torch.diff(q, n=n, dim=0)).flatten())
    d = q[obj.kf_frames] - obj.kf_target
    d = torch.where(obj.angular, torch.remainder(d + np.pi, 2 * np.pi) - np.pi, d)
    parts.append((d * obj.kf_weight).flatten())
    return torch.cat(parts)


def sparsity(obj, t_len: int, d: int):
    from scipy.sparse import lil_matrix

    k = obj.reprojection.observed.shape[-2]
    rows = []  # for each residual: the (frame, dof) columns it reads; dof None = every dof of the frame
    rows += [(t, None) for t in range(t_len) for _ in range(2 * k)]
    rows += [(t, dd) for t in range(t_len) for dd in range(d)]
    for n, _ in obj.smooth:
        rows += [(tuple(range(i, i + n + 1)), dd) for i in range(t_len - n) for dd in range(d)]
    rows += [(int(f), dd) for f in obj.kf_frames.tolist() for dd in range(d)]
    s = lil_matrix((len(rows), t_len * d), dtype=np.int8)
    for r, (frames, dof) in enumerate(rows):
        for f in (frames if isinstance(frames, tuple) else (frames,)):
            if dof is None:
                s[r, f * d:(f + 1) * d] = 1
            else:
                s[r, f * d + dof] = 1
    return s.tocsr()


def speed(args) -> None:
    torch.set_num_threads(1)
    cfg, prep, obj, q0 = problem(300)
    t_len, d = q0.shape
    print(f"problem: {t_len} frames, {d} dofs, {obj.kf_frames.numel()} keyframes, "
          f"{int((prep.problem.observations.confidence > 0).sum())} observed keypoints")
    lin = linearization(obj)
    lin(q0[None])  # warm-up (kernel caches)
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        q, info = banded_levenberg_marquardt(lin, q0[None], obj.lower, obj.upper, max_iter=30, tol=1e-300,
                                             gtol=0.0, damping=cfg.batch.damping)
        times.append(time.perf_counter() - t0)
    ours, cost = min(times), float(info.cost[0])
    check = 0.5 * float(residuals(obj, q[0]).square().sum())
    print(f"ptrack banded LM: 30 iterations in {ours:.2f} s (best of {args.repeats}: "
          f"{', '.join(f'{t:.2f}' for t in times)}), cost {float(info.history[0, 0]):.2f} -> {cost:.4f} "
          f"(same objective as scipy's: {check:.4f})")

    from scipy.optimize import least_squares

    lo, hi = obj.lower.expand(t_len, d).flatten().numpy(), obj.upper.expand(t_len, d).flatten().numpy()
    x0 = np.clip(q0.flatten().numpy(), lo + 1e-9, hi - 1e-9)
    fun = lambda x: residuals(obj, torch.from_numpy(x).reshape(t_len, d)).numpy()  # noqa: E731
    target = 1.01 * cost
    t0 = time.perf_counter()
    reached = {"t": None}

    def tracked(x):
        r = fun(x)
        if reached["t"] is None and 0.5 * float(r @ r) <= target:
            reached["t"] = time.perf_counter() - t0
        return r

    res = least_squares(tracked, x0, jac_sparsity=sparsity(obj, t_len, d), method="trf", bounds=(lo, hi),
                        max_nfev=args.scipy_nfev, xtol=1e-12, ftol=1e-12, gtol=1e-12, x_scale=1.0)
    total = time.perf_counter() - t0
    print(f"scipy least_squares trf + jac_sparsity: {res.nfev} evaluations in {total:.1f} s, cost {res.cost:.4f}; "
          f"within 1% of ptrack's cost after {reached['t']:.1f} s" if reached["t"] is not None else
          f"scipy least_squares trf + jac_sparsity: {res.nfev} evaluations in {total:.1f} s, cost {res.cost:.4f}; "
          f"never within 1% of ptrack's cost {cost:.4f}")
    scipy_time = reached["t"] if reached["t"] is not None else total
    bound = "" if reached["t"] is not None else " (at least: scipy had not reached the cost)"
    print(f"ptrack vs scipy least_squares: {scipy_time / ours:.1f}x faster to the same cost within 1%{bound}")


def memory_one(frames: int) -> None:
    """Child process: 3 iterations + joint_std on `frames` frames (the clip played back and forth)."""
    from ptrack.estimators.batch import joint_std

    torch.set_num_threads(1)
    cfg, prep, obj, q0 = problem(frames)
    t0 = time.perf_counter()
    q, info = banded_levenberg_marquardt(linearization(obj), q0[None], obj.lower, obj.upper, max_iter=3)
    std = joint_std(obj, q, info.hessian)
    sec = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2
    print(f"{q.shape[1]} frames x {q.shape[2]} dofs: 3 iterations + joint_std in {sec:.1f} s, "
          f"peak resident memory {peak:.2f} GB, joint_std finite: {bool(torch.isfinite(std).all())}")


def memory(args) -> None:
    for frames in (1000, 10000):
        subprocess.run([sys.executable, __file__, "--memory-child", str(frames)], check=True)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--memory", action="store_true")
    ap.add_argument("--memory-child", type=int, default=None)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scipy-nfev", type=int, default=40)
    a = ap.parse_args()
    if a.memory_child:
        memory_one(a.memory_child)
    elif a.memory:
        memory(a)
    else:
        speed(a)
