"""Benchmark of the batch MAP solver (`method: batch`): speed against scipy, and peak memory.

    python scripts/bench_batch.py              # 300 frames, full CMU skeleton (62 dofs), 30 iterations, + scipy
    python scripts/bench_batch.py --no-scipy   # ptrack's time alone (no scipy: its run takes minutes; no warm start)
    python scripts/bench_batch.py --memory     # peak memory of 3 iterations + joint_std at 1,000 and 10,000 frames
    python scripts/bench_batch.py --warm       # only the warm start (init_from) against a cold re-solve

Problem: the bundled CMU soccer kick (subject 10) at 120 fps, frames 0-299, default virtual camera,
2 px noise, 10% missing, full skeleton (`model.freeze=[]`: 62 dofs), ground-truth keyframes every
second, the batch objective with least-squares reprojection and smoothing (`costs.loss=l2`,
`batch.smooth_loss=l2`, so that it is the plain 0.5 |r|^2 scipy minimises; ptrack's time is also
printed with the config's robust losses, which change the weights, not the work), joint limits as
bounds and barrier, acceleration smoothing. Both solvers start from the keyframes interpolated.
Ours: `banded_levenberg_marquardt`, 30 iterations (no early stop). scipy:
`least_squares(method='trf', jac_sparsity=...)` (finite differences grouped by the sparsity, lsmr on
the sparse Jacobian), run until its cost is within 1% of ours or `--scipy-nfev` evaluations; the
script prints both times, both costs and the ratio, and the wall time of one iteration's parts
(linearisation, factorisation, solve). Threads (`--threads`, default 1): the solve inside
`ptrack.threads.one_thread`, so every op runs on one intra-op thread, as `method: batch` runs it;
with `--threads 2` (a budget of 2, what `method: batch` gets from torch's default on a 2-core
machine) the linearisation's two halves of the sequence also run on two Python threads. One thread
is the default because it was as fast or faster on the shared 2-core machine these numbers come
from: the two-thread linearisation is ~25% of an iteration and only gains while a second core is
free (docs/notes/batch-history.md, speed).
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import time
from math import comb
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from _bench import machine_line  # noqa: E402

from ptrack.estimators.batch import (  # noqa: E402
    interpolate_keyframes,
    linearization,
    trajectory_objective,
    warp_to_keyframes,
)
from ptrack.optim.solvers import banded_levenberg_marquardt  # noqa: E402
from ptrack.pipeline.config import load_config  # noqa: E402
from ptrack.pipeline.run import prepare  # noqa: E402
from ptrack.problem import evaluate_pose  # noqa: E402
from ptrack.threads import one_thread  # noqa: E402

CONFIG = REPO / "configs" / "batch.yaml"


def problem(frames: int, every_s: float = 1.0, plain: bool = True):
    """plain: least-squares reprojection, limits, smoothing and keyframes (the objective `residuals` gives scipy:
    no pose prior); else the config's losses and terms."""
    cfg = load_config(
        CONFIG,
        [
            "data.stride=1",
            f"data.stop={frames}",
            "model.freeze=[]",
            *(["costs.loss=l2", "batch.smooth_loss=l2", "batch.pose_prior_weight=0"] if plain else []),
            f"keyframes.every_s={every_s}",
            "progress=false",
        ],
    )
    prep = prepare(cfg)
    obj = trajectory_objective(prep.problem, cfg, torch.float64, torch.device("cpu"))
    q0 = interpolate_keyframes(prep.problem, obj.lower, obj.upper)
    return cfg, prep, obj, q0


def residuals(obj, q: torch.Tensor) -> torch.Tensor:
    """The stacked residual vector whose 0.5 |r|^2 is the batch energy (l2 loss). q (T, D) -> (M,)."""
    p = obj.problem
    ev = evaluate_pose(p.skeleton, p.observations.camera.to(dtype=q.dtype), p.keypoints, q)
    parts = [
        obj.reprojection.residual(ev),
        ((torch.clamp(q - obj.lower, max=0.0) + torch.clamp(q - obj.upper, min=0.0)) * obj.limits_scale).flatten(),
    ]
    for n, a in obj.smooth:
        parts.append((a * torch.diff(q, n=n, dim=0)).flatten())
    d = q[obj.kf_frames] - obj.kf_target
    d = torch.where(obj.angular, torch.remainder(d + np.pi, 2 * np.pi) - np.pi, d)
    parts.append((d * obj.kf_weight).flatten())
    return torch.cat(parts)


def jacobian(obj, q: torch.Tensor):
    """The analytic Jacobian of `residuals` as a scipy CSR matrix (M, T*D): per-frame reprojection
    blocks from the geometric joint Jacobian (one FK pass), limits and keyframes on the diagonal,
    the smoothing differences as constant bands. q (T, D)."""
    from scipy.sparse import coo_matrix

    from ptrack.optim.jacobians import pose_eval_and_jacobian

    p = obj.problem
    t_len, d = q.shape
    ev, jac = pose_eval_and_jacobian(p.skeleton, p.observations.camera.to(dtype=q.dtype), p.keypoints, q)
    jr = obj.reprojection.jacobian(ev, jac).reshape(t_len, -1, d)  # (T, 2K, D)
    m = jr.shape[1]
    frame = np.arange(t_len)[:, None, None]
    rows = [np.broadcast_to(frame * m + np.arange(m)[None, :, None], jr.shape).ravel()]
    cols = [np.broadcast_to(frame * d + np.arange(d)[None, None, :], jr.shape).ravel()]
    vals = [jr.numpy().ravel()]
    off = t_len * m
    outside = ((q < obj.lower) | (q > obj.upper)).flatten().numpy()
    idx = np.arange(t_len * d)
    rows.append(off + idx[outside])
    cols.append(idx[outside])
    vals.append(np.full(int(outside.sum()), obj.limits_scale))
    off += t_len * d
    for n, a in obj.smooth:
        coef = [(-1) ** (n - j) * comb(n, j) for j in range(n + 1)]
        r_len = t_len - n
        res = np.arange(r_len * d).reshape(r_len, d)
        for j, c in enumerate(coef):
            rows.append(off + res.ravel())
            cols.append(((np.arange(r_len)[:, None] + j) * d + np.arange(d)[None, :]).ravel())
            vals.append(np.broadcast_to(c * a.numpy(), (r_len, d)).ravel())
        off += r_len * d
    f_len = obj.kf_frames.numel()
    kf = np.arange(f_len * d)
    rows.append(off + kf)
    cols.append((obj.kf_frames.numpy()[:, None] * d + np.arange(d)[None, :]).ravel())
    vals.append(obj.kf_weight.numpy().ravel())
    off += f_len * d
    return coo_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(off, t_len * d)
    ).tocsr()


def sparsity(obj, t_len: int, d: int):
    """Which entries of the Jacobian may be non-zero (scipy's `jac_sparsity`)."""
    q = torch.zeros(t_len, d, dtype=torch.float64)
    s = jacobian(obj, q)
    s.data[:] = 1.0
    return s


def parts(lin, q: torch.Tensor, obj, damping: float, repeats: int = 10) -> str:
    """Median wall time of one iteration's parts at q: the linearisation, the factorisation of the
    damped normal equations and their solve (as `banded_levenberg_marquardt` calls them)."""
    from ptrack.optim.banded import factorize, solve
    from ptrack.optim.solvers import _band_damped, _free

    out = lin(q)
    lo, hi = obj.lower.expand_as(q), obj.upper.expand_as(q)
    free = _free(q, out.gradient, lo, hi)
    lam = damping * out.hessian.diagonal.diagonal(dim1=-2, dim2=-1).amax((-2, -1))
    damped = _band_damped(out.hessian, free, lam)
    factor, _ = factorize(damped)
    rhs = -torch.where(free, out.gradient, 0.0)
    res = []
    for name, fn in (
        ("linearisation", lambda: lin(q)),
        ("factorisation", lambda: factorize(damped)),
        ("solve", lambda: solve(factor, rhs)),
    ):
        walls = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fn()
            walls.append(time.perf_counter() - t0)
        res.append(f"{name} {1000 * float(np.median(walls)):.1f} ms")
    return ", ".join(res)


def timed_solves(obj, q0: torch.Tensor, damping: float, repeats: int):
    """`repeats` solves of 30 iterations (no early stop) from q0 (T, D) on one intra-op thread, as
    `method: batch` runs (module docstring), after one warm-up linearisation -> q (1, T, D) and info of
    the last, wall times, CPU times and load averages of each."""
    lin = linearization(obj)
    times, cpu, loads = [], [], []
    with one_thread():
        lin(q0[None])  # warm-up (kernel caches)
        for _ in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            q, info = banded_levenberg_marquardt(
                lin, q0[None], obj.lower, obj.upper, max_iter=30, tol=1e-300, gtol=0.0, damping=damping
            )
            times.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
            loads.append(os.getloadavg()[0])
    return q, info, times, cpu, loads


def speed(args) -> None:
    torch.set_num_threads(args.threads)
    cfg, prep, obj, q0 = problem(300)
    t_len, d = q0.shape
    print(
        f"problem: {t_len} frames, {d} dofs, {obj.kf_frames.numel()} keyframes, "
        f"{int((prep.problem.observations.confidence > 0).sum())} observed keypoints"
    )
    q, info, times, cpu, loads = timed_solves(obj, q0, cfg.batch.damping, args.repeats)
    with one_thread():
        split = parts(linearization(obj), q, obj, cfg.batch.damping)
    ours, cost, iters = float(np.median(times)), float(info.cost[0]), int(info.iterations[0])
    check = 0.5 * float(residuals(obj, q[0]).square().sum())
    how = "one thread" if args.threads == 1 else "the linearisation's two halves on two threads"
    print(
        f"ptrack banded LM: {iters} iterations in {ours:.2f} s (median of {args.repeats}: "
        f"{', '.join(f'{t:.2f}' for t in times)}; process CPU time {float(np.median(cpu)):.2f} s; {how}; "
        f"load {', '.join(f'{x:.1f}' for x in loads)}), cost {float(info.history[0, 0]):.2f} -> {cost:.4f} "
        f"(same objective as scipy's: {check:.4f})"
    )
    if iters < 30:  # converged to round-off: its steps no longer move q (info.converged) or the damping ran away
        print(
            f"LM stopped after {iters} iterations (converged {bool(info.converged[0])}); "
            f"30 iterations at this rate: {30 * ours / iters:.2f} s"
        )
    print(f"one iteration's parts (median wall time at the solution): {split}")
    _, _, robj, rq0 = problem(300, plain=False)
    _, rinfo, walls, _, _ = timed_solves(robj, rq0, cfg.batch.damping, args.repeats)
    print(
        f"with the config's robust losses (costs.loss {robj.reprojection.loss}, batch.smooth_loss "
        f"{robj.smooth_loss} {robj.smooth_scale:g}): {int(rinfo.iterations[0])} iterations in "
        f"{float(np.median(walls)):.2f} s (median of {args.repeats}: {', '.join(f'{t:.2f}' for t in walls)})"
    )
    if args.no_scipy:
        return

    from scipy.optimize import least_squares

    lo, hi = obj.lower.expand(t_len, d).flatten().numpy(), obj.upper.expand(t_len, d).flatten().numpy()
    x0 = np.clip(q0.flatten().numpy(), lo + 1e-9, hi - 1e-9)
    fun = lambda x: residuals(obj, torch.from_numpy(x).reshape(t_len, d)).numpy()  # noqa: E731
    target = 1.01 * cost
    t0 = time.perf_counter()
    reached = {"t": None}

    class Reached(Exception):
        pass

    def tracked(x):
        r = fun(x)
        if reached["t"] is None and 0.5 * float(r @ r) <= target:
            reached["t"], reached["cost"] = time.perf_counter() - t0, 0.5 * float(r @ r)
            raise Reached  # stop scipy there: the time to the cost is what is compared
        return r

    if args.scipy_jac == "analytic":
        jac_arg = dict(jac=lambda x: jacobian(obj, torch.from_numpy(x).reshape(t_len, d)))
        how = "trf + analytic sparse Jacobian (jac=, CSR)"
    else:
        jac_arg = dict(jac_sparsity=sparsity(obj, t_len, d))
        how = "trf + jac_sparsity (grouped finite differences)"
    try:
        res = least_squares(
            tracked,
            x0,
            method="trf",
            bounds=(lo, hi),
            max_nfev=args.scipy_nfev,
            xtol=1e-12,
            ftol=1e-12,
            gtol=1e-12,
            x_scale=1.0,
            **jac_arg,
        )
        head = f"scipy least_squares {how}: stopped after {res.nfev} evaluations, {time.perf_counter() - t0:.1f} s"
        print(f"{head}, cost {res.cost:.4f}; never within 1% of ptrack's cost {cost:.4f}")
        scipy_time, bound = time.perf_counter() - t0, " (at least: scipy had not reached the cost)"
    except Reached:
        print(
            f"scipy least_squares {how}: cost {reached['cost']:.4f} (within 1% of ptrack's {cost:.4f}) "
            f"after {reached['t']:.1f} s"
        )
        scipy_time, bound = reached["t"], ""
    print(
        f"times: ptrack {ours:.2f} s, scipy {scipy_time:.1f} s; costs: ptrack {cost:.4f}, "
        f"scipy {reached.get('cost', float('nan')):.4f}"
    )
    print(f"ptrack vs scipy least_squares: {scipy_time / ours:.1f}x faster to the same cost within 1%{bound}")


def warm_start(args) -> None:
    """The paper's interactive loop: solve, look at the result, add a keyframe, re-solve. After a
    converged solve with keyframes every second, the ground-truth pose of the worst frame (largest
    joint error, what one would spot in rerun) is added as a keyframe; the new objective is solved
    cold (from its keyframes interpolated) and warm (from the first solution, what `init_from: RUN_DIR`
    reads from result.npz and warps onto the keyframes, `warp_to_keyframes`; also unwarped), all to the
    config's tolerance (at most 100 iterations)."""
    torch.set_num_threads(args.threads)
    with one_thread():  # as `method: batch` runs (see speed())
        _warm_start(args)


def _warm_start(args) -> None:
    import dataclasses

    cfg, prep, obj, q0 = problem(300, 1.0)
    damping = cfg.batch.damping if args.damping is None else args.damping
    cfg = dataclasses.replace(cfg, batch=dataclasses.replace(cfg.batch, damping=damping))
    solve = dict(max_iter=100, tol=cfg.batch.tol, gtol=cfg.batch.tol * 1e-2, damping=cfg.batch.damping)
    first, info = banded_levenberg_marquardt(linearization(obj), q0[None], obj.lower, obj.upper, **solve)
    p = prep.problem
    err = (p.skeleton.forward_kinematics(first[0]) - prep.gt_joints.to(first)).norm(dim=-1).mean(-1)
    worst = int(err.argmax())
    kf = p.keyframes
    kf2 = dataclasses.replace(
        kf,
        frames=torch.cat([kf.frames, torch.tensor([worst])]),
        q=torch.cat([kf.q, prep.gt_q[worst : worst + 1].to(kf.q)]),
        mask=None if kf.mask is None else torch.cat([kf.mask, kf.mask[:1]]),
        sigma=None if kf.sigma is None else torch.cat([kf.sigma, kf.sigma[:1]]),
    )
    obj2 = trajectory_objective(dataclasses.replace(p, keyframes=kf2), cfg, torch.float64, torch.device("cpu"))
    q2 = interpolate_keyframes(dataclasses.replace(p, keyframes=kf2), obj2.lower, obj2.upper)
    out = {}
    warped = warp_to_keyframes(first[0], obj2)[None]  # what `init_from` starts from
    for name, start in (("cold", q2[None]), ("warm, unwarped", first), ("warm", warped)):
        lin = linearization(obj2)
        stamps = []
        t0, c0 = time.perf_counter(), time.process_time()
        _q, info2 = banded_levenberg_marquardt(
            lin,
            start,
            obj2.lower,
            obj2.upper,
            callback=lambda it, q, c: stamps.append(time.process_time() - c0),
            **solve,
        )
        out[name] = (
            time.perf_counter() - t0,
            time.process_time() - c0,
            int(info2.iterations[0]),
            info2.history[:, 0],
            stamps,
        )
    final = min(float(o[3][-1]) for o in out.values())
    print(
        f"first solve (keyframes every 1 s): {int(info.iterations[0])} iterations, cost {float(info.cost[0]):.2f}; "
        f"worst frame {worst} ({1000 * float(err[worst]):.1f} mm mean joint error) gets a keyframe "
        f"(damping {cfg.batch.damping:g}, load {os.getloadavg()[0]:.1f})"
    )
    reach = {}
    for name, (sec, cpu, it, hist, stamps) in out.items():
        reach[name] = {}
        for rel in (1e-3, 1e-5):
            near = int(torch.nonzero(hist <= (1 + rel) * final)[0, 0])  # history[0] is the start
            reach[name][rel] = (near, 0.0 if near == 0 else stamps[near - 1])
        print(
            f"re-solve with the added keyframe, {name} start: cost {float(hist[0]):.2f} -> {float(hist[-1]):.4f}; "
            + "; ".join(
                f"within {100 * rel:g}% of the final cost after {n} iterations ({c:.2f} s CPU)"
                for rel, (n, c) in reach[name].items()
            )
            + f"; converged (tol {cfg.batch.tol:g}) after {it} iterations ({cpu:.2f} s CPU, {sec:.2f} s wall)"
        )
    for rel in (1e-3, 1e-5):
        (nc, cc), (nw, cw) = reach["cold"][rel], reach["warm"][rel]
        print(
            f"warm start (init_from) vs cold re-solve, to within {100 * rel:g}% of the final cost: "
            f"{cc / max(cw, 1e-9):.1f}x less CPU time ({nc} -> {nw} iterations)"
        )
    print(
        f"warm start (init_from) vs cold re-solve, to the tolerance: {out['cold'][1] / out['warm'][1]:.1f}x less CPU "
        f"time ({out['cold'][2]} -> {out['warm'][2]} iterations)"
    )


def ping_pong(motion, frames: int):
    """The clip played forwards, backwards, forwards... to `frames` poses (continuous at the turns)."""
    from ptrack.body.skeleton import Motion

    q = motion.q
    cycle = torch.cat([q, q.flip(0)[1:-1]]) if q.shape[0] > 2 else q
    reps = -(-frames // cycle.shape[0])
    return Motion(
        q=cycle.repeat(reps, 1)[:frames],
        frames=np.arange(frames),
        fps=motion.fps,
        path=motion.path,
        frame_rate=motion.frame_rate,
    )


def memory_one(frames: int) -> None:
    """Child process: 3 iterations + joint_std on `frames` frames at 120 fps (the bundled clip's 590
    frames played back and forth), peak resident memory of the process (ru_maxrss)."""
    import ptrack.pipeline.run as run
    from ptrack.estimators.batch import joint_std

    torch.set_num_threads(1)
    load = run.load_amc
    run.load_amc = lambda path, sk: ping_pong(load(path, sk), frames)
    _cfg, _prep, obj, q0 = problem(frames)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    t0 = time.perf_counter()
    q, info = banded_levenberg_marquardt(linearization(obj), q0[None], obj.lower, obj.upper, max_iter=3)
    std = joint_std(obj, q, info.hessian)
    sec = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024**2
    print(
        f"{q.shape[1]} frames x {q.shape[2]} dofs: 3 iterations + joint_std in {sec:.1f} s, peak resident "
        f"memory {peak:.2f} GB ({before:.2f} GB before the solve: data, observations, start), joint_std finite: "
        f"{bool(torch.isfinite(std).all())}, cost {float(info.history[0, 0]):.1f} -> {float(info.cost[0]):.1f}"
    )


def memory(args) -> None:
    for frames in (1000, 10000):
        subprocess.run([sys.executable, __file__, "--memory-child", str(frames)], check=True)


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--memory", action="store_true")
    ap.add_argument("--warm", action="store_true", help="only the warm-start comparison")
    ap.add_argument("--memory-child", type=int, default=None)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--scipy-nfev", type=int, default=200)
    ap.add_argument("--scipy-jac", choices=["analytic", "sparsity"], default="analytic")
    ap.add_argument("--damping", type=float, default=None, help="initial LM damping (default: the config's)")
    ap.add_argument("--no-scipy", action="store_true", help="only ptrack's speed (no scipy, no warm start)")
    ap.add_argument(
        "--threads", type=int, default=1, help="torch's thread budget (default 1; 2: two-thread linearisation)"
    )
    a = ap.parse_args()
    if not a.memory_child:
        print(machine_line())
    if a.memory_child:
        memory_one(a.memory_child)
    elif a.memory:
        memory(a)
    elif a.warm:
        warm_start(a)
    else:
        speed(a)
        if not a.no_scipy:  # --no-scipy: a quick look at ptrack's speed alone
            warm_start(a)
