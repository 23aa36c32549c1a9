"""Golf from a detector's keypoint file, leave-one-swing-out: each swing of configs/clips/golf.txt made into
detector-like footage (`synthetic_footage.py`: HALPE-26 results JSON, 2 px noise, the face at score 0, a smaller
bystander in every third image, one image with nobody, an OpenCV camera with intrinsics only, 30 fps, the whole
clip) and reconstructed the way a user with a golf video and a detector would:

    pca     `ptrack run configs/golf.yaml observations.file=... camera.file=... subject.height_m=H
            observations.silhouettes=false motion.model_file=<the other swings' model>` (no silhouettes: a detector
            gives none; the limbs and the trunk measured in the 2D, configs/golf.yaml's `subject.lengths: observed`)
    pca_template  the same on the height's proportions (`subject.lengths=template`)
    pca_asf the same with the swing's own skeleton (`subject.lengths=asf`: subject 64's ASF, as
            scripts/eval_golf.py tracks it): what the body's proportions cost
    kjs     `ptrack run configs/video.yaml observations.file=... camera.file=... subject.height_m=H` (the
            real-footage defaults, no motion model)

Scored by `synthetic_footage.score` over the 12 body keypoints (shoulders to ankles): MPJPE after aligning the
mid-hips, and PA-MPJPE, mm, over the whole clip. The height given is the skeleton's own standing height.

    python scripts/eval_golf_footage.py [--out logs/eval_golf_footage] [--seed 0]
        [--methods pca,pca_template,pca_asf,kjs]

Runs go to <out>/<method>/<swing>-s<seed>/ and are reused when their result.npz exists.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np
import synthetic_footage

from ptrack.body.acclaim import skeleton_beside
from ptrack.body.skeleton import Skeleton, load_amc
from ptrack.clips import parse_clips
from ptrack.motion.motion_model import fit_motion_model, read_clips, save_motion_model
from ptrack.pipeline.config import load_config

REPO = Path(__file__).resolve().parents[1]
CLIPS = REPO / "configs" / "clips" / "golf.txt"
#: the pca variants' `subject.lengths` (plain `pca`: configs/golf.yaml's, observed)
LENGTHS = {"pca_template": "template", "pca_asf": "asf"}


def swings() -> list[Path]:
    """The golf swings' AMC files (configs/clips/golf.txt)."""
    return parse_clips(str(CLIPS))


def model_without(swing: Path, out: Path) -> Path:
    """The motion model of every swing but `swing` (configs/golf.yaml's `motion:` settings), made once."""
    path = out / "models" / f"wo_{swing.stem}.npz"
    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        cfg = load_config(REPO / "configs" / "golf.yaml", [])
        save_motion_model(fit_motion_model(read_clips([s for s in swings() if s != swing]), cfg.motion), path)
    return path


def run(config: str, footage: Path, height: float, out: Path, extra: list[str]) -> int:
    """`ptrack run configs/<config>` on the footage into `out` (reused when done) -> exit status."""
    if (out / "result.npz").is_file():
        return 0
    cmd = [sys.executable, "-m", "ptrack.cli", "run", str(REPO / "configs" / config)]
    cmd += [f"observations.file={footage / 'keypoints.json'}", f"camera.file={footage / 'camera.yml'}"]
    cmd += [f"subject.height_m={height:.6f}", "observations.fps=30", f"out_dir={out}", "progress=false", *extra]
    return subprocess.run(cmd, cwd=REPO, stdout=sys.stderr).returncode


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=REPO / "logs" / "eval_golf_footage")
    ap.add_argument("--seed", type=int, default=0, help="the footage's noise and the runs' seed")
    ap.add_argument("--methods", default="pca,pca_template,pca_asf,kjs")
    args = ap.parse_args()
    methods = args.methods.split(",")
    unknown = sorted(set(methods) - {"pca", "kjs", *LENGTHS})
    if unknown:
        ap.error(f"unknown method(s) {', '.join(unknown)}: pca, {', '.join(LENGTHS)}, kjs")
    rows: dict[str, dict[str, tuple[float, float]]] = {}
    for swing in swings():
        name = swing.stem
        footage = args.out / "footage" / f"{name}-s{args.seed}"
        if not (footage / "truth.npz").is_file():
            asf = skeleton_beside(swing)
            assert asf is not None  # the CMU swings' folder holds 64.asf
            frames = load_amc(swing, Skeleton.from_asf(asf)).q.shape[0] // 4  # the whole clip at 30 fps
            synthetic_footage.make(swing, asf, footage, frames, keypoints="halpe26", seed=args.seed)
        with np.load(footage / "truth.npz") as t:
            height = float(t["height_m"])
        rows[name] = {}
        for method in methods:
            out = args.out / method / f"{name}-s{args.seed}"
            if method.startswith("pca"):
                extra = ["observations.silhouettes=false", f"motion.model_file={model_without(swing, args.out)}"]
                extra += [f"subject.lengths={LENGTHS[method]}"] if method in LENGTHS else []
                rc = run("golf.yaml", footage, height, out, [*extra, f"seed={args.seed}"])
            else:
                rc = run("video.yaml", footage, height, out, [f"seed={args.seed}"])
            if rc != 0:
                print(f"{name} {method}: the run failed ({rc})", file=sys.stderr)
                rows[name][method] = (float("nan"), float("nan"))
                continue
            s = synthetic_footage.score(out / "result.npz", footage / "truth.npz")
            rows[name][method] = (s["mpjpe_mm"], s["pa_mpjpe_mm"])
            print(name, method, f"{s['mpjpe_mm']:.1f} / {s['pa_mpjpe_mm']:.1f}", file=sys.stderr, flush=True)
    print(f"| swing (seed {args.seed}) | " + " | ".join(f"{m} MPJPE / PA-MPJPE mm" for m in methods) + " |")
    print("|---|" + "---|" * len(methods))
    for name, r in rows.items():
        print(f"| {name} | " + " | ".join(f"{r[m][0]:.1f} / {r[m][1]:.1f}" for m in methods) + " |")
    means = [
        (statistics.fmean(r[m][0] for r in rows.values()), statistics.fmean(r[m][1] for r in rows.values()))
        for m in methods
    ]
    print("| **mean** | " + " | ".join(f"**{a:.1f} / {b:.1f}**" for a, b in means) + " |")


if __name__ == "__main__":
    main()
