"""Synthetic detector footage with known truth (`scripts/synthetic_footage.py`: a COCO-17 results JSON of a CMU
clip seen 5 m away, 2 px noise, face keypoints at score 0, a bystander, an empty image, an OpenCV YAML with
intrinsics only), reconstructed three ways, each with the clip skeleton's standing height:

    template  the CMU template (data.asf = subject 10) scaled to the height with Winter's proportions
    observed  `subject.lengths=observed`: limb and trunk lengths measured in the 2D, then the run again
    known     `subject.lengths=asf data.asf=<the clip's asf>`: the clip's own skeleton, as a known-skeleton bound

For each clip a markdown table: PA-MPJPE and MPJPE (mid-hip aligned) of the 12 body keypoints, mm
(`synthetic_footage.score`), the MPJPE's difference from the known-skeleton run, and each measured segment's
length in the run's model against the clip skeleton's own (`ptrack.body.subject.segment_lengths`), % error.

Clip groups (`--clips`):

    tune   10_02 (kick, subject 10 = the template's), 02_01 (walk), 49_18 (one-leg balance): used while developing
    check  07_05 (walk, subject 7), 35_01 (walk), 02_05 (punch), 49_19 (balance), 135_04 (kick): never tuned on

    python scripts/eval_synthetic_footage.py [--clips tune|check|all|NN_MM,...] [--out logs/eval_synthetic]
        [--frames 60] [--noise-px 2] [--seed 0] [--keypoints coco17|halpe26] [--extrinsics] [--mirror A-B]
        [key=value ...]

`--mirror 25-39`: the participant's detections in images 25..39 labelled mirrored (every left/right label exchanged,
the fault of a detector that takes the person for one facing the other way).

`--keypoints halpe26` (the feet, neck and pelvis seen as well) and `--extrinsics` (the camera's pose given: the runs
get `camera.up=y` and the footage's `camera.floor_m`) make footage closer to a lab's (the Pose2Sim trial's BODY_25B
and calibration); the issue's synthetic target is the default, COCO-17 with intrinsics only.

Extra key=value arguments go to every run. Existing footage and run folders (under OUT/<clip>-s<seed>[-halpe26]
[-extrinsics]/) are reused.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import synthetic_footage  # scripts/ (this script's folder)

from ptrack.body.skeleton import Skeleton
from ptrack.body.subject import add_landmark_joints, segment_lengths

REPO = Path(__file__).resolve().parents[1]
CMU = REPO.parent / "shared" / "data" / "cmu" / "subjects"
GROUPS = {
    "tune": {"10_02": "kick", "02_01": "walk", "49_18": "balance"},
    "check": {"07_05": "walk", "35_01": "walk", "02_05": "punch", "49_19": "balance", "135_04": "kick"},
}
GROUPS["all"] = {**GROUPS["tune"], **GROUPS["check"]}
#: the segments `subject.lengths: observed` measures (ptrack.pipeline.run.MEASURED_SEGMENTS)
MEASURED = ("thigh", "shank", "upper_arm", "forearm", "trunk")
SETTINGS = ("template", "observed", "known")


def clip_files(clip: str) -> tuple[Path, Path]:
    """ "NN_MM" -> (its AMC, its subject's ASF)."""
    subject = clip.split("_")[0]
    return CMU / subject / f"{clip}.amc", CMU / subject / f"{subject}.asf"


def run(setting: str, footage: Path, asf: Path, height: float, out: Path, seed: int, extra: list[str]) -> int:
    """One run of configs/video.yaml into `out` (reused when its result.npz exists) -> exit status."""
    if (out / "result.npz").is_file():
        return 0
    cmd = [sys.executable, "-m", "ptrack.cli", "run", str(REPO / "configs" / "video.yaml")]
    cmd += [f"observations.file={footage / 'keypoints.json'}", f"camera.file={footage / 'camera.yml'}"]
    cmd += [f"subject.height_m={height:.6f}", "observations.fps=30", f"seed={seed}", f"out_dir={out}", "progress=false"]
    cmd += {
        "template": ["subject.lengths=template"],  # configs/video.yaml measures them by default
        "observed": ["subject.lengths=observed"],
        "known": ["subject.lengths=asf", f"data.asf={asf}"],
    }[setting]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([*cmd, *extra], cwd=REPO, env=env, stdout=sys.stderr).returncode  # tables alone on stdout


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--clips", default="tune", help="tune, check, all or a comma-separated list of NN_MM")
    ap.add_argument("--out", type=Path, default=Path("logs/eval_synthetic"))
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--noise-px", type=float, default=2.0)
    ap.add_argument("--seed", type=int, default=0, help="the footage's noise and the runs' seed")
    ap.add_argument("--keypoints", choices=synthetic_footage.KEYPOINT_SETS, default="coco17")
    ap.add_argument("--extrinsics", action="store_true", help="the camera's pose and the floor given to the runs")
    ap.add_argument(
        "--mirror",
        type=synthetic_footage.image_range,
        default=None,
        metavar="A-B",
        help="the participant labelled mirrored in images A..B (a detector's fault)",
    )
    ap.add_argument("overrides", nargs="*")
    a = ap.parse_args()
    clips = list(GROUPS[a.clips]) if a.clips in GROUPS else a.clips.split(",")
    variant = ("" if a.keypoints == "coco17" else f"-{a.keypoints}") + ("-extrinsics" if a.extrinsics else "")
    variant += f"-mirror{a.mirror[0]}-{a.mirror[1]}" if a.mirror else ""
    for clip in clips:
        amc, asf = clip_files(clip)
        if not amc.is_file() or not asf.is_file():
            sys.exit(f"eval_synthetic_footage: {amc} or {asf} not found")
        folder = a.out.resolve() / f"{clip}-s{a.seed}{variant}"
        footage = folder / "footage"
        if not (footage / "truth.npz").is_file():
            synthetic_footage.make(
                amc,
                asf,
                footage,
                a.frames,
                noise_px=a.noise_px,
                seed=a.seed,
                keypoints=a.keypoints,
                extrinsics=a.extrinsics,
                mirrored=a.mirror,
            )
        with np.load(footage / "truth.npz") as t:
            height = float(t["height_m"])
            camera = ["camera.up=y", f"camera.floor_m={float(t['floor_m']):.6f}"] if a.extrinsics else []
        own = segment_lengths(add_landmark_joints(Skeleton.from_asf(asf), height))
        rows = {}
        for setting in SETTINGS:
            rc = run(setting, footage, asf, height, folder / setting, a.seed, [*camera, *a.overrides])
            if rc != 0:
                rows[setting] = None
                continue
            score = synthetic_footage.score(folder / setting / "result.npz", footage / "truth.npz")
            lengths = json.loads((folder / setting / "metrics.json").read_text())["bone_lengths"]
            rows[setting] = (score, {n: 100 * (lengths[n]["length_m"] / own[n] - 1) for n in MEASURED})
        kind = GROUPS["all"].get(clip, "")
        print(
            f"\n{clip} {kind} ({'tune' if clip in GROUPS['tune'] else 'check'}; height {height:.3f} m, "
            f"{a.frames} frames, {a.noise_px:g} px, seed {a.seed}, {a.keypoints}"
            f"{', extrinsics' if a.extrinsics else ''})\n"
        )
        print(
            "| setting | PA-MPJPE mm | MPJPE mm | MPJPE - known mm | " + " | ".join(f"{n} %" for n in MEASURED) + " |"
        )
        print("|---|---|---|---|" + "---|" * len(MEASURED))
        known = rows["known"][0]["mpjpe_mm"] if rows["known"] else float("nan")
        for setting, row in rows.items():
            if row is None:
                print(f"| {setting} | run failed | | |" + " |" * len(MEASURED))
                continue
            s, err = row
            cells = " | ".join(f"{err[n]:+.1f}" for n in MEASURED)
            print(
                f"| {setting} | {s['pa_mpjpe_mm']:.1f} | {s['mpjpe_mm']:.1f} | {s['mpjpe_mm'] - known:+.1f} | {cells} |"
            )
        sys.stdout.flush()


if __name__ == "__main__":
    main()
