"""Leave-one-swing-out evaluation of the golf tracker (`method: pca`) and its baselines.

For each of the dev swings (configs/clips/golf.txt), a motion model is fitted on the other swings
(<out>/models/wo_<swing>.npz) and the swing is tracked with it:

    pca         the full tracker (configs/eval_golf.yaml): joints + silhouettes, the frames after the swing handed
                to the MAP trajectory (pca.after_swing: batch, the default)
    pca_hold    the same holding the swing's last pose after the swing (pca.after_swing: hold; before issue 42)
    pca_frame   the same handing the frames after the swing to per-frame fits (pca.after_swing: frame)
    joints      the same without the silhouette term (pca.silhouette_weight=0; the paper's fig. 7 point)
    mean        the mean motion with the initial timing (pca.iterations=0; fig. 8)
    pca_corr    the full tracker with point correspondences between consecutive frames (section 4.3;
                CORR: 40 simulated pairs per frame, 1 px noise, 5% wrong matches)
    joints_corr joints and correspondences, no silhouette term (the paper's fig. 7 (b))
    pca_corr_m0 pca_corr keeping the pairs near the model's outlines too (pca.correspondence_margin_m=0)
    *_other     pca and joints with silhouettes of another body (OTHER: the capsules of subject 64's skeleton with
                Winter's proportions at 1.62 m, radii each within +-25%), keypoints 3 cm off the joint centres,
                and ROUGH: the issue-42 condition (does the silhouette term still help?)
    *_s6_other  OTHER with the tracker told the 2D's noise (costs.sigma_px=6); pca_s6_other with the foreground term
                at pca.silhouette_weight 0.3 against capsules pca.silhouette_radius_scale 1.6x as wide
    *_person    the same with that body the whole person seen (PERSON: its joints make the 2D and the ground
                truth too; the tracker's body differs by up to 24% in a segment, 47 mm MPJPE at the exact angles)
    *_6px       pca, joints, pca_corr, joints_corr, pca_corr_m0 with rougher joint tracks (ROUGH: noise_px 6, and the
                start's wrist track smoothed over pca.key_smooth_s 0.15 s, without which the key postures
                are not found in that noise)
    frame, kjs, batch   the other methods on the same observations (configs/eval_golf_<method>.yaml;
                these get frame 0 as a 3D keyframe, the pca tracker no 3D input at all)

Every run goes to <out>/<variant>/<swing>/ (seed 0) or <out>/<variant>/<swing>-seed<k>/ (a run folder;
existing ones are reused, so an interrupted evaluation resumes); --seeds sets the observations' seeds (the
noise; the trackers themselves are deterministic), the tables give each swing's mean over them. Metrics are
taken three times: over the whole clip (metrics.json), over the swing, the frames up to the end of the
follow-through plus 0.5 s (the end found in the ground-truth 3D wrists by the motion model's key-posture
rules), and over the clip's last sixth, since the clips go on for up to 2 s after the swing, where the
golfer does what no training swing does. Per seed, the means over the swings and, paired over the runs (swing x
seed), each variant's difference from the first with its standard error. The tables go to <out>/results.md;
--plot SWING draws that swing's full tracker run seen from the camera and from above into docs/golf_swing.png.

    OMP_NUM_THREADS=1 python scripts/eval_golf.py [--out logs/eval_golf] [--variants pca,joints,...]
        [--seeds 0,1,2] [--plot 64_01] [--set pca.silhouette_weight=0.5 ...]
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # run from a checkout without installing

from ptrack.body.keypoints import make_keypoints  # noqa: E402
from ptrack.body.skeleton import Skeleton, load_amc  # noqa: E402
from ptrack.clips import parse_clips  # noqa: E402
from ptrack.motion.key_postures import detect_key_postures  # noqa: E402
from ptrack.motion.motion_model import fit_motion_model, read_clips, save_motion_model  # noqa: E402
from ptrack.pipeline import metrics as M  # noqa: E402
from ptrack.pipeline.config import load_config  # noqa: E402
from ptrack.pipeline.evaluate import asf_for  # noqa: E402
from ptrack.pipeline.run import execute  # noqa: E402

log = logging.getLogger("eval_golf")
CORR = [
    "observations.correspondences=40",
    "observations.correspondence_noise_px=1",
    "observations.correspondence_outliers=0.05",
]
ROUGH = ["observations.noise_px=6", "pca.key_smooth_s=0.15"]
# silhouettes of another body than the tracker's (ptrack/observe/person.py): the capsules of subject 64's skeleton
# with Winter's proportions at its own standing height (1.62 m; forearms 24% and head 23% longer, trunk 10% shorter
# than 64's) moving with the clip's angles, each radius within +-25%; the 2D keypoints 3 cm off the joint centres
# (fixed to the bones), and ROUGH's 6 px
OTHER = [
    "observations.silhouette_height_m=1.62",
    "observations.silhouette_radius_jitter=0.25",
    "observations.keypoint_offset_m=0.03",
    *ROUGH,
]
# the same with that body the whole person seen: its joints make the 2D and the ground truth too
PERSON = ["observations.body_height_m=1.62", *OTHER[1:]]
# the tracker told the 2D's noise (costs.sigma_px 6, not the 2 px default); for the full tracker the foreground term
# at 0.3 and measured against capsules 1.6x as wide (chosen on 64_01, 64_02, 64_04; docs/results.md)
TOLD = ["costs.sigma_px=6"]
WIDE = ["pca.silhouette_weight=0.3", "pca.silhouette_radius_scale=1.6"]
PCA_VARIANTS = {
    "pca": [],
    "pca_hold": ["pca.after_swing=hold"],
    "pca_frame": ["pca.after_swing=frame"],
    "joints": ["pca.silhouette_weight=0"],
    "mean": ["pca.iterations=0"],
    "pca_corr": CORR,
    "joints_corr": ["pca.silhouette_weight=0", *CORR],
    "pca_6px": ROUGH,
    "joints_6px": ["pca.silhouette_weight=0", *ROUGH],
    "pca_corr_6px": [*CORR, *ROUGH],
    "joints_corr_6px": ["pca.silhouette_weight=0", *CORR, *ROUGH],
    "pca_corr_m0": [*CORR, "pca.correspondence_margin_m=0"],
    "pca_corr_m0_6px": [*CORR, "pca.correspondence_margin_m=0", *ROUGH],
    "pca_other": OTHER,
    "joints_other": ["pca.silhouette_weight=0", *OTHER],
    "pca_s6_other": [*OTHER, *TOLD, *WIDE],
    "joints_s6_other": ["pca.silhouette_weight=0", *OTHER, *TOLD],
    "pca_person": PERSON,
    "joints_person": ["pca.silhouette_weight=0", *PERSON],
}
BASELINES = ("frame", "kjs", "batch")
TAIL_S = 0.5  # seconds after the end of the follow-through kept in the swing span


def model_for(swing: Path, swings: list[Path], out: Path) -> Path:
    path = out / "models" / f"wo_{swing.stem}.npz"
    if not path.is_file():
        cfg = load_config(REPO / "configs" / "eval_golf.yaml", run=False)
        model = fit_motion_model(read_clips([s for s in swings if s != swing]), cfg.motion)
        save_motion_model(model, path)
        log.info("fitted %s on %d swings", path, len(swings) - 1)
    return path


def run(variant: str, swing: Path, model: Path, out: Path, seed: int = 0, overrides: tuple[str, ...] = ()) -> Path:
    folder = out / variant / (swing.stem if seed == 0 else f"{swing.stem}-seed{seed}")
    if (folder / "metrics.json").is_file():
        return folder
    if variant in PCA_VARIANTS:
        config, extra = REPO / "configs" / "eval_golf.yaml", [f"motion.model_file={model}", *PCA_VARIANTS[variant]]
    else:
        config, extra = REPO / "configs" / f"eval_golf_{variant}.yaml", []
    cfg = load_config(
        config,
        [
            f"data.amc={swing}",
            f"data.asf={asf_for(swing)}",
            f"out_dir={folder}",
            f"seed={seed}",
            "progress=false",
            "plots=false",
            *extra,
            *overrides,
        ],
    )
    log.info("%s %s seed %d", variant, swing.stem, seed)
    return execute(cfg, progress=False)


def swing_keys(swing: Path, stride: int) -> list[int]:
    """The key-posture frames (at the run's stride) found in the swing's ground-truth 3D wrists."""
    sk = Skeleton.from_asf(asf_for(swing))
    motion = load_amc(swing, sk)
    cfg = load_config(REPO / "configs" / "eval_golf.yaml", run=False)
    with torch.no_grad():
        keys = detect_key_postures(
            sk.forward_kinematics(motion.q.double()), sk, motion.fps, cfg.motion, clip=swing.stem
        )
    return [int(k) // stride for k in keys]


def swing_end(swing: Path, stride: int, tail_s: float = TAIL_S) -> int:
    """Index (at the run's stride) of the last frame of the swing span: end of follow-through + tail_s."""
    sk = Skeleton.from_asf(asf_for(swing))
    motion = load_amc(swing, sk)
    cfg = load_config(REPO / "configs" / "eval_golf.yaml", run=False)
    with torch.no_grad():
        keys = detect_key_postures(
            sk.forward_kinematics(motion.q.double()), sk, motion.fps, cfg.motion, clip=swing.stem
        )
    return int((int(keys[-1]) + tail_s * motion.fps) // stride)


def span_metrics(folder: Path, stop: int | None, start: int = 0) -> dict:
    """MPJPE, PA-MPJPE (17 keypoints, pelvis-aligned) and flip rate over frames [start, stop] of a run (stop None:
    to the last frame)."""
    end = None if stop is None else stop + 1
    with np.load(folder / "result.npz") as z:
        est = torch.from_numpy(z["joints"][start:end]).double()
        gt = torch.from_numpy(z["gt_joints"][start:end]).double()
        R, t = torch.from_numpy(z["camera_R"]).double(), torch.from_numpy(z["camera_t"]).double()
    sk = Skeleton.from_asf(load_config(folder / "config.yaml").data.asf)
    kps = make_keypoints(sk)
    idx = kps.index()
    e, g = est[:, idx], gt[:, idx]
    flips = M.limb_flip_errors(e, g, kps.limbs, R, t)
    return {
        "mpjpe_mm": float(M.mpjpe(e, g, root=0).mean()),
        "pa_mpjpe_mm": float(M.pa_mpjpe(e, g).mean()),
        "flip_error_rate": float(flips.nanmean()),
        "frames": int(est.shape[0]),
    }


def table(rows: dict[str, dict[str, dict]], variants: list[str], title: str) -> str:
    head = "| swing | " + " | ".join(f"{v} MPJPE / PA / flip" for v in variants) + " |"
    lines = [title, "", head, "|---" * (len(variants) + 1) + "|"]
    for swing, per in rows.items():
        cells = [
            f"{per[v]['mpjpe_mm']:.1f} / {per[v]['pa_mpjpe_mm']:.1f} / {per[v]['flip_error_rate']:.3f}"
            if v in per
            else "–"
            for v in variants
        ]
        lines.append(f"| {swing} | " + " | ".join(cells) + " |")
    means = []
    for v in variants:
        vals = [per[v] for per in rows.values() if v in per]
        cols = (("mpjpe_mm", ".1f"), ("pa_mpjpe_mm", ".1f"), ("flip_error_rate", ".3f"))
        means.append(" / ".join(f"{np.mean([x[k] for x in vals]):{f}}" for k, f in cols) if vals else "–")
    lines.append("| **mean** | " + " | ".join(f"**{m}**" for m in means) + " |")
    return "\n".join(lines) + "\n"


def seed_table(seed_span: dict[str, dict[int, list[float]]], seeds: list[int], tail_s: float) -> str:
    """Per variant and seed, the mean over the swings of MPJPE over the swing (the seeds' spread), and on how many
    swings the table's first variant is better than each other one, seed by seed."""
    if not seed_span:
        return ""
    first = next(iter(seed_span))
    head = f"| variant | {' | '.join(f'seed {s}' for s in seeds)} | mean | {first} better on (swings, per seed) |"
    title = f"Per seed, MPJPE over the swing (+ {tail_s:g} s), the mean over the swings:"
    lines = [title, "", head, "|---" * (len(seeds) + 3) + "|"]
    for v, per in seed_span.items():
        means = [float(np.mean(per[s])) for s in seeds]
        wins = [sum(a < b for a, b in zip(seed_span[first][s], per[s])) for s in seeds]
        better = "–" if v == first else " / ".join(f"{w} of {len(per[s])}" for w, s in zip(wins, seeds))
        lines.append(f"| {v} | " + " | ".join(f"{m:.1f}" for m in means) + f" | {np.mean(means):.1f} | {better} |")
    return "\n".join(lines) + "\n\n"


def paired_table(seed_span: dict[str, dict[int, list[float]]], seeds: list[int], tail_s: float) -> str:
    """The table's first variant against each other one, paired over the runs (swing x seed, the same
    observations): the mean of the other's MPJPE minus the first's over the swing (positive: the first is
    better), its standard error (the std of the n paired differences / sqrt(n)), per seed the mean difference,
    and the runs the first is better on."""
    if len(seed_span) < 2:
        return ""
    first = next(iter(seed_span))
    title = f"Paired over swings x seeds, MPJPE over the swing (+ {tail_s:g} s), other minus {first} (mm):"
    head = f"| variant | mean difference +- s.e. (n) | {' | '.join(f'seed {s}' for s in seeds)} | {first} better on |"
    lines = [title, "", head, "|---" * (len(seeds) + 3) + "|"]
    for v, per in seed_span.items():
        if v == first:
            continue
        d = np.array([b - a for s in seeds for a, b in zip(seed_span[first][s], per[s])])
        se = float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("nan")
        by_seed = [float(np.mean(np.subtract(per[s], seed_span[first][s]))) for s in seeds]
        lines.append(
            f"| {v} | {d.mean():+.1f} +- {se:.1f} ({len(d)}) | "
            + " | ".join(f"{x:+.1f}" for x in by_seed)
            + f" | {int((d > 0).sum())} of {len(d)} |"
        )
    return "\n".join(lines) + "\n\n"


def plot(folder: Path, path: Path, n: int = 8) -> None:
    """The estimate (orange) and the ground truth (green) at n frames of the swing: projected into the camera
    (top row) and seen from above (bottom row, world X-Z, Y up)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with np.load(folder / "result.npz") as z:
        est, gt, parents = z["joints"], z["gt_joints"], z["parents"]
        K, R, t = z["camera_K"], z["camera_R"], z["camera_t"]
    keys = swing_keys(Path(load_config(folder / "config.yaml").data.amc), 4)
    frames = np.linspace(max(keys[0] - 4, 0), min(keys[-1] + 4, len(est) - 1), n).round().astype(int)

    def project(x):
        c = x @ R.T + t
        return (c[..., :2] / c[..., 2:]) @ K[:2, :2].T + K[:2, 2]

    seen = np.concatenate([project(est[frames]), project(gt[frames])], axis=1).reshape(-1, 2)
    lo, hi = seen.min(0) - 20, seen.max(0) + 20  # the camera view cropped to the golfer
    fig, axes = plt.subplots(2, n, figsize=(1.5 * n, 4.4), dpi=80)
    for col, f in enumerate(frames):
        for row, fn in ((0, project), (1, lambda x: x[..., [0, 2]])):
            ax = axes[row, col]
            for x, colour in ((gt[f], "tab:green"), (est[f], "tab:orange")):
                p = fn(x)
                for j, par in enumerate(parents):
                    if par >= 0:
                        ax.plot(p[[par, j], 0], p[[par, j], 1], color=colour, lw=1.2)
            ax.set_aspect("equal")
            ax.set_xticks([])
            ax.set_yticks([])
            if row == 0:
                ax.set_xlim(lo[0], hi[0])
                ax.set_ylim(hi[1], lo[1])
                ax.set_title(f"frame {f}", fontsize=8)
            else:
                c = gt[f, 0, [0, 2]]
                ax.set_xlim(c[0] - 0.7, c[0] + 0.7)
                ax.set_ylim(c[1] - 0.7, c[1] + 0.7)
    axes[0, 0].set_ylabel("camera", fontsize=8)
    axes[1, 0].set_ylabel("above (X-Z)", fontsize=8)
    fig.suptitle(f"{folder.name}: pca tracker (orange) vs ground truth (green), model without this swing", fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    log.info("wrote %s", path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="logs/eval_golf")
    ap.add_argument("--swings", default=str(REPO / "configs" / "clips" / "golf.txt"))
    ap.add_argument("--variants", default=",".join([*PCA_VARIANTS, *BASELINES]))
    ap.add_argument("--plot", default=None, help="swing (e.g. 64_01) whose pca run to draw into docs/golf_swing.png")
    ap.add_argument("--seeds", default="0", help="observation seeds, comma-separated (tables: each swing's mean)")
    ap.add_argument(
        "--tail-s",
        type=float,
        default=TAIL_S,
        help="seconds after the end of the follow-through kept in the swing span (0: the swing alone)",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a config override added to every run after the variant's own (repeatable; use another --out)",
    )
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    out = Path(args.out)
    swings = parse_clips(args.swings)
    variants = [v for v in args.variants.split(",") if v]
    seeds = [int(x) for x in args.seeds.split(",") if x.strip()]
    whole: dict[str, dict[str, dict]] = {}
    span: dict[str, dict[str, dict]] = {}
    last: dict[str, dict[str, dict]] = {}
    fps: dict[str, list[float]] = {v: [] for v in variants}
    seed_span: dict[str, dict[int, list[float]]] = {}  # variant -> seed -> each swing's MPJPE over the swing
    for swing in swings:
        model = model_for(swing, swings, out)
        stop = swing_end(swing, 4, args.tail_s)
        for v in variants:
            per_seed: dict[str, list[dict]] = {"whole": [], "span": [], "last": []}
            for seed in seeds:
                folder = run(v, swing, model, out, seed, tuple(args.set))
                m = json.loads((folder / "metrics.json").read_text())
                per_seed["whole"].append({**span_metrics(folder, None), "fps": m["fps"]})
                per_seed["span"].append(span_metrics(folder, stop))
                seed_span.setdefault(v, {}).setdefault(seed, []).append(per_seed["span"][-1]["mpjpe_mm"])
                per_seed["last"].append(span_metrics(folder, None, start=m["frames"] - -(-m["frames"] // 6)))
                fps[v].append(m["fps"])
            for name, rows in (("whole", whole), ("span", span), ("last", last)):
                rows.setdefault(swing.stem, {})[v] = {
                    k: float(np.mean([x[k] for x in per_seed[name]])) for k in per_seed[name][0]
                }
    frames = {s: f"{whole[s][variants[0]]['frames']:.0f} / {span[s][variants[0]]['frames']:.0f}" for s in whole}
    groups = [
        [v for v in variants if not v.endswith(("_6px", "_other", "_person"))],
        [v for v in variants if v.endswith("_6px")],
        [v for v in variants if v.endswith("_other")],
        [v for v in variants if v.endswith("_person")],
    ]
    settings = (
        "",
        " Rougher joint tracks (noise_px 6):",
        " Silhouettes of another body, keypoints off the joints, 6 px (OTHER):",
        " Another person seen (PERSON):",
    )
    text = ""
    swing_title = f"Over the swing (to the end of the follow-through + {args.tail_s:g} s):"
    for group, setting in zip(groups, settings):
        if group:
            text += (
                table(span, group, f"{setting} {swing_title}".strip())
                + "\n"
                + table(whole, group, f"{setting} Over the whole clip:".strip())
                + "\n"
                + table(last, group, f"{setting} Over the last sixth of the clip:".strip())
                + "\n"
            )
    text += seed_table(seed_span, seeds, args.tail_s) + paired_table(seed_span, seeds, args.tail_s)
    text = (
        text
        + "Frames (whole clip / swing): "
        + ", ".join(f"{s} {f}" for s, f in frames.items())
        + "\n\n"
        + f"Seeds: {', '.join(map(str, seeds))} (each swing's figures: the mean over them)\n\n"
        + "Mean fps (whole run, `seconds` of metrics.json): "
        + ", ".join(f"{v} {np.mean(x):.1f}" for v, x in fps.items() if x)
        + "\n"
    )
    (out / "results.md").write_text(text, encoding="utf-8")
    (out / "results.json").write_text(
        json.dumps(
            {"seeds": seeds, "span": span, "whole": whole, "last_sixth": last},
            indent=1,
        )
        + "\n"
    )
    print(text)
    if args.plot:
        plot(out / "pca" / args.plot, REPO / "docs" / "golf_swing.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
