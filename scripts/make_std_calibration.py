"""Make `ptrack/data/batch_std_calibration.json`: the calibration of `method: batch`'s `joint_std`.

    ptrack evaluate configs/eval_batch.yaml batch.std_calibration=false --clips configs/clips/dev.txt --out A
    ptrack evaluate configs/eval_batch.yaml batch.std_calibration=false keyframes.every_s=null \\
        keyframes.last=true --clips configs/clips/dev.txt --out B
    python scripts/make_std_calibration.py A B [--mode branches] [--target 0.95] [--out FILE]
    (and the same with batch.uncertainty=laplace in both evaluations and --mode laplace)

The raw std (the Laplace approximation at the solution plus the flip branches, `batch.std_calibration=false`)
is overconfident: on the dev clips 0.78-0.82 of joint-frames lie within 2 std where a calibrated one puts 0.95.
Its variance is that of the model the solve assumes (2D noise of `costs.sigma_px`, the smoothing prior's
scales, the branches the flips reach), and the errors come mostly from what that model leaves out (depth
drift between keyframes, faster motion than the prior's). The fix is a variance factor and a floor,
var' = scale^2 var + floor^2: the scale as a posterior variance factor (the classical residual chi^2 per
degree of freedom, here measured against the truth, since the 2D residuals fit their assumed noise and
show none of the depth error), the floor (metres) for the error no term's curvature sees. Fitted on the
runs given (every result.npz under the folders: the dev clips in both keyframe settings), each run weighted
equally: for each floor of `FLOORS_M` the scale that puts `--target` of the joint-frames within 2 calibrated
std (bisection), and of those floors the one whose leave-one-clip-out interval score is lowest (sharpness
subject to calibration: a constant std of 80 mm also covers 0.95 and says nothing about which joint-frames
are wrong; the interval score prices the width of the bound and each error beyond it). Prints the score per
floor, each run's shares within 1, 2, 3 std before and after, and the leave-one-clip-out coverage.
"""

from __future__ import annotations

import argparse
import json
from datetime import date
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

#: floors tried (metres)
FLOORS_M = (0.0, 0.01, 0.02, 0.03, 0.04, 0.05, 0.06, 0.07, 0.08)


def load_runs(folders: list[str]) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, error (T, J) m, std (T, J) m) of every result.npz under the folders that has joint_std and the
    ground truth."""
    runs = []
    for folder in folders:
        for path in sorted(Path(folder).rglob("result.npz")):
            with np.load(path) as z:
                if "joint_std" not in z or "gt_joints" not in z:
                    continue
                err = np.linalg.norm(z["joints"] - z["gt_joints"], axis=-1)
                name = f"{Path(folder).name}/{path.parent.relative_to(folder).as_posix()}"
                runs.append((name, err, z["joint_std"].astype(np.float64)))
    return runs


def coverage(err: np.ndarray, std: np.ndarray, scale: float, floor: float, k: float) -> float:
    """Share of joint-frames with error <= k sqrt(scale^2 std^2 + floor^2)."""
    return float((err <= k * np.sqrt((scale * std) ** 2 + floor**2)).mean())


def pooled(runs, scale: float, floor: float, k: float) -> float:
    """Mean over the runs (each weighted equally) of the share within k calibrated std."""
    return float(np.mean([coverage(e, s, scale, floor, k) for _, e, s in runs]))


def scale_for(runs, floor: float, target: float) -> float:
    """The scale that puts `target` of the joint-frames within 2 std at this floor (bisection; 0 if the
    floor alone covers more)."""
    lo, hi = 0.0, 20.0
    if pooled(runs, lo, floor, 2.0) >= target:
        return 0.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if pooled(runs, mid, floor, 2.0) >= target else (mid, hi)
    return hi


def interval_score(runs, scale: float, floor: float, target: float) -> float:
    """Mean over the runs of the interval score (Gneiting & Raftery 2007) of the bound 2 calibrated std on
    the error at level `target`: 2 std + (1 / (1 - target)) * (error - 2 std, where positive), metres. Lower
    is better: narrow bounds, and few errors beyond them, each priced by how far."""
    out = []
    for _, err, std in runs:
        bound = 2.0 * np.sqrt((scale * std) ** 2 + floor**2)
        out.append(float((bound + np.maximum(err - bound, 0.0) / (1.0 - target)).mean()))
    return float(np.mean(out))


def loco_fits(runs, floor: float, target: float) -> dict[str, float]:
    """{clip: the scale fitted at this floor on the other clips' runs}."""
    clips = sorted({clip_of(n) for n, _, _ in runs})
    return {c: scale_for([r for r in runs if clip_of(r[0]) != c], floor, target) for c in clips}


def loco_score(runs, floor: float, target: float) -> float:
    """The interval score of each clip's runs under the scale fitted without that clip, averaged."""
    fits = loco_fits(runs, floor, target)
    return float(np.mean([interval_score([r], fits[clip_of(r[0])], floor, target) for r in runs]))


def fit(runs, target: float) -> tuple[float, float]:
    """(scale, floor m): the floor of `FLOORS_M` whose leave-one-clip-out interval score is lowest, and the
    scale that puts `target` of every run's joint-frames within 2 std at that floor."""
    floor = min(FLOORS_M, key=lambda f: loco_score(runs, f, target))
    return scale_for(runs, floor, target), floor


def clip_of(name: str) -> str:
    """The clip of a run's name (`<evaluation folder>/02_01` or `.../02_01/seed-0`)."""
    return Path(name).parts[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="+", help="evaluation folders of raw-std runs (batch.std_calibration=false)")
    ap.add_argument("--mode", default="branches", choices=("branches", "laplace"), help="the runs' batch.uncertainty")
    ap.add_argument("--target", type=float, default=0.95, help="share of joint-frames within 2 calibrated std")
    ap.add_argument("--out", default=str(ROOT / "ptrack" / "data" / "batch_std_calibration.json"))
    args = ap.parse_args()
    runs = load_runs(args.folders)
    if not runs:
        raise SystemExit("no result.npz with joint_std and gt_joints under the folders given")
    print("floor mm | scale | interval score mm, in-sample | leave-one-clip-out")
    for f in FLOORS_M:
        sc = scale_for(runs, f, args.target)
        print(
            f"{1000 * f:.0f} | {sc:.3f} | {1000 * interval_score(runs, sc, f, args.target):.0f} | "
            f"{1000 * loco_score(runs, f, args.target):.0f}"
        )
    scale, floor = fit(runs, args.target)
    print(f"{len(runs)} runs: scale {scale:.3f}, floor {1000 * floor:.0f} mm")
    loco = loco_fits(runs, floor, args.target)
    print("run | within 1 / 2 / 3 std, raw | calibrated | calibrated without the run's clip (2 std)")
    for name, err, std in runs:
        raw = [coverage(err, std, 1.0, 0.0, k) for k in (1, 2, 3)]
        cal = [coverage(err, std, scale, floor, k) for k in (1, 2, 3)]
        print(
            f"{name} | {raw[0]:.3f} / {raw[1]:.3f} / {raw[2]:.3f} | {cal[0]:.3f} / {cal[1]:.3f} / {cal[2]:.3f} | "
            f"{coverage(err, std, loco[clip_of(name)], floor, 2.0):.3f}"
        )
    for k in (1, 2, 3):
        raw_k, cal_k = pooled(runs, 1.0, 0.0, k), pooled(runs, scale, floor, k)
        print(f"mean within {k} std: raw {raw_k:.3f}, calibrated {cal_k:.3f}")
    loco_mean = float(np.mean([coverage(e, s, loco[clip_of(n)], floor, 2.0) for n, e, s in runs]))
    print(f"leave-one-clip-out, within 2 std: {loco_mean:.3f}")
    out = Path(args.out)
    doc = json.loads(out.read_text(encoding="utf-8")) if out.is_file() else {}
    doc.update(
        {
            "description": "Calibration of method: batch's joint_std per batch.uncertainty mode: std' = "
            "sqrt((scale * std)^2 + floor_m^2), std the raw standard deviation at the solution; scale fitted so "
            "that the share of joint-frames within 2 std is target_within_2std on the runs listed, floor_m by a "
            "leave-one-clip-out interval score (ptrack.estimators.batch.uncertainty.calibrate_std).",
            "made_by": "scripts/make_std_calibration.py",
        }
    )
    doc[args.mode] = {
        "date": date.today().isoformat(),
        "runs": sorted(n for n, _, _ in runs),
        "target_within_2std": args.target,
        "scale": round(scale, 4),
        "floor_m": round(floor, 4),
    }
    out.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
