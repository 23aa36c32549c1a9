"""Real footage against its 3D reference: the Pose2Sim balancing trial (../shared/data/pose2sim), each camera
on its own.

For each camera (cam01, cam02): `ptrack run configs/video.yaml` on its OpenPose BODY_25B folder with the
calibration and the participant's height (1.72 m, the session's own config), then the 12 body keypoints
(shoulders, elbows, wrists, hips, knees, ankles) of result.npz's `keypoints` (the calibration's world, Z up)
against the triangulated TRC (OpenSim's axes: TRC (X, Y, Z) = lab (Y, Z, X); TRC row i is frame i):

    MPJPE     mean over frames of the mean keypoint distance, no alignment (world frame), mm
    PA-MPJPE  the same after a per-frame similarity (rotation, translation, scale) onto the reference, mm

The reference is a triangulation of the same detector's keypoints from four cameras, not marker motion
capture: it reprojects into cam01/cam02 at about 8-12 px (README of the data).

    python scripts/eval_footage.py [--out logs/eval_footage] [--cameras cam01,cam02] [--video] [key=value ...]

--video: from the videos (MediaPipe through `ptrack detect`'s detector, the `video` extra) instead of the
OpenPose files.

Extra key=value arguments are passed to every run (e.g. method=batch), `{cam}` in them replaced by the camera's
name (the static trial: `subject.static=../shared/data/pose2sim/static/pose/{cam}_json`). Existing run folders
are reused.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from ptrack.body.keypoint_sets import BODY_25B, get_keypoint_set
from ptrack.pipeline.metrics import pa_mpjpe

REPO = Path(__file__).resolve().parents[1]
DATA = REPO.parent / "shared" / "data" / "pose2sim"
BODY12 = ["LShoulder", "RShoulder", "LElbow", "RElbow", "LWrist", "RWrist"]
BODY12 += ["LHip", "RHip", "LKnee", "RKnee", "LAnkle", "RAnkle"]
HEIGHT_M = 1.72
FPS = 60


def read_trc(path: Path) -> tuple[list[str], np.ndarray]:
    """An OpenSim TRC file -> (marker names (M,), positions (T, M, 3) in the file's axes and units)."""
    lines = path.read_text().splitlines()
    names = [n for n in lines[3].split("\t")[2:] if n.strip()]
    rows = [line.split("\t") for line in lines[5:] if line.strip()]
    data = np.array([[float(x) for x in r[2 : 2 + 3 * len(names)]] for r in rows])
    return names, data.reshape(len(rows), len(names), 3)


def body_rows(keypoint_set: str, names: list[str]) -> list[int]:
    """The 12 body keypoints (`BODY12`, in that order) among a keypoint list `names` of the set `keypoint_set`,
    matched by landmark (the TRC's names are BODY_25B's) -> their indices into `names`."""
    ks = get_keypoint_set(keypoint_set)
    return [names.index(ks.names[ks.index(BODY_25B.landmarks[BODY_25B.index(n)])]) for n in BODY12]


def reference_body(trc: Path, frames: np.ndarray) -> np.ndarray:
    """The TRC's 12 body keypoints (`BODY12`) at the input frames `frames` (TRC row i is frame i) -> (T, 12, 3)
    metres, the calibration's world (lab axes)."""
    tnames, ref = read_trc(trc)
    ref = ref[:, [tnames.index(n) for n in BODY12]][:, :, [2, 0, 1]]  # TRC (X, Y, Z) = lab (Y, Z, X)
    return ref[frames]


def body_pairs(result: Path, trc: Path) -> tuple[np.ndarray, np.ndarray]:
    """result.npz of a run and the TRC -> the 12 body keypoints (`BODY12`, in that order) of the run's frames,
    estimated and reference, (T, 12, 3) metres each, in the calibration's world (lab axes)."""
    keypoint_set = json.loads((result.parent / "metrics.json").read_text())["footage"]["keypoint_set"]
    with np.load(result) as z:
        est = z["keypoints"][:, body_rows(keypoint_set, [str(n) for n in z["keypoint_names"]])]
        frames = z["frames"]
    return est, reference_body(trc, frames)


def errors(result: Path, trc: Path) -> dict[str, float]:
    """result.npz of a run against the TRC -> {mpjpe_mm, pa_mpjpe_mm, frames}."""
    est, ref = body_pairs(result, trc)
    frames = est.shape[0]
    mpjpe = np.linalg.norm(est - ref, axis=-1).mean(-1)
    pa = pa_mpjpe(torch.as_tensor(est), torch.as_tensor(ref))
    return {"mpjpe_mm": 1000 * float(mpjpe.mean()), "pa_mpjpe_mm": float(pa.mean()), "frames": frames}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="logs/eval_footage")
    ap.add_argument("--cameras", default="cam01,cam02")
    ap.add_argument("--video", action="store_true", help="from the videos through MediaPipe (observations.video)")
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args()
    if not DATA.is_dir():
        sys.exit(f"eval_footage: no data at {DATA}")
    print(f"| camera | MPJPE mm | PA-MPJPE mm | frames | overrides: {' '.join(args.overrides) or '(defaults)'} |")
    print("|---|---|---|---|---|")
    for cam in args.cameras.split(","):
        out = Path(args.out) / cam
        if not (out / "result.npz").is_file():
            cmd = [sys.executable, "-m", "ptrack.cli", "run", str(REPO / "configs" / "video.yaml")]
            if args.video:
                cmd += [f"observations.video={DATA / 'balancing' / 'videos' / f'{cam}.mp4'}"]
            else:
                cmd += [f"observations.file={DATA / 'balancing' / 'pose' / f'{cam}_json'}"]
            cmd += [f"camera.file={DATA / 'Calib_qualisys.toml'}", f"camera.name={cam}"]
            cmd += [f"subject.height_m={HEIGHT_M}", f"observations.fps={FPS}", f"out_dir={out}", "progress=false"]
            subprocess.run([*cmd, *(o.replace("{cam}", cam) for o in args.overrides)], check=True)
        e = errors(out / "result.npz", DATA / "balancing" / "triangulated.trc")
        print(f"| {cam} | {e['mpjpe_mm']:.1f} | {e['pa_mpjpe_mm']:.1f} | {e['frames']} | |")


if __name__ == "__main__":
    main()
