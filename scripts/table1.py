"""Table 1 of Sminchisescu & Triggs 2003 (section 5.1, fig. 6) on a real CMU pose seen frontally.

As the paper ran it: one start pose near the true 3D configuration, the model-joint to image-joint cost, and
each sampler's samples (raw and after local optimisation) counted as distinct minima, with their distances
from the start and their costs.

Observations: the 17 keypoints of the true pose projected, plus Gaussian noise of `--noise-px` (2 px: the
eval configs' level, about a careful hand-click's error; the paper's image joints were measured, so its
minima do not fit them exactly: its optimised costs are 0.02-18, not 0). Cost: 0.5 sum over the keypoints of
(reprojection error / noise std)^2 + joint-limit barrier; costs are reported relative to the start's.
Start: the true pose polished by LM to a minimum of that cost; its Gauss-Newton Hessian H.
Methods, each optimised afterwards by batched Levenberg-Marquardt:
  KJS1     the product of the full interpretation trees of the left arm, the right arm and the left leg
           (2 links each: 4^3 = 64 leaves) from the single start, closed-form IK, leaves outside the joint
           limits pruned; KJS2 the left leg, the right leg and the right arm; KJS5 all five default chains
           (arms, legs, head: 4^5 = 1024 leaves, the paper's KJS1 count); KJS1 project the same leaves as
           KJS1 with those outside the limits projected onto them (`chain_ik` mode "project") rather than pruned;
  CSS      covariance scaled samples around the start, covariance scale * H^-1, Gaussian scales 1, 4, 8,
           16 and Cauchy scale 1; SS the same with the isotropic covariance of equal volume. H^-1's
           directions H barely constrains (feet, wrists' twist, depth) are capped at `CEILING` std before
           scaling, so the scale widens every direction (std <= 30 deg x sqrt(scale)). Samples are
           clamped into the joint limits.

    python scripts/table1.py                           # writes docs/table1.md and docs/table1_fig6.png
    python scripts/table1.py --seeds 0 1 2             # the seeds' count spread as a second table
    python scripts/table1.py --samples 500 --out /tmp/t1
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
from ptrack.hypotheses.ik import chain_ik, ik_plan, product_ik
from ptrack.hypotheses.jumps import default_chains, interpretation_trees, joint_observations, product
from ptrack.hypotheses.mixture import distinct_minima
from ptrack.hypotheses.samplers import css_proposal, project_to_limits, scaled_covariance, spherical_proposal
from ptrack.observe.camera import camera_for_motion
from ptrack.optim.jacobians import objective_linearization
from ptrack.optim.solvers import levenberg_marquardt
from ptrack.problem import evaluate_pose

ROOT = Path(__file__).resolve().parents[1]
#: poses linearised or polished at once (2000 at once added about 350 MB of Jacobians and their products);
#: each pose's LM is its own problem, so chunks give the same result (bit for bit, 600 CSS samples)
CHUNK = 250
#: largest std of a direction of H^-1 before scaling (the trackers capped it at 30 degrees until 2026-11-29, now at
#: half a turn after scaling: ptrack.estimators.kjs.model.WIDEST_STD); the scale multiplies it
CEILING = math.radians(30.0)
#: KJS experiments: the chains whose full interpretation trees are combined (a product) at the start, and
#: what IK does with a leaf outside the joint limits (prune it, or project it onto the limits: `chain_ik`)
KJS_CHAINS = {
    "KJS1": (("larm", "rarm", "lleg"), "prune"),
    "KJS2": (("lleg", "rleg", "rarm"), "prune"),
    "KJS5": (("larm", "rarm", "lleg", "rleg", "head"), "prune"),
    "KJS1 project": (("larm", "rarm", "lleg"), "project"),
}
SAMPLING = [
    ("CSS", 1, "gaussian"),
    ("CSS", 4, "gaussian"),
    ("CSS", 8, "gaussian"),
    ("CSS", 16, "gaussian"),
    ("CSS", 1, "cauchy"),
    ("SS", 1, "gaussian"),
    ("SS", 4, "gaussian"),
    ("SS", 8, "gaussian"),
    ("SS", 16, "gaussian"),
    ("SS", 1, "cauchy"),
]
#: the paper's Table 1 (minima; median parameter distance no-opt / opt; median std no-opt / opt; median cost
#: no-opt / opt), read from the paper's text; None where the paper has no value (SS scale 1 found no minimum)
PAPER = {
    "KJS1": (1024, 2.9345, 2.8378, 92.83, 93.96, 0.0998, 0.0212),
    "KJS2": (1466, 3.2568, 2.2986, 83.48, 82.57, 0.1045, 0.0203),
    "CSS Gaussian 1": (8, 1.1481, 2.5524, 10.94, 47.60, 116.95, 8.4968),
    "CSS Gaussian 4": (59, 3.2123, 2.9474, 35.29, 55.32, 1995.12, 6.9810),
    "CSS Gaussian 8": (180, 4.9694, 3.3466, 75.11, 109.81, 16200.81, 7.0986),
    "CSS Gaussian 16": (667, 6.4242, 6.7209, 177.11, 465.89, 45444.12, 8.6958),
    "CSS Cauchy 1": (580, 5.0536, 6.9362, 106.63, 517.39, 15247.71, 8.7242),
    "SS Gaussian 1": (0, 0.1993, None, 24.53, None, 273.51, None),
    "SS Gaussian 4": (11, 0.7673, 2.0492, 96.15, 39.07, 4291.12, 6.2801),
    "SS Gaussian 8": (42, 1.4726, 2.5488, 188.16, 56.83, 16856.12, 6.9648),
    "SS Gaussian 16": (135, 2.7195, 2.8494, 367.75, 87.85, 63591.42, 8.6958),
    "SS Cauchy 1": (232, 2.1861, 6.5474, 178.65, 535.999, 18173.11, 17.8807),
}


def frontal_azimuth(joints: torch.Tensor, names: list[str]) -> float:
    """Azimuth (deg, about +Y from +Z towards +X) of a camera in front of the body: forward = left x up."""
    left = joints[names.index("lclavicle")] - joints[names.index("rclavicle")]
    fwd = torch.linalg.cross(left, torch.tensor([0.0, 1.0, 0.0], dtype=left.dtype))
    return math.degrees(math.atan2(float(fwd[0]), float(fwd[2])))


class Study:
    """The scene, the noisy 2D, the cost and the start of one Table 1 run (seed: the noise's draw)."""

    def __init__(self, asf: str, amc: str, frame: int, noise_px: float, seed: int, iterations: int = 40):
        self.iterations = iterations
        self.sk = Skeleton.from_asf(asf).freeze(["*fingers", "*thumb", "*hand", "*toes"]).with_limits("data")
        q_all = load_amc(amc, self.sk).q.double()
        self.q_true = q_all[frame]
        joints = self.sk.forward_kinematics(self.q_true)
        self.azimuth = frontal_azimuth(joints, list(self.sk.joint_names))
        self.cam = camera_for_motion(joints[None].float(), 5.0, self.azimuth, 0.0, 1000.0, 640, 480)
        self.kps = make_keypoints(self.sk)
        clean = evaluate_pose(self.sk, self.cam, self.kps, self.q_true).pixels  # (K, 2)
        noise_gen = torch.Generator().manual_seed(10_000 + seed)
        self.noise_px = noise_px
        self.pixels = clean + noise_px * torch.randn(clean.shape, generator=noise_gen, dtype=clean.dtype)
        self.conf = torch.ones(self.pixels.shape[0], dtype=self.pixels.dtype)
        lo, hi = self.sk.limits(dtype=torch.float64)
        self.lower, self.upper = lo, hi
        self.angular = torch.as_tensor(self.sk.angular_dofs())
        objective = Objective(
            {
                "reprojection": Reprojection(self.pixels, self.conf, sigma_px=max(noise_px, 1.0), loss="l2"),
                "limits": JointLimits(lo, hi, sigma=0.05),
            },
            {"limits": 1.0},
        )
        self.linearize = objective_linearization(self.sk, objective, self.cam, self.kps)
        self.chains = {c.name: c for c in default_chains(self.sk)}
        self.plans = {n: ik_plan(self.sk, c) for n, c in self.chains.items()}
        self.cost_true = float(self.cost(torch.clamp(self.q_true, lo, hi)[None])[0])
        # the start: the true pose polished to a minimum of the noisy cost, and its Gauss-Newton Hessian
        q0, info = self.polish(torch.clamp(self.q_true, lo, hi)[None], 100)
        self.q0, self.cost0, self.hessian = q0[0], float(info.cost[0]), info.hessian[0]
        # unscaled covariance factor (for Mahalanobis distances)
        self.chol1 = scaled_covariance(self.hessian, 1.0, max_std=CEILING).chol
        # dofs that move some keypoint (the others - feet, wrists' twist, ... - are free at every minimum)
        self.seen = self.hessian.diagonal() > 1e-9

    def polish(self, q, iterations):
        """LM of every pose of q (N, D), CHUNK at a time (independent problems: the same result as one call)
        -> q (N, D), info with cost (N,) and hessian (N, D, D)."""
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

    def proposal(self, kind, scale, tail, n, gen):
        """n samples around the start: CSS (scale * H^-1, each direction's unscaled std capped at CEILING)
        or SS (isotropic, the same volume), Gaussian or Cauchy tails, clamped into the limits -> (n, D)."""
        chol = scaled_covariance(self.hessian, float(scale), max_std=CEILING).chol
        propose = spherical_proposal if kind == "SS" else css_proposal
        draws = propose(self.q0[None], chol[None], n, gen, tail=tail)
        return project_to_limits(
            draws.samples.reshape(-1, self.q0.numel()), self.lower, self.upper, self.angular, mode="clamp"
        )

    def kjs(self, name):
        """Every leaf of the product of the chains' interpretation trees, from the single start, through the
        noisy 2D -> leaves q (L, D) (leaf 0 the start itself), kept (L,) (unique, feasible, exact closed-form
        IK, and within the limits where the experiment prunes)."""
        names, mode = KJS_CHAINS[name]
        chains = [self.chains[c] for c in names]
        px, conf = joint_observations(self.kps, self.pixels, self.conf, self.sk.num_joints)
        q = self.q0[None]
        trees = interpretation_trees(chains, self.sk.forward_kinematics(q), self.cam, px, conf)
        prod = product(trees)
        results = [chain_ik(self.plans[c.name], q, t.positions, mode=mode) for c, t in zip(chains, trees)]
        ik = product_ik(q, results, prod)
        keep = (ik.keep & prod.unique & ~prod.infeasible)[0]
        return ik.q[0], keep

    def stats(self, q_raw, q_opt, c_raw, c_opt, min_deg):
        """Counts and medians of one method's raw samples q_raw (N, D) and their optima q_opt (N, D)."""
        thr = math.radians(min_deg)
        d_opt = q_opt - self.q0
        idx = distinct_minima(q_opt[:, self.seen], c_opt, thr)
        own = (q_opt[idx][:, self.seen] - self.q0[self.seen]).abs().amax(-1) <= thr
        n_q = int((~own).sum())
        # the same in 3D: keypoint positions (camera-independent), no coordinate apart by more than 5 cm
        kp = self.sk.forward_kinematics(q_opt)[:, self.kps.index()].reshape(q_opt.shape[0], -1)
        kp0 = self.sk.forward_kinematics(self.q0)[self.kps.index()].reshape(-1)
        idx3 = distinct_minima(kp, c_opt, 0.05)
        idx3 = idx3[(kp[idx3] - kp0).abs().amax(-1) > 0.05]
        white = torch.linalg.solve_triangular(self.chol1, (q_raw - self.q0).T, upper=False).T
        white_opt = torch.linalg.solve_triangular(self.chol1, d_opt.T, upper=False).T

        def med(x):
            return float(x.median()) if x.numel() else float("nan")

        return {
            "minima": n_q,
            "minima3d": int(idx3.numel()),
            "dist_raw": med((q_raw - self.q0).norm(dim=-1)),
            "dist_opt": med(d_opt[idx3].norm(dim=-1)),
            "std_raw": med(white.norm(dim=-1)),
            "std_opt": med(white_opt[idx3].norm(dim=-1)),
            "cost_raw": med(c_raw - self.cost0),
            "cost_opt": med(c_opt - self.cost0),
            "cost_minima": med(c_opt[idx3] - self.cost0),
            "hist": {
                "dist_all": d_opt.norm(dim=-1),
                "std_all": white_opt.norm(dim=-1),
                "dist_minima": d_opt[idx3].norm(dim=-1),
                "std_minima": white_opt[idx3].norm(dim=-1),
            },
        }


def run_methods(s: Study, samples: int, distinct_deg: float, gen: torch.Generator, log=print) -> list[dict]:
    """Every row of the table for one Study: the KJS experiments, then the samplers (`samples` each)."""
    rows = []
    for kind, scale, tail in [(n, None, None) for n in KJS_CHAINS] + SAMPLING:
        t0 = time.time()
        if kind.startswith("KJS"):
            q_raw, keep = s.kjs(kind)
            note = f"{keep.numel()} leaves from the start, {int(keep.sum())} kept by IK ({KJS_CHAINS[kind][1]})"
            q_raw = q_raw[keep]
            label = kind
        else:
            q_raw = s.proposal(kind, scale, tail, samples, gen)
            label, note = f"{kind} {'Gaussian' if tail == 'gaussian' else 'Cauchy'} {scale}", ""
        if q_raw.shape[0] == 0:  # every leaf pruned (the noise can make a ray miss its sphere: infeasible)
            q_raw = s.q0[None]
            note += "; none kept: the row shows the start alone"
        c_raw = s.cost(q_raw)
        q_opt, info = s.polish(q_raw, s.iterations)
        st = s.stats(q_raw, q_opt, c_raw, info.cost, distinct_deg)
        st.update(label=label, n=q_raw.shape[0], note=note, seconds=time.time() - t0)
        rows.append(st)
        log(
            f"{label:18s} n={st['n']:5d} minima={st['minima']:5d}/{st['minima3d']:5d}"
            f" dist {st['dist_raw']:.3f}/{st['dist_opt']:.3f}"
            f" std {st['std_raw']:.2f}/{st['std_opt']:.2f} dcost {st['cost_raw']:.3g}/{st['cost_opt']:.3g}"
            f" ({st['seconds']:.0f} s)"
        )
    return rows


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
    ap.add_argument("--iterations", type=int, default=40, help="LM iterations per sample")
    ap.add_argument("--noise-px", type=float, default=2.0, help="std of the 2D keypoints' Gaussian noise")
    ap.add_argument("--distinct-deg", type=float, default=1.5)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0], help="the first one's rows make the table")
    ap.add_argument("--out", default=str(ROOT / "docs"))
    args = ap.parse_args()
    torch.set_num_threads(2)
    keep_malloc_threshold()
    t_start = time.time()
    runs = []
    for seed in args.seeds:
        s = Study(args.asf, args.amc, args.frame, args.noise_px, seed, args.iterations)
        print(f"seed {seed}: start cost {s.cost0:.2f} (true pose {s.cost_true:.2f})", flush=True)
        gen = torch.Generator().manual_seed(seed)
        runs.append((seed, s, run_methods(s, args.samples, args.distinct_deg, gen, lambda m: print(m, flush=True))))
        write(args, runs, time.time() - t_start)  # after each seed: a long run leaves its finished seeds


def fig6(path: Path, rows: list[dict]) -> None:
    """The paper's fig. 6: histograms of the optimised samples' parameter distance and Mahalanobis distance
    from the start, KJS1 (top) and CSS Gaussian scale 8 (bottom); the 3D-distinct minima among them filled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    by = {r["label"]: r for r in rows}
    fig, axes = plt.subplots(2, 2, figsize=(9, 5.6))
    for i, label in enumerate(("KJS1", "CSS Gaussian 8")):
        h = by[label]["hist"]
        for j, (key, unit) in enumerate(
            (("dist", "parameter space distance (rad, m)"), ("std", "standard deviations"))
        ):
            ax = axes[i, j]
            every, minima = h[f"{key}_all"], h[f"{key}_minima"]
            top = float(every.quantile(0.99)) if every.numel() > 1 else float(every.max())
            bins = torch.linspace(0, max(top, 1e-6) * 1.02, 31).numpy()
            ax.hist(every.clamp_max(top).numpy(), bins=bins, histtype="step", color="k", label="optimised samples")
            if minima.numel():
                ax.hist(
                    minima.clamp_max(top).numpy(), bins=bins, color="tab:orange", alpha=0.8, label="3D-distinct minima"
                )
            ax.set_xlabel(unit, fontsize=8)
            ax.set_ylabel("count", fontsize=8)
            ax.set_title(f"{label}: {unit.split(' (')[0]}", fontsize=9)
            ax.tick_params(labelsize=7)
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def fmt(x, spec=".3g"):
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def write(args, runs, seconds):
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    seed0, s, rows = runs[0]
    png = None
    try:
        png = out / "table1_fig6.png"
        fig6(png, rows)
    except ImportError:
        png = None
    D = s.q0.numel()
    lines = [
        "# Table 1 of Sminchisescu & Triggs 2003, repeated on a CMU pose",
        "",
        f"Made by `python scripts/table1.py --samples {args.samples} --seeds {' '.join(str(r[0]) for r in runs)}` "
        f"({seconds:.0f} s on this "
        f"2-core machine). Setup: CMU `{Path(args.amc).name}` frame {args.frame}, skeleton `{Path(args.asf).name}` "
        f"with fingers, thumbs, hands and toes frozen, `data` joint limits, D = {D} dofs (6 root); camera 5 m "
        f"away, elevation 0, azimuth {s.azimuth:.1f} deg (in front of the subject), focal 1000 px, 640x480. "
        f"Observations: the 17 keypoints of the true pose with Gaussian noise of {args.noise_px:g} px. Cost: "
        f"0.5 sum of squared reprojection errors in units of the noise std + joint-limit barrier (seed {seed0}: "
        f"true pose {s.cost_true:.2f}, start {s.cost0:.2f}). Start: the true pose polished by LM; its Gauss-Newton "
        f"Hessian H gives the CSS covariance scale * H^-1, each direction's std capped at 30 deg before scaling "
        f"(directions the 2D does not constrain: feet, twists), so scaling widens every direction. "
        f"KJS: every leaf of the product of the named chains' full interpretation trees (2 links each) from "
        f"the single start, closed-form IK, leaves outside the limits pruned. Every sample is optimised by "
        f"{args.iterations} LM iterations.",
        "",
        f"Distinct minima (q): greedy suppression (`distinct_minima`) at {args.distinct_deg} deg, max over the "
        f"{int(s.seen.sum())} dofs that move some keypoint, excluding the start's own minimum. Distinct minima "
        "(3D): the same on the 17 keypoints' 3D positions, no coordinate more than 5 cm apart, excluding the "
        "start's. Distances: Euclidean norm of q - q_start over all dofs (radians, root position in metres); "
        "std: Mahalanobis distance under the unscaled covariance H^-1 (capped as above). Raw = before "
        "optimisation, over all samples; opt = over the 3D-distinct minima. Costs: cost - start cost, medians "
        "over all samples (raw, opt) and over the 3D-distinct minima. The paper's values follow each row "
        "in brackets (its minima count, median distance, std and cost).",
        "",
        f"## Table (seed {seed0})",
        "",
        "| method | samples | distinct minima q / 3D [paper] | median dist raw / opt [paper] "
        "| median std raw / opt [paper] | median cost raw [paper] | median cost opt all / minima [paper] | note |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        p = PAPER.get(r["label"])
        pm = f" [{p[0]}]" if p else ""
        pd = f" [{fmt(p[1], '.2f')} / {fmt(p[2], '.2f')}]" if p else ""
        ps = f" [{fmt(p[3], '.0f')} / {fmt(p[4], '.0f')}]" if p else ""
        pc = f" [{fmt(p[5])}]" if p else ""
        po = f" [{fmt(p[6])}]" if p else ""
        lines.append(
            f"| {r['label']} | {r['n']} | {r['minima']} / {r['minima3d']}{pm} "
            f"| {fmt(r['dist_raw'], '.2f')} / {fmt(r['dist_opt'], '.2f')}{pd} "
            f"| {fmt(r['std_raw'], '.1f')} / {fmt(r['std_opt'], '.1f')}{ps} | {fmt(r['cost_raw'])}{pc} "
            f"| {fmt(r['cost_opt'])} / {fmt(r['cost_minima'])}{po} | {r['note']} |"
        )
    if len(runs) > 1:
        lines += [
            "",
            "## 3D-distinct minima per seed (the seed draws the 2D noise and the samples)",
            "",
            "| method | " + " | ".join(f"seed {sd}" for sd, _, _ in runs) + " | mean | min-max |",
            "|---|" + "---|" * (len(runs) + 2),
        ]
        for i, r in enumerate(rows):
            counts = [rr[i]["minima3d"] for _, _, rr in runs]
            lines.append(
                f"| {r['label']} | "
                + " | ".join(str(c) for c in counts)
                + f" | {sum(counts) / len(counts):.1f} | {min(counts)}-{max(counts)} |"
            )
        lines += [
            "",
            "Start cost per seed (true pose): "
            + ", ".join(f"seed {sd} {st.cost0:.2f} ({st.cost_true:.2f})" for sd, st, _ in runs)
            + ".",
        ]
    lines += [
        "",
        "## Fig. 6 redrawn",
        "",
        "![fig. 6: KJS1 against CSS scale 8](table1_fig6.png)" if png else "(matplotlib is not installed.)",
        "",
        "## Reading",
        "",
    ]
    md = out / "table1.md"  # the reading is written by hand: a rerun keeps the existing one
    old = md.read_text().split("## Reading\n", 1) if md.exists() else []
    reading = old[1].lstrip("\n") if len(old) == 2 else "(not written yet: compare the table with the paper's)\n"
    md.write_text("\n".join(lines) + "\n" + reading)
    print(f"wrote {md}" + (f", {png}" if png else ""))


if __name__ == "__main__":
    main()
