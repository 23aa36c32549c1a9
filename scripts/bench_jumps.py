"""Benchmark: interpretation trees + closed-form IK for 4096 hypotheses x 8 leaves.

    python scripts/bench_jumps.py [--hypotheses 4096] [--repeats 15] [--threads N]

Work timed (issue target: under 50 ms): for N hypotheses of one frame (real CMU poses of the bundled
10_02 clip plus 0.1 rad of noise on every angle, observed through the exact 2D joints of the frame's
true pose), grow the trees of two chains -- the left arm (shoulder -> elbow -> wrist, 2 links,
4 leaves) and the neck (upper neck -> head top, 1 link, 2 leaves) -- take their product
(8 leaves), solve each chain's closed-form IK on its own leaves (prune mode, data limits), combine
them and build the full poses (N, 8, D). Not timed: forward kinematics of the N hypotheses, which
a tracker has already computed (printed for reference).

Baselines measured in the same run, same dtype:
- loop: the same calls made per hypothesis (batch of one) in a Python loop, on the first 64
  hypotheses, scaled to N;
- FK of the N x 8 leaf poses (ptrack's batched forward kinematics): the cost of merely evaluating
  the leaves the trees produce.
A ratio > 1 means trees + IK are faster. Medians of `--repeats` runs (wall clock); the machine's
load average is printed, since a shared 2-core machine skews every number: with other jobs
running, two torch threads wait on each other (FK and trees + IK alike get 3-20x slower), and
`--threads 1` measures the code rather than the contention.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from pathlib import Path

import torch
from _bench import machine_line

from ptrack.body.skeleton import Skeleton
from ptrack.hypotheses.ik import chain_ik, ik_plan, product_ik
from ptrack.hypotheses.jumps import interpretation_tree, make_chain, product
from ptrack.observe.camera import camera_for_motion

DATA = Path(__file__).resolve().parents[1] / "ptrack" / "data"
LOOP_SUBSET = 64


def _median_ms(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--hypotheses", type=int, default=4096)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)

    sk = Skeleton.from_asf(DATA / "10.asf").with_limits("data")
    clip = sk.load_amc(DATA / "10_02.amc").q
    truth = clip[300]
    gen = torch.Generator().manual_seed(0)
    angular = torch.as_tensor(sk.angular_dofs())
    noise = 0.1 * torch.randn(args.hypotheses, sk.num_dofs, generator=gen, dtype=torch.float64)
    q64 = truth + noise * angular
    q64[:, :3] = truth[:3]  # same root position: the hypotheses of one frame
    true_joints = sk.forward_kinematics(truth)
    cam64 = camera_for_motion(sk.forward_kinematics(clip[::20]), 5.0, 30.0, 10.0, 1000.0, 640, 480)
    cam64 = cam64.to(dtype=torch.float64)
    px64 = cam64.project(true_joints).pixels  # (J, 2) shared by all hypotheses
    chains = [
        make_chain(sk, ("lclavicle", "lhumerus", "lradius"), "larm"),
        make_chain(sk, ("upperneck", "head"), "neck"),
    ]
    plans = [ik_plan(sk, c) for c in chains]
    leaves = 1 << sum(c.num_links for c in chains)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(machine_line())
    print(
        f"bench_jumps: CMU skeleton 10 (J={sk.num_joints}, D={sk.num_dofs}), {args.hypotheses} hypotheses x "
        f"{leaves} leaves (larm 2 links x neck 1 link), torch {torch.__version__}, "
        f"{torch.get_num_threads()} threads, load average {load:.2f}"
    )

    for dtype in (torch.float32, torch.float64):
        q = q64.to(dtype)
        cam = cam64.to(dtype=dtype)
        px = px64.to(dtype)
        conf = torch.ones(sk.num_joints, dtype=dtype)
        joints = sk.forward_kinematics(q)

        def trees_and_ik(q=q, joints=joints):
            trees = [interpretation_tree(c, joints, cam, px, conf) for c in chains]
            prod = product(trees)
            results = [chain_ik(p, q, t.positions, mode="prune") for p, t in zip(plans, trees)]
            res = product_ik(q, results, prod)
            return res, res.q

        res, poses = trees_and_ik()
        # check: the leaves' poses put the chain joints on the tree positions
        fk = sk.forward_kinematics(poses)
        idx = [j for c in chains for j in c.joints]
        err = float((fk[..., idx, :] - res.positions).norm(dim=-1).max())

        t_fast = _median_ms(trees_and_ik, args.repeats)
        sub = min(LOOP_SUBSET, args.hypotheses)

        def loop():
            for i in range(sub):
                trees_and_ik(q[i : i + 1], joints[i : i + 1])

        t_loop = _median_ms(loop, 3) * args.hypotheses / sub
        t_fk_leaves = _median_ms(lambda: sk.forward_kinematics(poses), args.repeats)
        t_fk_hyp = _median_ms(lambda: sk.forward_kinematics(q), args.repeats)
        name = str(dtype).replace("torch.", "")
        print(
            f"{name}: trees + IK {t_fast:.1f} ms (target < 50 ms; kept leaves {float(res.keep.float().mean()):.0%}, "
            f"max |FK(leaf pose) - leaf| {err:.1e} m)"
        )
        print(f"  vs per-hypothesis loop {t_loop:.0f} ms (scaled from {sub}): {t_loop / t_fast:.1f}x")
        print(f"  vs FK of the {args.hypotheses * leaves} leaf poses {t_fk_leaves:.1f} ms: {t_fk_leaves / t_fast:.1f}x")
        print(f"  (not timed: FK of the {args.hypotheses} hypotheses {t_fk_hyp:.1f} ms)")


if __name__ == "__main__":
    main()
