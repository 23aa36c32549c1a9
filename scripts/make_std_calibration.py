"""Make `ptrack/data/batch_std_calibration.json`: the calibration of `method: batch`'s `joint_std`.

    E="ptrack evaluate configs/eval_batch.yaml batch.std_calibration=false --seeds 0-1"
    FL="keyframes.every_s=null keyframes.last=true"
    $E --clips configs/clips/dev.txt --out A/dev_every1
    $E $FL --clips configs/clips/dev.txt --out A/dev_firstlast
    $E --clips configs/clips/train.txt --out A/train_every1
    $E $FL --clips configs/clips/train.txt --out A/train_firstlast
    python scripts/make_std_calibration.py A/dev_every1 A/dev_firstlast A/train_every1 A/train_firstlast \\
        [--mode branches] [--target 0.95] [--out FILE]
    (and the same with batch.uncertainty=laplace in the evaluations and --mode laplace)

    python scripts/make_std_calibration.py --report [--mode branches] [--calibration FILE] ... FOLDER ...

The raw std (the Laplace approximation at the solution plus the flip branches, `batch.std_calibration=false`)
is overconfident: on the dev clips 0.78-0.82 of joint-frames lie within 2 std where a calibrated one puts 0.95.
Its variance is that of the model the solve assumes (2D noise of `costs.sigma_px`, the smoothing prior's
scales, the branches the flips reach), and the errors come mostly from what that model leaves out: depth drift
away from the keyframes, largest where a joint has moved far from where a keyframe put it. The calibration is

    var' = scale^2 var + floor^2 + (travel m)^2

with m (metres) the joint's distance from its own position at the nearest keyframe before or after the frame
(the smaller; `ptrack.estimators.batch.keyframe_travel`, from the solution, so known at run time): the scale as
a posterior variance factor (measured against the truth, since the 2D residuals fit their assumed noise and
show none of the depth error), the floor for the error no term's curvature sees, travel the share of a joint's
travel that drifts. Fitted on the runs given (every result.npz under the folders: the dev and train clips,
never the held-out ones, in both keyframe settings; the keyframes' frames from each run's config.yaml), each run
weighted equally: for each
(floor, travel) of `FLOORS_M` x `TRAVELS` the scale that puts `--target` of the joint-frames within 2
calibrated std (a weighted quantile), and of those the pair whose leave-one-clip-out interval score is
lowest (sharpness subject to calibration: a constant std of 80 mm also covers 0.95 and says nothing about which
joint-frames are wrong; the interval score prices the width of the bound and each error beyond it). Prints
the score per pair, each run's shares within 1, 2, 3 std before and after, and the leave-one-clip-out
coverage. `--travel 0` fits the constant-floor calibration of before (travel 0, as shipped until 2026-11-29).

`--report` fits nothing: for each calibration file given (default: the shipped one) it prints each run's
shares within 1, 2, 3 calibrated std and its interval score, and their means per folder (per seed too), for
runs the calibration was not fitted on (held-out clips; runs of `batch.std_calibration=false`).
"""

from __future__ import annotations

import argparse
import json
import subprocess
from dataclasses import dataclass
from datetime import date
from pathlib import Path

import numpy as np
import torch
import yaml

from ptrack.estimators.batch import StdCalibration, calibrate_std, keyframe_travel
from ptrack.pipeline.keyframes import keyframe_frames

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "ptrack" / "data" / "batch_std_calibration.json"

#: floors tried (metres)
FLOORS_M = (0.0, 0.01, 0.02, 0.03, 0.04, 0.05, 0.06, 0.07, 0.08)
#: travel shares tried (metres of std per metre of a joint's travel from its nearest keyframe)
TRAVELS = (0.0, 0.02, 0.03, 0.05, 0.07, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35, 0.4)


@dataclass(frozen=True)
class Run:
    """One result.npz: name `<folder>/<clip>[/seed-N]`; err, std, travel (T, J) metres."""

    name: str
    err: np.ndarray
    std: np.ndarray
    travel: np.ndarray


def run_keyframes(run_dir: Path, times: np.ndarray) -> torch.Tensor:
    """(F,) the frames of a ground-truth-keyframe evaluation run's keyframes (its config.yaml's keyframes.*)."""
    cfg = yaml.safe_load((run_dir / "config.yaml").read_text(encoding="utf-8"))
    kc, bc = cfg["keyframes"], cfg.get("batch", {})
    if kc.get("file") or bc.get("upsample", 1) != 1:
        raise SystemExit(f"{run_dir}: runs with keyframes.file or batch.upsample are not supported")
    return keyframe_frames(torch.from_numpy(times), kc["every_s"], kc["last"], kc.get("first", True))


def load_runs(folders: list[str]) -> list[Run]:
    """Every result.npz under the folders that has joint_std and the ground truth."""
    runs = []
    for folder in folders:
        for path in sorted(Path(folder).rglob("result.npz")):
            if any(p.startswith(".") for p in path.relative_to(folder).parts):
                continue  # a run in progress (`ptrack evaluate`'s .CLIP.partial)
            with np.load(path) as z:
                if "joint_std" not in z or "gt_joints" not in z:
                    continue
                joints = z["joints"].astype(np.float64)
                err = np.linalg.norm(joints - z["gt_joints"], axis=-1)
                frames = run_keyframes(path.parent, z["times"])
                travel = keyframe_travel(torch.from_numpy(joints), frames).numpy()
                name = f"{Path(folder).name}/{path.parent.relative_to(folder).as_posix()}"
                runs.append(Run(name, err, z["joint_std"].astype(np.float64), travel))
    return runs


def calibrated(run: Run, cal: StdCalibration) -> np.ndarray:
    """The run's std under the calibration (`calibrate_std`, as the estimator applies it)."""
    return calibrate_std(torch.from_numpy(run.std), cal, torch.from_numpy(run.travel)).numpy()


def coverage(run: Run, cal: StdCalibration, k: float) -> float:
    """Share of the run's joint-frames with error <= k calibrated std."""
    return float((run.err <= k * calibrated(run, cal)).mean())


def pooled(runs: list[Run], cal: StdCalibration, k: float) -> float:
    """Mean over the runs (each weighted equally) of the share within k calibrated std."""
    return float(np.mean([coverage(r, cal, k) for r in runs]))


def scale_for(runs: list[Run], floor: float, travel: float, target: float) -> float:
    """The least scale that puts `target` of the joint-frames (each run weighted equally) within 2 std at this
    floor and travel (0 if the floor and travel alone cover that much). A joint-frame is covered from the scale
    sqrt(max(err^2 / 4 - floor^2 - (travel m)^2, 0)) / std on, so the scale is a weighted quantile of those."""
    need, weight = [], []
    for r in runs:
        excess = np.maximum(0.25 * r.err**2 - floor**2 - (travel * r.travel) ** 2, 0.0)
        need.append((np.sqrt(excess) / np.maximum(r.std, 1e-12)).ravel())
        weight.append(np.full(r.err.size, 1.0 / (r.err.size * len(runs))))
    order = np.argsort(np.concatenate(need), kind="stable")
    cum = np.cumsum(np.concatenate(weight)[order])
    i = int(np.searchsorted(cum, target - 1e-12))
    return float(np.concatenate(need)[order][min(i, order.size - 1)]) * (1.0 + 1e-9)


def interval_score(runs: list[Run], cal: StdCalibration, target: float) -> float:
    """Mean over the runs of the interval score (Gneiting & Raftery 2007) of the bound 2 calibrated std on
    the error at level `target`: 2 std + (1 / (1 - target)) * (error - 2 std, where positive), metres. Lower
    is better: narrow bounds, and few errors beyond them, each priced by how far."""
    out = []
    for r in runs:
        bound = 2.0 * calibrated(r, cal)
        out.append(float((bound + np.maximum(r.err - bound, 0.0) / (1.0 - target)).mean()))
    return float(np.mean(out))


def clip_of(name: str) -> str:
    """The clip of a run's name (`<evaluation folder>/02_01` or `.../02_01/seed-0`)."""
    return Path(name).parts[1]


def loco_fits(runs: list[Run], floor: float, travel: float, target: float) -> dict[str, StdCalibration]:
    """{clip: the calibration fitted at this floor and travel on the other clips' runs}."""
    clips = sorted({clip_of(r.name) for r in runs})
    out = {}
    for c in clips:
        rest = [r for r in runs if clip_of(r.name) != c]
        out[c] = StdCalibration(scale_for(rest, floor, travel, target), floor, travel)
    return out


def loco_score(runs: list[Run], floor: float, travel: float, target: float) -> float:
    """The interval score of each clip's runs under the scale fitted without that clip, averaged."""
    fits = loco_fits(runs, floor, travel, target)
    return float(np.mean([interval_score([r], fits[clip_of(r.name)], target) for r in runs]))


def fit(runs: list[Run], target: float, travels: tuple[float, ...] = TRAVELS) -> tuple[StdCalibration, list]:
    """The (floor, travel) of `FLOORS_M` x travels whose leave-one-clip-out interval score is lowest, and the
    scale that puts `target` of every run's joint-frames within 2 std there; and the table of every pair
    [(floor, travel, scale, in-sample score, leave-one-clip-out score)]."""
    table = []
    for f in FLOORS_M:
        for c in travels:
            sc = scale_for(runs, f, c, target)
            score = interval_score(runs, StdCalibration(sc, f, c), target)
            table.append((f, c, sc, score, loco_score(runs, f, c, target)))
    f, c, sc, _, _ = min(table, key=lambda row: row[4])
    return StdCalibration(sc, f, c), table


def shares(run: Run, cal: StdCalibration) -> str:
    return " / ".join(f"{coverage(run, cal, k):.3f}" for k in (1, 2, 3))


def report(runs: list[Run], cals: dict[str, StdCalibration], target: float) -> None:
    """Per run and per folder (and seed): within 1 / 2 / 3 std and the interval score under each calibration."""
    print("run | " + " | ".join(f"{n}: within 1 / 2 / 3 std, interval score mm" for n in cals))
    for r in runs:
        cells = [f"{shares(r, c)}, {1000 * interval_score([r], c, target):.0f}" for c in cals.values()]
        print(f"{r.name} | " + " | ".join(cells))
    groups: dict[str, list[Run]] = {}
    for r in runs:
        parts = Path(r.name).parts
        groups.setdefault(parts[0], []).append(r)
        if len(parts) > 2:
            groups.setdefault(f"{parts[0]} {parts[2]}", []).append(r)
    for g, rs in groups.items():
        for n, c in cals.items():
            within = " / ".join(f"{pooled(rs, c, k):.3f}" for k in (1, 2, 3))
            std = np.mean([calibrated(r, c).mean() for r in rs])
            print(
                f"{g} ({len(rs)} runs), {n}: within 1 / 2 / 3 std {within}, interval score "
                f"{1000 * interval_score(rs, c, target):.0f} mm, mean std {1000 * std:.0f} mm"
            )


def commit() -> str:
    """The repository's commit (short), with `+` if the working tree has changes: what the fit ran at."""
    git = ["git", "-C", str(ROOT)]
    head = subprocess.run([*git, "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    dirty = subprocess.run([*git, "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True)
    return head + ("+" if dirty.stdout.strip() else "")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="+", help="evaluation folders of raw-std runs (batch.std_calibration=false)")
    ap.add_argument("--mode", default="branches", choices=("branches", "laplace"), help="the runs' batch.uncertainty")
    ap.add_argument("--target", type=float, default=0.95, help="share of joint-frames within 2 calibrated std")
    ap.add_argument("--travel", type=float, nargs="*", default=None, help="travel shares to try (default TRAVELS)")
    ap.add_argument("--out", default=str(DATA))
    ap.add_argument("--report", action="store_true", help="fit nothing: report the calibrations on the runs")
    ap.add_argument(
        "--calibration",
        action="append",
        help="with --report: a calibration file (repeat for more; default the shipped)",
    )
    args = ap.parse_args()
    runs = load_runs(args.folders)
    if not runs:
        raise SystemExit("no result.npz with joint_std and gt_joints under the folders given")
    if args.report:
        cals = {}
        for path in args.calibration or [str(DATA)]:
            entry = json.loads(Path(path).read_text(encoding="utf-8"))[args.mode]
            cals[Path(path).stem] = StdCalibration(entry["scale"], entry["floor_m"], entry.get("travel", 0.0))
        cals["raw"] = StdCalibration(1.0, 0.0, 0.0)
        report(runs, cals, args.target)
        return
    cal, table = fit(runs, args.target, TRAVELS if args.travel is None else tuple(args.travel))
    print("floor mm | travel | scale | interval score mm, in-sample | leave-one-clip-out")
    for f, c, sc, ins, loco in table:
        print(f"{1000 * f:.0f} | {c:.2f} | {sc:.3f} | {1000 * ins:.0f} | {1000 * loco:.0f}")
    print(f"{len(runs)} runs: scale {cal.scale:.3f}, floor {1000 * cal.floor_m:.0f} mm, travel {cal.travel:.2f}")
    loco = loco_fits(runs, cal.floor_m, cal.travel, args.target)
    print("run | within 1 / 2 / 3 std, raw | calibrated | calibrated without the run's clip (2 std)")
    raw = StdCalibration(1.0, 0.0, 0.0)
    for r in runs:
        print(f"{r.name} | {shares(r, raw)} | {shares(r, cal)} | {coverage(r, loco[clip_of(r.name)], 2.0):.3f}")
    for k in (1, 2, 3):
        print(f"mean within {k} std: raw {pooled(runs, raw, k):.3f}, calibrated {pooled(runs, cal, k):.3f}")
    for folder in sorted({Path(r.name).parts[0] for r in runs}):
        rs = [r for r in runs if Path(r.name).parts[0] == folder]
        print(
            f"{folder}: within 2 std calibrated {pooled(rs, cal, 2.0):.3f}, leave-one-clip-out "
            f"{np.mean([coverage(r, loco[clip_of(r.name)], 2.0) for r in rs]):.3f}"
        )
    loco_mean = float(np.mean([coverage(r, loco[clip_of(r.name)], 2.0) for r in runs]))
    print(f"leave-one-clip-out, within 2 std: {loco_mean:.3f}")
    out = Path(args.out)
    doc = json.loads(out.read_text(encoding="utf-8")) if out.is_file() else {}
    doc.update(
        {
            "description": "Calibration of method: batch's joint_std per batch.uncertainty mode: std' = "
            "sqrt((scale * std)^2 + floor_m^2 + (travel * m)^2), std the raw standard deviation at the solution, "
            "m the joint's distance (metres) from its position at the nearest keyframe before or after "
            "(keyframe_travel); floor_m and travel by the lowest leave-one-clip-out interval score, scale so that "
            "the share of joint-frames within 2 std is target_within_2std on the runs listed "
            "(ptrack.estimators.batch.uncertainty.calibrate_std).",
            "made_by": "scripts/make_std_calibration.py",
        }
    )
    doc[args.mode] = {
        "date": date.today().isoformat(),
        "made_with": f"scripts/make_std_calibration.py {' '.join(Path(f).name for f in args.folders)} "
        f"--mode {args.mode} on raw-std runs (`ptrack evaluate configs/eval_batch.yaml batch.std_calibration=false "
        f"batch.uncertainty={args.mode}`, keyframes every 1 s and first + last: keyframes.every_s=null "
        f"keyframes.last=true; the folders' names say which clip list) at {commit()}",
        "runs": sorted(r.name for r in runs),
        "target_within_2std": args.target,
        "scale": round(cal.scale, 4),
        "floor_m": round(cal.floor_m, 4),
        "travel": round(cal.travel, 4),
    }
    out.write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
