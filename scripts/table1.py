"""Table 1 of Sminchisescu & Triggs 2003 (section 5.1, fig. 6) on a real CMU pose seen frontally.

Start: the true pose of one frame, polished to a minimum of the model-joint to image-joint cost
(squared reprojection of the 17 keypoints, noiseless 2D from the true pose, sigma 1 px, + joint limits).
Methods, each optimised by batched Levenberg-Marquardt afterwards:
  KJS1 flips the left and right upper arms (shoulder) and the left calf, KJS2 both calves and the
       right upper arm: 2^3 = 8 leaves per start, from the start minimum and from CSS-diffused
       (scale 4, then polished) starts, as many starts as the sample count / 8;
  CSS  covariance scaled samples around the start (scale * H^-1, H the Gauss-Newton Hessian),
       Gaussian scales 4, 8, 16 and Cauchy scale 1; SS the same with the isotropic covariance of
       equal volume. Samples are projected onto the joint limits.

    python scripts/table1.py                       # writes docs/table1.md and docs/table1_hist.png
    python scripts/table1.py --samples 500 --seed 1 --out /tmp/t1
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import math
import time
from pathlib import Path
from types import SimpleNamespace

import torch

from ptrack.body.keypoints import make_keypoints
from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.costs import JointLimits, Objective, Reprojection
from ptrack.hypotheses.ik import chain_ik, ik_plan
from ptrack.hypotheses.jumps import default_chains, interpretation_tree, joint_observations
from ptrack.hypotheses.mixture import distinct_minima
from ptrack.hypotheses.samplers import css_proposal, project_to_limits, scaled_covariance, spherical_proposal
from ptrack.observe.camera import camera_for_motion
from ptrack.optim.jacobians import objective_linearization
from ptrack.problem import evaluate_pose

ROOT = Path(__file__).resolve().parents[1]
#: poses linearised or polished at once (2000 at once added about 350 MB of Jacobians and their products);
#: each pose's LM is its own problem, so chunks give the same result (bit for bit, 600 CSS samples)
CHUNK = 250
CEILING = math.radians(30.0)  # largest std of a dof before scaling (the trackers' kjs.ceiling_deg)
# KJS experiments: (chain, link that may flip) -- link 0 = upper arm / thigh, link 1 = forearm / calf
KJS_FLIPS = {"KJS1": (("larm", 0), ("rarm", 0), ("lleg", 1)), "KJS2": (("lleg", 1), ("rleg", 1), ("rarm", 0))}
SAMPLING = [
    ("CSS", 4, "gaussian"),
    ("CSS", 8, "gaussian"),
    ("CSS", 16, "gaussian"),
    ("CSS", 1, "cauchy"),
    ("SS", 4, "gaussian"),
    ("SS", 8, "gaussian"),
    ("SS", 16, "gaussian"),
    ("SS", 1, "cauchy"),
]


def frontal_azimuth(joints: torch.Tensor, names: list[str]) -> float:
    """Azimuth (deg, about +Y from +Z towards +X) of a camera in front of the body: forward = left x up."""
    left = joints[names.index("lclavicle")] - joints[names.index("rclavicle")]
    fwd = torch.linalg.cross(left, torch.tensor([0.0, 1.0, 0.0], dtype=left.dtype))
    return math.degrees(math.atan2(float(fwd[0]), float(fwd[2])))


class Study:
    def __init__(self, args):
        self.args = args
        self.sk = Skeleton.from_asf(args.asf).freeze(["*fingers", "*thumb", "*hand", "*toes"]).with_limits("data")
        q_all = load_amc(args.amc, self.sk).q.double()
        self.q_true = q_all[args.frame]
        joints = self.sk.forward_kinematics(self.q_true)
        self.azimuth = frontal_azimuth(joints, list(self.sk.joint_names))
        self.cam = camera_for_motion(joints[None].float(), 5.0, self.azimuth, 0.0, 1000.0, 640, 480)
        self.kps = make_keypoints(self.sk)
        self.pixels = evaluate_pose(self.sk, self.cam, self.kps, self.q_true).pixels  # (K, 2), noiseless
        self.conf = torch.ones(self.pixels.shape[0], dtype=self.pixels.dtype)
        lo, hi = self.sk.limits(dtype=torch.float64)
        self.lower, self.upper = lo, hi
        self.angular = torch.as_tensor(self.sk.angular_dofs())
        objective = Objective(
            {
                "reprojection": Reprojection(self.pixels, self.conf, sigma_px=1.0, loss="l2"),
                "limits": JointLimits(lo, hi, sigma=0.05),
            },
            {"limits": 1.0},
        )
        self.linearize = objective_linearization(self.sk, objective, self.cam, self.kps)
        self.chains = {c.name: c for c in default_chains(self.sk)}
        self.plans = {n: ik_plan(self.sk, c) for n, c in self.chains.items()}
        # the start: the true pose polished to a minimum, and its Gauss-Newton Hessian
        q0 = torch.clamp(self.q_true, lo, hi)[None]
        q0, info = self.polish(q0, 100)
        self.q0, self.cost0, self.hessian = q0[0], info.cost[0], info.hessian[0]
        # unscaled covariance factor (for Mahalanobis distances) and per-dof std
        self.chol1 = scaled_covariance(self.hessian, 1.0, max_std=CEILING).chol
        # dofs that move some keypoint (the others - feet, wrists' twist, ... - are free at every minimum)
        self.seen = self.hessian.diagonal() > 1e-9

    def polish(self, q, iterations):
        """LM of every pose of q (N, D), CHUNK at a time (independent problems: the same result as one call)
        -> q (N, D), info with cost (N,) and hessian (N, D, D)."""
        from ptrack.optim.solvers import levenberg_marquardt

        parts = [
            levenberg_marquardt(self.linearize, x, self.lower, self.upper, max_iter=iterations, tol=1e-8)
            for x in q.split(CHUNK)
        ]
        info = SimpleNamespace(
            cost=torch.cat([i.cost for _, i in parts]), hessian=torch.cat([i.hessian for _, i in parts])
        )
        return torch.cat([x for x, _ in parts]), info

    def cost(self, q):
        return torch.cat([self.linearize(x).energy for x in q.split(CHUNK)])

    def proposal(self, kind, scale, tail, n, gen, mean=None):
        chol = scaled_covariance(self.hessian, float(scale), max_std=CEILING / math.sqrt(scale)).chol
        propose = spherical_proposal if kind == "SS" else css_proposal
        mean = self.q0[None] if mean is None else mean
        draws = propose(mean, chol[None], n, gen, tail=tail)
        return project_to_limits(
            draws.samples.reshape(-1, self.q0.numel()), self.lower, self.upper, self.angular, mode="clamp"
        )

    def kjs(self, name, n, gen):
        """Leaves of the chosen flips from n // 8 starts (the start minimum + polished CSS draws)."""
        starts = max(n // 8, 1)
        q = self.q0[None]
        if starts > 1:
            extra, _ = self.polish(self.proposal("CSS", 4, "gaussian", starts - 1, gen), self.args.iterations)
            q = torch.cat([q, extra])
        px, conf = joint_observations(self.kps, self.pixels, self.conf, self.sk.num_joints)
        joints = self.sk.forward_kinematics(q)
        leaves, keep = [q.clone()], [torch.ones(q.shape[0], dtype=torch.bool)]
        for chain_name, link in KJS_FLIPS[name]:
            tree = interpretation_tree(self.chains[chain_name], joints, self.cam, px, conf)
            ik = chain_ik(self.plans[chain_name], q, tree.positions, mode="prune")
            dofs = torch.as_tensor(ik.dofs)
            new_leaves, new_keep = [], []
            for leaf, ok in zip(leaves, keep):  # each current leaf: unflipped, and with this link flipped
                for b in (0, 1 << link):
                    x = leaf.clone()
                    x[:, dofs] = ik.angles[:, b].to(x)
                    new_leaves.append(x)
                    new_keep.append(ok & ik.keep[:, b] & (tree.unique[:, b] if b else True))
            leaves, keep = new_leaves, new_keep
        q_all = torch.stack(leaves, 1).reshape(-1, q.shape[-1])  # (starts * 8, D)
        keep_all = torch.stack(keep, 1).reshape(-1)
        return q_all, keep_all, starts

    def stats(self, q_raw, q_opt, c_raw, c_opt, min_deg):
        thr = math.radians(min_deg)
        d_opt = q_opt - self.q0
        idx = distinct_minima(q_opt[:, self.seen], c_opt, thr)
        own = (q_opt[idx][:, self.seen] - self.q0[self.seen]).abs().amax(-1) <= thr
        idx = idx[~own]
        n_q = idx.numel()
        # the same in 3D: keypoint positions (camera-independent), no coordinate apart by more than 5 cm
        kp = self.sk.forward_kinematics(q_opt)[:, self.kps.index()].reshape(q_opt.shape[0], -1)
        kp0 = self.sk.forward_kinematics(self.q0)[self.kps.index()].reshape(-1)
        idx3 = distinct_minima(kp, c_opt, 0.05)
        idx3 = idx3[(kp[idx3] - kp0).abs().amax(-1) > 0.05]
        idx = idx3 if idx3.numel() else idx[:0]  # distances and costs of minima: over the 3D-distinct ones
        white = torch.linalg.solve_triangular(self.chol1, (q_raw - self.q0).T, upper=False).T
        white_opt = torch.linalg.solve_triangular(self.chol1, d_opt.T, upper=False).T
        return {
            "minima": int(n_q),
            "minima3d": int(idx3.numel()),
            "dist_raw": float((q_raw - self.q0).norm(dim=-1).median()),
            "dist_opt": float(d_opt[idx].norm(dim=-1).median()) if idx.numel() else float("nan"),
            "std_raw": float(white.norm(dim=-1).median()),
            "std_opt": float(white_opt[idx].norm(dim=-1).median()) if idx.numel() else float("nan"),
            "cost_raw": float(c_raw.median()),
            "cost_opt": float(c_opt.median()),
            "cost_minima": float(c_opt[idx].median()) if idx.numel() else float("nan"),
            "hist": (
                d_opt[idx].norm(dim=-1),
                white_opt[idx].norm(dim=-1),
                (q_raw - self.q0).norm(dim=-1),
                white.norm(dim=-1),
            ),
        }


def keep_malloc_threshold() -> None:
    """glibc only (a no-op elsewhere): hold malloc's mmap threshold at its default 128 KiB. glibc raises it
    (up to 32 MiB) whenever a block above it is freed; the chunks' temporaries of tens of MB then come from
    the heap, where freed pages stay mapped and fragment: one 2000-sample row peaked at 1.9 GB resident
    with it raised, 0.36 GB with it held."""
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6").mallopt(-3, 128 << 10)  # M_MMAP_THRESHOLD


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--asf", default=str(ROOT / "ptrack/data/10.asf"))
    ap.add_argument("--amc", default=str(ROOT / "ptrack/data/10_02.amc"))
    ap.add_argument("--frame", type=int, default=0)
    ap.add_argument("--samples", type=int, default=2000, help="CSS/SS samples per method")
    ap.add_argument("--kjs-samples", type=int, nargs=2, default=(1024, 1536), help="KJS1, KJS2 leaves")
    ap.add_argument("--iterations", type=int, default=40, help="LM iterations per sample")
    ap.add_argument("--distinct-deg", type=float, default=1.5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=str(ROOT / "docs"))
    args = ap.parse_args()
    torch.set_num_threads(2)
    keep_malloc_threshold()
    t_start = time.time()
    s = Study(args)
    gen = torch.Generator().manual_seed(args.seed)
    rows = []
    runs = [(n, None, None) for n in KJS_FLIPS] + SAMPLING
    for i, (kind, scale, tail) in enumerate(runs):
        t0 = time.time()
        if kind.startswith("KJS"):
            q_raw, keep, starts = s.kjs(kind, args.kjs_samples[i], gen)
            q_raw = q_raw[keep]
            label, note = kind, f"{starts} starts x 8 leaves, {int(keep.sum())} kept by IK"
        else:
            q_raw = s.proposal(kind, scale, tail, args.samples, gen)
            label, note = f"{kind} {'Gaussian' if tail == 'gaussian' else 'Cauchy'} scale {scale}", ""
        c_raw = s.cost(q_raw)
        q_opt, info = s.polish(q_raw, args.iterations)
        st = s.stats(q_raw, q_opt, c_raw, info.cost, args.distinct_deg)
        st.update(label=label, n=q_raw.shape[0], note=note, seconds=time.time() - t0)
        rows.append(st)
        print(
            f"{label:28s} n={st['n']:5d} minima={st['minima']:5d}/{st['minima3d']:5d}"
            f" dist {st['dist_raw']:.3f}/{st['dist_opt']:.3f}"
            f" std {st['std_raw']:.2f}/{st['std_opt']:.2f} cost {st['cost_raw']:.3g}/{st['cost_opt']:.3g}"
            f" ({st['seconds']:.0f} s)",
            flush=True,
        )
    write(args, s, rows, time.time() - t_start)


def write(args, s, rows, seconds):
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    png = None
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(2, 2, figsize=(11, 7))
        for r in rows:
            for ax, h in zip(axes.flat, (r["hist"][2], r["hist"][3], r["hist"][0], r["hist"][1])):
                if h.numel():  # x range: up to the 95th percentile (Cauchy tails reach far)
                    ax.hist(h.clamp_max(h.quantile(0.95)).numpy(), bins=30, histtype="step", label=r["label"])
        titles = (
            "raw samples: parameter distance (rad/m)",
            "raw samples: Mahalanobis distance (std)",
            "3D-distinct minima: parameter distance (rad/m)",
            "3D-distinct minima: Mahalanobis distance (std)",
        )
        for ax, t in zip(axes.flat, titles):
            ax.set_title(t, fontsize=9)
            ax.set_ylabel("count")
        axes[0, 0].legend(fontsize=6)
        fig.tight_layout()
        png = out / "table1_hist.png"
        fig.savefig(png, dpi=90)
    except ImportError:
        pass
    D = s.q0.numel()
    lines = [
        "# Table 1 of Sminchisescu & Triggs 2003, repeated on a CMU pose",
        "",
        f"Made by `python scripts/table1.py` ({seconds:.0f} s on this 2-core machine). Setup: CMU "
        f"`{Path(args.amc).name}` frame {args.frame}, skeleton `{Path(args.asf).name}` with fingers, thumbs, hands "
        f"and toes frozen, `data` joint limits, D = {D} dofs (6 root); camera 5 m away, elevation 0, azimuth "
        f"{s.azimuth:.1f} deg (in front of the subject: forward = left shoulder direction x up), focal 1000 px, "
        f"640x480. Cost: 0.5 sum of squared reprojection errors of the 17 keypoints (sigma 1 px, noiseless "
        f"2D of the true pose) + joint-limit barrier. Start: the true pose polished by LM (cost "
        f"{float(s.cost0):.2e}); its Gauss-Newton Hessian H gives the CSS covariance scale * H^-1 "
        f"(eigenvalues clamped as below). Every sample is optimised by {args.iterations} LM iterations. "
        f"Seed {args.seed}.",
        "",
        "Distinct minima (q): greedy suppression (`ptrack.hypotheses.mixture.distinct_minima`) at "
        f"{args.distinct_deg} deg, "
        f"max over the {int(s.seen.sum())} dofs that move some keypoint (root translation in the same number "
        "of metres' units; the other dofs - feet, wrists, ... - are free at every minimum), excluding the "
        "start's own minimum. Distinct minima (3D): the same on the 17 keypoints' 3D positions, no coordinate "
        "more than 5 cm apart, excluding the start's. Distances: Euclidean norm of "
        "q - q_start over all dofs (radians, root position in metres); std: Mahalanobis distance under the "
        "unscaled covariance H^-1 (std <= 30 deg per direction; sampling uses the same ceiling after scaling, "
        "as the trackers do). Raw = before optimisation, over all samples; opt = over the 3D-distinct minima "
        "found. Costs: medians over all samples (raw, opt) and over the 3D-distinct minima. Histograms: values "
        "above each method's 95th percentile are counted at it.",
        "",
        "| method | samples | distinct minima (q / 3D) | median dist raw / opt | median std raw / opt "
        "| median cost raw | median cost opt (all / minima) | note |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['label']} | {r['n']} | {r['minima']} / {r['minima3d']} "
            f"| {r['dist_raw']:.3f} / {r['dist_opt']:.3f} | "
            f"{r['std_raw']:.2f} / {r['std_opt']:.2f} | {r['cost_raw']:.3g} | "
            f"{r['cost_opt']:.3g} / {r['cost_minima']:.3g} | {r['note']} |"
        )
    lines += [
        "",
        "![histograms](table1_hist.png)" if png else "(matplotlib is not installed: no histograms written.)",
        "",
        "## Reading",
        "",
    ]
    md = out / "table1.md"  # the reading is written by hand: a rerun keeps the existing one
    old = md.read_text().split("## Reading\n", 1) if md.exists() else []
    reading = old[1].lstrip("\n") if len(old) == 2 else "(not written yet: compare the table with the paper's)\n"
    md.write_text("\n".join(lines) + reading)
    print(f"wrote {out / 'table1.md'}" + (f", {png}" if png else ""))


if __name__ == "__main__":
    main()
