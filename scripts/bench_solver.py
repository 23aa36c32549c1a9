"""Benchmark the batched solvers and the Jacobians they run on.

Problem: the bundled CMU skeleton (subject 10) without fingers, thumbs, hands and toes (J=31 joints,
D=50 dofs), data joint limits, a virtual camera on the clip 10_02 (6 m, 30 deg azimuth, 10 deg
elevation, f=1000 px, 640x480), one real frame (300) observed as its 17 keypoints plus 2 px noise,
and the per-frame objective of the frame estimator with the config defaults: Cauchy reprojection
(sigma 2 px, scale 3 sigma) + joint-limit barrier (sigma 0.02 rad). N=256 starts: the true pose
with every angle perturbed by `--perturb` rad (root translation by half as many metres), Gaussian.

    (a) Jacobian of the joint positions (N, J, 3, D) and of the residuals (N, M, D), float64:
        geometric (one FK) + chain rule vs torch.func.jacfwd (vmap over poses) through the whole
        pipeline vs autograd (torch.autograd.functional.jacobian of the batch sum: one backward per
        output row). Ratio = other / geometric. Max |difference| to autograd is printed.
    (b) Levenberg-Marquardt on all N poses in one batch vs N sequential single-pose solves (N=1
        each) with the same settings: both reach the same per-problem cost (max difference printed;
        the batched solver makes the same steps as the single ones). Ratio = sequential / batched.
        `--sequential K` times the first K single solves and scales by N/K (said in the output).
    (c) LM vs batched L-BFGS on the same polishing step (no convergence test: fixed budgets of 30
        LM / 300 L-BFGS iterations; a callback records the elapsed time and costs after every
        iteration). The cost both reach is, per problem, the worse of the two final costs plus
        `--cost-tol`; "time to equal cost" is when 95% of the problems are at or below it. Ratio =
        the slower time / the faster one.

Methodology: torch.set_num_threads(--threads) (default 1: the benchmark machine is shared; 2 cores),
float64, CPU; each time is the median of `--repeats` runs after one warm-up.

Usage (from the repo root):
    python scripts/bench_solver.py [--n 256] [--threads 1] [--sequential 32] [--quick]
"""

from __future__ import annotations

import argparse
import math
import statistics
import time
from collections.abc import Callable
from pathlib import Path

import torch
from _bench import machine_line

from ptrack.body.keypoints import make_keypoints
from ptrack.body.limits import wrap_to_limits
from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.costs import JointLimits, Objective, Reprojection
from ptrack.observe.camera import camera_for_motion
from ptrack.optim.jacobians import joint_jacobian, objective_linearization
from ptrack.optim.solvers import lbfgs, levenberg_marquardt
from ptrack.problem import evaluate_pose

DATA = Path(__file__).resolve().parents[1] / "ptrack" / "data"
F64 = torch.float64
FRAME = 300


def median_time(fn: Callable[[], object], repeats: int) -> tuple[float, object]:
    """(median seconds over `repeats` runs after a warm-up, last result)."""
    out = fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def build(n: int, perturb: float, seed: int = 0):
    sk = Skeleton.from_asf(DATA / "10.asf").freeze(["*fingers", "*thumb", "*hand", "*toes"]).with_limits("data")
    lo, hi = sk.limits(dtype=F64)
    q_all = wrap_to_limits(load_amc(DATA / "10_02.amc", sk).q.to(F64), lo, hi, torch.as_tensor(sk.angular_dofs()))
    joints = sk.forward_kinematics(q_all)
    cam = camera_for_motion(joints, 6.0, 30.0, 10.0, 1000.0, 640, 480).to(dtype=F64)
    kps = make_keypoints(sk)
    g = torch.Generator().manual_seed(seed)
    observed = cam.project(joints[FRAME, kps.index()]).pixels
    observed = observed + 2.0 * torch.randn(observed.shape, generator=g, dtype=F64)
    obj = Objective(
        {
            "reprojection": Reprojection(
                observed, torch.ones(kps.num_keypoints, dtype=F64), sigma_px=2.0, loss="cauchy", scale=3.0
            ),
            "limits": JointLimits(lo, hi, sigma=0.02),
        }
    )
    noise = perturb * torch.randn(n, sk.num_dofs, generator=g, dtype=F64)
    noise[:, :3] *= 0.5
    q0 = torch.clamp(q_all[FRAME] + noise, lo, hi)
    return sk, cam, kps, obj, q0, lo, hi


def bench_jacobians(sk, cam, kps, obj, q0, repeats: int) -> None:
    n, d = q0.shape
    # off the limits' kinks: at a dof exactly on its bound the barrier's derivative is one-sided (the
    # closed form takes 0, autograd of clamp 1 / sigma), which is not a Jacobian error
    lo, hi = sk.limits(dtype=q0.dtype)
    q0 = torch.where(q0 == lo, lo + 1e-9, torch.where(q0 == hi, hi - 1e-9, q0))
    print(f"(a) Jacobians, N={n} poses, J={sk.num_joints}, D={d}, float64 (ms, median of {repeats})")
    fk = lambda q: sk.forward_kinematics(q)  # noqa: E731
    t_geo, (_, jac_geo) = median_time(lambda: joint_jacobian(sk, q0), repeats)
    t_fwd, jac_fwd = median_time(lambda: torch.func.vmap(torch.func.jacfwd(fk))(q0), repeats)
    t_ad, jac_ad = median_time(
        lambda: torch.autograd.functional.jacobian(lambda q: fk(q).sum(0), q0).permute(2, 0, 1, 3), max(1, repeats // 3)
    )
    t_fk, _ = median_time(lambda: sk.forward_kinematics(q0, rotations=True), repeats)
    print(f"    joint positions (N, J, 3, D): FK alone {1e3 * t_fk:.1f}")
    print(
        f"      geometric {1e3 * t_geo:.1f} | jacfwd {1e3 * t_fwd:.1f} ({t_fwd / t_geo:.1f}x) | "
        f"autograd {1e3 * t_ad:.1f} ({t_ad / t_geo:.1f}x); max |geometric - autograd| "
        f"{(jac_geo - jac_ad).abs().max():.1e}, |jacfwd - autograd| {(jac_fwd - jac_ad).abs().max():.1e}"
    )
    lin = objective_linearization(sk, obj, cam, kps)
    full = lambda q: obj.residuals(evaluate_pose(sk, cam, kps, q))  # noqa: E731
    t_geo, out = median_time(lambda: lin(q0), repeats)
    t_fwd, r_fwd = median_time(lambda: torch.func.vmap(torch.func.jacfwd(full))(q0), repeats)
    t_ad, r_ad = median_time(
        lambda: torch.autograd.functional.jacobian(lambda q: full(q).sum(0), q0).permute(1, 0, 2), max(1, repeats // 3)
    )
    print(
        f"    residuals (N, M={out.residuals.shape[-1]}, D), with weights and energy: "
        f"chain rule {1e3 * t_geo:.1f} | jacfwd {1e3 * t_fwd:.1f} ({t_fwd / t_geo:.1f}x) | "
        f"autograd {1e3 * t_ad:.1f} ({t_ad / t_geo:.1f}x)"
    )
    print(
        f"      max |chain rule - autograd| {(out.jacobian - r_ad).abs().max():.1e} "
        f"(|J| up to {r_ad.abs().max():.0f}), |jacfwd - autograd| {(r_fwd - r_ad).abs().max():.1e}"
    )


def bench_batched_vs_sequential(sk, cam, kps, obj, q0, lo, hi, sequential: int, repeats: int) -> None:
    n = q0.shape[0]
    lin = objective_linearization(sk, obj, cam, kps)
    settings = dict(max_iter=30)
    t_batch, (_q_b, info_b) = median_time(lambda: levenberg_marquardt(lin, q0, lo, hi, **settings), repeats)
    k = min(sequential, n)

    def one_by_one():
        return [levenberg_marquardt(lin, q0[i : i + 1], lo, hi, **settings) for i in range(k)]

    t0 = time.perf_counter()
    singles = one_by_one()
    t_seq = (time.perf_counter() - t0) * n / k
    cost_s = torch.cat([info.cost for _, info in singles])
    diff = (cost_s - info_b.cost[:k]).abs().max()
    its = info_b.iterations.float()
    print(f"(b) LM, {n} poses at once vs {n} sequential single-pose solves (max_iter 30, default tolerances)")
    print(
        f"    batched {t_batch:.2f} s (iterations per problem: median {its.median():.0f}, max {its.max():.0f}; "
        f"{int(info_b.converged.sum())}/{n} converged; {info_b.evaluations} batched evaluations)"
    )
    scaled = f", timed on the first {k} and scaled by {n}/{k}" if k < n else ""
    print(
        f"    sequential {t_seq:.2f} s{scaled}; same cost: max |cost difference| {diff:.1e} "
        f"(costs {info_b.cost.min():.2f}..{info_b.cost.max():.2f})"
    )
    print(f"    speed-up {t_seq / t_batch:.1f}x")


def bench_polishing(sk, cam, kps, obj, q0, lo, hi, cost_tol: float, quick: bool) -> None:
    n = q0.shape[0]
    lin = objective_linearization(sk, obj, cam, kps)
    energy = lambda q: obj(evaluate_pose(sk, cam, kps, q)).total  # noqa: E731
    solvers = {
        "LM": lambda k, cb: levenberg_marquardt(lin, q0, lo, hi, max_iter=k, tol=0.0, gtol=0.0, callback=cb),
        "L-BFGS": lambda k, cb: lbfgs(energy, q0, lo, hi, max_iter=k, tol=0.0, gtol=0.0, callback=cb),
    }
    budgets = {"LM": 15 if quick else 30, "L-BFGS": 100 if quick else 300}
    start_cost = energy(q0)
    traces: dict[str, list[tuple[float, torch.Tensor]]] = {}
    for name, run in solvers.items():
        run(2, None)  # warm-up
        trace = [(0.0, start_cost)]
        t0 = time.perf_counter()
        run(budgets[name], lambda it, q, cost: trace.append((time.perf_counter() - t0, cost.clone())))
        traces[name] = trace
    # the cost both reach: per problem, the worse of the two final costs (+ tol)
    target = torch.maximum(traces["LM"][-1][1], traces["L-BFGS"][-1][1]) + cost_tol
    print(
        f"(c) polishing step, {n} poses perturbed from a real frame, 2 px noise: time until 95% of the "
        f"problems reach the cost both solvers reach (per problem the worse final cost + {cost_tol})"
    )
    print(f"    start cost: mean {start_cost.mean():.1f}, median {start_cost.median():.1f}")
    reached = {}
    for name, trace in traces.items():
        hit = [(t, it) for it, (t, cost) in enumerate(trace) if (cost <= target).double().mean() >= 0.95]
        reached[name] = hit[0] if hit else (math.inf, None)
        final = trace[-1][1]
        print(
            f"    {name}: {len(trace) - 1} iterations in {trace[-1][0]:.2f} s, final cost mean {final.mean():.4f} "
            f"median {final.median():.4f}; reached at iteration {reached[name][1]} after {reached[name][0]:.2f} s"
        )
        marks = [k for k in (1, 2, 3, 5, 10, 20, 30, 50, 100, 200, 300) if k < len(trace)]
        print("      mean cost by iteration: " + ", ".join(f"{k}: {trace[k][1].mean():.3f}" for k in marks))
    t_lm, t_lb = reached["LM"][0], reached["L-BFGS"][0]
    if t_lm <= t_lb:
        print(f"    LM reaches equal cost {t_lb / t_lm:.1f}x faster than L-BFGS")
    else:
        print(f"    L-BFGS reaches equal cost {t_lm / t_lb:.1f}x faster than LM")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--n", type=int, default=256)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--perturb", type=float, default=0.1, help="start perturbation, radians per angle")
    ap.add_argument("--sequential", type=int, default=32, help="single-pose solves actually timed in (b)")
    ap.add_argument("--cost-tol", type=float, default=1e-3)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="smaller budgets (for a smoke run)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    print(machine_line())
    sk, cam, kps, obj, q0, lo, hi = build(args.n, args.perturb)
    print(
        f"ptrack bench_solver: torch {torch.__version__}, {args.threads} thread(s), N={args.n}, "
        f"perturbation {args.perturb} rad"
    )
    bench_jacobians(sk, cam, kps, obj, q0, args.repeats)
    bench_batched_vs_sequential(sk, cam, kps, obj, q0, lo, hi, args.sequential, args.repeats)
    bench_polishing(sk, cam, kps, obj, q0, lo, hi, args.cost_tol, args.quick)


if __name__ == "__main__":
    main()
